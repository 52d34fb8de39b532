"""Side by side with LIGGGHTS (Debian's `liggghts`, LIGGGHTS-PUBLIC 3.8.0) on the shared scenes of
../shared/bench: speed per core, speed on 2 processes, and the mean temperatures of the initially
hot and cold halves after the thermal run, with our relative difference.

    python benchmarks/liggghts_side_by_side.py [--quick] [--no-docs] [--pairs N] [--beds 10k-heat ...]

* one core: ours in this process pinned to one core, LIGGGHTS pinned to the other at the same
  time (`taskset`), so both see the same machine state; --pairs such pairs (default 4), the cores
  swapped from one pair to the next, reported as each pair's ratio and their geometric mean (a
  core slowed by a factor c by the machine's other tenants scales half the pairs by c and half by
  1/c: it drops out of the mean);
* two processes: ours on 2 MPI ranks, then LIGGGHTS on 2 MPI processes, then ours as one
  process on 2 threads (`--threads 2`; one after the other, each uses both cores);
* temperatures: after the thermal run (LIGGGHTS `fix heat/gran/conduction contact_area overlap`,
  ours `batchelor_obrien` with the geometric contact radius and direct_factor = sqrt(pi), the
  same conductance), read from LIGGGHTS's last thermo line (c_Thot, c_Tcold) and from ours.

`--beds` (10k, 10k-heat, 50k, 50k-heat) runs the one-core pairs of those beds only and prints
them with a 90 % interval of the geometric mean (Student's t on the logarithms of the pairs'
ratios); it leaves docs/benchmarks.md alone.
`--liggghts-skin S` (with --beds) runs LIGGGHTS with `neighbor S bin` instead of the shared
inputs' 0.0002 (a copy of them in a temporary folder): LIGGGHTS at the skin ours chose itself
(ours: `neighbor_skin = "auto"`, the scenes' default, docs/notebook.md "The skin chosen from
the measured motion").

Sizes: 10k at 10,000 steps (the scene's timed run) and 50k at 3,000 steps (--quick: 10k at
3,000 steps only). Loop times only: start-up (reading, Numba cache, LIGGGHTS set-up) is
excluded on both sides. LIGGGHTS is installed with apt-get when missing (root or sudo -n);
without it the script says so and exits with status 2. Writes the section
"## Side by side with LIGGGHTS" of docs/benchmarks.md unless --no-docs.
"""
import argparse
import glob
import math
import os
import platform
import re
import shutil
import tempfile
import subprocess
import sys
import time

HERE = os.path.dirname(os.path.abspath(__file__))
ROOT = os.path.dirname(HERE)
sys.path.insert(0, HERE)
sys.path.insert(0, ROOT)
import shared_scene  # noqa: E402
from shared_scene import (SHARED, liggghts_cmd, missing_shared_inputs, ours as ours_serial,  # noqa: E402
                          parse_loop)
from scaling import ours as ours_mpi  # noqa: E402

SECTION = "## Side by side with LIGGGHTS"
N = {"10k": 10000, "50k": 50000}
STEPS = {"10k": 10000, "50k": 3000}   # each bed's timed run (--quick: 10k at 3,000)


def ensure_liggghts():
    if shutil.which("liggghts"):
        return True
    sudo = [] if os.geteuid() == 0 else (["sudo", "-n"] if shutil.which("sudo") else None)
    if sudo is None:
        return False
    print("installing Debian's liggghts (apt-get) ...", flush=True)
    env = dict(os.environ, DEBIAN_FRONTEND="noninteractive")
    subprocess.run(sudo + ["apt-get", "update", "-qq"], env=env, check=False)
    subprocess.run(sudo + ["apt-get", "install", "-y", "-qq", "--no-install-recommends", "liggghts"], env=env,
                   check=False)
    return shutil.which("liggghts") is not None


def liggghts_with_skin(tmp, skin):
    """A copy of the shared LIGGGHTS inputs in ``tmp`` whose `neighbor` line has ``skin`` (m);
    the packings are linked. Returns the copy's liggghts folder."""
    lig = os.path.join(tmp, "liggghts")
    os.makedirs(lig)
    for f in glob.glob(os.path.join(SHARED, "liggghts", "*")):
        shutil.copy(f, lig)
    os.symlink(os.path.join(SHARED, "packings"), os.path.join(tmp, "packings"))
    path = os.path.join(lig, "common.lig")
    text, n = re.subn(r"(?m)^neighbor\s+\S+\s+bin", f"neighbor        {skin!r} bin", open(path).read())
    if n != 1:
        raise SystemExit(f"{path}: no `neighbor <skin> bin` line to change")
    with open(path, "w") as fh:
        fh.write(text)
    return lig


