"""Every guard of a run, triggered on purpose, with the message the user sees.

DEM (SimulationError, raised by Simulation.run/step): overlap (pair and wall), non-finite
velocity, temperature (Euler and exponential advice), domain; `dem check` warnings (impact
overlap, Euler above the network limit). The initial-overlap and step-limit SceneErrors are
tested in tests/test_scene_errors.py (initial-overlap, test_time_step_above_limit_*).

Coupled: the case checks (cell size, eps_min clipping of the initial void fraction,
particle Courant number: `coupling check` and `coupling run` refuse), the gas-field guard
on every frame received from thermoDemFoam (GasFieldError), the runtime warnings (eps
clipping, sudden eps change, gas faster than Mach 0.3), a DEM guard inside a coupled run
(exit status 4, checkpoint written) and the solver's own check of the DEM data. The
benchmarks/stability sweeps show where each one fires (docs/benchmarks/stability.md, "Stability map").
"""
from __future__ import annotations

import math
import re
import sys
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

from dem import Simulation  # noqa: E402
from dem.simulation import SimulationError  # noqa: E402

R = 1e-3
MAT = dict(name="p", density=2500.0, youngs_modulus=1e7, poisson_ratio=0.3, restitution=0.5,
           friction=0.3, thermal_conductivity=1.0, heat_capacity=840.0)


def scene(particles, walls=(), thermal=None, dt=1e-6, end=1e-3, mech=True, L=0.01, **sim):
    sc = {"simulation": dict({"time_step": dt, "end_time": end, "mechanics": mech, "gravity": [0, 0, 0],
                              "force": True}, **sim),
          "domain": {"min": [-L] * 3, "max": [L] * 3}, "materials": [dict(MAT)],
          "particles": particles, "walls": list(walls)}
    if thermal is not None:
        sc["thermal"] = thermal
    return sc


def run_error(sc, steps=None):
    sim = Simulation.from_dict(sc)
    with pytest.raises(SimulationError) as ei:
        if steps:
            sim.step(steps)
        else:
            sim.run(progress=False)
    return str(ei.value), sim


# --------------------------------------------------------------------------- DEM guards

def test_overlap_guard_pair():
    """Pair impact at 1 m/s with a step of twice the Hertz time: overlap guard at once."""
    sc = scene([{"material": "p", "positions": [[-R - 1e-5, 0, 0], [R + 1e-5, 0, 0]], "radius": R,
                 "velocities": [[0.5, 0, 0], [-0.5, 0, 0]]}], dt=4e-4, end=4e-3)
    msg, sim = run_error(sc)
    assert re.search(r"particle id \d at \[.*\] and particle id \d overlap by [0-9.]+ of the radius at t = "
                     r"[0-9.e-]+ s \(step \d+\), beyond simulation.max_overlap_ratio = 0.1", msg), msg
    assert "Lower time_step (now 0.0004 s), raise youngs_modulus, or lower the impact speeds" in msg
    assert np.isfinite(sim.state.position).all() and np.isfinite(sim.state.velocity).all()


def test_overlap_guard_wall():
    """A soft sphere onto a wall at 10 m/s (Hertz overlap 1.3 R): the guard names the wall."""
    sc = scene([{"material": "p", "positions": [[0, 0, R * 1.01]], "radius": R, "velocities": [[0, 0, -10.0]]}],
               walls=[{"type": "plane", "name": "floor", "point": [0, 0, 0], "normal": [0, 0, 1],
                       "material": "p"}], dt=2e-7, end=1e-3)
    sc["materials"][0]["youngs_modulus"] = 1e6
    msg, _ = run_error(sc)
    assert "particle id 1 at" in msg and "and wall floor overlap by" in msg, msg
    assert "beyond simulation.max_overlap_ratio = 0.1" in msg


def test_nonfinite_velocity_guard():
    """A NaN force (e.g. from a broken fluid coupling) is caught at the next step."""
    sc = scene([{"material": "p", "positions": [[0, 0, 0], [0.005, 0, 0]], "radius": R}])
    sim = Simulation.from_dict(sc)
    sim.set_fluid(force=np.array([[0.0, 0.0, 0.0], [np.nan, 0.0, 0.0]]))
    with pytest.raises(SimulationError) as ei:
        sim.step(3)
    msg = str(ei.value)
    assert re.search(r"particle id 2 got a non-finite velocity at t = [0-9.e-]+ s \(step 1\): the run is "
                     r"unstable", msg), msg
    assert "Lower time_step (now 1e-06 s; see `dem check`), or check forces and properties" in msg


