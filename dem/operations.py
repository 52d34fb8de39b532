"""A run is a list of operations, each with a trigger (layer 4, beside dem.simulation).

    ops = operations.standard(sim, end_step, out_dir, ...)   # what Simulation.run composes
    operations.execute(sim, ops, end_step)

An :class:`Operation` does one thing to a running :class:`dem.Simulation` (check the
energy, sort the particles, write a history row, a VTK frame, a checkpoint, show the
progress) when its :class:`Trigger` says so. A trigger answers two questions:

* ``next_due(step)``: the first step after ``step`` at which it must run (None: no step of
  the loop). The loop advances the integrator in compiled chunks (dem.chunks) up to the
  earliest due step of all operations and the end step, never across one, so every
  operation sees exactly the step its trigger names, whatever the chunk sizes;
* ``fires(step, event)``: whether it runs now. ``event`` is PAUSE (the loop paused after a
  chunk; a chunk ends either at a due step or, when the wall-time budget of a chunk is
  spent, in between), END (the run reached its end step), STOP (a SIGINT/SIGTERM ends the
  run at this step: dem.interrupt) or FAIL (a SimulationError ends it).

Triggers: ``Every(n)`` (multiples of n steps; n = 0 never), ``At(step)``, ``EachPause()``,
``AtEnd(unless_every=n)`` / ``OnStop(unless_every=n)`` (at the end / the stop step, unless it
is a multiple of n, where ``Every(n)`` just ran), ``OnFailure()``, and ``a | b`` (either).

The time of step s is s * dt (dem.step.advance computes it from the step number), so the
chunking changes no bit: a run advanced in any chunk lengths ends in the same state.

Order. At every pause the due operations run in the order of the list, then the writes held
by the root under MPI are settled (Simulation.settle_writes: one collective point, every rank
raises the same OutputError). :func:`standard` composes the list in this fixed order:

    0. FlowEvents    at each inlet's and outlet's interval (dem.flow: particles out, then in)
    1. EnergyCheck   at output, checkpoint and sort steps and the end step (dem.energy_guard)
    2. Sorter        every sort_interval steps (Simulation.sort_particles)
    3. extra operations given to Simulation.run (in their order)
    4. HistoryWriter every output_interval; at the end / a stop unless that step wrote
    5. VTKWriter     the same steps, when output.vtk
    6. FinalState    at the end: final.npz
    7. FailedState   on a SimulationError: failed_state.npz (the state that failed)
    8. CheckpointWriter every checkpoint_interval, at the end and on a stop (checkpoint.npz)
    9. ProgressBar   after every chunk

``start`` hooks run in that order before the first chunk (the writers write the initial
state), ``close`` hooks when the loop ends in any way: before the END and STOP operations,
after the FAIL ones.
"""
import os
import sys

import numpy as np

PAUSE, END, STOP, FAIL = "pause", "end", "stop", "fail"


# --------------------------------------------------------------------------- triggers

class Trigger:
    """When an operation runs: ``next_due`` (loop steps) and ``fires`` (this step and event)."""

    def next_due(self, step):
        """The first step after ``step`` at which the loop must pause for it (None: never)."""
        return None

    def fires(self, step, event):
        return False

    def __or__(self, other):
        return AnyOf(self, other)


