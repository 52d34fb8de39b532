"""Particle radiation to walls (issue 14; dem.thermal.radiation, docs/models.md "Radiation to
walls").

* Krause (2017): a particle with no neighbour near a fixed-temperature wall with an
  emissivity sees only the wall (T_e = T_w), so C dT/dt = eps A sigma (T_w^4 - T^4), whose
  exact solution t(T) = [ln((T_w + T)/(T_w - T)) + 2 atan(T/T_w)] / (4 k T_w^3) each integrator
  follows to its order; the wall's radiation record is the particle's energy gain.
* Zhou (2009): the wall takes the cap fraction of the sphere of influence behind it, times its
  emissivity: the first step's rate is eps A sigma (T_e^4 - T^4) with
  T_e = (1 - g) T_f + g T_w, all of it the wall's while the particle is at T_f; a particle
  beyond the range exchanges nothing with the wall.
* A frozen bed next to a hot radiating wall, both models, all integrators: the wall's records
  (contact + gas gap + radiation) plus the rest of the radiation close the particles' energy
  to round-off.
* Bad input (an emissivity on an adiabatic wall, an emissivity without a radiation model) is
  refused by `dem check`, naming the key.
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
from dem.thermal.heat import TOT
from dem.thermal.radiation import SIGMA_SB

sys.path.insert(0, str(Path(__file__).resolve().parent))
from test_wall_heat import L, R, read, scene  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
TW, T0, EPS_P, EPS_W = 1000.0, 300.0, 0.9, 0.7


def _wall(h, model_extra=None):
    return {"type": "plane", "name": "floor", "point": [0, 0, -h], "normal": [0, 0, 1], "material": "p",
            "thermal": {"condition": "fixed_temperature", "temperature": TW, "emissivity": EPS_W}}


def _run(tmp_path, name, positions, model, integ, dt, end, walls, direct="batchelor_obrien"):
    sc = scene([{"material": "p", "positions": positions, "radius": R, "temperature": T0}],
               {"direct": direct, "radiation": model, "integrator": integ, "porosity": "global", "time_step": dt},
               walls, end=end, output=end / 2)
    sc["materials"][0]["emissivity"] = EPS_P
    sim = Simulation.from_dict(sc)
    C = 1.0 / sim.state.inv_heat_capacity.copy()
    T_start = sim.state.temperature.copy()
    sim.run(out_dir=str(tmp_path / name), progress=False)
    return sim, C, T_start


@pytest.mark.parametrize("integ", ["euler", "exponential", "implicit"])
def test_krause_particle_sees_only_the_wall(tmp_path, integ):
    h = 1.5 * R          # 0.5 R from the wall: no contact, inside the sphere of influence (3 R)
    sim, C, _ = _run(tmp_path, "out", [[0, 0, 0]], "krause_2017", integ, 5e-4, 1.0, [_wall(h)])
    k = EPS_P * 4 * math.pi * R * R * SIGMA_SB / C[0]

    def t_of(T):
        return (math.log((TW + T) / (TW - T)) + 2 * math.atan(T / TW)) / (4 * k * TW ** 3)
    from scipy.optimize import brentq
    T_exact = brentq(lambda T: t_of(T) - t_of(T0) - 1.0, T0, TW - 1e-9)
    T = float(sim.state.temperature[0])
    assert T_exact - T0 > 50.0   # a strong exchange: 72 K in the second
    # first-order schemes at dt = 5e-4 s (tau = 1 / (4 k T^3) ~ 5 s): 1e-4 of the rise
    assert T == pytest.approx(T_exact, abs=1e-4 * (T_exact - T0))
    gain = C[0] * (T - T0)
    # the wall's radiation record is the energy gained; nothing else moved
    assert sim.state.wrad[0] == pytest.approx(gain, rel=1e-12)
    assert sim.state.wtot[0] == pytest.approx(gain, rel=1e-12)
    assert sim.state.tot[TOT.wall] == pytest.approx(gain, rel=1e-12)
    assert abs(sim.state.tot[TOT.rad]) <= 1e-12 * gain
    w = read(tmp_path / "out" / "wall_heat.csv")
    assert w[("floor", "radiation")][-1, 1] == pytest.approx(gain, rel=1e-12)
    assert w[("floor", "contact")][-1, 1] == pytest.approx(0.0, abs=1e-12 * gain)
    assert w[("floor", "total")][-1, 1] == pytest.approx(gain, rel=1e-12)


def test_zhou_wall_takes_the_cap_of_the_sphere(tmp_path):
    """One Euler step: the rate is eps A sigma (T_e^4 - T^4) with T_e = (1 - g) T_f + g T_w,
    g = eps_w c^2 (3 s - c) / (4 s^3), c = s - h; at T = T_f all of it is the wall's; the
    particle 3.2 R from the wall (beyond s = 3 R) gets nothing."""
    h = (1.5 * R, 3.2 * R)
    walls = [_wall(h[0])]
    pos = [[-4 * R, 0, 0], [4 * R, 0, -h[0] + h[1]]]    # 8 R apart: not each other's neighbours
    dt = 1e-3
    sim, C, _ = _run(tmp_path, "out", pos, "zhou_2009", "euler", dt, dt, walls, direct="none")
    s = 3.0 * R
    c = s - h[0]
    g = EPS_W * c * c * (3 * s - c) / (4 * s ** 3)
    Te = (1 - g) * T0 + g * TW        # T_f = T0 (the scene's gas at 300 K)
    q = EPS_P * 4 * math.pi * R * R * SIGMA_SB * (Te ** 4 - T0 ** 4)
    assert sim.state.heat_rate[0] == pytest.approx(q, rel=1e-12)
    assert sim.state.heat_rate[1] == 0.0
    assert sim.state.wrad[0] == pytest.approx(q * dt, rel=1e-12)
    assert abs(sim.state.tot[TOT.rad]) <= 1e-12 * q * dt     # the rest (the fluid at T_f) gives nothing
    assert sim.state.temperature[0] == pytest.approx(T0 + q * dt / C[0], rel=1e-15)


@pytest.mark.parametrize("model", ["zhou_2009", "krause_2017"])
@pytest.mark.parametrize("integ", ["euler", "exponential", "implicit"])
def test_bed_next_to_a_radiating_wall_closes_its_energy(tmp_path, model, integ):
    """Two layers of touching beads, the lower one resting on a hot radiating floor: every
    particle's radiation splits into the wall's part and the rest, so
    sum C dT = (wall records: contact + gas gap + radiation) + (the rest of the radiation)."""
    ov = 2e-5
    xs = [(-2 * R + 2 * ov) * 1.0, 0.0, 2 * R - 2 * ov]
    pos = [[x, 0.0, 0.0] for x in xs] + [[x, 0.0, 2 * R - 2 * ov] for x in xs]
    walls = [_wall(R - ov)]
    sim, C, T_start = _run(tmp_path, "out", pos, model, integ, 0.01, 2.0, walls)
    gain = float((C * (sim.state.temperature - T_start)).sum())
    w = read(tmp_path / "out" / "wall_heat.csv")
    parts = w[("floor", "contact")][-1, 1] + w[("floor", "gas_gap")][-1, 1] + w[("floor", "radiation")][-1, 1]
    assert w[("floor", "radiation")][-1, 1] > 0.01 * gain     # radiation matters here
    assert w[("floor", "contact")][-1, 1] > 0.01 * gain       # and so does the contact
    assert parts == pytest.approx(sim.state.wtot[0], rel=1e-12)
    assert gain == pytest.approx(sim.state.tot[TOT.wall] + sim.state.tot[TOT.rad], rel=1e-10)


def _check(tmp_path, thermal_line, radiation):
    toml = f'''
[simulation]
time_step = 1e-5
end_time = 1e-4
mechanics = false

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
point = [0.0, 0.0, {-2 * R}]
normal = [0.0, 0.0, 1.0]
material = "p"
thermal = {thermal_line}

[thermal]
direct = "batchelor_obrien"
radiation = "{radiation}"
time_step = 1e-3

[gas]
conductivity = 0.026
density = 1.2
viscosity = 1.8e-5
heat_capacity = 1005.0
temperature = 300.0
'''
    (tmp_path / "scene.toml").write_text(toml)
    env = dict(os.environ, PYTHONPATH=str(ROOT) + os.pathsep + os.environ.get("PYTHONPATH", ""))
    return subprocess.run([sys.executable, "-m", "dem", "check", str(tmp_path / "scene.toml")],
                          capture_output=True, text=True, env=env, cwd=str(tmp_path))


@pytest.mark.parametrize("line,radiation,words", [
    ('{ condition = "adiabatic", emissivity = 0.5 }', "zhou_2009", ["only a fixed_temperature wall radiates"]),
    ('{ condition = "fixed_heat_flux", heat_flux = 100.0, emissivity = 0.5 }', "zhou_2009",
     ["only a fixed_temperature wall radiates"]),
    ('{ condition = "fixed_temperature", temperature = 400.0, emissivity = 0.5 }', "none",
     ["needs a radiation model"]),
    ('{ condition = "fixed_temperature", temperature = 400.0, emissivity = 1.5 }', "zhou_2009",
     ["must be in [0.0, 1.0]"]),
])
def test_bad_wall_emissivity_is_refused_by_name(tmp_path, line, radiation, words):
    r = _check(tmp_path, line, radiation)
    out = r.stdout + r.stderr
    assert r.returncode == 2, out
    assert "walls[0].thermal.emissivity" in out and "scene.toml" in out
    for wd in words:
        assert wd in out
    assert "Traceback" not in out


def test_good_wall_emissivity_passes_the_check(tmp_path):
    r = _check(tmp_path, '{ condition = "fixed_temperature", temperature = 400.0, emissivity = 0.5 }', "krause_2017")
    assert r.returncode == 0, r.stdout + r.stderr


def _exact_cylinder(a, h, s, inside):
    """The area of a cylinder surface of radius a within a sphere of radius s whose centre is at
    distance h from the surface (outside a solid tube, or inside a hollow one), and the fraction
    of the sphere's volume on the wall's side, by quadrature."""
    from scipy import integrate
    rho = a + h if not inside else a - h

    def band(r, phi):
        return 2.0 * math.sqrt(max(s * s - (r * r + rho * rho - 2 * r * rho * math.cos(phi)), 0.0))
    A = integrate.quad(lambda p: a * band(a, p), -math.pi, math.pi, limit=400, points=[0.0])[0]
    lo, hi = (max(rho - s, 0.0), a) if not inside else (a, rho + s)
    V = integrate.dblquad(lambda r, p: r * band(r, p), -math.pi, math.pi, lambda p: lo, lambda p: hi,
                          epsabs=1e-16)[0]
    return A, V / (4.0 / 3.0 * math.pi * s ** 3)


def test_tangent_plane_against_the_exact_cylinder():
    """A cylinder wall is taken as its tangent plane: for a particle of 0.5 mm touching a tube
    (h = R, s = 3 R), the plane's disc area (Krause) and cap fraction (Zhou) differ from the
    exact cylinder's by first-order amounts in s / a: +4.6 % (area) and +8.7 % (volume) outside
    a tube of 5 mm radius (s / a = 0.3), -5.4 % and -8.5 % inside a pipe of the same radius; the
    error halves with s / a."""
    from dem.thermal.radiation import radiation_wall_weight
    from dem.thermal.registry import RAD_KRAUSE_2017, RAD_ZHOU_2009
    R = 0.5e-3
    h, s = R, 3 * R
    plane_area = radiation_wall_weight(RAD_KRAUSE_2017, 1.0, h, s)
    plane_frac = radiation_wall_weight(RAD_ZHOU_2009, 1.0, h, s)
    assert plane_area == pytest.approx(math.pi * (s * s - h * h), rel=1e-15)
    errs = {}
    for a in (5e-3, 10e-3):
        for inside in (False, True):
            A, f = _exact_cylinder(a, h, s, inside)
            errs[a, inside] = (plane_area / A - 1.0, plane_frac / f - 1.0)
    # the plane over-counts a convex tube's surface and volume and under-counts a pipe's
    assert errs[5e-3, False][0] == pytest.approx(1 / 0.9557 - 1, abs=2e-3)
    assert errs[5e-3, False][1] == pytest.approx(1 / 0.9201 - 1, abs=2e-3)
    assert errs[5e-3, True][0] == pytest.approx(1 / 1.0571 - 1, abs=2e-3)
    assert errs[5e-3, True][1] == pytest.approx(1 / 1.0929 - 1, abs=2e-3)
    for inside in (False, True):   # first order in s / a
        for k in range(2):
            assert errs[10e-3, inside][k] / errs[5e-3, inside][k] == pytest.approx(0.5, abs=0.05)


@pytest.mark.parametrize("model", ["zhou_2009", "krause_2017"])
@pytest.mark.parametrize("integ", ["euler", "implicit"])
def test_a_radiating_stl_floor_is_the_radiating_plane(tmp_path, model, integ):
    """The bed of the test above on its hot floor given as an STL plane of 288 jittered triangles
    (issue 50): the mesh wall is its tangent plane at the nearest contact record, which the mesh
    pre-pass keeps out to the sphere of influence (radiation_range radii, beyond the heat models'
    reach), so every particle's radiation weights, the temperatures and the wall's records by path
    are the plane's to round-off (the closest point of a triangle against the plane's dot
    product: 1e-12 of the heat moved)."""
    from dem.contact.mesh import write_stl
    from test_mesh_walls import plane_mesh
    ov = 2e-5
    xs = [(-2 * R + 2 * ov) * 1.0, 0.0, 2 * R - 2 * ov]
    # (the last bead 2.58 R from the floor: beyond the heat models' reach, 2 R, inside the sphere, 3 R)
    pos = [[x, 0.0, 0.0] for x in xs] + [[x, 0.0, 2 * R - 2 * ov] for x in xs] + [[0.0, 4 * R, 1.6 * R]]
    stl = tmp_path / "floor.stl"   # z = -(R - ov) over the domain's section, 12 x 12 squares
    write_stl(str(stl), plane_mesh(n=12, size=2 * L, jitter=0.3) - [L, L, R - ov], binary=False)
    mesh = dict(_wall(R - ov), type="mesh", file=str(stl))
    for k in ("point", "normal"):
        mesh.pop(k)
    a, Ca, Ta = _run(tmp_path, "plane", pos, model, integ, 0.01, 0.5, [_wall(R - ov)])
    b, Cb, Tb = _run(tmp_path, "mesh", pos, model, integ, 0.01, 0.5, [mesh])
    gain = float((Ca * (a.state.temperature - Ta)).sum())
    assert a.state.wrad.sum() > 0.01 * gain
    assert np.abs(b.state.temperature - a.state.temperature).max() <= 1e-12 * (TW - T0)
    wa, wb = read(tmp_path / "plane" / "wall_heat.csv"), read(tmp_path / "mesh" / "wall_heat.csv")
    for path in ("contact", "gas_gap", "radiation", "total"):
        assert wb[("floor", path)][-1, 1] == pytest.approx(wa[("floor", path)][-1, 1], abs=1e-12 * gain), path
