"""The implicit (backward Euler) thermal integrator, thermal.integrator = "implicit".

Against the exact steady state of the conductance network at steps of 1 to 1000 network
steps, the exact discrete solution (1 + dt C^-1 A)^-n of backward Euler, the continuous
solution within the scheme's derived O(dt) bound, energy conservation, and the command line.
"""
import math
import os
import subprocess
import sys

import numpy as np
import pytest

from dem import Simulation
from test_thermal_runs import base, R, AIR
from dem.final import read as read_final

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
MATP = dict(name="p", density=2500.0, youngs_modulus=1e7, poisson_ratio=0.3, restitution=0.5,
            friction=0.3, thermal_conductivity=1.0, heat_capacity=840.0, emissivity=0.8)
HOT = {"condition": "fixed_temperature", "temperature": 400.0}
COLD = {"condition": "fixed_temperature", "temperature": 300.0}


def line_scene(dt, integrator, end, hot=HOT, cold=COLD):
    """Ten spheres of 1 mm in a line between two walls, touching with a 20 um overlap."""
    n, ov = 10, 2e-5
    xs = [R - ov + k * (2 * R - ov) for k in range(n)]
    L = xs[-1] + R - ov
    walls = [{"type": "plane", "name": "left", "point": [0, 0, 0], "normal": [1, 0, 0], "material": "p",
              "thermal": hot},
             {"type": "plane", "name": "right", "point": [L, 0, 0], "normal": [-1, 0, 0], "material": "p",
              "thermal": cold}]
    parts = [{"material": "p", "positions": [[x, 0, 0] for x in xs], "radius": R}]
    sc = base(parts, {"direct": "batchelor_obrien", "time_step": dt, "initial_temperature": 300.0,
                      "integrator": integrator}, walls=walls, end=end, mats=[dict(MATP)])
    sc["domain"] = {"min": [-0.001, -0.01, -0.01], "max": [L + 0.001, 0.01, 0.01]}
    return sc


def line(dt, integrator="implicit", end=1.0):
    sim = Simulation.from_dict(line_scene(dt, integrator, end))
    sim.state.temperature[:] = np.linspace(350.0, 300.0, 10)
    return sim


def network(sim):
    """(C, A, f): heat capacities, the network matrix A = L + K (pairs and fixed-temperature
    walls) and the wall source f, so that C dT/dt = f - A T (dense: for 10 particles only)."""
    st = sim.state
    n = st.n
    A = np.zeros((n, n))
    f = np.zeros(n)
    for i in range(n):
        for s in range(st.nnb[i]):
            j, h = st.nb[i, s], st.Hd[i, s]
            A[i, i] += h
            A[j, j] += h
            A[i, j] -= h
            A[j, i] -= h
        for q in range(st.wnn[i]):
            h, w = st.Hw[i, q], st.wnb[i, q]
            if h > 0 and st.wth[w, 0] == 1.0:
                A[i, i] += h
                f[i] += h * st.wth[w, 1]
    return 1.0 / st.inv_heat_capacity, A, f


def modes(sim):
    """Steady state and the modes of C dT/dt = f - A T: (T_ss, lam, U, c) with
    T(t) = T_ss + sum_k c_k exp(-lam_k t) U[:, k] from the current temperatures."""
    C, A, f = network(sim)
    Tss = np.linalg.solve(A, f)
    s = 1.0 / np.sqrt(C)
    lam, V = np.linalg.eigh(s[:, None] * A * s[None, :])
    U = s[:, None] * V
    c = V.T @ (np.sqrt(C) * (sim.state.temperature - Tss))
    return Tss, lam, U, c


@pytest.fixture(scope="module")
def net_limit():
    return line(1.0).thermal.network_limit()


@pytest.mark.parametrize("factor", [1, 10, 100, 1000])
def test_line_steady_state_exact_at_any_step(net_limit, factor):
    """The fixed point of backward Euler is Q(T) = 0 whatever dt: the chain reaches the exact
    network steady state (np.linalg.solve of the 10 x 10 system) to 1e-9 K at steps of 1 to
    1000 times the Euler limit (the exponential update is off by 7.7e-4 K already at 0.036)."""
    dt = factor * net_limit
    sim = line(dt)
    Tss, lam, _, _ = modes(sim)
    # the slowest mode decays by 1 / (1 + lam_min dt) a step: to 1e-13 of the initial 100 K
    nsteps = int(math.ceil(math.log(1e13) / math.log(1.0 + lam[0] * dt))) + 1
    sim.run(end_time=nsteps * dt, progress=False)
    assert sim.step_count == nsteps
    assert np.abs(sim.state.temperature - Tss).max() < 1e-9
    assert Tss.max() < 400.0 and Tss.min() > 300.0 and np.all(np.diff(Tss) < -1.0)


