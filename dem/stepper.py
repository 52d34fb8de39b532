"""The stepper: advances the world with the compiled step (dem.step.advance), serial or MPI
behind one interface.

    stepper = Stepper(world)                 # one process
    stepper = ParallelStepper(world, par)    # mpirun -np N: par is a dem.parallel.ParallelDomain
    stepper.init_neighbors(); stepper.advance(nsteps); stepper.compute_forces()

Owns the neighbour set-up and rebuilds, the force evaluation without a step, the advance
(serial: whole chunks in one compiled call; MPI: the phases one step at a time with the ghost
messages between them), the spatial sort, the instability messages, and the contact counts
of the last step. The coupled inputs (dem.fluid) are one more set of declared arrays that the
step reads like any other.
"""
import os
import sys
import threading

import numpy as np

from . import schema as S
from . import step as K
from .contact.tangential import TANGENTIAL_PROJECTED
from .errors import SimulationError
from .neighbors import Box, adaptive_skin, build_half_list, sort_permutation


COMPILE_NOTICE_AFTER = 4.0   # seconds, unless THERMODEM_COMPILE_NOTICE_AFTER says otherwise


def compile_notice_delay():
    """Seconds a call of the step kernel for a new combination of the scene's switches may take
    before the run says that it is compiling (THERMODEM_COMPILE_NOTICE_AFTER, default 4 s: a
    kernel found in the cache loads in 1-2 s; a form that the set-up did not compile takes 10-20
    s the first time). A negative value turns the notice off; a value that is not a number is
    said on stderr and the default taken."""
    text = os.environ.get("THERMODEM_COMPILE_NOTICE_AFTER")
    if text is None:
        return COMPILE_NOTICE_AFTER
    try:
        return float(text)
    except ValueError:
        print(f"note: THERMODEM_COMPILE_NOTICE_AFTER={text!r} is not a number of seconds; the compile notice "
              f"waits {COMPILE_NOTICE_AFTER:g} s (a negative number turns it off)", file=sys.stderr, flush=True)
        return COMPILE_NOTICE_AFTER


COMPILE_NOTICE = ("note: compiling the step for this scene's options (heat {heat}, {form} form, tangential "
                  "{tangential}), once: later runs load it from Numba's cache in a second or two (`dem compile` "
                  "fills the cache for the default options)")


def _layout(bundles):
    """What Numba's type of each array of the kernels' bundles depends on: dtype, axes, C or F
    contiguity, alignment, writability (numba.typeof of an array). Two calls with the same
    layout take the same compiled form."""
    return tuple((a.dtype.num, a.ndim, a.flags.c_contiguous, a.flags.f_contiguous, a.flags.aligned, a.flags.writeable)
                 for bundle in bundles for a in bundle)


class _CompileNotice:
    """Prints COMPILE_NOTICE on stderr when the call it wraps is still running after
    compile_notice_delay() seconds (a timer thread; cancelled when the call returns)."""

    def __init__(self, text):
        delay = compile_notice_delay()
        self.timer = None
        if delay >= 0.0:
            self.timer = threading.Timer(delay, lambda: print(text, file=sys.stderr, flush=True))
            self.timer.daemon = True

    def __enter__(self):
        if self.timer is not None:
            self.timer.start()
        return self

    def __exit__(self, *exc):
        if self.timer is not None:
            self.timer.cancel()
        return False


