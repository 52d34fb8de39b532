"""Where a step of the discharging hopper goes (docs/benchmarks.md, "Hopper discharge"): the
D = 8 mm scene of examples/hopper_discharge.toml run to t = 0.15 s (the beads flowing), then the
step's particle-steps per second on one thread against the mesh pre-pass alone
(dem.contact.mesh.mesh_contacts, called on the same state), and how many beads are within reach
of the mesh.

    python3 benchmarks/hopper_profile.py [--steps 4000]
"""
import argparse
import os
import sys
import tempfile
import time

import numpy as np

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
sys.path.insert(0, ROOT)

from dem import Simulation  # noqa: E402
from dem import step as K  # noqa: E402
from dem.contact import mesh as M  # noqa: E402


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--steps", type=int, default=4000)
    a = ap.parse_args(argv)
    src = open(os.path.join(ROOT, "examples", "hopper_discharge.toml")).read().replace(
        "data/discharge_D8.stl", os.path.join(ROOT, "examples", "data", "discharge_D8.stl"))
    with tempfile.TemporaryDirectory() as tmp:
        f = os.path.join(tmp, "hopper.toml")
        open(f, "w").write(src)
        sim = Simulation.from_file(f)
    sim.set_threads(1)
    sim.warmup()
    flow = sim.world.flow
    flow.advance(sim, int(round(0.15 / sim.dt)))   # the outlet checks on the way, as a run does them
    st = sim.state
    n0 = st.n_owned
    t0 = time.perf_counter()
    flow.advance(sim, a.steps)
    step_s = (time.perf_counter() - t0) / a.steps
    P, C, W, TB, prm = st.bundles()
    t0 = time.perf_counter()
    for _ in range(a.steps // 4):
        M.mesh_contacts(P, W, st.n_owned, prm.fp[K.FP.reach], 0.0, sim.time, False, False)
    pre = (time.perf_counter() - t0) / (a.steps // 4)
    near = int(np.count_nonzero(st.wnn[:st.n_owned] > 0))
    print(f"beads {n0}, within reach of the mesh {near}; step {step_s * 1e6:.0f} us "
          f"({n0 / step_s:.3g} particle-steps/s), mesh pre-pass {pre * 1e6:.0f} us ({100 * pre / step_s:.0f} %, "
          f"{pre / max(near, 1) * 1e9:.0f} ns per bead near the mesh)")


if __name__ == "__main__":
    main()
