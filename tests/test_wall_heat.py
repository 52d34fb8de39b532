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
from dem.final import read as read_final

ROOT = Path(__file__).resolve().parents[1]
R = 1e-3
MAT = dict(name="p", density=2500.0, youngs_modulus=1e7, poisson_ratio=0.3, restitution=0.5,
           friction=0.3, thermal_conductivity=1.0, heat_capacity=840.0)
AIR = dict(conductivity=0.026, density=1.2, viscosity=1.8e-5, heat_capacity=1005.0, temperature=300.0)
L = 0.01


def _coupling_run(case, out, *args):
    """`coupling run CASE --out OUT ARGS` through the command line; it must succeed."""
    env = dict(os.environ, PYTHONPATH=str(ROOT) + os.pathsep + os.environ.get("PYTHONPATH", ""))
    r = subprocess.run([sys.executable, "-m", "coupling.run", "run", str(case), "--out", str(out), *args],
                       capture_output=True, text=True, env=env, cwd=str(ROOT))
    assert r.returncode == 0, r.stdout[-2000:] + r.stderr[-2000:]


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
    # a mesh reaching beyond the box: the part inside (a 6 x 6 square of 0.7 triangles, not
    # aligned with the box's faces; flat at z = 0.5, then tilted to z = y + 0.5)
    from dem.thermal.wall_heat import mesh_area_in_box
    g = np.arange(-3.0, 3.01, 0.75) + 0.1
    v = np.array([[x, y, 0.5] for y in g for x in g])
    k = len(g)
    f = np.array([q for i in range(k - 1) for j in range(k - 1)
                  for q in ([i * k + j, i * k + j + 1, (i + 1) * k + j], [i * k + j + 1, (i + 1) * k + j + 1, (i + 1) * k + j])])
    assert mesh_area_in_box(v, f, lo, hi) == pytest.approx(4.0, rel=1e-12)
    v[:, 2] = v[:, 1] + 0.5
    assert mesh_area_in_box(v, f, lo, hi) == pytest.approx(4.0 * math.sqrt(2.0), rel=1e-12)
    assert mesh_area_in_box(v + [10.0, 0.0, 0.0], f, lo, hi) == 0.0


def test_stopped_and_continued_run_writes_the_same_records(tmp_path):
    """Through the command line: a run to 30 s continued to 60 s (--restart) gives the
    wall_heat.csv of one run to 60 s, byte for byte (contact, gas gap and radiation: the
    floor radiates, Zhou 2009)."""
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
emissivity = 0.9

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
thermal = {{ condition = "fixed_temperature", temperature = 400.0, emissivity = 0.8 }}

[thermal]
direct = "batchelor_obrien"
indirect = "voronoi_a"
radiation = "zhou_2009"
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
    assert a.count("\n") == 1 + 13 * 4
    w1 = read(tmp_path / "one" / "wall_heat.csv")
    assert w1[("floor", "radiation")][-1, 1] > 1e-3 * w1[("floor", "total")][-1, 1] > 0

    # a checkpoint of the earlier version (without the gas-gap arrays) still continues: the
    # conductances are recomputed (same temperatures, bit for bit), the gap count restarts at 0
    import json
    from dem import checkpoint as ckpt
    dem("--out", str(tmp_path / "three"), "--end-time", "30")
    z = np.load(tmp_path / "three" / "checkpoint.npz")
    meta = ("format", "format_version", "record", "checksum", "th_Hwg", "th_wgap", "th_wrad")
    old = {k: z[k] for k in z.files if k not in meta}
    ckpt.write(str(tmp_path / "old.npz"), old, json.loads(str(z["record"])))
    dem("--out", str(tmp_path / "three"), "--restart", str(tmp_path / "old.npz"))
    f1, f3 = read_final(tmp_path / "one" / "final.npz"), read_final(tmp_path / "three" / "final.npz")
    assert np.array_equal(f1["temperature"].view(np.uint64), f3["temperature"].view(np.uint64))
    w1, w3 = read(tmp_path / "one" / "wall_heat.csv"), read(tmp_path / "three" / "wall_heat.csv")
    assert w3[("floor", "total")][:, 1] == pytest.approx(w1[("floor", "total")][:, 1], rel=1e-14)
    for path in ("gas_gap", "radiation"):   # counted from t = 30 s
        p1, p3 = w1[("floor", path)], w3[("floor", path)]
        assert p3[-1, 1] == pytest.approx(p1[-1, 1] - p1[6, 1], rel=1e-12)


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

    def run(out, *args):
        _coupling_run(case, out, *args)
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