@pytest.mark.parametrize("integrator", ["implicit", "trbdf2"])
def test_two_particle_relaxation_discrete_formula(integrator):
    """Two spheres (R, 1.5 R), one contact conductance H: backward Euler multiplies
    T1 - T2 by 1 / (1 + z) a step, TR-BDF2 by its amplification R(z) (dem.thermal.step_error),
    z = H (1/C1 + 1/C2) dt (2 x 2 systems: two CG iterations are exact up to round-off), and
    sum C T is constant."""
    from dem.thermal.step_error import amplification
    sc = base([{"material": "p", "positions": [[0, 0, 0]], "radius": R, "temperature": 400.0},
               {"material": "p", "positions": [[2.5 * R - 2e-5, 0, 0]], "radius": 1.5 * R,
                "temperature": 300.0}],
              {"direct": "batchelor_obrien", "time_step": 7.0, "integrator": integrator}, end=84.0)
    sim = Simulation.from_dict(sc)
    st = sim.state
    C = 1.0 / st.inv_heat_capacity
    H = sim.state.Hd[sim.state.Hd > 0]
    assert H.size == 1
    sim.run(progress=False)
    n = sim.step_count
    assert n == 12
    ratio = (st.temperature[0] - st.temperature[1]) / 100.0
    z = H[0] * (1 / C[0] + 1 / C[1]) * 7.0
    assert z > 0.1  # a step the exponential formula and backward Euler tell apart
    assert ratio == pytest.approx(float(amplification(integrator, z)) ** n, rel=1e-12)
    assert np.sum(C * st.temperature) == pytest.approx(C[0] * 400 + C[1] * 300, rel=1e-14)


def test_line_transient_within_derived_bound(net_limit):
    """Small steps (0.1 and 0.2 of the Euler limit), to t = 150 s: the run equals the exact
    discrete solution T_ss + sum_k c_k (1 + lam_k dt)^-n u_k to the CG tolerance, and each
    mode's error against exp(-lam t) is bounded by (ln(1+z) >= z - z^2/2, z = lam dt)
        0 <= (1 + z)^-n - e^{-lam t} <= e^{-lam t} (e^{lam^2 t dt / 2} - 1)      (O(dt)),
    and Euler's, (ln(1-z) >= -z - z^2 / (2 (1 - z))), by e^{-lam t} (1 - e^{-lam^2 t dt / (2 (1 - z))}):
    the implicit and Euler runs differ by at most the sum of the two bounds, which halves
    with the step."""
    bounds = []
    for frac in (0.2, 0.1):
        dt = frac * net_limit
        end = 150.0
        runs = {}
        for integ in ("implicit", "euler"):
            sim = line(dt, integ, end)
            Tss, lam, U, c = modes(sim)
            sim.run(progress=False)
            runs[integ] = sim.state.temperature.copy()
        n = sim.step_count
        t = n * dt
        umax = np.abs(U).max(0)
        disc = Tss + U @ (c * (1.0 + lam * dt) ** -n)
        assert np.abs(runs["implicit"] - disc).max() < 1e-9
        z = lam * dt
        b_be = np.sum(np.abs(c) * umax * np.exp(-lam * t) * np.expm1(lam ** 2 * t * dt / 2))
        b_fe = np.sum(np.abs(c) * umax * np.exp(-lam * t) * -np.expm1(-lam ** 2 * t * dt / (2 * (1 - z))))
        exact = Tss + U @ (c * np.exp(-lam * t))
        assert np.abs(runs["implicit"] - exact).max() <= b_be + 1e-9
        assert np.abs(runs["euler"] - exact).max() <= b_fe + 1e-9
        diff = np.abs(runs["implicit"] - runs["euler"]).max()
        assert diff <= b_be + b_fe
        assert diff > 0.2 * (b_be + b_fe)  # the bound is not vacuous: the first-order errors are there
        bounds.append(b_be + b_fe)
    assert bounds[1] / bounds[0] == pytest.approx(0.5, rel=0.05)


