"""Heat through each wall, by path (issue 14): wall_heat.csv of DEM runs.

* One particle resting on a fixed-temperature wall (direct + indirect conduction, frozen,
  exponential integrator): its temperature is the exact exponential, the wall's record equals
  the particle's energy gain to round-off, and the gas-gap share is the indirect part of the
  conductance.
* One particle on a fixed-flux wall: the wall delivers q_w A_c (reference 001), all through the
  contact, and the file's mean flux times the wall area is that rate.
* A frozen column between a heated and a cooled wall: both records close the energy balance at
  every output, and at steady state what the floor gives the top takes.
* Areas: plane sections of the domain box, bounded planes, cylinders.
* A run stopped and continued (command line) writes the same wall_heat.csv as one run.
"""
from __future__ import annotations

import csv
import math
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from dem import Simulation
from dem.thermal.wall_heat import line_length_in_box, plane_section_area, wall_area

ROOT = Path(__file__).resolve().parents[1]
R = 1e-3
MAT = dict(name="p", density=2500.0, youngs_modulus=1e7, poisson_ratio=0.3, restitution=0.5,
           friction=0.3, thermal_conductivity=1.0, heat_capacity=840.0)
AIR = dict(conductivity=0.026, density=1.2, viscosity=1.8e-5, heat_capacity=1005.0, temperature=300.0)
L = 0.01


def scene(particles, thermal, walls, end, dt=1e-5, output=None):
    sc = {"simulation": {"time_step": dt, "end_time": end, "mechanics": False, "gravity": [0, 0, 0],
                         "output_interval": output or end},
          "domain": {"min": [-L] * 3, "max": [L] * 3}, "materials": [dict(MAT)],
          "particles": particles, "thermal": thermal, "walls": list(walls), "gas": dict(AIR, porosity=0.4)}
    return sc


def read(path):
    with open(path, newline="") as f:
        rows = list(csv.DictReader(f))
    out = {}
    for r in rows:
        out.setdefault((r["wall"], r["mechanism"]), []).append(
            (float(r["time"]), float(r["energy_J"]), float(r["heat_rate_W"]), float(r["heat_flux_W_m2"]),
             float(r["area_m2"])))
    return {k: np.array(v) for k, v in out.items()}


def test_particle_on_a_fixed_temperature_wall(tmp_path):
    ov = 2e-5
    walls = [{"type": "plane", "name": "floor", "point": [0, 0, -R + ov], "normal": [0, 0, 1], "material": "p",
              "thermal": {"condition": "fixed_temperature", "temperature": 400.0}}]
    sc = scene([{"material": "p", "positions": [[0, 0, 0]], "radius": R, "temperature": 300.0}],
               {"direct": "batchelor_obrien", "indirect": "voronoi_a", "integrator": "exponential",
                "porosity": "global", "time_step": 0.5},
               walls, end=60.0, output=5.0)
    sim = Simulation.from_dict(sc)
    C = 1 / sim.state.inv_heat_capacity[0]
    sim.run(out_dir=str(tmp_path / "out"), progress=False)
    H, Hg = float(sim.state.Hw[0, 0]), float(sim.state.Hwg[0, 0])
    assert 0 < Hg < H  # both paths conduct
    tau = C / H
    assert 60.0 > tau  # more than one time constant
    T = sim.state.temperature[0]
    assert T == pytest.approx(400.0 - 100.0 * math.exp(-60.0 / tau), rel=1e-12)
    d = read(tmp_path / "out" / "wall_heat.csv")
    tot, gap, con = d[("floor", "total")], d[("floor", "gas_gap")], d[("floor", "contact")]
    assert tot[:, 0].tolist() == pytest.approx(np.arange(0.0, 60.01, 5.0).tolist())
    # the wall's record is the particle's energy gain, the gap its conductance share
    # (the file holds 12 significant digits)
    assert tot[-1, 1] == pytest.approx(C * (T - 300.0), rel=1e-11)
    assert gap[-1, 1] == pytest.approx(tot[-1, 1] * Hg / H, rel=1e-11)
    assert con[:, 1] + gap[:, 1] == pytest.approx(tot[:, 1], rel=1e-11)
    # interval means: C dT over each interval of the exact solution
    t = tot[:, 0]
    Tt = 400.0 - 100.0 * np.exp(-t / tau)
    assert tot[1:, 2] == pytest.approx(C * np.diff(Tt) / np.diff(t), rel=1e-10)
    # an unbounded floor: its section of the domain box
    assert tot[0, 4] == pytest.approx((2 * L) ** 2)
    assert tot[1:, 3] == pytest.approx(tot[1:, 2] / (2 * L) ** 2)


