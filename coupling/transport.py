"""The transport of a coupled run: how the DEM ranks get the gas solver's frames and give it
theirs. Today's transport is rank 0's: rank 0 holds the one exchange with the solver
(coupling.exchange: file or socket, one frame format), checks every frame it receives and
broadcasts it to the other DEM ranks (:func:`_share`), which only listen. This module is the
one place a many-to-many transport (every DEM rank exchanging its part with the gas ranks)
would replace; the loop (coupling.loop), the restart points (coupling.restart) and the
diagnostics (coupling.diagnostics) only use the interface below.

The interface
-------------
:class:`Ranks` (the MPI front: the DEM ranks of the run) provides ``root`` (this rank talks
to the solver and writes the files), ``size``, ``par``, ``comm``, ``barrier()``,
``bcast(obj)``, ``on_root(fn, ...)`` (run on rank 0, its failure raised on every rank),
``everywhere(fn, ...)`` (run on every rank, the first failure raised on all) and
``log(fn)`` (``fn`` on rank 0, a silent logger elsewhere).

A link (one per DEM rank, from :func:`open_link`) provides:

* ``own_stop()``: the signal number of a stop request of this process (0 if none);
* ``first(i0, t_start, cstate)``: the gas fields the first DEM interval uses (after a
  restart: the frame of the restart point, coupling.restart.restored_frame);
* ``send(step, frame, time_value, final)``: the exchange fields of the particles
  (coupling.interface.prepare's frame; ``final`` on the last step);
* ``receive(step, t, eps_change, stop_sig)``: ``(fluid, final, peer_sig)``: the checked
  gas fields of ``t`` (coupling.diagnostics.check_gas_fields), the solver's FINAL flag and
  the signal that stopped it (or 0); every rank gets the same, or the same failure;
* ``finish(step)``: after the last step (the solver must exit cleanly);
* ``fail(e)``: the run failed on this rank outside a receive (tell the others);
* ``explain(e, sim)``: add the checkpoint and the solver's log tail to a CouplingError;
* ``close(status, write_timings)``: stop the solver if still running, close the exchange,
  write timings.json (``write_timings(failing)``).

:func:`open_exchange` makes the exchange (and the solver's couplingDict) when the case is
prepared; :func:`open_link` makes the link once the solver is started (coupling.launch).
"""
from __future__ import annotations

from pathlib import Path

from dem.interrupt import stop_requested

from . import foam_case as fc
from .diagnostics import check_gas_fields
from .errors import CouplingError
from .exchange import FileExchange, SocketExchange
from .launch import log_tail
from .restart import restored_frame


def _silent(*a, **k):
    pass


class Ranks:
    """The DEM ranks of a coupled run: rank 0 talks to the gas solver and writes the files;
    every rank advances its own particles and adds its share to the exchange fields."""

    def __init__(self, sim):
        self.par = sim.par
        self.comm = sim.par.comm if sim.par is not None else None
        self.root = self.comm is None or self.comm.Get_rank() == 0
        self.size = 1 if self.comm is None else self.comm.Get_size()
        self.failure_shared = False

    def log(self, fn):
        """``fn`` on rank 0 (which reports for every rank), a silent logger elsewhere."""
        return fn if self.root else _silent

    def barrier(self):
        if self.comm is not None:
            self.comm.Barrier()

    def bcast(self, obj):
        return obj if self.comm is None else self.comm.bcast(obj, root=0)

    def on_root(self, fn, *a, **kw):
        """Run fn on rank 0 (result there, None elsewhere); its failure is raised on every rank."""
        res, err = None, None
        if self.root:
            try:
                res = fn(*a, **kw)
            except Exception as e:  # noqa: BLE001
                err = e
        if self.comm is not None:
            err = self.comm.bcast(err, root=0)
        if err is not None:
            raise err
        return res

    def everywhere(self, fn, *a, **kw):
        """Run fn on every rank; if it fails on any, raise the first failure on all."""
        res, err = None, None
        try:
            res = fn(*a, **kw)
        except Exception as e:  # noqa: BLE001
            err = e
        if self.comm is not None:
            errs = self.comm.allgather(err)
            err = next((e for e in errs if e is not None), None)
        if err is not None:
            raise err
        return res


def open_exchange(out: Path, cfg, n_cells: int, tied):
    """Rank 0's exchange with the solver (cfg.transport: socket or file) and the solver's
    system/couplingDict saying how to reach it (``tied``: the tied walls' entries)."""
    from dem import outdir
    outdir.claim(out / "coupling")   # the exchange folder (file transport; the solver's pid file)
    if cfg.transport == "socket":
        ex = SocketExchange(port=0, timeout=cfg.timeout, n_cells=n_cells)
        fc.write_coupling_dict(out, "socket", port=ex.port, timeout=cfg.timeout,
                               send_velocity=cfg.send_velocity, tied=tied)
    else:
        fc.write_coupling_dict(out, "file", timeout=cfg.timeout, send_velocity=cfg.send_velocity, tied=tied)
        ex = FileExchange(out / "coupling", timeout=cfg.timeout, n_cells=n_cells)
    return ex


def open_link(R, ex, proc, mesh, cfg, out, timer, *, external=False):
    """This rank's link: rank 0 talks to the solver process ``proc`` through ``ex`` (watching
    the process unless the user started it: ``external``), the others listen to rank 0."""
    if not R.root:
        return _FollowerLink(R)
    ex.peer_process = proc if not external else None
    return _SolverLink(R, ex, proc, mesh, cfg, out, timer)


