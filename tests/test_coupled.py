"""Coupled CFD-DEM runs (coupling.run) against thermoDemFoam.

The session fixture builds the solver like tests/test_openfoam_solver.py (install
OpenFOAM if needed, build cached on the sources' sha256). Each test is small (< ~1 min).
"""
from __future__ import annotations

import math
import os
import re
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

from coupling import foam_case as fc  # noqa: E402
from coupling.case import CaseConfigError, load_case  # noqa: E402
from coupling.run import main as coupling_main, run_case  # noqa: E402
from dem.final import read as read_final

CASES = ROOT / "openfoam_cases"
RHO, NU, CP, K = 1.2, 1.5e-5, 1005.0, 0.0262
MU = RHO * NU


def copy_case(name: str, dest: Path) -> Path:
    shutil.copytree(CASES / name, dest, ignore=shutil.ignore_patterns("README.md"))
    return dest


def read_csv(path: Path):
    return np.atleast_1d(np.genfromtxt(path, delimiter=",", names=True))


def set_toml(path: Path, **entries):
    """Replace/add keys of the [coupling] table of coupling.toml (scalars)."""
    text = path.read_text()
    for k, v in entries.items():
        val = f'"{v}"' if isinstance(v, str) else ("true" if v is True else "false" if v is False else repr(v))
        pat = re.compile(rf"^{k}\s*=.*$", re.M)
        text = pat.sub(f"{k} = {val}", text) if pat.search(text) else text.replace(
            "[coupling]\n", f"[coupling]\n{k} = {val}\n")
    path.write_text(text)


def set_inlet_velocity(case: Path, u: float):
    f = case / "0" / "U"
    f.write_text(re.sub(r"uniform \(0 0 [0-9.eE+-]+\)", f"uniform (0 0 {u})", f.read_text()))


# --------------------------------------------------------------------------- single particle

def lumped_analytic(t, T0=373.15, Tg=298.15, u=6.0, d=3.6e-3, rho_p=8850.0, cp_p=55.0):
    re_ = RHO * u * d / MU
    pr = MU * CP / K
    nu = 2.0 + 0.6 * math.sqrt(re_) * pr ** (1.0 / 3.0)          # Ranz-Marshall
    hA = math.pi * d * K * nu                                    # h * pi d^2, h = Nu k / d
    C = rho_p * math.pi / 6.0 * d ** 3 * cp_p
    return Tg + (T0 - Tg) * np.exp(-hA / C * np.asarray(t)), C / hA


def test_single_particle_heating(tmp_path, solver):
    """Zhou, Yu & Zulli (2009) single sphere: lumped solution with Ranz-Marshall, 1 %."""
    s = run_case(CASES / "single_particle_heating", tmp_path / "out", end_time=2.0, solver=solver,
                 quiet=True)
    d = read_csv(Path(s["out"]) / "coupling.csv")
    T_ref, tau = lumped_analytic(d["time"])
    assert d["time"][-1] == pytest.approx(2.0)
    assert d["time"][-1] > tau
    err = np.abs(d["T_particles"] - T_ref) / (373.15 - 298.15)
    assert err.max() < 0.01, err.max()
    assert d["T_particles"][-1] < 340.0        # really cooled (more than one time constant)


# --------------------------------------------------------------------------- Ergun

def ergun_gradient(u, eps, d=2e-3):
    return (150 * MU * (1 - eps) ** 2 * u / (eps ** 3 * d ** 2)
            + 1.75 * RHO * (1 - eps) * u ** 2 / (eps ** 3 * d))


@pytest.mark.parametrize("u", [0.1, 0.4, 0.8])
def test_ergun_pressure_drop(tmp_path, solver, u):
    """Fixed lattice bed (eps = 1 - pi/6), Gidaspow (Ergun) drag: pressure drop vs Ergun."""
    case = copy_case("ergun", tmp_path / "case")
    set_inlet_velocity(case, u)
    s = run_case(case, tmp_path / "out", end_time=0.01, solver=solver, quiet=True)
    out = Path(s["out"])
    d = read_csv(out / "coupling.csv")
    eps = 1 - math.pi / 6
    g = ergun_gradient(u, eps)
    # total: bottom cell centre (z = 3 mm) .. bed top (60 mm) + hydrostatics to the top cell.
    # Measured -0.1 % (0.1 m/s) to -0.8 % (0.8 m/s), where the momentum of the bed's
    # interstitial jets, rho u^2 (1/eps - 1), is 0.3 % of the drop (before the face treatment
    # of the drag, dragFaces.H: -2.6 to -4.6 %)
    expected = g * (0.06 - 0.003) + RHO * 9.81 * (0.117 - 0.003)
    assert d["dp"][-1] == pytest.approx(expected, rel=0.015)
    # inside the bed the gradient (written p is kinematic) is Ergun's
    n = 320
    p = fc.read_internal_field(out / "0.01" / "p", n).reshape(20, 16).mean(axis=1) * RHO
    grad = (p[1] - p[8]) / 0.042 - RHO * 9.81
    assert grad == pytest.approx(g, rel=0.005)
    # the gas of the top bed cell moves at u/eps (measured 0.96-0.99; before: 0.71-0.73)
    U = fc.read_internal_field(out / "0.01" / "U", n)[:, 2].reshape(20, 16).mean(axis=1)
    assert U[9] * eps / u == pytest.approx(1.0, abs=0.05)


# --------------------------------------------------------------------------- transports

