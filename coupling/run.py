"""``coupling`` command: check and run a coupled CFD-DEM case (DEM side + thermoDemFoam).

    coupling check CASE_DIR
    coupling run   CASE_DIR [--out DIR] [--transport file|socket] [--end-time T] [--restart | --overwrite]

``run`` copies the OpenFOAM part of CASE_DIR into the output directory (default
``out/<case name>``; new, empty or an earlier output of this tool, never the case folder nor
inside it: dem.outdir), meshes it (blockMesh), writes the initial void fraction of the
particles into 0/eps, decomposes it when ``gas_processes > 1``, builds the solver if
needed (scripts/build_openfoam_solver.sh, cached), starts thermoDemFoam, runs the coupled
loop (coupling.interface) and writes

* ``history.csv``, ``particles.pvd`` + ``vtk/``, ``final.npz`` (DEM, dem.output);
* ``wall_heat.csv`` (with heat and DEM walls: the particles' heat from each wall by path,
  dem.thermal.wall_heat; the gas's is thermoDemFoam's ``wallHeatFlux`` field);
* ``coupling.csv`` (gas and particle energies, heat rate, pressure drop, bed height);
* ``checkpoint.npz`` (DEM state at the end, or at the failure) and a restart point at
  every OpenFOAM write, at the end of the run and on SIGINT/SIGTERM:
  ``checkpoints/checkpoint_<step>.npz`` (DEM) + ``checkpoints/coupling_<step>.npz`` (the
  relaxed eps/Ksl last sent and the gas frame the next DEM interval uses) + the gas time
  directory (written with 17 significant digits);
* the OpenFOAM time directories (written by the solver), ``log.thermoDemFoam``;
* ``timings.json`` (wall time per phase) and ``coupling.png``.

If the solver dies or hangs (CouplingError) the DEM state is checkpointed first, then the
command exits with status 3 and a message naming the peer and the coupling step. Every gas
frame is checked before the particles see it (``check_gas_fields``: finite U, T, grad p, p;
T > 0; |U| below the speed of sound); a bad frame stops the run the same way
(GasFieldError, naming the field, the cell, the time and what to change). A DEM guard
(SimulationError: overlap, non-finite velocity, temperature, domain) checkpoints and exits
with status 4. ``RunWatch`` warns once per run when the void fraction is clipped at eps_min
(solid volume the gas does not see), when a cell's void fraction changes by more than 0.2
in one coupling step, and when the gas is faster than Mach 0.3; coupling.csv records the
smallest unclipped void fraction and the number of clipped cells of every output step.
``--restart`` continues a run in --out from its latest restart point; the continued run
equals the uninterrupted one to round-off (bit-identical in tests). SIGINT/SIGTERM (of
this process, or of the gas solver) end the current coupling step, the solver writes its
fields there, a restart point is written, one line gives the command to continue, and the
command exits 130/143 (the ``coupling`` command installs the handlers, dem.interrupt;
``run_case`` called from Python does not). Under ``mpirun -np 1`` the command works as in
serial; more DEM ranks are not supported yet.
"""
from __future__ import annotations

import argparse
import contextlib
import json
import os
import re
import shutil
import sys
import time
from pathlib import Path

import numpy as np

from .exchange import CouplingError
from dem.interrupt import StopRequested, StopSignals, signal_name, stop_requested

EXIT_CHECK = 2
EXIT_COUPLING = 3
EXIT_DEM = 4


class CouplingRunError(RuntimeError):
    pass


class RunInterrupted(StopRequested):
    """A coupled run stopped cleanly on SIGINT/SIGTERM (of the DEM or of the gas solver)
    after writing a restart point; ``message`` is the one line for the user."""

    def __init__(self, signum, message):
        super().__init__(signum)
        self.message = message


def _scrub_mpi_env():
    """Started by mpirun -np 1: the solver's own mpirun must not inherit our MPI job."""
    for k in list(os.environ):
        if k.startswith(("OMPI_", "PMIX_", "PMI_", "OPAL_", "PRTE_", "HYDRA_")):
            del os.environ[k]


# --------------------------------------------------------------------------- helpers

class _Ranks:
    """The DEM ranks of a coupled run: rank 0 talks to the gas solver and writes the files;
    every rank advances its own particles and adds its share to the exchange fields."""

    def __init__(self, sim):
        self.par = sim.par
        self.comm = sim.par.comm if sim.par is not None else None
        self.root = self.comm is None or self.comm.Get_rank() == 0
        self.size = 1 if self.comm is None else self.comm.Get_size()
        self.failure_shared = False

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


def _time_dirs(case: Path) -> list[tuple[float, Path]]:
    out = []
    for p in case.iterdir():
        if p.is_dir():
            try:
                out.append((float(p.name), p))
            except ValueError:
                pass
    return sorted(out)


def _time_index(tdir: Path) -> int | None:
    f = tdir / "uniform" / "time"
    if not f.exists():
        return None
    m = re.search(r"\bindex\s+(\d+)\s*;", f.read_text())
    return int(m.group(1)) if m else None


def output_rule(case_dir, *, restart: bool, overwrite: bool) -> dict:
    """The output-folder rule of a coupled run (dem.outdir): --out new, empty or an earlier
    output (continued with --restart, replaced with --overwrite), never the case folder, a
    folder inside it or one holding it."""
    return dict(restart=restart, overwrite=overwrite, protect=[Path(case_dir)])


def prepare_output(case, out: Path, *, restart: bool, overwrite: bool = False) -> None:
    """Claim --out (dem.outdir: refused unless new, empty or an earlier output of ours; with
    --overwrite the earlier output's entries are removed, nothing else), copy the case's
    OpenFOAM part into it and mesh it."""
    from . import foam_case as fc
    from dem import outdir
    rule = output_rule(case.dir, restart=restart, overwrite=overwrite)
    if restart:
        outdir.check(out, **rule)
        if not (out / "system" / "controlDict").exists():
            raise CouplingRunError(f"{out}: nothing to restart (no system/controlDict)")
    outdir.claim_folder(out, command="coupling run", **rule)
    if restart:
        return
    for sub in ("0", "constant", "system"):
        outdir.claim(out / sub)
        shutil.copytree(case.dir / sub, out / sub)
    for f in ("dem.toml", "coupling.toml"):
        outdir.claim(out / f)
        shutil.copy2(case.dir / f, out / f)
    if not (out / "constant" / "polyMesh" / "owner").exists():
        outdir.claim(out / "log.blockMesh")
        fc.block_mesh(out)


# --------------------------------------------------------------------------- diagnostics