class _SolverLink:
    """Rank 0's side of the gas link: frames to and from the solver process; every received
    frame is checked (check_gas_fields) and passed on to the other DEM ranks (_share)."""

    def __init__(self, R, ex, proc, mesh, cfg, out, timer):
        self.R, self.ex, self.proc, self.mesh, self.cfg, self.out, self.timer = R, ex, proc, mesh, cfg, out, timer

    @staticmethod
    def own_stop():
        return stop_requested()

    def first(self, i0, t_start, cstate):
        with self.timer("gas_wait"):
            fluid = _share(self.R, lambda: _first_frame(self.ex, i0, t_start, self.mesh, self.cfg, cstate), self.ex)
        grow = getattr(self.ex, "grow_buffers", None)  # the socket transport only
        if grow is not None:
            grow(self.mesh.n_cells)
        return fluid

    def send(self, step, frame, time_value, final):
        with self.timer("exchange"):
            self.ex.send(step, frame, time_value=time_value, final=final)

    def receive(self, step, t, eps_change, stop_sig):
        """(gas fields of t, the solver's FINAL flag, the signal that stopped it or 0)."""
        ex = self.ex
        with self.timer("gas_wait"):
            fluid = _share(self.R, lambda: check_gas_fields(ex.receive(step), step, time_value=t, mesh=self.mesh,
                                                            cfg=self.cfg, eps_change=eps_change), ex,
                           stop_sig=lambda: stop_sig or _peer_signal(ex))
        from dem import outdir
        outdir.adopt_solver_entries(self.out)   # the time folders the solver wrote (dem.outdir)
        return fluid, bool(ex.peer_final), _peer_signal(ex)

    def finish(self, step):
        """The solver must exit cleanly after the last step."""
        try:
            rc = self.proc.wait(timeout=max(self.cfg.timeout, 30))
        except Exception:  # noqa: BLE001
            self.proc.kill()
            rc = self.proc.wait()
        if rc != 0:
            raise CouplingError(f"CFD solver exited with code {rc} after the last step "
                                f"(log: {self.out / 'log.thermoDemFoam'})", peer="CFD solver", step=step)

    def fail(self, e):
        """Rank 0 failed outside a receive: the other ranks wait in one; tell them."""
        from dem.simulation import SimulationError
        R = self.R
        if R.comm is not None and not isinstance(e, SimulationError) and not R.failure_shared:
            _share_failure(R, e)

    def explain(self, e, sim):
        if isinstance(e, CouplingError):
            out = self.out
            tail = log_tail(out / "log.thermoDemFoam")
            e.args = (e.args[0] + f"\n  DEM checkpoint at t = {sim.time:.9g} s written to "
                      f"{out / 'checkpoint.npz'}" + (f"\n  solver log tail:\n{tail}" if tail else ""),)

    def close(self, status, write_timings):
        from dem import outdir
        if self.proc.poll() is None and status != "finished":
            self.proc.kill()
            self.proc.wait()
        self.ex.close()
        outdir.adopt_solver_entries(self.out)
        write_timings(status != "finished")


class _FollowerLink:
    """A DEM rank other than 0: what rank 0 received from the solver (or its failure), the
    FINAL flag and the signal that ends the run, by broadcast; nothing to send or close."""

    def __init__(self, R):
        self.R = R

    @staticmethod
    def own_stop():
        return 0

    def _receive(self, step):
        fluid, final, err, signum = self.R.comm.bcast(None, root=0)
        if err is not None:
            raise CouplingError(f"rank 0: {err}", peer="CFD solver", step=step)
        return fluid, final, signum

    def first(self, i0, t_start, cstate):
        fluid, _, _ = self._receive(i0)
        if cstate is not None:
            fluid = dict(fluid, **cstate["fluid"])
        return fluid

    def send(self, step, frame, time_value, final):
        pass

    def receive(self, step, t, eps_change, stop_sig):
        return self._receive(step)

    def finish(self, step):
        pass

    def fail(self, e):
        pass

    def explain(self, e, sim):
        pass

    def close(self, status, write_timings):
        pass


def _first_frame(ex, i0, t_start, mesh, cfg, cstate):
    """The gas state the first DEM interval uses: the solver's first frame, checked (after a
    restart replaced by the restart point's: coupling.restart.restored_frame)."""
    fluid = check_gas_fields(ex.receive(i0), i0, time_value=t_start, mesh=mesh, cfg=cfg)
    return restored_frame(fluid, cstate)


def _peer_signal(ex):
    """The signal number that stopped the gas solver (flags bits 8-15 of its last frame)."""
    h = ex.last_header
    return int((h["flags"] >> 8) & 0xFF) if h and (h["flags"] & 1) else 0


def _share(R, receive, ex, stop_sig=lambda: 0):
    """Rank 0 receives the gas fields and passes them (or the failure) to every DEM rank,
    with the FINAL flag and the number of the signal that ends the run (0 if none)."""
    fluid, err = None, None
    try:
        fluid = receive()
    except Exception as e:  # noqa: BLE001
        err = e
    if R.comm is not None:
        R.comm.bcast((fluid, bool(ex.peer_final), None if err is None else repr(err), int(stop_sig())),
                     root=0)
        R.failure_shared = err is not None
    if err is not None:
        raise err
    return fluid


def _share_failure(R, e):
    """Rank 0 failed outside a receive: the other ranks wait in one; tell them."""
    try:
        R.comm.bcast((None, True, repr(e), 0), root=0)
    except Exception:  # noqa: BLE001
        pass
