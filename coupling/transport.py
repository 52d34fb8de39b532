"""The transport of a coupled run: how the DEM ranks get the gas solver's frames and give it
theirs. Two links, one interface:

* one DEM rank and one gas process (any transport), or one DEM rank with the file transport:
  :class:`_SolverLink`, rank 0's one exchange with the solver (coupling.exchange: file or
  socket, one frame of every cell);
* several DEM ranks or several gas processes with the socket transport: the many-to-many link
  (:class:`_M2MLink`, coupling.m2m): every DEM rank exchanges the cells it owns
  (coupling.cells) with the gas processors holding them, and the DEM ranks share only the
  cells they both see. Per step the ranks agree, in one reduction of a few numbers, on a
  stop request, a failure anywhere and the solver's flags; nothing of the size of the mesh
  is broadcast or reduced.

The loop (coupling.loop), the restart points (coupling.restart) and the diagnostics
(coupling.diagnostics) only use the interface below.

The interface
-------------
:class:`Ranks` (the MPI front: the DEM ranks of the run) provides ``root`` (this rank talks
to the solver and writes the files), ``size``, ``par``, ``comm``, ``barrier()``,
``bcast(obj)``, ``on_root(fn, ...)`` (run on rank 0, its failure raised on every rank),
``everywhere(fn, ...)`` (run on every rank, the first failure raised on all) and
``log(fn)`` (``fn`` on rank 0, a silent logger elsewhere).

A link (one per DEM rank, from :func:`open_link`) provides:

* ``own_stop()``: the signal number of a stop request (0 if none; the same on every rank);
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
  write timings.json (``write_timings(failing, extra)``; ``extra``: the per-rank message
  and memory figures of a many-to-many run).

:func:`open_exchange` makes rank 0's exchange (and the solver's couplingDict) when the case
is prepared; :func:`open_m2m` makes every rank's many-to-many exchange and its plan before
the solver starts; :func:`open_link` makes the link once the solver is started
(coupling.launch).
"""
from __future__ import annotations

import shutil
from pathlib import Path

import numpy as np

from dem.interrupt import stop_requested

from . import foam_case as fc
from .diagnostics import check_gas_fields
from .errors import CouplingError
from .exchange import FileExchange, SocketExchange
from .launch import log_tail
from .restart import FLUID_FIELDS, restored_frame


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


def uses_m2m(cfg, n_dem_ranks: int) -> bool:
    """The many-to-many link: the socket transport with several DEM ranks or gas processes."""
    return cfg.transport == "socket" and (n_dem_ranks > 1 or cfg.gas_processes > 1)


def open_exchange(out: Path, cfg, n_cells: int, tied, *, m2m: bool = False):
    """Rank 0's exchange with the solver (cfg.transport: socket or file) and the solver's
    system/couplingDict saying how to reach it (``tied``: the tied walls' entries). With
    ``m2m`` only the couplingDict and an empty plan folder (the ranks' exchanges: open_m2m)."""
    from dem import outdir
    particle_fields = getattr(cfg, "averaging", None) is not None   # [averaging]: 5 more frame columns
    outdir.claim(out / "coupling")   # the exchange folder (file transport; the solver's pid file)
    if m2m:
        folder = out / "coupling" / "m2m"
        if folder.exists():   # the plan of an earlier run (inside our claimed coupling/ folder)
            shutil.rmtree(folder)
        folder.mkdir(parents=True)
        fc.write_coupling_dict(out, "m2m", timeout=cfg.timeout, send_velocity=cfg.send_velocity, tied=tied,
                               options=fc.LinkOptions(m2m_directory=str(folder)), particle_fields=particle_fields)
        return None
    if cfg.transport == "socket":
        ex = SocketExchange(port=0, timeout=cfg.timeout, n_cells=n_cells)
        fc.write_coupling_dict(out, "socket", port=ex.port, timeout=cfg.timeout,
                               send_velocity=cfg.send_velocity, tied=tied, particle_fields=particle_fields)
    else:
        fc.write_coupling_dict(out, "file", timeout=cfg.timeout, send_velocity=cfg.send_velocity, tied=tied,
                               particle_fields=particle_fields)
        ex = FileExchange(out / "coupling", timeout=cfg.timeout, n_cells=n_cells)
    return ex


