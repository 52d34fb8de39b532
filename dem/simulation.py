"""Simulation: a run composed of parts with one job each, and the operations that run it.

    sim = Simulation.from_file("examples/settle_box.toml")
    sim.run(end_time=0.2, out_dir="out/settle")
    sim.state.position, sim.state.velocity, ...

The parts (docs/architecture.md, "The parts of a Simulation"):

world         dem.world.World: the declared state, tables, walls and parameters built from the
              scene, the thermal model, the clock (step_count, time)
stepper       dem.stepper.Stepper / ParallelStepper: neighbours, forces, the advance (serial or
              MPI behind one interface), the sort, instability messages
writers       dem.writers.Writers: history rows, wall heat totals, VTK and final arrays, the
              root's writes
checkpointer  dem.checkpointer.Checkpointer: write, verify, load, restart with an edited scene
(reports)     dem.reports: `dem check`, the models that run, time scales, memory estimate

This class only wires them and runs the operations (dem.operations). The methods below are
the public API (README, coupling/), each one line into the part that does it.
"""
import gc
import time

from . import reports
from . import step as K
from .blocks import cross_count_slots
from . import scene as scene_mod
from .checkpointer import Checkpointer
from .errors import SimulationError  # noqa: F401  (dem.simulation.SimulationError, as before)
from .fluid import set_fluid as _set_fluid
from .stepper import ParallelStepper, Stepper
from .world import World
from .writers import Writers


