"""A frozen packed bed of about 9,000 glass spheres of 6.4 mm heated from its floor for
4,000 s of physical time (thermal-only run, mechanics = false).

    python benchmarks/packed_bed_heating.py [--dt 2.0] [--reference-dt 0.25]

The packing is the shared settled 10k bed (benchmarks/packings/settled_10k.npz)
scaled from 1 mm to 3.2 mm radius, cut to the particles below 88 % of its height. Floor
at 400 K, other walls adiabatic, bed initially at 300 K; Batchelor & O'Brien contact
conduction (Hertz-overlap contact radius) plus Voronoi gas conduction (Cheng 1999, local
porosity) in air. Prints the wall time of the run (start-up excluded and reported
separately), particle-steps/s, and the error of the final temperatures against a run with
a smaller step.
"""
import argparse
import os
import sys
import tempfile
import time

import numpy as np

HERE = os.path.dirname(os.path.abspath(__file__))
PACKING = os.path.join(HERE, "packings", "settled_10k.npz")
SCALE = 3.2


def make_scene(tmp, dt, end=4000.0):
    d = np.load(PACKING)
    x = np.stack([d["x"], d["y"], d["z"]], 1) * SCALE
    r = d["radius"] * SCALE
    keep = x[:, 2] < 0.88 * x[:, 2].max()
    path = os.path.join(tmp, "bed.npz")
    np.savez(path, x=x[keep, 0], y=x[keep, 1], z=x[keep, 2], radius=r[keep])
    L = 0.04 * SCALE
    H = float(x[keep, 2].max() + 2 * r.max())
    walls = [dict(type="plane", name="floor", point=[0, 0, 0], normal=[0, 0, 1], material="glass",
                  thermal={"condition": "fixed_temperature", "temperature": 400.0})]
    for p, nrm in (([0, 0, 0], [1, 0, 0]), ([L, 0, 0], [-1, 0, 0]), ([0, 0, 0], [0, 1, 0]), ([0, L, 0], [0, -1, 0])):
        walls.append(dict(type="plane", point=p, normal=nrm, material="glass"))
    return {
        "simulation": {"time_step": 1e-5, "end_time": end, "mechanics": False, "output_interval": end},
        "domain": {"min": [0, 0, 0], "max": [L, L, H]},
        "materials": [dict(name="glass", density=2500.0, youngs_modulus=5e6 * SCALE ** 0, poisson_ratio=0.3,
                           restitution=0.9, friction=0.3, thermal_conductivity=1.0, heat_capacity=840.0)],
        "particles": [{"material": "glass", "file": path}],
        "walls": walls,
        "gas": {"conductivity": 0.026, "density": 1.2, "viscosity": 1.8e-5, "heat_capacity": 1005.0,
                "temperature": 300.0},
        "thermal": {"direct": "batchelor_obrien", "indirect": "voronoi_a", "time_step": dt,
                    "initial_temperature": 300.0},
    }


def run(dt, tmp):
    from dem import Simulation
    t0 = time.perf_counter()
    sim = Simulation.from_dict(make_scene(tmp, dt), base_dir=tmp)
    sim.warmup()
    setup = time.perf_counter() - t0
    t0 = time.perf_counter()
    sim.run(progress=False)
    wall = time.perf_counter() - t0
    order = np.argsort(sim.state.id)
    return sim, setup, wall, sim.state.temperature[order].copy()


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--dt", type=float, default=2.0)
    ap.add_argument("--reference-dt", type=float, default=0.25)
    args = ap.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        t_all = time.perf_counter()
        sim, setup, wall, T = run(args.dt, tmp)
        total = time.perf_counter() - t_all
        n = sim.state.n
        steps = sim.step_count
        print(f"{n} spheres of 6.4 mm, {sim.time:.0f} s of heating with dt = {args.dt} s ({steps} steps, "
              f"{sim.thermal.cfg['integrator']}): run {wall:.2f} s, start-up {setup:.2f} s, whole {total:.2f} s, "
              f"{n * steps / wall:.3g} particle-steps/s")
        print(f"mean bed temperature {T.mean():.4f} K, floor heat {sim.thermal.wtot[0]:.2f} J, "
              f"energy balance: sum(m c (T - 300 K)) - floor heat = "
              f"{np.sum((sim.state.temperature - 300.0) / sim.state.inv_heat_capacity) - sim.thermal.wtot[0]:.2e} J")
        if args.reference_dt:
            _, _, wref, Tref = run(args.reference_dt, tmp)
            err = np.abs(T - Tref).max() / (400 - 300)
            print(f"reference dt = {args.reference_dt} s ({wref:.1f} s): max |T - T_ref| / (400 K - 300 K) = {err:.2e}, "
                  f"mean-temperature difference {abs(T.mean() - Tref.mean()):.2e} K")


if __name__ == "__main__":
    sys.exit(main())
