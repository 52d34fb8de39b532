"""Restart equivalence of an interrupted `dem run` (docs/reliability/signals.md).

For a serial run and a run on 2 MPI ranks of tests/scenes/signals_bed.toml: run it
uninterrupted to an end time; run it again, send SIGTERM once history.csv shows progress,
continue with the command the interruption printed; print the largest differences of the
final positions, velocities, spins and temperatures.

    python scripts/signals_restart_figures.py [--steps-after 300]
"""
import argparse
import os
import shlex
import shutil
import signal
import subprocess
import sys
import tempfile
import time

import numpy as np

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
SCENE = os.path.join(ROOT, "tests", "scenes", "signals_bed.toml")
DT = 1e-5
ENV = dict(os.environ, PYTHONPATH=ROOT + os.pathsep + os.environ.get("PYTHONPATH", ""),
           OMPI_ALLOW_RUN_AS_ROOT="1", OMPI_ALLOW_RUN_AS_ROOT_CONFIRM="1",
           OMPI_MCA_rmaps_base_oversubscribe="1", OMPI_MCA_odls_base_sigkill_timeout="5",
           THERMODEM_CHUNK_SECONDS="0.2")


def dem(prefix, *args):
    return prefix + [sys.executable, "-m", "dem", *args]


def rows(out):
    try:
        return sum(1 for _ in open(os.path.join(out, "history.csv"))) - 1
    except OSError:
        return 0


def interrupted(prefix, out, steps_after):
    p = subprocess.Popen(dem(prefix, "run", SCENE, "--out", out, "--end-time", "1.0", "--quiet"),
                         stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True, env=ENV)
    while rows(out) < 3:
        if p.poll() is not None:
            sys.exit(p.stderr.read())
        time.sleep(0.05)
    p.send_signal(signal.SIGTERM if not prefix else signal.SIGINT)
    err = p.communicate()[1]
    line = next(s for s in err.splitlines() if s.startswith("interrupted by"))
    step = int(line.split("(step ")[1].split(")")[0])
    cmd = shlex.split(line.split("continue with: ")[1])
    i = cmd.index("dem")
    argv = cmd[:i] + [sys.executable, "-m", "dem"] + cmd[i + 1:]
    end = repr((step + steps_after) * DT)
    argv[argv.index("--end-time") + 1] = end
    subprocess.run(argv, check=True, capture_output=True, env=ENV)
    return step, end, line


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--steps-after", type=int, default=300)
    args = ap.parse_args()
    tmp = tempfile.mkdtemp()
    try:
        for name, prefix in (("serial", []), ("mpirun -np 2", ["mpirun", "-np", "2"])):
            if prefix and shutil.which("mpirun") is None:
                continue
            a, b = os.path.join(tmp, name + "_cut"), os.path.join(tmp, name + "_ref")
            step, end, line = interrupted(prefix, a, args.steps_after)
            subprocess.run(dem(prefix, "run", SCENE, "--out", b, "--end-time", end, "--quiet"),
                           check=True, capture_output=True, env=ENV)
            from dem.final import read as read_final   # an MPI run's final.npz: a manifest and its pieces
            x, y = read_final(os.path.join(b, "final.npz")), read_final(os.path.join(a, "final.npz"))
            assert np.array_equal(x["id"], y["id"])
            diffs = ", ".join(f"{k} {np.abs(x[k] - y[k]).max():.3g}" for k in
                              ("position", "velocity", "angular_velocity", "temperature"))
            print(f"{name}: interrupted at step {step}, continued to t = {end} s; max |difference| "
                  f"vs uninterrupted: {diffs} (m, m/s, rad/s, K)")
    finally:
        shutil.rmtree(tmp, ignore_errors=True)


if __name__ == "__main__":
    main()
