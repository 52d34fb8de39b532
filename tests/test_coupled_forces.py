"""Fluid torque, lift and virtual mass on coupled particles (issue 13, item 3; coupling.forces).

* the laws (njit functions) against their published forms: Stokes / Dennis et al. torque,
  Saffman's lift at low Re with Mei's correction values, Magnus direction and Rubinow &
  Keller's magnitude at low Re;
* the gas vorticity and Du/Dt the interface computes from a frame (least-squares gradient);
* a sphere spinning in still gas decays as the Stokes torque -pi mu d^3 omega predicts, through
  `coupling run` with torque = "rotational_drag" (and does not decay with the key off);
* a sphere accelerated from rest by gravity in a still fluid approaches its terminal velocity
  with the time constant (m + C_vm m_f) / beta of the virtual-mass equation (DEM API: the
  implicit added mass of the kick with a Stokes drag coefficient), and through `coupling run`
  a bead's first interval is slowed by the added mass as the kick's recursion predicts;
* bad coupling.toml values are refused naming the file, the key and the allowed values.
"""
from __future__ import annotations

import math
import sys
from pathlib import Path

import numpy as np
import pytest

ROOT = Path(__file__).resolve().parents[1]
for p in (ROOT, ROOT / "benchmarks"):
    if str(p) not in sys.path:
        sys.path.insert(0, str(p))

from coupling.forces import (C_VM, magnus_oesterle_bui_dinh_1998, mei_1992_factor,  # noqa: E402
                             rotational_drag_dennis_1980, saffman_mei_1992)
from dem.final import read as read_final  # noqa: E402

RHO, MU = 1.2, 1.8e-5


# --------------------------------------------------------------------------- torque law

def test_rotational_drag_stokes_and_dennis():
    d = 1e-4
    # Stokes (Rubinow & Keller): T = pi mu d^3 Omega_rel, independent of the spin below Re_R = 32
    for om in (1e-3, 1.0, 1e3):
        assert rotational_drag_dennis_1980(d, RHO, MU, om) == pytest.approx(math.pi * MU * d ** 3, rel=1e-14)
    # Dennis, Singh & Ingham (1980) in their own variables: C_M = T / (rho Omega^2 a^5 / 2) =
    # 6.45 / Re^0.5 + 32.1 / Re, Re = a^2 Omega / nu
    a = d / 2
    for re in (20.0, 100.0, 1000.0):
        om = re * MU / (RHO * a * a)
        cm = rotational_drag_dennis_1980(d, RHO, MU, om) * om / (0.5 * RHO * om * om * a ** 5)
        assert cm == pytest.approx(6.45 / math.sqrt(re) + 32.1 / re, rel=1e-12)
    # the two branches meet at Re_R = 32 within 0.2 % (no jump in the torque)
    om32 = 32.0 * MU / (RHO * d * d)
    lo = rotational_drag_dennis_1980(d, RHO, MU, om32)
    hi = rotational_drag_dennis_1980(d, RHO, MU, om32 * (1 + 1e-9))
    assert abs(hi / lo - 1) < 2e-3


# --------------------------------------------------------------------------- lift laws

def test_saffman_lift_low_re_direction_and_magnitude():
    """Simple shear u = (G y, 0, 0): curl u = (0, 0, -G). A particle lagging the gas (slip +x)
    is lifted towards +y (the faster gas), one leading it towards -y; at Re_p -> 0 the
    magnitude is Saffman's 6.46 mu a^2 |ur| (G / nu)^0.5 (Mei's factor -> 1)."""
    d, G = 1e-4, 2.0
    nu = MU / RHO
    ur = 1e-3 * MU / (RHO * d)                  # Re_p = 1e-3 ...
    G = 2 * 0.1 * ur / d                        # ... alpha = G d / (2 ur) = 0.1
    saff = 6.46 * MU * (d / 2) ** 2 * ur * math.sqrt(G / nu)
    f = saffman_mei_1992(d, RHO, MU, ur, 0.0, 0.0, 0.0, 0.0, -G)
    assert f[0] == 0.0 and f[2] == 0.0
    # Mei's factor at Re_p = 1e-3: 1 + 0.3314 alpha^0.5 (1 - exp(-Re_p / 10)) = 1 + 1e-5
    assert f[1] == pytest.approx(saff, rel=2e-5)
    assert f[1] > 0
    g = saffman_mei_1992(d, RHO, MU, -ur, 0.0, 0.0, 0.0, 0.0, -G)
    assert g[1] == pytest.approx(-f[1], rel=1e-14)
    # no shear or no slip: no lift
    assert saffman_mei_1992(d, RHO, MU, ur, 0.0, 0.0, 0.0, 0.0, 0.0) == (0.0, 0.0, 0.0)
    assert saffman_mei_1992(d, RHO, MU, 0.0, 0.0, 0.0, 0.0, 0.0, -G) == (0.0, 0.0, 0.0)


