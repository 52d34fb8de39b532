"""Binary impacts: restitution, Hertz contact time, energy, oblique impacts on a wall
(Chung & Ooi, Granular Matter 13 (2011) 643, test 6 regimes)."""
import math
import os
import sys

import numpy as np
import pytest

from dem import Simulation

R = 1e-3
RHO = 2500.0
E = 1e7
NU = 0.3


def two_spheres(e, v=1.0, mu=0.0, dt=None):
    m = 4 / 3 * math.pi * R ** 3 * RHO
    estar = E / (2 * (1 - NU ** 2))
    tc = 2.8682 * ((m / 2) ** 2 / (R / 2 * estar ** 2 * v)) ** 0.2
    scene = {
        "simulation": {"time_step": dt or tc / 400, "end_time": 1.0, "gravity": [0.0, 0.0, 0.0]},
        "domain": {"min": [-0.01] * 3, "max": [0.01] * 3},
        "materials": [dict(name="m", density=RHO, youngs_modulus=E, poisson_ratio=NU,
                           restitution=e, friction=mu)],
        "particles": [{"material": "m", "positions": [[-R - 1e-5, 0, 0], [R + 1e-5, 0, 0]],
                       "radius": R, "velocities": [[v / 2, 0, 0], [-v / 2, 0, 0]]}],
    }
    return Simulation.from_dict(scene), tc


def collide(sim, max_steps=100000):
    """Step until the pair has touched and separated; returns (contact steps)."""
    touching = 0
    started = False
    for _ in range(max_steps):
        sim.step(1)
        if sim.last_contacts:
            started = True
            touching += 1
        elif started:
            return touching
    raise AssertionError("collision did not end")


def collide_until_apart(sim, max_steps=100000, chunk=25):
    """Step until the pair has touched and separated, in compiled calls of ``chunk`` steps (for
    the tests that read only the state after the impact, not its duration). A call of k steps
    gives the states of k calls of one step bit for bit (tests/test_threads.py); the contact
    lasts hundreds of steps, so no chunk skips it, and the up to chunk - 1 steps run after the
    separation are free flight without gravity, which changes no velocity or spin: the state
    read is that of :func:`collide`, bit for bit, at a twentieth of the Python calls."""
    started = False
    for _ in range(0, max_steps, chunk):
        sim.step(chunk)
        if sim.last_contacts:
            started = True
        elif started:
            return
    raise AssertionError("collision did not end")


@pytest.mark.parametrize("e", [0.5, 0.9])
def test_pair_restitution(e):
    sim, _ = two_spheres(e)
    v0 = sim.state.velocity[0, 0] - sim.state.velocity[1, 0]
    collide(sim)
    v1 = sim.state.velocity[0, 0] - sim.state.velocity[1, 0]
    assert -v1 / v0 == pytest.approx(e, rel=0.01)


def test_pair_elastic_duration_and_energy():
    sim, tc = two_spheres(1.0, v=1.0)
    ke0 = sum(sim.state.kinetic_energy())
    steps = collide(sim)
    ke1 = sum(sim.state.kinetic_energy())
    assert steps * sim.dt == pytest.approx(tc, rel=0.02)
    assert abs(ke1 - ke0) / ke0 < 1e-6


def wall_drop(e, vn, vt=0.0, mu=0.0, w0=0.0, radius=R, density=RHO, youngs=E, nu=NU, dt_frac=400,
              tangential="rescaled"):
    m = 4 / 3 * math.pi * radius ** 3 * density
    estar = 1 / (2 * (1 - nu ** 2) / youngs)
    tc = 2.8682 * (m ** 2 / (radius * estar ** 2 * vn)) ** 0.2
    scene = {
        "simulation": {"time_step": tc / dt_frac, "end_time": 1.0, "gravity": [0.0, 0.0, 0.0]},
        "domain": {"min": [-100 * radius] * 3, "max": [100 * radius] * 3},
        "materials": [dict(name="m", density=density, youngs_modulus=youngs, poisson_ratio=nu,
                           restitution=e, friction=mu)],
        "particles": [{"material": "m", "positions": [[0, 0, radius * 1.001]], "radius": radius,
                       "velocities": [[vt, 0, -vn]], "angular_velocities": [[0, w0, 0]]}],
        "walls": [{"type": "plane", "point": [0, 0, 0], "normal": [0, 0, 1], "material": "m"}],
        "contact": {"tangential": tangential},
    }
    return Simulation.from_dict(scene), tc


