"""Interruptions, kills and full disks of `dem run`, on real processes through the command line
(docs/reliability/signals.md).

- SIGINT / SIGTERM / SIGUSR1 to a running `dem run` (serial, and `mpirun -np 2`): exit 130 / 143 / 138, one line
  with the time reached, the checkpoint and the command to continue; that command runs to the end
  and gives the final state of an uninterrupted run. Serial: bit-identical (the step arithmetic does
  not depend on where the loop pauses and the serial checkpoint holds every array the next step
  reads, neighbour lists and contact histories included), asserted exactly. MPI: a restart rebuilds
  the neighbour lists and ghosts, so contact forces are summed in another order: equal to round-off
  (bounds of tests/test_parallel.py).
- The chunk size (THERMODEM_CHUNK_SECONDS) does not change a run's result: bit-identical.
- kill -9 at random instants of a run writing a checkpoint every 2 ms of simulated time: the
  checkpoint always loads, complete; the next start removes the stale temporaries (ours only).
- A full disk (2 MiB tmpfs as --out): exit 3, one line naming the file, no traceback, no 0-byte or
  temporary file, the earlier checkpoint byte-identical.
"""
import contextlib
import glob
import hashlib
import json
import os
import random
import re
import shlex
import shutil
import signal
import subprocess
import sys
import time

import numpy as np
import pytest

HERE = os.path.dirname(os.path.abspath(__file__))
ROOT = os.path.dirname(HERE)
SCENE = os.path.join(HERE, "scenes", "signals_bed.toml")
END = 0.03          # serial runs: 3,000 steps
FIELDS = ("position", "velocity", "angular_velocity", "temperature")
MPI_ENV = dict(OMPI_ALLOW_RUN_AS_ROOT="1", OMPI_ALLOW_RUN_AS_ROOT_CONFIRM="1",
               OMPI_MCA_rmaps_base_oversubscribe="1", OMPI_MCA_mpi_yield_when_idle="1",
               # mpirun sends SIGCONT, waits this many seconds, sends SIGTERM, waits again, then
               # SIGKILL (default 1 s: too short to finish a chunk and write a checkpoint)
               OMPI_MCA_odls_base_sigkill_timeout="3")


def env(**extra):
    e = dict(os.environ, PYTHONPATH=ROOT + os.pathsep + os.environ.get("PYTHONPATH", ""))
    e.update(extra)
    return e


def dem(*args):
    return [sys.executable, "-m", "dem", *args]


def history_rows(out):
    try:
        with open(os.path.join(out, "history.csv")) as fh:
            return max(len(fh.readlines()) - 1, 0)
    except OSError:
        return 0


def wait_for_rows(proc, out, rows, timeout=120):
    """Wait until history.csv has ``rows`` rows (the run is stepping), or the process ended."""
    t0 = time.monotonic()
    while history_rows(out) < rows:
        assert proc.poll() is None, f"the run ended before it could be signalled: {proc.communicate()}"
        assert time.monotonic() - t0 < timeout, "no progress in history.csv"
        time.sleep(0.05)


def load_all(path):
    """Every array of an npz (reads each member completely: a truncated file raises); a final.npz
    in either form (dem.output.read_final)."""
    if os.path.basename(path) == "final.npz":
        from dem.final import read as read_final
        return dict(read_final(path))
    with np.load(path) as z:
        return {k: z[k] for k in z.files}


def continue_argv(line):
    """The continue command of the interruption line, as argv running this checkout."""
    cmd = shlex.split(line.split("continue with: ", 1)[1])
    i = cmd.index("dem")
    return cmd[:i], dem(*cmd[i + 1:])


def assert_one_stop_line(stderr, signame, out):
    lines = [s for s in stderr.splitlines() if s.strip()]
    assert "Traceback" not in stderr
    stop = [s for s in lines if s.startswith("interrupted by")]
    assert len(stop) == 1, stderr
    m = re.match(rf"interrupted by {signame} at t = (\S+) s \(step (\d+)\); checkpoint written to (\S+); "
                 rf"continue with: .*dem run {re.escape(SCENE)} --out {re.escape(str(out))} --restart "
                 rf"{re.escape(os.path.join(str(out), 'checkpoint.npz'))}", stop[0])
    assert m, stop[0]
    return float(m.group(1)), int(m.group(2)), stop[0]