def _pair_heat(integrator, dt, **th):
    d = 2 * R - 2e-5
    t = {"direct": "batchelor_obrien", "integrator": integrator, "time_step": dt}
    t.update(th)
    return scene([{"material": "p", "positions": [[0, 0, 0]], "radius": R, "temperature": 400.0},
                  {"material": "p", "positions": [[d, 0, 0]], "radius": R, "temperature": 300.0}],
                 thermal=t, dt=1e-5, end=200 * dt, mech=False)


def test_temperature_guard_euler():
    """Euler far above the network limit: the oscillation drives a temperature below 0 K."""
    sc = _pair_heat("euler", 1.0)
    lim = Simulation.from_dict(sc).check()["network_step_limit"]
    sc = _pair_heat("euler", 50 * lim)
    sim = Simulation.from_dict(sc)
    assert any("exceeds the network stability limit" in w for w in sim.check()["warnings"])
    msg, sim = run_error(sc)
    assert re.search(r"particle id \d reached temperature -?[0-9.e+-]+ K at t = [0-9.e+-]+ s \(step \d+\): the "
                     r"heat step \(euler, dt = [0-9.e+-]+ s\) is unstable", msg), msg
    assert 'use thermal.integrator = "exponential" or a step below the network and radiation limits' in msg


def test_temperature_guard_exponential_source():
    """Exponential update with an explicit heat sink larger than the particle's heat content."""
    sc = _pair_heat("exponential", 10.0, sources=[{"group": 0, "power": -1.0}])
    msg, _ = run_error(sc)
    assert "reached temperature" in msg and "(exponential, dt = 10 s)" in msg, msg
    assert "lower the thermal step: heat sources, fixed wall fluxes or friction heat are explicit" in msg


def test_domain_guard():
    sc = scene([{"material": "p", "positions": [[0, 0, 0]], "radius": R, "velocities": [[0, 0, 5.0]]}],
               dt=1e-5, end=0.01)
    msg, sim = run_error(sc)
    assert re.search(r"particle id 1 left the domain at t = [0-9.e-]+ s \(step \d+\) at \[.*\] \(domain "
                     r"\[-0.01, -0.01, -0.01\] to \[0.01, 0.01, 0.01\]\)", msg), msg
    assert "Add walls, enlarge [domain], or make the axis periodic" in msg
    assert sim.time < 0.0025


def test_check_warns_impact_overlap():
    """`dem check` predicts the overlap guard of a soft impact at the characteristic velocity."""
    sc = scene([{"material": "p", "positions": [[0, 0, 0]], "radius": R}], dt=1e-7)
    sc["materials"][0]["youngs_modulus"] = 1e6
    sc["contact"] = {"characteristic_velocity": 3.0}
    w = Simulation.from_dict(sc).check()["warnings"]
    assert any(re.search(r"a Hertz impact at the characteristic velocity 3 m/s overlaps [0-9.]+ of the radius, "
                         r"above simulation.max_overlap_ratio = 0.1: the overlap guard may stop the run", x)
               for x in w), w
    sc["contact"] = {"characteristic_velocity": 0.1}
    assert not any("Hertz impact" in x for x in Simulation.from_dict(sc).check()["warnings"])


# --------------------------------------------------------------------------- coupled: unit level

