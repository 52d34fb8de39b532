"""Command line: ``dem run``, ``dem check``, ``dem render``."""
import argparse
import os
import sys
import time

# dt / t_H below which a Hertz impact's restitution and contact time are within 1 % with
# damping = exact (work-precision sweep, docs/benchmarks/accuracy.md "Hertz binary impact")
ACCURATE_HERTZ_FRACTION = 0.02


def _load(path):
    from .simulation import Simulation
    return Simulation.from_file(path)  # refuses a scene over the available memory (dem.memory)


def cmd_check(args):
    sim = _load(args.scene)
    rep = sim.check()
    p = print if sim.is_root else (lambda *a, **k: None)   # under mpirun: rank 0 reports for all
    p(f"scene: {args.scene}")
    p(f"particles: {rep['particles']}  walls: {rep['walls']}  materials: {rep['materials']}")
    p(f"radius: {rep['radius_min']:.4g} .. {rep['radius_max']:.4g} m   mass: {rep['mass_min']:.4g} .. "
      f"{rep['mass_max']:.4g} kg (total {rep['mass_total']:.4g} kg)")
    from .scene import parcel_factors
    cgs = parcel_factors(sim.scene)
    if cgs is not None:
        import numpy as np
        sc = sim.scene
        counts = (sc.group_totals if getattr(sc, "distributed", False)
                  else np.bincount(sc.group, minlength=len(sc.group_cg)).tolist())
        for g, (c, k) in enumerate(zip(sc.group_cg, counts)):
            if c != 1.0:
                p(f"coarse graining, group {int(g)}: cg = {c:g}, parcels of {c:g} x the real radius, each "
                  f"{c ** 3:.4g} real particles: {k} parcels = {k * c ** 3:.4g} real particles")
    p(f"time step: {rep['dt']:.4g} s   steps: {rep['steps']}")
    p(f"Rayleigh time: {rep['rayleigh_time']:.4g} s  (dt / t_R = {rep['dt_over_rayleigh']:.3g}, "
      f"allowed <= 0.3)")
    p(f"Hertz collision time at {rep['characteristic_velocity']:.3g} m/s: {rep['hertz_time']:.4g} s  "
      f"(dt / t_H = {rep['dt_over_hertz']:.3g}, allowed <= 0.1); impact overlap "
      f"{rep['impact_overlap_ratio']:.3g} of the radius")
    if rep["mechanics"] and rep["dt_over_hertz"] > ACCURATE_HERTZ_FRACTION:
        p(f"accuracy: impacts at {rep['characteristic_velocity']:.3g} m/s resolve restitution and contact time to "
          f"1 % for dt <= {ACCURATE_HERTZ_FRACTION} t_H = {ACCURATE_HERTZ_FRACTION * rep['hertz_time']:.3g} s "
          f"(at 0.1 t_H: about 3.6 %; docs/benchmarks.md, Hertz binary impact)")
    if "thermal_critical_step" in rep:
        p(f"thermal step: {rep['thermal_step']:.4g} s; thermal critical step rho c R / k: "
          f"{rep['thermal_critical_step']:.4g} s (ratio {rep['thermal_step_ratio']:.3g}); "
          f"euler network limit min C_i / sum H_ij: {rep['network_step_limit']:.4g} s")
    if "integrator" in rep:
        line = f"thermal integrator: {rep['integrator']}"
        if "integrator_reason" in rep:
            line += (f" (auto: {rep['integrator_reason']}); expected error: transient "
                     f"{rep['expected_transient_error']}; steady state {rep['expected_steady_error']}")
        p(line)
    if "radiation_step_limit" in rep:
        p(f"euler radiation limit C / (4 eps sigma A T_max^3): {rep['radiation_step_limit']:.4g} s")
    if "biot_max" in rep:
        p(f"largest Biot number h R / (3 k_p) (length V/A = R/3): {rep['biot_max']:.3g} (lumped temperature "
          f"valid below 0.1)")
    for w in rep.get("warnings", []):
        p(f"warning: {w}")
    p(f"memory: {rep['memory_bytes'] / 2**20:.2f} MiB ({rep['memory_per_particle']:.0f} B per particle)")
    from .memory import available_bytes, fmt, scene_bytes
    est, avail = scene_bytes(sim.scene), available_bytes()
    p(f"memory estimated before allocating: {fmt(est['total'])} (neighbour grid {fmt(est['grid'])}); "
      f"available: {fmt(avail) if avail else 'unknown'}")
    p("runs:")
    for r in rep["runs"]:
        p(f"  + {r}")
    p("skipped:")
    for r in rep["skipped"]:
        p(f"  - {r}")
    for pr in rep["problems"]:
        p(f"note: {pr} (accepted: simulation.force = true)")
    return 0


