"""Memory per particle of the shared 10k bed in its own box and in a much larger one.

    python benchmarks/memory.py [--boxes 0.04 10] [--steps 200] [--packing PATH]

The same settled bed (benchmarks/shared_bed_10k.toml, 10,000 spheres of 1 mm) is loaded
with its domain widened to an L x L x 2L box (the bed and its walls stay where they are),
checked and advanced ``--steps`` steps (neighbour rebuilds included), each box in a fresh
process. Two figures per box, in bytes per particle:

* estimate: ``Simulation.check()["memory_bytes"]`` (the per-particle arrays, the neighbour
  list and its history slots, and during a rebuild the new list beside the old one plus the
  cell grid of the build: the array sizes, counted exactly);
* peak RSS: the rise of the process's resident high-water mark (VmHWM, reset through
  /proc/self/clear_refs after the kernels are loaded) over loading the scene, check() and
  the steps; it includes the CSV reader's and the scene parser's temporaries.

The neighbour search stores only the box of occupied cells (or sorted cell keys), so both
figures must be the same in the two boxes. Kernels must be compiled beforehand (`dem
compile`); the first process compiles them otherwise (excluded from the figures).
"""
import argparse
import json
import os
import subprocess
import sys

HERE = os.path.dirname(os.path.abspath(__file__))
ROOT = os.path.dirname(HERE)
SCENE = os.path.join(HERE, "shared_bed_10k.toml")


def _status(key):
    with open("/proc/self/status") as fh:
        for line in fh:
            if line.startswith(key + ":"):
                return int(line.split()[1]) * 1024
    return 0


def child(box, steps, packing):
    """Runs in a fresh process: one box; prints one JSON line."""
    import tomllib
    sys.path.insert(0, ROOT)
    from dem import Simulation
    from dem.cli import cmd_compile  # noqa: F401  (same import cost in every box)
    with open(SCENE, "rb") as fh:
        data = tomllib.load(fh)
    data["particles"][0]["file"] = packing
    # load the kernels with a tiny scene first, so that only the bed is measured
    tiny = json.loads(json.dumps(data))
    tiny["particles"] = [{"material": "glass", "positions": [[0.01, 0.01, 0.001], [0.0121, 0.01, 0.001]],
                          "radius": 0.001}]
    Simulation.from_dict(tiny, base_dir=HERE).step(2)
    try:
        with open("/proc/self/clear_refs", "w") as fh:
            fh.write("5")  # reset VmHWM to the current RSS
        hwm_ok = True
    except OSError:
        hwm_ok = False
    base = _status("VmRSS")
    data["domain"]["max"] = [box, box, 2 * box]
    out = dict(box=box)
    try:
        sim = Simulation.from_dict(data, base_dir=HERE)
        rep = sim.check()
        sim.step(steps)
    except MemoryError as exc:
        out.update(error=f"MemoryError: {exc}")
        print(json.dumps(out))
        return
    n = sim.n_particles
    out.update(n=n, estimate=rep["memory_bytes"] / n, build=rep.get("memory_neighbor_build_bytes", 0) / n,
               peak_rss=(_status("VmHWM") - base) / n if hwm_ok else None, steps=steps)
    print(json.dumps(out))


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--boxes", type=float, nargs="+", default=[0.04, 10.0], help="box widths L (m)")
    ap.add_argument("--steps", type=int, default=200)
    ap.add_argument("--packing", default=os.path.join(HERE, "packings", "settled_10k.npz"))
    ap.add_argument("--child", type=float, help=argparse.SUPPRESS)
    a = ap.parse_args(argv)
    packing = os.path.abspath(a.packing)
    if a.child is not None:
        child(a.child, a.steps, packing)
        return 0
    if not os.path.exists(packing):
        print(f"no packing at {packing} (give --packing PATH to a settled bed, e.g. benchmarks/packings/settled_10k.npz)",
              file=sys.stderr)
        return 2
    print(f"shared 10k bed, {a.steps} steps; bytes per particle")
    print(f"{'box L [m]':>10} {'estimate':>10} {'of which one rebuild':>21} {'peak RSS rise':>14}")
    for box in a.boxes:
        p = subprocess.run([sys.executable, os.path.abspath(__file__), "--child", str(box), "--steps",
                            str(a.steps), "--packing", packing], capture_output=True, text=True)
        lines = [ln for ln in p.stdout.splitlines() if ln.startswith("{")]
        if p.returncode != 0 or not lines:
            tail = (p.stderr.strip().splitlines() or ["?"])[-1]
            print(f"{box:>10g} failed (exit {p.returncode}): {tail}")
            continue
        r = json.loads(lines[-1])
        if "error" in r:
            print(f"{box:>10g} {r['error']}")
            continue
        rss = f"{r['peak_rss']:.0f}" if r["peak_rss"] is not None else "n/a"
        print(f"{box:>10g} {r['estimate']:>10.0f} {r['build']:>21.0f} {rss:>14}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