def liggghts_run(size, heat, steps, nproc, pin=None):
    """Start LIGGGHTS (returns the Popen); its output names the work directory with log.run."""
    cmd = liggghts_cmd(size, heat, steps, nproc)
    if pin is not None:
        cmd = ["taskset", "-c", str(pin)] + cmd
    env = dict(os.environ, OMPI_ALLOW_RUN_AS_ROOT="1", OMPI_ALLOW_RUN_AS_ROOT_CONFIRM="1")
    return subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, env=env)


def liggghts_result(proc):
    text = proc.communicate()[0]
    res = dict(loop=parse_loop(text))
    m = re.search(r"outputs in (\S+)", text)
    if m:
        log = os.path.join(m.group(1), "log.run")
        if os.path.exists(log):
            rows = [ln.split() for ln in open(log) if re.match(r"^\s*\d+\s", ln)]
            # thermal block: step ke rke heat Thot Tcold cpu
            rows = [r for r in rows if len(r) == 7]
            if rows:
                res["T_hot"], res["T_cold"] = float(rows[-1][4]), float(rows[-1][5])
        shutil.rmtree(m.group(1), ignore_errors=True)
    return res


def one_core_pairs(size, heat, steps, pairs):
    """``pairs`` runs of ours and LIGGGHTS on one core each at the same time, the cores swapped
    from one pair to the next (ours on core 0 then 1, ...), so that a core slowed by the machine's
    other tenants weighs on both sides alike. Returns the pairs' (ours, LIGGGHTS) results."""
    runs = []
    ncpu = os.cpu_count() or 1
    for k in range(pairs):
        mine, theirs = (0, 1) if k % 2 == 0 or ncpu < 2 else (1, 0)
        p = liggghts_run(size, heat, steps, 1, pin=theirs if ncpu > 1 else None)
        os.sched_setaffinity(0, {mine})
        try:
            o1 = ours_serial(size, heat, steps)
        finally:
            os.sched_setaffinity(0, set(range(ncpu)))
        runs.append((o1, liggghts_result(p)))
    return runs


def pair_ratios(runs, n):
    """Ours / LIGGGHTS (particle-steps per second) of each pair of :func:`one_core_pairs`, for
    ``n`` particle-steps."""
    return [o["pps"] / (n / lg["loop"]) for o, lg in runs]


def _median(v):
    v = sorted(v)
    h = len(v) // 2
    return v[h] if len(v) % 2 else 0.5 * (v[h - 1] + v[h])


def _gmean(v):
    """Geometric mean: with as many pairs on each core, a core slowed by a factor c (the
    machine's other tenants) scales the ratio by c in half the pairs and by 1/c in the other
    half, and drops out."""
    return math.exp(sum(math.log(q) for q in v) / len(v))


def _interval(v, level=0.90):
    """(low, high): the ``level`` interval of the geometric mean of the ratios ``v`` (Student's t
    on their logarithms; the pairs' spread, not a bound on the machine's)."""
    if len(v) < 2:
        return float("nan"), float("nan")
    from scipy.stats import t as student
    lg = [math.log(q) for q in v]
    m = sum(lg) / len(lg)
    sd = math.sqrt(sum((x - m) ** 2 for x in lg) / (len(lg) - 1))
    h = student.ppf(0.5 + level / 2, len(lg) - 1) * sd / math.sqrt(len(lg))
    return math.exp(m - h), math.exp(m + h)


def one_core_only(beds, pairs, log=print):
    """The one-core pairs of ``beds`` (e.g. "10k-heat"), each bed's ratios, geometric mean and
    its 90 % interval; returns the rows."""
    rows = []
    for bed in beds:
        size, _, heat = bed.partition("-")
        steps = STEPS[size]
        n = N[size] * steps
        runs = one_core_pairs(size, heat == "heat", steps, pairs)
        row = dict(bed=bed, ratios=pair_ratios(runs, n))
        row.update(gmean=_gmean(row["ratios"]), interval=_interval(row["ratios"]))
        log(f"{bed}: {steps} steps, ours / LIGGGHTS per core, {pairs} pairs: "
            f"{', '.join(f'{q:.2f}' for q in row['ratios'])}; geometric mean {row['gmean']:.3f}, 90 % interval "
            f"{row['interval'][0]:.3f}-{row['interval'][1]:.3f}; ours {_median([o['pps'] for o, _ in runs]):.3g}, "
            f"LIGGGHTS {_median([n / lg['loop'] for _, lg in runs]):.3g} particle-steps/s (medians)")
        rows.append(row)
    return rows


