"""Radiation, friction heat, sources, wall heat flux, Voronoi porosity, and the effective
conductivity of a frozen random packing beside Zehner-Schlunder."""
import math

import numpy as np
import pytest

from dem import Simulation

R = 1e-3
SIGMA = 5.670374419e-8
MAT = dict(name="p", density=2500.0, youngs_modulus=1e7, poisson_ratio=0.3, restitution=0.5,
           friction=0.3, thermal_conductivity=1.0, heat_capacity=840.0, emissivity=0.8)
AIR = dict(conductivity=0.026, density=1.2, viscosity=1.8e-5, heat_capacity=1005.0, temperature=300.0)


def scene(particles, thermal, walls=(), mech=False, dt=1e-5, end=1.0, gas=None, gravity=(0, 0, 0), L=0.01):
    sc = {"simulation": {"time_step": dt, "end_time": end, "mechanics": mech, "gravity": list(gravity)},
          "domain": {"min": [-L] * 3, "max": [L] * 3}, "materials": [dict(MAT)],
          "particles": particles, "thermal": thermal, "walls": list(walls)}
    if gas is not None:
        sc["gas"] = gas
    return sc


def test_radiation_single_particle():
    """Zhou 2009 with no neighbours: T_env = T_f, Q = sigma eps A (T_f^4 - T^4); compared with
    the ODE m c dT/dt = Q integrated by SciPy."""
    from scipy.integrate import solve_ivp
    sc = scene([{"material": "p", "positions": [[0, 0, 0]], "radius": R, "temperature": 1200.0}],
               {"direct": "none", "radiation": "zhou_2009", "time_step": 0.01, "integrator": "euler",
                "porosity": "global"}, gas=dict(AIR, porosity=1.0), end=20.0)
    sim = Simulation.from_dict(sc)
    sim.run(progress=False)
    m = 4 / 3 * math.pi * R ** 3 * 2500
    A = 4 * math.pi * R ** 2
    sol = solve_ivp(lambda t, T: [SIGMA * 0.8 * A * (300.0 ** 4 - T[0] ** 4) / (m * 840)], (0, 20.0), [1200.0],
                    rtol=1e-10, atol=1e-10)
    assert sim.state.temperature[0] == pytest.approx(sol.y[0, -1], rel=1e-3)
    assert sim.thermal.tot[3] == pytest.approx(m * 840 * (sim.state.temperature[0] - 1200.0), rel=1e-9)


def test_heat_source_and_flux_wall():
    """A group source of P watts and a fixed-flux wall: the thermal energy rises by exactly
    (P + q pi r_c^2) t, and history.csv reports both."""
    ov = 2e-5
    walls = [{"type": "plane", "name": "heater", "point": [0, 0, -R + ov], "normal": [0, 0, 1], "material": "p",
              "thermal": {"condition": "fixed_heat_flux", "heat_flux": 5000.0}}]
    sc = scene([{"material": "p", "positions": [[0, 0, 0]], "radius": R, "temperature": 300.0}],
               {"direct": "batchelor_obrien", "time_step": 0.1, "sources": [{"group": 0, "power": 0.01}]},
               walls=walls, end=10.0)
    sim = Simulation.from_dict(sc)
    C = 1 / sim.state.inv_heat_capacity[0]
    sim.run(progress=False)
    rc = math.sqrt(R * ov)  # Hertz-overlap contact radius against a wall
    expected = (0.01 + 5000.0 * math.pi * rc ** 2) * 10.0
    assert C * (sim.state.temperature[0] - 300.0) == pytest.approx(expected, rel=1e-10)
    assert sim.thermal.wtot[0] == pytest.approx(5000.0 * math.pi * rc ** 2 * 10.0, rel=1e-10)
    assert sim.thermal.tot[5] == pytest.approx(0.1, rel=1e-10)


