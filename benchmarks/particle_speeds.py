"""Largest particle speed of a coupled run, from its VTK output, and the particle Courant
number it gives (the measurement behind the particle Courant rule, docs/models.md "Checks").

    coupling run openfoam_cases/fluidized_bed_heating --out out/fb        # vtk = true in dem.toml
    python benchmarks/particle_speeds.py out/fb --cell 0.006 [--split 0.12]

Prints, for every VTK output, the largest |v| and its 99th percentile; then the largest |v| before
and after ``--split`` seconds (e.g. the end of the collapse of a loose insertion) and the particle
Courant number max|v| x deltaT / cell for the run's deltaT (its system/controlDict) and any
``--dt`` given.
"""
from __future__ import annotations

import argparse
import glob
import os
import sys

import numpy as np

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
if ROOT not in sys.path:
    sys.path.insert(0, ROOT)


def speeds(out: str):
    import meshio
    rows = []
    for f in sorted(glob.glob(os.path.join(out, "vtk", "particles_*.vtu"))):
        m = meshio.read(f)
        s = np.linalg.norm(m.point_data["velocity"], axis=1)
        rows.append((int(os.path.basename(f)[10:-4]), float(s.max()), float(np.percentile(s, 99))))
    return rows


def main(argv=None) -> int:
    from coupling.case import control
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("out", help="output folder of a coupled run (with vtk/)")
    ap.add_argument("--cell", type=float, required=True, help="smallest cell edge (m)")
    ap.add_argument("--split", type=float, default=None, help="report before / after this time (s)")
    ap.add_argument("--dt", type=float, action="append", default=[], help="other coupling steps (s)")
    a = ap.parse_args(argv)
    dt_dem = None
    import dem
    ctl = control(a.out)
    sim = dem.Simulation.from_file(os.path.join(a.out, "dem.toml"), end_time=ctl["endTime"])
    dt_dem = sim.dt
    rows = speeds(a.out)
    if not rows:
        print(f"no VTK output in {a.out}/vtk")
        return 1
    for step, vmax, p99 in rows:
        print(f"t = {step * dt_dem:8.4f} s  max |v| = {vmax:.3f} m/s  99th percentile {p99:.3f} m/s")
    parts = [("all", rows)]
    if a.split is not None:
        parts += [(f"t <= {a.split:g} s", [r for r in rows if r[0] * dt_dem <= a.split]),
                  (f"t > {a.split:g} s", [r for r in rows if r[0] * dt_dem > a.split])]
    for label, rs in parts:
        if not rs:
            continue
        v = max(r[1] for r in rs)
        cos = ", ".join(f"{v * dt / a.cell:.3g} at {dt:g} s" for dt in [ctl["deltaT"]] + a.dt)
        print(f"{label}: max |v| = {v:.3f} m/s; particle Courant number {cos}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