def measure(size, steps, pairs=4, log=print):
    out = []
    n = N[size] * steps
    for heat in (False, True):
        # one core each, at the same time, several pairs
        runs = one_core_pairs(size, heat, steps, pairs)
        ratios = pair_ratios(runs, n)
        o1, l1 = runs[0]
        # two processes, one after the other
        o2 = ours_mpi(size, heat, steps, 2)
        o2t = ours_mpi(size, heat, steps, 1, threads=2)
        l2 = liggghts_result(liggghts_run(size, heat, steps, 2))
        r = dict(size=size, heat=heat, steps=steps, ours1=_median([o["pps"] for o, _ in runs]),
                 lig1=_median([n / lg["loop"] for _, lg in runs]), ratios=ratios, ratio1=_gmean(ratios),
                 ours2=o2["pps"], ours2t=o2t["pps"], lig2=n / l2["loop"], mem=o1["mem"])
        if heat:
            r.update(T_hot=o1["T_hot"], T_cold=o1["T_cold"], L_hot=l1.get("T_hot"), L_cold=l1.get("T_cold"))
        log(f"{size} heat {'on ' if heat else 'off'}: 1 core ours {r['ours1']:.3g} LIGGGHTS {r['lig1']:.3g} "
            f"(pairs {', '.join(f'{q:.2f}' for q in ratios)}: geometric mean {r['ratio1']:.2f}); "
            f"2 processes ours {r['ours2']:.3g} LIGGGHTS {r['lig2']:.3g} "
            f"({r['ours2'] / r['lig2']:.2f}); ours 1 process x 2 threads {r['ours2t']:.3g} "
            f"({r['ours2t'] / r['ours2']:.2f} of 2 ranks, {r['ours2t'] / r['ours1']:.2f} of 1 thread, median)"
            + (f"; T_hot {r['T_hot']:.10f}/{r['L_hot']} T_cold {r['T_cold']:.10f}/{r['L_cold']}" if heat else ""))
        out.append(r)
    return out


