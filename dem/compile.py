"""``dem compile`` / ``coupling compile``: fill Numba's cache in parallel worker processes.

The warm-up is declared as data: a list of :class:`Job`, each naming a small function
("module:function") that builds a throwaway scene and runs it, so that it compiles one group
of kernels (and saves them in Numba's on-disk cache, dem._numba_cache_dir). The jobs run in
N spawned worker processes (N = the usable cores by default); ``after`` names the jobs whose
kernels a job calls too, so that it starts once they are in the cache and loads them instead
of compiling them a second time in parallel.

Numba keeps one index file (.nbi) per cached function, which every process that saves an
entry reads, extends and replaces: two processes saving entries of the same function at the
same time can each write an index without the other's entry, and both can pick the same data
file name (an entry lost, or a key pointing at another signature's machine code). The
workers therefore hold an exclusive ``fcntl.flock`` on a lock file in the cache folder
around each save (:func:`install_index_lock`); a normal run (one process) is left as Numba
made it. docs/architecture.md, "Compiling the kernels"; docs/reliability.md for the faults.
"""
from __future__ import annotations

import importlib
import os
import signal
import sys
import tempfile
import time
import traceback
from dataclasses import dataclass

LOCK_NAME = ".thermodem-index.lock"


@dataclass(frozen=True)
class Job:
    """One warm-up: ``target`` ("module:function") called with ``args`` in a worker, after the
    jobs named in ``after`` have finished."""
    name: str
    target: str
    args: tuple = ()
    after: tuple = ()


class CompileError(RuntimeError):
    """A warm-up job failed (its traceback in the message) or its worker died."""


# --------------------------------------------------------------------------- the lock

def install_index_lock():
    """Serialise Numba's cache saves across processes (this process's saves from now on):
    ``IndexDataCacheFile.save`` (read the index, add the key, write the index, write the data
    file) runs under an exclusive flock on ``<cache folder>/.thermodem-index.lock``."""
    import fcntl
    from numba.core import caching
    orig = caching.IndexDataCacheFile.save
    if getattr(orig, "_thermodem_locked", False):
        return

    def save(self, key, data):
        with open(os.path.join(self._cache_path, LOCK_NAME), "a") as fh:
            fcntl.flock(fh, fcntl.LOCK_EX)
            try:
                return orig(self, key, data)
            finally:
                fcntl.flock(fh, fcntl.LOCK_UN)
    save._thermodem_locked = True
    caching.IndexDataCacheFile.save = save


# --------------------------------------------------------------------------- the runner

def default_jobs():
    """The number of worker processes by default: the cores this process may use."""
    try:
        return len(os.sched_getaffinity(0))
    except (AttributeError, OSError):
        return os.cpu_count() or 1


def jobs_argument(text):
    """argparse type of ``--jobs``: a positive integer (else argparse's exit 2 and message)."""
    import argparse
    try:
        n = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"must be a positive integer (worker processes), got {text!r}") from None
    if n < 1:
        raise argparse.ArgumentTypeError(f"must be a positive integer (worker processes), got {text!r}")
    return n


def _resolve(target):
    mod, _, fn = target.partition(":")
    return getattr(importlib.import_module(mod), fn)