def open_m2m(R, out: Path, cfg, cells):
    """Every rank's many-to-many exchange (listening) and its plan lines; rank 0 writes
    ``ready`` once all are written (collective; before the solver starts)."""
    from .case import exchange_address
    from .m2m import M2MExchange, gas_pairs
    folder = out / "coupling" / "m2m"
    from .errors import CouplingRunError
    rank = 0 if R.comm is None else R.comm.Get_rank()

    def listen():
        host = cfg.exchange_host
        try:
            return M2MExchange(rank, gas_pairs(out, cfg.gas_processes, cells), folder,
                               timeout=cfg.timeout, host=exchange_address(host))
        except OSError as e:
            raise CouplingRunError(f"coupling.exchange_host = {host!r}: DEM rank {rank} cannot listen there "
                                   f"({e.strerror or e}); give an address of this node, or \"auto\"") from None

    ex = R.everywhere(listen)
    R.everywhere(ex.write_plan)
    R.barrier()
    if R.root:
        (folder / "ready").write_text(f"{R.size}\n")
    return ex


def open_link(R, ex, proc, mesh, cfg, out, timer, *, external=False, cells=None, restart_pieces=None):
    """This rank's link: rank 0 talks to the solver process ``proc`` through ``ex`` (watching
    the process unless the user started it: ``external``); with a many-to-many exchange
    (coupling.m2m.M2MExchange) every rank talks to its gas processors."""
    from .m2m import M2MExchange
    if isinstance(ex, M2MExchange):
        ex.peer_process = proc if (R.root and not external) else None
        return _M2MLink(R, ex, proc, mesh, cfg, out, timer, cells, restart_pieces)
    ex.peer_process = proc if not external else None
    return _SolverLink(R, ex, proc, mesh, cfg, out, timer)


class _SolverLink:
    """The one DEM rank's gas link: frames of every cell to and from the solver process; every
    received frame is checked (check_gas_fields)."""

    def __init__(self, R, ex, proc, mesh, cfg, out, timer):
        self.R, self.ex, self.proc, self.mesh, self.cfg, self.out, self.timer = R, ex, proc, mesh, cfg, out, timer

    @staticmethod
    def own_stop():
        return stop_requested()

    def first(self, i0, t_start, cstate):
        with self.timer("gas_wait"):
            fluid = _first_frame(self.ex, i0, t_start, self.mesh, self.cfg, cstate)
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
            fluid = check_gas_fields(ex.receive(step), step, time_value=t, mesh=self.mesh, cfg=self.cfg,
                                     eps_change=eps_change)
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
        pass

    def explain(self, e, sim):
        if isinstance(e, CouplingError):
            out = self.out
            tail = log_tail(out / "log.thermoDemFoam")
            e.args = (e.args[0] + f"\n  DEM checkpoint at t = {sim.time:.9g} s written to "
                      f"{out / 'checkpoint.npz'}" + (f"\n  solver log tail:\n{tail}" if tail else ""),)

    def stats(self):
        """This rank's message and memory figures (bytes per run; peak RSS in MiB)."""
        return dict(owned_cells=self.mesh.n_cells, halo_cells=0, gas_partners=1, gas_bytes_sent=self.ex.bytes_sent,
                    dem_bytes_sent=0, dem_messages=0, peak_rss_mib=_peak_rss_mib())

    def close(self, status, write_timings):
        from dem import outdir
        if self.proc.poll() is None and status != "finished":
            self.proc.kill()
            self.proc.wait()
        self.ex.close()
        outdir.adopt_solver_entries(self.out)
        write_timings(status != "finished", dict(ranks=[self.stats()]))