class Diagnostics:
    """coupling.csv rows: energies, heat rate, pressure drop, bed height, timings."""

    COLUMNS = ["time", "step", "T_particles", "T_gas", "E_particles", "E_gas", "Q_to_gas",
               "E_conv_particles", "dp", "bed_height", "v_max", "n_outside", "eps_raw_min",
               "eps_clipped_cells", "wall"]

    def __init__(self, path, mesh, gas, keep_until=None, ledger=None):
        from dem.output import History
        from .energy import BALANCE_COLUMNS
        self.ledger = ledger
        self.hist = History(str(path), self.COLUMNS + (BALANCE_COLUMNS if ledger is not None else []), keep_until)
        self.mesh = mesh
        self.gas = gas
        z = np.round(mesh.cell_centres[:, 2], 12)
        self.zlev = np.unique(z)
        self.bottom = np.flatnonzero(z == self.zlev[0])
        self.top = np.flatnonzero(z == self.zlev[-1])

    @staticmethod
    def particle_records(sim):
        """[E_particles, E_conv, E_walls, E_sources] (J) of the particles, summed over the ranks
        (collective): their thermal energy sum(C T) and what they received since the DEM's start
        by convection, through the walls, and by radiation, generation and sources."""
        from dem.thermal.heat import TOT
        a = np.zeros(4)
        if sim.thermal is not None:
            st, tot = sim.state, sim.thermal.tot
            n = st.n_owned
            a[:] = (float((st.temperature[:n] / st.inv_heat_capacity[:n]).sum()), tot[TOT.conv], tot[TOT.wall],
                    tot[TOT.rad] + tot[TOT.gen] + tot[TOT.src])
        if sim.par is not None:
            a = np.asarray(sim.par.allsum(a), float)
        return a

    @staticmethod
    def row_of(diag, t, step, sim, iface, fluid, frame, wall):
        """Particle sums of this rank, summed over the ranks; rank 0 (diag) writes the row. The
        particles' energy and convective heat are particle_records' (the balance's own)."""
        st = sim.state
        n = st.n_owned
        loc = np.zeros(7)
        if n:
            loc[3] = float(st.position[:n, 2].sum())
            loc[5] = float(np.sqrt((st.velocity[:n] ** 2).sum(1)).max())
        loc[4] = n
        loc[6] = iface.n_lost
        if sim.thermal is not None:
            loc[1] = float((1.0 / st.inv_heat_capacity[:n]).sum())
        if sim.par is not None:
            vmax = sim.par.allmax(loc[5])
            loc = sim.par.allsum(loc)
            loc[5] = vmax
        precs = Diagnostics.particle_records(sim)
        if diag is not None:
            diag.row(t, step, sim, iface, fluid, frame, wall, loc, precs)

    def row(self, t, step, sim, iface, fluid, frame, wall, sums, precs):
        """One coupling.csv row: ``sums`` = [-, sum C, -, sum z, n, max |v|, n lost] over the
        ranks, ``precs`` = particle_records."""
        V = self.mesh.cell_volumes
        g = self.gas
        eps = frame["eps"]
        T = fluid["T"]
        if sim.thermal is not None:
            Ep = float(precs[0])
            Tp = float(precs[0] / sums[1])
            Ec = float(precs[1])
        else:
            Tp = Ep = Ec = float("nan")
        mg = g.rho * g.cp * eps * V
        Eg = float((mg * T).sum())
        Tg = float(Eg / mg.sum())
        q = float(((frame["Sexp"] - frame["Simp"] * T) * V).sum())
        p = fluid["p"]
        dp = float(p[self.bottom].mean() - p[self.top].mean())
        zb = float(sums[3] / sums[4]) if sums[4] else 0.0
        row = dict(time=t, step=step, T_particles=Tp, T_gas=Tg, E_particles=Ep, E_gas=Eg,
                   Q_to_gas=q, E_conv_particles=Ec, dp=dp, bed_height=zb, v_max=float(sums[5]),
                   n_outside=int(sums[6]), eps_raw_min=iface.clip["eps_raw_min"],
                   eps_clipped_cells=iface.clip["cells"], wall=wall)
        if self.ledger is not None:
            row.update(self.ledger.row(fluid["scalars"], precs))
        self.hist.add(row)


def plot(out: Path, title: str) -> Path | None:
    """coupling.png: particle/gas temperature, heat rate, pressure drop, bed height."""
    try:
        import matplotlib
        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError:
        return None
    f = out / "coupling.csv"
    if not f.exists():
        return None
    d = np.atleast_1d(np.genfromtxt(f, delimiter=",", names=True))
    if d.size < 2:
        return None
    fig, ax = plt.subplots(2, 2, figsize=(10, 7))
    t = d["time"]
    ax[0, 0].plot(t, d["T_particles"], label="particles (mass-weighted)")
    ax[0, 0].plot(t, d["T_gas"], label="gas (eps rho cp V weighted)")
    ax[0, 0].set_ylabel("T [K]")
    ax[0, 0].legend()
    ax[0, 1].plot(t, d["Q_to_gas"])
    ax[0, 1].set_ylabel("heat to the gas [W]")
    ax[1, 0].plot(t, d["dp"])
    ax[1, 0].set_ylabel("p(bottom cells) - p(top cells) [Pa]")
    ax[1, 1].plot(t, d["bed_height"])
    ax[1, 1].set_ylabel("mean particle height [m]")
    for a in ax.ravel():
        a.set_xlabel("t [s]")
        a.grid(alpha=0.3)
    fig.suptitle(title)
    fig.tight_layout()
    p = out / "coupling.png"
    from dem.output import atomic_write
    try:
        atomic_write(str(p), lambda tmp: fig.savefig(tmp, dpi=110, format="png"))
    finally:
        plt.close(fig)
    return p


# --------------------------------------------------------------------------- run

class _ExternalSolver:
    """Stand-in for the solver process when the user starts it by hand (second terminal)."""

    pid = None

    def poll(self):
        return 0

    def wait(self, timeout=None):
        return 0

    def kill(self):
        pass


