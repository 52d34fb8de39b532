"""Coarse graining (issue 15; docs/models.md "Coarse graining").

A parcel of factor cg has the radius cg r (r: the real particles' radius the scene gives), the
same density and material, and stands for W = cg^3 real particles. Its exchanges are its real
particles' laws scaled:

* fluid: drag and convection with the real diameter (Re, Nu, C_d), times W (each drag law and
  each Nusselt correlation);
* radiation: W times the real particle's, i.e. cg times the parcel's own surface;
* conduction: a pair's conductance is cg times its real particles' law at the real size
  (lengths / cg), a wall contact's cg^2 times (so the bed's effective conductivity and the wall's
  conductance per area are the fine bed's);
* sources: a group's power per real particle times W.

cg = 1 is today's run bit for bit. Bad input is refused by name.
"""
from __future__ import annotations

import math
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from dem import Simulation
from dem.final import read as read_final

ROOT = Path(__file__).resolve().parents[1]
R = 0.5e-3
MAT = dict(name="p", density=2500.0, youngs_modulus=1e7, poisson_ratio=0.3, restitution=0.5, friction=0.3,
           thermal_conductivity=1.0, heat_capacity=840.0, emissivity=0.9)
AIR = dict(conductivity=0.026, density=1.2, viscosity=1.8e-5, heat_capacity=1005.0, temperature=350.0,
           porosity=0.4)


def _scene(positions, cg=None, thermal=None, walls=(), mechanics=True, end=2e-3, dom=0.01, gas=None, mat=None,
           extra=None):
    g = {"material": "p", "positions": positions, "radius": R, "temperature": 300.0}
    if cg is not None:
        g["coarse_graining"] = cg
    if extra:
        g.update(extra)
    sc = {"simulation": {"time_step": 1e-5, "end_time": end, "mechanics": mechanics, "gravity": [0, 0, -9.81],
                         "output_interval": end},
          "domain": {"min": [0, 0, 0], "max": [dom, dom, dom]}, "materials": [dict(mat or MAT)],
          "particles": [g], "walls": list(walls)}
    if thermal is not None:
        sc["thermal"] = thermal
        sc["gas"] = dict(gas or AIR)
    return sc


def _floor(T=400.0):
    return {"type": "plane", "name": "floor", "point": [0, 0, 0], "normal": [0, 0, 1], "material": "p",
            "thermal": {"condition": "fixed_temperature", "temperature": T, "emissivity": 0.5}}


def test_cg_one_is_the_run_without(tmp_path):
    """coarse_graining = 1 is exactly the scene without the key: every final array and the
    history bit for bit, and no parcel column in the output."""
    pos = [[0.002 + 0.0011 * i, 0.005, 0.0006 + 0.0011 * (i % 2)] for i in range(6)]
    th = {"direct": "batchelor_obrien", "indirect": "cheng_1999_voronoi_a", "convection": "gunn",
          "radiation": "zhou_2009"}
    gas = dict(AIR, velocity=[0.0, 0.0, 0.2])
    outs = []
    for k, cg in enumerate((None, 1.0)):
        sim = Simulation.from_dict(_scene(pos, cg, th, [_floor()], gas=gas))
        out = tmp_path / f"o{k}"
        sim.run(out_dir=str(out), progress=False)
        outs.append(out)
    a, b = read_final(outs[0] / "final.npz"), read_final(outs[1] / "final.npz")
    assert sorted(a.files) == sorted(b.files) and "coarse_graining" not in a.files
    for f in a.files:
        assert np.array_equal(a[f], b[f]), f
    assert (outs[0] / "history.csv").read_text() == (outs[1] / "history.csv").read_text()


def test_parcel_size_mass_and_output(tmp_path):
    sim = Simulation.from_dict(_scene([[0.005, 0.005, 0.005]], 3.0, {"direct": "batchelor_obrien"},
                                      mechanics=False, end=1e-4))
    st = sim.state
    assert st.radius[0] == pytest.approx(3 * R, rel=1e-15)
    real_mass = 2500.0 * 4 / 3 * math.pi * R ** 3
    assert st.mass[0] == pytest.approx(27 * real_mass, rel=1e-14)
    assert 1 / st.inv_heat_capacity[0] == pytest.approx(27 * real_mass * 840.0, rel=1e-14)
    sim.run(out_dir=str(tmp_path / "o"), progress=False)
    f = read_final(tmp_path / "o" / "final.npz")
    assert f["coarse_graining"].tolist() == [3.0]


