"""Coupled run on M DEM ranks x N gas processes: speed, bytes per rank per coupling step and
peak memory per rank (the many-to-many exchange: coupling.cells, coupling.m2m).

    python benchmarks/coupled_scaling.py [--case fluidized_bed_cg] [--dem 1,2,4,8] [--gas 1,2,4]
                                         [--end-time 0.005] [--json out.json] [--gas-axis x]

Each layout runs ``mpirun -np M python -m coupling.run run CASE`` with ``gas_processes = N``
(oversubscribed when M + N exceeds the cores: the byte and memory figures do not depend on
it, the times do) and reads its timings.json. Printed per layout:

* particle-steps/s of the coupled loop and wall time per coupling step;
* per DEM rank (largest and smallest over the ranks): the gas cells it owns, the halo cells
  it shares with other DEM ranks, the cells of its local mesh (of the mesh's cells) and the
  bytes that mesh holds (geometry, connectivity, location tables: coupling.mesh.PolyMesh.
  nbytes), the bytes it sends to the gas and to other DEM ranks per coupling step, its peak
  resident memory (MiB);
* at set-up, per DEM rank: the cells it read (the whole mesh, or with gas_processes > 1 the
  gas pieces around its box: coupling.pieces), the bytes of that mesh and the peak resident
  memory at the end of the set-up.

The (1, 1) layout takes the one-frame socket exchange (every cell in one frame, the same
bytes).
"""
from __future__ import annotations

import argparse
import json
import os
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
CASES = ROOT / "openfoam_cases"


def run_layout(case: str, m: int, n: int, end: float, work: Path, gas_axis: str | None = None) -> dict:
    src = CASES / case
    dst = work / f"case_{m}x{n}"
    shutil.copytree(src, dst, ignore=shutil.ignore_patterns("README.md"))
    t = dst / "coupling.toml"
    t.write_text(t.read_text().replace("[coupling]\n", f"[coupling]\ngas_processes = {n}\n", 1))
    if gas_axis:   # the gas in n slabs across this axis (decomposeParDict's simple split)
        import re
        d = dst / "system" / "decomposeParDict"
        split = " ".join(str(n) if a == gas_axis else "1" for a in "xyz")
        d.write_text(re.sub(r"(\bn\s+)\([^)]*\)", rf"\g<1>({split})", d.read_text()))
    out = work / f"out_{m}x{n}"
    cmd = [sys.executable, "-m", "coupling.run", "run", str(dst), "--out", str(out), "--end-time", repr(end),
           "--quiet"]
    if m > 1:
        cmd = ["mpirun", "-np", str(m)] + cmd
    env = dict(os.environ, OMPI_ALLOW_RUN_AS_ROOT="1", OMPI_ALLOW_RUN_AS_ROOT_CONFIRM="1",
               OMPI_MCA_rmaps_base_oversubscribe="1", OMPI_MCA_mpi_yield_when_idle="1")
    p = subprocess.run(cmd, capture_output=True, text=True, env=env, cwd=str(ROOT))
    if p.returncode != 0:
        raise SystemExit(f"{' '.join(cmd)} failed ({p.returncode}):\n{p.stdout[-2000:]}\n{p.stderr[-2000:]}")
    tm = json.loads((out / "timings.json").read_text())
    steps = max(int(tm["coupling_steps"]), 1)
    ranks = tm["ranks"]
    per = [dict(owned=r["owned_cells"], halo=r["halo_cells"], gas_b=r["gas_bytes_sent"] / steps,
                dem_b=r["dem_bytes_sent"] / steps, rss=r["peak_rss_mib"], local=r.get("local_cells"),
                mesh_b=r.get("mesh_bytes"), setup_cells=r.get("setup_cells_read"),
                setup_mesh_b=r.get("setup_mesh_bytes"), setup_rss=r.get("setup_peak_rss_mib"),
                setup_pieces=r.get("setup_pieces_read")) for r in ranks]
    return dict(dem=m, gas=n, steps=steps, particles=tm["particles"], pss=tm["particle_steps_per_s"],
                loop_per_step=tm["loop"] / steps, ranks=per)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--case", default="fluidized_bed_cg")
    ap.add_argument("--dem", default="1,2,4,8")
    ap.add_argument("--gas", default="1,2,4")
    ap.add_argument("--end-time", type=float, default=0.005)
    ap.add_argument("--json", default=None)
    ap.add_argument("--gas-axis", choices=["x", "y", "z"], default=None,
                    help="decompose the gas in slabs across this axis (default: the case's decomposeParDict)")
    a = ap.parse_args(argv)
    rows = []
    with tempfile.TemporaryDirectory(prefix="coupled_scaling_") as tmp:
        for n in [int(x) for x in a.gas.split(",")]:
            for m in [int(x) for x in a.dem.split(",")]:
                r = run_layout(a.case, m, n, a.end_time, Path(tmp), a.gas_axis)
                rows.append(r)
                rk = r["ranks"]
                print(f"DEM {m} x gas {n}: {r['pss']:.3g} particle-steps/s, {1e3 * r['loop_per_step']:.1f} ms per "
                      f"coupling step; per DEM rank: owned cells {min(x['owned'] for x in rk)}-"
                      f"{max(x['owned'] for x in rk)}, halo cells {max(x['halo'] for x in rk)}, "
                      + (f"local cells {min(x['local'] for x in rk)}-{max(x['local'] for x in rk)} of "
                         f"{sum(x['owned'] for x in rk)} (mesh {min(x['mesh_b'] for x in rk) / 1024:.0f}-"
                         f"{max(x['mesh_b'] for x in rk) / 1024:.0f} KiB), " if rk[0]["local"] is not None else "")
                      + f"to gas {max(x['gas_b'] for x in rk) / 1024:.1f} KiB/step, "
                      f"to DEM ranks {max(x['dem_b'] for x in rk) / 1024:.1f} KiB/step, "
                      f"peak RSS {max(x['rss'] for x in rk):.0f} MiB", flush=True)
                if rk[0]["setup_cells"] is not None:   # set-up: the mesh a rank read before dropping it
                    print(f"  set-up per DEM rank: cells read {min(x['setup_cells'] for x in rk)}-"
                          f"{max(x['setup_cells'] for x in rk)} of {sum(x['owned'] for x in rk)} "
                          f"({'pieces' if rk[0]['setup_pieces'] else 'the whole mesh'}), mesh "
                          f"{min(x['setup_mesh_b'] for x in rk) / 1024:.0f}-{max(x['setup_mesh_b'] for x in rk) / 1024:.0f}"
                          f" KiB, peak RSS {min(x['setup_rss'] for x in rk):.0f}-{max(x['setup_rss'] for x in rk):.0f}"
                          " MiB", flush=True)
    if a.json:
        Path(a.json).write_text(json.dumps(rows, indent=1))


if __name__ == "__main__":
    main()