def run_case(case_dir, out=None, *, transport=None, end_time=None, restart=False,
             quiet=False, solver=None, log=print, external_solver=False, overwrite=False):
    """Run a coupled case; returns a summary dict. Raises CouplingError / CaseConfigError /
    SimulationError / CouplingRunError / dem.outdir.OutputFolderError (``main`` maps them to
    exit codes). ``out`` must be new, empty or an earlier output of this tool (continued with
    ``restart``, replaced with ``overwrite``: dem.outdir)."""
    from . import foam_case as fc
    from .case import check_coupled_case, format_report, load_case
    from .exchange import CouplingError, FileExchange, SocketExchange
    from .interface import CouplingInterface
    from .mesh import read_polymesh
    from dem.output import VTKSeries, History, remove_stale_temporaries, save_npz
    from dem.simulation import SimulationError

    from dem import outdir
    t_wall0 = time.perf_counter()
    out = Path(out) if out is not None else Path("out") / Path(case_dir).resolve().name
    out = out.resolve()
    # read-only, on every rank: a user's folder is refused before anything is read or written
    outdir.check(out, **output_rule(Path(case_dir).resolve(), restart=restart, overwrite=overwrite))
    case = load_case(case_dir)
    cfg = case.config
    if transport is not None:
        cfg.transport = transport
    sim = case.sim
    R = _Ranks(sim)
    R.barrier()   # every rank has checked --out before rank 0 claims it
    R.on_root(prepare_output, case, out, restart=restart, overwrite=overwrite)
    R.on_root(remove_stale_temporaries, str(out))  # left by a kill -9 of an earlier run (ours only)
    mesh = read_polymesh(str(out))
    from .energy import EnergyLedger, FluxSplit, tie_walls
    ties = tie_walls(case, mesh)          # tied walls checked on the gas mesh
    ledger = EnergyLedger(mesh, ties)
    split = FluxSplit(case, mesh, ties)   # tied walls: the particles' paths per cell (fixed flux: the split)
    iface = CouplingInterface.for_case(case, mesh)
    dt = case.dt_cfd
    k = cfg.coupling_interval
    # ---- checks of the case (on the scene's packing: the DEM check evaluates the contact
    # forces, so it must run before a restart loads its checkpoint)
    eps0 = iface.initial_void_fraction()
    rep = R.everywhere(check_coupled_case, case, mesh, eps0=eps0, clip=dict(iface.clip))
    rep = R.bcast(rep)
    if not quiet and R.root:
        log(format_report(case, rep))
        if R.par is not None:
            log(f"DEM: {R.size} MPI ranks, {R.par.describe()}")
    if rep["problems"] and not cfg.force:
        raise CouplingRunError(f"{case.config_file}: case refused by the checks:\n  "
                               + "\n  ".join(rep["problems"]))
    # ---- restart: the latest restart point (gas time + DEM checkpoint + coupling state)
    i0 = 0
    t_start = 0.0
    cstate = None
    if restart:
        i0, t_start, cstate = _restart(out, sim, iface, dt, log if R.root else _silent, R, mesh.n_cells)
        iface.reset_hints()
        iface.restore_state(cstate["iface"])  # the relaxation continues from what the gas last got
        ledger.restore(cstate["ledger"])      # the balance continues from its start (if recorded)
        split.restore(cstate["ledger"], sim)
    end = case.end_time if end_time is None else float(end_time)
    n_steps = int(round((end - t_start) / dt))
    if n_steps < 1:
        source = "--end-time" if end_time is not None else case.end_time_source
        if restart and n_steps == 0:  # the run already reached this end time: nothing to do
            if R.root:
                log(f"the run in {out} is already complete: it reached t = {t_start:.9g} s, the end time "
                    f"({end:g} s, from {source}); there is nothing to run. To continue it, give a later "
                    f"end time: coupling run {case_dir} --out {out} --restart --end-time T")
            return dict(out=str(out), steps=0, time=t_start, complete=True) if R.root else {}
        raise CouplingRunError(f"end time {end:g} s (from {source}) is not after the start time {t_start:g} s"
                               + (" of the restart point: give a later --end-time" if restart else ""))
    def _setup_gas():
        ctl = out / "system" / "controlDict"
        # 17 significant digits: a written time is a restart point that continues to round-off
        fc.set_entries(ctl, {"endTime": repr(end), "startFrom": "latestTime", "writePrecision": 17})
        if not restart:
            fc.write_eps(out, eps0)
        # ---- transport
        ex = None
        outdir.claim(out / "coupling")   # the exchange folder (file transport; the solver's pid file)
        if cfg.transport == "socket":
            ex = SocketExchange(port=0, timeout=cfg.timeout, n_cells=mesh.n_cells)
            fc.write_coupling_dict(out, "socket", port=ex.port, timeout=cfg.timeout,
                                   send_velocity=cfg.send_velocity, tied=split.couplingdict_entries())
        else:
            fc.write_coupling_dict(out, "file", timeout=cfg.timeout, send_velocity=cfg.send_velocity,
                                   tied=split.couplingdict_entries())
            ex = FileExchange(out / "coupling", timeout=cfg.timeout, n_cells=mesh.n_cells)
        if cfg.gas_processes > 1:
            if restart and (out / "processor0").exists():
                pass
            else:
                for name in ["log.decomposePar"] + [f"processor{i}" for i in range(cfg.gas_processes)]:
                    outdir.claim(out / name)
                fc.decompose(out, cfg.gas_processes)
        fc.check_case(out)
        exe = Path(solver) if solver else fc.build_solver()
        return ex, exe

    ex, exe = R.on_root(_setup_gas) or (None, None)
    sim.warmup()
    # ---- output writers
    out_int = cfg.output_interval or sim.scene.simulation["output_interval"]
    out_every = max(1, int(round(out_int / dt)))
    write_every = int(round(case.control["writeInterval"])) if case.control["writeControl"] == "timeStep" else 0
    keep = t_start if restart else None
    hist = vtk = diag = walls = walls_by_angle = None
    if R.root:
        hist = History(str(out / "history.csv"), sim.history_columns(), keep)
        if sim.thermal is not None and sim.scene.walls:
            from dem.thermal.wall_heat import WallAngleFile, WallHeatFile
            walls = WallHeatFile(str(out / "wall_heat.csv"), sim.scene, keep)
            if WallAngleFile.wanted(sim.scene):
                walls_by_angle = WallAngleFile(str(out / "wall_heat_angle.csv"), sim.scene, keep)
        vtk = VTKSeries(str(out)) if sim.scene.output["vtk"] else None
        diag = Diagnostics(out / "coupling.csv", mesh, case.gas, keep, ledger)
        outdir.claim(out / "checkpoints")
        (out / "checkpoints").mkdir(exist_ok=True)
    cont = _continue_command(case_dir, out, end_time, transport, R.size)
    timer = iface.timer
    if R.root:
        proc = _start_solver(out, cfg, exe, external_solver, log)
        ex.peer_process = proc if not external_solver else None
        link = _SolverLink(R, ex, proc, mesh, cfg, out, timer)
    else:
        link = _FollowerLink(R)

    def output(fluid, frame, t, step):
        _output(hist, vtk, diag, sim, iface, fluid, frame, t, step, t_wall0, timer)
        totals = sim.wall_heat_totals()   # collective over the DEM ranks
        from dem.thermal.wall_heat import WallAngleFile, cylinder_flux_by_angle
        by_angle = cylinder_flux_by_angle(sim) if WallAngleFile.wanted(sim.scene) else None   # collective
        with timer("output"):
            if walls is not None:
                walls.add(t, totals, gas=ledger.gas_wall_energy(len(sim.scene.walls)))
            if walls_by_angle is not None:
                walls_by_angle.add(t, by_angle)

    def restart_point(step, t, fluid):
        with timer("output"):
            _write_restart_point(R, sim, iface, out, step, t, fluid, ledger, split)

    loop = CoupledLoop(link, iface, RunWatch(mesh, cfg, log if R.root else _silent), output, restart_point,
                       n_steps=n_steps, i0=i0, t_start=t_start, dt=dt, k=k, out_every=out_every,
                       write_every=write_every, restart=restart, cstate=cstate,
                       log=log if R.root else _silent, ledger=ledger, split=split,
                       particle_energy=lambda: Diagnostics.particle_records(sim))
    status = "running"
    try:
        loop.run()
        status = "finished"
        link.finish(loop.step)
    except (CouplingError, SimulationError, KeyboardInterrupt) as e:
        status = "failed"
        link.fail(e)
        with timer("output"):
            sim.write_checkpoint(str(out / "checkpoint.npz"))
        link.explain(e, sim)
        raise
    finally:
        link.close(status, lambda failing: _write_timings(
            out / "timings.json", _timings(timer, t_wall0, sim, n_steps=loop.step - i0, k=k), failing=failing))
    # ---- final output
    fa = sim.final_arrays()
    if fa is not None:
        save_npz(str(out / "final.npz"), **fa)
    sim.write_checkpoint(str(out / "checkpoint.npz"))
    step, t = loop.step, loop.t
    png = plot(out, f"{case.dir.name}: {cfg.transport} transport") if R.root else None
    stop_sig, peer_sig = loop.stop_sig, loop.peer_sig
    if peer_sig:  # the solver stopped on a signal: did this process get one too (a scheduler's TERM)?
        stop_sig = stop_sig or link.own_stop()
    signum = stop_sig or peer_sig
    if signum:
        raise RunInterrupted(signum, _stopped_line(signum, bool(stop_sig), t, step, out, cont))
    if not R.root:
        return {}
    summ = _timings(timer, t_wall0, sim, n_steps=step - i0, k=k)
    summ.update(out=str(out), steps=step - i0, time=t, png=str(png) if png else None, **loop.watch.summary())
    if cstate is not None:
        summ["restart_frame_difference"] = cstate.get("frame_difference")
    if not quiet:
        log(_format_timings(summ))
    return summ


