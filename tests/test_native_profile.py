"""benchmarks/native_profile.py: the samples of a stepping process are found in the copied
machine code of the compiled step, and --out never replaces an existing file (no timing here)."""
import os
import re
import shutil
import subprocess
import sys

import pytest

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
SCRIPT = os.path.join(ROOT, "benchmarks", "native_profile.py")
SCENE = os.path.join(ROOT, "examples", "settle_box.toml")


def _perf_usable():
    if shutil.which("perf") is None or shutil.which("objdump") is None:
        return False
    r = subprocess.run(["perf", "record", "-q", "-e", "cpu-clock", "-o", os.devnull, "--", "true"],
                       capture_output=True)
    return r.returncode == 0


needs_perf = pytest.mark.skipif(not _perf_usable(), reason="perf (cpu-clock) or objdump not usable here")


@needs_perf
def test_samples_fall_in_the_compiled_step(tmp_path):
    out = tmp_path / "annotated.s"
    r = subprocess.run([sys.executable, SCRIPT, SCENE, "--steps", "3000", "--top", "5", "--out", str(out)],
                       capture_output=True, text=True, timeout=900)
    assert r.returncode == 0, r.stderr
    m = re.search(r"(\d+) samples, (\d+) \(", r.stdout)
    total, inside = int(m.group(1)), int(m.group(2))
    # 3,000 steps of 2,000 beads run for a good fraction of a second: with a sample every 0.25 ms
    # the step's code must hold well over a hundred of them (none would mean the copy is not the
    # code that ran)
    assert inside >= 100 and inside < total
    lines = out.read_text().splitlines()
    shares = [float(line.split()[0]) for line in lines]
    assert len(lines) > 1000                                 # the whole step, disassembled
    hot = sum(1 for q in shares if q > 0.0)
    # each line's share is the instruction's samples over all, to 3 decimals: they add up to the
    # step's share within half a unit of the last decimal per line that has samples
    assert hot >= 1 and abs(sum(shares) - 100.0 * inside / total) <= 0.0005 * hot + 1e-9


def test_out_never_replaces_a_file(tmp_path):
    mine = tmp_path / "notes.s"
    mine.write_text("a user's file\n")
    r = subprocess.run([sys.executable, SCRIPT, SCENE, "--steps", "10", "--out", str(mine)],
                       capture_output=True, text=True, timeout=120)
    if shutil.which("perf") is None or shutil.which("objdump") is None:
        assert r.returncode == 2 and "not found" in r.stderr
    else:
        assert r.returncode == 2 and "not overwritten" in r.stderr
    assert mine.read_text() == "a user's file\n"


@needs_perf
def test_a_bad_scene_is_named_without_a_traceback(tmp_path):
    bad = tmp_path / "bad.toml"
    bad.write_text('[simulation]\ntime_step = 1e-5\n')
    r = subprocess.run([sys.executable, SCRIPT, str(bad), "--steps", "10"], capture_output=True, text=True,
                       timeout=120)
    assert r.returncode == 2
    assert str(bad) in r.stderr and "domain" in r.stderr and "Traceback" not in r.stderr