@pytest.mark.parametrize("corr", ["ranz_marshall", "whitaker", "gunn", "li_mason"])
def test_convection_is_the_real_particles_times_W(corr):
    """h A of a parcel = cg^3 x 2 pi R_r k_f Nu(Re_r, Pr, eps), Re_r with the real diameter."""
    from dem.thermal import nusselt
    cg, u, eps = 2.5, 0.7, 0.45
    gas = dict(AIR, porosity=eps, velocity=[0.0, 0.0, u])
    sim = Simulation.from_dict(_scene([[0.005, 0.005, 0.005]], cg, {"direct": "none", "convection": corr,
                                                                     "porosity": "global"},
                                      mechanics=False, end=1e-4, gas=gas))
    hA = sim.thermal.convection_h()[0]
    Rr = R
    Re = eps * AIR["density"] * u * 2 * Rr / AIR["viscosity"]
    Pr = AIR["heat_capacity"] * AIR["viscosity"] / AIR["conductivity"]
    Nu = nusselt(corr, Re, Pr, eps)
    assert hA == pytest.approx(cg ** 3 * 2 * math.pi * Rr * AIR["conductivity"] * Nu, rel=1e-12)
    # ... and not the parcel's own law (the Re of the parcel's diameter)
    own = 2 * math.pi * cg * R * AIR["conductivity"] * nusselt(corr, cg * Re, Pr, eps)
    assert abs(hA / own - 1) > 0.05


@pytest.mark.parametrize("law", ["di_felice_1994", "gidaspow_1994", "beetstra_2007", "huilin_gidaspow_2003"])
def test_drag_is_the_real_particles_times_W(law):
    """beta of a parcel = cg^3 beta(d / cg) for every drag law, and the pressure-gradient force
    is on the parcel's whole volume."""
    from coupling.drag import DRAG_MODELS, drag_coefficient, drag_model_id
    from coupling.interface import DRAG_EXPLICIT, AtParticles, _particle_forces
    assert sorted(DRAG_MODELS) == sorted(["di_felice_1994", "gidaspow_1994", "beetstra_2007",
                                          "huilin_gidaspow_2003"])   # every law of the catalogue
    mid = drag_model_id(law)
    cg = np.array([1.0, 2.0, 3.0])
    rad = R * cg
    vel = np.zeros((3, 3))
    uf = np.tile([0.0, 0.0, 0.8], (3, 1))
    gradp = np.tile([0.0, 0.0, -1.2e4], (3, 1))
    eps = np.array([0.5, 0.5, 0.5])
    cells = np.zeros(3, np.int64)
    force, beta, bimp, fexp, fdrag, fpres = _particle_forces(
        mid, False, DRAG_EXPLICIT, AtParticles(rad, vel, uf, cells), cg, gradp, eps, np.zeros(0), vel, 1.2, 1.8e-5,
        np.array([0.0, 0.0, -9.81]))
    b1 = drag_coefficient(mid, 2 * R, 0.5, 1.2, 1.8e-5, 0.8)
    assert beta == pytest.approx(cg ** 3 * b1, rel=1e-13)
    vp = 4 / 3 * math.pi * rad ** 3
    assert force[:, 2] == pytest.approx(beta * 0.8 + vp * 1.2e4, rel=1e-13)
    # the output's split: the drag beta (u_f - u_p) and the pressure-gradient force -V_p grad p
    assert fdrag[:, 2] == pytest.approx(beta * 0.8, rel=1e-15) and fpres[:, 2] == pytest.approx(vp * 1.2e4, rel=1e-15)
    assert np.array_equal(force, fdrag + fpres)
    # without coarse graining (an empty cg), the law at the given diameter
    _, b0, _, _, _, _ = _particle_forces(mid, False, DRAG_EXPLICIT, AtParticles(rad[:1], vel[:1], uf[:1], cells[:1]),
                                   np.zeros(0), gradp[:1], eps[:1], np.zeros(0), vel[:1], 1.2, 1.8e-5, np.array([0.0, 0.0, -9.81]))
    assert b0[0] == b1