class CoupledLoop:
    """The coupled loop, the same on every DEM rank (rank 0 talks to the gas solver through
    its link, the other ranks receive what rank 0 got: :class:`_SolverLink`,
    :class:`_FollowerLink`), for a fresh start and a restart alike. Coupling step s
    (global index ``step = i0 + s``, time t -> t + dt):

    1. a stop request of this process (rank 0; every rank learns it with the next frame)
       makes this the last step;
    2. ``iface.prepare``: the exchange fields of the particles at t, the fluid force and heat
       set as the DEM's input for the interval (Simulation.set_fluid);
    3. (first step of a fresh run) the output of t = t_start;
    4. the frame is sent (FINAL flag on the last step), the DEM advances ``k`` steps while
       the gas solves the same interval, the particles are mapped for the next step;
    5. the gas frame of t + dt is received and checked (check_gas_fields);
    6. output every ``out_every`` coupling steps, a restart point every ``write_every``
       steps (the solver's writeInterval), both at the last step (end, stop or the solver's
       FINAL frame)."""

    def __init__(self, link, iface, watch, output, restart_point, *, n_steps, i0, t_start, dt, k,
                 out_every, write_every, restart, cstate, log, ledger=None, particle_energy=None, split=None):
        from dem.operations import Every
        self.link, self.iface, self.watch = link, iface, watch
        self.output, self.restart_point = output, restart_point
        self.n_steps, self.i0, self.t_start, self.dt, self.k = n_steps, i0, t_start, dt, k
        self.outputs = Every(out_every)            # in coupling steps of this run
        self.restart_points = Every(write_every)   # in coupling steps since t = 0 (OpenFOAM's writes)
        self.restart, self.cstate, self.log = restart, cstate, log
        self.ledger, self.particle_energy = ledger, particle_energy   # the energy balance (coupling.energy)
        self.split = split   # tied walls: the particles' paths per cell (coupling.energy.FluxSplit)
        self.step, self.t = i0, t_start
        self.stop_sig = 0   # SIGINT/SIGTERM of this process (rank 0 decides for every DEM rank)
        self.peer_sig = 0   # the signal that stopped the gas solver (other ranks: either signal)

    def run(self):
        from dem.operations import PAUSE
        link, iface, dt = self.link, self.iface, self.dt
        fluid = link.first(self.i0, self.t_start, self.cstate)
        ledger = self.ledger
        if ledger is not None:
            ledger.check(fluid["scalars"], self.i0)
            ledger.begin(fluid["scalars"], self.particle_energy())   # collective
        for s in range(1, self.n_steps + 1):
            self.step = step = self.i0 + s
            self.stop_sig = self.stop_sig or link.own_stop()
            last = s == self.n_steps or bool(self.stop_sig)   # a stop request ends this coupling step
            frame = iface.prepare(fluid, dt)
            if self.split:
                frame["wall_columns"] = self.split.columns(iface.sim, dt)   # collective
            self.watch.after_prepare(iface, self.t)
            if s == 1 and not self.restart:
                self.output(fluid, frame, self.t, step - 1)
            link.send(step, frame, self.t + dt, last)
            iface.advance_dem(self.k)
            self.t = t = self.t_start + s * dt
            if s < self.n_steps:   # (also on a stop step: every DEM rank does it, collectively)
                iface.map_particles()   # overlaps with the gas solve
            fluid, final, self.peer_sig = link.receive(step, t, iface.eps_change, self.stop_sig)
            if ledger is not None:
                ledger.check(fluid["scalars"], step)
                ledger.add(fluid["scalars"], dt)
            self.watch.after_receive(fluid, t)
            # peer_sig implies a FINAL frame; on the other ranks it also carries rank 0's stop
            done = last or final or bool(self.peer_sig)
            if self.outputs.fires(s, PAUSE) or done:
                self.output(fluid, frame, t, step)
            if done or self.restart_points.fires(step, PAUSE):
                self.restart_point(step, t, fluid)
            if done:
                if final and not last and not self.peer_sig:
                    self.log(f"coupling: the solver reached its endTime at step {step} (t = {t:g} s)")
                break