class Stepper:
    """One process: the whole domain, chunks of steps in one compiled call."""

    def __init__(self, world):
        self.world = world
        self.state = world.state
        self.par = None
        self.forces_ready = False
        self.pair_count = 0      # contacts x 2 of the last force evaluation (a half list counts each twice)
        self.last_contacts = 0
        self._entry = None       # (bundles, heat, form and tangential switches, compiled entry point) of the last call

    # ------------------------------------------------------------------ compiled calls
    @property
    def hon(self):
        """The kernels' heat switch as a type: True with a [thermal] section, None without, so
        that Numba compiles a mechanics-only specialisation with the heat code removed
        (docs/benchmarks.md, "Cost of each mechanism": a run-time flag alone cost ~5 %)."""
        return True if self.world.thermal is not None else None

    @property
    def xon(self):
        """The kernels' optional-physics switch as a type: True when the scene uses rolling
        resistance, periodic images or (with heat) indirect conduction, radiation, frictional
        heating or contact age (dem.step.full_form), None otherwise, so that Numba compiles a
        lean interact phase without that code (docs/notebook.md, "The lean form of the contact
        loops")."""
        st = self.state
        return True if K.full_form(st.ip, st.thi, st.periodic) else None

    @property
    def ton(self):
        """The kernels' tangential-spring switch as a type: None for the rescaled model (the
        default), True for the projected one (dem.contact.tangential), so that Numba compiles
        each model's code alone: as a run-time switch it made the pair loop 5-15 % slower
        whichever model ran (docs/notebook.md). The set-up (dem.compile) compiles the
        rescaled forms; a scene with the projected model compiles its own once."""
        return True if self.state.ip[K.IP.tangential] == TANGENTIAL_PROJECTED else None

    def phases(self, phases, nsteps=1, s0=None):
        """dem.step.advance over ``nsteps`` steps from step number s0 (by default the step in
        progress: a force evaluation alone is at the current time), the given phases only."""
        st = self.state
        b = st.bundles()
        s0 = self.world.step_count - 1 if s0 is None else s0
        hon = self.hon
        xon = self.xon
        ton = self.ton
        st.ip[K.IP.nown] = st.n_owned   # the kernels' owned rows (dem.step.advance reads them there)
        ent = self._entry
        if ent is not None and ent[1] is hon and ent[2] is xon and ent[3] is ton and \
                (ent[0] is b or ent[5] == _layout(b)):
            # the compiled form found for these bundles, or for arrays of the same dtypes, axes and
            # layouts (an outlet's event replaces them): called without the dispatcher's type
            # resolution of the ~80 arrays (25 us -> 12 us a call; an MPI step makes 2-3 calls;
            # after each event 0.5 ms)
            if ent[0] is not b:
                self._entry = (b,) + ent[1:]
            return ent[4](nsteps, s0, st.n, *b, hon, xon, ton, phases)
        args = (nsteps, s0, st.n, *b, hon, xon, ton, phases)
        types = tuple(K.advance.typeof_pyval(a) for a in args)
        if types in K.advance.overloads or (self.par is not None and self.par.rank != 0):
            res = K.advance(*args)
        else:  # a form this process has not loaded: from the cache, or compiled now (said if it takes long)
            text = COMPILE_NOTICE.format(heat="on" if hon else "off", form="full" if xon else "lean",
                                         tangential="projected" if ton else "rescaled")
            with _CompileNotice(text):
                res = K.advance(*args)
        self._entry = (b, hon, xon, ton, K.advance.get_overload(types), _layout(b))
        return res

    def set_pairs(self, C):
        """Adopt the pair bundle a compiled call returned (a rebuild may reallocate it)."""
        st = self.state
        for name, a in zip(C._fields, C):
            setattr(st, name, a)

    def compute_forces(self):
        """The interact phase at the current time (no step): forces, torques and (with heat)
        the conductances; the heat totals are left as they were. Returns the largest overlap."""
        st = self.state
        saved = st.heat_totals()  # the initial force evaluation exchanges no heat
        _, _, i, j, maxov, nc, _, _ = self.phases(K.PH_FORCES)
        st.restore_heat_totals(saved)
        self._count(nc)
        return maxov

    def _count(self, nc):
        self.pair_count = nc
        self.last_contacts = nc // 2

    def recompute_forces_keeping_history(self):
        """Forces at the current time with edited physics (masses, tables, walls, gravity); the
        contact springs, ages and temperatures stay as they are so that the next step increments
        them once, as an uninterrupted run does (collective in a parallel run: the ghosts were
        exchanged by the caller)."""
        st = self.state
        keep = [(f.name, getattr(st, f.name).copy()) for f in S.FIELDS
                if f.record or f.name in ("whist", "wrhist", "temperature", "heat_rate")]
        self.compute_forces()
        for name, a in keep:
            getattr(st, name)[...] = a
        self.forces_ready = True

    def _ready(self):
        if not self.forces_ready:
            self.compute_forces()
            self.forces_ready = True

    # ------------------------------------------------------------------ neighbours
    def rebuild(self, step, glo, ghi, gwrap, initial=False):
        """The rebuild phase (dem.step.rebuild) from Python at the time of step number
        ``step``, with the history starting empty (restored by the caller): the half list over
        the cell grid [glo, ghi] (wrapped on ``gwrap``), then dem.step.after_build (advance's
        PH_AFTER_BUILD). The rows are as wide as the longest (dem.neighbors.balance_rows); the
        last list's width (6 before the first) sizes the build's buffer."""
        st = self.state
        slots = 6 if initial or st.nb.shape[0] == 0 else st.nb.shape[1]
        empty = S.Pairs(*[f.empty() for f in S.of("pair", kernel_only=True)])
        nb, nnb, hist, rhist, age, _ = build_half_list(
            st.position, st.radius, st.n, st.n_owned, Box(st.lo, st.hi, st.periodic), Box(glo, ghi, gwrap),
            self.world.reach, st.fp[K.FP.skin], slots, empty, st.ip[K.IP.threads])
        self.set_pairs(S.Pairs(nb, nnb, hist, rhist, age, st.Hd, st.Hi, st.rnear))
        self.set_pairs(self.phases(K.PH_AFTER_BUILD, s0=step - 1)[-1])

    def init_neighbors(self):
        """The first neighbour build of the run (and of a restart with its own records)."""
        st = self.state
        self.rebuild(self.world.step_count, st.lo, st.hi, st.periodic, initial=True)

    def start_skin(self):
        """neighbor_skin = "auto", at the start of a run (not a restart, which continues with its
        checkpoint's skin): the skin from the gap density of the first build and the fastest
        particle's displacement per step (its speed, plus the walls', times dt). The first
        list, built with the largest skin, holds every pair the chosen one would, so it serves
        until the first rebuild."""
        st = self.state
        if not st.ip[K.IP.autoskin]:
            return
        fp = st.fp
        v = st.velocity[:st.n_owned]
        vmax = self._max(float(np.sqrt(np.max(np.einsum("ij,ij->i", v, v), initial=0.0))))
        fp[K.FP.skin] = adaptive_skin.py_func((vmax + fp[K.FP.vwall]) * fp[K.FP.dt], fp[K.FP.gapd],
                                              fp[K.FP.skinmax])

    def _max(self, x):
        return x

    def restore_neighbors(self, rec):
        """Neighbours built here and the contact history restored from its id-keyed records
        (a checkpoint written on any number of ranks)."""
        from .parallel import records
        self.init_neighbors()
        records.restore(rec, self.state, int(self.state.id.max(initial=0)) + 1)

    # ------------------------------------------------------------------ particles in and out
    def change_particles(self, keep, new):
        """Particles leave and enter (dem.flow, at an event between two chunks): the owned rows
        where ``keep`` is False go, the rows of ``new`` (every enabled per-particle array of
        dem.schema) come after the rest; then the neighbour lists are built again at the
        current time with the contact history kept by id (dem.parallel.records), as after a
        migration. Collective under MPI. One process with particles leaving and none entering
        keeps its lists instead (:meth:`remove_rows`)."""
        from .parallel import records
        st = self.state
        if self.par is None and new["id"].size == 0:
            self.remove_rows(keep)
            return
        rec = records.extract(st)
        n = st.n_owned
        gone = st.id[:n][~keep]
        if gone.size and rec["a"] is not None:   # the history of the pairs with a particle gone goes too
            rec = records.subset(rec, ~(np.isin(rec["a"], gone) | np.isin(rec["b"], gone)))
        for f in S.of("particle"):
            if S.enabled(f, st.features):
                a = getattr(st, f.name)
                setattr(st, f.name, np.ascontiguousarray(np.concatenate([a[:n][keep], new[f.name]])))
        st.n_owned = st.id.shape[0]
        st.n_ghost = 0
        st.ip[K.IP.nown] = st.n_owned
        self.restore_neighbors(rec)   # (on several ranks: the exchange sends each its ghosts again)
        th = self.world.thermal
        if th is not None and th.voronoi:
            th.update_porosity(self.world.time)
            self.forward_porosity()

    def remove_rows(self, keep):
        """Particles leave (one process, none entering: an outlet's event): the rows where
        ``keep`` is False go from every enabled per-particle array, and from the neighbour lists
        the slots that held them, the others keeping their order, springs and conductances (every
        slot-aligned pair array of dem.schema). The lists still hold every pair within reach
        + skin of the particles that stay, so no build is needed: at a few microseconds a
        thousand rows, where a build of the hopper's 2500 beads took 2 ms at every outlet check
        (docs/benchmarks.md, "Hopper discharge")."""
        st = self.state
        n = st.n_owned
        kept = np.nonzero(keep)[0]
        inv = np.full(n, -1, np.int64)
        inv[kept] = np.arange(kept.size)
        nb, nnb = st.nb[kept], st.nnb[kept]
        used = np.arange(nb.shape[1])[None, :] < nnb[:, None]
        j = np.where(used, inv[np.where(used, nb, 0)], -1)
        stay = j >= 0
        order = np.argsort(~stay, axis=1, kind="stable")   # the slots that stay first, in their order
        live = np.take_along_axis(stay, order, axis=1)
        for f in S.of("pair"):
            a = getattr(st, f.name)
            if f.name in ("nb", "nnb") or a.shape[0] != n:
                continue
            a = a[kept]
            idx = order.reshape(order.shape + (1,) * (a.ndim - 2))
            a = np.take_along_axis(a, idx, axis=1)
            a[~live] = 0
            setattr(st, f.name, np.ascontiguousarray(a))
        for f in S.of("particle"):
            if S.enabled(f, st.features):
                setattr(st, f.name, np.ascontiguousarray(getattr(st, f.name)[kept]))
        st.nb = np.ascontiguousarray(np.where(live, np.take_along_axis(j, order, axis=1), 0).astype(np.int32))
        st.nnb = np.ascontiguousarray(stay.sum(axis=1).astype(np.int32))
        st.n_owned = kept.size
        st.n_ghost = 0
        st.ip[K.IP.nown] = st.n_owned
        th = self.world.thermal
        if th is not None and th.voronoi:
            th.update_porosity(self.world.time)

    def forward_porosity(self):
        """Send the owned particles' porosity to the ghosts (nothing to do in one process)."""

    def sort(self):
        """Reorder particles by cell for cache locality; every sorted array of dem.schema
        follows (neighbour rows renumbered), so the physics is unchanged."""
        st = self.state
        w = self.world
        cell = 2 * float(st.radius.max()) + w.reach + st.fp[K.FP.skinmax]   # (not the adaptive skin: the same
        # cells whatever the motion chose)
        st.permute(sort_permutation(st.position, st.lo, st.hi, cell))
        if w.thermal is not None and w.thermal.voronoi and w.scene.simulation["mechanics"]:
            w.thermal.update_porosity(w.time)

    # ------------------------------------------------------------------ stepping
    def advance(self, nsteps):
        """``nsteps`` steps in one compiled call; raises SimulationError on an instability."""
        w = self.world
        self._ready()
        phases = K.PH_STEP if w.mechanics else K.PH_HEAT  # frozen packing: heat on fixed conductances
        done, status, who, other, value, nc, nreb, C = self.phases(phases, nsteps, w.step_count)
        self.set_pairs(C)
        w.set_step(w.step_count + done)
        if w.mechanics:  # frozen packings keep the contact count of their set-up
            self._count(nc)
        if status != K.OK:
            raise SimulationError(self.instability_message(status, who, other, value))
        return done

    def instability_message(self, status, i, j, value):
        """What went wrong with particle row ``i`` (and ``j``: a particle row, or -1 - wall),
        when, and what to change."""
        st = self.state
        w = self.world
        dt = w.dt
        pid = int(st.id[i])
        where = f"at t = {w.time:.9g} s (step {w.step_count})"
        pos = np.array2string(st.position[i], precision=6)
        if status == K.OVERLAP:
            other = (f"wall {w.scene.walls[int(w.wall_of_row[-1 - j])]['name']}" if j < 0
                     else f"particle id {int(st.id[j])}")
            return (f"particle id {pid} at {pos} and {other} overlap by {value:.3g} of the radius {where}, "
                    f"beyond simulation.max_overlap_ratio = {st.fp[K.FP.maxov]:g}. Lower time_step "
                    f"(now {dt:g} s), raise youngs_modulus, or lower the impact speeds")
        if status == K.NONFINITE:
            return (f"particle id {pid} got a non-finite velocity {where}: the run is unstable. "
                    f"Lower time_step (now {dt:g} s; see `dem check`), or check forces and properties")
        if status == K.BAD_TEMPERATURE:
            integ = w.thermal.cfg["integrator"] if w.thermal is not None else "euler"
            advice = ("use thermal.integrator = \"exponential\" or a step below the network and "
                      "radiation limits printed by `dem check`" if integ == "euler" else
                      "lower the thermal step: heat sources, fixed wall fluxes or friction heat are "
                      "explicit and outrun the particle's heat capacity")
            return (f"particle id {pid} reached temperature {value:.6g} K {where}: the heat step "
                    f"({integ}, dt = {dt:g} s) is unstable; {advice}")
        return (f"particle id {pid} left the domain {where} at {pos} (domain {st.lo.tolist()} to "
                f"{st.hi.tolist()}). Add walls, enlarge [domain], or make the axis periodic")


