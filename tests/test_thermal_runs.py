"""Thermal DEM runs against exact solutions and conservation laws."""
import math

import numpy as np
import pytest

from dem import Simulation
from dem.scene import SceneError

R = 1e-3
MAT = dict(name="p", density=2500.0, youngs_modulus=1e7, poisson_ratio=0.3, restitution=0.5,
           friction=0.3, thermal_conductivity=1.0, heat_capacity=840.0)


def base(particles, thermal, walls=(), gas=None, mech=False, dt=1e-5, end=1.0, domain=0.01, mats=None):
    sc = {"simulation": {"time_step": dt, "end_time": end, "mechanics": mech, "output_interval": end,
                         "gravity": [0.0, 0.0, 0.0]},
          "domain": {"min": [-domain] * 3, "max": [domain] * 3},
          "materials": mats or [dict(MAT)], "particles": particles, "thermal": thermal,
          "walls": list(walls)}
    if gas is not None:
        sc["gas"] = gas
    return sc


AIR = dict(conductivity=0.026, density=1.2, viscosity=1.8e-5, heat_capacity=1005.0, temperature=300.0)


def test_two_particles_exact_decay():
    """Held in contact (mechanics = false), constant conductance H: T1 - T2 decays as
    exp(-H (1/(m1 c1) + 1/(m2 c2)) t); default settings (exponential update)."""
    sc = base([{"material": "p", "positions": [[0, 0, 0]], "radius": R, "temperature": 400.0},
               {"material": "p", "positions": [[2.5 * R - 2e-5, 0, 0]], "radius": 1.5 * R,
                "temperature": 300.0}],
              {"direct": "batchelor_obrien", "time_step": 0.5}, end=60.0)
    sim = Simulation.from_dict(sc)
    st = sim.state
    C = 1.0 / st.inv_heat_capacity
    H = sim.state.Hd[sim.state.Hd > 0]
    assert H.size == 1
    # the conductance is Batchelor & O'Brien's 4 k_eff r_c with r_c = sqrt(R* delta)
    rstar = R * 1.5 * R / (2.5 * R)
    assert H[0] == pytest.approx(4 * 0.5 * math.sqrt(rstar * 2e-5), rel=1e-12)
    sim.run(progress=False)
    ratio = (st.temperature[0] - st.temperature[1]) / 100.0
    assert ratio == pytest.approx(math.exp(-H[0] * (1 / C[0] + 1 / C[1]) * sim.time), rel=1e-4)
    assert np.sum(C * st.temperature) == pytest.approx(C[0] * 400 + C[1] * 300, rel=1e-13)


def test_two_particles_euler_converges():
    sc = base([{"material": "p", "positions": [[0, 0, 0]], "radius": R, "temperature": 400.0},
               {"material": "p", "positions": [[2 * R - 2e-5, 0, 0]], "radius": R, "temperature": 300.0}],
              {"direct": "batchelor_obrien", "time_step": 0.01, "integrator": "euler"}, end=20.0)
    sim = Simulation.from_dict(sc)
    C = 1.0 / sim.state.inv_heat_capacity
    H = sim.state.Hd[sim.state.Hd > 0][0]
    sim.run(progress=False)
    lam = H * (2 / C[0])
    exact = math.exp(-lam * sim.time)
    ratio = (sim.state.temperature[0] - sim.state.temperature[1]) / 100.0
    # first order: relative error lam^2 dt t / 2
    assert abs(ratio / exact - 1) < lam ** 2 * 0.01 * sim.time


def test_single_particle_stagnant_gas():
    """Nu = 2 in stagnant gas: T = T_f + (T0 - T_f) exp(-h A t / (m c)), h = 2 k_f / d."""
    sc = base([{"material": "p", "positions": [[0, 0, 0]], "radius": R, "temperature": 400.0}],
              {"direct": "none", "convection": "ranz_marshall", "time_step": 0.2}, gas=AIR, end=100.0)
    sim = Simulation.from_dict(sc)
    sim.run(progress=False)
    m = 4 / 3 * math.pi * R ** 3 * 2500
    hA = 2 * 0.026 / (2 * R) * 4 * math.pi * R ** 2
    exact = 300 + 100 * math.exp(-hA * sim.time / (m * 840))
    assert sim.state.temperature[0] == pytest.approx(exact, rel=1e-4)
    # and with the explicit scheme and a small step
    sc["thermal"].update(integrator="euler", time_step=0.02)
    sim = Simulation.from_dict(sc)
    sim.run(progress=False)
    assert sim.state.temperature[0] == pytest.approx(exact, rel=1e-4)