# ------------------------------------------------------------------ walls of both phases

def _tied_case(dest, n_steps=10, Tw=400.0, q_w=None, emissivity=None):
    """A frozen bed of 9 beads of 2 mm on the floor of a 12 x 12 x 30 mm box meshed 3 x 3 x 6, hot
    gas (373.15 K) entering at 0.5 m/s; the DEM wall `left` (x = 0, three beads touch it) at a
    fixed 400 K is tied to the gas patch `left` (fixedValue 400 K); every other wall adiabatic.
    emissivity: the wall radiates (Zhou 2009 radiation, beads of emissivity 0.9)."""
    import re
    sys.path.insert(0, str(ROOT / "benchmarks"))
    from stability.coupled import write_case
    d, ov = 2e-3, 2e-5
    x = np.array([[0.003 + 0.004 * i, 0.003 + 0.004 * j, d / 2 - ov] for i in range(3) for j in range(3)])
    x[:3, 0] = d / 2 - ov
    case = write_case(Path(dest), L=0.012, H=0.03, nxy=3, nz=6, positions=x, dt_dem=1e-5, interval=10,
                      n_steps=n_steps, u_in=0.5, mechanics=False, walls_top=False, periodic=False)
    t = (case / "dem.toml").read_text()
    old = 'name = "left"\npoint = [0.0, 0.0, 0.0]\nnormal = [1.0, 0.0, 0.0]\nmaterial = "glass"\n'
    assert old in t
    emis = "" if emissivity is None else f", emissivity = {emissivity!r}"
    cond = (f'thermal = {{ condition = "fixed_temperature", temperature = {Tw!r}{emis} }}\n' if q_w is None else
            f'thermal = {{ condition = "fixed_heat_flux", heat_flux = {q_w!r} }}\n')
    t = t.replace(old, old + cond)
    if emissivity is not None:
        for a, b in (('thermal_conductivity = 1.0\n', 'thermal_conductivity = 1.0\nemissivity = 0.9\n'),
                     ('direct = "batchelor_obrien"\n', 'direct = "batchelor_obrien"\nradiation = "zhou_2009"\n')):
            assert a in t
            t = t.replace(a, b)
    (case / "dem.toml").write_text(t)
    bm = case / "system" / "blockMeshDict"
    s = bm.read_text()
    s2 = re.sub(r"xWalls\s*\{[^}]*\}", "left\n{\n    type wall;\n    faces ( (0 4 7 3) );\n}\nright\n{\n"
                "    type wall;\n    faces ( (1 2 6 5) );\n}", s)
    assert s2 != s
    bm.write_text(s2)
    for f in (case / "0").iterdir():
        s = f.read_text()
        m = re.search(r"xWalls\s*\{([^}]*)\}", s)
        body = m.group(1)
        left = body
        if f.name == "T":
            left = (f"\n        type fixedValue;\n        value uniform {Tw!r};\n    " if q_w is None else
                    "\n        type fixedGradient;\n        gradient uniform 0;\n    ")
        f.write_text(s.replace(m.group(0), "left\n    {" + left + "}\n    right\n    {" + body + "}"))
    with open(case / "coupling.toml", "a") as fh:
        fh.write('\n[[walls]]\ndem = "left"\npatch = "left"\n')
    return case