@pytest.mark.parametrize("re_p,alpha,factor", [
    # Mei (1992): (1 - 0.3314 a^.5) exp(-Re/10) + 0.3314 a^.5 (Re <= 40), 0.0524 (a Re)^.5 above;
    # the values worked by hand
    (1.0, 0.1, (1 - 0.3314 * 0.1 ** 0.5) * math.exp(-0.1) + 0.3314 * 0.1 ** 0.5),   # 0.9089
    (10.0, 0.1, (1 - 0.3314 * 0.1 ** 0.5) * math.exp(-1.0) + 0.3314 * 0.1 ** 0.5),   # 0.4341
    (40.0, 0.4, (1 - 0.3314 * 0.4 ** 0.5) * math.exp(-4.0) + 0.3314 * 0.4 ** 0.5),  # 0.2190
    (100.0, 0.1, 0.0524 * math.sqrt(10.0)),                                           # 0.1657
])
def test_mei_correction_values(re_p, alpha, factor):
    assert mei_1992_factor(re_p, 2 * alpha * re_p) == pytest.approx(factor, rel=1e-5)
    # and the lift carries it: |F| / (1.615 mu d |ur| Re_s^0.5) is the factor
    d = 1e-4
    ur = re_p * MU / (RHO * d)
    G = 2 * alpha * ur / d
    f = saffman_mei_1992(d, RHO, MU, ur, 0.0, 0.0, 0.0, 0.0, -G)
    re_s = RHO * G * d * d / MU
    assert f[1] / (1.615 * MU * d * ur * math.sqrt(re_s)) == pytest.approx(factor, rel=1e-5)


def test_magnus_direction_and_rubinow_keller_limit():
    """A sphere moving along +x in still gas with backspin (omega_p along -y: Omega_rel =
    -omega_p along +y, slip u_f - v along -x) is lifted along +z; at low Re the magnitude is
    Rubinow & Keller's pi a^3 rho |omega| |v|."""
    d = 1e-4
    v = 1e-4 * MU / (RHO * d)                   # Re_p = 1e-4
    w = v / d                                   # Re_R = Re_p: exp(-0.05684 Re_R^0.4 Re_p^0.3) = 1 - 9e-5
    f = magnus_oesterle_bui_dinh_1998(d, RHO, MU, -v, 0.0, 0.0, 0.0, w, 0.0)
    rk = math.pi * (d / 2) ** 3 * RHO * w * v
    assert f[0] == 0.0 and f[1] == 0.0 and f[2] > 0
    assert f[2] == pytest.approx(rk, rel=1e-4)
    # topspin: down
    g = magnus_oesterle_bui_dinh_1998(d, RHO, MU, -v, 0.0, 0.0, 0.0, -w, 0.0)
    assert g[2] == pytest.approx(-f[2], rel=1e-14)
    # at Re_p = Re_R = 100 the lift coefficient is Oesterle & Bui Dinh's
    v = 100 * MU / (RHO * d)
    w = v / d
    cl = 0.45 + (1 - 0.45) * math.exp(-0.05684 * 100 ** 0.4 * 100 ** 0.3)      # 0.581
    f = magnus_oesterle_bui_dinh_1998(d, RHO, MU, -v, 0.0, 0.0, 0.0, w, 0.0)
    assert f[2] == pytest.approx(math.pi / 8 * RHO * d * d * cl * v * v, rel=1e-12)


# --------------------------------------------------------------------------- interface terms

def _box_mesh():
    """A 4 x 4 x 4 hex mesh of the unit cube (coupling.mesh.structured_hex_mesh)."""
    from coupling.mesh import PolyMesh, structured_hex_mesh
    g = np.linspace(0.0, 1.0, 5)
    X = np.stack(np.meshgrid(g, g, g, indexing="ij"), axis=-1)
    return PolyMesh(*structured_hex_mesh(X))


