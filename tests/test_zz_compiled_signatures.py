"""One cached kernel serves every scene: the declared state (dem.schema) gives every scene the
same argument types, a disabled feature being an empty array of the same dtype and axes.

Runs every example and test scene plus variants that switch each optional array on (rolling
springs, contact age, friction heat, indirect conduction, radiation, group sources,
exponential, implicit and TR-BDF2 integration, frozen packing, fluid forces, fluid torque and virtual
mass, no walls, periodic axes) in this one
process, then counts the compiled signatures of each kernel: at most two (heat on, heat off:
the ``hon`` switch), eight for the step and its interact phase (lean or full form too: the
``xon`` switch, dem.step.full_form; and the tangential model, ``ton``), whatever ran before in this test session (this file runs
last).
"""
import glob
import os

import numpy as np

from dem import Simulation
from dem import scene as scene_mod
from dem import step as K
from dem.thermal import heat as H
from dem.thermal import implicit as IM
from dem import neighbors as NB

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))

BASE = {"simulation": {"time_step": 1e-5, "end_time": 1e-3, "gravity": [0, 0, -9.81]},
        "domain": {"min": [0.0, 0.0, 0.0], "max": [0.004, 0.004, 0.004]},
        "materials": [dict(name="g", density=2500.0, youngs_modulus=5e6, poisson_ratio=0.3, restitution=0.5,
                           friction=0.4, rolling_friction=0.05, thermal_conductivity=1.0, heat_capacity=840.0,
                           emissivity=0.8, microhardness=1e9, roughness=1e-7, asperity_slope=0.1)],
        "particles": [{"material": "g", "count": 40, "radius": 2e-4,
                       "region": {"type": "box", "min": [0.0005, 0.0005, 0.0005], "max": [0.0035, 0.0035, 0.0035]}}],
        "walls": [{"name": "floor", "type": "plane", "point": [0, 0, 0], "normal": [0, 0, 1], "material": "g"}]}
GAS = {"conductivity": 0.026, "density": 1.2, "viscosity": 1.8e-5, "heat_capacity": 1000.0, "temperature": 300.0}


def _variants():
    heat = {"initial_temperature": 300.0, "direct": "batchelor_obrien"}
    yield "mechanics only", {}
    yield "epsd rolling", {"contact": {"rolling": "epsd"}}
    yield "projected tangential spring", {"contact": {"tangential": "projected"}}
    yield "heat, euler fused", {"thermal": dict(heat)}
    yield "heat, exponential", {"thermal": dict(heat, integrator="exponential")}
    yield "heat, implicit", {"thermal": dict(heat, integrator="implicit")}
    yield "heat, trbdf2", {"thermal": dict(heat, integrator="trbdf2")}
    yield "trbdf2, radiation, convection, sources", {
        "thermal": dict(heat, integrator="trbdf2", radiation="zhou_2009", convection="ranz_marshall",
                        sources=[{"group": 0, "power": 1e-3}]), "gas": GAS}
    yield "implicit, radiation, convection, sources", {
        "thermal": dict(heat, integrator="implicit", radiation="zhou_2009", convection="ranz_marshall",
                        sources=[{"group": 0, "power": 1e-3}]), "gas": GAS}
    yield "contact age", {"thermal": dict(heat, direct="zhou_2008_collisional")}
    yield "friction heat", {"thermal": dict(heat, friction_heat="nguyen_2009")}
    yield "indirect + convection", {"thermal": dict(heat, indirect="vargas_mccarthy_2002", convection="ranz_marshall"),
                                    "gas": GAS}
    yield "radiation", {"thermal": dict(heat, radiation="zhou_2009"), "gas": GAS}
    yield "group sources", {"thermal": dict(heat, sources=[{"group": 0, "power": 1e-3}])}
    yield "no walls, periodic", {"walls": [], "domain": {"min": [0.0] * 3, "max": [0.004] * 3,
                                                         "periodic": [True, True, False]}}


def _run_variant(extra, steps=30):
    data = {k: (dict(v) if isinstance(v, dict) else v) for k, v in BASE.items()}
    data.update(extra)
    try:
        sim = Simulation.from_dict(data)
    except scene_mod.SceneError as exc:  # a key this variant needs is named in the message
        raise AssertionError(str(exc)) from None
    sim.step(steps)
    return sim


KERNELS = (K.advance, K.compute_forces, K.after_build, K.drift, K.kick_guard, K.heat_phase, K.outside,
           H.heat_step, H._implicit_step, H._trbdf2_step, H._implicit_assemble, H._implicit_totals,
           IM.jacobi_pcg, IM.laplacian_apply, NB.build_half_list)


def test_every_scene_shares_one_kernel_per_heat_switch():
    for path in sorted(glob.glob(os.path.join(ROOT, "examples", "*.toml"))
                       + glob.glob(os.path.join(ROOT, "tests", "scenes", "*.toml"))):
        Simulation.from_file(path).step(5)
    for name, extra in _variants():
        sim = _run_variant(extra)
        assert np.all(np.isfinite(sim.state.position)), name
    sim = _run_variant({"thermal": {"initial_temperature": 300.0, "direct": "batchelor_obrien"}})
    sim.set_fluid(force=np.full((sim.state.n_owned, 3), 1e-9), velocity=np.zeros((sim.state.n_owned, 3)),
                  temperature=np.full(sim.state.n_owned, 310.0))
    sim.step(10)
    # fluid torque (implicit rotational drag) and virtual mass (added mass) of a coupled run
    sim = _run_variant({})
    n = sim.state.n_owned
    sim.set_fluid(force=np.full((n, 3), 1e-9), drag=np.full(n, 1e-6), torque=np.full((n, 3), 1e-12),
                  torque_drag=np.full(n, 1e-12), added_mass=np.full(n, 1e-9))
    sim.step(10)
    assert np.all(np.isfinite(sim.state.angular_velocity))
    assert len(K.advance.signatures) >= 1  # every run calls advance (its phases, serial or MPI)
    for k in KERNELS:  # (a phase called only inside advance has no signature of its own when
        # advance came from the cache, one per heat switch when it was compiled here; advance and
        # compute_forces one per heat switch, form (lean or full: dem.step.full_form) and
        # tangential model (dem.stepper.Stepper.ton))
        sigs = k.signatures
        switches = 3 if k in (K.advance, K.compute_forces) else 1
        assert len(sigs) <= 2 ** switches, (k.py_func.__name__, len(sigs), sigs)
        for a in sigs:  # any two differ in the switches alone (types none / bool)
            for b in sigs:
                diff = [i for i, (x, y) in enumerate(zip(a, b)) if x != y]
                assert len(diff) <= switches and all({str(a[i]), str(b[i])} == {"none", "bool"} for i in diff), (
                    k.py_func.__name__, a, b)