def test_radiation_is_the_real_particles_times_W(tmp_path):
    """A lone parcel (Zhou 2009, no neighbour: T_e = T_f): one Euler step's rate is
    cg^3 eps A_r sigma (T_f^4 - T^4), i.e. cg times its own surface's."""
    cg = 2.0
    sim = Simulation.from_dict(_scene([[0.005, 0.005, 0.005]], cg, {"direct": "none", "radiation": "zhou_2009",
                                                                     "integrator": "euler", "porosity": "global",
                                                                     "time_step": 1e-3},
                                      mechanics=False, end=1e-3, gas=dict(AIR, temperature=1000.0)))
    sim.run(out_dir=str(tmp_path / "o"), progress=False)
    q = 0.9 * 4 * math.pi * R * R * 5.670374419e-8 * (1000.0 ** 4 - 300.0 ** 4)
    assert sim.state.heat_rate[0] == pytest.approx(cg ** 3 * q, rel=1e-12)


@pytest.mark.parametrize("indirect", ["cheng_1999_voronoi_a", "vargas_mccarthy_2002"])
def test_pair_and_wall_conductances_scale_by_cg_and_cg2(tmp_path, indirect):
    """Two touching parcels and a parcel on a fixed-temperature wall, frozen, in the
    configuration of the fine pair scaled by cg (overlaps cg times the fine ones): the pair's
    direct and indirect conductances are cg times the fine pair's, the wall's cg^2 times, for a
    geometrically similar model (Voronoi A) and one with an absolute length (Vargas & McCarthy's
    gas mean free path), since each parcel law is its real particles' at the real size."""
    ov = 2e-6
    res = {}
    for cg in (1.0, 3.0):
        Rp = cg * R
        z0 = Rp - cg * ov   # on the floor, overlap cg ov; the second on top of it, overlap cg ov
        pos = [[0.01, 0.01, z0], [0.01, 0.01, z0 + 2 * Rp - cg * ov]]
        th = {"direct": "batchelor_obrien", "indirect": indirect, "integrator": "exponential",
              "porosity": "global", "time_step": 1e-3}
        walls = [{"type": "plane", "name": "floor", "point": [0, 0, 0], "normal": [0, 0, 1], "material": "p",
                  "thermal": {"condition": "fixed_temperature", "temperature": 400.0}}]
        sim = Simulation.from_dict(_scene(pos, cg, th, walls, mechanics=False, end=1e-3, dom=0.03))
        sim.run(out_dir=str(tmp_path / f"o{cg:g}"), progress=False)
        st = sim.state
        order = np.argsort(st.id)
        i0 = int(order[0])
        res[cg] = dict(Hd=float(st.Hd[st.Hd > 0].sum()), Hi=float(st.Hi[st.Hi > 0].sum()),
                       Hw=float(st.Hw[i0, 0]), Hwg=float(st.Hwg[i0, 0]))
    f, p = res[1.0], res[3.0]
    assert f["Hd"] > 0 and f["Hi"] > 0 and f["Hw"] > 0 and f["Hwg"] > 0
    assert p["Hd"] == pytest.approx(3 * f["Hd"], rel=1e-10)
    assert p["Hi"] == pytest.approx(3 * f["Hi"], rel=1e-10)
    assert p["Hw"] == pytest.approx(9 * f["Hw"], rel=1e-10)
    assert p["Hwg"] == pytest.approx(9 * f["Hwg"], rel=1e-10)


def test_group_source_is_per_real_particle(tmp_path):
    sim = Simulation.from_dict(_scene([[0.005, 0.005, 0.005]], 2.0, {"direct": "none", "integrator": "euler",
                                                                     "time_step": 1e-3,
                                                                     "sources": [{"group": 0, "power": 0.01}]},
                                      mechanics=False, end=1e-3))
    sim.run(out_dir=str(tmp_path / "o"), progress=False)
    assert sim.state.heat_rate[0] == pytest.approx(8 * 0.01, rel=1e-14)