@pytest.fixture(scope="module")
def serial_bed(tmp_path_factory, solver):
    """The heated fluidized bed (openfoam_cases/fluidized_bed_heating, its own transport: socket)
    run in serial to t = 0.002 s (4 coupling steps, 200 DEM steps): the output folder. The
    reference of the file/socket, transport-plug-in and two-DEM-rank tests, which each ran this
    same command before; they only read its final.npz and coupling.csv."""
    s = run_case(CASES / "fluidized_bed_heating", tmp_path_factory.mktemp("serial_bed") / "socket",
                 end_time=0.002, solver=solver, quiet=True)
    return Path(s["out"])


def test_file_and_socket_bit_identical(tmp_path, solver, serial_bed):
    """Fluidized bed, 4 coupling steps (200 DEM steps, heat on): same particle temperatures.
    The socket run is the module's serial_bed (the case's transport is socket)."""
    s = run_case(CASES / "fluidized_bed_heating", tmp_path / "file", transport="file", end_time=0.002,
                 solver=solver, quiet=True)
    a, b = read_final(Path(s["out"]) / "final.npz"), read_final(serial_bed / "final.npz")
    assert np.array_equal(a["id"], b["id"])
    assert np.array_equal(a["temperature"].view(np.uint64), b["temperature"].view(np.uint64))
    assert np.array_equal(a["position"].view(np.uint64), b["position"].view(np.uint64))
    assert a["temperature"].max() > 300.0      # heat was exchanged


class MeasuredLink:
    """The worked example of a transport (docs/architecture.md, "A transport plugs in"): a link
    that wraps today's rank-0 link and measures the bytes of every frame each way. It implements
    the whole link interface of coupling/transport.py, passing each call on."""

    def __init__(self, link):
        self.link, self.sent, self.received, self.cells = link, [], [], []

    @staticmethod
    def _bytes(fields):
        return sum(v.nbytes for v in fields.values() if isinstance(v, np.ndarray))

    def own_stop(self):
        return self.link.own_stop()

    def first(self, i0, t_start, cstate):
        return self.link.first(i0, t_start, cstate)

    def send(self, step, frame, time_value, final):
        self.sent.append(self._bytes(frame))
        self.cells.append(frame["eps"].shape[0])
        return self.link.send(step, frame, time_value, final)

    def receive(self, step, t, eps_change, stop_sig):
        fluid, final, peer = self.link.receive(step, t, eps_change, stop_sig)
        self.received.append(self._bytes(fluid))
        return fluid, final, peer

    def finish(self, step):
        return self.link.finish(step)

    def fail(self, e):
        return self.link.fail(e)

    def explain(self, e, sim):
        return self.link.explain(e, sim)

    def close(self, status, write_timings):
        return self.link.close(status, write_timings)


def test_a_transport_plugs_in(tmp_path, solver, monkeypatch, serial_bed):
    """A transport replaces coupling.transport.open_link and nothing else: the measured link runs
    the fluidized bed to the same bits as the plain one, and what it measured is the frame of the
    protocol, 5 fields of 9 doubles per cell each way (eps, Ksl, Us, Simp, Sexp out; U, T, p,
    grad p, eps in: docs/coupling_protocol.md) for each of the 4 coupling steps. The plain run
    is the module's serial_bed (the same command)."""
    import coupling.run as crun
    from coupling import transport
    links = []

    def open_measured(*a, **kw):
        links.append(MeasuredLink(transport.open_link(*a, **kw)))
        return links[-1]

    monkeypatch.setattr(crun, "open_link", open_measured)
    s = run_case(CASES / "fluidized_bed_heating", tmp_path / "measured", end_time=0.002, solver=solver, quiet=True)
    a, b = read_final(serial_bed / "final.npz"), read_final(Path(s["out"]) / "final.npz")
    for k in ("position", "velocity", "temperature"):
        assert np.array_equal(a[k].view(np.uint64), b[k].view(np.uint64)), k
    (link,) = links
    n = fc.read_internal_field(Path(s["out"]) / "0.002" / "eps").shape[0]   # the gas mesh's cells
    assert len(link.sent) == 4 and len(set(link.sent)) == 1 and set(link.cells) == {n}
    assert link.sent[0] == n * 8 * (1 + 1 + 3 + 1 + 1)      # eps, Ksl, Us (3), Simp, Sexp
    assert len(link.received) == 4 and min(link.received) >= n * 8 * (3 + 1 + 1)   # U (3), T, p at least


# --------------------------------------------------------------------------- energy

CLOSED_BOX_DEM = """
[simulation]
time_step = 1e-4
mechanics = false
output_interval = 0.01

[domain]
min = [0.0, 0.0, 0.0]
max = [0.024, 0.024, 0.12]

[[materials]]
name = "glass"
density = 2500.0
youngs_modulus = 1e7
poisson_ratio = 0.25
restitution = 0.5
friction = 0.3
heat_capacity = 840.0
thermal_conductivity = 1.0

[[particles]]
material = "glass"
file = "bed.csv"
temperature = 400.0

[thermal]
direct = "none"
convection = "ranz_marshall"
porosity = "global"
time_step = 1e-4

[gas]
conductivity = 0.0262
density = 1.2
viscosity = 1.8e-5
heat_capacity = 1005.0
temperature = 300.0

[output]
vtk = false
"""