def assert_same(a, b, rel=0.0):
    assert np.array_equal(a["id"], b["id"])
    for k in FIELDS:
        scale = np.abs(a[k]).max()
        assert np.abs(a[k] - b[k]).max() <= rel * scale, k


@pytest.fixture(scope="module")
def reference(tmp_path_factory):
    """The uninterrupted serial run to END."""
    out = tmp_path_factory.mktemp("ref") / "out"
    p = subprocess.run(dem("run", SCENE, "--out", str(out), "--end-time", str(END), "--quiet"),
                       capture_output=True, text=True, env=env(), timeout=600)
    assert p.returncode == 0, p.stderr
    return load_all(out / "final.npz")


def test_chunk_size_does_not_change_the_result(tmp_path, monkeypatch):
    """One step per chunk and the adaptive chunks give bit-identical states (the moving lid
    makes each step's time enter the arithmetic)."""
    from dem import Simulation
    res = []
    for seconds in ("0", "1"):
        monkeypatch.setenv("THERMODEM_CHUNK_SECONDS", seconds)
        sim = Simulation.from_file(SCENE)
        sim.run(end_time=0.004, out_dir=str(tmp_path / seconds), progress=False)
        res.append(load_all(tmp_path / seconds / "final.npz"))
    assert_same(res[0], res[1], rel=0.0)
    assert np.ptp(res[0]["temperature"]) > 0.0  # the floor heated some beads


@pytest.mark.parametrize("sig,code", [(signal.SIGINT, 130), (signal.SIGTERM, 143), (signal.SIGUSR1, 138)])
def test_signal_checkpoints_and_continues_exactly(reference, tmp_path, sig, code):
    out = tmp_path / "out"
    p = subprocess.Popen(dem("run", SCENE, "--out", str(out), "--end-time", str(END), "--quiet"),
                         stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env())
    wait_for_rows(p, out, 4)
    p.send_signal(sig)
    _, err = p.communicate(timeout=120)
    assert p.returncode == code, err
    t, step, line = assert_one_stop_line(err, signal.Signals(sig).name, out)
    assert 0 < step < int(round(END / 1e-5)) and t == pytest.approx(step * 1e-5, rel=1e-12)
    ck = load_all(out / "checkpoint.npz")
    assert int(ck["step_count"]) == step
    assert not (out / "final.npz").exists()  # the run did not end
    assert not glob.glob(str(out / "**" / ".tmp_*"), recursive=True)
    # the history holds the state reached, the last row at the time of the interruption
    h = np.genfromtxt(out / "history.csv", delimiter=",", names=True)
    assert h["time"][-1] == pytest.approx(t, rel=1e-12)
    prefix, argv = continue_argv(line)
    assert prefix == []
    q = subprocess.run(argv, capture_output=True, text=True, env=env(), timeout=600)
    assert q.returncode == 0, q.stderr
    assert_same(reference, load_all(out / "final.npz"), rel=0.0)
    h = np.genfromtxt(out / "history.csv", delimiter=",", names=True)
    assert np.all(np.diff(h["time"]) > 0) and h["time"][-1] == pytest.approx(END)


@pytest.mark.skipif(shutil.which("mpirun") is None, reason="needs Open MPI (mpirun)")
@pytest.mark.parametrize("sig,seen,code,timeout", [(signal.SIGINT, "SIGTERM", 143, "3"),
                                                   (signal.SIGUSR1, "SIGUSR1", 138, "1")])