def _start_solver(out, cfg, exe, external_solver, log):
    """The gas solver process (rank 0): started here, or by the user (external_solver)."""
    from . import foam_case as fc
    from dem import outdir
    if external_solver:
        par = (f"mpirun --allow-run-as-root -np {cfg.gas_processes} " if cfg.gas_processes > 1 else "")
        log("coupling: start the gas solver yourself, in a second terminal:\n"
            f"  . {Path(__file__).resolve().parent.parent / 'scripts' / 'foam_env.sh'} && "
            f"{par}{exe} -case {out}{' -parallel' if cfg.gas_processes > 1 else ''}\n"
            f"coupling: waiting up to {cfg.timeout:g} s for it ({cfg.transport} transport)")
        sys.stdout.flush()
        proc = _ExternalSolver()
    else:
        outdir.claim(out / "log.thermoDemFoam")
        proc = fc.start_solver(out, nprocs=cfg.gas_processes, solver=exe, own_session=True)
    if cfg.solver_nice and proc.pid:
        try:  # a woken solver then does not preempt the DEM (the critical path) on busy cores
            os.setpriority(os.PRIO_PROCESS, proc.pid, cfg.solver_nice)
        except OSError:
            pass
    return proc


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
            tail = _log_tail(out / "log.thermoDemFoam")
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


def _write_timings(path, timings, failing):
    """timings.json, atomically (never a 0-byte file). While a run is already failing, a write
    error here is dropped so that the first error, the one the user needs, is the one reported."""
    from dem.output import OutputError, write_text
    try:
        write_text(str(path), json.dumps(timings, indent=1))
    except OutputError:
        if not failing:
            raise


def _first_frame(ex, i0, t_start, mesh, cfg, cstate):
    """The gas state the first DEM interval uses. After a restart the solver's frame is
    replaced by the one the DEM used at that step in the interrupted run (stored in the
    restart point), so the particles see exactly the same fluid data; the largest
    difference between the two is kept (0 when the gas fields were restored exactly)."""
    fluid = check_gas_fields(ex.receive(i0), i0, time_value=t_start, mesh=mesh, cfg=cfg)
    if cstate is None:
        return fluid
    saved = cstate["fluid"]
    cstate["frame_difference"] = max(float(np.max(np.abs(np.asarray(fluid[k]) - saved[k]), initial=0.0))
                                     for k in FLUID_FIELDS)
    return dict(fluid, **saved)


def _peer_signal(ex):
    """The signal number that stopped the gas solver (flags bits 8-15 of its last frame)."""
    h = ex.last_header
    return int((h["flags"] >> 8) & 0xFF) if h and (h["flags"] & 1) else 0


def _continue_command(case_dir, out, end_time, transport, nranks):
    """The exact command that continues this run from its latest restart point."""
    import shlex
    cmd = ([f"mpirun -np {nranks}"] if nranks > 1 else []) + [
        "coupling run", shlex.quote(str(case_dir)), "--out", shlex.quote(str(out)), "--restart"]
    if end_time is not None:
        cmd += ["--end-time", repr(float(end_time))]
    if transport is not None:
        cmd += ["--transport", transport]
    return " ".join(cmd)


def _stopped_line(signum, own, t, step, out, cont):
    who = "" if own else " of the gas solver"
    ck = out / "checkpoints" / f"checkpoint_{step:08d}.npz"
    return (f"stopped by {signal_name(signum)}{who} at t = {t:.9g} s (coupling step {step}); "
            f"restart point {ck} (gas: {out}/<time>); continue with: {cont}")


def _silent(*a, **k):
    pass


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


# gas speed above which the (incompressible) gas solution is taken as diverged: the
# speed of sound in air at 20 C (the model is invalid far below it, above Mach ~0.3)
GAS_SPEED_LIMIT = 343.0


class GasFieldError(CouplingError):
    """The gas state received from thermoDemFoam is non-physical (non-finite values,
    T <= 0 K, or a gas speed above GAS_SPEED_LIMIT): the gas solution diverged, or a
    sudden change of the void fraction forced it."""


class RunWatch:
    """Runtime warnings of a coupled run, each printed once (rank 0), the worst values kept
    for the summary: void fraction clipped at eps_min (solid volume the gas does not see),
    a sudden change of the void fraction between two coupling steps (the gas must displace
    that volume within one CFD step), a gas faster than Mach 0.3 (outside the
    incompressible model)."""

    EPS_CHANGE = 0.2          # void fraction change of a cell in one coupling step
    CLIPPED = 1e-3            # fraction of the particle volume hidden by the eps_min clipping
    GAS_SPEED = 100.0         # m/s, about Mach 0.3 in air

    def __init__(self, mesh, cfg, log):
        self.mesh, self.cfg, self.log = mesh, cfg, log
        self.clip = None
        self.eps_change = 0.0
        self.gas_speed = 0.0
        self._said = set()

    def _at(self, c):
        return f"cell {c} at {np.array2string(self.mesh.cell_centres[c], precision=6)}"

    def after_prepare(self, iface, t):
        c = iface.clip
        if c["cells"]:
            if c["fraction"] >= self.CLIPPED and "clip" not in self._said:
                self._said.add("clip")
                from .case import wider_void_fraction_models
                alt = wider_void_fraction_models(self.cfg.void_fraction)
                self.log(f"coupling: WARNING: at t = {t:.9g} s the void fraction of {c['cells']} cell(s) is below "
                         f"coupling.eps_min = {self.cfg.eps_min:g} (lowest 1 - V_solid/V_cell = "
                         f"{c['eps_raw_min']:.3g} in {self._at(c['cell'])}) and is clipped: "
                         f"{100 * c['fraction']:.3g} % of the particle volume is not seen by the gas (drag and "
                         f"pressure drop too low there). Use cells of at least 3 particle diameters, "
                         + (f"void_fraction = {alt} (now '{self.cfg.void_fraction}'), " if alt else "")
                         + "or a lower eps_min for a really dense bed")
            if self.clip is None:
                self.clip = dict(cells=0, fraction=0.0, eps_raw_min=1.0, first_time=t)
            self.clip["cells"] = max(self.clip["cells"], c["cells"])
            self.clip["fraction"] = max(self.clip["fraction"], c["fraction"])
            self.clip["eps_raw_min"] = min(self.clip["eps_raw_min"], c["eps_raw_min"])
        de, cell = iface.eps_change
        self.eps_change = max(self.eps_change, de)
        if de > self.EPS_CHANGE and "eps" not in self._said:
            self._said.add("eps")
            self.log(f"coupling: WARNING: at t = {t:.9g} s the void fraction of {self._at(cell)} changes by "
                     f"{de:.3g} in one coupling step: the gas must displace that volume within one CFD step "
                     f"(pressure and velocity spikes). Set coupling.smoothing_time to a few CFD steps (now "
                     f"{self.cfg.smoothing_time:g} s) or lower coupling_interval")

    def after_receive(self, fluid, t):
        u = np.asarray(fluid["U"])
        s2 = (u * u).sum(axis=1)
        c = int(np.argmax(s2)) if s2.size else -1
        v = float(np.sqrt(s2[c])) if c >= 0 else 0.0
        self.gas_speed = max(self.gas_speed, v)
        if v > self.GAS_SPEED and "speed" not in self._said:
            self._said.add("speed")
            self.log(f"coupling: WARNING: at t = {t:.9g} s the gas speed is {v:.3g} m/s in {self._at(c)}, above "
                     f"{self.GAS_SPEED:g} m/s (Mach 0.3): outside the incompressible gas model"
                     + (f"; the void fraction changed by up to {self.eps_change:.3g} in one coupling step "
                        f"(smoothing_time now {self.cfg.smoothing_time:g} s)" if self.eps_change > self.EPS_CHANGE
                        else ""))

    def summary(self):
        return dict(eps_clipping=self.clip, eps_change_max=self.eps_change, gas_speed_max=self.gas_speed)