def make_closed_box(dest: Path) -> Path:
    case = copy_case("ergun", dest)
    (case / "dem.toml").write_text(CLOSED_BOX_DEM)
    (case / "coupling.toml").write_text(
        '[coupling]\ntransport = "socket"\ncoupling_interval = 1\ndrag = "gidaspow_1994"\n'
        'void_fraction = "centre"\nheat = true\noutput_interval = 0.005\n')
    fc.set_entries(case / "system" / "controlDict", {"endTime": "0.05"})   # the case's one end time
    # walls everywhere: gas at rest, no inlet/outlet
    u = (case / "0" / "U").read_text()
    u = re.sub(r"internalField\s+uniform \([^)]*\);", "internalField   uniform (0 0 0);", u)
    u = re.sub(r"(inlet|outlet)\s*\{[^}]*\}", r"\1 { type noSlip; }", u)
    (case / "0" / "U").write_text(u)
    p = (case / "0" / "p").read_text()
    p = re.sub(r"outlet\s*\{[^}]*\}", "outlet { type fixedFluxPressure; value uniform 0; }", p)
    (case / "0" / "p").write_text(p)
    t = (case / "0" / "T").read_text()
    t = re.sub(r"(inlet|outlet)\s*\{[^}]*\}", r"\1 { type zeroGradient; }", t)
    (case / "0" / "T").write_text(t)
    # gravity stays on (constant/g = -9.81 z, p carries the hydrostatic part; all p
    # patches fixedFluxPressure, so p needs a reference and adjustPhi runs); particles
    # are held (mechanics = false)
    assert "-9.81" in (case / "constant" / "g").read_text()
    return case


def test_closed_box_energy_balance(tmp_path, solver):
    """Hot fixed bed in a closed, adiabatic box with gravity: gas + particle energy is conserved.

    The explicit (staggered) exchange lags the gas temperature seen by the particles by
    one coupling step; the mismatch telescopes, so it stays O(dt / tau_gas) of the
    exchanged energy (tau_gas = gas capacity / hA, 14 ms here, dt = 0.1 ms): 1.5 % bound.
    """
    case = make_closed_box(tmp_path / "case")
    s = run_case(case, tmp_path / "out", solver=solver, quiet=True)
    out = Path(s["out"])
    mesh_V = fc.read_cell_volumes(out)
    n = len(mesh_V)
    eps = fc.read_internal_field(out / "0" / "eps", n)
    T0 = fc.read_internal_field(out / "0" / "T", n)
    T1 = fc.read_internal_field(out / "0.05" / "T", n)
    dEg = float((RHO * CP * eps * mesh_V * (T1 - T0)).sum())
    sim_final = read_final(out / "final.npz")
    d = 2e-3
    C = 2500.0 * math.pi / 6 * d ** 3 * 840.0
    dEp = float(C * (sim_final["temperature"] - 400.0).sum())
    assert dEg > 1.0                                   # joules exchanged
    assert dEg + dEp == pytest.approx(0.0, abs=0.015 * dEg)
    # with gravity the gas stays at rest and p (kinematic) is hydrostatic: the g-flux
    # on the wall faces is balanced by the fixedFluxPressure gradient (no spurious flow)
    U1 = fc.read_internal_field(out / "0.05" / "U", n)
    assert np.abs(U1).max() < 1e-6
    p_lay = fc.read_internal_field(out / "0.05" / "p", n).reshape(20, 16).mean(axis=1)
    assert np.diff(p_lay) == pytest.approx(np.full(19, -9.81 * 0.006), rel=1e-6)
    # the DEM's own convection total matches the particle energy change
    h = read_csv(out / "coupling.csv")
    assert h["E_conv_particles"][-1] == pytest.approx(dEp, rel=1e-9)


# --------------------------------------------------------------------------- Schumann

def schumann_bessel(Y, Z):
    """Schumann (1929) gas/solid temperatures theta = (T - T0)/(Tin - T0) at dimensionless
    distance Y = h a x/(rho c u_s) and time Z = h a (t - x/u_i)/((1 - eps) rho_s c_s):
    theta_s = exp(-Y) int_0^Z exp(-s) I0(2 sqrt(Y s)) ds, theta_g = theta_s + exp(-Y-Z) I0(2 sqrt(YZ))."""
    from scipy import integrate, special

    def k(s, y):   # exp(-y - s) I0(2 sqrt(y s)), overflow-free
        return special.i0e(2 * np.sqrt(y * s)) * np.exp(-(np.sqrt(y) - np.sqrt(s)) ** 2)

    Y, Z = np.broadcast_arrays(np.asarray(Y, float), np.asarray(Z, float))
    tg, ts = np.zeros(Y.shape), np.zeros(Y.shape)
    for i in np.ndindex(Y.shape):
        if Z[i] > 0:
            ts[i] = integrate.quad(k, 0.0, Z[i], args=(Y[i],), epsabs=1e-12, epsrel=1e-10, limit=200)[0]
            tg[i] = ts[i] + k(Z[i], Y[i])
    return tg, ts


def schumann_numerical(y_max, z_max, h=0.01):
    """The two Schumann equations dtg/dY = ts - tg, dts/dZ = tg - ts (tg(0, Z) = 1,
    ts(Y, 0) = 0) by the method of lines: trapezoidal rule in Y, solve_ivp in Z."""
    from scipy.integrate import solve_ivp
    Y = np.arange(0.0, y_max + h / 2, h)
    a, b = (1 - h / 2) / (1 + h / 2), (h / 2) / (1 + h / 2)

    def gas(ts):
        tg = np.empty_like(ts)
        tg[0] = 1.0
        for j in range(len(ts) - 1):
            tg[j + 1] = a * tg[j] + b * (ts[j] + ts[j + 1])
        return tg

    sol = solve_ivp(lambda z, ts: gas(ts) - ts, (0.0, z_max), np.zeros(len(Y)), rtol=1e-9, atol=1e-11)
    ts = sol.y[:, -1]
    return Y, gas(ts), ts


def test_schumann_reference_solutions_agree():
    """The Bessel form used below against an independent numerical solution."""
    Y, tg_n, ts_n = schumann_numerical(4.5, 3.0)
    tg_b, ts_b = schumann_bessel(Y[::10], 3.0)
    assert np.abs(tg_b - tg_n[::10]).max() < 1e-4
    assert np.abs(ts_b - ts_n[::10]).max() < 1e-4
    assert tg_b[0] == pytest.approx(1.0) and ts_b[0] == pytest.approx(1 - math.exp(-3.0))