def _check(tmp_path, scene_text):
    (tmp_path / "scene.toml").write_text(scene_text)
    env = dict(os.environ, PYTHONPATH=str(ROOT) + os.pathsep + os.environ.get("PYTHONPATH", ""))
    return subprocess.run([sys.executable, "-m", "dem", "check", str(tmp_path / "scene.toml")],
                          capture_output=True, text=True, env=env, cwd=str(tmp_path))


BASE = '''
[simulation]
time_step = 1e-5
end_time = 1e-4

[domain]
min = [0.0, 0.0, 0.0]
max = [0.02, 0.02, 0.02]

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
radius = 0.0005
positions = [[0.005, 0.005, 0.005]]
temperature = 300.0
coarse_graining = {cg}
{more}
[thermal]
direct = "{direct}"

[gas]
conductivity = 0.026
density = 1.2
viscosity = 1.8e-5
heat_capacity = 1005.0
temperature = 300.0
'''


@pytest.mark.parametrize("cg,direct,more,words", [
    (0.5, "batchelor_obrien", "", ["particles[0].coarse_graining", "must be in [1.0, inf)"]),
    (2.0, "batchelor_obrien",
     '\n[[particles]]\nmaterial = "p"\nradius = 0.0005\npositions = [[0.015, 0.015, 0.015]]\n'
     'temperature = 300.0\ncoarse_graining = 3.0\n', ["different coarse-graining factors (2, 3)"]),
])
def test_bad_coarse_graining_is_refused_by_name(tmp_path, cg, direct, more, words):
    r = _check(tmp_path, BASE.format(cg=cg, direct=direct, more=more))
    out = r.stdout + r.stderr
    assert r.returncode == 2, out
    assert "scene.toml" in out and "Traceback" not in out
    for w in words:
        assert w in out, out


def _coupled_case(dest, cg=2.0, coupling_extra=""):
    """4 parcels of cg x 1 mm radius (real beads of 2 mm) resting apart on the floor of a 24 x 24
    x 30 mm box meshed 3 x 3 x 6, hot gas (373.15 K) entering at 0.5 m/s."""
    sys.path.insert(0, str(ROOT / "benchmarks"))
    from stability.coupled import write_case
    Rp = 1e-3 * cg
    x = [[0.006, 0.006, Rp], [0.018, 0.006, Rp], [0.006, 0.018, Rp], [0.018, 0.018, Rp]]
    case = write_case(Path(dest), L=0.024, H=0.03, nxy=3, nz=6, positions=x, dt_dem=1e-5, interval=10,
                      n_steps=10, u_in=0.5, mechanics=True, periodic=False, walls_top=False)
    t = (case / "dem.toml").read_text()
    a = 'file = "particles.csv"\ntemperature = 300.0\n'
    assert a in t
    (case / "dem.toml").write_text(t.replace(a, a + f"coarse_graining = {cg!r}\n"))
    if coupling_extra:
        with open(case / "coupling.toml", "a") as fh:
            fh.write(coupling_extra)
    return case


def _cli(*args, cwd):
    env = dict(os.environ, PYTHONPATH=str(ROOT) + os.pathsep + os.environ.get("PYTHONPATH", ""))
    return subprocess.run([sys.executable, "-m", *args], capture_output=True, text=True, env=env, cwd=str(cwd))