def test_gas_field_guard_messages():
    from coupling.exchange import CouplingError
    from coupling.diagnostics import GasFieldError, check_gas_fields
    n = 6
    fluid = dict(U=np.zeros((n, 3)), T=np.full(n, 300.0), gradp=np.zeros((n, 3)), p=np.zeros(n))
    mesh = SimpleNamespace(cell_centres=np.arange(3 * n, dtype=float).reshape(n, 3) * 1e-3)
    cfg = SimpleNamespace(smoothing_time=0.0, eps_min=0.3, void_fraction="centre")
    assert check_gas_fields(fluid, 1, time_value=0.1, mesh=mesh, cfg=cfg) is fluid
    cases = [("T", 3, np.nan, r"gas field T received from the solver is non-finite in 1 cell\(s\) \(first: "
                                r"cell 3 at \[0.009 0.01 +0.011\]"),
             ("p", 2, np.inf, r"gas field p .* is non-finite"),
             ("T", 4, -5.0, r"gas field T .* is at or below 0 K in 1 cell\(s\) \(first: cell 4"),
             ("U", 5, 400.0, r"gas field U .* is faster than 343 m/s \(the speed of sound\)")]
    for name, c, val, pat in cases:
        f = {k: v.copy() for k, v in fluid.items()}
        f[name][c] = val
        with pytest.raises(GasFieldError) as ei:
            check_gas_fields(f, 7, time_value=0.5, mesh=mesh, cfg=cfg)
        msg = str(ei.value)
        assert isinstance(ei.value, CouplingError)
        assert re.search(pat, msg), msg
        assert "at t = 0.5 s: the gas solution diverged; the field is not passed to the particles" in msg
        assert "Check log.thermoDemFoam; lower deltaT" in msg and "smoothing_time to a few CFD steps (now 0 s)" in msg
        assert "raise coupling.eps_min (now 0.3) or use void_fraction = 'divided' or 'smoothed'" in msg
        assert msg.endswith("[peer: CFD solver, coupling step 7]")
    # after a sudden eps change the message names it and puts smoothing first
    f = {k: v.copy() for k, v in fluid.items()}
    f["U"][1, 2] = -360.0
    with pytest.raises(GasFieldError) as ei:
        check_gas_fields(f, 4, time_value=4e-5, mesh=mesh, cfg=cfg, eps_change=(0.7, 2))
    msg = str(ei.value)
    assert "the void fraction of cell 2 changed by 0.7 in the last coupling step" in msg, msg
    assert re.search(r"; set coupling.smoothing_time .*; if particles moved that far within one step, lower deltaT",
                     msg), msg


def test_run_watch_warns_once():
    from coupling.diagnostics import RunWatch
    lines = []
    mesh = SimpleNamespace(cell_centres=np.zeros((10, 3)))
    cfg = SimpleNamespace(smoothing_time=0.0, eps_min=0.3, void_fraction="centre")
    w = RunWatch(mesh, cfg, lines.append)
    iface = SimpleNamespace(clip=dict(cells=3, volume=1e-9, fraction=0.2, eps_raw_min=-1.5, cell=4),
                            eps_change=(0.6, 5))
    for t in (0.0, 1e-3):
        w.after_prepare(iface, t)
        w.after_receive(dict(U=np.full((10, 3), 70.0)), t)     # |U| = 121 m/s
    assert len(lines) == 3, lines
    assert re.search(r"at t = 0 s the void fraction of 3 cell\(s\) is below coupling.eps_min = 0.3 \(lowest "
                     r"1 - V_solid/V_cell = -1.5 in cell 4 at .*\) and is clipped: 20 % of the particle volume is "
                     r"not seen by the gas", lines[0]), lines[0]
    assert "void_fraction = 'divided' or 'smoothed' (now 'centre')" in lines[0]
    assert "the void fraction of cell 5 at" in lines[1] and "changes by 0.6 in one coupling step" in lines[1]
    assert "coupling.smoothing_time" in lines[1]
    assert "the gas speed is 121 m/s in cell 0" in lines[2] and "Mach 0.3" in lines[2]
    s = w.summary()
    assert s["eps_clipping"]["fraction"] == 0.2 and s["eps_change_max"] == 0.6
    assert s["gas_speed_max"] == pytest.approx(70 * math.sqrt(3))


# --------------------------------------------------------------------------- coupled: with the solver

def _lattice(L=0.02, d=2e-3, layers=3):
    n = int(L / (1.05 * d))
    g = (np.arange(n) + 0.5) * L / n
    z = (np.arange(layers) + 0.5) * 1.05 * d
    X, Y, Z = np.meshgrid(g, g, z, indexing="ij")
    return np.c_[X.ravel(), Y.ravel(), Z.ravel()]


def _case(tmp_path, name, L=0.02, H=0.02, positions=None, **kw):
    """A coupled case of benchmarks/stability (L x L x H box, hot air from below, beads at rest
    on a lattice unless positions are given)."""
    from benchmarks.stability.coupled import write_case
    return write_case(tmp_path / name, L=L, H=H, positions=_lattice(L) if positions is None else positions, **kw)