def test_friction_heat_equals_dissipated_work():
    """A sphere launched sliding (no spin) on a floor: Coulomb friction dissipates
    (2/7) of ... until rolling; nguyen_2009 (mu |v_t| F_n) with equal partition gives the
    particle half of the work lost by friction, i.e. half the kinetic energy lost."""
    v0 = 0.5
    walls = [{"type": "plane", "point": [0, 0, 0], "normal": [0, 0, 1], "material": "p"}]
    sc = scene([{"material": "p", "positions": [[-0.008, 0, R * 0.9995]], "radius": R, "temperature": 300.0,
                 "velocity": [v0, 0, 0]}],
               {"direct": "none", "friction_heat": "nguyen_2009", "partition": "equal"},
               walls=walls, mech=True, dt=2e-6, end=0.05, gravity=(0, 0, -9.81), L=0.05)
    sc["materials"][0]["restitution"] = 0.3
    sim = Simulation.from_dict(sc)
    ke0 = sum(sim.state.kinetic_energy())
    sim.run(progress=False)
    st = sim.state
    ke1 = sum(st.kinetic_energy())
    # rolling without slip at the end: v = 5/7 v0 (angular momentum about the contact point)
    assert st.velocity[0, 0] == pytest.approx(5 / 7 * v0, rel=0.01)
    assert ke0 - ke1 == pytest.approx(0.5 * 2500 * 4 / 3 * math.pi * R ** 3 * v0 ** 2 * 2 / 7, rel=0.02)
    heat = (st.temperature[0] - 300.0) / st.inv_heat_capacity[0]
    assert heat == pytest.approx(0.5 * (ke0 - ke1), rel=0.03)


def test_voronoi_porosity_of_fcc_lattice():
    """FCC packing of touching spheres: every Voronoi cell (rhombic dodecahedron, volume
    4 sqrt(2) R^3) has porosity 1 - pi/(3 sqrt 2) = 0.2595 exactly."""
    from dem.thermal.voronoi import voronoi_porosity
    a = 2 * math.sqrt(2) * R
    base = np.array([[0, 0, 0], [0.5, 0.5, 0], [0.5, 0, 0.5], [0, 0.5, 0.5]])
    cells = np.array([[i, j, k] for i in range(4) for j in range(4) for k in range(4)])
    x = ((cells[:, None, :] + base[None]) * a).reshape(-1, 3)
    por = voronoi_porosity(x, np.full(len(x), R), x.min(0) - a / 4, x.max(0) + a / 4)
    inner = np.all((x > a * 1.2) & (x < a * 2.8), axis=1)
    assert inner.sum() > 10
    assert np.allclose(por[inner], 1 - math.pi / (3 * math.sqrt(2)), rtol=1e-9)


def zehner_schlunder(eps, kappa):
    """Zehner & Schlunder (1970) k_eff / k_f of a packed bed, no radiation, no flattening."""
    B = 1.25 * ((1 - eps) / eps) ** (10 / 9)
    s = math.sqrt(1 - eps)
    f = (1 - 1 / kappa) * B / (1 - B / kappa) ** 2 * math.log(kappa / B) - (B + 1) / 2 - (B - 1) / (1 - B / kappa)
    return 1 - s + 2 * s / (1 - B / kappa) * f


@pytest.fixture(scope="module")
def packing():
    L = 0.012
    sc = {"simulation": {"time_step": 1e-5, "end_time": 0.35, "gravity": [0, 0, -9.81], "seed": 11},
          "domain": {"min": [0, 0, 0], "max": [L, L, 0.1], "periodic": [True, True, False]},
          "materials": [dict(MAT, friction=0.5, restitution=0.3)],
          "particles": [{"material": "p", "count": 600, "radius": R,
                         "region": {"type": "box", "min": [0, 0, 0.001], "max": [L, L, 0.099]}}],
          "walls": [{"type": "plane", "point": [0, 0, 0], "normal": [0, 0, 1], "material": "p"}]}
    sim = Simulation.from_dict(sc)
    sim.run(progress=False)
    return sim.state.position.copy(), L


