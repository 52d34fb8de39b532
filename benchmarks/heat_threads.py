"""The heat step on threads: the shared 50k heat bed with each kind of per-particle heat link
switched on, its interact phase (pairs, walls, fused conduction) and its heat step timed on 1 and
on 2 threads.

    python benchmarks/heat_threads.py                    # every variant, 15 repeats
    python benchmarks/heat_threads.py --variants convection --repeats 30

Variants of benchmarks/shared_bed_heat_50k.toml (contact conduction, Euler fused into the force
loop, as the LIGGGHTS comparison):

* ``conduction``: the bed as it is (the heat step is one pass over the rows);
* ``convection``: gas convection (Gunn 1978) with a gas at 350 K rising at 0.5 m/s, local
  porosity, a source of 1 mW per particle;
* ``exponential``: the same with the exponential integrator (pair sweeps serial by design) and
  the floor held at 500 K;
* ``radiation``: radiation to the environment (Zhou 2009, emissivity 0.8) and a radiating floor
  at 500 K (emissivity 0.7);
* ``frozen_implicit``, ``frozen_trbdf2``: the bed frozen (``mechanics = false``), a thermal step of
  0.01 s, the floor at 500 K, backward Euler or TR-BDF2 (conjugate gradients; the interact
  columns are then not timed).

Each figure is the best of ``--repeats`` calls of the one phase from the same state (in ns per
particle: the phase's time over the owned particles), after 20 steps on the thread count timed.
The machine is shared: compare the two thread counts of one line, not lines of different runs.
"""
import argparse
import os
import sys
import time
import tomllib

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
sys.path.insert(0, ROOT)

from dem import Simulation  # noqa: E402
from dem import step as K  # noqa: E402

SCENE = os.path.join(ROOT, "benchmarks", "shared_bed_heat_50k.toml")
GAS = {"conductivity": 0.026, "density": 1.2, "viscosity": 1.8e-5, "heat_capacity": 1005.0,
       "temperature": 350.0}


def variant(name):
    """The scene of one variant (a dict for Simulation.from_dict)."""
    with open(SCENE, "rb") as fh:
        data = tomllib.load(fh)
    th = data["thermal"]
    floor = data["walls"][4]
    if name in ("convection", "exponential"):
        th.update(convection="gunn", porosity="local", integrator="euler",
                  sources=[{"group": 0, "power": 1e-3}])
        data["gas"] = dict(GAS, velocity=[0.0, 0.0, 0.5])
    if name == "exponential":
        th["integrator"] = "exponential"
        floor["thermal"] = {"condition": "fixed_temperature", "temperature": 500.0}
    if name.startswith("frozen_"):
        data["simulation"]["mechanics"] = False
        th.update(integrator=name.split("_", 1)[1], time_step=0.01)
        floor["thermal"] = {"condition": "fixed_temperature", "temperature": 500.0}
    if name == "radiation":
        th.update(radiation="zhou_2009", integrator="euler")
        data["materials"][0]["emissivity"] = 0.8
        data["gas"] = {"temperature": 350.0}
        floor["thermal"] = {"condition": "fixed_temperature", "temperature": 500.0, "emissivity": 0.7}
    return data


def best(sim, phase, repeats):
    n = sim.state.n_owned
    b = float("inf")
    for _ in range(repeats):
        t0 = time.perf_counter()
        sim.stepper.phases(phase)
        b = min(b, time.perf_counter() - t0)
    return b / n * 1e9


def main(argv=None):
    names = ("conduction", "convection", "exponential", "radiation", "frozen_implicit", "frozen_trbdf2")
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--variants", nargs="+", choices=names, default=list(names))
    ap.add_argument("--repeats", type=int, default=15)
    a = ap.parse_args(argv)
    print("| variant | interact, 1 thread | interact, 2 threads | heat step, 1 thread | heat step, 2 threads "
          "| heat step 1/2 |")
    print("|---|---|---|---|---|---|")
    for name in a.variants:
        row = {}
        for th in (1, 2):
            sim = Simulation.from_dict(variant(name), base_dir=os.path.dirname(SCENE), name=name)
            sim.set_threads(th)
            frozen = name.startswith("frozen_")
            sim.step(3 if frozen else 20)
            row[th] = (float("nan") if frozen else best(sim, K.PH_FORCES, a.repeats),
                       best(sim, K.PH_HEAT, 5 if frozen else a.repeats))
        cells = " | ".join("-" if v != v else f"{v:.1f}" for v in (row[1][0], row[2][0]))
        print(f"| {name} | {cells} | {row[1][1]:.1f} | {row[2][1]:.1f} | {row[1][1] / row[2][1]:.2f} |", flush=True)


if __name__ == "__main__":
    main()