def test_packed_bed_heating_schumann(tmp_path, solver):
    """openfoam_cases/packed_bed_heating (hot gas through a held lattice bed) vs Schumann.

    The case meets Schumann's assumptions: plug flow (one lateral cell, slip walls,
    uniform lattice), no conduction in the bed (thermal.direct = none), lumped particles
    (the DEM; Biot h (V/A) / k_p = 0.035), negligible axial gas conduction (Peclet u_i L / alpha = 2,900).
    Measured (dt = 1 ms, 4 mm cells = 0.28 in Y): max |error| 0.27 % of Tin - T0 in the
    interior layers (O(dt / tau_gas) lag of the staggered exchange, tau_gas = 14 ms: halving
    dt lowers it; second-order upwind in Y), 0.76 % in the last bed layer (second-order
    upwind gradient at the bed exit, where the source stops). Bounds: twice these.
    """
    s = run_case(CASES / "packed_bed_heating", tmp_path / "out", end_time=1.0, solver=solver, quiet=True)
    out = Path(s["out"])
    C = fc.read_cell_centres(out)
    n = len(C)
    order = np.argsort(C[:, 2])
    x = C[order, 2]
    bed = x < 0.06
    x = x[bed]
    assert bed.sum() == 15
    eps = fc.read_internal_field(out / "0" / "eps", n)[order][bed]
    assert eps == pytest.approx(np.full(15, 1 - math.pi / 6), rel=1e-9)
    eps = float(eps[0])
    d, u_s, T0, Tin = 4e-3, 0.5, 300.0, 373.15
    rho_s_cs = 2500.0 * 8.4
    re_ = RHO * u_s * d / MU
    ha = (2 + 0.6 * math.sqrt(re_) * (MU * CP / K) ** (1 / 3)) * K / d * 6 * (1 - eps) / d  # Ranz-Marshall
    dt = 1e-3
    worst = {"gas": [0.0, 0.0], "solid": [0.0, 0.0]}     # [interior layers, last layer]
    times = [0.2, 0.4, 0.6, 0.8, 1.0]
    for t in times:
        tdir = out / f"{t:g}"
        T = fc.read_internal_field(tdir / "T", n)[order][bed]
        simp = fc.read_internal_field(tdir / "Simp", n)[order][bed]
        sexp = fc.read_internal_field(tdir / "Sexp", n)[order][bed]
        assert simp == pytest.approx(np.full(15, ha), rel=1e-6)    # h a used by the coupling
        Y = ha * x / (RHO * CP * u_s)
        z_of = lambda tt: ha * (tt - x * eps / u_s) / ((1 - eps) * rho_s_cs)  # noqa: E731
        tg_ref, _ = schumann_bessel(Y, z_of(t))
        _, ts_ref = schumann_bessel(Y, z_of(t - dt))   # Sexp/Simp: particles at the start of the step
        for key, num, ref in (("gas", T, tg_ref), ("solid", sexp / simp, ts_ref)):
            e = np.abs((num - T0) / (Tin - T0) - ref)
            worst[key] = [max(worst[key][0], e[:-1].max()), max(worst[key][1], e[-1])]
    for key in worst:
        assert worst[key][0] < 0.006, (key, worst)
        assert worst[key][1] < 0.015, (key, worst)
    # the front has really moved through the bed: the last layer's solid is > 30 % heated
    fin = read_final(out / "final.npz")
    top = fin["position"][:, 2] > 0.056
    assert ((fin["temperature"][top] - T0) / (Tin - T0)).mean() > 0.3


# --------------------------------------------------------------------------- solver killed

def test_solver_killed_checkpoint_restart(tmp_path, solver):
    case = copy_case("single_particle_heating", tmp_path / "case")
    set_toml(case / "coupling.toml", transport="file", timeout=20.0, output_interval=0.01)
    out = tmp_path / "out"
    env = dict(os.environ)
    env["PYTHONPATH"] = str(ROOT) + os.pathsep + env.get("PYTHONPATH", "")
    proc = subprocess.Popen([sys.executable, "-m", "coupling.run", "run", str(case), "--out", str(out),
                             "--end-time", "3.0"], stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                            text=True, env=env)
    pidfile = out / "coupling" / "cfd.pid"
    csv = out / "coupling.csv"
    t0 = time.monotonic()
    try:
        # wait until the run is past the first OpenFOAM write (t = 1 s)
        while time.monotonic() - t0 < 120:
            if csv.exists() and pidfile.exists():
                d = read_csv(csv)
                if d.size > 2 and d["time"][-1] > 1.2:
                    break
            if proc.poll() is not None:
                break
            time.sleep(0.2)
        assert proc.poll() is None, proc.communicate()[1][-2000:]
        os.kill(int(pidfile.read_text().split()[0]), signal.SIGKILL)
        _, err = proc.communicate(timeout=60)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    assert proc.returncode == 3, err
    assert "peer: CFD solver, coupling step" in err, err
    assert "checkpoint" in err
    # the checkpoint is usable: a new Simulation continues from it
    import dem
    sim = dem.Simulation.from_file(str(out / "dem.toml"), end_time=3.0)   # the scene takes controlDict's
    sim.load_checkpoint(str(out / "checkpoint.npz"))
    assert sim.time > 1.2
    T = sim.state.temperature.copy()
    sim.step(5)
    assert sim.step_count > 0 and np.all(np.isfinite(sim.state.temperature))
    assert np.all(T < 373.15)
    # coupled restart from the last OpenFOAM write that has a DEM checkpoint (t = 1 s)
    s = run_case(case, out, restart=True, end_time=1.5, solver=solver, quiet=True)
    assert s["time"] == pytest.approx(1.5)
    d = read_csv(out / "coupling.csv")
    T_ref, _ = lumped_analytic(d["time"])
    assert np.abs(d["T_particles"] - T_ref).max() < 0.01 * 75


