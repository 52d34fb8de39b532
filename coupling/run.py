"""``coupling`` command: check and run a coupled CFD-DEM case (DEM side + thermoDemFoam).

    coupling check CASE_DIR
    coupling run   CASE_DIR [--out DIR] [--transport file|socket] [--end-time T] [--restart | --overwrite]

``run`` copies the OpenFOAM part of CASE_DIR into the output directory (default
``out/<case name>``; new, empty or an earlier output of this tool, never the case folder nor
inside it: dem.outdir), meshes it (blockMesh), writes the initial void fraction of the
particles into 0/eps, decomposes it when ``gas_processes > 1`` (under MPI with the socket
transport the other way round: decomposePar first, then each processor's 0/eps from the DEM
ranks owning its cells, no rank reading the whole mesh: coupling.pieces), builds the solver if
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
``run_case`` called from Python does not). Under ``mpirun -np M`` the DEM runs on M ranks;
with several DEM ranks or ``gas_processes > 1`` the socket transport is many-to-many
(coupling.m2m: each DEM rank exchanges the cells it owns with the gas processors holding
them; coupling.cells).
"""
from __future__ import annotations

import argparse
import contextlib
import os
import shutil
import sys
import time
from pathlib import Path

import numpy as np

from dem.interrupt import StopSignals

# the stages of a coupled run (each module's docstring says what it owns)
from .diagnostics import (Diagnostics, Outputs, RunWatch, check_gas_fields, format_timings,  # noqa: F401
                          plot, timings, write_timings)
from .errors import CouplingError, CouplingRunError, GasFieldError, RunInterrupted  # noqa: F401
from .launch import scrub_mpi_env, start_solver
from . import pieces
from .loop import CoupledLoop, LoopPlan
from .prepare import output_rule, prepare_gas, prepare_output
from .restart import RestartPoints, continue_command, resume, stopped_line
from .transport import Ranks, _peak_rss_mib, open_link, open_m2m, uses_m2m

EXIT_CHECK = 2
EXIT_COUPLING = 3
EXIT_DEM = 4