def test_coarse_grained_coupled_run(tmp_path, solver):
    """A short coupled run of parcels (cg = 2) through the command line: the parcels are heated
    by the gas, coupling.csv's energy balance closes, final.npz carries the factor, and the
    gas's heat from the parcels is what their records say (E_conv_particles)."""
    case = _coupled_case(tmp_path / "case")
    r = _cli("coupling.run", "run", str(case), "--out", str(tmp_path / "out"), cwd=ROOT)
    assert r.returncode == 0, r.stdout[-2000:] + r.stderr[-2000:]
    f = read_final(tmp_path / "out" / "final.npz")
    assert f["coarse_graining"].tolist() == [2.0] * 4
    assert np.all(f["temperature"] > 300.0)
    c = np.atleast_1d(np.genfromtxt(tmp_path / "out" / "coupling.csv", delimiter=",", names=True))
    through = np.abs(c["E_open"]) + np.abs(c["E_walls_gas"]) + np.abs(c["E_walls_particles"])
    scale = np.abs(c["E_particles"]) + np.abs(c["E_gas_solver"])
    assert np.all(np.abs(c["balance_residual"]) <= 1e-14 * scale + 1e-9 * through)
    # the particles' energy gain is what convection gave them (no walls, no other source)
    mass = 2500.0 * 4 / 3 * math.pi * (2e-3) ** 3       # a parcel: 8 beads of 1 mm radius
    gain = float(((f["temperature"] - 300.0) * mass * 840.0).sum())
    assert c["E_conv_particles"][-1] == pytest.approx(gain, rel=1e-9)


def test_coupled_torque_with_parcels_is_refused(tmp_path):
    case = _coupled_case(tmp_path / "case", coupling_extra='torque = "rotational_drag"\n')
    r = _cli("coupling.run", "check", str(case), cwd=tmp_path)
    out = r.stdout + r.stderr
    assert r.returncode == 2, out
    assert "coupling.toml" in out and "torque" in out and "coarse_graining = 2" in out
    assert "Traceback" not in out


def test_dem_check_reports_the_parcels(tmp_path):
    r = _check(tmp_path, BASE.format(cg=2.0, direct="batchelor_obrien", more=""))
    assert r.returncode == 0, r.stdout + r.stderr
    assert "coarse graining, group 0: cg = 2, parcels of 2 x the real radius, each 8 real particles: " \
           "1 parcels = 8 real particles" in r.stdout


def test_dem_check_warns_of_a_period_few_parcels_across(tmp_path):
    """A periodic axis of 20 mm is 20 diameters of these 1 mm beads, but 5 parcel diameters at
    cg = 4: dem check warns (naming the axis, the count and the length to give), and says nothing
    for the fine bed in the same domain."""
    per = BASE.replace('max = [0.02, 0.02, 0.02]\n', 'max = [0.02, 0.02, 0.02]\nperiodic = [false, true, false]\n')
    r = _check(tmp_path, per.format(cg=4.0, direct="batchelor_obrien", more=""))
    assert r.returncode == 0, r.stdout + r.stderr
    w = [ln for ln in r.stdout.splitlines() if ln.startswith("warning:")]
    assert len(w) == 1 and "axis y is periodic over 0.02 m, 5 parcel diameters" in w[0], r.stdout
    assert "at least 10 parcel diameters (0.04 m)" in w[0]
    r = _check(tmp_path, per.format(cg=1.0, direct="batchelor_obrien", more=""))
    assert r.returncode == 0 and "parcel diameters" not in r.stdout, r.stdout + r.stderr


def test_parcels_on_two_ranks_equal_serial(tmp_path):
    """A settling bed of parcels (cg = 2) heated by a radiating floor, the gas and conduction: 2
    MPI ranks give the serial run's temperatures, positions and factors bit for bit (the factor
    travels with the particles and their ghosts)."""
    import shutil
    sys.path.insert(0, str(ROOT / "tests"))
    if shutil.which("mpirun") is None:
        pytest.fail("Open MPI (mpirun) is part of this project's setup")
    from test_parallel import mpirun
    scene = str(ROOT / "tests" / "scenes" / "cg_heat_bed.toml")
    mpirun(1, "run", scene, "--out", str(tmp_path / "s"), "--quiet")
    mpirun(2, "run", scene, "--out", str(tmp_path / "p"), "--quiet")
    a, b = read_final(tmp_path / "s" / "final.npz"), read_final(tmp_path / "p" / "final.npz")
    ia, ib = np.argsort(a["id"]), np.argsort(b["id"])
    assert np.all(a["coarse_graining"] == 2.0) and a["temperature"].max() > 300.0
    for k in ("temperature", "position", "velocity", "coarse_graining"):
        assert np.array_equal(a[k][ia], b[k][ib]), k