def _worker(conn):
    """A worker process: runs the jobs it is sent, one at a time, until it gets None."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)   # the parent stops the workers (terminate)
    # compiling is what this process is for: no "note: compiling the step ..." of a run that
    # compiles unexpectedly (dem.stepper, a negative delay turns it off); the parent prints
    # one line per job with its time instead
    os.environ["THERMODEM_COMPILE_NOTICE_AFTER"] = "-1"
    install_index_lock()
    while True:
        try:
            msg = conn.recv()
        except EOFError:   # the parent is gone
            return
        if msg is None:
            return
        name, target, args = msg
        t0 = time.perf_counter()
        try:
            _resolve(target)(*args)
            conn.send((name, None, time.perf_counter() - t0))
        except BaseException:   # noqa: BLE001 (reported by the parent, with the traceback)
            conn.send((name, traceback.format_exc(), time.perf_counter() - t0))


def _check(jobs):
    names = [j.name for j in jobs]
    if len(set(names)) != len(names):
        raise ValueError(f"duplicate job names: {names}")
    for j in jobs:
        for a in j.after:
            if a not in names:
                raise ValueError(f"job {j.name}: 'after' names an unknown job {a!r}")
    done, left = set(), list(jobs)
    while left:   # every job can start at some point (no cycle)
        ready = [j for j in left if set(j.after) <= done]
        if not ready:
            raise ValueError(f"jobs wait on each other: {[j.name for j in left]}")
        done |= {j.name for j in ready}
        left = [j for j in left if j not in ready]


def run(jobs, processes=None, log=None):
    """Run ``jobs`` in ``processes`` spawned workers (default :func:`default_jobs`, at most one
    per job), each job once its ``after`` jobs have finished, the longest-waiting first.
    Returns {name: (start, end)} in seconds from the start. Raises CompileError when a job
    fails or a worker dies (the other workers are stopped), KeyboardInterrupt as it came."""
    import multiprocessing as mp
    from multiprocessing.connection import wait
    _check(jobs)
    log = log or _print
    n = max(1, min(processes or default_jobs(), len(jobs)))
    ctx = mp.get_context("spawn")
    t0 = time.perf_counter()
    workers = []
    for _ in range(n):
        parent, child = ctx.Pipe()
        p = ctx.Process(target=_worker, args=(child,), daemon=True)
        p.start()
        child.close()
        workers.append([p, parent, None])          # process, connection, running job
    pending = list(jobs)
    started, times = {}, {}
    try:
        while pending or any(w[2] for w in workers):
            for w in workers:
                if w[2] is None:
                    ready = [j for j in pending if all(a in times for a in j.after)]
                    if ready:
                        job = ready[0]
                        pending.remove(job)
                        started[job.name] = time.perf_counter() - t0
                        w[1].send((job.name, job.target, tuple(job.args)))
                        w[2] = job.name
            busy = [w for w in workers if w[2]]
            if not busy:
                raise CompileError("no job can start (unknown 'after')")
            hit = wait([w[1] for w in busy] + [w[0].sentinel for w in busy])
            for w in busy:
                if w[1] in hit:
                    try:
                        name, err, _ = w[1].recv()
                    except EOFError:
                        err, name = None, w[2]
                        hit.append(w[0].sentinel)
                    else:
                        if err:
                            raise CompileError(f"compile job {name} failed:\n{err.rstrip()}")
                        times[name] = (started[name], time.perf_counter() - t0)
                        w[2] = None
                        log(f"  {name}: compiled in {times[name][1] - times[name][0]:.1f} s "
                            f"({times[name][0]:.1f} .. {times[name][1]:.1f} s)")
                        continue
                if w[0].sentinel in hit and w[2]:
                    w[0].join(1.0)
                    raise CompileError(f"compile job {w[2]}: its worker process died (exit code "
                                       f"{w[0].exitcode}); what it saved before is usable, run the "
                                       "command again to compile the rest")
    except BaseException:
        for p, _, _ in workers:
            if p.is_alive():
                p.terminate()
        for p, _, _ in workers:
            p.join(5.0)
        raise
    for p, conn, _ in workers:
        try:
            conn.send(None)
        except OSError:
            pass
    for p, _, _ in workers:
        p.join(10.0)
    return times


def _print(line):
    print(line, flush=True)


def critical_path(jobs, times):
    """The chain of jobs that ended last: the job that ended last, preceded by whichever of its
    ``after`` jobs ended last, and so on."""
    by = {j.name: j for j in jobs}
    name = max(times, key=lambda k: times[k][1])
    chain = [name]
    while by[name].after:
        name = max(by[name].after, key=lambda k: times[k][1])
        chain.append(name)
    return list(reversed(chain))


def main_compile(jobs, processes, what="kernels", log=None):
    """Run the jobs, print per-job times, the critical path and the total; the exit status
    (0, 1 when a job failed, 130/143 when interrupted: one line, no traceback)."""
    t0 = time.perf_counter()
    log = log or _print
    n = max(1, min(processes or default_jobs(), len(jobs)))
    stop = _TermAsInterrupt()
    try:
        with stop:
            times = run(jobs, n, log=log)
    except CompileError as exc:
        print(f"error: {exc}", file=sys.stderr, flush=True)
        return 1
    except KeyboardInterrupt:
        sig = "SIGTERM" if stop.termed else "SIGINT"
        print(f"interrupted by {sig}: compiling stopped; the kernels saved so far stay in the cache "
              f"(complete entries only), the command compiles the rest when run again", file=sys.stderr,
              flush=True)
        return 143 if stop.termed else 130
    chain = critical_path(jobs, times)
    log(f"critical path: {' -> '.join(f'{c} {times[c][1] - times[c][0]:.1f} s' for c in chain)}")
    log(f"{what} compiled and cached in {time.perf_counter() - t0:.1f} s ({n} process{'es' if n > 1 else ''})")
    return 0


class _TermAsInterrupt:
    """SIGTERM raises KeyboardInterrupt in the main thread while compiling (stops the workers)."""
    termed = False

    def __enter__(self):
        def on_term(signum, frame):
            self.termed = True
            raise KeyboardInterrupt("SIGTERM")
        try:
            self._old = signal.signal(signal.SIGTERM, on_term)
        except ValueError:   # not the main thread
            self._old = None
        return self

    def __exit__(self, *exc):
        if self._old is not None:
            signal.signal(signal.SIGTERM, self._old)
        return False


# --------------------------------------------------------------------------- the DEM jobs

_MAT = dict(name="m", density=2500.0, youngs_modulus=1e7, poisson_ratio=0.3, restitution=0.5,
            friction=0.3, thermal_conductivity=1.0, heat_capacity=840.0)


def _base(full=False):
    """A throwaway scene of two particles and a floor; ``full``: with a rolling model, so that
    its step is the full form of the interact phase (dem.step.full_form), else the lean one."""
    data = {"simulation": {"time_step": 1e-5, "end_time": 1e-4},
            "domain": {"min": [-0.01] * 3, "max": [0.01] * 3}, "materials": [dict(_MAT)],
            "particles": [{"material": "m", "positions": [[0, 0, 0], [0.00199, 0, 0]], "radius": 1e-3}],
            "walls": [{"type": "plane", "point": [0, 0, -0.001], "normal": [0, 0, 1], "material": "m"}]}
    if full:
        data["materials"][0]["rolling_friction"] = 0.02
        data["contact"] = {"model": "hertz_mindlin", "rolling": "epsd"}
    return data


def _thermal(full=False):
    return dict(_base(full), thermal={"direct": "batchelor_obrien", "initial_temperature": 300.0})


def _state(hon, full=False):
    """The declared state of a throwaway scene (with heat or not), no kernel run yet: the
    bundles every kernel takes have the types of every scene's (dem.schema)."""
    from . import scene
    from .world import World
    return World(scene.parse(_thermal(full) if hon else _base(full), "<compile>")).state