def test_coupled_check_cell_size_and_clipping(tmp_path, solver, capsys):
    from coupling.run import main as coupling_main
    # 1 mm cells, 2 mm beads, centre: each particle overfills its cell -> refused
    c = _case(tmp_path, "fine", nxy=20, nz=20, void_fraction="centre")
    rc = coupling_main(["check", str(c)])
    out = capsys.readouterr().out
    assert rc == 2, out
    assert "WARNING: smallest cell 0.001 m is 0.50 particle diameters: particles larger than the cells" in out
    assert re.search(r"PROBLEM: initial void fraction below coupling.eps_min = 0.3 in 243 cell\(s\) \(lowest "
                     r"1 - V_solid/V_cell = -3.19\): clipping hides [0-9.]+ % of the particle volume from the gas; "
                     r"use void_fraction = 'divided' or 'smoothed' \(.*\) in coupling.toml \(now 'centre'\) or cells "
                     r"of at least 0.006 m \(system/blockMeshDict\) \(refused above 5 %\)", out), out
    assert "verdict: refused (fix the problems or set coupling.force = true)" in out
    # 4 mm cells, divided: a warning only
    c = _case(tmp_path, "mid", nxy=5, nz=5, void_fraction="divided")
    rc = coupling_main(["check", str(c)])
    out = capsys.readouterr().out
    assert rc == 0, out
    w = [ln for ln in out.splitlines() if "WARNING: void fraction averaged over 0.004 m = 2.00 particle diameters "
         "(< 3; void_fraction = 'divided' averages over the cells; smallest cell 0.004 m)" in ln]
    assert len(w) == 1 and "void fraction and drag of the unresolved model are inaccurate" in w[0], out
    assert "use cells of at least 0.006 m with 'divided'" in w[0], w[0]    # 3 diameters
    assert "void_fraction = 'divided' in" not in w[0]                    # never the model in use
    assert "larger than the cells" not in out and "PROBLEM" not in out


def test_coupled_run_refused_by_particle_courant(tmp_path, solver):
    from coupling.run import CouplingRunError, run_case
    c = _case(tmp_path, "fast", nxy=5, nz=5, interval=100, n_steps=2,
              velocities=np.tile([0.0, 0.0, 20.0], (243, 1)))
    with pytest.raises(CouplingRunError) as ei:
        run_case(c, tmp_path / "out", quiet=True)
    msg = str(ei.value)
    assert "coupling.toml: case refused by the checks" in msg
    assert re.search(r"particle Courant number 5 > 0.5: particles move up to 20 m/s \(the largest initial particle "
                     r"speed\) x coupling step 0.001 s = 5 of the smallest cell edge 0.004 m per coupling step", msg), msg
    # the fix: 0.1 x 4 mm / (20 m/s x 1e-5 s) = 2 DEM steps per coupling step
    assert "set deltaT = 2e-05 s in system/controlDict and coupling_interval = 2 in coupling.toml" in msg, msg
    assert not (tmp_path / "out" / "log.thermoDemFoam").exists()      # the solver never started


def test_coupled_check_relaxation_and_gas_cfl(tmp_path, solver, capsys):
    """0.1 mm, 250 kg/m3 beads with a 3 ms coupling step (many drag relaxation times) and
    a 30 m/s gas: the gas CFL is a problem; the coupling step over the bed's drag relaxation
    time m/beta_imp is a warning only (the semi-implicit drag is stable at any step: docs/models.md),
    with the particles' void fraction and the step that resolves it."""
    from coupling.run import main as coupling_main
    x = _lattice(L=1e-3, d=1e-4)
    c = _case(tmp_path, "fine", L=1e-3, H=2e-3, positions=x, nxy=3, nz=6, diameter=1e-4, density=250.0, youngs=1e5,
              dt_dem=3e-6, interval=1000, n_steps=2, u_in=30.0)
    rc = coupling_main(["check", str(c)])
    out = capsys.readouterr().out
    assert rc == 2, out
    assert re.search(r"PROBLEM: gas CFL [0-9.e+]+ > 1.0 \(\|U\|/eps = [0-9.]+ m/s, deltaT 0.003 s, cell ", out), out
    m = re.search(r"WARNING: coupling step 0.003 s is ([0-9.e+]+) x the drag relaxation time of the bed m/beta_imp = "
                  r"([0-9.e-]+) s \(void fraction ([0-9.]+), \|u\| = 30 m/s\): stable and exact at steady state, but "
                  r"the particles see the gas one coupling step late.*use deltaT <= ([0-9.e-]+) s in "
                  r"system/controlDict with coupling_interval = (\d+)", out)
    assert m, out
    ratio, tau, eps, dt_ok, k_ok = float(m.group(1)), float(m.group(2)), float(m.group(3)), float(m.group(4)), \
        int(m.group(5))
    assert ratio == pytest.approx(0.003 / tau, rel=1e-2) and ratio > 1
    assert 0.3 <= eps < 1.0                      # the lattice's own void fraction, not a fixed 0.4
    assert k_ok * 3e-6 == pytest.approx(dt_ok, rel=1e-2) and dt_ok <= tau * (1 + 1e-9)
    assert "relaxation" not in "".join(ln for ln in out.splitlines() if "PROBLEM" in ln)