def _foam_list(path, patch=None):
    """Values of an ASCII OpenFOAM scalar field: the internal field, or a patch's value."""
    import re
    text = Path(path).read_text()
    if patch is not None:
        text = text[re.search(rf"\n\s*{patch}\s*\{{", text).end():]
        u = re.match(r"[^}]*?value\s+uniform\s+([^;\s]+)\s*;", text)
        if u:
            return np.full(18, float(u.group(1)))     # the tied patch `left` of these tests: 18 faces
        m = re.search(r"value\s+nonuniform List<scalar>\s*(\d+)\s*\(([^)]*)\)", text)
    else:
        m = re.search(r"internalField\s+nonuniform List<scalar>\s*(\d+)\s*\(([^)]*)\)", text)
    v = np.array(m.group(2).split(), float)
    assert v.size == int(m.group(1))
    return v


def test_tied_wall_heats_both_phases_and_the_energy_balance_closes(tmp_path, solver):
    """A DEM wall tied to its gas patch (coupling.toml [[walls]]): wall_heat.csv gets the gas's own
    heat from it (`gas_convection`, the solver's wall conduction: equal to the written
    wallHeatFlux field, and to eps k (T_w - T_P)/(dx/2) A of the wall cells), and `total` is the
    particles' paths plus the gas's. coupling.csv's energy balance: the change of particle and
    gas energy equals the heat from the walls plus the inflow through inlet and outlet plus the
    two explained parts (the explicit exchange's mismatch and the continuity residual) to
    round-off; a run stopped and continued writes the same records."""
    case = _tied_case(tmp_path / "case")

    def run(out, *args):
        _coupling_run(case, out, *args)
    one = tmp_path / "one"
    run(one)
    w = read(one / "wall_heat.csv")
    assert ("left", "gas_convection") in w and ("right", "gas_convection") not in w   # only the tied wall
    gas, tot = w[("left", "gas_convection")], w[("left", "total")]
    parts = w[("left", "contact")][:, 1] + w[("left", "gas_gap")][:, 1] + gas[:, 1]
    assert parts == pytest.approx(tot[:, 1], rel=1e-12, abs=1e-300)
    assert w[("left", "contact")][-1, 1] > 0 and gas[-1, 1] > 0   # the hot wall heats beads and gas
    # the last row's rate is the last CFD step's (one step per output): the solver's field
    last = one / "0.001"
    q = _foam_list(last / "wallHeatFlux", "left")
    A = 0.004 * 0.005     # the 18 faces of the patch
    assert gas[-1, 2] == pytest.approx(float(q.sum()) * A, rel=1e-9)
    # ... which is the conduction across the half cell next to the wall, eps k (T_w - T_P)/(dx/2)
    from coupling.mesh import read_polymesh
    mesh = read_polymesh(str(one))
    T, eps = _foam_list(last / "T"), _foam_list(last / "eps")
    cells = np.flatnonzero(mesh.cell_centres[:, 0] < 0.004)
    assert cells.size == 18
    from coupling.case import gas_properties
    k = gas_properties(one).k
    expect = float((eps[cells] * k * (400.0 - T[cells]) / 0.002).sum() * A)
    assert gas[-1, 2] == pytest.approx(expect, rel=1e-6)
    # the particles' paths per face: the beads' faces only (the bottom row), integrating to the
    # DEM's records (the last step's rate, its estimate at the step's start: within 1e-6), and
    # the total the sum of the three paths
    zc = mesh.face_centres[[f for p in mesh.boundary if p["name"] == "left"
                            for f in range(p["startFace"], p["startFace"] + p["nFaces"])], 2]
    qc, qg = _foam_list(last / "wallHeatFluxContact", "left"), _foam_list(last / "wallHeatFluxGasGap", "left")
    assert np.all(qc[zc < 0.005] > 0) and np.all(qc[zc > 0.005] == 0)
    assert float(qc.sum()) * A == pytest.approx(w[("left", "contact")][-1, 2], rel=1e-6)
    assert float(qg.sum()) * A == pytest.approx(w[("left", "gas_gap")][-1, 2], rel=1e-6, abs=1e-12)
    assert _foam_list(last / "wallHeatFluxTotal", "left") == pytest.approx(q + qc + qg, rel=1e-12)
    # the energy balance of coupling.csv
    c = np.atleast_1d(np.genfromtxt(one / "coupling.csv", delimiter=",", names=True))
    # round-off: of the energy sums (24 J of beads, 1.5 J of gas) and of the boundary integrals
    through = np.abs(c["E_open"]) + np.abs(c["E_walls_gas"]) + np.abs(c["E_walls_particles"])
    scale = np.abs(c["E_particles"]) + np.abs(c["E_gas_solver"])
    assert np.all(np.abs(c["balance_residual"]) <= 1e-14 * scale + 1e-9 * through)
    assert c["balance_error"] == pytest.approx(c["E_exchange_mismatch"] + c["E_continuity"], abs=1e-12)
    assert c["E_walls_gas"][-1] == pytest.approx(gas[-1, 1], rel=1e-12)
    assert c["E_walls_particles"][-1] == pytest.approx(w[("left", "contact")][-1, 1] + w[("left", "gas_gap")][-1, 1],
                                                       rel=1e-12)
    assert c["E_gas_solver"] == pytest.approx(c["E_gas"], rel=1e-12)
    assert c["E_open"][-1] > 0    # the hot inflow brings heat
    # stopped at step 5 and continued: the same records
    two = tmp_path / "two"
    run(two, "--end-time", "0.0005")
    run(two, "--restart")
    assert (one / "wall_heat.csv").read_text() == (two / "wall_heat.csv").read_text()
    c2 = np.atleast_1d(np.genfromtxt(two / "coupling.csv", delimiter=",", names=True))
    for name in ("E_walls_gas", "E_open", "balance_error", "E_exchange_mismatch", "E_gas_solver"):
        assert np.array_equal(c[name], c2[name]), name


