"""Where the compiled step spends its time on this CPU: a sampling profile of one scene's steps,
instruction by instruction of the compiled step (no hardware counters needed):

    python benchmarks/native_profile.py benchmarks/shared_bed_heat_10k.toml --steps 3000 [--top 25] [--out FILE]

The script runs itself under ``perf record -e cpu-clock`` (a timer interrupt, so it works in a
virtual machine without performance counters). The profiled process loads the scene, warms up,
copies the machine code of the compiled step (``dem.step.advance`` and everything compiled into it)
out of its own memory, then steps. The samples are mapped onto that copy and disassembled with
``objdump``. It prints the share of the samples in the step's code, the hottest instructions and
the share by 512-byte stretch of code; ``--out`` writes every instruction with its share.

A sample lands on the instruction the core retires next: the wait for a long-latency result (a
square root, a division, a load that misses) shows on the instruction that uses it. Needs ``perf``
(Debian: linux-perf) and ``objdump`` (binutils); run it pinned (``taskset -c 0``) on a quiet core.
"""
import argparse
import collections
import ctypes
import os
import shutil
import subprocess
import sys
import tempfile

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


def _child(scene, steps, out):
    """The profiled process: load, warm up, 5 steps, copy the step's code, then ``steps`` steps."""
    from dem import Simulation
    import dem.step as K
    sim = Simulation.from_file(scene)
    sim.warmup()
    sim.step(5)
    ptrs = [cres.library.get_pointer_to_function(cres.fndesc.llvm_func_name) for cres in K.advance.overloads.values()]
    for line in open("/proc/self/maps"):
        lo, hi = (int(s, 16) for s in line.split()[0].split("-"))
        if any(lo <= p < hi for p in ptrs):
            with open(os.path.join(out, f"code_{lo:x}.bin"), "wb") as fh:
                fh.write(ctypes.string_at(lo, hi - lo))
    sim.step(steps)


def _disassemble(path, base):
    """(address, text) of each instruction of the code copied from ``base``."""
    dis = subprocess.run(["objdump", "-D", "-b", "binary", "-mi386:x86-64", f"--adjust-vma={base:#x}", path],
                         capture_output=True, text=True, check=True).stdout
    for line in dis.splitlines():
        head, _, rest = line.partition(":")
        try:
            a = int(head.strip(), 16)
        except ValueError:
            continue
        parts = rest.split("\t")
        if len(parts) >= 3:
            yield a, parts[2].strip()


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("scene", help="scene file (e.g. benchmarks/shared_bed_heat_10k.toml)")
    ap.add_argument("--steps", type=int, default=3000, help="steps profiled after the warm-up (default 3000)")
    ap.add_argument("--top", type=int, default=25, help="hottest instructions printed (default 25)")
    ap.add_argument("--out", help="write every instruction of the step's code with its share of the samples")
    ap.add_argument("--child", help=argparse.SUPPRESS)
    a = ap.parse_args(argv)
    if a.child:
        sys.path.insert(0, ROOT)
        from dem.errors import SceneError, SimulationError
        try:
            _child(a.scene, a.steps, a.child)
        except (SceneError, SimulationError) as e:   # the scene's own message, without a traceback
            print(e, file=sys.stderr)
            return 2
        return 0
    missing = [t for t in ("perf", "objdump") if shutil.which(t) is None]
    if missing:
        print(f"native_profile: {' and '.join(missing)} not found (Debian: apt-get install linux-perf binutils)",
              file=sys.stderr)
        return 2
    if a.steps < 1 or a.top < 1:
        print("native_profile: --steps and --top must be at least 1", file=sys.stderr)
        return 2
    if not os.path.isfile(a.scene):
        print(f"native_profile: no scene file {a.scene}", file=sys.stderr)
        return 2
    if a.out and os.path.exists(a.out):
        print(f"native_profile: {a.out} exists; name a new file for --out (it is not overwritten)", file=sys.stderr)
        return 2
    with tempfile.TemporaryDirectory() as tmp:
        data = os.path.join(tmp, "perf.data")
        run = subprocess.run(["perf", "record", "-q", "-e", "cpu-clock", "-F", "4000", "-o", data, "--",
                              sys.executable, os.path.abspath(__file__), os.path.abspath(a.scene),
                              "--steps", str(a.steps), "--child", tmp], capture_output=True, text=True)
        codes = [f for f in os.listdir(tmp) if f.startswith("code_")]
        if run.returncode != 0 or not codes:
            print(f"native_profile: the profiled run failed (exit {run.returncode}):\n{run.stderr.strip()[-2000:]}",
                  file=sys.stderr)
            return 2 if run.returncode == 2 else 1
        ips = subprocess.run(["perf", "script", "-i", data, "-F", "ip"], capture_output=True, text=True,
                             check=True).stdout.split()
        count = collections.Counter(int(s, 16) for s in ips)
        total = sum(count.values())
        text = {}   # address -> instruction, over every stretch of memory holding a compiled form of the step
        for name in codes:
            base = int(name[5:-4], 16)
            text.update(_disassemble(os.path.join(tmp, name), base))
        inside = {ip: c for ip, c in count.items() if ip in text}
        n_in = sum(inside.values())
        print(f"{a.scene}, {a.steps} steps: {total} samples, {n_in} ({100 * n_in / total:.1f} %) in the compiled "
              f"step (start-up, loading and warm-up included in the total)")
        print(f"\nhottest instructions (% of all samples; the wait of a long-latency instruction shows on the "
              f"next that uses its result):")
        for ip, c in sorted(inside.items(), key=lambda kv: -kv[1])[:a.top]:
            print(f"{100 * c / total:6.2f}  {ip:#x}  {text[ip]}")
        region = collections.Counter()
        for ip, c in inside.items():
            region[ip >> 9] += c
        print("\nby 512-byte stretch of code (stretches with >= 0.5 % of the samples):")
        for k in sorted(region):
            if region[k] >= 0.005 * total:
                print(f"  {k << 9:#x}  {100 * region[k] / total:6.2f} %")
        if a.out:
            part = os.path.join(tmp, "annotated.s")   # written whole, then moved into place
            with open(part, "w") as fh:
                for ip, t in sorted(text.items()):
                    fh.write(f"{100 * inside.get(ip, 0) / total:7.3f}  {ip:#x}  {t}\n")
            shutil.move(part, a.out)
            print(f"\nevery instruction: {a.out}")
    return 0


if __name__ == "__main__":
    try:
        sys.exit(main())
    except KeyboardInterrupt:
        print("native_profile: interrupted; nothing written", file=sys.stderr)
        sys.exit(130)