@pytest.mark.parametrize("e", [0.5, 0.9])
def test_wall_restitution(e):
    sim, _ = wall_drop(e, 1.0)
    collide(sim)
    assert sim.state.velocity[0, 2] / 1.0 == pytest.approx(e, rel=0.01)


def test_wall_elastic_duration_and_energy():
    sim, tc = wall_drop(1.0, 0.5)
    ke0 = sum(sim.state.kinetic_energy())
    steps = collide(sim)
    assert steps * sim.dt == pytest.approx(tc, rel=0.02)
    assert abs(sum(sim.state.kinetic_energy()) - ke0) / ke0 < 1e-6


# Chung & Ooi (2011) test 6: aluminium-alloy sphere, R = 0.1 m, E = 70 GPa, nu = 0.33,
# rho = 2700, mu = 0.4, impact speed 3.9 m/s at angles from the normal.
AL = dict(radius=0.1, density=2700.0, youngs=7.0e10, nu=0.33)
MU = 0.4
V = 3.9


# both tangential models (dem.contact.tangential): they differ in how the spring turns with the
# contact plane (flat here) and in what the Coulomb cap compares; each impact law below holds for both
TANGENTIAL = ["rescaled", "projected"]


@pytest.mark.parametrize("tangential", TANGENTIAL)
@pytest.mark.parametrize("angle", [72.0, 76.0, 80.0, 85.0])
def test_oblique_sliding_regime(angle, tangential):
    """Gross sliding throughout the impact (tan(theta) > 7/2 mu (1+e)): Coulomb impulse
    gives v_t' = v_t - mu (1+e) v_n and omega R = 5/2 mu (1+e) v_n exactly."""
    e = 0.9
    th = math.radians(angle)
    vn, vt = V * math.cos(th), V * math.sin(th)
    assert math.tan(th) > 3.5 * MU * (1 + e)
    sim, _ = wall_drop(e, vn, vt, mu=MU, tangential=tangential, **AL)
    collide_until_apart(sim)
    vt1 = sim.state.velocity[0, 0]
    wR = sim.state.angular_velocity[0, 1] * AL["radius"]
    assert vt1 == pytest.approx(vt - MU * (1 + e) * vn, rel=0.05)
    assert wR == pytest.approx(2.5 * MU * (1 + e) * vn, rel=0.05)
    rebound = math.degrees(math.atan2(vt1, sim.state.velocity[0, 2]))
    expected = math.degrees(math.atan2(vt - MU * (1 + e) * vn, e * vn))
    assert rebound == pytest.approx(expected, rel=0.05)


@pytest.mark.parametrize("tangential", TANGENTIAL)
@pytest.mark.parametrize("angle", [5.0, 15.0, 30.0, 50.0])
def test_oblique_sticking_regime(angle, tangential):
    """Below the sliding limit (tan(theta) < 7/2 mu (1+e)) the tangential impulse stays
    under the Coulomb bound, angular momentum about the contact point is conserved, and
    the result has converged in the time step (5 %)."""
    e = 0.9
    th = math.radians(angle)
    vn, vt = V * math.cos(th), V * math.sin(th)
    assert math.tan(th) < 3.5 * MU * (1 + e)
    out = []
    for frac in (400, 4000):
        sim, _ = wall_drop(e, vn, vt, mu=MU, dt_frac=frac, tangential=tangential, **AL)
        collide_until_apart(sim, max_steps=10 ** 6)
        vt1 = sim.state.velocity[0, 0]
        wR = sim.state.angular_velocity[0, 1] * AL["radius"]
        assert vt - vt1 < 0.99 * MU * (1 + e) * vn
        # m vt R = m vt1 R + I w about the contact point ->  vt1 + 2/5 wR = vt
        assert vt1 + 0.4 * wR == pytest.approx(vt, rel=1e-6)
        out.append((vt1, wR))
    assert out[0][1] == pytest.approx(out[1][1], rel=0.05)


