"""``dem compile`` / ``coupling compile`` (dem.compile): the warm-up jobs in parallel worker
processes, the lock around Numba's cache index, the command's exits. Sized for a 2-core
machine: at most two compiling processes at once, no timed assertions."""
import glob
import os
import pickle
import signal
import subprocess
import sys
import textwrap
import time

import pytest

from dem import compile as C

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


def _env(tmp_path, **extra):
    """The environment of a subprocess with its own, empty, Numba cache (dem._numba_cache_dir
    keys it on XDG_CACHE_HOME)."""
    env = {k: v for k, v in os.environ.items() if k not in ("NUMBA_CACHE_DIR", "NUMBA_DEBUG_CACHE")}
    env.update(XDG_CACHE_HOME=str(tmp_path / "xdg"), PYTHONPATH=ROOT + os.pathsep + env.get("PYTHONPATH", ""))
    env.update(extra)
    return env


def _cache_files(tmp_path):
    files = glob.glob(str(tmp_path / "xdg" / "**" / "*.nb[ic]"), recursive=True)
    return sorted(os.path.relpath(f, tmp_path) for f in files)


# --------------------------------------------------------------------------- the command line

@pytest.mark.parametrize("cmd", [["dem.cli", "compile"], ["coupling.run", "compile"]])
@pytest.mark.parametrize("value", ["0", "-2", "two", "1.5"])
def test_bad_jobs_value_exits_2_without_traceback(tmp_path, cmd, value):
    p = subprocess.run([sys.executable, "-m", *cmd, "--jobs", value], capture_output=True, text=True,
                       env=_env(tmp_path), cwd=ROOT, timeout=120)
    assert p.returncode == 2, p.stderr
    assert "--jobs" in p.stderr and "positive integer" in p.stderr and repr(value) in p.stderr
    assert "Traceback" not in p.stderr
    assert not (tmp_path / "xdg").exists() or _cache_files(tmp_path) == []


# --------------------------------------------------------------------------- the runner

def test_jobs_start_after_their_dependencies():
    jobs = [C.Job("a", "time:sleep", (0.3,)), C.Job("b", "time:sleep", (0.1,), after=("a",)),
            C.Job("c", "time:sleep", (0.1,)), C.Job("d", "time:sleep", (0.1,), after=("b", "c"))]
    lines = []
    times = C.run(jobs, 2, log=lines.append)
    assert set(times) == {"a", "b", "c", "d"} and len(lines) == 4
    assert times["b"][0] >= times["a"][1]
    assert times["d"][0] >= max(times["b"][1], times["c"][1])
    assert C.critical_path(jobs, times) == ["a", "b", "d"]


def test_declared_jobs_are_consistent():
    from coupling.run import compile_jobs
    C._check(list(C.DEM_JOBS))
    jobs = compile_jobs()
    C._check(jobs)
    names = [j.name for j in jobs]
    assert {j.name for j in C.DEM_JOBS} <= set(names) and len(names) > len(C.DEM_JOBS)
    # a case named alone: its job only, no DEM job, no dependency left dangling
    one = compile_jobs([os.path.join(ROOT, "openfoam_cases", "single_particle_heating")], dem_jobs=False)
    assert [(j.name, j.after) for j in one] == [("single_particle_heating", ())]
    with pytest.raises(ValueError, match="wait on each other"):
        C._check([C.Job("x", "time:sleep", after=("y",)), C.Job("y", "time:sleep", after=("x",))])


def test_a_failing_job_and_a_dying_worker_raise_compile_error():
    with pytest.raises(C.CompileError, match=r"compile job bad failed:(.|\n)*ValueError"):
        C.run([C.Job("bad", "math:sqrt", (-1.0,)), C.Job("ok", "time:sleep", (0.01,))], 2, log=lambda s: None)
    with pytest.raises(C.CompileError, match=r"compile job dies: its worker process died \(exit code 3\)"):
        C.run([C.Job("dies", "os:_exit", (3,))], 1, log=lambda s: None)


def _notice_off():
    """A compile job: in the worker that runs it, the compile notice of dem.stepper is off."""
    from dem import stepper
    delay = stepper.compile_notice_delay()
    if not delay < 0:
        raise AssertionError(f"a compile worker would say 'note: compiling the step' after {delay} s")


def test_compile_workers_say_nothing_of_the_compile_they_are_for(monkeypatch):
    """`dem compile` / `coupling compile` (the set-up) compile on purpose: their workers never
    print the notice a run prints when it compiles unexpectedly, whatever the user's
    THERMODEM_COMPILE_NOTICE_AFTER (here 0: any compile would be announced)."""
    monkeypatch.setenv("THERMODEM_COMPILE_NOTICE_AFTER", "0")
    C.run([C.Job("quiet", "test_compile:_notice_off")], 1, log=lambda s: None)


# --------------------------------------------------------------------------- the lock

TOY = '''
import numba


@numba.njit(cache=True)
def length(t):
    return len(t)
'''