def test_tied_wall_radiation_reaches_the_gas_fields_and_the_balance(tmp_path, solver):
    """A tied wall at 800 K with an emissivity (Zhou 2009): the particles' radiation from it is a
    path of its own in wall_heat.csv and, per face, in wallHeatFluxRadiation (the beads next to
    the wall only, integrating to the DEM's record), wallHeatFluxTotal is the sum of the four
    paths, coupling.csv's balance closes with it, and a stopped and continued run writes the
    same records."""
    case = _tied_case(tmp_path / "case", Tw=800.0, emissivity=0.8)
    one = tmp_path / "one"
    _coupling_run(case, one)
    w = read(one / "wall_heat.csv")
    rad = w[("left", "radiation")]
    assert rad[-1, 1] > 0.01 * w[("left", "contact")][-1, 1] > 0
    parts = sum(w[("left", p)][:, 1] for p in ("contact", "gas_gap", "radiation", "gas_convection"))
    assert parts == pytest.approx(w[("left", "total")][:, 1], rel=1e-12)
    last = one / "0.001"
    A = 0.004 * 0.005
    from coupling.mesh import read_polymesh
    mesh = read_polymesh(str(one))
    zc = mesh.face_centres[[f for p in mesh.boundary if p["name"] == "left"
                            for f in range(p["startFace"], p["startFace"] + p["nFaces"])], 2]
    qr = _foam_list(last / "wallHeatFluxRadiation", "left")
    assert np.all(qr[zc < 0.005] > 0) and np.all(qr[zc > 0.005] == 0)   # the bottom row of beads
    assert float(qr.sum()) * A == pytest.approx(rad[-1, 2], rel=1e-6)
    q = _foam_list(last / "wallHeatFlux", "left")
    qc, qg = _foam_list(last / "wallHeatFluxContact", "left"), _foam_list(last / "wallHeatFluxGasGap", "left")
    assert _foam_list(last / "wallHeatFluxTotal", "left") == pytest.approx(q + qc + qg + qr, rel=1e-12)
    c = np.atleast_1d(np.genfromtxt(one / "coupling.csv", delimiter=",", names=True))
    through = np.abs(c["E_open"]) + np.abs(c["E_walls_gas"]) + np.abs(c["E_walls_particles"])
    scale = np.abs(c["E_particles"]) + np.abs(c["E_gas_solver"])
    assert np.all(np.abs(c["balance_residual"]) <= 1e-14 * scale + 1e-9 * through)
    assert c["E_walls_particles"][-1] == pytest.approx(
        sum(w[("left", p)][-1, 1] for p in ("contact", "gas_gap", "radiation")), rel=1e-12)
    two = tmp_path / "two"
    _coupling_run(case, two, "--end-time", "0.0005")
    _coupling_run(case, two, "--restart")
    assert (one / "wall_heat.csv").read_text() == (two / "wall_heat.csv").read_text()