def test_mpirun_signal_stops_every_rank_with_a_checkpoint(tmp_path, sig, seen, code, timeout):
    """Ctrl-C to mpirun: Open MPI 4.1 sends SIGCONT to every rank at once and SIGTERM only
    odls_base_sigkill_timeout seconds later. SIGUSR1 to mpirun is forwarded to every rank at
    once and mpirun kills nothing (exit 138: no SIGTERM ever reached the ranks), so the default
    1 s timeout is enough. Either way the ranks stop at the same step, the root writes the
    checkpoint, and continued 100 steps further the run ends where an uninterrupted run on 2
    ranks ends, to round-off."""
    out, ref = tmp_path / "out", tmp_path / "ref"
    base = ["mpirun", "-np", "2"]
    mpi_env = env(**dict(MPI_ENV, OMPI_MCA_odls_base_sigkill_timeout=timeout), THERMODEM_CHUNK_SECONDS="0.2")
    # each rank's exit status, recorded by a shell that ignores the signals itself
    rank = ("trap '' INT TERM USR1; \"$@\"; echo $? > " + shlex.quote(str(tmp_path)) +
            "/rc.$OMPI_COMM_WORLD_RANK")
    p = subprocess.Popen(base + ["sh", "-c", rank, "sh"] +
                         dem("run", SCENE, "--out", str(out), "--end-time", "0.5", "--quiet"),
                         stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=mpi_env)
    wait_for_rows(p, out, 2)
    p.send_signal(sig)
    _, err = p.communicate(timeout=120)
    codes = [int(open(tmp_path / f"rc.{k}").read()) for k in (0, 1)]
    assert codes == [code, code], err
    t, step, line = assert_one_stop_line(err, seen, out)
    assert int(load_all(out / "checkpoint.npz")["step_count"]) == step
    prefix, argv = continue_argv(line)
    assert prefix == ["mpirun", "-np", "2"] and argv[-3:] == ["--end-time", "0.5", "--quiet"]
    end = repr((step + 100) * 1e-5)
    argv[-2] = end
    q = subprocess.run(prefix + argv, capture_output=True, text=True, env=mpi_env, timeout=600)
    assert q.returncode == 0, q.stderr
    r = subprocess.run(base + dem("run", SCENE, "--out", str(ref), "--end-time", end, "--quiet"),
                       capture_output=True, text=True, env=mpi_env, timeout=600)
    assert r.returncode == 0, r.stderr
    a, b = load_all(ref / "final.npz"), load_all(out / "final.npz")
    assert np.array_equal(a["id"], b["id"]) and int(round(float(a["time"]) / 1e-5)) == step + 100
    for k, tol in (("position", 1e-10), ("velocity", 1e-7), ("angular_velocity", 5e-4), ("temperature", 1e-9)):
        assert np.abs(a[k] - b[k]).max() <= tol, k


def test_kill9_during_checkpoint_writes_leaves_a_loadable_checkpoint(tmp_path):
    """A checkpoint every 100 steps (about 20 checkpoint writes a second): kill -9 at random
    instants, three times, continuing each time from the checkpoint the kill left."""
    scene = tmp_path / "scene.toml"
    text = open(SCENE).read().replace('seed = 11', 'seed = 11\ncheckpoint_interval = 0.001')
    scene.write_text(text)
    out = tmp_path / "out"
    rng = random.Random(3)
    step = 0
    for k in range(3):
        args = ["run", str(scene), "--out", str(out), "--quiet", "--end-time", "1.0"]
        if k:
            args += ["--restart", str(out / "checkpoint.npz")]
        p = subprocess.Popen(dem(*args), stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, env=env())
        # the first checkpoint of this start exists once history.csv grew by a few rows
        wait_for_rows(p, out, history_rows(out) + 3)
        time.sleep(rng.uniform(0.0, 1.0))
        p.kill()
        p.wait()
        ck = load_all(out / "checkpoint.npz")  # complete, whatever the instant of the kill
        assert int(ck["step_count"]) % 100 == 0 and int(ck["step_count"]) > step
        step = int(ck["step_count"])
    # a stale temporary of ours (as a kill leaves mid-write) and a user's look-alike file
    ours = out / ".tmp_thermodem_abcd1234.npz"
    ours.write_bytes(b"partial")
    (out / "vtk" / ".tmp_thermodem_x.vtu").write_bytes(b"")
    user = out / "vtk" / ".tmp_notes.txt"   # inside vtk/: a user's file at the top would be refused
    user.write_text("mine")                  # by the output-folder rule (tests/test_reliability_outdir.py)
    p = subprocess.Popen(dem("run", str(scene), "--out", str(out), "--quiet", "--end-time", "1.0",
                             "--restart", str(out / "checkpoint.npz")),
                         stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True, env=env())
    wait_for_rows(p, out, history_rows(out) + 1)
    p.send_signal(signal.SIGTERM)
    _, err = p.communicate(timeout=120)
    assert p.returncode == 143, err
    assert not glob.glob(str(out / "**" / ".tmp_thermodem_*"), recursive=True)
    assert user.read_text() == "mine"


