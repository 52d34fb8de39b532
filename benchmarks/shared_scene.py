"""Speed on the shared benchmark scene (../shared/bench), side by side with LIGGGHTS.

    python benchmarks/shared_scene.py [--sizes 10k 50k] [--steps 10000] [--liggghts]
                                      [--concurrent]

For each bed size, runs 10,000 steps of the settled bed without and with contact
conduction (our kernels are compiled/loaded first and not timed) and prints
particle-steps per second, the heat/no-heat cost ratio, memory per particle, and the mean
temperatures of the initially hot and cold halves (LIGGGHTS's reference after 10,000
steps of the 10k bed: 399.9667014482 K and 300.0332985518 K).
With --liggghts the same runs are made with Debian's LIGGGHTS (`apt-get install liggghts`)
through shared/bench/liggghts/run_lig.sh (the shared inputs, see SHARED below); --concurrent
runs ours and LIGGGHTS at the same time pinned to different cores (taskset), which removes the drift of a shared host.
"""
import argparse
import os
import re
import subprocess
import sys
import time

HERE = os.path.dirname(os.path.abspath(__file__))
ROOT = os.path.dirname(HERE)
# The LIGGGHTS inputs of the shared scene (liggghts/*.lig, run_lig.sh and the beds in LIGGGHTS's
# format, packings/*.data) are not part of this repository: they are read from the folder that
# THERMODEM_SHARED_BENCH names, by default ../shared/bench beside the clone.  Our side reads the
# same beds from benchmarks/packings/*.npz and needs nothing beside the clone.
SHARED = os.path.abspath(os.environ.get("THERMODEM_SHARED_BENCH")
                         or os.path.join(os.path.dirname(ROOT), "shared", "bench"))
SHARED_MISSING = (
    "the LIGGGHTS side of the shared scene needs its inputs (liggghts/run_lig.sh, liggghts/*.lig, "
    "packings/settled_*.data), which are not part of this repository; none at {path}. Put the shared "
    "benchmark folder beside the clone as ../shared/bench, or set THERMODEM_SHARED_BENCH=/path/to/bench. "
    "Our side alone runs without them: python benchmarks/shared_scene.py")


def missing_shared_inputs():
    """None when the shared LIGGGHTS inputs are at SHARED, else the message that says how to get them."""
    if os.path.isfile(os.path.join(SHARED, "liggghts", "run_lig.sh")) and \
            os.path.isdir(os.path.join(SHARED, "packings")):
        return None
    return SHARED_MISSING.format(path=SHARED)
ZSPLIT = {"10k": 0.02282313764, "50k": 0.03628337489}
REF_T = {"10k": (399.9667014482, 300.0332985518)}


def ours(size, heat, steps):
    """Run in this process; returns dict(seconds, pps, T_hot, T_cold, mem)."""
    import numpy as np
    from dem import Simulation
    scene = os.path.join(HERE, f"shared_bed{'_heat' if heat else ''}_{size}.toml")
    sim = Simulation.from_file(scene)
    sim.warmup()
    z0 = sim.state.position[:, 2].copy()
    ids0 = sim.state.id.copy()
    t0 = time.perf_counter()
    sim.run(end_time=steps * sim.dt, progress=False)
    sec = time.perf_counter() - t0
    out = dict(seconds=sec, pps=sim.state.n * steps / sec,
               mem=sim.check()["memory_per_particle"])
    if heat:
        hot_ids = set(ids0[z0 < ZSPLIT[size]].tolist())
        hot = np.array([i in hot_ids for i in sim.state.id])
        T = sim.state.temperature
        out["T_hot"] = float(T[hot].mean())
        out["T_cold"] = float(T[~hot].mean())
    return out


# the LIGGGHTS inputs run: the shared ones, or a copy with another skin (liggghts_side_by_side.py
# --liggghts-skin)
LIGGGHTS_DIR = os.path.join(SHARED, "liggghts")