# --------------------------------------------------------------------------- bad cases

def _check(case: Path, capsys) -> tuple[int, str]:
    from unittest import mock
    with mock.patch.dict(os.environ):   # main drops the OMPI_* settings (conftest's) of a serial process
        rc = coupling_main(["check", str(case)])
    return rc, capsys.readouterr().err


def test_bad_cases_refused(tmp_path, capsys):
    # missing field
    c = copy_case("single_particle_heating", tmp_path / "a")
    (c / "0" / "T").unlink()
    rc, err = _check(c, capsys)
    assert rc == 2 and "0/T: missing field 'T'" in err
    # mesh without the needed patch (outlet renamed in blockMeshDict)
    c = copy_case("single_particle_heating", tmp_path / "b")
    bm = c / "system" / "blockMeshDict"
    bm.write_text(bm.read_text().replace("outlet", "top"))
    rc, err = _check(c, capsys)
    assert rc == 2 and "0/U" in err and "['top']" in err
    # non-physical gas property
    c = copy_case("single_particle_heating", tmp_path / "c")
    tp = c / "constant" / "transportProperties"
    tp.write_text(tp.read_text().replace("rho             1.2", "rho             -1.2"))
    rc, err = _check(c, capsys)
    assert rc == 2 and "transportProperties: non-physical gas property rho" in err
    # DEM gas properties inconsistent with the OpenFOAM ones
    c = copy_case("single_particle_heating", tmp_path / "d")
    tp = c / "dem.toml"
    tp.write_text(tp.read_text().replace("conductivity = 0.0262", "conductivity = 0.03"))
    rc, err = _check(c, capsys)
    assert rc == 2 and "dem.toml: gas.conductivity" in err and "transportProperties" in err
    # coupling.toml: unknown key, bad value, interval inconsistent with deltaT
    c = copy_case("single_particle_heating", tmp_path / "e")
    set_toml(c / "coupling.toml", drag="stokes")
    rc, err = _check(c, capsys)
    assert rc == 2 and "coupling.toml: coupling.drag: 'stokes' is not one of" in err
    set_toml(c / "coupling.toml", drag="di_felice_1994", coupling_interval=2)
    rc, err = _check(c, capsys)
    assert rc == 2 and "coupling.coupling_interval" in err and "deltaT" in err
    (c / "coupling.toml").write_text("[coupling]\ntransprt = 'file'\n")
    with pytest.raises(CaseConfigError, match=r"coupling.toml: coupling.transprt: unknown key"):
        load_case(c)
    # particle outside the mesh
    c = copy_case("single_particle_heating", tmp_path / "f")
    tp = c / "dem.toml"
    tp.write_text(tp.read_text().replace("[[0.015, 0.015, 0.025]]", "[[0.015, 0.015, 0.0595]]")
                  .replace("max = [0.03, 0.03, 0.06]", "max = [0.03, 0.03, 0.07]")
                  .replace("0.0595", "0.065"))
    rc, err = _check(c, capsys)
    assert rc == 2 and "dem.toml" in err and "outside the OpenFOAM mesh" in err


def test_two_dem_ranks_match_serial(tmp_path, solver, serial_bed):
    """mpirun -np 2 coupling run: the DEM split over two ranks (each adds its particles' void
    fraction, drag and heat terms; rank 0 talks to thermoDemFoam) gives the serial result
    to round-off after 4 coupling steps (200 DEM steps) of the heated fluidized bed. The serial
    run is the module's serial_bed (the same command)."""
    if shutil.which("mpirun") is None:
        pytest.skip("needs Open MPI")
    a = read_final(serial_bed / "final.npz")
    env = dict(os.environ, OMPI_ALLOW_RUN_AS_ROOT="1", OMPI_ALLOW_RUN_AS_ROOT_CONFIRM="1",
               OMPI_MCA_rmaps_base_oversubscribe="1")
    p = subprocess.run(["mpirun", "-np", "2", sys.executable, "-m", "coupling.run", "run",
                        str(CASES / "fluidized_bed_heating"), "--out", str(tmp_path / "two"),
                        "--end-time", "0.002"], capture_output=True, text=True, env=env, timeout=900)
    assert p.returncode == 0, p.stdout + p.stderr
    assert "2 MPI ranks" in p.stdout
    b = read_final(tmp_path / "two" / "final.npz")
    assert np.array_equal(a["id"], b["id"])
    assert np.abs(a["position"] - b["position"]).max() < 1e-13
    assert np.abs(a["velocity"] - b["velocity"]).max() < 1e-10
    assert np.abs(a["temperature"] - b["temperature"]).max() < 1e-10
    assert a["temperature"].max() > 300.0
    ca, cb = read_csv(serial_bed / "coupling.csv"), read_csv(tmp_path / "two" / "coupling.csv")
    assert cb[-1]["Q_to_gas"] == pytest.approx(ca[-1]["Q_to_gas"], rel=1e-9)
    assert cb[-1]["E_particles"] == pytest.approx(ca[-1]["E_particles"], rel=1e-12)