def test_particle_on_a_fixed_flux_wall(tmp_path):
    ov = 2e-5
    q = 5000.0
    walls = [{"type": "plane", "name": "heater", "point": [0, 0, -R + ov], "normal": [0, 0, 1], "material": "p",
              "extent": [0.004, 0.003], "u_axis": [1, 0, 0],
              "thermal": {"condition": "fixed_heat_flux", "heat_flux": q}}]
    sc = scene([{"material": "p", "positions": [[0, 0, 0]], "radius": R, "temperature": 300.0}],
               {"direct": "batchelor_obrien", "indirect": "voronoi_a", "time_step": 0.1}, walls, end=10.0,
               output=2.0)
    sim = Simulation.from_dict(sc)
    C = 1 / sim.state.inv_heat_capacity[0]
    sim.run(out_dir=str(tmp_path / "out"), progress=False)
    Ac = math.pi * R * ov  # Hertz-overlap contact radius against a wall: r_c^2 = R delta
    d = read(tmp_path / "out" / "wall_heat.csv")
    tot, gap, con = d[("heater", "total")], d[("heater", "gas_gap")], d[("heater", "contact")]
    # the particle heats linearly: q A_c t, all of it through the contact
    assert C * (sim.state.temperature[0] - 300.0) == pytest.approx(q * Ac * 10.0, rel=1e-10)
    assert tot[:, 1] == pytest.approx(q * Ac * tot[:, 0], rel=1e-10, abs=1e-300)
    assert np.all(gap[:, 1] == 0.0)
    assert con[:, 1] == pytest.approx(tot[:, 1])
    assert tot[1:, 2] == pytest.approx(np.full(len(tot) - 1, q * Ac), rel=1e-10)
    # a bounded plane: its rectangle (4 e_u e_v); mean flux over it = rate / area
    assert tot[0, 4] == pytest.approx(4 * 0.004 * 0.003)
    assert tot[1:, 3] * tot[0, 4] == pytest.approx(tot[1:, 2], rel=1e-11)


def test_frozen_column_between_a_heated_and_a_cooled_wall(tmp_path):
    """Ten spheres in a line between a 400 K floor and a 300 K plate (both touching, overlap
    2e-5 m everywhere): the two walls' records close the energy balance at every output, and
    at steady state the floor's heat rate is the plate's, with the opposite sign."""
    ov = 2e-5
    n = 10
    z = np.array([(2 * R - ov) * k for k in range(n)])
    walls = [{"type": "plane", "name": "hot", "point": [0, 0, -R + ov / 2], "normal": [0, 0, 1], "material": "p",
              "thermal": {"condition": "fixed_temperature", "temperature": 400.0}},
             {"type": "plane", "name": "cold", "point": [0, 0, z[-1] + R - ov / 2], "normal": [0, 0, -1],
              "material": "p", "thermal": {"condition": "fixed_temperature", "temperature": 300.0}}]
    sc = scene([{"material": "p", "positions": [[0, 0, zz] for zz in z], "radius": R, "temperature": 300.0}],
               {"direct": "batchelor_obrien", "integrator": "exponential", "time_step": 2.0}, walls,
               end=20000.0, output=1000.0)
    sc["domain"] = {"min": [-L, -L, -L], "max": [L, L, 0.03]}
    sim = Simulation.from_dict(sc)
    C = 1 / sim.state.inv_heat_capacity[:n]
    sim.run(out_dir=str(tmp_path / "out"), progress=False)
    d = read(tmp_path / "out" / "wall_heat.csv")
    hot, cold = d[("hot", "total")], d[("cold", "total")]
    hist = np.genfromtxt(tmp_path / "out" / "history.csv", delimiter=",", names=True)
    # energy closure at every output: what both walls gave is what the particles gained
    gained = hist["thermal_energy"] - hist["thermal_energy"][0]
    assert hot[:, 1] + cold[:, 1] == pytest.approx(gained, rel=1e-9, abs=1e-12 * float(C.sum()) * 100)
    # steady state: the floor gives what the plate takes (last interval, relative to the rate)
    assert hot[-1, 2] > 0 > cold[-1, 2]
    assert hot[-1, 2] + cold[-1, 2] == pytest.approx(0.0, abs=1e-6 * hot[-1, 2])
    assert float(sim.state.temperature[0]) > float(sim.state.temperature[n - 1])