class ParallelStepper(Stepper):
    """One rank of an MPI run: the rank's box and its ghosts (dem.parallel.domain), the phases
    of dem.step.advance one step at a time with the ghost messages between them."""

    def __init__(self, world, par):
        super().__init__(world)
        self.par = par
        self._pending = None  # (code, message) of an instability found on this rank

    def init_neighbors(self):
        self._exchange_rebuild(self.world.step_count, initial=True)

    def restore_neighbors(self, rec):
        self._exchange_rebuild(self.world.step_count, rec=rec, weights_from_list=False)

    def forward_porosity(self):
        self.par.forward(self.world, motion=False, porosity=True)

    def _max(self, x):
        return self.par.allmax(x)

    def sort(self):
        self.par.sort_pending = True  # done at the next exchange with the other ranks

    def _exchange_rebuild(self, step, initial=False, rec=None, weights_from_list=True, due=False):
        """Exchange particles and ghosts with the other ranks, then the rebuild phase
        (dem.step.rebuild, the same as a serial run's) and the contact history brought back
        from its id-keyed records (dem.parallel.records). ``due``: the rebuild the displacement
        test asked for, where an adaptive skin is chosen again (before the exchange: it sets the
        ghost halo)."""
        from .parallel import records
        par = self.par
        st = self.state
        w = self.world
        th = w.thermal
        weights = None
        auto = st.ip[K.IP.autoskin] != 0
        if due and auto:   # every rank holds the same skin, build time and (summed) gap density
            fp = st.fp
            fp[K.FP.skin] = adaptive_skin.py_func(K.skin_rate.py_func(fp, step * w.dt), fp[K.FP.gapd],
                                                  fp[K.FP.skinmax])
        if not initial:
            nown = st.n_owned
            i, k = K.outside(st.position, st.lo, st.hi, st.periodic, nown, st.ip[K.IP.openfaces])
            if i >= 0 and self._pending is None:
                self._pending = (K.LEFT_DOMAIN, self.instability_message(K.LEFT_DOMAIN, int(i), -1,
                                                                         float(st.position[i, k])))
            if rec is None:
                rec = records.extract(st)
            if weights_from_list:
                weights = 1.0 + w.scene.parallel["pair_weight"] * st.nnb[:nown]
        resort_vor = par.sort_pending and th is not None and th.voronoi
        rec = par.exchange(w, rec, weights)
        glo, ghi, gwrap = par.grid_box(w)
        self.rebuild(step, glo, ghi, gwrap, initial=initial)
        if auto:   # the gap density over every rank (each counted its own rows' pairs)
            far, nown = par.sums(st.fp[K.FP.nfar], float(st.n_owned))
            st.fp[K.FP.gapd] = far / (max(nown, 1.0) * st.fp[K.FP.skin])
        records.restore(rec, st, par.key_base)
        st.ip[K.IP.nown] = st.n_owned
        if th is not None and not initial:
            from .thermal.heat import TI
            if th.thi[TI.localpor] == 1:
                self.forward_porosity()
            elif resort_vor:
                th.update_porosity(w.time)
                self.forward_porosity()

    def _note(self, status, who, other, value):
        if status != K.OK and self._pending is None:
            self._pending = (status, self.instability_message(status, who, other, value))

    def _agree(self, need):
        """One Allreduce: the rebuild decision and any rank's instability (raised on every rank)."""
        code, need = self.par.flags(self._pending[0] if self._pending else 0.0, need)
        if code:
            msgs = self.par.comm.allgather(self._pending[1] if self._pending else None)
            raise SimulationError(next(m for m in msgs if m))
        return need

    def advance(self, nsteps):
        """The phases of dem.step.advance (drift, rebuild, interact, kick + guards, heat),
        one step at a time with the ghost messages between them (one Allreduce per step
        carries the rebuild decision and the previous step's stability status)."""
        from .thermal.heat import cross_rates, TI
        from .thermal import implicit_mpi
        par = self.par
        st = self.state
        w = self.world
        heat = w.thermal is not None
        integ = w.thermal.thi[TI.integ] if heat else 0
        expo_cross = integ == 1
        implicit = integ in (2, 3)   # backward Euler, TR-BDF2: conjugate gradients over the ranks
        self._ready()
        mech = w.mechanics
        done = 0
        for _ in range(nsteps):
            need = 0.0
            if mech:
                need = 1.0 if self.phases(K.PH_DRIFT, s0=w.step_count)[1] == K.REBUILD_DUE else 0.0
            need = self._agree(need)
            fused = False
            if mech:
                if need:
                    self._exchange_rebuild(w.step_count + 1, due=True)
                else:
                    par.forward(w, motion=True, temperature=heat)
                # Euler needs no message before its heat phase: one call for interact, kick and heat
                fused = heat and integ == 0
                ph = K.PH_FORCES | K.PH_KICK | (K.PH_HEAT if fused else 0)
                _, status, who, other, value, nc, _, _ = self.phases(ph, s0=w.step_count)
                self.pair_count = nc
                self._note(status, who, other, value)
            elif heat:
                par.forward(w, motion=False, temperature=True)
            if heat and implicit:
                bad = implicit_mpi.heat_step(par, st, (w.step_count + 1) * st.fp[K.FP.dt])
                if bad >= 0:
                    self._note(K.BAD_TEMPERATURE, bad, -1, float(st.temperature[bad]))
            elif heat and not fused:
                if expo_cross:
                    cross_rates(st.n_owned, st.inv_heat_capacity, st.nb, st.nnb, st.Hd, st.Hi, st.work)
                    par.forward(w, motion=False, rate=True)
                _, status, who, _, value, _, _, _ = self.phases(K.PH_HEAT, s0=w.step_count)
                self._note(status, who, -1, value)
            w.set_step(w.step_count + 1)
            done += 1
        self._agree(0.0)
        return done