def bed_scene(dt, end, integrator="implicit"):
    """A frozen 4 x 4 x 3 lattice of touching spheres (20 um overlaps) on a floor at 400 K, a
    side wall with a fixed flux of 2 kW/m2, gas convection (350 K gas), continuum radiation
    and a source of 5 mW per particle of group 1."""
    ov = 2e-5
    pitch = 2 * R - ov
    pos = [[R + i * pitch, R + j * pitch, R - ov + k * pitch] for i in range(4) for j in range(4) for k in range(3)]
    walls = [{"type": "plane", "name": "floor", "point": [0, 0, 0], "normal": [0, 0, 1], "material": "p",
              "thermal": HOT},
             {"type": "plane", "name": "side", "point": [R - ov, 0, 0], "normal": [1, 0, 0], "material": "p",
              "thermal": {"condition": "fixed_heat_flux", "heat_flux": 2000.0}}]
    parts = [{"material": "p", "positions": pos[:24], "radius": R, "temperature": 300.0},
             {"material": "p", "positions": pos[24:], "radius": R, "temperature": 320.0}]
    sc = base(parts, {"direct": "batchelor_obrien", "convection": "ranz_marshall", "radiation": "zhou_2009",
                      "time_step": dt, "integrator": integrator, "sources": [{"group": 1, "power": 0.005}]},
              walls=walls, gas=dict(AIR, temperature=350.0, velocity=[0.0, 0.0, 0.5]), end=end,
              mats=[dict(MATP)])
    sc["domain"] = {"min": [-0.001, -0.001, -0.001], "max": [0.01, 0.01, 0.01]}
    return sc


@pytest.mark.parametrize("integrator", ["implicit", "trbdf2"])
def test_energy_conserved_on_a_bed_with_walls_gas_radiation_sources(net_limit, integrator):
    """sum C (T - T0) equals the heat in from the walls (fixed temperature and flux), the gas,
    radiation and the sources, to the CG tolerance (relative 1e-10 a step), at a step far
    above the explicit limits (TR-BDF2: each link counted at T^n, T^g and T^{n+1} with the
    weights a, a, w of its two stages)."""
    sim = Simulation.from_dict(bed_scene(100.0, 3000.0, integrator))
    st = sim.state
    C = 1.0 / st.inv_heat_capacity
    e0 = np.sum(C * st.temperature)
    assert sim.thermal.network_limit() < 10.0  # dt = 100 s is > 10 network steps
    sim.run(progress=False)
    tot = sim.thermal.tot
    heat_in = tot[2] + tot[3] + tot[4] + tot[5] + tot[6]  # convection, radiation, generation, sources, walls
    gain = np.sum(C * st.temperature) - e0
    assert abs(sim.thermal.wtot.sum() - tot[6]) <= 1e-9 * abs(tot[6])
    assert sim.thermal.wtot[0] > 0 and sim.thermal.wtot[1] > 0 and tot[5] > 0 and tot[2] != 0 and tot[3] != 0
    scale = np.sum(np.abs(tot[2:7]))
    assert abs(gain - heat_in) <= 1e-9 * scale
    assert np.all(np.isfinite(st.temperature)) and st.temperature.min() > 300.0


def test_trbdf2_wall_table_second_order_and_balanced(net_limit):
    """A hot wall ramped 300 -> 400 K over 60 s (a temperature table): TR-BDF2 takes the wall at
    each stage's time (t_n, t_n + gamma dt, t_n+1), so halving the step divides the error at
    t = 120 s (against a run at dt / 16) by about 4, second order (with the wall at the end of
    the step only it would be first order: about 2); the heat balance closes at each step."""
    ramp = {"condition": "fixed_temperature", "table": [[0.0, 300.0], [60.0, 400.0]]}
    dts = (120.0 / 8, 120.0 / 16, 120.0 / 128)   # 0.82, 0.41, 0.05 network limits; the ramp's end on a step
    finals = []
    for dt in dts:
        n = int(round(120.0 / dt))
        sim = Simulation.from_dict(line_scene(dt, "trbdf2", n * dt, hot=ramp))
        st = sim.state
        C = 1.0 / st.inv_heat_capacity
        e0 = np.sum(C * st.temperature)
        sim.run(progress=False)
        assert sim.step_count == n
        gain = np.sum(C * st.temperature) - e0
        assert gain == pytest.approx(sim.thermal.wtot.sum(), rel=1e-9)
        finals.append(st.temperature.copy())
    e1 = np.abs(finals[0] - finals[2]).max()
    e2 = np.abs(finals[1] - finals[2]).max()
    assert e1 > 1e-6   # the ramp is resolved by neither step exactly
    assert 3.0 < e1 / e2 < 5.0