def liggghts_cmd(size, heat, steps, nproc=1):
    return ["bash", os.path.join(LIGGGHTS_DIR, "run_lig.sh"), size, "heat" if heat else "noheat",
            str(nproc), str(steps)]


def parse_loop(text):
    m = re.search(r"Loop time of ([0-9.eE+-]+)", text)
    return float(m.group(1)) if m else float("nan")


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--sizes", nargs="+", default=["10k"])
    ap.add_argument("--steps", type=int, default=10000)
    ap.add_argument("--liggghts", action="store_true")
    ap.add_argument("--concurrent", action="store_true",
                    help="run LIGGGHTS at the same time on the other core (taskset)")
    args = ap.parse_args()
    missing = missing_shared_inputs() if args.liggghts else None
    if missing:
        print(missing, file=sys.stderr)
        return 2
    n = {"10k": 10000, "50k": 50000}
    rows = []
    for size in args.sizes:
        for heat in (False, True):
            lig = None
            proc = None
            if args.liggghts and args.concurrent:
                proc = subprocess.Popen(["taskset", "-c", "1"] + liggghts_cmd(size, heat, args.steps),
                                        stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
                os.sched_setaffinity(0, {0})
            r = ours(size, heat, args.steps)
            if proc is not None:
                lig = parse_loop(proc.communicate()[0])
                os.sched_setaffinity(0, set(range(os.cpu_count())))
            elif args.liggghts:
                res = subprocess.run(liggghts_cmd(size, heat, args.steps), capture_output=True, text=True)
                lig = parse_loop(res.stdout + res.stderr)
            r.update(size=size, heat=heat, liggghts_s=lig)
            rows.append(r)
            lp = n[size] * args.steps / lig if lig else float("nan")
            print(f"{size} heat={'on ' if heat else 'off'} ours {r['seconds']:.2f} s = {r['pps']:.3g} particle-steps/s"
                  + (f" | LIGGGHTS {lig:.2f} s = {lp:.3g} | ratio ours/LIGGGHTS speed {r['pps'] / lp:.2f}" if lig else "")
                  + (f" | T_hot {r['T_hot']:.10f} T_cold {r['T_cold']:.10f}" if heat else ""), flush=True)
    print("\n| N | heat | ours s | ours particle-steps/s | LIGGGHTS s | LIGGGHTS particle-steps/s | speed ratio |")
    print("|---|---|---|---|---|---|---|")
    for r in rows:
        lig = r["liggghts_s"]
        lp = n[r["size"]] * args.steps / lig if lig else float("nan")
        print(f"| {r['size']} | {'on' if r['heat'] else 'off'} | {r['seconds']:.2f} | {r['pps']:.3g} | "
              f"{lig if lig else float('nan'):.2f} | {lp:.3g} | {r['pps'] / lp:.2f} |")
    for size in args.sizes:
        off = [r for r in rows if r["size"] == size and not r["heat"]][0]
        on = [r for r in rows if r["size"] == size and r["heat"]][0]
        line = f"{size}: heat cost ratio ours {on['seconds'] / off['seconds']:.3f}"
        if on["liggghts_s"]:
            line += f", LIGGGHTS {on['liggghts_s'] / off['liggghts_s']:.3f}"
        line += f"; memory {off['mem']:.0f} B/particle (no heat), {on['mem']:.0f} B/particle (heat)"
        print(line)
        if size in REF_T:
            th, tc = REF_T[size]
            drop, ldrop = 400.0 - on["T_hot"], 400.0 - th
            print(f"{size}: T_hot {on['T_hot']:.10f} K (LIGGGHTS {th}), T_cold {on['T_cold']:.10f} K "
                  f"(LIGGGHTS {tc}); heat moved (400 - T_hot) ours {drop:.6e} K, LIGGGHTS {ldrop:.6e} K, "
                  f"relative difference {abs(drop - ldrop) / ldrop:.2e}")


if __name__ == "__main__":
    sys.exit(main())