def test_interface_vorticity_and_material_derivative():
    """For a linear gas field U = A x + b the least-squares gradient is exact (interior and
    boundary cells of a hex mesh), so the interface's vorticity is curl U = the axial vector
    of A - A^T, and Du/Dt = (U - U_prev)/dt + A U."""
    from coupling.interface import AtParticles, _extra_terms, _material_derivative
    from coupling.interpolate import cell_gradient
    mesh = _box_mesh()
    A = np.array([[0.1, 2.0, -0.5], [0.3, -0.2, 1.5], [0.7, -1.1, 0.1]])
    b = np.array([0.2, -0.1, 0.05])
    cc = mesh.cell_centres
    U = cc @ A.T + b
    G = cell_gradient(mesh, U)
    assert np.allclose(G, A[None], atol=1e-12)
    Up = U - 0.3 * 1e-3
    acc = _material_derivative(U, G, Up, 1e-3)
    assert np.allclose(acc, 0.3 + U @ A.T, rtol=1e-12, atol=1e-12)
    curl = np.array([A[2, 1] - A[1, 2], A[0, 2] - A[2, 0], A[1, 0] - A[0, 1]])
    n = 3
    cells = np.array([0, 21, 63], np.int64)
    rad = np.full(n, 1e-4)
    vel = np.zeros((n, 3))
    om_p = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, 0.0], [0.0, -2.0, 5.0]])
    at = AtParticles(rad, vel, U[cells], cells)
    flift, fvm, texp, krot, madd, tfr = _extra_terms(1, 0, True, at, om_p, G, acc, RHO, MU, C_VM)
    d = 2e-4
    k = math.pi * MU * d ** 3
    assert np.allclose(krot, k, rtol=1e-14)
    assert np.allclose(texp, 0.5 * k * curl[None], rtol=1e-12)
    assert np.allclose(tfr, k * (0.5 * curl[None] - om_p), rtol=1e-12)
    mf = C_VM * RHO * math.pi / 6 * d ** 3
    assert np.allclose(madd, mf, rtol=1e-14)
    assert np.allclose(fvm, mf * acc[cells], rtol=1e-12)
    assert not flift.any()   # (lift off)


# --------------------------------------------------------------------------- virtual mass (DEM kick)

def _falling_sphere(added_mass: bool, dt: float, t_end: float):
    """One sphere (1500 kg/m3, 1 mm) from rest in a still liquid (1000 kg/m3, 1e-3 Pa s) under
    gravity, Stokes drag beta = 3 pi mu d taken implicitly, buoyancy as the explicit fluid force,
    with or without the virtual mass as an added mass. Returns (times, v_z, m, m_f, beta)."""
    from dem import Simulation
    d, rho_p, rho_f, mu = 1e-3, 1500.0, 1000.0, 1e-3
    sc = {"simulation": {"time_step": dt, "end_time": t_end, "gravity": [0, 0, -9.81]},
          "domain": {"min": [-1, -1, -1], "max": [1, 1, 1]},
          "materials": [dict(name="p", density=rho_p, youngs_modulus=1e7, poisson_ratio=0.25,
                             restitution=0.5, friction=0.3)],
          "particles": [{"material": "p", "radius": d / 2, "positions": [[0.0, 0.0, 0.0]]}]}
    sim = Simulation.from_dict(sc)
    vp = math.pi / 6 * d ** 3
    beta = 3 * math.pi * mu * d
    sim.set_fluid(force=np.array([[0.0, 0.0, rho_f * vp * 9.81]]), drag=np.array([beta]),
                  added_mass=np.array([C_VM * rho_f * vp]) if added_mass else None)
    sim.step(0)   # the forces of time 0 with the fluid force
    ts, vs = [], []
    steps = int(round(t_end / dt))
    every = steps // 20
    for k in range(20):
        sim.step(every)
        ts.append(sim.time)
        vs.append(sim.state.velocity[0, 2])
    return np.array(ts), np.array(vs), rho_p * vp, rho_f * vp, beta