@pytest.mark.parametrize("tangential", TANGENTIAL)
def test_oblique_no_slip_against_continuous_solution(tangential):
    """Elastic (e = 1), no sliding (mu large): the spin after impact matches the
    continuous Hertz-Mindlin equations integrated independently with SciPy:
    m delta'' = -4/3 E* sqrt(R) delta^3/2,  u' = -(7 / 2m) 8 G* sqrt(R delta) xi,  xi' = u."""
    from scipy.integrate import solve_ivp
    r, rho, Y, nu = AL["radius"], AL["density"], AL["youngs"], AL["nu"]
    m = 4 / 3 * math.pi * r ** 3 * rho
    estar = Y / (2 * (1 - nu ** 2))
    gstar = Y / (2 * (1 + nu)) / (2 * (2 - nu))  # wall of the same material: G* = G / (2 (2 - nu))
    th = math.radians(20.0)
    vn, vt = V * math.cos(th), V * math.sin(th)

    def rhs(t, y):
        d, dd, xi, u = y
        dpos = max(d, 0.0)
        fn = 4 / 3 * estar * math.sqrt(r) * dpos ** 1.5
        kt = 8 * gstar * math.sqrt(r * dpos)
        return [dd, -fn / m, u, -3.5 / m * kt * xi]

    ev = lambda t, y: y[0] if t > 0 else 1.0  # noqa: E731
    ev.terminal, ev.direction = True, -1
    sol = solve_ivp(rhs, (0, 1.0), [0.0, vn, 0.0, vt], events=ev, rtol=1e-10, atol=1e-14, max_step=1e-6)
    u_end = sol.y[3, -1]
    # contact point u = vt1 - wR and vt1 + 0.4 wR = vt  ->  wR = (vt - u) / 1.4
    wR_ref = (vt - u_end) / 1.4
    sim, _ = wall_drop(1.0, vn, vt, mu=1e3, dt_frac=2000, tangential=tangential, **AL)
    collide_until_apart(sim, max_steps=10 ** 6)
    wR = sim.state.angular_velocity[0, 1] * r
    assert wR == pytest.approx(wR_ref, rel=0.05)


def test_the_solved_damping_factor_is_kept_beside_the_cache(tmp_path):
    """The exact damping's factor, solved by bisection once per restitution, is read back by
    the next process bit for bit from the file beside Numba's cache (dem.contact.damping.MEMO);
    an unreadable file is solved again and replaced, and what it holds is the same factor."""
    import subprocess
    env = dict(os.environ, NUMBA_CACHE_DIR=str(tmp_path))
    code = ("import sys; from dem.contact import damping as d; "
            "print(repr(d.damping_factor(float(sys.argv[1]), 0, 0)), repr(d._solve_g(float(sys.argv[1]), True)))")
    root = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
    first = subprocess.run([sys.executable, "-c", code, "0.73"], capture_output=True, text=True, env=env, cwd=root)
    assert first.returncode == 0, first.stderr
    memo = tmp_path / "damping_factors.json"
    assert memo.is_file() and "0.73 hertz" in memo.read_text()
    again = subprocess.run([sys.executable, "-c", code, "0.73"], capture_output=True, text=True, env=env, cwd=root)
    a, g = (float(v) for v in first.stdout.split())
    b, _ = (float(v) for v in again.stdout.split())
    assert a == b == g / math.sqrt(0.75)
    memo.write_text("{not json")
    third = subprocess.run([sys.executable, "-c", code, "0.73"], capture_output=True, text=True, env=env, cwd=root)
    assert third.returncode == 0 and float(third.stdout.split()[0]) == a, third.stderr
    assert "0.73 hertz" in memo.read_text()
