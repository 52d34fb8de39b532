"""How the interact phase's time depends on the neighbour slots per row (the contact history's
bytes), on a shared bed:

    python benchmarks/slot_capacity.py --bed 50k --slots 6 12 24

Loads the bed, steps 5 times, then times the interact phase alone (``PH_FORCES``, 100 steps in
one compiled call, best of 3) on copies of the pair arrays padded to each slot count (more
slots: the same pairs, more bytes between rows) or cut to it (fewer slots than the largest row:
the rows' last pairs left out, so the time is given per candidate pair, not per particle).
Three rounds, in turn. Prints ns per candidate pair and step for each slot count.
"""
import argparse
import os
import sys
import time

import numpy as np

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
sys.path.insert(0, ROOT)

from dem import Simulation  # noqa: E402
from dem import schema as S  # noqa: E402
from dem import step as K  # noqa: E402


def _resized(a, n, slots):
    """A copy of a pair array (n, slots_now, ...) with ``slots`` slots (zeros beyond the old ones)."""
    if a.ndim < 2 or a.shape[0] != n:
        return a
    shape = list(a.shape)
    shape[1] = slots
    b = np.zeros(shape, a.dtype)
    k = min(slots, a.shape[1])
    b[:, :k] = a[:, :k]
    return b


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--bed", default="50k", help="10k, 50k, heat_10k or heat_50k (benchmarks/shared_bed_*.toml)")
    ap.add_argument("--slots", type=int, nargs="+", default=[6, 12, 24])
    ap.add_argument("--steps", type=int, default=100)
    ap.add_argument("--rounds", type=int, default=3)
    a = ap.parse_args()
    sim = Simulation.from_file(os.path.join(ROOT, "benchmarks", f"shared_bed_{a.bed}.toml"))
    sim.set_threads(1)
    sim.step(5)
    stp = sim.stepper
    st = stp.state
    s0 = sim.world.step_count - 1
    names = ("nb", "hist", "Hd", "Hi", "rnear")
    base = {f: getattr(st, f).copy() for f in names + ("nnb",)}
    print(f"{a.bed}: {st.n} particles, {base['nb'].shape[1]} slots, "
          f"{base['nnb'][:st.n].mean():.2f} candidates per row (largest {base['nnb'].max()})")
    res = {c: [] for c in a.slots}
    for _ in range(a.rounds):
        for c in a.slots:
            pairs = S.Pairs(*[_resized(base[f], st.n, c) if f in names else getattr(st, f) for f in S.Pairs._fields])
            pairs = pairs._replace(nnb=np.minimum(base["nnb"], c).astype(base["nnb"].dtype))
            stp.set_pairs(pairs)
            stp._entry = None
            best = np.inf
            for _ in range(3):
                t0 = time.perf_counter()
                stp.phases(K.PH_FORCES, nsteps=a.steps, s0=s0)
                best = min(best, time.perf_counter() - t0)
            res[c].append(best / a.steps / int(pairs.nnb[:st.n].sum()) * 1e9)
    for c in a.slots:
        print(f"{c:3d} slots: " + " ".join(f"{v:.1f}" for v in res[c]) + " ns per candidate pair and step")


if __name__ == "__main__":
    main()