WORKER = '''
import os, sys, time
sys.path.insert(0, {tmp!r})
import dem   # the cache folder (XDG_CACHE_HOME)
from dem.compile import install_index_lock
if sys.argv[3] == "lock":
    install_index_lock()
import toy
start, count = int(sys.argv[1]), int(sys.argv[2])
while not os.path.exists({go!r}):   # every process ready before any compiles
    time.sleep(0.01)
for k in range(start, start + count):
    assert toy.length((1,) * k) == k   # a signature of its own: UniTuple(int64, k)
'''


def _compile_concurrently(tmp_path, procs, per, lock):
    (tmp_path / "toy.py").write_text(TOY)
    go = tmp_path / "go"
    script = tmp_path / "worker.py"
    script.write_text(textwrap.dedent(WORKER.format(tmp=str(tmp_path), go=str(go))))
    env = _env(tmp_path)
    ps = [subprocess.Popen([sys.executable, str(script), str(1 + i * per), str(per), lock], env=env, cwd=ROOT,
                           stderr=subprocess.PIPE, text=True) for i in range(procs)]
    time.sleep(0.5)
    go.write_text("")
    for p in ps:
        _, err = p.communicate(timeout=600)
        assert p.returncode == 0, err[-3000:]
    (index,) = glob.glob(str(tmp_path / "xdg" / "**" / "toy.length-*.nbi"), recursive=True)
    with open(index, "rb") as fh:
        pickle.load(fh)   # numba's version
        _stamp, overloads = pickle.loads(fh.read())
    return index, overloads


def test_index_lock_keeps_every_entry_of_concurrent_saves(tmp_path):
    """Two processes compile distinct signatures of one cached function at the same time:
    with the lock (what the compile workers install) the index keeps every entry, each with a
    data file of its own, and a third process loads them all without compiling any."""
    procs, per = 2, 40
    index, overloads = _compile_concurrently(tmp_path, procs, per, "lock")
    assert len(overloads) == procs * per
    names = set(overloads.values())
    assert len(names) == procs * per
    assert all(os.path.isfile(os.path.join(os.path.dirname(index), n)) for n in names)
    check = tmp_path / "check.py"
    check.write_text(textwrap.dedent(f'''
        import sys
        sys.path.insert(0, {str(tmp_path)!r})
        import dem, toy
        for k in range(1, {procs * per + 1}):
            assert toy.length((1,) * k) == k
        assert len(toy.length.stats.cache_hits) == {procs * per}, toy.length.stats
        assert sum(toy.length.stats.cache_misses.values()) == 0, toy.length.stats
    '''))
    p = subprocess.run([sys.executable, str(check)], capture_output=True, text=True, env=_env(tmp_path), cwd=ROOT,
                       timeout=600)
    assert p.returncode == 0, p.stderr[-3000:]


# --------------------------------------------------------------------------- the whole compile

def _as_from_a_shell():
    """In the child before exec: SIGINT delivered and handled by default, as for a command typed
    in a shell (a child inherits ignored signals and the blocked mask of the test runner's
    thread: twice in the full suite, the child ignored the SIGINT below)."""
    signal.pthread_sigmask(signal.SIG_UNBLOCK, [signal.SIGINT])
    signal.signal(signal.SIGINT, signal.SIG_DFL)


def _setup_compile_copy(tmp_path):
    """The cache the set-up's compile wrote into an empty cache folder (scripts/test.sh has
    scripts/setup.sh leave a hard-linked copy of it under THERMODEM_TEST_SETUP_CACHE, in a folder
    named as the cache, by the sources' digest), copied to where this test's processes look for
    their cache (replacing what the interrupted compile left there); None when there is none
    (pytest run on its own, a set-up that found its cache already there, or sources edited since)."""
    import shutil
    import dem
    name = dem.source_digest()[:16]
    src = os.path.join(os.environ.get("THERMODEM_TEST_SETUP_CACHE", ""), name)
    if not os.environ.get("THERMODEM_TEST_SETUP_CACHE") or not os.path.isdir(src):
        return None
    shutil.rmtree(tmp_path / "xdg")
    dst = tmp_path / "xdg" / "thermodem" / "numba" / name
    shutil.copytree(src, dst)
    return dst


