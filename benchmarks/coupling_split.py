"""Split of the wall time of the coupled fluidized bed (socket and file transports).

    python benchmarks/coupling_split.py [--end-time 0.1] [--out /tmp/coupling_split]
                                        [--write-docs]

Runs openfoam_cases/fluidized_bed_heating with each transport (one after the other) and
prints, per phase, the wall time and its share of the coupled loop:

* dem            DEM steps (sim.step), run while the gas solver solves the same interval
* gas_wait       time blocked waiting for the solver's frame (gas slower than the DEM)
* exchange       encoding and sending the DEM -> CFD frame
* locate         particle location (hint = previous cell)
* void_fraction  stencil + solid volume per cell
* interpolation  gas fields at the particles
* exchange_terms drag, forces, h A, Ksl/Us/Simp/Sexp accumulation
* output         history/VTK/checkpoints

"coupling" = locate + void_fraction + interpolation + exchange_terms + exchange.
The gas solver's own time overlaps with the DEM; it shows up only as gas_wait.
With --write-docs the table is appended to docs/benchmarks.md under
"## Coupled fluidized bed" (replacing an earlier table of that heading).
"""
from __future__ import annotations

import argparse
import os
import platform
import re
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

COUPLING = ("locate", "void_fraction", "interpolation", "exchange_terms", "exchange")


def run(transport, end_time, out):
    from coupling.run import run_case
    # overwrite: replaces this benchmark's earlier output there, never anything else (dem.outdir)
    return run_case(ROOT / "openfoam_cases" / "fluidized_bed_heating", Path(out) / transport,
                    transport=transport, end_time=end_time, quiet=True, overwrite=True)


def table(results, end_time) -> str:
    phases = list(next(iter(results.values()))["phases"])
    head = "| phase | " + " | ".join(f"{t} [s] | {t} [%]" for t in results) + " |"
    sep = "|---|" + "---|---|" * len(results)
    rows = [head, sep]
    for p in phases:
        cells = []
        for s in results.values():
            v = s["phases"][p]
            cells.append(f"{v:.2f} | {100 * v / s['loop']:.1f}")
        rows.append(f"| {p} | " + " | ".join(cells) + " |")
    for label, f in (("**coupling** (locate+vf+interp+terms+send)",
                      lambda s: sum(s["phases"][p] for p in COUPLING)),):
        rows.append(f"| {label} | " + " | ".join(
            f"{f(s):.2f} | {100 * f(s) / s['loop']:.1f}" for s in results.values()) + " |")
    rows.append("| coupled loop | " + " | ".join(f"{s['loop']:.2f} | 100" for s in results.values()) + " |")
    rows.append("| particle-steps/s | " + " | ".join(
        f"{s['particle_steps_per_s']:.3g} | " for s in results.values()) + " |")
    s0 = next(iter(results.values()))
    info = (f"{s0['particles']} particles, {s0['coupling_steps']} coupling steps x "
            f"{s0['dem_steps'] // max(s0['coupling_steps'], 1)} DEM steps (t = {end_time:g} s), "
            f"600 gas cells (serial thermoDemFoam), {os.cpu_count()} cores ({platform.machine()}), "
            "shared with other jobs")
    return info, "\n".join(rows)


def write_docs(info, tab, cmd):
    doc = ROOT / "docs" / "benchmarks.md"
    text = doc.read_text() if doc.exists() else "# Benchmarks\n"
    section = (f"## Coupled fluidized bed\n\n`{cmd}`\n\n{info}.\n\n{tab}\n\n"
               "The DEM and the gas solver run concurrently over each coupling interval (the gas "
               "solve is hidden behind the DEM unless it is slower: then it appears as gas_wait); "
               "locating and the void fraction of the next step are computed right after the DEM "
               "interval, also while the solver is still busy.\n")
    pat = re.compile(r"## Coupled fluidized bed\n.*?(?=\n## |\Z)", re.S)
    if pat.search(text):
        text = pat.sub(section.rstrip("\n"), text)
    else:
        text = text.rstrip("\n") + "\n\n" + section
    doc.write_text(text)
    return doc


def main(argv=None):
    ap = argparse.ArgumentParser()
    ap.add_argument("--end-time", type=float, default=0.1)
    ap.add_argument("--out", default="/tmp/coupling_split")
    ap.add_argument("--transports", default="socket,file")
    ap.add_argument("--write-docs", action="store_true")
    a = ap.parse_args(argv)
    res = {}
    for tr in a.transports.split(","):
        res[tr] = run(tr, a.end_time, a.out)
        print(f"{tr}: loop {res[tr]['loop']:.2f} s, wall {res[tr]['wall_total']:.2f} s", flush=True)
    info, tab = table(res, a.end_time)
    print(info)
    print(tab)
    if a.write_docs:
        cmd = "python benchmarks/coupling_split.py " + " ".join(argv if argv is not None else sys.argv[1:])
        print("written to", write_docs(info, tab, cmd.strip()))


if __name__ == "__main__":
    main()