class Every(Trigger):
    """At the multiples of ``n`` steps (n = 0: never), when the loop pauses there."""

    def __init__(self, n):
        self.n = int(n)
        if self.n < 0:
            raise ValueError(f"Every(n) needs n >= 0, got {n}")

    def next_due(self, step):
        return (step // self.n + 1) * self.n if self.n else None

    def fires(self, step, event):
        return event == PAUSE and self.n > 0 and step % self.n == 0

    def __repr__(self):
        return f"Every({self.n})"


class At(Trigger):
    """At one step of the loop."""

    def __init__(self, step):
        self.step = int(step)

    def next_due(self, step):
        return self.step if step < self.step else None

    def fires(self, step, event):
        return event == PAUSE and step == self.step

    def __repr__(self):
        return f"At({self.step})"


class EachPause(Trigger):
    """After every chunk (due step or not): it never makes the loop pause."""

    def fires(self, step, event):
        return event == PAUSE


class _Event(Trigger):
    event = None

    def __init__(self, unless_every=0):
        self.unless_every = int(unless_every)

    def fires(self, step, event):
        if event != self.event:
            return False
        return not (self.unless_every and step % self.unless_every == 0)

    def __repr__(self):
        extra = f"unless_every={self.unless_every}" if self.unless_every else ""
        return f"{type(self).__name__}({extra})"


class AtEnd(_Event):
    """When the run reached its end step; ``unless_every=n``: not if that step is a multiple
    of n (the periodic trigger wrote it already, in this run or in the one it continues)."""
    event = END


class OnStop(_Event):
    """When a stop request (SIGINT/SIGTERM) ends the run; ``unless_every`` as AtEnd."""
    event = STOP


class OnFailure(_Event):
    """When a SimulationError ends the run."""
    event = FAIL


class AnyOf(Trigger):
    def __init__(self, *triggers):
        self.triggers = triggers

    def next_due(self, step):
        due = [d for d in (t.next_due(step) for t in self.triggers) if d is not None]
        return min(due) if due else None

    def fires(self, step, event):
        return any(t.fires(step, event) for t in self.triggers)

    def __repr__(self):
        return " | ".join(map(repr, self.triggers))


def next_pause(operations, step, end_step):
    """The step the next chunk must stop at: the earliest due step of any operation, or the
    end step (a chunk never crosses it)."""
    nxt = end_step
    for op in operations:
        d = op.trigger.next_due(step)
        if d is not None and d < nxt:
            nxt = d
    return nxt


# --------------------------------------------------------------------------- operations

class Operation:
    """One thing done to the running simulation when ``trigger`` fires (subclass and
    override ``act``; ``start`` / ``close`` are optional). ``run`` is the :class:`Run`."""

    trigger = Trigger()

    def start(self, run):
        pass

    def act(self, run, event):
        pass

    def close(self, run):
        pass


class FlowEvents(Operation):
    """Particles leave by the outlets and enter by the inlets (dem.flow) at the multiples of
    each one's interval, before anything else looks at the step (collective)."""

    def __init__(self, flow):
        self.flow = flow
        self.trigger = AnyOf(*[Every(n) for n in sorted(set(flow.steps()))])

    def act(self, run, event):
        self.flow.apply(run.sim.stepper, run.sim.step_count)


class EnergyCheck(Operation):
    """dem.energy_guard: a closed system must not gain energy (raises SimulationError).
    It is checked where the run loop has always paused for the other operations: output,
    checkpoint and sort steps (with or without files) and the end step."""

    def __init__(self, out_every, ck_every, sort_every, end_step):
        self.trigger = Every(out_every) | Every(ck_every) | Every(sort_every) | At(end_step)

    def start(self, run):
        from .energy_guard import EnergyGuard
        self.guard = run.sim.energy_guard = EnergyGuard(run.sim)

    def act(self, run, event):
        self.guard.check()


class Sorter(Operation):
    """Particles reordered by cell (Simulation.sort_particles) every ``n`` steps."""

    def __init__(self, n):
        self.trigger = Every(n)

    def act(self, run, event):
        run.sim.sort_particles()


class HistoryWriter(Operation):
    """One row of history.csv (collective; the root writes) at the start (a new run), every
    ``n`` steps, and at the end or a stop unless that step is a multiple of n."""

    def __init__(self, out_dir, n, write_initial, keep_until=None):
        self.path = os.path.join(out_dir, "history.csv")
        self.write_initial, self.keep_until = write_initial, keep_until
        self.trigger = Every(n) | AtEnd(unless_every=n) | OnStop(unless_every=n)
        self.hist = None

    def start(self, run):
        from .output import History
        sim = run.sim
        if sim.is_root:  # the root writes; the others take part in the sums
            self.hist = History(self.path, sim.history_columns(), self.keep_until)
        if self.write_initial:
            self.act(run, PAUSE)

    def act(self, run, event):
        row = run.sim.history_row()
        if self.hist is not None:
            run.sim.root_write(lambda: self.hist.add(row))


class WallHeatWriter(Operation):
    """wall_heat.csv (dem.thermal.wall_heat: heat through each wall by path) on the steps of
    the history rows (collective sums; the root writes)."""

    def __init__(self, out_dir, n, write_initial, keep_until=None):
        self.path = os.path.join(out_dir, "wall_heat.csv")
        self.angle_path = os.path.join(out_dir, "wall_heat_angle.csv")
        self.write_initial, self.keep_until = write_initial, keep_until
        self.trigger = Every(n) | AtEnd(unless_every=n) | OnStop(unless_every=n)
        self.file = self.angles = None
        self.by_angle = False

    def start(self, run):
        from .thermal.wall_heat import WallAngleFile, WallHeatFile
        sim = run.sim
        self.by_angle = WallAngleFile.wanted(sim.scene)   # thermal cylinder walls: wall_heat_angle.csv
        if sim.is_root:
            self.file = WallHeatFile(self.path, sim.scene, self.keep_until)
            if self.by_angle:
                self.angles = WallAngleFile(self.angle_path, sim.scene, self.keep_until)
        if self.write_initial:
            self.act(run, PAUSE)

    def act(self, run, event):
        from .thermal.wall_heat import cylinder_flux_by_angle
        sim = run.sim
        totals = sim.wall_heat_totals()
        by_angle = cylinder_flux_by_angle(sim) if self.by_angle else None   # collective
        if self.file is not None:
            sim.root_write(lambda: self.file.add(sim.time, totals))
        if self.angles is not None:
            sim.root_write(lambda: self.angles.add(sim.time, by_angle))


class VTKWriter(Operation):
    """particles.pvd + vtk/ frames (one .vtu; under MPI one piece per rank and a .pvtu), on the
    steps of the history rows."""

    def __init__(self, out_dir, n, write_initial):
        self.out_dir, self.write_initial = out_dir, write_initial
        self.trigger = Every(n) | AtEnd(unless_every=n) | OnStop(unless_every=n)
        self.vtk = None

    def start(self, run):
        self.vtk = run.sim.vtk_series(self.out_dir)   # every rank: each writes its own piece under MPI
        # contacts.pvd: the contact network ([output] contacts), a piece per rank under MPI
        self.contacts = run.sim.vtk_series(self.out_dir, "contacts") if run.sim.scene.output.get("contacts") else None
        self.walls = None
        meshes = [w for w in run.sim.scene.walls if w["type"] == "mesh"]
        if meshes:   # walls.pvd: the mesh walls where they are at each output (the root alone)
            from .output import VTKSeries
            self.walls = VTKSeries(self.out_dir, name="walls")
        if self.write_initial:
            self.act(run, PAUSE)

    def act(self, run, event):
        run.sim.write_vtk(self.vtk)
        if self.contacts is not None:
            run.sim.write_contacts(self.contacts)
        if self.walls is not None:
            sim = run.sim
            sim.root_write(lambda: _write_mesh_walls(self.walls, sim))


def _write_mesh_walls(series, sim):
    """One frame of walls.pvd: every mesh wall's triangles at the run's time, with the wall's
    number in the scene (cell data ``wall``)."""
    from .contact.mesh import placed_vertices
    pts, tri, wall = [], [], []
    nv = 0
    for k, w in enumerate(sim.scene.walls):
        if w["type"] != "mesh":
            continue
        v = placed_vertices(w, sim.time)
        pts.append(v)
        tri.append(w["surface"].faces + nv)
        wall.append(np.full(len(w["surface"].faces), k, np.int64))
        nv += len(v)
    series.write_surface(sim.time, sim.world.step_count, np.concatenate(pts), np.concatenate(tri),
                         {"wall": np.concatenate(wall)})


class FinalState(Operation):
    """final.npz (per-particle results by id; under MPI a piece per rank and a manifest) at the end
    of the run."""

    trigger = AtEnd()

    def __init__(self, out_dir):
        self.path = os.path.join(out_dir, "final.npz")

    def act(self, run, event):
        run.sim.write_final(self.path)   # under MPI a piece per rank and a manifest (dem.final)


class FailedState(Operation):
    """failed_state.npz: the state the SimulationError was raised in (for a post-mortem)."""

    trigger = OnFailure()

    def __init__(self, out_dir):
        self.path = os.path.join(out_dir, "failed_state.npz")

    def act(self, run, event):
        from .output import save_npz
        fa = run.sim.final_arrays()
        if fa is not None:
            save_npz(self.path, **fa)


class CheckpointWriter(Operation):
    """checkpoint.npz every ``n`` steps (n = 0: only) at the end and on a stop."""

    def __init__(self, path, n):
        self.path = path
        self.trigger = Every(n) | AtEnd() | OnStop()

    def act(self, run, event):
        run.sim.write_checkpoint(self.path)


class ProgressBar(Operation):
    """dem.progress after every chunk (root, when enabled); its wall clock times the run."""

    trigger = EachPause()

    def __init__(self, end_step, enabled, stream):
        self.end_step, self.enabled, self.stream = end_step, enabled, stream
        self.bar = None

    def start(self, run):
        from .progress import Progress
        sim = run.sim
        self.bar = Progress(sim.step_count, self.end_step, sim.dt, sim.n_particles, sim.compile_seconds,
                            enabled=self.enabled and sim.is_root, stream=self.stream)

    def act(self, run, event):
        self.bar.n = run.sim.n_particles   # (inlets and outlets change it)
        self.bar.update(run.sim.step_count)

    def close(self, run):
        self.bar.close()
        run.wall_seconds = self.bar.elapsed


# --------------------------------------------------------------------------- the run

class Run:
    """What the operations see: the simulation, the end step, the checkpoint path (for the
    stop message) and the wall time measured by the progress operation."""

    def __init__(self, sim, operations, end_step):
        self.sim, self.operations, self.end_step = sim, list(operations), int(end_step)
        self.wall_seconds = None
        self.checkpoint = next((op.path for op in self.operations if isinstance(op, CheckpointWriter)), None)

    def fire(self, event):
        step = self.sim.step_count
        for op in self.operations:
            if op.trigger.fires(step, event):
                op.act(self, event)

    def close(self):
        for op in self.operations:
            op.close(self)


def intervals(sim):
    """(output, checkpoint, sort) intervals in steps, from the scene (0: never)."""
    s = sim.scene.simulation
    out_every = max(1, int(round(s["output_interval"] / sim.dt)))
    ck = s["checkpoint_interval"]
    ck_every = int(round(ck / sim.dt)) if ck > 0 else 0
    return out_every, ck_every, int(s["sort_interval"])


def standard(sim, end_step, out_dir=None, restarted=False, progress=None, log=None, extra=()):
    """The operations of ``Simulation.run`` in their fixed order (module docstring)."""
    out_every, ck_every, sort_every = intervals(sim)
    ops = [FlowEvents(sim.world.flow)] if sim.world.flow is not None else []
    ops += [EnergyCheck(out_every, ck_every, sort_every, end_step), Sorter(sort_every)]
    ops += list(extra)
    if out_dir is not None:
        initial = sim.step_count == 0 or not restarted
        keep = sim.time if restarted else None
        ops.append(HistoryWriter(out_dir, out_every, initial, keep))
        if sim.thermal is not None and sim.scene.walls:
            ops.append(WallHeatWriter(out_dir, out_every, initial, keep))
        if sim.scene.output["vtk"]:
            ops.append(VTKWriter(out_dir, out_every, initial))
        ops += [FinalState(out_dir), FailedState(out_dir),
                CheckpointWriter(os.path.join(out_dir, "checkpoint.npz"), ck_every)]
    ops.append(ProgressBar(end_step, progress, log or sys.stderr))
    return ops


def open_output(sim, out_dir, restarted, restart_file=None):
    """Claim the output folder (new, empty or an earlier output continued: dem.outdir; every
    rank) and prepare it (root); a write failure is raised on every rank."""
    from .outdir import claim_collective
    from .output import prepare_output_folder
    claim_collective(out_dir, sim.par.comm if sim.par is not None else None, sim.is_root,
                     restart=restarted, reuse=True, keep=[restart_file] if restart_file else ())
    if sim.is_root:
        sim.root_write(lambda: prepare_output_folder(out_dir))
    sim.settle_writes()


def execute(sim, operations, end_step):
    """Run the loop to ``end_step``: chunks of about a second (dem.chunks) up to the next
    due step, the due operations, the settled writes; then the END operations. A stop
    request (polled between chunks; MPI: agreed by every rank) runs the STOP operations and
    raises StopRequested with ``time``, ``step`` and ``checkpoint``; a SimulationError runs
    the FAIL operations and is raised again. Returns the :class:`Run`."""
    from .chunks import ChunkClock, agree
    from .interrupt import StopRequested, StopSignals
    from .errors import SimulationError
    run = Run(sim, operations, end_step)
    first = sim.step_count     # (a restart's step, its checkpoint loaded)
    sim.particle_steps = 0
    for op in run.operations:
        op.start(run)
    sim.settle_writes()
    clock = ChunkClock()
    try:
        with StopSignals():
            while sim.step_count < end_step:
                sig, chunk = agree(sim.par, clock.steps)  # every rank stops at the same step
                if sig:
                    raise StopRequested(sig)
                s = sim.step_count
                nxt = next_pause(run.operations, s, end_step)
                clock.start()
                done = sim.step(min(nxt - s, chunk))
                sim.particle_steps += done * sim.n_particles   # (the particles of this chunk: dem.flow
                clock.done(done)                               # changes them between chunks only)
                run.fire(PAUSE)
                sim.settle_writes()
    except StopRequested as stop:
        run.close()
        run.fire(STOP)   # the series closed with the current state, then the checkpoint
        sim.settle_writes()
        stop.time, stop.step, stop.checkpoint = sim.time, sim.step_count, run.checkpoint
        sim.wall_seconds, sim.steps_run = run.wall_seconds, sim.step_count - first
        raise
    except SimulationError:
        run.fire(FAIL)
        run.close()
        raise
    run.close()
    run.fire(END)
    sim.settle_writes()
    sim.wall_seconds, sim.steps_run = run.wall_seconds, sim.step_count - first
    return run


__all__ = ["Trigger", "Every", "At", "EachPause", "AtEnd", "OnStop", "OnFailure", "AnyOf", "Operation",
           "FlowEvents", "EnergyCheck", "Sorter", "HistoryWriter", "VTKWriter", "FinalState", "FailedState",
           "CheckpointWriter", "ProgressBar", "Run", "standard", "open_output", "execute", "next_pause",
           "intervals", "PAUSE", "END", "STOP", "FAIL"]