def test_compile_fills_the_cache_and_the_examples_then_compile_nothing(tmp_path):
    """An interrupted `dem compile` (SIGINT) exits 130 with one line and no traceback; then
    `dem compile --jobs 2` into the same cache fills it, and a first `dem run` of each example
    loads every kernel from it (no cache file added, no kernel saved).

    Under scripts/test.sh the compile of an empty cache was just done by the set-up (the same
    compile, `coupling compile`, DEM and coupling jobs, 2 processes) and the test reads a copy of
    what it wrote, the same files and entries (THERMODEM_TEST_SETUP_CACHE): then `dem compile
    --jobs 2` on that copy must compile nothing (no file added) and the checks below hold for the
    set-up's own cache. Without the copy (pytest on its own) the test compiles the empty cache
    itself (about 2 minutes on 2 cores)."""
    from test_reliability_coupled_restart import _children   # (the tests' folder is on the path under pytest)
    env = _env(tmp_path)
    p = subprocess.Popen([sys.executable, "-m", "dem.cli", "compile", "--jobs", "2"], env=env, cwd=ROOT,
                         stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, preexec_fn=_as_from_a_shell)
    # compiling: the parent's imports are done once it has started its workers (a fixed delay
    # could fall in the imports of a loaded machine, where the suite once saw the signal lost)
    t0 = time.monotonic()
    while len(_children(p.pid)) < 2 and p.poll() is None and time.monotonic() - t0 < 120:
        time.sleep(0.2)
    time.sleep(3.0)
    p.send_signal(signal.SIGINT)
    out, err = p.communicate(timeout=120)
    assert p.returncode == 130, out + err
    assert "Traceback" not in err and err.strip().count("\n") == 0 and "interrupted" in err, err

    copied = _setup_compile_copy(tmp_path)
    setup_files = _cache_files(tmp_path)
    p = subprocess.run([sys.executable, "-m", "dem.cli", "compile", "--jobs", "2"], capture_output=True, text=True,
                       env=env, cwd=ROOT, timeout=1800)
    assert p.returncode == 0, p.stdout[-2000:] + p.stderr[-3000:]
    assert "kernels compiled and cached in" in p.stdout and "(2 processes)" in p.stdout
    for job in C.DEM_JOBS:
        assert f"  {job.name}: compiled in " in p.stdout
    # the compile it was asked for is no surprise: no "compiling the step ... once" notice
    assert "note: compiling" not in p.stdout + p.stderr, p.stderr[-2000:]
    before = _cache_files(tmp_path)
    assert len(before) > 100
    if copied is not None:
        assert before == setup_files, "dem compile added to the set-up's cache: " + \
            ", ".join(sorted(set(before) - set(setup_files)))[:2000]
    # compute_forces and heat_step, compiled alone by signature (dem.compile.forces, heat_step),
    # have the types dem.step.advance calls them with, and the heat step's parallel loops
    # (dem.compile.heat_blocks) those heat_step calls them with: one entry per heat switch (and
    # for compute_forces per form, lean or full: dem.step.full_form), none added by the compile
    # of their caller
    for kernel, entries in (("step.compute_forces", 4), ("heat.heat_step", 1), ("heat._heat_blocks", 1),
                            ("heat._radiation_accumulators_blocks", 1),
                            ("implicit.jacobi_pcg_blocks", 1), ("implicit.pair_heat_blocks", 1)):
        (index,) = glob.glob(str(tmp_path / "xdg" / "**" / f"{kernel}-*.nbi"), recursive=True)
        with open(index, "rb") as fh:
            pickle.load(fh)
            _stamp, overloads = pickle.loads(fh.read())
        assert len(overloads) == entries, (kernel, list(overloads))
    for scene, end in (("settle_box", "0.002"), ("rotating_drum", "0.002"), ("packed_bed_heating", "2")):
        r = subprocess.run([sys.executable, "-m", "dem.cli", "run", os.path.join("examples", f"{scene}.toml"),
                            "--end-time", end, "--out", str(tmp_path / "out" / scene), "--quiet"],
                           capture_output=True, text=True, cwd=ROOT, timeout=600,
                           env=dict(env, NUMBA_DEBUG_CACHE="1", THERMODEM_COMPILE_NOTICE_AFTER="8"))
        assert r.returncode == 0, r.stdout[-2000:] + r.stderr[-3000:]
        assert "data saved" not in r.stdout, (scene, [ln for ln in r.stdout.splitlines() if "data saved" in ln])
        assert _cache_files(tmp_path) == before, scene
        # loaded from the cache in a second or two: no notice of a compile
        assert "note: compiling the step" not in r.stderr, (scene, r.stderr[-2000:])

    # a form the set-up does not compile (the projected tangential spring): the first run says
    # that it compiles, once, on stderr, and runs; the next run loads it and says nothing
    scene = tmp_path / "projected.toml"
    with open(os.path.join(ROOT, "examples", "settle_box.toml")) as fh:
        text = fh.read()
    text = text.replace('rolling = "epsd"', 'rolling = "epsd"\ntangential = "projected"')
    assert 'tangential = "projected"' in text
    scene.write_text(text)
    for k, (delay, said) in enumerate((("1", True), ("8", False), ("soon", False))):
        r = subprocess.run([sys.executable, "-m", "dem.cli", "run", str(scene), "--end-time", "0.002",
                            "--out", str(tmp_path / "out" / f"projected{k}"), "--quiet"], capture_output=True,
                           text=True, env=dict(env, THERMODEM_COMPILE_NOTICE_AFTER=delay), cwd=ROOT, timeout=900)
        assert r.returncode == 0, r.stdout[-2000:] + r.stderr[-3000:]
        notes = [ln for ln in r.stderr.splitlines() if ln.startswith("note: compiling the step")]
        assert len(notes) == (1 if said else 0), r.stderr[-3000:]
        if said:
            assert "tangential projected" in notes[0] and "full form" in notes[0] and "once" in notes[0]
        # a value that is not a number: said in one line, the default taken, the run goes on
        assert ("THERMODEM_COMPILE_NOTICE_AFTER='soon' is not a number" in r.stderr) == (delay == "soon")
        assert "Traceback" not in r.stderr
