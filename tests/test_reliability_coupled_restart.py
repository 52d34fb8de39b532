"""Coupled restarts continue the same run; SIGINT/SIGTERM stop a coupled run cleanly.

Everything runs through the command line (``python -m coupling.run run ...``) on the heated
fluidized bed (openfoam_cases/fluidized_bed_heating: 3,000 beads, 600 gas cells, heat and
time-smoothed void fraction on), shortened to ``2 N`` coupling steps:

(a) ``2 N`` steps in one run equal ``N`` steps + ``--restart`` to ``2 N`` (particle positions,
    velocities and temperatures, gas U, T, p to 1e-10 relative; in fact bit-identical);
(b) SIGINT to the running command: exit 130, one line with the continue command, no solver
    process left; continuing gives the uninterrupted result;
(c) SIGTERM to the command and to the gas solver at once (what a batch scheduler does at the
    end of the wall time): exit 143, the same guarantees.
"""
from __future__ import annotations

import os
import re
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
from dem.final import read as read_final

ROOT = Path(__file__).resolve().parents[1]
CASE = ROOT / "openfoam_cases" / "fluidized_bed_heating"
DT = 5e-4                  # CFD step = coupling step of the case (system/controlDict deltaT)
N = 10                     # coupling steps before the restart; the runs have 2 N
END = 2 * N * DT
TOL = 1e-10                # relative


def _env():
    env = dict(os.environ)
    env["PYTHONPATH"] = str(ROOT) + os.pathsep + env.get("PYTHONPATH", "")
    return env


def _cmd(out: Path, end: float, *extra: str) -> list[str]:
    return [sys.executable, "-m", "coupling.run", "run", str(CASE), "--out", str(out),
            "--end-time", repr(end), "--quiet", *extra]


def _run(out: Path, end: float, *extra: str) -> subprocess.CompletedProcess:
    p = subprocess.run(_cmd(out, end, *extra), capture_output=True, text=True, env=_env(), timeout=600)
    assert p.returncode == 0, p.stdout[-2000:] + p.stderr[-3000:]
    return p


def _children(pid: int) -> list[int]:
    """Processes whose parent is ``pid`` (from /proc)."""
    kids = []
    for d in Path("/proc").iterdir():
        if d.name.isdigit():
            try:
                stat = (d / "stat").read_text()
            except OSError:
                continue
            if int(stat.rsplit(")", 1)[1].split()[1]) == pid:
                kids.append(int(d.name))
    return kids


def _cmdline(pid: int) -> str:
    try:
        return Path(f"/proc/{pid}/cmdline").read_bytes().decode(errors="replace")
    except OSError:      # ended meanwhile (blockMesh, the build check, ...)
        return ""


def _alive(pid: int) -> bool:
    try:
        stat = Path(f"/proc/{pid}/stat").read_text()
    except OSError:
        return False
    return stat.rsplit(")", 1)[1].split()[0] != "Z"


def _gas(out: Path, field: str) -> np.ndarray:
    from coupling import foam_case as fc
    return fc.read_internal_field(out / f"{END:g}" / field, 600)


def _assert_same_run(ref: Path, other: Path):
    """Final particle and gas states of two outputs agree to TOL (relative to the field's scale)."""
    a, b = read_final(ref / "final.npz"), read_final(other / "final.npz")
    assert float(a["time"]) == pytest.approx(END) and float(b["time"]) == pytest.approx(END)
    assert np.array_equal(a["id"], b["id"])
    for k in ("position", "velocity", "temperature"):
        scale = np.abs(a[k]).max()
        err = np.abs(a[k] - b[k]).max()
        assert err <= TOL * scale, f"{k}: {err:.3g} (scale {scale:.3g})"
    assert a["temperature"].max() > 300.0 + 1e-3          # the gas heated the beads
    for f in ("U", "T", "p"):
        x, y = _gas(ref, f), _gas(other, f)
        assert np.abs(x - y).max() <= TOL * np.abs(x).max(), f


@pytest.fixture(scope="module")
def reference(tmp_path_factory, solver):
    """The uninterrupted run of 2 N coupling steps."""
    out = tmp_path_factory.mktemp("ref") / "out"
    _run(out, END)
    return out


@pytest.fixture(scope="module")
def first_half(tmp_path_factory, solver):
    """The first N coupling steps as a run of their own (to N DT): its end is a restart point.
    Shared by the restart and the corrupt-state tests, each of which continues (or damages) a
    copy of it."""
    out = tmp_path_factory.mktemp("half") / "out"
    _run(out, N * DT)
    return out