def mount_tmpfs(folder, size):
    """Mount a tmpfs of ``size`` on ``folder`` (the result of `mount`; a failed result when the
    command is missing, so that the caller skips)."""
    try:
        return subprocess.run(["mount", "-t", "tmpfs", "-o", f"size={size}", "tmpfs", str(folder)],
                              capture_output=True, text=True)
    except FileNotFoundError:
        return subprocess.CompletedProcess(["mount"], 127, "", "mount: command not found")


def processes_mentioning(text):
    """pids of running processes whose command line contains ``text`` (read from /proc, so the
    test needs no procps); this test process itself excluded."""
    pids = []
    for d in os.listdir("/proc"):
        if not d.isdigit() or int(d) == os.getpid():
            continue
        try:
            with open(f"/proc/{d}/cmdline", "rb") as fh:
                cmd = fh.read().replace(b"\0", b" ").decode(errors="replace")
        except OSError:  # ended meanwhile
            continue
        if text in cmd:
            pids.append(int(d))
    return pids


@contextlib.contextmanager
def tiny_disk(tmp_path, size):
    """A tmpfs of ``size`` at tmp_path/disk, unmounted at the end whatever happens (the test
    is skipped where mounting is refused)."""
    d = tmp_path / "disk"
    d.mkdir()
    r = mount_tmpfs(d, size)
    if r.returncode != 0:
        pytest.skip(f"cannot mount a tmpfs here: {r.stderr.strip()}")
    try:
        yield d
    finally:
        subprocess.run(["umount", "-l", str(d)], capture_output=True)


@pytest.fixture
def small_disk(tmp_path):
    """A 2 MiB tmpfs."""
    with tiny_disk(tmp_path, "2m") as d:
        yield d


def sha(path):
    return hashlib.sha256(open(path, "rb").read()).hexdigest()


def fill(disk, leave):
    """Fill the disk with a file of the test's own, leaving about ``leave`` bytes free."""
    st = os.statvfs(disk)
    free = st.f_bavail * st.f_frsize
    with open(disk / "filler.bin", "wb") as fh:
        fh.write(b"\0" * max(free - leave, 0))