def test_wall_areas():
    lo, hi = [-1.0, -1.0, -1.0], [1.0, 1.0, 2.0]
    # axis-aligned sections of the 2 x 2 x 3 box
    assert plane_section_area([0, 0, 0.5], [0, 0, 1], lo, hi) == pytest.approx(4.0)
    assert plane_section_area([0, 0, 0], [1, 0, 0], lo, hi) == pytest.approx(6.0)
    # the diagonal plane x = y: a 2 sqrt(2) x 3 rectangle
    assert plane_section_area([0, 0, 0], [1, -1, 0], lo, hi) == pytest.approx(2 * math.sqrt(2) * 3)
    # a plane through a corner only, and one outside the box
    assert plane_section_area([5, 0, 0], [1, 0, 0], lo, hi) == 0.0
    # the section by x + y + z = 0 of the cube [-1, 1]^3 is the regular hexagon of side sqrt 2
    assert plane_section_area([0, 0, 0], [1, 1, 1], [-1] * 3, [1] * 3) == pytest.approx(3 * math.sqrt(3))
    assert line_length_in_box([0, 0, 0], [0, 0, 1], lo, hi) == pytest.approx(3.0)
    assert line_length_in_box([0, 0, 0], [1, 1, 0], lo, hi) == pytest.approx(2 * math.sqrt(2))
    cyl = {"type": "cylinder", "point": [0, 0, 0], "axis": [0, 0, 1], "radius": 0.5, "length": math.inf}
    assert wall_area(cyl, lo, hi) == pytest.approx(2 * math.pi * 0.5 * 3.0)
    assert wall_area(dict(cyl, length=1.0), lo, hi) == pytest.approx(2 * math.pi * 0.5)
    plane = {"type": "plane", "point": [0, 0, 0], "normal": [0, 0, 1], "extent": [0.2, 0.3]}
    assert wall_area(plane, lo, hi) == pytest.approx(0.24)


def test_stopped_and_continued_run_writes_the_same_records(tmp_path):
    """Through the command line: a run to 30 s continued to 60 s (--restart) gives the
    wall_heat.csv of one run to 60 s, byte for byte."""
    ov = 2e-5
    toml = f'''
[simulation]
time_step = 1e-5
end_time = 60.0
mechanics = false
output_interval = 5.0
checkpoint_interval = 10.0

[domain]
min = [{-L}, {-L}, {-L}]
max = [{L}, {L}, {L}]

[[materials]]
name = "p"
density = 2500.0
youngs_modulus = 1e7
poisson_ratio = 0.3
restitution = 0.5
friction = 0.3
thermal_conductivity = 1.0
heat_capacity = 840.0

[[particles]]
material = "p"
radius = {R}
positions = [[0.0, 0.0, 0.0]]
temperature = 300.0

[[walls]]
type = "plane"
name = "floor"
point = [0.0, 0.0, {-R + ov}]
normal = [0.0, 0.0, 1.0]
material = "p"
thermal = {{ condition = "fixed_temperature", temperature = 400.0 }}

[thermal]
direct = "batchelor_obrien"
indirect = "voronoi_a"
integrator = "exponential"
porosity = "global"
time_step = 0.5

[gas]
conductivity = 0.026
density = 1.2
viscosity = 1.8e-5
heat_capacity = 1005.0
temperature = 300.0
porosity = 0.4
'''
    (tmp_path / "scene.toml").write_text(toml)
    env = dict(os.environ, PYTHONPATH=str(ROOT) + os.pathsep + os.environ.get("PYTHONPATH", ""))

    def dem(*args):
        r = subprocess.run([sys.executable, "-m", "dem", "run", str(tmp_path / "scene.toml"), *args],
                           capture_output=True, text=True, env=env, cwd=str(tmp_path))
        assert r.returncode == 0, r.stdout + r.stderr
    dem("--out", str(tmp_path / "one"))
    dem("--out", str(tmp_path / "two"), "--end-time", "30")
    dem("--out", str(tmp_path / "two"), "--restart", str(tmp_path / "two" / "checkpoint.npz"))
    a = (tmp_path / "one" / "wall_heat.csv").read_text()
    b = (tmp_path / "two" / "wall_heat.csv").read_text()
    assert a == b
    assert a.count("\n") == 1 + 13 * 3

    # a checkpoint of the earlier version (without the gas-gap arrays) still continues: the
    # conductances are recomputed (same temperatures, bit for bit), the gap count restarts at 0
    import json
    from dem import checkpoint as ckpt
    dem("--out", str(tmp_path / "three"), "--end-time", "30")
    z = np.load(tmp_path / "three" / "checkpoint.npz")
    meta = ("format", "format_version", "record", "checksum", "th_Hwg", "th_wgap")
    old = {k: z[k] for k in z.files if k not in meta}
    ckpt.write(str(tmp_path / "old.npz"), old, json.loads(str(z["record"])))
    dem("--out", str(tmp_path / "three"), "--restart", str(tmp_path / "old.npz"))
    f1, f3 = np.load(tmp_path / "one" / "final.npz"), np.load(tmp_path / "three" / "final.npz")
    assert np.array_equal(f1["temperature"].view(np.uint64), f3["temperature"].view(np.uint64))
    w1, w3 = read(tmp_path / "one" / "wall_heat.csv"), read(tmp_path / "three" / "wall_heat.csv")
    assert w3[("floor", "total")][:, 1] == pytest.approx(w1[("floor", "total")][:, 1], rel=1e-14)
    gap1, gap3 = w1[("floor", "gas_gap")], w3[("floor", "gas_gap")]
    assert gap3[-1, 1] == pytest.approx(gap1[-1, 1] - gap1[6, 1], rel=1e-12)  # counted from t = 30 s