def test_a_model_without_a_scaling_would_be_refused_by_name(monkeypatch):
    """Every model of the catalogue has its coarse-grained form; the guard that refuses one
    without (dem.thermal.scene.CG_REFUSED) names the model, the key and the way out."""
    from dem.scene import SceneError
    from dem.thermal import scene as ts
    monkeypatch.setitem(ts.CG_REFUSED, "batchelor_obrien", "a reason")
    with pytest.raises(SceneError) as e:
        Simulation.from_dict(_scene([[0.005, 0.005, 0.005]], 2.0, {"direct": "batchelor_obrien"}, mechanics=False,
                                    end=1e-4))
    msg = str(e.value)
    assert "particles[0].coarse_graining" in msg and 'thermal.direct = "batchelor_obrien"' in msg
    assert "a reason" in msg and "use coarse_graining = 1 or another direct model" in msg


def test_collisional_conduction_scales_by_W_during_the_collision(tmp_path):
    """zhou_2008_collisional: two parcels (cg = 2) colliding head-on at 0.5 m/s against the fine
    pair scaled (time step cg times, lengths cg times): at every step of the collisional phase
    the parcels' conductance is cg^3 the fine pair's, so a parcel collision, cg times longer,
    exchanges cg^4 the heat of a real one (the fine bed's collisional heat per volume at cg^-4
    the collision rate); in the static phase that follows (the contact outlives the Hertz time)
    cg times; contact, the switch and separation happen at the same step."""
    hist = {}
    for cg in (1.0, 2.0):
        Rp = cg * R
        gap = 0.2 * Rp
        pos = [[0.01 - Rp - gap / 2, 0.01, 0.01], [0.01 + Rp + gap / 2, 0.01, 0.01]]
        sc = _scene(pos, cg, {"direct": "zhou_2008_collisional", "integrator": "exponential"},
                    mechanics=True, end=1e-3, dom=0.02, extra={"velocities": [[0.25, 0, 0], [-0.25, 0, 0]]})
        sc["simulation"]["gravity"] = [0, 0, 0]
        sc["simulation"]["time_step"] = 1e-6 * cg
        sim = Simulation.from_dict(sc)
        h = []
        for _ in range(400):
            sim.step(1)
            h.append(float(sim.state.Hd[sim.state.Hd > 0].sum()) if sim.state.Hd.size else 0.0)
        hist[cg] = np.array(h)
    f, p = hist[1.0], hist[2.0]
    on = np.flatnonzero(f > 0)
    assert on.size > 20 and on[-1] < 399          # the collision is resolved and over
    assert np.array_equal(np.flatnonzero(p > 0), on)
    # Zhou's law is collisional while the contact is younger than the Hertz collision time, then
    # static (Batchelor & O'Brien, scaled by cg like every static contact)
    ratio = p[on] / f[on]
    coll = np.abs(ratio - 8.0) <= 8e-9
    # (the overlap of the last steps before separation is a few 1e-9 of the radius: the round-off
    # of the scaled positions shows in it, 3e-5 at the last step)
    stat = np.abs(ratio - 2.0) <= 2e-4
    assert np.all(coll | stat)
    k = int(np.argmin(coll))          # the first static step
    assert k > 20 and np.all(coll[:k]) and np.all(stat[k:])


def test_coupling_check_uses_the_real_particles(tmp_path):
    """`coupling check` of a case of parcels (cg = 2 of 2 mm beads) reports the minimum
    fluidization velocity of the real beads (the parcels follow their drag), not of a 4 mm
    sphere."""
    from coupling.drag import wen_yu_1966_umf
    case = _coupled_case(tmp_path / "case")
    r = _cli("coupling.run", "check", str(case), cwd=tmp_path)
    assert r.returncode == 0, r.stdout + r.stderr
    line = [ln for ln in r.stdout.splitlines() if ln.strip().startswith("u_mf")]
    assert len(line) == 1, r.stdout
    umf = float(line[0].split()[1])
    assert umf == pytest.approx(wen_yu_1966_umf(2e-3, 2500.0, 1.2, 1.8e-5, 9.81), rel=1e-3)
    assert abs(umf / wen_yu_1966_umf(4e-3, 2500.0, 1.2, 1.8e-5, 9.81) - 1) > 0.3