def run_case(case_dir, out=None, *, transport=None, end_time=None, restart=False,
             quiet=False, solver=None, log=print, external_solver=False, overwrite=False, threads=1):
    """Run a coupled case; returns a summary dict. Raises CouplingError / CaseConfigError /
    SimulationError / CouplingRunError / dem.outdir.OutputFolderError (``main`` maps them to
    exit codes). ``out`` must be new, empty or an earlier output of this tool (continued with
    ``restart``, replaced with ``overwrite``: dem.outdir). The stages: prepare (folder, case,
    checks, restart point, gas case), launch (the solver), the transport (link), the loop,
    the final output."""
    from dem import outdir
    from dem.output import remove_stale_temporaries
    from .case import load_case
    from .energy import EnergyLedger, FluxSplit, tie_walls
    from .interface import CouplingInterface
    from .mesh import read_polymesh
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
    # the DEM's threads in each DEM rank; 'auto' leaves each DEM rank's share of the gas solver's
    # processes their cores (the gas solves while the DEM steps: docs/architecture.md)
    ranks = sim.par.comm.Get_size() if sim.par is not None else 1
    sim.set_threads(threads, reserve=0 if external_solver else -(-cfg.gas_processes // ranks))
    R = Ranks(sim)
    if R.size > 1 and cfg.transport != "socket":
        raise CouplingRunError(f"{case.config_file}: transport = \"{cfg.transport}\" runs with one DEM rank; with "
                               f"{R.size} DEM ranks use transport = \"socket\" (each rank exchanges its own cells "
                               "with the gas processors: docs/coupling_protocol.md)")
    R.barrier()   # every rank has checked --out before rank 0 claims it
    R.on_root(prepare_output, case, out, restart=restart, overwrite=overwrite)
    R.on_root(remove_stale_temporaries, str(out))  # left by a kill -9 of an earlier run (ours only)
    m2m = uses_m2m(cfg, R.size)
    table = None
    if R.par is not None and pieces.pieced(out, cfg, restart, m2m):
        # the gas decomposed first; each DEM rank reads the pieces around its box and those
        # holding its cells, never the whole mesh (coupling.pieces)
        if not restart:
            R.on_root(pieces.decompose_first, out, cfg.gas_processes)
        table, mesh = R.everywhere(pieces.on_rank, R.par.rank, _pieces_mesh, out, R.par, sim, cfg)
        iface = CouplingInterface.for_case(case, mesh, source=mesh_source(out, cfg, mesh, table))
        iface.cells.setup_read["table"] = table.table_read
        ties = tie_walls(case, iface.mesh, ranks=iface.cells)   # the owned cells' patch faces, reduced
    else:
        # the whole mesh, at set-up only: each DEM rank keeps the cells it sees (its local mesh,
        # coupling.cells) and reads the whole mesh again only when a re-cut of the DEM boxes moves
        # its view beyond them
        mesh = read_polymesh(str(out))
        ties = tie_walls(case, mesh)          # tied walls checked on the gas mesh
        iface = CouplingInterface.for_case(case, mesh, source=mesh_source(out, cfg, mesh))
    ledger = EnergyLedger(iface.mesh, ties)   # the patches (names, types: every local mesh has them all)
    split = FluxSplit(case, iface.mesh, ties)   # tied walls: the particles' paths per cell (fixed flux: the split)
    # ---- checks of the case (on the scene's packing: the DEM check evaluates the contact
    # forces, so it must run before a restart loads its checkpoint)
    eps0 = iface.initial_void_fraction()
    if table is not None:
        _check(R, case, iface.mesh, iface, eps0, quiet, log, umax=table.umax)
    else:
        _check(R, case, mesh, iface, iface.cells.spread(eps0, 1.0), quiet, log)
    # ---- restart: the latest restart point (gas time + DEM checkpoint + coupling state)
    i0, t_start, cstate = resume(R, out, iface, ledger, split, case.dt_cfd, log) if restart else (0, 0.0, None)
    end = case.end_time if end_time is None else float(end_time)
    plan = _plan(case, restart, end, i0, t_start, cstate)
    if plan.n_steps < 1:
        return _nothing_to_run(R, case_dir, case, out, end_time, end, restart, plan, log)
    if table is not None:   # each processor's 0/eps from its cells' owners (coupling.pieces)
        eps_all = None
        if not restart:
            R.everywhere(pieces.on_rank, R.par.rank, pieces.write_eps_pieces, table, iface.cells, eps0)
    else:
        eps_all = iface.cells.gather_owned(eps0)   # rank 0 writes the gas's initial void fraction (set-up)
    ex, exe = R.on_root(prepare_gas, out, cfg, iface.cells.n_global, split, eps_all, end, restart=restart,
                        solver=solver, m2m=m2m, gas_dir=cstate["gas_dir"] if cstate else None,
                        decomposed=table is not None, log=log) or (None, None)
    eps_all = mesh = None   # from here on each rank holds its local mesh only (iface.mesh)
    iface.cells.setup_read["peak_rss_mib"] = _peak_rss_mib()   # the set-up's peak (timings.json)
    if m2m:
        ex = open_m2m(R, out, cfg, iface.cells)   # every rank listens and writes its plan lines
    sim.warmup()
    output = Outputs(R.root, iface, case, ledger, out, t_start if restart else None, t_wall0)
    restart_point = RestartPoints(R, sim, iface, out, ledger, split)
    cont = continue_command(case_dir, out, end_time, transport, R.size)
    proc = start_solver(out, cfg, exe, external_solver, log) if R.root else None
    link = open_link(R, ex, proc, iface.mesh, cfg, out, iface.timer, external=external_solver, cells=iface.cells,
                     restart_pieces=cstate.get("pieces_read") if cstate else None)
    loop = CoupledLoop(link, iface, RunWatch(iface.mesh, cfg, R.log(log), cells=iface.cells), output, restart_point, plan,
                       log=R.log(log), ledger=ledger, split=split,
                       particle_energy=lambda: Diagnostics.particle_records(sim))
    _drive(loop, link, sim, out, t_wall0)
    return _finish(R, loop, case, out, cont, t_wall0, quiet, log)


def mesh_source(out, cfg, mesh, table=None):
    """Where a DEM rank reads gas cells again after a re-cut of the DEM boxes moved its view
    beyond its local mesh (coupling.cells.CellShare): the pieces of the decomposed gas case
    that overlap the regions it needs (gas_processes > 1), else the whole mesh. Keeps only
    the whole mesh's size, lattice spacing and location tolerance (``table``: the pieces'
    boxes, coupling.pieces.PieceTable, when the set-up read by pieces)."""
    from .mesh import MeshPieces, UniformGrid, read_polymesh
    ug = mesh.uniform_grid
    grid = None if ug is None else UniformGrid(ug.origin, ug.h, ug.dims, np.zeros(0, np.int64))
    reader = (table.pieces(grid, mesh.tol) if table is not None
              else MeshPieces(out, getattr(mesh, "n_global", mesh.n_cells), grid, mesh.tol))

    def read(regions):
        if cfg.gas_processes > 1 and MeshPieces.procs(str(out)):
            return reader.read(regions)
        return read_polymesh(str(out))
    return read


def _pieces_mesh(out, par, sim, cfg):
    """(PieceTable, the mesh of the pieces this rank needs) (coupling.pieces)."""
    from .cells import CellShare
    table = pieces.PieceTable(out, par.comm, par.dec, par.rank, par.size)
    reach = sim.world.halo(bound=True) + table.cell_diag * CellShare.REACH_CELLS
    mesh = table.local_mesh((par.dec.blo[par.rank], par.dec.bhi[par.rank]), reach, par.dec)
    return table, mesh


def _check(R, case, mesh, iface, eps0, quiet, log, umax=None):
    """The coupling checks on every rank (report on rank 0); CouplingRunError if refused."""
    from .case import check_coupled_case, format_report
    rep = R.everywhere(check_coupled_case, case, mesh, eps0=eps0, clip=dict(iface.clip),
                       ranks=iface.cells, umax=umax)
    rep = R.bcast(rep)
    if not quiet and R.root:
        log(format_report(case, rep))
        if R.par is not None:
            log(f"DEM: {R.size} MPI ranks, {R.par.describe()}")
    if rep["problems"] and not case.config.force:
        raise CouplingRunError(f"{case.config_file}: case refused by the checks:\n  "
                               + "\n  ".join(rep["problems"]))


def _plan(case, restart, end, i0, t_start, cstate) -> LoopPlan:
    """The coupling steps from t_start to ``end``, the output and restart-point intervals."""
    dt = case.dt_cfd
    out_int = case.config.output_interval or case.sim.scene.simulation["output_interval"]
    write_every = int(round(case.control["writeInterval"])) if case.control["writeControl"] == "timeStep" else 0
    return LoopPlan(n_steps=int(round((end - t_start) / dt)), i0=i0, t_start=t_start, dt=dt,
                    k=case.config.coupling_interval, out_every=max(1, int(round(out_int / dt))),
                    write_every=write_every, restart=restart, cstate=cstate)


def _nothing_to_run(R, case_dir, case, out, end_time, end, restart, plan, log):
    """A restart that already reached its end time (a summary saying so), else the error."""
    t_start = plan.t_start
    source = "--end-time" if end_time is not None else case.end_time_source
    if restart and plan.n_steps == 0:  # the run already reached this end time: nothing to do
        if R.root:
            log(f"the run in {out} is already complete: it reached t = {t_start:.9g} s, the end time "
                f"({end:g} s, from {source}); there is nothing to run. To continue it, give a later "
                f"end time: coupling run {case_dir} --out {out} --restart --end-time T")
        return dict(out=str(out), steps=0, time=t_start, complete=True) if R.root else {}
    raise CouplingRunError(f"end time {end:g} s (from {source}) is not after the start time {t_start:g} s"
                           + (" of the restart point: give a later --end-time" if restart else ""))


def _drive(loop, link, sim, out, t_wall0):
    """Run the loop; on a failure checkpoint the DEM and explain; always close the link."""
    from dem.simulation import SimulationError
    timer = loop.iface.timer
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
        link.close(status, lambda failing, extra: write_timings(
            out / "timings.json", dict(timings(timer, t_wall0, sim, n_steps=loop.step - loop.i0, k=loop.k),
                                       **(extra or {})), failing=failing))


def _finish(R, loop, case, out, cont, t_wall0, quiet, log):
    """The final output (final.npz, checkpoint.npz, coupling.png), RunInterrupted after a
    signal, the summary (rank 0; {} elsewhere)."""
    sim = loop.iface.sim
    sim.write_final(str(out / "final.npz"))   # under MPI a piece per rank and a manifest (dem.final)
    sim.write_checkpoint(str(out / "checkpoint.npz"))
    step, t = loop.step, loop.t
    png = plot(out, f"{case.dir.name}: {case.config.transport} transport") if R.root else None
    stop_sig, peer_sig = loop.stop_sig, loop.peer_sig
    if peer_sig:  # the solver stopped on a signal: did this process get one too (a scheduler's TERM)?
        stop_sig = stop_sig or loop.link.own_stop()
    signum = stop_sig or peer_sig
    if signum:
        raise RunInterrupted(signum, stopped_line(signum, bool(stop_sig), t, step, out, cont))
    if not R.root:
        return {}
    summ = timings(loop.iface.timer, t_wall0, sim, n_steps=step - loop.i0, k=loop.k)
    summ.update(out=str(out), steps=step - loop.i0, time=t, png=str(png) if png else None, **loop.watch.summary())
    if loop.cstate is not None:
        summ["restart_frame_difference"] = loop.cstate.get("frame_difference")
    if not quiet:
        log(format_timings(summ))
    return summ


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
        rep = check_coupled_case(case, mesh, eps0=iface.cells.spread(eps0, 1.0), clip=dict(iface.clip))
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


def compile_case(case_dir, void_methods=False) -> None:
    """A warm-up job of ``coupling compile`` (dem.compile): mesh a temporary copy of the case,
    then two exchanges (locate, void fraction, interpolation, drag, heat terms; the second
    one also gathers the particle velocity the gas responded to) each followed by one DEM step
    with the fluid data, as the first coupling steps of a run do. No gas solver runs and
    nothing is written outside the temporary folders. ``void_methods``: also the particle
    void fraction of every method (coupling.particle_void), whatever the case chose."""
    with _case_on_temporary_mesh(Path(case_dir)) as (case, mesh, iface, _eps0, _rep):
        nc = mesh.n_cells
        st = case.sim.state
        t_gas = float(st.temperature[:st.n_owned].mean()) if case.sim.thermal is not None and st.n_owned else 300.0
        fluid = {"U": np.zeros((nc, 3)), "gradp": np.zeros((nc, 3)), "T": np.full(nc, t_gas)}
        case.sim.warmup()
        for _ in range(2):
            iface.prepare(fluid, case.dt_cfd)
            iface.advance_dem(1)
            iface.map_particles()
        if void_methods:
            from .particle_void import METHODS, ParticleVoidFraction
            eps_c = np.full(st.n_owned, 0.5)
            for method in METHODS[1:]:
                ParticleVoidFraction(method, case.sim.world.rmax)(case.sim, eps_c, iface.rmin, 0.3)


def compile_jobs(cases=(), dem_jobs=True):
    """The warm-up jobs of ``coupling compile`` (dem.compile.Job): one per case (default: every
    case of openfoam_cases/), plus the DEM jobs (dem.compile.DEM_JOBS) when ``dem_jobs``. A
    case's job starts after the DEM job compiling its step (heat or not) and after the first
    case's (which compiles the coupling kernels every case shares), so that no kernel is
    compiled twice at the same time."""
    import tomllib
    from dem.compile import DEM_JOBS, Job
    root = Path(__file__).resolve().parent.parent / "openfoam_cases"
    cases = [Path(c) for c in cases] or sorted(p.parent for p in root.glob("*/coupling.toml"))

    def dem_scene(c):
        try:
            with open(c / "dem.toml", "rb") as fh:
                return tomllib.load(fh)
        except (OSError, tomllib.TOMLDecodeError):
            return {}   # the job itself reports what is wrong with the case
    scenes = [dem_scene(c) for c in cases]
    # first: a case without heat, so that it can start as soon as the mechanics-only step is in
    # the cache (the heat step takes longest to compile)
    order = sorted(range(len(cases)), key=lambda i: "thermal" in scenes[i])
    first = order[0] if order else None
    names = {}
    jobs = list(DEM_JOBS) if dem_jobs else []
    present = {j.name for j in jobs}
    for i in order:
        c, sc = cases[i], scenes[i]
        name = c.resolve().name
        names[i] = name = name if name not in names.values() else f"{name}#{i}"
        after = ["dem.heat" if "thermal" in sc else "dem.mechanics"]
        if any("count" in g for g in sc.get("particles", []) if isinstance(g, dict)):
            after.append("dem.insertion")
        if i != first:
            after.append(names[first])
        jobs.append(Job(name, "coupling.run:compile_case", (str(c), i == first),
                        after=tuple(a for a in after if a in present or a in names.values())))
    return jobs


def cmd_compile(args) -> int:
    """Fill Numba's cache with the coupling and DEM kernels (done by scripts/setup.sh): the
    jobs of :func:`compile_jobs` in parallel worker processes (dem.compile). Every case shares
    the kernels, so a case of the user's then starts its first step in seconds. Cases named on
    the command line: only theirs."""
    from dem.compile import main_compile
    jobs = compile_jobs(args.case, dem_jobs=not args.case)
    return main_compile(jobs, args.jobs, what="coupling kernels" if args.case else "DEM and coupling kernels")


def cmd_render(args) -> int:
    from dem.outdir import OutputFolderError
    from .render import animate, render
    if not args.animate:
        for given, opt in ((args.times, "--times"), (args.frames, "--frames")):
            if given is not None:
                raise OutputFolderError(f"{opt} is an option of --animate (add --animate; for one picture give "
                                        f"--time T and --png P)")
        print(f"wrote {render(args.out_dir, args.png, field=args.field, time=args.time)}")
        return 0
    for given, opt in ((args.time, "--time"), (args.png, "--png")):
        if given is not None:
            raise OutputFolderError(f"{opt} is for one picture; --animate draws every written gas time (choose them "
                                    f"with --times START:END) into --frames DIR")
    folder, frames, gif = animate(args.out_dir, field=args.field, times=args.times, frames=args.frames)
    print(f"wrote {len(frames)} frames {os.path.join(folder, 'frame_0000.png')} ... and {gif}")
    return 0


def cmd_run(args) -> int:
    # SIGINT/SIGTERM from here on (also during meshing and compiling) only set a flag: the
    # coupled loop ends its current coupling step, writes a restart point and stops
    with StopSignals():
        run_case(args.case, args.out, transport=args.transport, end_time=args.end_time,
                 restart=args.restart, quiet=args.quiet, external_solver=args.external_solver,
                 overwrite=args.overwrite, threads=args.threads)
    return 0


def main(argv=None) -> int:
    from dem.args import end_time
    from dem.threads import argument as threads_argument
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
    r.add_argument("--threads", type=threads_argument, default="auto",
                   help="threads of each DEM rank (default auto: the cores of this process, shared among the DEM "
                        "ranks of its node); the gas runs between the DEM intervals")
    r.add_argument("--external-solver", action="store_true",
                   help="do not start thermoDemFoam: print the command to run it by hand in a second "
                        "terminal and wait for it")
    g = sub.add_parser("render", help="one picture of both phases: a mid-plane slice of a gas field with the "
                                      "particles near the plane (off-screen PNG); --animate: one per written gas time")
    g.add_argument("out_dir", help="the --out folder of a coupling run")
    g.add_argument("--field", default="eps", help="gas field on the slice: eps (alias alpha, the default), U "
                                                  "(speed), T or p")
    from .render import time_argument, times_argument
    g.add_argument("--time", type=time_argument, default=None, help="the written gas time nearest this (s, >= 0; "
                                                                    "default the last)")
    g.add_argument("--png", default=None, help="where (default OUT/gas_render.png; never a file the tool did "
                                               "not write)")
    g.add_argument("--animate", action="store_true",
                   help="a short animation: one frame per written gas time (t = 0 included) into a folder of its "
                        "own, frame_0000.png ... and animation.gif, with the colour ranges of all the frames")
    g.add_argument("--times", type=times_argument, default=None, metavar="START:END",
                   help="with --animate: the written gas times from START to END (s; either end may be left out; "
                        "default all)")
    g.add_argument("--frames", default=None, metavar="DIR",
                   help="with --animate: the folder of the frames (default OUT/gas_animation_<field>; new, empty "
                        "or an earlier animation: never a folder holding files the tool did not write)")
    k = sub.add_parser("compile", help="compile and cache the coupling kernels (done by scripts/setup.sh)")
    k.add_argument("case", nargs="*", help="cases to exercise (default: every case of openfoam_cases/, and the "
                                           "DEM kernels of `dem compile`)")
    from dem.compile import jobs_argument
    k.add_argument("--jobs", "-j", type=jobs_argument, default=None,
                   help="worker processes compiling in parallel (default: the usable cores)")
    args = ap.parse_args(argv)

    from dem.parallel import launched_rank, launched_size
    nranks = launched_size()
    if nranks == 1 and any(k.startswith("OMPI_") or k.startswith("PMIX_") for k in os.environ):
        scrub_mpi_env()  # mpirun -np 1: a serial DEM; nothing of the job must reach the solver
    if launched_rank() != 0:  # the DEM ranks other than 0 say nothing; rank 0 reports for all
        sys.stdout = open(os.devnull, "w")
        sys.stderr = open(os.devnull, "w")

    from .case import CaseConfigError
    from .exchange import CouplingError
    from .foam_case import CaseError, FoamError
    from dem.output import DISK_ERRNOS, OutputError
    from dem.scene import SceneError
    from dem.simulation import SimulationError
    from dem.threads import ThreadsError
    try:
        return {"check": cmd_check, "compile": cmd_compile, "run": cmd_run, "render": cmd_render}[args.cmd](args)
    except CouplingError as e:
        print(f"coupling: error: coupling failed: {e}", file=sys.stderr)
        return EXIT_COUPLING
    except SimulationError as e:
        print(f"coupling: error: DEM failed: {e}", file=sys.stderr)
        return EXIT_DEM
    except (CaseConfigError, CaseError, SceneError, CouplingRunError, FoamError, ThreadsError) as e:
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
