"""What the drag's local void fraction costs the main example's coupled loop (issue 51 item 1).

    python3 benchmarks/drag_void_cost.py [--end-time 0.3] [--pairs 2] [--methods cell,voronoi]

Runs `coupling run openfoam_cases/fluidized_bed_heating` (3,000 beads, coupling every 50 DEM
steps) to --end-time with each drag_void_fraction in turn, A B A B ... (a drift of the machine's
speed then falls on both), each in a fresh output folder in a temporary directory, and reads the
loop's time and its phases from each run's timings.json (set-up, compile and final output
excluded). Prints each pair's loop times, the ratio to the first method pair by pair and its
median, the void_fraction phase per particle and coupling step, and the bed's mean temperature
at the end (the methods change the drag, so the bed's state, a little).
"""
import argparse
import json
import os
import shutil
import statistics
import subprocess
import sys
import tempfile
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
CASE = ROOT / "openfoam_cases" / "fluidized_bed_heating"


def run(tmp, method, end, k):
    case = Path(tmp) / f"case_{method}"
    if not case.exists():
        shutil.copytree(CASE, case)
        t = case / "coupling.toml"
        t.write_text(t.read_text().replace("[coupling]\n", f'[coupling]\ndrag_void_fraction = "{method}"\n', 1))
    out = Path(tmp) / f"out_{method}_{k}"
    p = subprocess.run([sys.executable, "-m", "coupling.run", "run", str(case), "--out", str(out),
                        "--end-time", str(end), "--quiet"], cwd=ROOT, capture_output=True, text=True)
    if p.returncode != 0:
        sys.exit(f"coupling run ({method}) failed:\n{p.stderr[-2000:]}")
    tm = json.loads((out / "timings.json").read_text())
    shutil.rmtree(out, ignore_errors=True)
    return tm


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--end-time", type=float, default=0.3)
    ap.add_argument("--pairs", type=int, default=2)
    ap.add_argument("--methods", default="cell,voronoi")
    a = ap.parse_args()
    methods = a.methods.split(",")
    with tempfile.TemporaryDirectory() as tmp:
        for m in methods:   # a first run of each fills the kernel cache for it (not counted)
            run(tmp, m, 0.002, "warm")
        ratios = {m: [] for m in methods[1:]}
        for k in range(a.pairs):
            tms = {m: run(tmp, m, a.end_time, k) for m in methods}
            base = tms[methods[0]]["loop"]
            cells = []
            for m in methods:
                tm = tms[m]
                per = tm["phases"]["void_fraction"] / (tm["coupling_steps"] * tm["particles"]) * 1e6
                cells.append(f"{m} {tm['loop']:.2f} s (void_fraction {tm['phases']['void_fraction']:.2f} s, "
                             f"{per:.2f} us a particle and coupling step)")
                if m != methods[0]:
                    ratios[m].append(tm["loop"] / base)
            print(f"pair {k + 1}: " + "; ".join(cells), flush=True)
        for m, r in ratios.items():
            print(f"{m} / {methods[0]}: coupled loop ratio median {statistics.median(r):.3f} "
                  f"(pairs {', '.join(f'{x:.3f}' for x in r)}), to t = {a.end_time:g} s")


if __name__ == "__main__":
    main()