def test_disk_full_names_the_file_and_keeps_the_checkpoint(small_disk, tmp_path):
    """The disk fills while the continued run writes its checkpoint: the checkpoint written
    before is kept byte for byte (the new one went to a temporary name, removed)."""
    scene = tmp_path / "novtk.toml"  # no VTK: the history and final.npz fit, the checkpoint does not
    scene.write_text(open(SCENE).read().replace("vtk = true", "vtk = false"))
    out = small_disk / "out"
    first = subprocess.run(dem("run", str(scene), "--out", str(out), "--end-time", "0.004", "--quiet"),
                           capture_output=True, text=True, env=env(), timeout=600)
    assert first.returncode == 0, first.stderr
    ck = str(out / "checkpoint.npz")
    before = sha(ck)
    fill(small_disk, os.path.getsize(ck) // 2)
    p = subprocess.run(dem("run", str(scene), "--out", str(out), "--end-time", "0.008", "--quiet",
                           "--restart", ck), capture_output=True, text=True, env=env(), timeout=600)
    assert p.returncode == 3, p.stderr
    assert "Traceback" not in p.stderr
    lines = [s for s in p.stderr.splitlines() if s.strip()]
    assert len(lines) == 1, p.stderr
    assert lines[0].startswith(f"error: cannot write {ck}: the disk is full. "), lines[0]
    assert sha(ck) == before  # the earlier checkpoint, byte for byte
    assert int(load_all(ck)["step_count"]) == 400
    files = [f for f in glob.glob(str(out / "**" / "*"), recursive=True) if os.path.isfile(f)]
    assert not [f for f in files if os.path.getsize(f) == 0]
    assert not glob.glob(str(out / "**" / ".tmp_*"), recursive=True)
    assert load_all(out / "final.npz")["time"] == pytest.approx(0.008)  # written before the disk filled


@pytest.mark.skipif(shutil.which("mpirun") is None, reason="needs Open MPI (mpirun)")
def test_disk_full_under_mpirun_stops_every_rank(small_disk):
    """A rank cannot write its VTK piece (or the root its frame): every rank stops (no hang),
    exit 3, one line naming the file and the rank."""
    out = small_disk / "out"
    fill(small_disk, 60_000)
    p = subprocess.run(["mpirun", "-np", "2"] + dem("run", SCENE, "--out", str(out), "--end-time", "0.004",
                                                    "--quiet"),
                       capture_output=True, text=True, env=env(**MPI_ENV), timeout=600)
    assert p.returncode != 0
    assert "Traceback" not in p.stderr
    errs = [s for s in p.stderr.splitlines() if s.startswith("error:")]
    assert len(errs) == 1 and re.match(rf"error: cannot write {re.escape(str(out))}/\S+: the disk is full\. ",
                                       errs[0]), p.stderr
    assert re.search(r"\[rank [01] of 2\]$", errs[0]), errs[0]   # which rank could not write
    files = [f for f in glob.glob(str(out / "**" / "*"), recursive=True) if os.path.isfile(f)]
    assert not [f for f in files if os.path.getsize(f) == 0]
    assert not glob.glob(str(out / "**" / ".tmp_*"), recursive=True)


def test_coupled_run_on_a_full_disk(tmp_path, solver):
    """`coupling run` whose output disk fills (1 MiB tmpfs; the gas solver's log fills it):
    exit 4, one line naming the file, no traceback, no 0-byte or temporary file (timings.json
    used to be left empty), the solver stopped."""
    with tiny_disk(tmp_path, "1m") as disk:
        case = tmp_path / "case"
        shutil.copytree(os.path.join(ROOT, "openfoam_cases", "single_particle_heating"), case)
        out = disk / "out"
        p = subprocess.run([sys.executable, "-m", "coupling.run", "run", str(case), "--out", str(out),
                            "--end-time", "3.0", "--quiet"], capture_output=True, text=True, env=env(),
                           timeout=600)
        assert p.returncode == 4, p.stderr[-3000:]
        assert "Traceback" not in p.stderr
        errs = [s for s in p.stderr.splitlines() if s.strip()]
        assert len(errs) == 1, p.stderr[-3000:]
        m = re.match(r"coupling: error: cannot write (\S+): the disk is full\. ", errs[0])
        assert m and m.group(1).startswith(str(out)), errs[0]
        files = [f for f in glob.glob(str(out / "**" / "*"), recursive=True) if os.path.isfile(f)]
        # (the gas's <case>.foam opener is empty by design: ParaView reads the folder around it)
        assert not [f for f in files if os.path.getsize(f) == 0 and not f.endswith((".pid", ".foam"))], files
        assert not glob.glob(str(out / "**" / ".tmp_*"), recursive=True)
        for f in files:
            if f.endswith(".npz"):
                load_all(f)
        # the gas solver was stopped: no process left running on this case
        assert not processes_mentioning(str(out))


# A 2-rank run to 1 ms, then the disk filled, then each folder-making collective write called
# outside run() (where the coupled run's failure path calls the checkpoint: the gas solver
# died of the same full disk): every rank must get the OutputError, none wait for the root.
_FOLDER_WRITES_ON_A_FULL_DISK = r"""
import json, os, sys
from dem.output import OutputError
from dem.simulation import Simulation

scene, out, report = sys.argv[1:4]
sim = Simulation.from_file(scene)
sim.run(end_time=1e-3, out_dir=out)
comm = sim.par.comm
if comm.Get_rank() == 0:
    with open(os.path.join(os.path.dirname(out), "filler.bin"), "wb") as fh:
        try:
            while True:
                fh.write(bytes(65536))
                fh.flush()
        except OSError:
            pass
comm.Barrier()
got = {}
for what, call in [("checkpoint", lambda: sim.write_checkpoint(os.path.join(out, "more.npz"))),
                   ("vtk", lambda: sim.writers.vtk_series(out, name="more")),
                   ("final", lambda: sim.writers.write_final(os.path.join(out, "more_final.npz")))]:
    try:
        call()
        got[what] = None
    except OutputError as exc:
        got[what] = str(exc)
json.dump(got, open(os.path.join(report, f"rank{comm.Get_rank()}.json"), "w"))
"""


@pytest.mark.skipif(shutil.which("mpirun") is None, reason="needs Open MPI (mpirun)")
def test_folder_writes_on_a_full_disk_stop_every_rank(tmp_path):
    """A checkpoint, a VTK series and a final output written under MPI outside run() on a full
    disk: the root cannot make their pieces' folder and every rank raises its OutputError, naming
    the folder and the root (before the fix the other ranks waited at a barrier for ever)."""
    scene = tmp_path / "novtk.toml"   # no vtk/ made by the run: the VTK series makes it on the full disk
    scene.write_text(open(SCENE).read().replace("vtk = true", "vtk = false"))
    with tiny_disk(tmp_path, "3m") as disk:
        out = disk / "out"
        p = subprocess.run(["mpirun", "-np", "2", sys.executable, "-c", _FOLDER_WRITES_ON_A_FULL_DISK,
                            str(scene), str(out), str(tmp_path)], capture_output=True, text=True,
                           env=env(**MPI_ENV), timeout=300)
        assert p.returncode == 0, p.stderr[-3000:]
        ranks = [json.load(open(tmp_path / f"rank{r}.json")) for r in range(2)]
        assert ranks[0] == ranks[1]
        for what, folder in [("checkpoint", "more.pieces"), ("vtk", "vtk"), ("final", "more_final.pieces")]:
            msg = ranks[0][what]
            assert msg is not None, what
            assert re.match(rf"cannot write {re.escape(str(out / folder))}: the disk is full\. .*\[rank 0 of 2\]$",
                            msg), msg


@pytest.mark.skipif(shutil.which("mpirun") is None, reason="needs Open MPI (mpirun)")
def test_coupled_two_by_two_on_a_full_disk(tmp_path, solver):
    """`mpirun -np 2 coupling run` with 2 gas processes whose output disk fills (3 MiB tmpfs:
    the run needs about 5): every DEM rank and every gas processor ends, exit 4, one error
    line naming the file (and the DEM rank that could not write it), no traceback, no
    temporary file, no process left running on the case."""
    with tiny_disk(tmp_path, "3m") as disk:
        case = tmp_path / "case"
        shutil.copytree(os.path.join(ROOT, "openfoam_cases", "fluidized_bed_heating"), case)
        t = case / "coupling.toml"
        t.write_text(t.read_text().replace("[coupling]\n", "[coupling]\ngas_processes = 2\n", 1))
        out = disk / "out"
        p = subprocess.run(["mpirun", "-np", "2", sys.executable, "-m", "coupling.run", "run", str(case),
                            "--out", str(out), "--end-time", "0.05", "--quiet"], capture_output=True, text=True,
                           env=env(**MPI_ENV), timeout=900)
        assert p.returncode != 0 and "Traceback" not in p.stderr, p.stderr[-3000:]
        errs = [s for s in p.stderr.splitlines() if "error" in s.lower()]
        assert len(errs) == 1, p.stderr[-3000:]
        m = re.match(r"coupling: error: cannot write (\S+): the disk is full\. .*", errs[0])
        assert m and m.group(1).startswith(str(out)), errs[0]
        if "pieces" in m.group(1):   # a DEM rank's own piece: the line names the rank
            assert re.search(r"\[rank [01] of 2\]$", errs[0]), errs[0]
        assert not glob.glob(str(out / "**" / ".tmp_*"), recursive=True)
        deadline = time.monotonic() + 30
        while processes_mentioning(str(out)) and time.monotonic() < deadline:
            time.sleep(0.5)
        assert not processes_mentioning(str(out))
