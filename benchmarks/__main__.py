"""Every generated benchmark (docs/benchmarks.md and its pages), one after the other, in a bounded time.

    python -m benchmarks [--quick] [--no-docs] [--skip NAME ...]

Runs, each as its own process (a failure is reported and the others still run):

  accuracy    work-precision of every reference case, DEM, thermal and coupled
              (benchmarks/accuracy/run.py)
  stability   stress sweeps and the guard that stops each break (benchmarks/stability/run.py)
  cost        what each heat-transfer mechanism and the coupling cost (benchmarks/cost/run.py)
  liggghts    speed per core, on 2 processes, and temperatures against LIGGGHTS
              (benchmarks/liggghts_side_by_side.py; installs Debian's liggghts if missing)

Each writes its section (accuracy: docs/benchmarks/accuracy.md; stability: docs/benchmarks/stability.md;
cost and liggghts: docs/benchmarks.md) and its plots unless --no-docs. Full run: about 15 minutes on
the project's 2-core machine (856 s measured; each part's time is printed at the end); --quick 3
minutes (172 s measured). Logs: out/benchmarks/<name>.log. Exit status: 0 when every part
succeeded, 1 otherwise (a part exits 1 when, e.g., a stability run leaves NaN in its state).
"""
import argparse
import os
import subprocess
import sys
import time

HERE = os.path.dirname(os.path.abspath(__file__))
ROOT = os.path.dirname(HERE)

PARTS = {
    "accuracy": ["benchmarks/accuracy/run.py"],
    "stability": ["benchmarks/stability/run.py"],
    "cost": ["benchmarks/cost/run.py"],
    "liggghts": ["benchmarks/liggghts_side_by_side.py"],
}


def main(argv=None):
    ap = argparse.ArgumentParser(prog="python -m benchmarks", description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="shorter sweeps of every part")
    ap.add_argument("--no-docs", action="store_true", help="print only; do not write docs/")
    ap.add_argument("--skip", nargs="*", default=[], choices=list(PARTS), help="parts to leave out")
    a = ap.parse_args(argv)
    logs = os.path.join(ROOT, "out", "benchmarks")
    sys.path.insert(0, ROOT)
    from dem import outdir   # replaces our earlier logs there, never a user's file
    outdir.claim_folder(logs, overwrite=True, command="python -m benchmarks", what="log folder")
    env = dict(os.environ, PYTHONPATH=ROOT + os.pathsep + os.environ.get("PYTHONPATH", ""),
               PYTHONUNBUFFERED="1")
    results = []
    t_all = time.perf_counter()
    # the kernels as scripts/setup.sh leaves them (dem compile): the compiled code of some
    # models depends on the order in which Numba first compiles them, so every figure here is
    # measured on the cache a user's set-up produces
    subprocess.run([sys.executable, "-m", "dem.cli", "compile"], cwd=ROOT, env=env, check=True)
    for name, cmd in PARTS.items():
        if name in a.skip:
            continue
        args = [sys.executable] + cmd + (["--quick"] if a.quick else []) + (["--no-docs"] if a.no_docs else [])
        print(f"[benchmarks] {name}: {' '.join(args[1:])}", flush=True)
        t0 = time.perf_counter()
        outdir.claim(os.path.join(logs, f"{name}.log"))
        with open(os.path.join(logs, f"{name}.log"), "w") as f:
            p = subprocess.Popen(args, cwd=ROOT, env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
            for line in p.stdout:
                f.write(line)
                sys.stdout.write(f"  {line}")
            rc = p.wait()
        dt = time.perf_counter() - t0
        results.append((name, rc, dt))
        print(f"[benchmarks] {name}: {'ok' if rc == 0 else f'FAILED (exit {rc})'} in {dt:.0f} s", flush=True)
    total = time.perf_counter() - t_all
    print("\n[benchmarks] summary")
    for name, rc, dt in results:
        print(f"  {name:10s} {'ok' if rc == 0 else f'exit {rc}':8s} {dt:7.0f} s")
    print(f"  {'total':10s} {'':8s} {total:7.0f} s")
    return 0 if all(rc == 0 for _, rc, _ in results) else 1


if __name__ == "__main__":
    sys.exit(main())