class _M2MLink(_SolverLink):
    """A DEM rank's gas link in a many-to-many run: frames of the cells it owns to and from
    the gas processors holding them (coupling.m2m), the gas fields of the cells it sees but
    does not own from their owners (coupling.cells.update), and one small reduction per step
    so that every rank takes the same decision: a stop request, a failure on any rank (its
    message, naming the rank, is raised on every rank), the solver's flags and its energy
    ledger (the same in every frame; a rank owning no cell gets it there)."""

    def __init__(self, R, ex, proc, mesh, cfg, out, timer, cells, restart_pieces=None):
        super().__init__(R, ex, proc, mesh, cfg, out, timer)
        self.cells = cells
        self.restart_pieces = restart_pieces   # the coupling-state pieces this rank read at a restart
        self.pending = None     # a failure of this rank in a send, raised with the next agreement
        self.flags = 0
        self.stop = 0           # a stop request of any rank, agreed with each gas frame

    def own_stop(self):
        """A stop request of any rank (a scheduler signals every rank; Open MPI passes a Ctrl-C on
        to every rank as SIGTERM), as agreed with the last gas frame (no message of its own: a
        signal that arrives after that agreement ends the next coupling step)."""
        return self.stop

    def _agree(self, err, scalars):
        """Every rank learns whether any failed (then raises the first failure, naming its rank),
        the solver's flags and its ledger scalars (one reduction of a few numbers)."""
        R = self.R
        n_sc = -1 if scalars is None else int(scalars.size)
        head = np.array([1.0 if err is not None else 0.0, float(self.flags), float(n_sc), float(stop_requested())])
        head = self.cells.allmax(head)
        self.stop = max(self.stop, int(head[3]))
        if head[0] > 0:
            errs = [err] if R.comm is None else R.comm.allgather(None if err is None else str(err))
            k, msg = next((k, e) for k, e in enumerate(errs) if e is not None)
            if R.size > 1:
                msg = f"[DEM rank {k} of {R.size}] {msg}"
            if err is not None:   # this rank's own failure (GasFieldError, CouplingError), the first one's text
                err.args = (msg,)
                raise err
            relayed = CouplingError("", peer="CFD solver")
            relayed.args = (msg,)
            raise relayed
        self.flags = int(head[1])
        n = int(head[2])
        sc = np.full(max(n, 0), -np.inf) if scalars is None or scalars.size != n else np.asarray(scalars, float)
        return self.cells.allmax(sc) if n > 0 else sc

    def _accept(self, step):
        """Every rank accepts its gas processors; the ranks check together every 0.02 s, so that
        a failure seen by one (the solver exited: rank 0 watches it) ends the wait of all."""
        done, err = False, None
        while True:
            if not done and err is None:
                try:
                    done = self.ex.accept(step, wait=0.02)
                except CouplingError as e:
                    err = e
                except Exception as e:  # noqa: BLE001 - a failure here must reach every rank
                    err = CouplingError(f"accepting the gas processors failed: {type(e).__name__}: {e}",
                                        peer="CFD solver", step=step)
            failed, waiting = self.cells.allmax(np.array([err is not None, not done], float))
            if failed:
                self._agree(err, None)
            if not waiting:
                return

    def _collect(self, step, t, eps_change):
        """The gas frame of ``step`` on this rank: own cells from the gas, checked; halo from
        the owners (collective)."""
        cs = self.cells
        fluid, scalars, err = {"_n": cs.n_cells}, None, None
        try:
            if self.pending is not None:
                raise self.pending
            self.ex.on_cells(cs)
            scalars = self.ex.receive(step, fluid)
            fluid.pop("_n")
            for k, comp in FLUID_FIELDS.items():
                if k not in fluid:   # a rank that owns no cell
                    fluid[k] = np.zeros((cs.n_cells, 3) if comp == 3 else cs.n_cells)
            h = self.ex.last_header
            self.flags = int(h["flags"]) if h is not None else 0
            own = cs.owned
            check_gas_fields({k: fluid[k][own] for k in FLUID_FIELDS}, step, time_value=t, mesh=cs.mesh,
                             cfg=self.cfg, eps_change=eps_change, cells=own, global_ids=cs.global_ids)
        except CouplingError as e:
            err = e
        except Exception as e:  # noqa: BLE001 - any failure on one rank must reach every rank
            err = CouplingError(f"receiving the gas frame failed: {type(e).__name__}: {e}", peer="CFD solver",
                                step=step)
        self.pending = None
        fluid["scalars"] = self._agree(err, scalars)
        cs.update(*(fluid[k] for k in FLUID_FIELDS))
        return fluid

    def first(self, i0, t_start, cstate):
        with self.timer("gas_wait"):
            self._accept(i0)   # raises on every rank alike
            fluid = self._collect(i0, t_start, None)
        return restored_frame(fluid, cstate, self.cells)

    def send(self, step, frame, time_value, final):
        with self.timer("exchange"):
            try:
                self.ex.on_cells(self.cells)
                self.ex.send(step, frame, time_value=time_value, final=final)
            except CouplingError as e:   # told to every rank at the next receive
                self.pending = e

    def receive(self, step, t, eps_change, stop_sig):
        with self.timer("gas_wait"):
            fluid = self._collect(step, t, eps_change)
        if self.R.root:
            from dem import outdir
            outdir.adopt_solver_entries(self.out)
        f = self.flags
        final = bool(f & 1)
        return fluid, final, int((f >> 8) & 0xFF) if final else 0

    def finish(self, step):
        """The solver must exit cleanly after the last step (rank 0 waits; every rank learns)."""
        err = None
        if self.R.root:
            try:
                super().finish(step)
            except CouplingError as e:
                err = e
        self._agree(err, None)

    def explain(self, e, sim):
        if self.R.root:
            super().explain(e, sim)

    def stats(self):
        """This rank's message and memory figures (bytes per run; peak RSS in MiB)."""
        cs, ex = self.cells, self.ex
        return dict(owned_cells=int(cs.owned.size), halo_cells=cs.halo_cells, gas_partners=len(ex.pairs),
                    local_cells=int(cs.n_cells), mesh_bytes=int(cs.mesh.nbytes()), mesh_rebuilds=cs.rebuilds,
                    mesh_pieces_read=cs.pieces_read, setup_pieces_read=cs.setup_read["pieces"],
                    setup_cells_read=cs.setup_read["cells"], table_pieces_read=cs.setup_read.get("table"),
                    setup_mesh_bytes=cs.setup_read.get("mesh_bytes"),
                    setup_peak_rss_mib=cs.setup_read.get("peak_rss_mib"), dem_recuts=0 if cs.par is None else int(cs.par.rebalances),
                    restart_pieces=self.restart_pieces, view_reach=cs.view_reach,
                    view_box=None if cs.view_box is None else [b.tolist() for b in cs.view_box],
                    gas_bytes_sent=ex.bytes_sent, gas_bytes_received=ex.bytes_received,
                    dem_bytes_sent=cs.bytes_sent, dem_messages=cs.messages, peak_rss_mib=_peak_rss_mib())

    def close(self, status, write_timings):
        from dem import outdir
        R = self.R
        if R.root and self.proc.poll() is None and status != "finished":
            self.proc.kill()
            self.proc.wait()
        self.ex.close()
        ranks = [self.stats()] if R.comm is None else R.comm.gather(self.stats(), root=0)
        if R.root:
            outdir.adopt_solver_entries(self.out)
            write_timings(status != "finished", dict(ranks=ranks))


def _peak_rss_mib():
    import resource
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


def _first_frame(ex, i0, t_start, mesh, cfg, cstate):
    """The gas state the first DEM interval uses: the solver's first frame, checked (after a
    restart replaced by the restart point's: coupling.restart.restored_frame)."""
    fluid = check_gas_fields(ex.receive(i0), i0, time_value=t_start, mesh=mesh, cfg=cfg)
    return restored_frame(fluid, cstate)


def _peer_signal(ex):
    """The signal number that stopped the gas solver (flags bits 8-15 of its last frame)."""
    h = ex.last_header
    return int((h["flags"] >> 8) & 0xFF) if h and (h["flags"] & 1) else 0