def check_gas_fields(fluid, step, *, time_value=None, mesh=None, cfg=None, eps_change=None):
    """Guard on every gas frame received from the solver (before the DEM sees it): U, T,
    grad p and p finite, T > 0, |U| <= GAS_SPEED_LIMIT. Raises :class:`GasFieldError`
    naming the field, the number of bad cells, the first one (index and centre), the time
    and what to change."""
    bad = None
    for name, test, what in (
            ("U", lambda a: ~np.isfinite(a).all(axis=1), "non-finite"),
            ("T", lambda a: ~np.isfinite(a), "non-finite"),
            ("gradp", lambda a: ~np.isfinite(a).all(axis=1), "non-finite"),
            ("p", lambda a: ~np.isfinite(a), "non-finite"),
            ("T", lambda a: a <= 0.0, "at or below 0 K"),
            ("U", lambda a: (a * a).sum(axis=1) > GAS_SPEED_LIMIT ** 2,
             f"faster than {GAS_SPEED_LIMIT:g} m/s (the speed of sound)")):
        a = np.asarray(fluid[name])
        with np.errstate(invalid="ignore", over="ignore"):
            m = test(a)
        if np.any(m):
            cells = np.flatnonzero(m)
            bad = (name, what, cells)
            break
    if bad is None:
        return fluid
    name, what, cells = bad
    c = int(cells[0])
    val = np.asarray(fluid[name])[c]
    where = f"cell {c}"
    if mesh is not None:
        where += f" at {np.array2string(mesh.cell_centres[c], precision=6)}"
    when = f"t = {time_value:.9g} s" if time_value is not None else f"coupling step {step}"
    jump = eps_change is not None and eps_change[0] > RunWatch.EPS_CHANGE
    cause = "the gas solution diverged"
    smooth = (f"set coupling.smoothing_time to a few CFD steps (now {cfg.smoothing_time:g} s) so that eps and Ksl "
              f"change gradually" if cfg is not None else "set coupling.smoothing_time > 0")
    lower = ("lower deltaT in system/controlDict with coupling_interval (CFD step = coupling_interval x "
             "DEM time_step)")
    if jump:
        cause = (f"the void fraction of cell {eps_change[1]} changed by {eps_change[0]:.3g} in the last coupling "
                 f"step (the gas displaces that volume within one CFD step), or the gas solution diverged")
        advice = f"{smooth}; if particles moved that far within one step, {lower}"
    else:
        advice = f"{lower}, or {smooth}"
    if cfg is not None:
        advice += f"; raise coupling.eps_min (now {cfg.eps_min:g})"
        if cfg.void_fraction == "centre":
            advice += " or use void_fraction = 'divided' or 'smoothed' (now 'centre')"
    raise GasFieldError(
        f"gas field {name} received from the solver is {what} in {cells.size} cell(s) (first: {where}, "
        f"{name} = {np.array2string(np.atleast_1d(val), precision=6)}) at {when}: {cause}; the field is not "
        f"passed to the particles. Check log.thermoDemFoam; {advice}",
        peer="CFD solver", step=step)


def _share_failure(R, e):
    """Rank 0 failed outside a receive: the other ranks wait in one; tell them."""
    try:
        R.comm.bcast((None, True, repr(e), 0), root=0)
    except Exception:  # noqa: BLE001
        pass


COUPLING_STATE_FORMAT = "thermodem coupling state"
COUPLING_STATE_VERSION = 1
FLUID_FIELDS = {"U": 3, "T": 1, "gradp": 3, "p": 1}


def _restart_point_files(out: Path, step: int) -> tuple[Path, Path]:
    """checkpoints/checkpoint_<step>.npz (DEM) and checkpoints/coupling_<step>.npz."""
    d = out / "checkpoints"
    return d / f"checkpoint_{step:08d}.npz", d / f"coupling_{step:08d}.npz"


def _coupling_state(iface, step, t, fluid, ledger=None, split=None):
    """Arrays of checkpoints/coupling_<step>.npz: the exchange-field state of the
    interface (eps, Ksl as last sent: the time-smoothing relaxes from them) and the gas
    frame of this step (U, T, grad p, p), which the next DEM interval uses."""
    d = dict(format=np.str_(COUPLING_STATE_FORMAT), version=np.int64(COUPLING_STATE_VERSION),
             step=np.int64(step), time=np.float64(t))
    for key, a in iface.restart_state().items():
        d[f"iface_{key}"] = a
    for key in FLUID_FIELDS:
        d[f"fluid_{key}"] = np.ascontiguousarray(fluid[key], dtype=np.float64)
    d["fluid_scalars"] = np.ascontiguousarray(fluid.get("scalars", ()), dtype=np.float64)
    if ledger is not None:
        d.update(ledger.state())
    if split:
        d.update(split.state())
    return d


def _write_restart_point(R, sim, iface, out, step, t, fluid, ledger=None, split=None):
    """A restart point at this step (collective): the coupling state first, then the DEM
    checkpoint, each written atomically; ``--restart`` only takes a step whose DEM
    checkpoint exists, so a kill between the two writes leaves the previous point."""
    ck, cs = _restart_point_files(out, step)
    if R.root:
        from dem.output import save_npz
        save_npz(str(cs), durable=True, **_coupling_state(iface, step, t, fluid, ledger, split))
    sim.write_checkpoint(str(ck))
    return ck