def cmd_run(args):
    from .interrupt import StopRequested, StopSignals
    from .output import OutputError
    from . import outdir, threads
    if args.threads != "auto":
        threads.resolve(args.threads)   # more than this machine runs: refused before anything is read
    out = args.out or os.path.join("out", os.path.splitext(os.path.basename(args.scene))[0])
    rule = dict(overwrite=args.overwrite, restart=bool(args.restart), keep=[args.scene])
    outdir.check(out, **rule)          # a user's folder is refused before the scene is even read
    with StopSignals():  # a signal during loading or compiling stops at the first chunk boundary
        sim = _load(args.scene)
        sim.set_threads(args.threads)   # ('auto': this process's share of its node's cores)
        if args.restart is not None:
            sim.prepare_restart(args.restart)  # a bad checkpoint or a refused scene edit: exit 2 now
        sim.check()
        if sim.par is not None:
            sim.par.comm.Barrier()         # every rank has checked the folder before rank 0 claims it
        outdir.claim_collective(out, sim.par.comm if sim.par is not None else None, sim.is_root, **rule)
        t0 = time.perf_counter()
        c = sim.warmup()
        try:
            sim.run(end_time=args.end_time, out_dir=out, restart=args.restart, progress=not args.quiet)
        except StopRequested as stop:
            if sim.is_root:
                print(stop_message(args, sim, stop, out), file=sys.stderr, flush=True)
            if sim.par is not None:
                _exit_stopped_rank(sim, stop.exit_code)
            return stop.exit_code
        except OutputError as exc:
            if sim.is_root:
                ck = os.path.join(out, "checkpoint.npz")
                again = (f"; then continue with: {continue_command(args, sim, ck)}" if os.path.isfile(ck)
                         else "")
                print(f"error: {exc}{again}", file=sys.stderr, flush=True)
            return 3
    wall = time.perf_counter() - t0
    steps = sim.step_count
    n = sim.n_particles
    stats = sim.par.stats(sim.world) if sim.par is not None else None
    setup = None
    if sim.par is not None and getattr(sim.scene, "distributed", False):
        rows = sim.scene.setup_rows   # the largest over the ranks
        setup = [int(v) for v in sim.par.flags(rows["read"], rows["held"])]
    if sim.is_root:
        ranks = f" on {sim.par.size} ranks ({sim.par.describe()})" if sim.par is not None else ""
        ranks += f", {sim.threads} thread{'s' if sim.threads > 1 else ''}" + (" per rank" if sim.par is not None else "")
        if stats:
            print(f"parallel: {stats['ghosts']} ghosts ({100 * stats['ghosts'] / max(n, 1):.1f} % of the particles), "
                  f"halo traffic {stats['halo_bytes'] / 1024:.1f} KiB per step in {stats['messages']} messages, "
                  f"{stats['exchanges']} exchanges, {stats['migrated']} migrations, {stats['rebalances']} "
                  f"re-balancings, load imbalance {stats['imbalance']:.3f}; exchanges sent "
                  f"{stats['bytes_migrated'] / 1024:.1f} KiB of migrating particles ({stats['records_migrated']} "
                  f"contact records) and {stats['bytes_ghosts'] / 1024:.1f} KiB of ghosts"
                  + (f"; implicit heat: {stats['cg_solves']} solves, "
                     f"{stats['cg_iterations'] / stats['cg_solves']:.1f} iterations a solve, "
                     f"{stats['cg_bytes'] / stats['cg_iterations'] / 1024:.2f} KiB of ghost values an iteration"
                     if stats["cg_iterations"] else "")
                  + (f"; mesh triangles held per rank {stats['mesh_held'][0]}-{stats['mesh_held'][1]} of "
                     f"{sum(w['surface'].n_triangles for w in sim.scene.walls if w['type'] == 'mesh')}"
                     if sim.world.nmeshes else "")
                  + (f"; set-up per rank: at most {setup[0]} packing-file rows read and {setup[1]} particle "
                     f"rows held before the distribution" if setup else ""))
        print(f"done: t = {sim.time:.6g} s, {steps} steps, {n} particles{ranks}, wall {wall:.2f} s "
              f"(kernels compile/load {c:.2f} s), {max(sim.particle_steps, n) / max(sim.wall_seconds, 1e-9):.3g} "
              f"particle-steps/s; output in {out}")
    return 0


def _exit_stopped_rank(sim, code):
    """End a rank of a stopped MPI run at once. Open MPI's mpirun, once signalled, is killing
    the job (SIGTERM to the ranks, then SIGKILL after odls_base_sigkill_timeout): MPI_Finalize
    then waits for daemons that no longer answer until the SIGKILL. Every file is written and
    fsync'ed and every rank has reached this point (barrier), so nothing is lost by skipping it."""
    sim.par.comm.Barrier()
    sys.stdout.flush()
    sys.stderr.flush()
    os._exit(code)


def continue_command(args, sim, checkpoint):
    """The command line that continues an interrupted ``dem run`` (same scene, folder, end)."""
    import shlex
    cmd = []
    if sim.par is not None:
        cmd += ["mpirun", "-np", str(sim.par.size)]
    cmd += ["dem", "run", args.scene, "--out", args.out or os.path.dirname(checkpoint),
            "--restart", checkpoint]
    if args.end_time is not None:
        cmd += ["--end-time", repr(args.end_time)]
    if args.quiet:
        cmd.append("--quiet")
    return " ".join(shlex.quote(str(c)) for c in cmd)