# ------------------------------------------------------------------ the frozen default (auto)
def _steps_to_converge(name, lam, dt, drop=1e13):
    """Steps after which every mode of rates lam has decayed by ``drop`` under the scheme
    ``name`` (its per-step amplification, dem.thermal.step_error.amplification)."""
    from dem.thermal.step_error import amplification
    rho = np.abs(amplification(name, lam * dt)).max()
    return int(math.ceil(math.log(drop) / -math.log(rho))) + 1


@pytest.mark.parametrize("factor,chosen", [(1, "trbdf2"), (10, "trbdf2"), (100, "implicit"),
                                           (1000, "implicit")])
def test_default_line_steady_state_exact_at_any_step(net_limit, factor, chosen):
    """The default integrator of a frozen packing (auto) reaches the exact network steady state
    (np.linalg.solve of the 10 x 10 system) to 1e-8 K at 1, 10, 100 and 1000 times the Euler
    limit: it picks TR-BDF2 or backward Euler by the step (dem.thermal.step_error.choose), both
    with the fixed point Q(T) = 0 (the exponential update it replaced is off by 0.45, 9.3 and
    9.9 K at 1, 10 and 100 times the limit), and `dem check` reports the choice."""
    dt = factor * net_limit * (1 + 1e-9)
    sim = line(dt, "auto")
    assert sim.thermal.cfg["integrator"] == chosen
    rep = sim.check()
    assert rep["integrator"] == chosen and rep["auto_steady"] == 0.0
    assert "exact" in rep["expected_steady_error"]
    Tss, lam, _, _ = modes(sim)
    nsteps = _steps_to_converge(chosen, lam, dt)
    sim.run(end_time=nsteps * dt, progress=False)
    assert sim.step_count == nsteps
    assert np.abs(sim.state.temperature - Tss).max() < 1e-8
    assert Tss.max() < 400.0 and Tss.min() > 300.0 and np.all(np.diff(Tss) < -1.0)


@pytest.mark.parametrize("frac", [0.1, 0.3, 1.0])
def test_default_line_transient_at_and_below_the_limit(net_limit, frac):
    """At and below the Euler limit the default (auto: TR-BDF2 there) equals its exact discrete
    solution T_ss + sum_k c_k R(z_k)^n u_k (z_k = lam_k dt) to 1e-8 K at every step (two
    solves a step to the relative CG tolerance 1e-10, over up to 1,500 steps), so its
    error against the exact solution is bounded by sum_k |c_k| max|u_k| max_n |R(z_k)^n -
    e^{-n z_k}| (step_error.mode_error, per mode); and its largest error over the run is not
    above that of the exponential update that was the default before (measured: 2.3, 2.2 and
    1.9 x below at 0.1, 0.3 and 1 limit)."""
    from dem.thermal.step_error import amplification, mode_error
    dt = frac * net_limit
    errs = {}
    for integ in ("auto", "exponential"):
        sim = line(dt, integ)
        Tss, lam, U, c = modes(sim)
        nsteps = int(math.ceil(6.0 / lam[0] / dt))
        worst = 0.0
        for k in range(1, nsteps + 1):
            sim.step(1)
            exact = Tss + U @ (c * np.exp(-lam * k * dt))
            worst = max(worst, np.abs(sim.state.temperature - exact).max())
            if integ == "auto":
                disc = Tss + U @ (c * amplification("trbdf2", lam * dt) ** k)
                assert np.abs(sim.state.temperature - disc).max() < 1e-8   # CG tolerance, 2 solves a step
        errs[integ] = worst
        if integ == "auto":
            assert sim.thermal.cfg["integrator"] == "trbdf2"
            bound = sum(abs(c[q]) * np.abs(U[:, q]).max() * mode_error("trbdf2", lam[q] * dt) for q in range(len(lam)))
            assert worst <= 1.01 * bound
    assert errs["auto"] <= errs["exponential"]