def _load_coupling_state(path: Path, step: int, n_cells: int) -> dict:
    """Read and check checkpoints/coupling_<step>.npz; CouplingRunError naming the file."""
    why = ("it holds the exchange-field state and the last gas frame of the restart point, "
           "written with checkpoints/checkpoint_%08d.npz" % step)
    if not path.is_file():
        raise CouplingRunError(f"{path}: missing ({why}); this output cannot be continued exactly: "
                               f"start the run again without --restart")
    try:
        with np.load(path, allow_pickle=False) as z:
            arrays = {key: z[key] for key in z.files}
    except Exception as e:  # noqa: BLE001 - zip CRC, truncation, not an npz
        raise CouplingRunError(f"{path}: cannot be read as a coupling state ({type(e).__name__}: {e}); "
                               f"the file is damaged: restart from an earlier restart point by removing "
                               f"the later OpenFOAM time directories, or start again without --restart") from None
    fmt = str(arrays.get("format", ""))
    if fmt != COUPLING_STATE_FORMAT:
        raise CouplingRunError(f"{path}: not a coupling state of thermodem (format {fmt!r})")
    ver = int(arrays.get("version", -1))
    if ver != COUPLING_STATE_VERSION:
        raise CouplingRunError(f"{path}: coupling state version {ver}, this thermodem reads "
                               f"version {COUPLING_STATE_VERSION}")
    if int(arrays.get("step", -1)) != step:
        raise CouplingRunError(f"{path}: holds step {int(arrays.get('step', -1))}, expected {step}")
    fluid = {}
    for key, ncomp in FLUID_FIELDS.items():
        a = arrays.get(f"fluid_{key}")
        shape = (n_cells, ncomp) if ncomp > 1 else (n_cells,)
        if a is None or a.shape != shape or a.dtype != np.float64 or not np.all(np.isfinite(a)):
            raise CouplingRunError(f"{path}: gas field fluid_{key} missing, not float64 of shape {shape} "
                                   f"(the mesh has {n_cells} cells) or not finite")
        fluid[key] = a
    if "fluid_scalars" in arrays:   # the solver's energy ledger of the step (older states: none)
        fluid["scalars"] = np.asarray(arrays["fluid_scalars"], np.float64)
    iface = {key[6:]: a for key, a in arrays.items() if key.startswith("iface_")}
    for key in ("eps_sent", "ksl_sent"):
        if key not in iface:
            raise CouplingRunError(f"{path}: iface_{key} missing")
    ledger = {key: arrays[key] for key in ("ledger_acc", "ledger_ref", "split_sent") if key in arrays}
    return dict(fluid=fluid, iface=iface, ledger=ledger, time=float(arrays["time"]), path=path)


def _restart(out: Path, sim, iface, dt, log, R, n_cells):
    """Continue from the latest restart point: the latest OpenFOAM time directory whose
    step has a DEM checkpoint (checkpoints/checkpoint_<step>.npz) and a coupling state
    (checkpoints/coupling_<step>.npz). Loads both (the coupling state is returned, to be
    applied after the initial void fraction), removes later gas time directories.
    Returns (step index, time, coupling state)."""
    cks = {int(m.group(1)): p for p in (out / "checkpoints").glob("checkpoint_*.npz")
           if (m := re.match(r"checkpoint_(\d+)\.npz", p.name))}
    gas_times = [(tv, p) for tv, p in _time_dirs(out) if tv > 0]
    best = None
    for tv, p in gas_times:
        idx = _time_index(p)
        if idx is None:
            idx = int(round(tv / dt))
        if idx in cks:
            best = (idx, tv, p)
    if best is None:
        raise CouplingRunError(f"{out}: no OpenFOAM time directory with a matching DEM checkpoint "
                               f"(checkpoints/checkpoint_<step>.npz); gas times: "
                               f"{[p.name for _, p in gas_times]}, DEM checkpoints: {sorted(cks)}")
    idx, tv, p = best
    cstate = _load_coupling_state(_restart_point_files(out, idx)[1], idx, n_cells)
    R.barrier()  # every rank has chosen the same restart point before rank 0 prunes
    if R.root:
        for tv2, p2 in gas_times:
            if tv2 > tv + 1e-12:
                shutil.rmtree(p2)
        for proc in out.glob("processor*"):
            for tv2, p2 in _time_dirs(proc):
                if tv2 > tv + 1e-12:
                    shutil.rmtree(p2)
    sim.load_checkpoint(str(cks[idx]))
    if abs(sim.time - tv) > 1e-9 * max(1.0, tv):
        raise CouplingRunError(f"{cks[idx]}: DEM time {sim.time} does not match the gas time {tv}")
    log(f"coupling: restarting from t = {tv:g} s (step {idx}, {cks[idx].name}, {cstate['path'].name})")
    return idx, tv, cstate


def _output(hist, vtk, diag, sim, iface, fluid, frame, t, step, t_wall0, timer):
    """history.csv, VTK and coupling.csv rows (collective over the DEM ranks; rank 0 writes)."""
    with timer("output"):
        row = sim.history_row()
        if hist is not None:
            hist.add(row)
        if sim.scene.output["vtk"]:
            n = sim.state.n_owned
            force = np.ascontiguousarray(iface.last.get("force", np.zeros((n, 3))))
            sim.write_vtk(vtk, fluid_force=force)
        Diagnostics.row_of(diag, t, step, sim, iface, fluid, frame, time.perf_counter() - t_wall0)


def _timings(timer, t_wall0, sim, n_steps, k):
    wall = time.perf_counter() - t_wall0
    loop = sum(v for p, v in timer.total.items())
    d = {"wall_total": wall, "loop": loop, "phases": dict(timer.total),
         "coupling_steps": n_steps, "dem_steps": n_steps * k, "particles": sim.n_particles,
         "dem_ranks": 1 if sim.par is None else sim.par.size}
    d["particle_steps_per_s"] = sim.n_particles * n_steps * k / loop if loop > 0 else 0.0
    return d


def _format_timings(s):
    lines = [f"done: {s['coupling_steps']} coupling steps ({s['dem_steps']} DEM steps, "
             f"{s['particles']} particles) to t = {s['time']:.6g} s in {s['wall_total']:.1f} s "
             f"(loop {s['loop']:.1f} s, {s['particle_steps_per_s']:.3g} particle-steps/s)"]
    for p, v in s["phases"].items():
        lines.append(f"  {p:15s} {v:9.3f} s  {100 * v / max(s['loop'], 1e-12):5.1f} %")
    lines.append(f"output in {s['out']}" + (f" (plot {s['png']})" if s.get("png") else ""))
    return "\n".join(lines)


def _log_tail(path: Path, n=12) -> str:
    try:
        lines = path.read_text(errors="replace").splitlines()
    except OSError:
        return ""
    return "\n".join("    " + x for x in lines[-n:])


# --------------------------------------------------------------------------- CLI