def _compile(kernel, args):
    """Compile ``kernel`` for the types of ``args`` (and save it in the cache) without running
    it: a kernel with no Python entry (no_cpython_wrapper) that dem.step.advance calls, so
    that advance, compiled later in another job, loads it instead of compiling it."""
    kernel.compile(tuple(kernel.typeof_pyval(a) for a in args))


def forces(hon, full=False):
    """dem.step.compute_forces of one heat switch and one form (the largest part of the step:
    contact and wall laws, the pair loop serial and on blocks of rows, and with heat the
    conductance laws; ``full``: the full form, with rolling, periodic images and every heat
    model, else the lean one), with the argument types dem.step.advance calls it with (n int64,
    t float64, hon, xon, and ton None: the rescaled tangential model of every scene that does not
    ask for the projected one, whose forms a scene compiles once on its first run)."""
    from . import step as K
    st = _state(hon, full)
    _compile(K.compute_forces, (*st.bundles(), st.n, 0.0, True if hon else None, True if full else None, None))


def heat_step():
    """dem.thermal.heat.heat_step (every integrator, convection, radiation, the guards), with
    the argument types of dem.step.heat_phase's call."""
    from .thermal.heat import heat_step as kernel
    st = _state(True)
    _compile(kernel, (*st.bundles(), st.n, st.n_owned, 1e-5, 0.0, 1))


def heat_blocks():
    """The heat step's kernels on blocks of rows (dem.thermal.heat._heat_blocks,
    _radiation_accumulators_blocks, the implicit solver's jacobi_pcg_blocks and pair_heat_blocks:
    parallel loops, seconds each), with the argument types of heat_step's calls, so that the heat
    step's own job, after this one, loads them."""
    import numpy as np
    from .thermal import heat as H
    st = _state(True)
    P, C, W, TB, prm = st.bundles()
    i, f = np.int64(1), np.zeros(0)
    links = (f, f, np.zeros((0, 1)), f, f, f, f, f, f, f)
    _compile(H._heat_blocks, (P, W, TB, prm, i, 1e-5, 0.0, True, True, links, i, i))
    _compile(H._radiation_accumulators_blocks, (i, i, i, prm.xcnt, P.temperature, P.radius, P.material, TB.tmat,
                                                C, i))
    pairs = (C.nb, C.nnb, C.Hd, C.Hi)
    _compile(H.jacobi_pcg_blocks, (i, pairs, True, f, f, f, 1e-10, i, i))
    _compile(H.pair_heat_blocks, (i, pairs, True, f, 1e-5, i))