def test_tied_wall_check_names_both(tmp_path, capsys):
    """`coupling check` refuses a tie that cannot be one wall, naming the file, the key and both
    sides: a patch that does not exist, one of another type, one elsewhere, another temperature.
    The refusals call the command's own entry point (coupling.run.main, what `python -m
    coupling.run check` runs) in this process, each meshing its case with blockMesh as before: a
    fresh Python for each of the seven checks cost 2.5 s of start-up apiece, and an exception
    escaping main fails the test as a traceback did; the accepted case at the end still runs
    through the command line (exit 0 of the real command)."""
    from unittest import mock
    from coupling.run import main as coupling_main
    case = _tied_case(tmp_path / "case")
    env = dict(os.environ, PYTHONPATH=str(ROOT) + os.pathsep + os.environ.get("PYTHONPATH", ""))
    cfg = (case / "coupling.toml").read_text()

    def check(text, command_line=False):
        (case / "coupling.toml").write_text(text)
        if command_line:
            r = subprocess.run([sys.executable, "-m", "coupling.run", "check", str(case)],
                               capture_output=True, text=True, env=env, cwd=str(ROOT))
            assert "Traceback" not in r.stderr
            return r.returncode, r.stdout + r.stderr
        capsys.readouterr()
        with mock.patch.dict(os.environ):     # main drops the OMPI_* settings of a serial process
            rc = coupling_main(["check", str(case)])
        out, err = capsys.readouterr()
        assert "Traceback" not in err
        return rc, out + err
    rc, msg = check(cfg.replace('patch = "left"', 'patch = "lft"'))
    assert rc == 2 and "walls[0].patch: no gas patch 'lft'" in msg and "left, right" in msg
    rc, msg = check(cfg.replace('patch = "left"', 'patch = "inlet"'))
    assert rc == 2 and "DEM wall 'left'" in msg and "gas patch 'inlet'" in msg   # not this wall's condition
    rc, msg = check(cfg.replace('dem = "left"', 'dem = "wall_x"'))
    assert rc == 2 and "walls[0].dem: no DEM wall 'wall_x'" in msg
    T = (case / "0" / "T").read_text()
    (case / "0" / "T").write_text(T.replace("uniform 400.0", "uniform 410.0"))
    rc, msg = check(cfg)
    assert rc == 2 and "DEM wall 'left'" in msg and "gas patch 'left'" in msg and "it is 410 K" in msg
    (case / "0" / "T").write_text(T)
    # `right` is an adiabatic DEM wall 12 mm away from the patch `left`
    rc, msg = check(cfg.replace('dem = "left"', 'dem = "right"'))
    assert rc == 2 and "DEM wall 'right'" in msg
    # the patch `right` at 400 K too: the same condition, but 12 mm from the DEM wall `left`
    import re
    (case / "0" / "T").write_text(re.sub(r"right\s*\{[^}]*\}", "right { type fixedValue; value uniform 400.0; }", T))
    rc, msg = check(cfg.replace('patch = "left"', 'patch = "right"'))
    assert rc == 2 and "do not coincide" in msg and "0.012 m from the DEM wall" in msg
    (case / "0" / "T").write_text(T)
    rc, msg = check(cfg, command_line=True)
    assert rc == 0, msg