def test_gas_field_guard_stops_coupled_run(tmp_path, solver, capsys):
    """Initial gas at 400 m/s: the first frame of the solver is refused before the DEM moves."""
    from coupling.run import main as coupling_main
    c = _case(tmp_path, "u400", nxy=2, nz=2, n_steps=3, force=True)
    u = c / "0" / "U"
    u.write_text(re.sub(r"internalField\s+uniform \([^)]*\);", "internalField   uniform (0 0 400);", u.read_text()))
    out = tmp_path / "out"
    rc = coupling_main(["run", str(c), "--out", str(out), "--quiet"])
    err = capsys.readouterr().err
    assert rc == 3, err
    assert re.search(r"coupling: error: coupling failed: gas field U received from the solver is faster than "
                     r"343 m/s \(the speed of sound\) in 8 cell\(s\) \(first: cell 0 at \[0.005 0.005 0.005\], "
                     r"U = \[ *0. +0. +400.\]\) at t = 0 s: the gas solution diverged", err), err
    assert "[peer: CFD solver, coupling step 0]" in err and "DEM checkpoint at t = 0 s written" in err
    z = np.load(out / "checkpoint.npz")
    assert np.isfinite(z["state_position"]).all() and np.isfinite(z["state_temperature"]).all()


def test_dem_guard_inside_coupled_run(tmp_path, solver, capsys):
    """A bead leaving the domain through the open top: DEM domain guard, exit status 4."""
    from coupling.run import main as coupling_main
    c = _case(tmp_path, "leave", nxy=2, nz=4, H=0.04, positions=np.array([[0.01, 0.01, 0.03]]),
              velocities=np.array([[0.0, 0.0, 20.0]]), walls_top=False, n_steps=20, force=True)
    out = tmp_path / "out"
    rc = coupling_main(["run", str(c), "--out", str(out), "--quiet"])
    err = capsys.readouterr().err
    assert rc == 4, err
    assert re.search(r"coupling: error: DEM failed: particle id 1 left the domain at t = [0-9.e-]+ s \(step \d+\)",
                     err), err
    assert "Add walls, enlarge [domain]" in err
    z = np.load(out / "checkpoint.npz")
    assert z["step_count"] > 0 and np.isfinite(z["state_velocity"]).all()


@pytest.mark.parametrize("field, value", [("Ksl", -1.0), ("eps", np.nan)])
def test_solver_rejects_bad_dem_data(tmp_path, solver, field, value):
    """thermoDemFoam's own check of every DEM frame (eps in (0, 1], Ksl, Simp >= 0, finite): the
    solver stops and the DEM side reports the dead peer. (A NaN is reported cell by cell, then
    OpenFOAM's floating-point trap ends the solver before the summary line.)"""
    from coupling import foam_case as fc
    from coupling.exchange import CouplingError, FileExchange
    case = fc.copy_template("ergun", tmp_path / "ergun")
    fc.set_entries(case / "system" / "controlDict", {"deltaT": 1e-4, "endTime": "0.001", "writeInterval": 10})
    fc.block_mesh(case)
    n = len(fc.read_cell_volumes(case))
    fc.write_coupling_dict(case, "file", timeout=20)
    ex = FileExchange(case / "coupling", timeout=20)
    proc = fc.start_solver(case, solver=solver)
    ex.peer_process = proc
    frame = dict(eps=np.ones(n), Ksl=np.zeros(n), Us=np.zeros((n, 3)), Simp=np.zeros(n), Sexp=np.zeros(n))
    frame[field][7] = value
    try:
        ex.receive(0)
        ex.send(1, frame)
        with pytest.raises(CouplingError, match=r"CFD solver.*peer: CFD solver, coupling step 1"):
            ex.receive(1)
    finally:
        if proc.poll() is None:
            proc.kill()
        proc.wait()
    log = (case / "log.thermoDemFoam").read_text()
    assert re.search(rf"bad DEM data in local cell 7: eps {'nan' if field == 'eps' else '1'} Ksl "
                     rf"{'-1' if field == 'Ksl' else '0'} Simp 0 Sexp 0", log), log[-2000:]
    if field == "Ksl":
        assert "1 cells with non-physical data (need 0 < eps <= 1, Ksl >= 0, Simp >= 0, finite values) " \
               "[peer: DEM, coupling step 1]" in log, log[-2000:]