class Simulation:
    def __init__(self, scene):
        self.world = world = World(scene)
        self.scene = scene
        self.state = world.state
        self.thermal = world.thermal
        self.dt = world.dt
        self.end_time = world.end_time
        self.par = None
        from .parallel import world as mpi_world
        comm = mpi_world()
        if comm is not None:
            from .parallel.domain import ParallelDomain
            self.par = ParallelDomain(comm, world)
            self.par.select_initial(world)
            self.stepper = ParallelStepper(world, self.par)
        else:
            self.stepper = Stepper(world)
        self.writers = Writers(world, self.stepper)
        self.checkpointer = Checkpointer(self)
        self.energy_guard = None   # set by the run's EnergyCheck operation
        self.compile_seconds = None
        self.wall_seconds = None
        self.steps_run = 0         # steps of the last run() (a restarted run: from its checkpoint on)
        self.particle_steps = 0    # the particles of each of those steps, summed (inlets and outlets change them)
        self.threads = 1
        t0 = time.perf_counter()
        self.stepper.init_neighbors()   # the first call of the step kernel: compiled or loaded here
        self._first_call = time.perf_counter() - t0
        self.stepper.start_skin()       # neighbor_skin = "auto": from the first build and the speeds
        if self.par is not None and getattr(scene, "distributed", False):
            from .parallel.setup import check_overlaps
            check_overlaps(world, self.par)   # needs the neighbours' particles: after the first exchange
        if self.thermal is not None:
            self.thermal.update_porosity(world.time)
            self.stepper.forward_porosity()
        if self.thermal is not None and not scene.simulation["mechanics"]:
            # frozen packing: contacts, overlaps and conductances are computed once, here
            self.stepper.compute_forces()
            self.stepper.forces_ready = True
            # integrator = "auto": chosen from the step and the network's rates (dem.thermal.step_error)
            self.thermal.choose_integrator(world.dt, self.par)

    @classmethod
    def from_file(cls, path, end_time=None):
        """Scene file -> Simulation; ``end_time`` is used when the file has no
        simulation.end_time (:func:`dem.scene.load`)."""
        return cls(scene_mod.load(path, end_time=end_time))

    @classmethod
    def from_dict(cls, data, base_dir=".", name="<dict>"):
        return cls(scene_mod.parse(data, name, base_dir=base_dir))

    # ------------------------------------------------------------------ the clock and sizes
    @property
    def time(self):
        return self.world.time

    @property
    def step_count(self):
        return self.world.step_count

    @property
    def n_particles(self):
        """Particles in the whole run now (all ranks; [[inlets]] and [[outlets]] change it: dem.flow)."""
        return self.world.n_total

    @property
    def is_root(self):
        """True on the rank that writes files (always in a serial run)."""
        return self.writers.is_root

    @property
    def last_contacts(self):
        """Contacts of the last force evaluation (this rank's in an MPI run)."""
        return self.stepper.last_contacts

    # ------------------------------------------------------------------ checks and reports
    def check(self):
        """`dem check`'s report; raises SceneError for a step above the stability limits."""
        return reports.check(self.world, self.stepper)

    def models_report(self):
        return reports.models_report(self.world, self.par)

    def time_scales(self):
        return reports.time_scales(self.world, self.par)

    # ------------------------------------------------------------------ stepping
    def set_threads(self, k, reserve=0):
        """Run this process's kernels on ``k`` threads from now on (blocks of rows at once,
        dem.step.interact_blocks; deterministic for a given k). Applies to calls made from the
        calling thread (Numba's setting is per thread)."""
        from . import threads
        k = threads.resolve(k, self.par.comm if self.par is not None else None, reserve=reserve)
        threads.apply(k)
        self.threads = k
        self.state.ip[K.IP.threads] = k
        self.state.xcnt = cross_count_slots(k)

    def warmup(self):
        """Compile (or load from Numba's cache) the kernels; returns seconds spent, the first
        call of the step kernel when the Simulation was made (the first neighbour build)
        included: a scene whose compiled forms are not in the cache compiles them there."""
        t0 = time.perf_counter()
        self.stepper.advance(0)
        self.compile_seconds = self._first_call + time.perf_counter() - t0
        self._first_call = 0.0   # counted once
        return self.compile_seconds

    def step(self, nsteps=1):
        """Advance ``nsteps`` steps (0: only the forces of the current time, if not yet known)."""
        return self.stepper.advance(nsteps)

    def sort_particles(self):
        self.stepper.sort()

    def set_fluid(self, force=None, velocity=None, temperature=None, porosity=None, drag=None, torque=None,
                  torque_drag=None, added_mass=None):
        """Fluid data at each owned particle (rows of ``state``) for the next steps of a
        coupled run: force (N, added every step), gas velocity (m/s) and temperature (K) for
        convection, void fraction (replaces the locally measured porosity in the heat models).
        ``drag`` (kg/s, optional): the drag coefficient beta_p of a drag beta_p (u_f - v) that
        the kicks take implicitly in the particle velocity v (dem.step.half_kick_implicit);
        ``force`` then holds the rest, beta_p u_f + pressure gradient / buoyancy. Without it
        ``force`` is the whole fluid force, held over the interval.

        ``torque`` (N m, optional): fluid torque added every step; with ``torque_drag`` k_rot
        (N m s) the torque k_rot (Omega_f - omega) is taken implicitly in the angular velocity
        (dem.step.half_kick_angular_implicit) and ``torque`` holds its explicit part
        k_rot Omega_f. ``added_mass`` (kg, optional): C_vm rho_f V_p of a virtual-mass force, taken
        implicitly as an effective mass m + added_mass in the translational kicks (``force`` then
        holds C_vm rho_f V_p Du_f/Dt). Without them (None) no fluid torque / virtual mass."""
        _set_fluid(self.world, self.stepper, force=force, velocity=velocity, temperature=temperature,
                   porosity=porosity, drag=drag, torque=torque, torque_drag=torque_drag, added_mass=added_mass)

    # ------------------------------------------------------------------ output
    def history_columns(self):
        return self.writers.history_columns()

    def history_row(self):
        """One row of history.csv (collective in a parallel run)."""
        return self.writers.history_row()

    def wall_heat_totals(self):
        """Heat through each wall since the start (J), [n_walls, 3] (collective); None without
        heat or walls."""
        return self.writers.wall_heat_totals()

    def final_arrays(self):
        """Per-particle results ordered by id (collective; None on ranks other than the root)."""
        return self.writers.final_arrays()

    def write_final(self, path):
        """final.npz (collective): one file in a serial run, a piece per rank and a manifest under
        MPI (dem.final)."""
        self.writers.write_final(path)

    def vtk_series(self, out_dir, name="particles"):
        """This rank's VTK series ``name`` of ``out_dir`` (pieces per rank under MPI)."""
        return self.writers.vtk_series(out_dir, name)

    def write_contacts(self, series):
        """One frame of the contact network ([output] contacts; collective)."""
        self.writers.write_contacts(series)

    def write_vtk(self, vtk, **extra):
        """One VTK output of every rank's particles (collective; ``vtk``: :meth:`vtk_series`)."""
        self.writers.write_vtk(vtk, **extra)

    def root_write(self, write):
        self.writers.root_write(write)

    def settle_writes(self):
        self.writers.settle_writes()

    # ------------------------------------------------------------------ checkpoints
    def write_checkpoint(self, path):
        """Write a checkpoint (collective; dem.checkpoint: format version, record, checksum)."""
        self.checkpointer.write(path)

    def prepare_restart(self, path):
        """Read, verify and plan a restart before anything is written (raises SceneError)."""
        return self.checkpointer.prepare(path)

    def load_checkpoint(self, path):
        """Continue from a checkpoint (an edited scene: the applied changes are printed)."""
        self.checkpointer.load(path)

    @property
    def restart_changes(self):
        return self.checkpointer.applied

    # ------------------------------------------------------------------ run
    def run(self, end_time=None, out_dir=None, progress=None, restart=None, log=None, operations=()):
        """Run to ``end_time`` (default: the scene's). Writes output when out_dir is given.

        The run is a list of operations with triggers (dem.operations.standard: energy guard,
        sorter, ``operations`` (extra dem.operations.Operation objects, run in their order
        after the sorter), history and VTK writers, final state, checkpoint, progress),
        executed by dem.operations.execute: compiled chunks of about a second never crossing
        a due step; between chunks a SIGINT / SIGTERM (dem.interrupt) stops the run: the
        current output and a checkpoint are written, then StopRequested is raised (its
        ``time`` and ``checkpoint`` say where). A checkpoint is written at the end of every
        run with out_dir, whatever checkpoint_interval. A file that cannot be written raises
        OutputError (every rank)."""
        from . import operations as ops
        self.writers.begin()
        try:
            if restart is not None:
                self.load_checkpoint(restart)
            end_time = self.end_time if end_time is None else float(end_time)
            end_step = int(round(end_time / self.dt))
            if self.compile_seconds is None:
                self.warmup()
            if out_dir is not None:
                ops.open_output(self, out_dir, restart is not None, restart)
            plan = ops.standard(self, end_step, out_dir, restarted=restart is not None, progress=progress,
                                log=log, extra=operations)
            # the set-up's objects (Numba's compiled kernels and types, the scene) out of the garbage
            # collector's reach for the run: its collections then walk only what the run allocates
            # (walking them all took 3-4 % of the hopper's run, docs/benchmarks.md)
            gc.freeze()
            ops.execute(self, plan, end_step)
            return self
        finally:
            gc.unfreeze()
            self.writers.hold = False