@contextlib.contextmanager
def _case_on_temporary_mesh(case_dir):
    """A case read and checked on a meshed temporary copy of its OpenFOAM part (`coupling
    check`, `coupling compile`): yields (case, mesh, interface, initial void fraction, check
    report); the copy is removed afterwards."""
    from .case import check_coupled_case, load_case, mesh_in_tmp
    from .interface import CouplingInterface
    case = load_case(case_dir)
    tmp, mesh = mesh_in_tmp(case.dir)
    try:
        from .energy import tie_walls
        tie_walls(case, mesh)
        iface = CouplingInterface.for_case(case, mesh)
        eps0 = iface.initial_void_fraction()
        rep = check_coupled_case(case, mesh, eps0=eps0, clip=dict(iface.clip))
        yield case, mesh, iface, eps0, rep
    finally:
        shutil.rmtree(tmp, ignore_errors=True)


def cmd_check(args) -> int:
    from .case import format_report
    with _case_on_temporary_mesh(args.case) as (case, _mesh, _iface, eps0, rep):
        pass
    print(format_report(case, rep))
    print(f"  initial void fraction: min {eps0.min():.3f}, mean {eps0.mean():.3f}")
    return 0 if (not rep["problems"] or case.config.force) else EXIT_CHECK


def cmd_compile(args) -> int:
    """Fill Numba's cache with the coupling kernels (done by scripts/setup.sh): for each case
    shipped in openfoam_cases/ (or the cases named), mesh a temporary copy, then one exchange
    (locate, void fraction, interpolation, drag, heat terms) and one DEM step with the fluid
    data, as the first coupling step of a run does. No gas solver runs and nothing is written
    outside the temporary folders. Every case shares the kernels, so a case of the user's
    then starts its first step in seconds."""
    t0 = time.perf_counter()
    root = Path(__file__).resolve().parent.parent / "openfoam_cases"
    cases = [Path(c) for c in args.case] or sorted(p.parent for p in root.glob("*/coupling.toml"))
    for case_dir in cases:
        with _case_on_temporary_mesh(case_dir) as (case, mesh, iface, _eps0, _rep):
            nc = mesh.n_cells
            st = case.sim.state
            t_gas = float(st.temperature[:st.n_owned].mean()) if case.sim.thermal is not None and st.n_owned else 300.0
            fluid = {"U": np.zeros((nc, 3)), "gradp": np.zeros((nc, 3)), "T": np.full(nc, t_gas)}
            case.sim.warmup()
            iface.prepare(fluid, case.dt_cfd)
            iface.advance_dem(1)
            iface.map_particles()
        print(f"  {case.dir.name}: compiled", flush=True)
    print(f"coupling kernels compiled and cached in {time.perf_counter() - t0:.1f} s")
    return 0


def cmd_run(args) -> int:
    # SIGINT/SIGTERM from here on (also during meshing and compiling) only set a flag: the
    # coupled loop ends its current coupling step, writes a restart point and stops
    with StopSignals():
        run_case(args.case, args.out, transport=args.transport, end_time=args.end_time,
                 restart=args.restart, quiet=args.quiet, external_solver=args.external_solver,
                 overwrite=args.overwrite)
    return 0


def main(argv=None) -> int:
    from dem.args import end_time
    ap = argparse.ArgumentParser(prog="coupling", description="CFD-DEM coupling (thermodem + thermoDemFoam)")
    sub = ap.add_subparsers(dest="cmd", required=True)
    c = sub.add_parser("check", help="validate a coupled case and print the coupling checks")
    c.add_argument("case")
    r = sub.add_parser("run", help="run a coupled case")
    r.add_argument("case")
    r.add_argument("--out", default=None, help="output directory (default out/<case name>)")
    r.add_argument("--transport", choices=["file", "socket"], default=None)
    r.add_argument("--end-time", type=end_time, default=None, help="override the end time (s)")
    r.add_argument("--restart", action="store_true", help="continue the run in --out")
    r.add_argument("--overwrite", action="store_true",
                   help="replace an earlier output in --out: removes only what the tool wrote there "
                        "(listed in its .thermodem-manifest.json) and refuses if anything else is there")
    r.add_argument("--quiet", action="store_true")
    r.add_argument("--external-solver", action="store_true",
                   help="do not start thermoDemFoam: print the command to run it by hand in a second "
                        "terminal and wait for it")
    k = sub.add_parser("compile", help="compile and cache the coupling kernels (done by scripts/setup.sh)")
    k.add_argument("case", nargs="*", help="cases to exercise (default: every case of openfoam_cases/)")
    args = ap.parse_args(argv)

    from dem.parallel import launched_rank, launched_size
    nranks = launched_size()
    if nranks == 1 and any(k.startswith("OMPI_") or k.startswith("PMIX_") for k in os.environ):
        _scrub_mpi_env()  # mpirun -np 1: a serial DEM; nothing of the job must reach the solver
    if launched_rank() != 0:  # the DEM ranks other than 0 say nothing; rank 0 reports for all
        sys.stdout = open(os.devnull, "w")
        sys.stderr = open(os.devnull, "w")

    from .case import CaseConfigError
    from .exchange import CouplingError
    from .foam_case import CaseError, FoamError
    from dem.output import DISK_ERRNOS, OutputError
    from dem.scene import SceneError
    from dem.simulation import SimulationError
    try:
        return {"check": cmd_check, "compile": cmd_compile, "run": cmd_run}[args.cmd](args)
    except CouplingError as e:
        print(f"coupling: error: coupling failed: {e}", file=sys.stderr)
        return EXIT_COUPLING
    except SimulationError as e:
        print(f"coupling: error: DEM failed: {e}", file=sys.stderr)
        return EXIT_DEM
    except (CaseConfigError, CaseError, SceneError, CouplingRunError, FoamError) as e:
        print(f"coupling: error: {e}", file=sys.stderr)
        return EXIT_CHECK
    except MemoryError:
        print("coupling: error: out of memory (the DEM scene or the mesh did not fit); use fewer particles "
              "or cells", file=sys.stderr)
        return EXIT_DEM
    except OutputError as e:  # disk full, quota, read-only: written by the DEM side
        print(f"coupling: error: {e}", file=sys.stderr)
        return EXIT_DEM
    except OSError as e:
        if e.errno not in DISK_ERRNOS:
            raise
        print(f"coupling: error: {OutputError(e.filename or '(unnamed file)', e)}", file=sys.stderr)
        return EXIT_DEM
    except RunInterrupted as e:
        print(f"coupling: {e.message}", file=sys.stderr)
        return e.exit_code
    except KeyboardInterrupt:  # a second signal while the first one was served
        print("coupling: interrupted (second signal): stopped at once; continue from the latest "
              "restart point with --restart", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