def test_virtual_mass_time_constant():
    """m_e dv/dt = (m - m_f) g - beta v, m_e = m + C_vm m_f: v = -v_t (1 - exp(-t beta / m_e)),
    v_t = (m - m_f) g / beta. The two implicit half kicks of a step multiply v_t + v by
    1 / (1 + x/2)^2 = exp(-x) (1 + x^2/4 + O(x^3)), x = dt / tau: after t / dt steps v_t + v is
    (t / tau) x / 4 above the exact value (relative; 0.5 % at t = 4 tau, x = 1/200); the test
    asserts that error to 5 % of itself. The time constant without the virtual mass, m / beta,
    is 25 % shorter and misses by far more."""
    d, rho_f = 1e-3, 1000.0
    m = 1500.0 * math.pi / 6 * d ** 3
    mf = rho_f * math.pi / 6 * d ** 3
    beta = 3 * math.pi * 1e-3 * d
    tau = (m + C_VM * mf) / beta
    dt = tau / 200
    t, v, *_ = _falling_sphere(True, dt, 4 * tau)
    vt = (m - mf) * 9.81 / beta
    exact = -vt * (1 - np.exp(-t / tau))
    # relative error of the distance to the terminal velocity, v_t + v = v_t exp(-t/tau)
    err = (vt + v) / (vt + exact) - 1
    predicted = t / tau * (dt / tau) / 4
    assert np.all(np.abs(err - predicted) < 0.05 * predicted), (err, predicted)
    wrong = -vt * (1 - np.exp(-t * beta / m))
    assert np.abs((vt + v) / (vt + wrong) - 1).max() > 0.5
    # without the added mass the kick follows m / beta (same bound)
    t0, v0, *_ = _falling_sphere(False, dt, 4 * tau)
    ref = -vt * (1 - np.exp(-t0 * beta / m))
    x0 = dt * beta / m
    predicted = t0 * beta / m * x0 / 4
    assert np.all(np.abs((vt + v0) / (vt + ref) - 1 - predicted) < 0.05 * predicted)


# --------------------------------------------------------------------------- spinning sphere (CLI)

def _spinning_case(dest: Path, omega0, torque: str | None):
    """One bead (80 um, 2500 kg/m3) spinning at omega0 and falling from rest in the still gas of
    the single-particle column of benchmarks/coupled_drag.py (rho 10, nu 1.5e-4): CFD step 0.1
    drag relaxation times, 6 coupling steps (about two spin decay times)."""
    import coupled_drag as CD
    from stability.coupled import write_case
    d = 8e-5
    dt_dem = 5e-7
    cell = 0.01
    k = 118
    x = np.array([[cell / 2, cell / 2, 2.2 * cell]])
    case = write_case(dest, L=cell, H=3 * cell, nxy=1, nz=3, positions=x, velocities=np.zeros((1, 3)),
                      diameter=d, density=CD.RHO_P, dt_dem=dt_dem, interval=k, n_steps=6, u_in=0.0,
                      void_fraction="divided", eps_min=0.3, heat=False, rho_g=CD.RHO_G, nu_g=CD.NU_G,
                      walls_top=False)
    dem = (case / "dem.toml").read_text()
    w = "[[" + ", ".join(repr(float(c)) for c in omega0) + "]]"
    dem = dem.replace("\nvelocities = ", f"\nangular_velocities = {w}\nvelocities = ", 1)
    assert "angular_velocities" in dem
    (case / "dem.toml").write_text(dem)
    if torque is not None:
        with open(case / "coupling.toml", "a") as f:
            f.write(f'torque = "{torque}"\nlift = "none"\nvirtual_mass = false\n')
    return case, d, k * dt_dem * 6