def test_local_flux_around_a_heated_tube(tmp_path):
    """wall_heat_angle.csv: two particles resting on a horizontal tube at a fixed temperature,
    at 5 deg (top) and 100 deg from the top, frozen: their local flux lands in the sectors of
    their angles, and each sector's flux times its area is the particle's exact rate
    H (T_w - T(t)) of the exponential solution, split between contact and gas gap as the
    conductances are (wall_heat.csv's shares)."""
    Rc, ov = 4e-3, 2e-5
    ang = np.radians([5.0, 100.0])
    rr = Rc + R - ov
    pos = [[rr * math.sin(a), 0.0, rr * math.cos(a)] for a in ang]   # angle from the top (+z), towards +x
    # axis +y: the angle turns from the top (+z) towards +x (right-hand rule about the axis)
    walls = [{"type": "cylinder", "name": "tube", "point": [0, 0, 0], "axis": [0, 1, 0], "radius": Rc,
              "inside": False, "length": 0.004, "material": "p",
              "thermal": {"condition": "fixed_temperature", "temperature": 400.0}}]
    sc = scene([{"material": "p", "positions": pos, "radius": R, "temperature": 300.0}],
               {"direct": "batchelor_obrien", "indirect": "voronoi_a", "integrator": "exponential",
                "porosity": "global", "time_step": 0.5}, walls, end=20.0, output=5.0)
    sc["simulation"]["gravity"] = [0, 0, -9.81]
    sim = Simulation.from_dict(sc)
    C = 1 / sim.state.inv_heat_capacity[0]
    sim.run(out_dir=str(tmp_path / "out"), progress=False)
    H, Hg = sim.state.Hw[:2, 0].copy(), sim.state.Hwg[:2, 0].copy()
    assert np.all(H > 0) and H[0] == pytest.approx(H[1], rel=1e-9)   # the same contact on both
    with open(tmp_path / "out" / "wall_heat_angle.csv", newline="") as f:
        rows = list(csv.DictReader(f))
    times = sorted({float(r["time"]) for r in rows})
    assert times == pytest.approx([0.0, 5.0, 10.0, 15.0, 20.0])
    area = 2 * math.pi * Rc * 0.004 / 24
    for t in times[1:]:
        sel = [r for r in rows if float(r["time"]) == t]
        assert len(sel) == 24
        qc = np.array([float(r["contact_W_m2"]) for r in sel])
        qg = np.array([float(r["gas_gap_W_m2"]) for r in sel])
        hot = np.flatnonzero(qc + qg)
        assert hot.tolist() == [0, 6]     # 0-15 deg and 90-105 deg, measured from the top
        Tt = 400.0 - 100.0 * math.exp(-t * H[0] / C)
        exact = H[0] * (400.0 - Tt)
        assert (qc[hot] + qg[hot]) * area == pytest.approx([exact, exact], rel=1e-9)
        assert qg[hot] * area == pytest.approx(Hg[:2] * (400.0 - Tt), rel=1e-9)