def test_compile_command_fills_the_cache_and_touches_nothing(tmp_path, solver):
    """`coupling compile CASE` (what scripts/setup.sh runs): meshes a temporary copy, runs one
    exchange and one DEM step, exits 0; the case folder is unchanged and no temporary copy is
    left behind."""
    case = copy_case("single_particle_heating", tmp_path / "case")
    before = {p.relative_to(case): p.read_bytes() for p in case.rglob("*") if p.is_file()}
    tmp = tmp_path / "tmp"
    tmp.mkdir()
    env = dict(os.environ, TMPDIR=str(tmp), PYTHONPATH=str(ROOT) + os.pathsep + os.environ.get("PYTHONPATH", ""))
    p = subprocess.run([sys.executable, "-m", "coupling.run", "compile", str(case)], capture_output=True,
                       text=True, env=env, timeout=900)
    assert p.returncode == 0, p.stdout[-2000:] + p.stderr[-3000:]
    assert "case: compiled" in p.stdout and "coupling kernels compiled and cached in" in p.stdout
    after = {q.relative_to(case): q.read_bytes() for q in case.rglob("*") if q.is_file()}
    assert after == before
    assert list(tmp.iterdir()) == []


BED_END, BED_WRITE = 0.02, 10    # the bed's run: 40 coupling steps, a gas time every 10 (5 ms), t = 0 included
PY_WARNING = re.compile(r"\w+Warning:|WARN|warning:", re.I)   # Python's, VTK's, a tool's warning line


@pytest.fixture(scope="module")
def bed_output(tmp_path_factory, solver):
    """The heated bubbling bed's coupled output (openfoam_cases/fluidized_bed_heating, a gas
    time and a particle frame every 5 ms to 20 ms) run twice into the same --out, the second time with
    --overwrite; (output folder, the runs' stderr). Shared by the ParaView/render, animation
    and coupling.png tests."""
    base = tmp_path_factory.mktemp("bed")
    case = copy_case("fluidized_bed_heating", base / "fluidized_bed_heating")
    fc.set_entries(case / "system" / "controlDict", {"writeInterval": str(BED_WRITE)})
    set_toml(case / "coupling.toml", output_interval=BED_WRITE * 5e-4)   # a particle frame at each gas time
    out = base / "out"
    errs = []
    for extra in ([], ["--overwrite"]):
        p = subprocess.run([sys.executable, "-m", "coupling.run", "run", str(case), "--out", str(out),
                            "--end-time", str(BED_END), "--quiet", *extra],
                           cwd=ROOT, capture_output=True, text=True, timeout=600)
        assert p.returncode == 0, p.stderr
        errs.append(p.stderr)
    return out, errs


def render_cmd(*args, timeout=300):
    """`coupling render ...` in a fresh process (as a user runs it): the CompletedProcess."""
    return subprocess.run([sys.executable, "-m", "coupling.run", "render", *map(str, args)], cwd=ROOT,
                          capture_output=True, text=True, timeout=timeout)


def test_output_opens_in_paraview_and_renders_both_phases(tmp_path, solver, bed_output):
    """A coupled output folder holds `<case>.foam` (the gas, for ParaView and pyvista's
    OpenFOAM reader) beside `particles.pvd`: the reader finds the gas's time folders and the
    void fraction, velocity, temperature and pressure on every cell, and the wall heat flux on
    the wall patches; the opener is the tool's (in the manifest: --overwrite replaces the run).
    Neither the runs (coupling.png included) nor the renders print a warning on stderr."""
    pv = pytest.importorskip("pyvista")
    out, run_errs = bed_output
    for err in run_errs:
        assert not PY_WARNING.search(err), err
    opener = out / "fluidized_bed_heating.foam"
    assert opener.is_file() and opener.stat().st_size == 0
    assert (out / "particles.pvd").is_file()
    r = pv.OpenFOAMReader(str(opener))
    assert r.time_values[0] == 0.0 and abs(r.time_values[-1] - BED_END) < 1e-12
    r.set_active_time_value(r.time_values[-1])
    m = r.read()
    cells = m["internalMesh"]
    for name in ("eps", "U", "T", "p"):
        assert name in cells.cell_data, name
    eps = np.asarray(cells.cell_data["eps"])
    assert eps.size == cells.n_cells and 0.3 < eps.min() < 0.95 and eps.max() <= 1.0  # a bed in a gas
    walls = m["boundary"]
    assert any("wallHeatFluxTotal" in walls[k].cell_data for k in walls.keys())
    # the picture of both phases: the void-fraction slice (yellow freeboard, eps = 1, above the
    # bed) with the particles near the plane on it, drawn without a display and without warnings
    p = render_cmd(out)
    assert p.returncode == 0, p.stderr
    if not os.environ.get("DISPLAY"):
        assert not PY_WARNING.search(p.stderr) and "Traceback" not in p.stderr, p.stderr
    from PIL import Image
    img = np.asarray(Image.open(out / "gas_render.png").convert("RGB")).astype(int)
    freeboard = ((img[..., 0] > 150) & (img[..., 1] > 140) & (img[..., 2] < 80)).mean()
    particles = (img.max(axis=2) < 40).mean()            # the coldest particles (inferno's dark end)
    assert freeboard > 0.03 and particles > 0.005, (freeboard, particles)
    assert len(np.unique(img.reshape(-1, 3), axis=0)) > 500    # shaded spheres on a coloured slice
    # the particles' picture of the same folder (the main job's second render), without warnings
    d = subprocess.run([sys.executable, "-m", "dem.cli", "render", str(out), "--png", str(tmp_path / "dem.png")],
                       cwd=ROOT, capture_output=True, text=True, timeout=300)
    assert d.returncode == 0 and (tmp_path / "dem.png").is_file(), d.stderr
    if not os.environ.get("DISPLAY"):
        assert not PY_WARNING.search(d.stderr) and "Traceback" not in d.stderr, d.stderr
    r = render_cmd(out, "--field", "speed")
    assert r.returncode == 2 and "--field speed: allowed are" in r.stderr and "Traceback" not in r.stderr
    for bad in ("nan", "-0.1", "soon"):   # a time that names no written time: refused, nothing written
        r = render_cmd(out, "--time", bad, "--png", str(tmp_path / "never.png"))
        assert r.returncode == 2 and "argument --time: must be a time in seconds" in r.stderr, r.stderr
        assert "Traceback" not in r.stderr and not (tmp_path / "never.png").exists()
    # decomposed gas (gas_processes = 2): the same opener, read as a decomposed case
    case = copy_case("fluidized_bed_heating", tmp_path / "dcase")
    set_toml(case / "coupling.toml", gas_processes=2)
    out2 = tmp_path / "out2"
    p = subprocess.run([sys.executable, "-m", "coupling.run", "run", str(case), "--out", str(out2), "--end-time",
                        "0.004", "--quiet"], cwd=ROOT, capture_output=True, text=True, timeout=600,
                       env=dict(os.environ, OMPI_ALLOW_RUN_AS_ROOT="1", OMPI_ALLOW_RUN_AS_ROOT_CONFIRM="1",
                                OMPI_MCA_rmaps_base_oversubscribe="1"))
    assert p.returncode == 0, p.stderr
    assert (out2 / "processor1").is_dir()
    r = pv.POpenFOAMReader(str(out2 / "dcase.foam"))
    r.case_type = "decomposed"
    r.set_active_time_value(r.time_values[-1])
    cells2 = r.read()["internalMesh"]
    assert cells2.n_cells == cells.n_cells and "eps" in cells2.cell_data
    p = subprocess.run([sys.executable, "-m", "coupling.run", "render", str(out2), "--field", "T"], cwd=ROOT,
                       capture_output=True, text=True, timeout=300)
    assert p.returncode == 0 and (out2 / "gas_render.png").is_file(), p.stderr
    # an animation of the decomposed gas: one frame per written time (0 and the end)
    p = render_cmd(out2, "--animate", "--field", "T")
    assert p.returncode == 0, p.stderr
    assert sorted(q.name for q in (out2 / "gas_animation_T").glob("frame_*.png")) == ["frame_0000.png",
                                                                                     "frame_0001.png"]