def test_default_restart_continues_exactly(tmp_path):
    """TR-BDF2 (auto at 1 network limit) keeps no history between steps: a frozen run stopped at a
    checkpoint and continued ends with the same temperatures, bit for bit, as one run."""
    def scene():
        sc = line_scene(18.0, "auto", 720.0)
        sc["simulation"].update(output_interval=180.0, checkpoint_interval=360.0)
        return sc
    one = Simulation.from_dict(scene())
    one.run(out_dir=str(tmp_path / "one"), progress=False)
    assert one.thermal.cfg["integrator"] == "trbdf2"
    first = Simulation.from_dict(scene())
    first.run(end_time=360.0, out_dir=str(tmp_path / "two"), progress=False)
    second = Simulation.from_dict(scene())
    second.run(out_dir=str(tmp_path / "two"), restart=str(tmp_path / "two" / "checkpoint.npz"), progress=False)
    a, b = read_final(tmp_path / "one" / "final.npz"), read_final(tmp_path / "two" / "final.npz")
    assert second.step_count == one.step_count == 40
    assert np.array_equal(a["temperature"], b["temperature"])
    assert a["temperature"].max() > 300.5   # the hot wall's heat came in


ENV = dict(os.environ, PYTHONPATH=ROOT + os.pathsep + os.environ.get("PYTHONPATH", ""))


def _dem(*args, cwd):
    return subprocess.run([sys.executable, "-m", "dem", *args], capture_output=True, text=True, cwd=cwd,
                          env=ENV, timeout=600)


def _write_scene(path, integrator, dt=500.0, end=20000.0):
    from test_scene_errors import to_toml
    sc = line_scene(dt, integrator, end)
    sc["simulation"]["output_interval"] = end / 4
    path.write_text(to_toml(sc))


def test_cli_run_implicit_reaches_linear_profile(tmp_path):
    """`dem run` of the frozen line with integrator = "implicit" and dt = 500 s (27 Euler
    limits): the equal pair conductances give a linear interior profile, and the two equal
    wall links a profile symmetric about 350 K, both to 1e-9 K; the heat balance closes."""
    scene = tmp_path / "line.toml"
    _write_scene(scene, "implicit")
    p = _dem("run", str(scene), "--out", str(tmp_path / "out"), "--quiet", cwd=tmp_path)
    assert p.returncode == 0, p.stderr
    f = read_final(tmp_path / "out" / "final.npz")
    T = f["temperature"][np.argsort(f["position"][:, 0])]
    steps = np.diff(T)
    assert np.abs(steps - steps.mean()).max() < 1e-9
    assert abs(T[0] + T[-1] - 700.0) < 1e-9
    assert 300.0 < T[-1] < T[0] < 400.0
    import csv
    with open(tmp_path / "out" / "history.csv") as fh:
        rows = list(csv.DictReader(fh))
    h0, h1 = rows[0], rows[-1]
    gain = float(h1["thermal_energy"]) - float(h0["thermal_energy"])
    walls = float(h1["E_wall_left"]) + float(h1["E_wall_right"])
    assert gain == pytest.approx(walls, rel=1e-9, abs=1e-9 * float(h1["E_wall_left"]))