def test_restart_continues_the_same_run(reference, first_half, tmp_path):
    """N steps (the module's first_half, copied: this test continues it) + --restart to 2 N
    steps are the uninterrupted 2 N."""
    out = tmp_path / "out"
    shutil.copytree(first_half, out, symlinks=True)
    ck = out / "checkpoints"
    # the end of a run is a restart point: gas time, DEM checkpoint and coupling state
    assert (out / f"{N * DT:g}").is_dir()
    assert (ck / f"checkpoint_{N:08d}.npz").is_file() and (ck / f"coupling_{N:08d}.npz").is_file()
    p = _run(out, END, "--restart")
    assert f"restarting from t = {N * DT:g} s (step {N}" in p.stdout + p.stderr
    _assert_same_run(reference, out)
    # history.csv continues without duplicates
    h = np.atleast_1d(np.genfromtxt(out / "coupling.csv", delimiter=",", names=True))
    assert np.all(np.diff(h["time"]) > 0) and h["time"][-1] == pytest.approx(END)
    # continuing a run that already reached its end time says so (exit 0) and changes nothing
    before = {f: (out / f).read_bytes() for f in ("coupling.csv", "final.npz", "checkpoint.npz")}
    p = _run(out, END, "--restart")
    assert "is already complete" in p.stdout and f"--restart --end-time T" in p.stdout, p.stdout
    assert {f: (out / f).read_bytes() for f in before} == before


def _interrupt(out: Path, signum: int, solver_too: bool):
    """Start the run, wait for its first coupling step, send ``signum``; returns
    (exit status, stderr, solver pid)."""
    proc = subprocess.Popen(_cmd(out, END), stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                            env=_env())
    try:
        t0 = time.monotonic()
        solver_pid = None
        while time.monotonic() - t0 < 300 and proc.poll() is None:
            kids = ([k for k in _children(proc.pid) if "thermoDemFoam" in _cmdline(k)]
                    if solver_pid is None else [solver_pid])
            if kids:
                solver_pid = kids[0]
            if solver_pid and (out / "coupling.csv").exists():   # first row: the loop has started
                break
            time.sleep(0.02)
        assert proc.poll() is None and solver_pid, "the run ended before it could be interrupted"
        proc.send_signal(signum)
        if solver_too:
            os.kill(solver_pid, signum)
        _, err = proc.communicate(timeout=300)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    return proc.returncode, err, solver_pid


@pytest.mark.parametrize("signum,code,solver_too", [(signal.SIGINT, 130, False), (signal.SIGTERM, 143, True)],
                         ids=["SIGINT", "SIGTERM-scheduler"])
def test_signal_stops_cleanly_and_continues(reference, tmp_path, signum, code, solver_too):
    out = tmp_path / "out"
    rc, err, solver_pid = _interrupt(out, signum, solver_too)
    assert rc == code, err[-3000:]
    assert not _alive(solver_pid), "thermoDemFoam left running"
    lines = [x for x in err.splitlines() if x.strip()]
    assert len(lines) == 1, err                                   # one line, no traceback
    name = signal.Signals(signum).name
    m = re.fullmatch(rf"coupling: stopped by {name} at t = (\S+) s \(coupling step (\d+)\); restart point "
                     rf"(\S+) \(gas: .*\); continue with: (coupling run .* --restart --end-time \S+)", lines[0])
    assert m, lines[0]
    step = int(m.group(2))
    assert 1 <= step < 2 * N and float(m.group(1)) == pytest.approx(step * DT)
    assert Path(m.group(3)) == out / "checkpoints" / f"checkpoint_{step:08d}.npz" and Path(m.group(3)).is_file()
    assert (out / "checkpoints" / f"coupling_{step:08d}.npz").is_file()
    assert (out / f"{step * DT:g}" / "U").is_file()                 # the gas wrote the same step
    log = (out / "log.thermoDemFoam").read_text()
    assert log.rstrip().endswith("End") and "FOAM FATAL" not in log     # the solver ended cleanly
    assert float(np.load(out / "checkpoint.npz")["step_count"]) > 0
    # the printed command continues to the end and gives the uninterrupted run
    cont = m.group(4).split()
    assert cont[:2] == ["coupling", "run"]
    p = subprocess.run([sys.executable, "-m", "coupling.run", *cont[1:], "--quiet"], capture_output=True,
                       text=True, env=_env(), timeout=600)
    assert p.returncode == 0, p.stderr[-3000:]
    _assert_same_run(reference, out)


def test_corrupt_coupling_state_is_refused(first_half, tmp_path):
    """A damaged checkpoints/coupling_<step>.npz is refused naming the file (exit 2), before
    any gas time directory is removed. The damaged run is a copy of the module's first_half (N
    steps, continued to 2 N: the refusal comes before any step, so how many steps the damaged
    run had does not enter; it had 2, continued to 4, before)."""
    out = tmp_path / "out"
    shutil.copytree(first_half, out, symlinks=True)
    cs = out / "checkpoints" / f"coupling_{N:08d}.npz"
    data = bytearray(cs.read_bytes())
    data[len(data) // 2] ^= 0xFF
    cs.write_bytes(bytes(data))
    before = sorted(p.name for p in out.iterdir())
    p = subprocess.run(_cmd(out, END, "--restart"), capture_output=True, text=True, env=_env(), timeout=600)
    assert p.returncode == 2, p.stderr
    assert str(cs) in p.stderr and "Traceback" not in p.stderr
    assert sorted(p.name for p in out.iterdir()) == before
    cs.unlink()
    p = subprocess.run(_cmd(out, END, "--restart"), capture_output=True, text=True, env=_env(), timeout=600)
    assert p.returncode == 2 and str(cs) in p.stderr and "missing" in p.stderr, p.stderr