def test_spinning_sphere_decays_as_stokes_torque(tmp_path, solver):
    import coupled_drag as CD
    omega0 = np.array([400.0, -300.0, 1000.0])
    case, d, t_end = _spinning_case(tmp_path / "case", omega0, "rotational_drag")
    code, text, _ = CD.run(case, tmp_path / "out")
    assert code == 0, text[-3000:]
    f = read_final(tmp_path / "out" / "final.npz")
    w = f["angular_velocity"][0]
    mu = CD.RHO_G * CD.NU_G
    m = CD.RHO_P * math.pi / 6 * d ** 3
    tau = (m * d * d / 10) / (math.pi * mu * d ** 3)      # I / (pi mu d^3) = rho_p d^2 / (60 mu)
    # Re_R = rho |omega| d^2 / mu = 0.05 at the start: Stokes
    assert CD.RHO_G * np.linalg.norm(omega0) * d * d / mu < 32
    assert 1.5 < t_end / tau < 2.5
    expect = omega0 * math.exp(-t_end / tau)
    # implicit half kicks: exponent error t dt / (4 tau^2) = 1e-3 at dt / tau = 1/355, t = 2 tau;
    # the gas stays still (curl u = 0 to round-off), so the axis is kept
    assert np.allclose(w, expect, rtol=3e-3, atol=0), (w, expect)
    # the same case with the keys off: no fluid torque, the spin is kept exactly
    case2, _, _ = _spinning_case(tmp_path / "case2", omega0, "none")
    code, text, _ = CD.run(case2, tmp_path / "out2")
    assert code == 0, text[-3000:]
    w2 = read_final(tmp_path / "out2" / "final.npz")["angular_velocity"][0]
    assert np.array_equal(w2, omega0), w2


def test_bad_force_keys_are_refused(tmp_path):
    from coupling.case import CaseConfigError, load_config
    for key, val, allowed in (("torque", '"stokes"', "rotational_drag"), ("lift", '"saffman"', "saffman_mei"),
                              ("virtual_mass", '"yes"', "true or false")):
        p = tmp_path / f"{key}.toml"
        p.write_text(f"[coupling]\n{key} = {val}\n")
        with pytest.raises(CaseConfigError) as e:
            load_config(p)
        msg = str(e.value)
        assert str(p) in msg and f"coupling.{key}" in msg and allowed in msg, msg
    p = tmp_path / "ok.toml"
    p.write_text('[coupling]\ntorque = "rotational_drag"\nlift = "magnus"\nvirtual_mass = true\n')
    c = load_config(p)
    assert (c.torque, c.lift, c.virtual_mass) == ("rotational_drag", "magnus", True)


def test_virtual_mass_slows_the_first_interval_through_coupling_run(tmp_path, solver):
    """One bead (80 um, 2500 kg/m3) falling from rest in the still dense gas (rho 10) of the
    single-particle column, one coupling step of 0.1 drag relaxation times, with and without
    virtual_mass = true. The gas of the first frame is at rest (Du_f/Dt = 0), so both runs
    integrate the same constant force F and drag beta over the interval, with the mass m or
    m_e = m + C_vm rho_f V_p: v = F/beta (1 - (1 + h beta / m)^(-2k)) after k steps. The ratio of
    the two velocities is computed from that recursion (close to m / m_e = 0.998; F cancels):
    the runs must give it to 1e-6 (beta at the frame depends on eps_p ~ 1 - 1e-10 and
    on nothing that differs between the runs)."""
    import coupled_drag as CD
    from coupling.drag import drag_coefficient, drag_model_id
    d = 8e-5
    v = {}
    for vm in (False, True):
        case, dt_cfd, tau = CD.single_particle(tmp_path / f"case{vm}", d, 0.1, n_steps=1)
        if vm:
            with open(case / "coupling.toml", "a") as f:
                f.write("virtual_mass = true\n")
        code, text, _ = CD.run(case, tmp_path / f"out{vm}")
        assert code == 0, text[-3000:]
        v[vm] = read_final(tmp_path / f"out{vm}" / "final.npz")["velocity"][0]
    dt_dem = 5e-7
    k = int(round(dt_cfd / dt_dem))
    vp = math.pi / 6 * d ** 3
    m = CD.RHO_P * vp
    me = m + C_VM * CD.RHO_G * vp
    beta = drag_coefficient(drag_model_id("di_felice_1994"), d, 1.0, CD.RHO_G, CD.RHO_G * CD.NU_G, 0.0)

    def fall(mass):
        h = 0.5 * dt_dem
        x = 0.0
        for _ in range(2 * k):
            x = (x + h / mass) / (1 + h * beta / mass)
        return x
    ratio = fall(me) / fall(m)
    assert abs(ratio - m / me) < 2e-4            # the recursion itself: m / m_e to O(dt beta / m)
    assert v[True][2] / v[False][2] == pytest.approx(ratio, rel=1e-6), (v, ratio, m / me)
    assert v[True][2] < 0