def stop_message(args, sim, stop, out):
    """The one line printed when SIGINT / SIGTERM stopped a run."""
    from .interrupt import signal_name
    return (f"interrupted by {signal_name(stop.signum)} at t = {stop.time:.9g} s (step {stop.step}); "
            f"checkpoint written to {stop.checkpoint}; continue with: "
            f"{continue_command(args, sim, stop.checkpoint)}")


def cmd_compile(args):
    """Fill Numba's cache with the kernels (one kernel serves every scene): the warm-up jobs of
    dem.compile in parallel worker processes."""
    from . import compile as C
    return C.main_compile(C.DEM_JOBS, args.jobs)


def cmd_gather(args):
    from .final import gather
    path = gather(args.out_dir)
    print(f"wrote {path}")
    return 0


def cmd_render(args):
    from .render import render
    path = render(args.out_dir, args.png, color=args.color)
    print(f"wrote {path}")
    return 0


def main(argv=None):
    try:
        return _main(argv)
    except KeyboardInterrupt:  # Ctrl-C before the run installed its handlers (imports, parsing)
        print("interrupted before the run started: nothing was written", file=sys.stderr)
        return 130


def _main(argv=None):
    from .args import end_time
    from .threads import argument as threads_argument
    ap = argparse.ArgumentParser(prog="dem", description="Thermal DEM solver")
    sub = ap.add_subparsers(dest="cmd", required=True)
    r = sub.add_parser("run", help="run a scene")
    r.add_argument("scene")
    r.add_argument("--out", help="output folder (default out/<scene name>)")
    r.add_argument("--restart", help="checkpoint to continue from (--out may then be the earlier output)")
    r.add_argument("--threads", type=threads_argument, default="auto",
                   help="threads of each process (default auto: the cores this process may use, shared among "
                        "the MPI ranks of its node); results are deterministic for a given count")
    r.add_argument("--overwrite", action="store_true",
                   help="replace an earlier output in --out: removes only what the tool wrote there "
                        "(listed in its .thermodem-manifest.json) and refuses if anything else is there")
    r.add_argument("--end-time", type=end_time, help="override simulation.end_time (s)")
    r.add_argument("--quiet", action="store_true", help="no progress display")
    c = sub.add_parser("check", help="validate a scene and print derived quantities")
    c.add_argument("scene")
    k = sub.add_parser("compile", help="compile and cache the kernels (done by scripts/setup.sh)")
    from .compile import jobs_argument
    k.add_argument("--jobs", "-j", type=jobs_argument, default=None,
                   help="worker processes compiling in parallel (default: the usable cores)")
    d = sub.add_parser("render", help="render the last output of a run to PNG")
    d.add_argument("out_dir")
    d.add_argument("--png", default=None, help="PNG to write (default OUT_DIR/render.png); never replaces a "
                                               "file the tool did not write")
    d.add_argument("--color", default=None, help="field to colour by (default temperature or velocity)")
    g = sub.add_parser("gather", help="write OUT_DIR/final_gathered.npz: an MPI run's final pieces as one file "
                                      "ordered by id (what a serial run's final.npz holds)")
    g.add_argument("out_dir")
    args = ap.parse_args(argv)
    from .errors import SceneError
    from .simulation import SimulationError
    from .parallel.domain import ParallelError
    from .threads import ThreadsError
    from .parallel import launched_rank
    root = launched_rank() == 0
    try:
        return {"run": cmd_run, "check": cmd_check, "render": cmd_render, "compile": cmd_compile,
                "gather": cmd_gather}[args.cmd](args)
    except (SceneError, ParallelError, ThreadsError) as exc:
        if root:  # every rank found the same problem: say it once
            print(f"error: {exc}", file=sys.stderr)
        return 2
    except SimulationError as exc:
        if root:
            print(f"error: {exc}", file=sys.stderr)
        return 3
    except MemoryError:
        from .parallel import launched_size
        if launched_size() > 1:  # one rank out of memory: the abort hook ends the whole job
            raise
        if root:
            print(f"error: {args.scene if hasattr(args, 'scene') else args.cmd}: out of memory (the scene "
                  "did not fit although `dem check` estimated it would, or simulation.force = true); use "
                  "fewer particles or a smaller domain", file=sys.stderr)
        return 3
    except KeyboardInterrupt as exc:
        if not str(exc).startswith("second"):  # Ctrl-C in dem check / render / compile
            if root:
                print("interrupted", file=sys.stderr)
            return 130
        if root:  # a second Ctrl-C / SIGTERM while the first was being served
            print(f"interrupted again ({exc}): stopped at once; every file written is complete (atomic "
                  f"writes) and the last checkpoint is the one to continue from", file=sys.stderr)
        return 143 if "SIGTERM" in str(exc) else 130


if __name__ == "__main__":
    sys.exit(main())