def test_packed_bed_effective_conductivity(packing):
    """Frozen packing heated from the floor (400 K) and cooled through the top layer
    (300 K wall): the steady conductivity from the mid-bed gradient lies within a factor
    of two of Zehner-Schlunder for the same porosity and k_p/k_f (contact conduction with
    the softened stiffness of the packing plus Voronoi gas conduction)."""
    x, L = packing
    top = float(np.max(x[:, 2])) + R - 2e-5
    walls = [{"type": "plane", "name": "hot", "point": [0, 0, 0], "normal": [0, 0, 1], "material": "p",
              "thermal": {"condition": "fixed_temperature", "temperature": 400.0}},
             {"type": "plane", "name": "cold", "point": [0, 0, top], "normal": [0, 0, -1], "material": "p",
              "thermal": {"condition": "fixed_temperature", "temperature": 300.0}}]
    sc = {"simulation": {"time_step": 1e-5, "end_time": 6000.0, "mechanics": False, "gravity": [0, 0, -9.81],
                         "output_interval": 6000.0},
          "domain": {"min": [0, 0, 0], "max": [L, L, 0.05], "periodic": [True, True, False]},
          "materials": [dict(MAT)],
          "particles": [{"material": "p", "positions": x.tolist(), "radius": R}],
          "walls": walls, "gas": dict(AIR),
          "thermal": {"direct": "batchelor_obrien", "indirect": "voronoi_a", "time_step": 5.0,
                      "initial_temperature": 350.0}}
    sim = Simulation.from_dict(sc)
    e_hot = []
    for _ in range(3):
        sim.run(end_time=sim.time + 10000.0, progress=False)
        e_hot.append(sim.thermal.wtot.copy())
    # steady: what enters through the hot wall leaves through the cold one
    q_hot = (e_hot[2][0] - e_hot[1][0]) / 10000.0
    q_cold = (e_hot[2][1] - e_hot[1][1]) / 10000.0
    print(f"q_hot {q_hot:.5g} W, q_cold {q_cold:.5g} W, earlier {(e_hot[1][0] - e_hot[0][0]) / 10000.0:.5g} W")
    assert q_hot > 0
    assert q_cold == pytest.approx(-q_hot, rel=0.01)
    z, T = sim.state.position[:, 2], sim.state.temperature
    mid = (z > 0.25 * top) & (z < 0.75 * top)
    grad = np.polyfit(z[mid], T[mid], 1)[0]
    k_eff = q_hot / (L * L) / -grad
    n_mid = mid.sum()
    eps = 1 - n_mid * 4 / 3 * math.pi * R ** 3 / (L * L * (z[mid].max() - z[mid].min()))
    zs = zehner_schlunder(eps, 1.0 / 0.026) * 0.026
    print(f"porosity {eps:.3f}: k_eff DEM {k_eff:.4f} W/(m K), Zehner-Schlunder {zs:.4f} W/(m K), "
          f"ratio {k_eff / zs:.2f}")
    assert 0.5 < k_eff / zs < 2.0


def test_exponential_update_with_radiation_is_bounded_and_steady():
    """A particle on a 1500 K wall radiating to 300 K surroundings: the exponential update
    treats walls and radiation as one exact relaxation, so a 20 s step stays inside
    [300, 1500] K and reaches the same steady temperature as a 0.1 s step (flux balance
    H_w (T_w - T) = eps sigma A (T^4 - T_env^4))."""
    def final(dt, end=400.0):
        sc = scene([{"material": "p", "positions": [[0, 0, R - 2e-5]], "radius": R, "temperature": 300.0}],
                   {"direct": "batchelor_obrien", "radiation": "zhou_2009", "porosity": "global",
                    "integrator": "exponential", "time_step": dt},
                   walls=[{"type": "plane", "point": [0, 0, 0], "normal": [0, 0, 1], "material": "p",
                           "thermal": {"condition": "fixed_temperature", "temperature": 1500.0}}],
                   gas={"conductivity": 0.026, "temperature": 300.0, "porosity": 1.0}, end=end)
        sim = Simulation.from_dict(sc)
        sim.run(progress=False)
        return sim
    fine = final(0.1)
    coarse = final(20.0)
    T = coarse.state.temperature[0]
    assert 300.0 < T < 1500.0
    assert T == pytest.approx(fine.state.temperature[0], rel=1e-3)
    # steady flux balance
    Hw = fine.state.Hw[fine.state.Hw > 0][0]
    Tf = fine.state.temperature[0]
    A = 4 * math.pi * R ** 2
    assert Hw * (1500.0 - Tf) == pytest.approx(0.8 * SIGMA * A * (Tf ** 4 - 300.0 ** 4), rel=1e-3)
    # energy bookkeeping: wall in = stored + radiated
    C = 1 / fine.state.inv_heat_capacity[0]
    assert fine.thermal.wtot[0] + fine.thermal.tot[3] == pytest.approx(C * (Tf - 300.0), rel=1e-9)