def closed_box(direct, indirect, mech, integrator="auto"):
    """A box of particles with adiabatic walls; every conduction mechanism on."""
    L = 0.006
    walls = [{"type": "plane", "point": [0, 0, 0], "normal": list(nrm), "material": "p"}
             for nrm in ([1, 0, 0], [0, 1, 0], [0, 0, 1])]
    walls += [{"type": "plane", "point": [L, L, L], "normal": list(nrm), "material": "p"}
              for nrm in ([-1, 0, 0], [0, -1, 0], [0, 0, -1])]
    th = {"direct": direct, "indirect": indirect, "initial_temperature": 300.0,
          "initial_regions": [{"min": [0, 0, 0], "max": [L, L, L / 2], "temperature": 500.0}],
          "integrator": integrator}
    parts = [{"material": "p", "count": 60, "radius": {"distribution": "uniform", "min": 4e-4, "max": 6e-4},
              "region": {"type": "box", "min": [0, 0, 0], "max": [L, L, L]},
              "velocity": [0.05, -0.03, 0.0]}]
    if not mech:
        th["time_step"] = 0.05
        # frozen: a slightly overlapping cubic lattice of unequal spheres (contacts and gaps)
        a = 1e-3
        g = (np.arange(5) + 0.6) * a
        pos = np.array([[x, y, z] for x in g for y in g for z in g])
        rad = np.where(np.arange(len(pos)) % 7 == 0, 0.45 * a, 0.5 * a + 1e-5)
        parts = [{"material": "p", "positions": pos.tolist(), "radii": rad.tolist()}]
    sc = {"simulation": {"time_step": 1e-5, "end_time": 0.03 if mech else 20.0, "mechanics": mech,
                         "gravity": [0, 0, -9.81], "seed": 2},
          "domain": {"min": [0, 0, 0], "max": [L, L, L]},
          "materials": [dict(MAT)],
          "particles": parts,
          "walls": walls, "thermal": th, "gas": dict(AIR)}
    return Simulation.from_dict(sc)


@pytest.mark.parametrize("direct,indirect", [
    ("batchelor_obrien", "voronoi_a"), ("thermal_pipe", "voronoi_b"),
    ("quintana_ruiz_campello_2020", "gan_2016_voronoi_a"), ("rojek_2014", "chen_2019_voronoi_b"),
    ("zhou_2008_collisional", "musser_2011_surrounding_layer"), ("none", "rong_horio_1999_surrounding_layer"),
    ("beaulieu_2020", "vargas_mccarthy_2002")])
@pytest.mark.parametrize("mech", [True, False])
def test_adiabatic_box_conserves_energy(direct, indirect, mech):
    sim = closed_box(direct, indirect, mech)
    st = sim.state
    C = 1.0 / st.inv_heat_capacity
    e0 = np.sum(C * st.temperature)
    spread0 = np.std(st.temperature)
    sim.run(progress=False)
    st = sim.state  # particles are reordered in space during the run
    e1 = np.sum(st.temperature / st.inv_heat_capacity)
    assert abs(e1 - e0) / e0 < 1e-10
    # heat did flow
    assert np.std(st.temperature) < spread0
    assert sim.thermal.tot[0] + sim.thermal.tot[1] > 0


MAT_BEAULIEU = dict(microhardness=3e9, roughness=1e-6, asperity_slope=0.1, emissivity=0.8)
MAT.update(MAT_BEAULIEU)