def test_tied_fixed_flux_wall_delivers_q_w_A(tmp_path, solver):
    """A tied fixed-heat-flux wall (5 kW/m^2) partly covered by three beads (one in each of the
    three bottom faces of the patch): the particles' contacts take A_c q_w (reference 001), the
    gas takes the rest of each face's q_w A_f, so wall_heat.csv's total is q_w A t to round-off;
    on the faces with a bead the solver's wallHeatFlux is q_w minus the bead's A_c q_w over the
    face, on the others q_w; a run stopped and continued writes the same records."""
    q_w = 5000.0
    case = _tied_case(tmp_path / "case", q_w=q_w)

    def run(out, *args):
        _coupling_run(case, out, *args)
    one = tmp_path / "one"
    run(one)
    w = read(one / "wall_heat.csv")
    A = 0.012 * 0.03
    tot, con, gas = w[("left", "total")], w[("left", "contact")], w[("left", "gas_convection")]
    assert tot[:, 1] == pytest.approx(q_w * A * tot[:, 0], rel=1e-12, abs=1e-18)
    assert con[-1, 1] > 0 and gas[-1, 1] > 0
    # per face: the bottom row (z < 5 mm) holds one bead per face, A_c q_w each
    from coupling.mesh import read_polymesh
    mesh = read_polymesh(str(one))
    patch = next(p for p in mesh.boundary if p["name"] == "left")
    f0, nf = patch["startFace"], patch["nFaces"]
    zc = mesh.face_centres[f0:f0 + nf, 2]
    q = _foam_list(one / "0.001" / "wallHeatFlux", "left")
    Af = 0.004 * 0.005
    bead = con[-1, 2] / 3          # A_c q_w of one bead (W), the last step's rate
    assert bead > 0
    assert q[zc < 0.005] == pytest.approx(np.full(3, q_w - bead / Af), rel=1e-9)
    assert q[zc > 0.005] == pytest.approx(np.full(15, q_w), rel=1e-12)
    qc = _foam_list(one / "0.001" / "wallHeatFluxContact", "left")
    assert qc[zc < 0.005] == pytest.approx(np.full(3, bead / Af), rel=1e-9)
    assert _foam_list(one / "0.001" / "wallHeatFluxTotal", "left") == pytest.approx(np.full(18, q_w), rel=1e-12)
    two = tmp_path / "two"
    run(two, "--end-time", "0.0005")
    run(two, "--restart")
    assert (one / "wall_heat.csv").read_text() == (two / "wall_heat.csv").read_text()


def test_local_flux_of_a_moving_bed_run(tmp_path):
    """With mechanics on, the Euler integrator exchanges wall heat inside the force loop (fused);
    the wall conductances are kept there too, so wall_heat_angle.csv sees a bead resting on top
    of a heated tube: all its flux in the top sector, and the flux times the sector's area is the
    rate of wall_heat.csv (its interval mean over 1 ms, while the bead's temperature relaxes
    over seconds: within 1e-3)."""
    from dem.thermal.kernel import TI
    Rc, ov = 4e-3, 1e-6
    walls = [{"type": "cylinder", "name": "tube", "point": [0, 0, 0], "axis": [0, 1, 0], "radius": Rc,
              "inside": False, "length": 0.004, "material": "p",
              "thermal": {"condition": "fixed_temperature", "temperature": 400.0}}]
    sc = scene([{"material": "p", "positions": [[1e-9, 0.0, Rc + R - ov]], "radius": R, "temperature": 300.0}],
               {"direct": "batchelor_obrien", "indirect": "voronoi_a", "integrator": "euler",
                "porosity": "global"}, walls, end=0.005, dt=1e-6, output=0.001)
    sc["simulation"].update(mechanics=True, gravity=[0, 0, -9.81])
    sim = Simulation.from_dict(sc)
    assert sim.thermal.thi[TI.fused] == 1
    sim.run(out_dir=str(tmp_path / "out"), progress=False)
    with open(tmp_path / "out" / "wall_heat_angle.csv", newline="") as f:
        rows = [r for r in csv.DictReader(f) if float(r["time"]) == pytest.approx(0.005)]
    q = np.array([float(r["contact_W_m2"]) + float(r["gas_gap_W_m2"]) for r in rows])
    assert np.flatnonzero(q).tolist() == [0]
    rate = read(tmp_path / "out" / "wall_heat.csv")[("tube", "total")][-1, 2]
    assert rate > 0
    assert q[0] * 2 * math.pi * Rc * 0.004 / 24 == pytest.approx(rate, rel=1e-3)
