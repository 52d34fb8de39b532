"""Parallel speed-up on the shared settled beds: our DEM on 1 and 2 MPI ranks, and
LIGGGHTS (Debian's package) on 2 processes, same scene, same step count, same session.

    python benchmarks/scaling.py [--sizes 50k] [--steps 10000] [--liggghts] [--ranks 1 2]

Prints particle-steps per second of the time loop (start-up excluded: our "done" line, the
LIGGGHTS "Loop time"), the speed-up of 2 ranks over 1, the ghost fraction and the halo
traffic per step (the inputs of docs/scaling.md).
"""
import argparse
import os
import re
import subprocess
import tempfile
import sys

HERE = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, HERE)
from shared_scene import liggghts_cmd, parse_loop  # noqa: E402

ENV = dict(os.environ, OMPI_ALLOW_RUN_AS_ROOT="1", OMPI_ALLOW_RUN_AS_ROOT_CONFIRM="1",
           OMPI_MCA_rmaps_base_oversubscribe="1")


def ours(size, heat, steps, ranks, threads=1):
    """Our run of the shared bed on ``ranks`` MPI ranks of ``threads`` threads each (one process
    without mpirun when ranks == 1 and threads > 1)."""
    scene = os.path.join(HERE, f"shared_bed{'_heat' if heat else ''}_{size}.toml")
    with tempfile.TemporaryDirectory(prefix=f"scaling_{size}_{heat}_{ranks}_") as tmp:  # ours alone
        out = os.path.join(tmp, "out")
        launch = [] if ranks == 1 and threads > 1 else ["mpirun", "-np", str(ranks)]
        cmd = launch + [sys.executable, "-m", "dem", "run", scene, "--end-time",
                        repr(steps * 1e-5), "--out", out, "--quiet", "--threads", str(threads)]
        p = subprocess.run(cmd, capture_output=True, text=True, env=ENV)
    if p.returncode:
        raise SystemExit(p.stdout + p.stderr)
    pps = float(re.search(r"([0-9.e+]+) particle-steps/s", p.stdout).group(1))
    r = dict(pps=pps)
    m = re.search(r"parallel: (\d+) ghosts \(([0-9.]+) %.*halo traffic ([0-9.]+) KiB per step in (\d+) messages",
                  p.stdout)
    if m:
        r.update(ghosts=int(m.group(1)), ghost_pct=float(m.group(2)), halo_kib=float(m.group(3)),
                 messages=int(m.group(4)))
    return r


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--sizes", nargs="+", default=["50k"])
    ap.add_argument("--steps", type=int, default=10000)
    ap.add_argument("--ranks", nargs="+", type=int, default=[1, 2])
    ap.add_argument("--liggghts", action="store_true")
    ap.add_argument("--no-heat", action="store_true")
    args = ap.parse_args()
    n_of = {"10k": 10000, "50k": 50000}
    print("| scene | heat | ranks | ours particle-steps/s | speed-up | ghosts | halo KiB/step | "
          "LIGGGHTS 2 proc particle-steps/s | ours / LIGGGHTS |")
    print("|---|---|---|---|---|---|---|---|---|")
    for size in args.sizes:
        for heat in ([False] if args.no_heat else [False, True]):
            base = None
            lig = None
            if args.liggghts:
                res = subprocess.run(liggghts_cmd(size, heat, args.steps, nproc=2), capture_output=True, text=True)
                lig = n_of[size] * args.steps / parse_loop(res.stdout)
            for nr in args.ranks:
                r = ours(size, heat, args.steps, nr)
                base = base or r["pps"]
                lig_s = f"{lig:.3g}" if (lig and nr == 2) else ""
                ratio = f"{r['pps'] / lig:.2f}" if (lig and nr == 2) else ""
                print(f"| {size} | {'on' if heat else 'off'} | {nr} | {r['pps']:.3g} | {r['pps'] / base:.2f} | "
                      f"{r.get('ghosts', 0)} ({r.get('ghost_pct', 0):.1f} %) | {r.get('halo_kib', 0):.0f} | "
                      f"{lig_s} | {ratio} |", flush=True)


if __name__ == "__main__":
    main()