def line_of_ten(hot=None, cold=None, integrator="auto"):
    """Ten particles in a line between two walls (x = 0 and x = L), touching with a fixed
    small overlap; mechanics frozen."""
    n = 10
    ov = 2e-5
    xs = [R - ov + k * (2 * R - ov) for k in range(n)]
    L = xs[-1] + R - ov
    T0 = list(np.linspace(350, 300, n))
    walls = [{"type": "plane", "name": "left", "point": [0, 0, 0], "normal": [1, 0, 0], "material": "p",
              "thermal": hot or {"condition": "adiabatic"}},
             {"type": "plane", "name": "right", "point": [L, 0, 0], "normal": [-1, 0, 0], "material": "p",
              "thermal": cold or {"condition": "adiabatic"}}]
    parts = [{"material": "p", "positions": [[x, 0, 0] for x in xs], "radius": R}]
    sc = base(parts, {"direct": "batchelor_obrien", "time_step": 0.5, "initial_temperature": 300.0,
                      "integrator": integrator},
              walls=walls, end=4000.0, domain=0.05)
    sc["domain"] = {"min": [-0.001, -0.01, -0.01], "max": [L + 0.001, 0.01, 0.01]}
    sim = Simulation.from_dict(sc)
    sim.state.temperature[:] = T0
    return sim


def test_line_adiabatic_equilibrium():
    sim = line_of_ten()
    st = sim.state
    mean0 = np.mean(st.temperature)
    sim.run(end_time=20000.0, progress=False)  # slowest mode: tau ~ 450 s
    assert np.allclose(st.temperature, mean0, rtol=1e-9, atol=0)


@pytest.mark.parametrize("integrator,tol", [("euler", 1e-6), ("exponential", 1e-4)])
def test_line_linear_steady_profile(integrator, tol):
    """Euler's steady state is the exact one; the split exponential update is off by
    O((H dt / C)^2) (here H dt / C = 0.011)."""
    sim = line_of_ten(hot={"condition": "fixed_temperature", "temperature": 400.0},
                      cold={"condition": "fixed_temperature", "temperature": 300.0}, integrator=integrator)
    sim.run(end_time=20000.0, progress=False)
    T = sim.state.temperature[np.argsort(sim.state.position[:, 0])]
    steps = np.diff(T)
    # equal conductances between neighbours: the interior profile is linear
    assert np.allclose(steps, steps.mean(), rtol=tol)
    # series network: H_w (Tw_h - T1) = H (T_k - T_k+1) = H_w (T10 - Tw_c); here H_w = 2 H (k_wall
    # in series with k_p halves the pair conductivity), so each wall gap takes half a pair step
    H = sim.state.Hd[sim.state.Hd > 0][0]
    Hw = sim.state.Hw[sim.state.Hw > 0]
    q = H * (-steps.mean())
    assert Hw[0] * (400.0 - T[0]) == pytest.approx(q, rel=tol)
    assert Hw[-1] * (T[-1] - 300.0) == pytest.approx(q, rel=tol)
    # and the exact solution of the chain
    total_R = 2 / Hw[0] + 9 / H
    assert q == pytest.approx(100.0 / total_R, rel=tol)


def test_bad_thermal_input():
    good = base([{"material": "p", "positions": [[0, 0, 0]], "radius": R}],
                {"direct": "batchelor_obrien", "initial_temperature": 300.0, "time_step": 1.0})
    bad = {k: (dict(v) if isinstance(v, dict) else v) for k, v in good.items()}
    bad["thermal"] = dict(good["thermal"], direct="batchelor_obrian")
    with pytest.raises(SceneError) as e:
        Simulation.from_dict(bad)
    assert "thermal.direct" in str(e.value) and "batchelor_obrien" in str(e.value) and "valid" in str(e.value)
    # every valid name once: the correction registry has a record named "none" of its own
    for key in ("direct", "correction"):
        bad["thermal"] = dict(good["thermal"], **{key: "bogus"})
        with pytest.raises(SceneError) as e:
            Simulation.from_dict(bad)
        names = str(e.value).split("valid: ")[1].split(", ")
        assert f"thermal.{key}" in str(e.value) and names[0] == "none" and len(names) == len(set(names)), names
    m = dict(MAT)
    del m["thermal_conductivity"]
    bad = dict(good, materials=[m])
    with pytest.raises(SceneError) as e:
        Simulation.from_dict(bad)
    assert "materials[0].thermal_conductivity" in str(e.value)
    m = dict(MAT, heat_capacity=-840.0)
    bad = dict(good, materials=[m])
    with pytest.raises(SceneError) as e:
        Simulation.from_dict(bad)
    assert "materials[0].heat_capacity" in str(e.value)
    bad = dict(good, thermal=dict(good["thermal"], convection="ranz_marshall"))
    with pytest.raises(SceneError) as e:
        Simulation.from_dict(bad)
    assert "gas" in str(e.value)