def mechanics(full=False):
    """The step without heat (the ``hon`` = None specialisation of dem.step.advance), lean or
    ``full`` (``xon``)."""
    from .simulation import Simulation
    Simulation.from_dict(_base(full)).run(progress=False)


def heat(full=False):
    """The step with heat (lean or ``full``), and the output kernels of a run with an output
    folder."""
    from .simulation import Simulation
    with tempfile.TemporaryDirectory(prefix="dem_compile_") as tmp:
        Simulation.from_dict(_thermal(full)).run(progress=False, out_dir=os.path.join(tmp, "out"))


def frozen():
    """A frozen packing (mechanics = false): the thermal-only step and its integrators."""
    from .simulation import Simulation
    frozen = dict(_thermal(), simulation={"time_step": 1e-5, "end_time": 2.0, "mechanics": False},
                  thermal={"direct": "batchelor_obrien", "initial_temperature": 300.0, "time_step": 1.0})
    Simulation.from_dict(frozen).run(progress=False)


def mpi_entry_points():
    """What an MPI run calls besides dem.step.advance (whose phases it calls one group at a
    time, the same compiled form as a serial run's): it must be in the cache before the ranks
    start."""
    from . import step as K
    from .simulation import Simulation
    from .thermal.heat import cross_rates
    sim = Simulation.from_dict(_thermal())
    st = sim.state
    sim.warmup()
    K.outside(st.position, st.lo, st.hi, st.periodic, st.n_owned, st.ip[K.IP.openfaces])
    cross_rates(st.n_owned, st.inv_heat_capacity, st.nb, st.nnb, st.Hd, st.Hi, st.work)


def insertion():
    """Random insertion of ``count`` particles in a region (dem.insertion), as the scene of a
    ``dem run`` with [[particles]] count does before its first step: the scene alone."""
    from . import scene
    data = _base()
    data["particles"] = [{"material": "m", "count": 5, "radius": 1e-3,
                          "region": {"type": "box", "min": [-0.008, -0.008, 0.0005], "max": [0.008] * 3}}]
    scene.parse(data, "<compile>")


def flow():
    """The overlap tests of an inlet's batch (dem.flow: against the particles, the plane and
    cylinder walls), as an insertion event calls them."""
    import numpy as np
    from .contact.walls import WF, WI
    from .flow import clashes, plane_wall_clashes
    x, r = np.zeros((1, 3)), np.full(1, 1e-3)
    clashes(x, r, x + 1.0, r)
    plane_wall_clashes(x, r, np.zeros((1, WF.SIZE)), np.zeros((1, WI.SIZE), np.int64), 1, 0.0)


# compute_forces and heat_step are compiled on their own first (by signature, in parallel; the
# heat step's parallel loops before it, in a job of their own that starts first: the longest chain
# is theirs, the heat step's and the step with heat), then the step of each heat switch
# (dem.step.advance and the rest) loads them; the heat step after the mechanics-only one, whose
# neighbour, kick and rebuild kernels it shares
DEM_JOBS = (
    Job("dem.forces", "dem.compile:forces", (False,)),
    Job("dem.heat_blocks", "dem.compile:heat_blocks"),
    Job("dem.forces_heat", "dem.compile:forces", (True,)),
    Job("dem.forces_full", "dem.compile:forces", (False, True)),
    Job("dem.forces_heat_full", "dem.compile:forces", (True, True)),
    Job("dem.mechanics", "dem.compile:mechanics", after=("dem.forces",)),
    Job("dem.heat_step", "dem.compile:heat_step", after=("dem.heat_blocks",)),
    Job("dem.insertion", "dem.compile:insertion"),
    Job("dem.flow", "dem.compile:flow"),
    Job("dem.mechanics_full", "dem.compile:mechanics", (True,), after=("dem.forces_full", "dem.mechanics")),
    Job("dem.heat", "dem.compile:heat", after=("dem.forces_heat", "dem.heat_step", "dem.mechanics")),
    Job("dem.heat_full", "dem.compile:heat", (True,), after=("dem.forces_heat_full", "dem.heat",
                                                             "dem.mechanics_full")),
    Job("dem.frozen", "dem.compile:frozen", after=("dem.heat",)),
    Job("dem.mpi", "dem.compile:mpi_entry_points", after=("dem.heat",)),
)
