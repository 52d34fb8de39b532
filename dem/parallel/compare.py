"""Compare two runs of the same scene output by output (e.g. serial and MPI), by particle id.

    python -m dem.parallel.compare OUT_SERIAL OUT_MPI

prints, for every VTK output both runs wrote, the largest difference of position (m),
velocity (m/s) and temperature (K) over the particles, and how many particles each rank
owned in the second run (docs/reliability/mpi.md lists figures measured with it).
"""
import os
import re
import sys

import numpy as np


def snapshots(out_dir):
    """{step: dict(id, x, v, T, rank)} of every VTK output of a run (a serial frame or the pieces of
    every rank), rows ordered by id."""
    from ..output import read_frames
    snaps = {}
    for _, path, x, d in read_frames(out_dir):
        n = x.shape[0]
        snaps[int(re.findall(r"_(\d+)\.p?vtu$", path)[0])] = dict(
            id=d["id"], x=x, v=d["velocity"], T=d["temperature"] if "temperature" in d else np.zeros(n),
            rank=d["rank"] if "rank" in d else np.zeros(n))
    return snaps


def differences(a, b):
    """Largest |a - b| of position, velocity and temperature (same particle ids)."""
    if not np.array_equal(a["id"], b["id"]):
        raise ValueError("the two outputs hold different particles")
    return (float(np.abs(a["x"] - b["x"]).max()), float(np.abs(a["v"] - b["v"]).max()),
            float(np.abs(a["T"] - b["T"]).max()))


def main(argv=None):
    argv = sys.argv[1:] if argv is None else argv
    if len(argv) != 2:
        print(__doc__.strip().splitlines()[2].strip(), file=sys.stderr)
        return 2
    a, b = snapshots(argv[0]), snapshots(argv[1])
    common = sorted(set(a) & set(b))
    if not common:
        print(f"error: {argv[0]} and {argv[1]} have no VTK output of the same step", file=sys.stderr)
        return 2
    print("step        |dx| max (m)  |dv| max (m/s)  |dT| max (K)  particles per rank (2nd run)")
    nranks = 1 + int(max(b[s]["rank"].max(initial=0) for s in common))
    for s in common:
        dx, dv, dT = differences(a[s], b[s])
        per_rank = np.bincount(b[s]["rank"].astype(int), minlength=nranks).tolist()
        print(f"{s:<10d}  {dx:12.3g}  {dv:14.3g}  {dT:12.3g}  {per_rank}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