def test_coupled_run_writes_the_particles_wall_heat(tmp_path, solver):
    """A coupled run (`coupling run`) with a heated distributor: wall_heat.csv holds the particles'
    heat from it by path, equal to history.csv's E_wall_distributor, and a run stopped at step 5
    and continued (--restart) writes the same file as one run of 10 steps."""
    sys.path.insert(0, str(ROOT / "benchmarks"))
    from stability.coupled import write_case
    d = 2e-3
    ov = 2e-5
    x = np.array([[0.003 + 0.004 * i, 0.003 + 0.004 * j, d / 2 - ov] for i in range(3) for j in range(3)])
    case = write_case(tmp_path / "case", L=0.012, H=0.03, nxy=3, nz=6, positions=x, dt_dem=1e-5, interval=10,
                      n_steps=10, u_in=0.5, mechanics=False, walls_top=False)
    dem_toml = case / "dem.toml"
    text = dem_toml.read_text()
    old = 'name = "distributor"\npoint = [0.0, 0.0, 0.0]\nnormal = [0.0, 0.0, 1.0]\nmaterial = "glass"\n'
    assert old in text
    dem_toml.write_text(text.replace(old, old + 'thermal = { condition = "fixed_temperature", temperature = 400.0 }\n'))
    env = dict(os.environ, PYTHONPATH=str(ROOT) + os.pathsep + os.environ.get("PYTHONPATH", ""))

    def run(out, *args):
        r = subprocess.run([sys.executable, "-m", "coupling.run", "run", str(case), "--out", str(out), *args],
                           capture_output=True, text=True, env=env, cwd=str(ROOT))
        assert r.returncode == 0, r.stdout[-2000:] + r.stderr[-2000:]
    run(tmp_path / "one")
    w = read(tmp_path / "one" / "wall_heat.csv")
    tot = w[("distributor", "total")]
    assert tot[-1, 1] > 0  # the distributor heats the beads
    assert w[("distributor", "contact")][:, 1] + w[("distributor", "gas_gap")][:, 1] == \
        pytest.approx(tot[:, 1], rel=1e-12, abs=1e-300)
    h = np.atleast_1d(np.genfromtxt(tmp_path / "one" / "history.csv", delimiter=",", names=True))
    assert tot[-1, 0] == pytest.approx(float(h["time"][-1]))
    assert tot[-1, 1] == pytest.approx(float(h["E_wall_distributor"][-1]), rel=1e-10)
    run(tmp_path / "two", "--end-time", "0.0005")
    run(tmp_path / "two", "--restart")
    assert (tmp_path / "one" / "wall_heat.csv").read_text() == (tmp_path / "two" / "wall_heat.csv").read_text()