def test_parcel_heat_own_is_the_parcels_own_law():
    """[thermal] parcel_heat = "own" (a comparison): a parcel exchanges heat as a particle of its
    size would, 2 pi R_p k_f Nu(Re_p), what a code without the thermal scaling computes."""
    from dem.thermal import nusselt
    cg, u, eps = 2.5, 0.7, 0.45
    gas = dict(AIR, porosity=eps, velocity=[0.0, 0.0, u])
    sim = Simulation.from_dict(_scene([[0.005, 0.005, 0.005]], cg, {"direct": "none", "convection": "ranz_marshall",
                                                                     "porosity": "global", "parcel_heat": "own"},
                                      mechanics=False, end=1e-4, gas=gas))
    Rp = cg * R
    Re = eps * AIR["density"] * u * 2 * Rp / AIR["viscosity"]
    Pr = AIR["heat_capacity"] * AIR["viscosity"] / AIR["conductivity"]
    own = 2 * math.pi * Rp * AIR["conductivity"] * nusselt("ranz_marshall", Re, Pr, eps)
    assert sim.thermal.convection_h()[0] == pytest.approx(own, rel=1e-12)


def test_million_bead_case_passes_its_checks(tmp_path):
    """openfoam_cases/fluidized_bed_cg: 37,100 parcels of cg 3 are 1,001,700 real beads; `coupling
    check` accepts it without a warning and reports the real beads' minimum fluidization velocity
    (Wen & Yu for the smallest, 0.475 mm), which the inlet's 0.377 m/s exceeds twice over."""
    from coupling.drag import wen_yu_1966_umf
    case = ROOT / "openfoam_cases" / "fluidized_bed_cg"
    r = _cli("coupling.run", "check", str(case), cwd=tmp_path)
    out = r.stdout + r.stderr
    assert r.returncode == 0, out
    assert "WARNING" not in out and "verdict: OK" in out
    vals = dict(ln.split(None, 1) for ln in r.stdout.splitlines() if ln.startswith("  ") and len(ln.split()) == 2)
    assert int(vals["particles"]) * 27 == 1001700
    umf = float(vals["u_mf"])
    assert umf == pytest.approx(wen_yu_1966_umf(0.475e-3, 2500.0, 1.2, 1.8e-5, 9.81), rel=1e-3)
    assert 0.377 / wen_yu_1966_umf(0.5e-3, 2500.0, 1.2, 1.8e-5, 9.81) == pytest.approx(2.0, rel=0.01)


def test_parcels_stopped_and_continued_equal_one_run(tmp_path):
    """Through the command line: the parcel bed run to 0.01 s and continued to 0.02 s (--restart)
    ends bit for bit where one run does, with the same wall_heat.csv; a restart that changes the
    factor is refused, naming it (the parcels are initial conditions)."""
    scene = str(ROOT / "tests" / "scenes" / "cg_heat_bed.toml")

    def dem(*args, scene_file=scene):
        return _cli("dem", "run", scene_file, "--quiet", *args, cwd=tmp_path)
    assert dem("--out", "one").returncode == 0
    assert dem("--out", "two", "--end-time", "0.01").returncode == 0
    assert dem("--out", "two", "--restart", "two/checkpoint.npz").returncode == 0
    a, b = read_final(tmp_path / "one" / "final.npz"), read_final(tmp_path / "two" / "final.npz")
    for k in a.files:
        assert np.array_equal(a[k], b[k]), k
    assert (tmp_path / "one" / "wall_heat.csv").read_text() == (tmp_path / "two" / "wall_heat.csv").read_text()
    edited = tmp_path / "edited.toml"
    edited.write_text(Path(scene).read_text().replace("coarse_graining = 2.0", "coarse_graining = 3.0"))
    r = dem("--out", "two", "--restart", "two/checkpoint.npz", "--end-time", "0.03", scene_file=str(edited))
    out = r.stderr + r.stdout
    assert r.returncode == 2 and "edited.toml" in out and "coarse-graining factors (particles[].coarse_graining) " \
        "differ from the scene that wrote the checkpoint" in out