# --------------------------------------------------------------------------- animation, coupling.png

def _png(path):
    from PIL import Image
    with open(path, "rb") as fh:
        assert fh.read(8) == b"\x89PNG\r\n\x1a\n", path
    im = Image.open(path)
    return np.asarray(im.convert("RGB")).astype(int), im.info


def test_render_animates_the_bubbling_bed(tmp_path, bed_output):
    """`coupling render OUT --animate`: one frame per written gas time (t = 0 included) into a
    folder of the tool's own, PNGs of one size, with the colour ranges of all the frames (the
    colour bars of the first and the last frame are the same pixels), showing the bed move
    (the frames differ where the bed is), and a GIF of them; --times picks a range; bad input
    and a folder holding a user's file are refused (exit 2, one line, nothing touched)."""
    pytest.importorskip("pyvista")
    from PIL import Image
    from dem import outdir
    out, _ = bed_output
    written = [k * BED_WRITE * 5e-4 for k in range(5)]          # 0, 5, 10, 15, 20 ms
    assert sorted(float(d.name) for d in out.iterdir() if re.fullmatch(r"[0-9.e-]+", d.name)) == \
        pytest.approx(written, abs=1e-12)
    p = render_cmd(out, "--animate")
    assert p.returncode == 0, p.stderr
    if not os.environ.get("DISPLAY"):
        assert not PY_WARNING.search(p.stderr) and "Traceback" not in p.stderr, p.stderr
    folder = out / "gas_animation_eps"
    names = sorted(q.name for q in folder.iterdir())
    assert names == [".thermodem-manifest.json", "animation.gif"] + [f"frame_{k:04d}.png" for k in range(5)], names
    frames = [_png(folder / f"frame_{k:04d}.png") for k in range(5)]
    assert {f[0].shape for f in frames} == {(1000, 900, 3)}
    assert all(f[1].get("Software") == "thermodem coupling render --animate" for f in frames)
    # the colour bars (particle T left, void fraction right; below the time label) are the same
    # pixels in the first and the last frame: one colour range for all; and they are bars (many
    # colours), not blank margins
    first, last = frames[0][0], frames[-1][0]
    for bar in (np.s_[60:, :220], np.s_[60:, 700:]):
        assert np.array_equal(first[bar], last[bar])
        assert len(np.unique(first[bar].reshape(-1, 3), axis=0)) > 50
    # the bed moves: the collapse of the loose packing (the particles fall about g t^2 / 2 = 2 mm
    # in 20 ms, 9 pixels) and its heating change the picture where the bed is, from each frame to
    # the next (measured: 2.4, 7.1, 10.4 and 13.1 % of the domain's pixels change by more than 30
    # of 255 in a channel)
    dom = np.s_[60:900, 300:600]
    changed = [(np.abs(frames[k + 1][0][dom] - frames[k][0][dom]).max(axis=2) > 30).mean() for k in range(4)]
    assert min(changed) > 0.005, changed
    # the GIF: every frame, the same size, one palette for all
    gif = Image.open(folder / "animation.gif")
    assert gif.n_frames == 5 and gif.size == (900, 1000) and gif.info["duration"] == 250
    # the folder is the tool's: listed in the output's manifest (its --overwrite removes it)
    assert "gas_animation_eps" in outdir.read_manifest(str(out))
    assert outdir.check(str(out), overwrite=True) == "output"
    # --times: the written times in the range; another folder (--frames) outside OUT
    p = render_cmd(out, "--animate", "--times", "0.01:0.02", "--field", "U", "--frames", tmp_path / "anim")
    assert p.returncode == 0, p.stderr
    assert sorted(q.name for q in (tmp_path / "anim").glob("frame_*.png")) == [f"frame_{k:04d}.png" for k in range(3)]
    # a second animation into the same folder replaces what the first wrote (no stale frame)
    p = render_cmd(out, "--animate", "--times", "0.015:", "--field", "U", "--frames", tmp_path / "anim")
    assert p.returncode == 0, p.stderr
    assert sorted(q.name for q in (tmp_path / "anim").glob("frame_*.png")) == ["frame_0000.png", "frame_0001.png"]
    # refused, exit 2, one line naming the option and what is allowed, nothing written
    before = {q.name: q.read_bytes() for q in folder.iterdir()}
    (tmp_path / "mine").mkdir()
    (tmp_path / "mine" / "notes.txt").write_text("a user's file")
    for args, phrase in (
            (["--times", "0.3"], "--times: must be START:END in seconds"),
            (["--times", "0.02:0.01"], "--times: START must not be after END"),
            (["--times", "0.1:0.2"], "--times 0.1:0.2: no written gas time in that range; the gas wrote 5 time(s) "
                                     "from 0 to 0.02 s"),
            (["--time", "0.01"], "--time is for one picture"),
            (["--frames", out], "is (or holds) the output folder"),
            (["--frames", tmp_path / "mine"], "holds files this tool did not write (notes.txt)"),
            (["--frames", out / "gas_animation_eps" / "x", "--field", "speed"], "--field speed: allowed are")):
        r = render_cmd(out, "--animate", *args)
        assert r.returncode == 2, (args, r.stderr)
        assert phrase in r.stderr.strip().splitlines()[-1] and "Traceback" not in r.stderr, (args, r.stderr)
    r = render_cmd(out, "--times", "0:0.01")
    assert r.returncode == 2 and "--times is an option of --animate" in r.stderr, r.stderr
    bare = tmp_path / "bare"      # the case and its opener, no time folder (the reader still lists t = 0)
    for name in ("constant", "system"):
        shutil.copytree(out / name, bare / name)
    (bare / "fluidized_bed_heating.foam").touch()
    r = render_cmd(bare, "--animate")
    assert r.returncode == 2 and "--animate: the gas wrote no time folder yet" in r.stderr, r.stderr
    assert sorted(q.name for q in bare.iterdir()) == ["constant", "fluidized_bed_heating.foam", "system"]
    assert {q.name: q.read_bytes() for q in folder.iterdir()} == before
    assert (tmp_path / "mine" / "notes.txt").read_text() == "a user's file"
    assert sorted(q.name for q in (tmp_path / "mine").iterdir()) == ["notes.txt"]