def markdown(rows, cmd, total, pairs):
    L = [f"```\n{cmd}\n```\n",
         f"Measured {time.strftime('%Y-%m-%d')} on {platform.machine()} ({os.cpu_count()} cores, a shared "
         f"virtual machine), {total:.0f} s in all. Loop time only on both sides (particle-steps per second). "
         f"One core: ours pinned to one core and LIGGGHTS to the other, running at the same time, {pairs} "
         f"pairs with the cores swapped from one pair to the next; the speeds are the pairs' medians, the "
         f"ratio the geometric mean of the pairs' ratios (each pair's in brackets: with as many pairs on each "
         f"core, a core slowed by the machine's other tenants drops out). Two processes (once): "
         f"our 2 MPI ranks of 1 thread, then LIGGGHTS on 2 MPI processes, then ours as one process "
         f"on 2 threads (`--threads 2`). Ratios > 1: ours faster.\n",
         "| N | steps | heat | ours, 1 core | LIGGGHTS, 1 core | ratio | ours, 2 ranks | LIGGGHTS, 2 processes "
         "| ratio | ours 2/1 | LIGGGHTS 2/1 | ours, 1 process x 2 threads | threads / ranks | threads 2/1 |",
         "|---|---|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        L.append(f"| {r['size']} | {r['steps']} | {'on' if r['heat'] else 'off'} | {r['ours1']:.3g} | "
                 f"{r['lig1']:.3g} | **{r['ratio1']:.2f}** ({', '.join(f'{q:.2f}' for q in r['ratios'])}) | "
                 f"{r['ours2']:.3g} | {r['lig2']:.3g} | "
                 f"**{r['ours2'] / r['lig2']:.2f}** | {r['ours2'] / r['ours1']:.2f} | {r['lig2'] / r['lig1']:.2f} | "
                 f"{r['ours2t']:.3g} | **{r['ours2t'] / r['ours2']:.2f}** | **{r['ours2t'] / r['ours1']:.2f}** |")
    L.append("")
    L.append("Temperatures after the thermal run (mean of the initially hot and cold halves; the heat moved "
             "is 400 K - T_hot):\n")
    L.append("| N | steps | T_hot ours [K] | T_hot LIGGGHTS [K] | T_cold ours [K] | T_cold LIGGGHTS [K] | "
             "heat moved, relative difference |")
    L.append("|---|---|---|---|---|---|---|")
    for r in rows:
        if not r["heat"]:
            continue
        if r.get("L_hot") is None:
            L.append(f"| {r['size']} | {r['steps']} | {r['T_hot']:.10f} | – | {r['T_cold']:.10f} | – | – |")
            continue
        d, ld = 400.0 - r["T_hot"], 400.0 - r["L_hot"]
        L.append(f"| {r['size']} | {r['steps']} | {r['T_hot']:.10f} | {r['L_hot']:.10f} | {r['T_cold']:.10f} | "
                 f"{r['L_cold']:.10f} | {abs(d - ld) / ld:.2e} |")
    L.append("")
    L.append("The scene, the conduction law and the LIGGGHTS inputs: ../shared/bench/README.md. Our scenes "
             "(benchmarks/shared_bed_*.toml) run LIGGGHTS's own tangential law, `[contact] tangential = "
             "\"projected\"` (docs/models.md; since 2026-12-05, before that the default `rescaled`: "
             "docs/notebook.md, \"LIGGGHTS's own tangential law\"), and the default neighbour skin, "
             "`\"auto\"`: chosen at each build from the measured motion, at most LIGGGHTS's 0.2 mm (0.018 mm on "
             "the 10k bed; since 2026-12-05, before that 0.2 mm fixed: docs/notebook.md, \"The skin chosen from "
             "the measured motion\", which also runs LIGGGHTS at our skin). Runs on this "
             "shared machine vary by up to 30 % from one period to the next; the ratios, measured side by side, "
             "vary much less (earlier periods: docs/notebook.md).")
    return "\n".join(L)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="10k bed, 3,000 steps")
    ap.add_argument("--no-docs", action="store_true")
    ap.add_argument("--pairs", type=int, default=4,
                    help="one-core runs of each side at the same time, cores swapped between pairs (default 4; "
                         "even: as many on each core)")
    ap.add_argument("--beds", nargs="+", choices=("10k", "10k-heat", "50k", "50k-heat"),
                    help="only the one-core pairs of these beds, with a 90 %% interval (docs left alone)")
    ap.add_argument("--liggghts-skin", type=float, metavar="S",
                    help="with --beds: LIGGGHTS runs `neighbor S bin` (m) instead of the shared inputs' 0.0002")
    a = ap.parse_args(argv)
    if a.liggghts_skin is not None and not (a.beds and a.liggghts_skin > 0):
        ap.error("--liggghts-skin needs --beds and a skin > 0 (m)")
    missing = missing_shared_inputs()
    if missing:
        print(missing, file=sys.stderr)
        return 2
    if not ensure_liggghts():
        print("LIGGGHTS is not installed and could not be installed (apt-get install liggghts needs root): "
              "skipped", file=sys.stderr)
        return 2
    if a.beds:
        with tempfile.TemporaryDirectory() as tmp:
            if a.liggghts_skin is not None:
                shared_scene.LIGGGHTS_DIR = liggghts_with_skin(tmp, a.liggghts_skin)
                print(f"LIGGGHTS: neighbor {a.liggghts_skin:g} bin (the shared inputs: 0.0002)")
            one_core_only(a.beds, max(1, a.pairs))
        return 0
    t0 = time.perf_counter()
    plan = [("10k", 3000)] if a.quick else list(STEPS.items())
    rows = []
    for size, steps in plan:
        rows += measure(size, steps, max(1, a.pairs))
    total = time.perf_counter() - t0
    md = markdown(rows, "python benchmarks/liggghts_side_by_side.py" + (" --quick" if a.quick else "")
                  + (f" --pairs {a.pairs}" if a.pairs != 4 else ""), total, max(1, a.pairs))
    print(md)
    if not a.no_docs:
        from benchmarks.accuracy.common import replace_section
        replace_section(os.path.join(ROOT, "docs", "benchmarks.md"), SECTION, md)
    return 0


if __name__ == "__main__":
    sys.exit(main())