def test_cli_default_frozen_line_exact_steady_state(tmp_path):
    """`dem check` names the integrator auto picks and its expected errors, and `dem run` of the
    frozen line with the default integrator at dt = 18 s (about the Euler limit, 18.2 s: TR-BDF2)
    ends on the exact steady profile to 1e-8 K (linear inside, symmetric about 350 K) with the heat
    balance closed."""
    from test_scene_errors import to_toml
    sc = line_scene(18.0, "auto", 20000.0)
    del sc["thermal"]["integrator"]   # the default
    sc["simulation"]["output_interval"] = 5000.0
    scene = tmp_path / "line.toml"
    scene.write_text(to_toml(sc))
    p = _dem("check", str(scene), cwd=tmp_path)
    assert p.returncode == 0, p.stderr
    line_ = [x for x in p.stdout.splitlines() if x.startswith("thermal integrator:")]
    assert len(line_) == 1
    assert "trbdf2 (auto:" in line_[0] and "network limit" in line_[0]
    assert "steady state exact" in line_[0] and "transient at most" in line_[0]
    p = _dem("run", str(scene), "--out", str(tmp_path / "out"), "--quiet", cwd=tmp_path)
    assert p.returncode == 0, p.stderr
    assert "note:" not in p.stderr   # exact at steady state: nothing to warn about
    f = read_final(tmp_path / "out" / "final.npz")
    T = f["temperature"][np.argsort(f["position"][:, 0])]
    steps = np.diff(T)
    assert np.abs(steps - steps.mean()).max() < 1e-8
    assert abs(T[0] + T[-1] - 700.0) < 1e-8
    assert 300.0 < T[-1] < T[0] < 400.0
    import csv
    with open(tmp_path / "out" / "history.csv") as fh:
        rows = list(csv.DictReader(fh))
    h1 = rows[-1]
    gain = float(h1["thermal_energy"]) - float(rows[0]["thermal_energy"])
    walls = float(h1["E_wall_left"]) + float(h1["E_wall_right"])
    assert gain == pytest.approx(walls, rel=1e-9, abs=1e-9 * float(h1["E_wall_left"]))


def test_cli_bad_integrator_name(tmp_path):
    scene = tmp_path / "line.toml"
    _write_scene(scene, "backward_euler")
    p = _dem("run", str(scene), "--out", str(tmp_path / "out"), "--quiet", cwd=tmp_path)
    assert p.returncode == 2
    assert "Traceback" not in p.stderr
    msg = p.stderr
    assert "line.toml" in msg and "thermal.integrator" in msg and "'backward_euler'" in msg
    for name in ("auto", "euler", "exponential", "implicit", "trbdf2"):
        assert name in msg
    assert not (tmp_path / "out").exists()


@pytest.mark.parametrize("integrator", ["implicit", "trbdf2"])
def test_two_threads_solve_the_same_steps(integrator):
    """The conjugate gradients, the diagonal and the pairs' heat totals run on blocks of rows
    (dem.thermal.implicit.jacobi_pcg_blocks, pair_heat_blocks) when a process has 2 threads: a
    frozen lattice of 2,560 touching spheres (two blocks of rows) between a floor at 400 K and a
    side wall with a fixed flux, with convection, radiation and a source, advanced 20 steps far
    above the explicit limits, has the temperatures of one thread to the solver's tolerance
    (CG_RTOL 1e-10 a solve), and conserves energy on 2 threads as on one."""
    from dem import step as K
    sc = bed_scene(100.0, 2000.0, integrator)
    ov = 2e-5
    pitch = 2 * R - ov
    pos = [[R + i * pitch, R + j * pitch, R - ov + k * pitch] for i in range(16) for j in range(16) for k in range(10)]
    sc["particles"] = [{"material": "p", "positions": pos[:1280], "radius": R, "temperature": 300.0},
                       {"material": "p", "positions": pos[1280:], "radius": R, "temperature": 320.0}]
    sc["domain"] = {"min": [-0.001, -0.001, -0.001], "max": [0.034, 0.034, 0.022]}
    runs = {}
    for threads in (1, 2):
        sim = Simulation.from_dict(sc)
        sim.set_threads(threads)
        assert K.blocks(sim.state.ip) == threads
        st = sim.state
        C = 1.0 / st.inv_heat_capacity
        t0 = st.temperature.copy()
        sim.run(progress=False)
        tot = sim.thermal.tot.copy()
        heat_in = tot[2] + tot[3] + tot[4] + tot[5] + tot[6]
        gain = np.sum(C * (st.temperature - t0))
        assert abs(gain - heat_in) <= 1e-9 * np.sum(np.abs(tot[2:7])), threads
        runs[threads] = (st.temperature - t0, tot)
    (d1, tot1), (d2, tot2) = runs[1], runs[2]
    assert np.abs(d1).max() > 10.0  # the bed heated through
    assert np.abs(d2 - d1).max() <= 1e-8 * np.abs(d1).max()
    assert tot1[0] > 0.0 and abs(tot2[0] - tot1[0]) <= 1e-8 * tot1[0]  # pair conduction