def test_coupling_png_says_what_it_shows_and_plots_the_recorded_balance(bed_output, monkeypatch):
    """coupling.png (coupling.diagnostics.plot) of the finished bed: each panel's title says
    what its traces are; the pressure-drop panel carries the bed's weight over the bottom area,
    which is sum(m) g / A of the particles (final.npz) and the column (60 x 12 mm); the heat
    balance panel draws coupling.csv's balance_residual over the heat moved (the boundaries'
    and the exchange's heat, read from the same file)."""
    from coupling.diagnostics import figure, plot
    out, _ = bed_output
    png = plot(out, "bed")
    assert png == out / "coupling.png" and png.stat().st_size > 0
    axes = figure(out, "bed").axes
    titles = [a.get_title(loc="left") for a in axes]
    assert titles[0].startswith("Mean temperature of each phase (K)")
    assert titles[1].startswith("Heat from the particles to the gas (W)")
    assert titles[2].startswith("Pressure drop across the bed (Pa)") and "bed weight / area" in titles[2]
    assert titles[3].startswith("Bed height: mean height z of the particle centres")
    assert titles[4].startswith("Heat balance of both phases: |error| relative to the heat moved")
    d = read_csv(out / "coupling.csv")
    fin = read_final(out / "final.npz")
    weight = float((2500.0 * 4.0 / 3.0 * math.pi * fin["radius"] ** 3).sum()) * 9.81 / (0.06 * 0.012)
    assert weight == pytest.approx(428.0, rel=0.05)           # 3,000 beads of 2 mm on 7.2 cm^2
    assert d["weight_per_area"] == pytest.approx(np.full(d.size, weight), rel=1e-9)
    dp_lines = {ln.get_label(): ln for ln in axes[2].get_lines()}
    ref = dp_lines["bed weight / bottom area, sum(m) g / A"]
    assert np.array_equal(ref.get_ydata(), d["weight_per_area"])
    assert np.array_equal(dp_lines["p(bottom cell layer) - p(top cell layer)"].get_ydata(), d["dp"])
    moved = (np.abs(d["E_walls_particles"]) + np.abs(d["E_walls_gas"]) + np.abs(d["E_open"])
             + np.abs(d["E_sources_particles"]) + np.abs(d["E_conv_particles"]))
    assert moved[-1] > 1.0                                      # joules through the bed's inlet and outlet
    lines = {ln.get_label().split(":")[0]: np.asarray(ln.get_ydata(), float) for ln in axes[4].get_lines()}
    for col in ("balance_residual", "balance_error"):
        drawn = lines[col]
        ok = np.isfinite(drawn)
        assert ok.sum() >= d.size - 1                           # every row but the start (nothing moved yet)
        assert drawn[ok] * moved[ok] == pytest.approx(np.abs(d[col][ok]), rel=1e-12)
    assert axes[4].get_yscale() == "log"
    # the balance closes: the residual is round-off, the error the explicit exchange's (< 5 %)
    assert np.nanmax(lines["balance_residual"]) < 1e-9
    assert np.nanmax(lines["balance_error"][1:]) < 0.05
