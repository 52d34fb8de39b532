"""Simulation: owns the state, builds the step from the scene, runs it, writes output.

    sim = Simulation.from_file("examples/settle_box.toml")
    sim.run(end_time=0.2, out_dir="out/settle")
    sim.state.position, sim.state.velocity, ...
"""
import math
import os
import time

import numpy as np

from . import scene as scene_mod
from .contact.damping import damping_factor, mixed_tables, rayleigh_time, hertz_collision_time
from .contact.registry import CONTACT_MODELS, ROLLING_MODELS, DAMPING_MODELS
from .contact import walls as W
from .neighbors import Box, build_half_list, grid_bytes, sort_permutation
from .output import OutputError
from .state import State
from . import step as K
from .thermal.kernel import MECHANISMS as THERMAL_MECHANISMS
from . import schema as S
from .schema import BY_NAME as _SCHEMA

_SCHEMA_NAMES = frozenset(_SCHEMA)


class SimulationError(RuntimeError):
    """The run went unstable or cannot continue; the message says who, when and what to change."""


class Simulation:
    def __init__(self, scene):
        from .memory import check_scene
        check_scene(scene)  # refuse a scene larger than the available memory before allocating
        self.scene = scene
        sim = scene.simulation
        self.dt = sim["time_step"]
        if scene.thermal is not None and scene.thermal["time_step"] is not None:
            self.dt = scene.thermal["time_step"]  # frozen packing: the thermal step
        self.step_count = 0
        self.time = 0.0
        self.end_time = sim["end_time"]
        mats = scene.materials
        self.state = State(scene.id, scene.position, scene.velocity, scene.angular_velocity,
                           scene.radius, scene.material, scene.group, [m["density"] for m in mats],
                           walls=len(scene.walls))
        st = self.state
        cgs = scene_mod.parcel_factors(scene)
        if cgs is not None:   # cg = 1 everywhere: exactly the run without
            st.enable(coarse_graining=True)
            st.cg[:] = cgs
        st.lo = np.ascontiguousarray(scene.domain["min"], float)
        st.hi = np.ascontiguousarray(scene.domain["max"], float)
        st.periodic = np.array(scene.domain["periodic"], np.bool_)
        # wrap periodic axes
        L = self.hi - self.lo
        for k in range(3):
            if self.periodic[k]:
                self.state.position[:, k] = self.lo[k] + np.mod(self.state.position[:, k] - self.lo[k], L[k])
        self._build_tables()
        self._build_walls()
        self._build_params()
        self.thermal = None
        if scene.thermal is not None:
            from .thermal.kernel import ThermalModel
            self.thermal = ThermalModel(scene, self.state)
        else:
            from .thermal.kernel import no_heat_tables
            no_heat_tables(self.state)
        self.reach = self.thermal.reach if self.thermal is not None else 0.0
        self.fp[K.FP.reach] = self.reach
        self.rmax = float(self.state.radius.max(initial=0.0))
        self.n_total = self.state.n_owned  # every rank holds the whole scene at this point
        self.par = None
        self._pending = None  # (code, message) of an instability found on this rank
        self._nc2 = 0
        from .parallel import world
        comm = world()
        if comm is not None:
            from .parallel.domain import ParallelDomain
            self.par = ParallelDomain(comm, self)
            self.par.select_initial(self)
        self._init_neighbors()
        if self.thermal is not None:
            self.thermal.update_porosity(self.time)
            if self.par is not None:
                self.par.forward(self, motion=False, porosity=True)
        self.compile_seconds = None
        self._forces_ready = False
        self.last_contacts = 0
        if self.thermal is not None and not sim["mechanics"]:
            # frozen packing: contacts, overlaps and conductances are computed once, here
            self._compute_forces()
            self._forces_ready = True

    # ------------------------------------------------------------------ construction
    @classmethod
    def from_file(cls, path, end_time=None):
        """Scene file -> Simulation; ``end_time`` is used when the file has no
        simulation.end_time (:func:`dem.scene.load`)."""
        return cls(scene_mod.load(path, end_time=end_time))

    @classmethod
    def from_dict(cls, data, base_dir=".", name="<dict>"):
        return cls(scene_mod.parse(data, name, base_dir=base_dir))

    def _build_tables(self):
        sc = self.scene
        t = mixed_tables(sc.materials)
        nm = t["n"]
        model = CONTACT_MODELS[sc.contact["model"]]
        damping = DAMPING_MODELS[sc.contact["damping"]]
        tab = np.zeros((K.TAB.SIZE, nm, nm))
        tab[K.TAB.estar] = t["estar"]
        tab[K.TAB.gstar] = t["gstar"]
        tab[K.TAB.mu] = t["friction"]
        tab[K.TAB.mur] = t["rolling_friction"]
        for a in range(nm):
            for b in range(nm):
                tab[K.TAB.damp, a, b] = damping_factor(t["restitution"][a, b], model, damping)
        self.state.tab = np.ascontiguousarray(tab)
        self.pair_tables = t

    def _build_walls(self):
        walls = self.scene.walls
        nw = len(walls)
        wf = np.zeros((max(nw, 1), W.WF.SIZE))
        wi = np.zeros((max(nw, 1), W.WI.SIZE), np.int64)
        for k, w in enumerate(walls):
            wf[k, W.WF.px:W.WF.px + 3] = w["point"]
            wf[k, W.WF.vx:W.WF.vx + 3] = w["velocity"]
            wf[k, W.WF.ox:W.WF.ox + 3] = w["angular_velocity"]
            wf[k, W.WF.cx:W.WF.cx + 3] = w["rotation_center"]
            wi[k, W.WI.mat] = w["material"]
            if w["type"] == "plane":
                wi[k, W.WI.type] = W.PLANE
                wf[k, W.WF.nx:W.WF.nx + 3] = w["normal"]
                wf[k, W.WF.ux:W.WF.ux + 3] = w["u_axis"]
                ext = w["extent"]
                wf[k, W.WF.eu] = math.inf if ext is None else ext[0]
                wf[k, W.WF.ev] = math.inf if ext is None else ext[1]
            else:
                wi[k, W.WI.type] = W.CYLINDER
                wf[k, W.WF.nx:W.WF.nx + 3] = w["axis"]
                wf[k, W.WF.rad] = w["radius"]
                wf[k, W.WF.eu] = w["length"] / 2
                wf[k, W.WF.side] = 1.0 if w["inside"] else -1.0
        self.state.wf, self.state.wi, self.nwalls = wf, wi, nw
        self.state.enable(epsd=ROLLING_MODELS[self.scene.contact["rolling"]] == 2)
        self.wall_speed = max([float(np.linalg.norm(w["velocity"])) for w in walls], default=0.0)

    def _build_params(self):
        sc = self.scene
        ip = np.zeros(K.IP.SIZE, np.int64)
        ip[K.IP.contact] = CONTACT_MODELS[sc.contact["model"]]
        ip[K.IP.rolling] = ROLLING_MODELS[sc.contact["rolling"]]
        ip[K.IP.nwalls] = self.nwalls
        ip[K.IP.mech] = 1 if sc.simulation["mechanics"] else 0
        ip[K.IP.nown] = self.state.n_owned
        fp = np.zeros(K.FP.SIZE)
        fp[K.FP.dt] = self.dt
        fp[K.FP.gx:K.FP.gz + 1] = sc.simulation["gravity"]
        fp[K.FP.skin] = sc.simulation["neighbor_skin"]
        fp[K.FP.vchar] = self.characteristic_velocity()
        fp[K.FP.ktratio] = sc.contact["tangential_stiffness_ratio"]
        fp[K.FP.linkn] = sc.contact["normal_stiffness"]
        fp[K.FP.etar] = sc.contact["rolling_damping"]
        fp[K.FP.maxov] = sc.simulation["max_overlap_ratio"]
        fp[K.FP.vwall] = self.wall_speed
        self.state.ip, self.state.fp = ip, fp

    def characteristic_velocity(self):
        """Impact velocity used for the Hertz time and the linear stiffness: the scene's
        [contact] characteristic_velocity, else the largest of the initial speeds, the
        wall surface speeds and the free-fall speed over the domain height."""
        c = self.scene.contact["characteristic_velocity"]
        if c:
            return c
        g = np.linalg.norm(self.scene.simulation["gravity"])
        h = float(np.max(self.hi - self.lo))
        v0 = float(np.max(np.linalg.norm(self.state.velocity, axis=1), initial=0.0))
        vw = 0.0
        for w in self.scene.walls:
            vw = max(vw, float(np.linalg.norm(w["velocity"])))
            om = float(np.linalg.norm(w["angular_velocity"]))
            if om > 0:
                vw = max(vw, om * (w.get("radius") or float(np.max(self.hi - self.lo))))
        return max(v0, vw, math.sqrt(2 * g * h), 1e-3)

    def halo(self):
        """Ghost layer width: the longest pair reach 2 r_max + reach + skin."""
        return 2.0 * self.rmax + self.reach + self.fp[K.FP.skin]

    def __getattr__(self, name):
        """The run's arrays by their dem.schema names (``sim.nb`` is ``sim.state.nb``)."""
        if name in _SCHEMA_NAMES and "state" in self.__dict__:
            return getattr(self.__dict__["state"], name)
        raise AttributeError(name)

    def __setattr__(self, name, value):
        if name in _SCHEMA_NAMES:  # one owner for every array: the state
            raise AttributeError(f"Simulation.{name} is dem.state.State.{name}: assign sim.state.{name}")
        object.__setattr__(self, name, value)

    def _init_neighbors(self):
        if self.par is not None:
            self._par_rebuild(self.step_count, initial=True)
            return
        self._rebuild(self.step_count, self.lo, self.hi, self.periodic, initial=True)

    def _rebuild(self, step, glo, ghi, gwrap, initial=False):
        """The rebuild phase (dem.step.rebuild) from Python at the time of step number
        ``step``, with the history starting empty (restored by the caller): the half list over
        the cell grid [glo, ghi] (wrapped on ``gwrap``), then dem.step.after_build (advance's
        PH_AFTER_BUILD). A first build sizes the slots tightly (the largest count + 2)."""
        st = self.state
        slots = 12 if initial else st.nb.shape[1]
        empty = S.Pairs(*[f.empty() for f in S.of("pair", kernel_only=True)])
        for _ in range(2):
            nb, nnb, hist, rhist, age, maxc = build_half_list(
                st.position, st.radius, st.n, st.n_owned, Box(self.lo, self.hi, self.periodic), Box(glo, ghi, gwrap),
                self.reach, self.fp[K.FP.skin], slots, empty)
            if not initial or maxc + 2 >= slots:
                break
            slots = maxc + 2
        self._set_pairs(S.Pairs(nb, nnb, hist, rhist, age, st.Hd, st.Hi, st.rnear))
        self._set_pairs(self._phases(K.PH_AFTER_BUILD, s0=step - 1)[-1])

    def _set_pairs(self, C):
        st = self.state
        for name, a in zip(C._fields, C):
            setattr(st, name, a)

    # ------------------------------------------------------------------ checks
    def check(self):
        """Derived quantities and the time-step verdict; raises SceneError when the step is
        above the documented fraction and the scene does not say force = true."""
        sc = self.scene
        st = self.state
        rep = {"particles": self.n_particles, "walls": self.nwalls, "materials": len(sc.materials)}
        rep["mass_total"] = float(st.mass.sum())
        rep["mass_min"] = float(st.mass.min())
        rep["mass_max"] = float(st.mass.max())
        rep["radius_min"] = float(st.radius.min())
        rep["radius_max"] = float(st.radius.max())
        tr, th, ovmax = self.time_scales()
        vchar = self.fp[K.FP.vchar]
        rep["impact_overlap_ratio"] = ovmax
        rep["rayleigh_time"] = tr
        rep["hertz_time"] = th
        rep["characteristic_velocity"] = vchar
        rep["dt"] = self.dt
        rep["dt_over_rayleigh"] = self.dt / tr
        rep["dt_over_hertz"] = self.dt / th
        rep["mechanics"] = bool(sc.simulation["mechanics"])
        rep["steps"] = int(round(self.end_time / self.dt))
        mem, rep["memory_neighbor_build_bytes"] = self._memory_estimate()
        rep["memory_bytes"] = int(mem)
        rep["memory_per_particle"] = mem / max(st.n, 1)
        runs, skipped = self.models_report()
        rep["runs"], rep["skipped"] = runs, skipped
        warnings = []
        if sc.simulation["mechanics"] and ovmax > self.fp[K.FP.maxov]:
            warnings.append(f"a Hertz impact at the characteristic velocity {vchar:.3g} m/s overlaps "
                            f"{ovmax:.3g} of the radius, above simulation.max_overlap_ratio = "
                            f"{self.fp[K.FP.maxov]:g}: the overlap guard may stop the run (raise "
                            f"youngs_modulus, or the bound if such overlaps are acceptable)")
        warnings += _parcel_period_warnings(sc)
        if self.thermal is not None:
            rep.update(self.thermal.check(self.dt, self._compute_forces))
        rep["warnings"] = warnings + rep.get("warnings", [])
        problems = []
        if sc.simulation["mechanics"]:
            if self.dt > scene_mod.RAYLEIGH_FRACTION * tr:
                problems.append(f"time_step {self.dt:g} s is {self.dt / tr:.3g} of the Rayleigh time {tr:.3g} s "
                                f"(allowed: {scene_mod.RAYLEIGH_FRACTION})")
            if self.dt > scene_mod.HERTZ_FRACTION * th:
                problems.append(f"time_step {self.dt:g} s is {self.dt / th:.3g} of the Hertz collision time {th:.3g} s "
                                f"at {vchar:.3g} m/s (allowed: {scene_mod.HERTZ_FRACTION})")
        rep["problems"] = problems
        if problems and not sc.simulation["force"]:
            raise scene_mod.SceneError(sc.file, "simulation.time_step",
                                       "; ".join(problems) + ". Lower time_step, or set simulation.force = true "
                                       "to run anyway")
        return rep

    def models_report(self):
        sc = self.scene
        runs = [f"contact: {sc.contact['model']} (damping {sc.contact['damping']})"]
        skipped = []
        if sc.contact["rolling"] != "none":
            runs.append(f"rolling resistance: {sc.contact['rolling']}")
        else:
            skipped.append("rolling resistance: [contact] rolling = 'none'")
        if self.nwalls:
            runs.append(f"walls: {self.nwalls}")
        else:
            skipped.append("walls: none in the scene")
        if not sc.simulation["mechanics"]:
            runs[0] = "mechanics frozen (simulation.mechanics = false): contacts computed once"
        if self.par is not None:
            runs.append(f"parallel: {self.par.describe()}, ghosts within {self.halo():.4g} m, "
                        f"re-balanced above {self.scene.parallel['balance_threshold']:g}")
        else:
            skipped.append("parallel decomposition: one process (mpirun -np N dem run ... splits the domain)")
        from .energy_guard import inputs_of
        why = inputs_of(self)
        if why:
            skipped.append(f"energy guard: {', '.join(why)} (energy enters the system)")
        else:
            runs.append("energy guard: the mechanical energy of this closed system may not grow")
        if self.thermal is None:
            skipped.append("heat transfer: no [thermal] section (no thermal arrays, no thermal cost)")
        else:
            r, s = self.thermal.models_report()
            runs += r
            skipped += s
        return runs, skipped

    def time_scales(self):
        """(Rayleigh time, Hertz collision time at the characteristic velocity, largest Hertz
        impact overlap / radius) of the smallest particle of each material (and its walls)."""
        sc = self.scene
        st = self.state
        vchar = self.fp[K.FP.vchar]
        tr, th = math.inf, math.inf
        ovmax = 0.0
        for k, m in enumerate(sc.materials):
            sel = st.material == k
            if not np.any(sel):
                continue
            rmin = float(st.radius[sel].min())
            G = m["youngs_modulus"] / (2 * (1 + m["poisson_ratio"]))
            tr = min(tr, rayleigh_time(rmin, m["density"], G, m["poisson_ratio"]))
            mmin = 4 / 3 * math.pi * rmin ** 3 * m["density"]
            estar = self.tab[K.TAB.estar, k, k]
            th = min(th, hertz_collision_time(mmin / 2, rmin / 2, estar, vchar))
            for w in sc.walls:
                th = min(th, hertz_collision_time(mmin, rmin, self.tab[K.TAB.estar, k, w["material"]], vchar))
            # largest Hertz overlap of an impact at the characteristic velocity (smallest particle)
            d = (15 * (mmin / 2) * vchar ** 2 / (16 * estar * math.sqrt(rmin / 2))) ** 0.4
            ovmax = max(ovmax, d / rmin)
        return tr, th, ovmax

    def _memory_estimate(self):
        """(peak bytes of this process's particle arrays, bytes of one neighbour build).

        Peak = the per-particle arrays + the neighbour list and its history slots + during a
        rebuild, the new list beside the old one and the cell grid of the build (the box of
        occupied cells or sorted keys: O(n), independent of the domain size)."""
        st = self.state
        lists = sum(getattr(st, f.name).nbytes for f in S.of("pair") if f.name in ("nb", "nnb") or f.record)
        if self.par is None:
            glo, ghi, gwrap = self.lo, self.hi, self.periodic
        else:
            glo, ghi, gwrap = self.par.grid_box(self)
        grid = grid_bytes(st.position, st.radius, st.n, glo, ghi, gwrap, self.reach, self.fp[K.FP.skin])
        mem = st.memory_bytes("particle") + st.memory_bytes("pair")
        return mem + lists + grid, lists + grid

    # ------------------------------------------------------------------ stepping
    def _compute_forces(self):
        """The interact phase at the current time (no step): forces, torques and (with heat)
        the conductances; the heat totals are left as they were."""
        st = self.state
        saved = st.heat_totals()  # the initial force evaluation exchanges no heat
        _, _, i, j, maxov, nc, _, _ = self._phases(K.PH_FORCES)
        st.restore_heat_totals(saved)
        self._nc2 = nc
        self.last_contacts = nc // 2
        return maxov

    @property
    def _hon(self):
        """The kernels' heat switch as a type: True with a [thermal] section, None without, so
        that Numba compiles a mechanics-only specialisation with the heat code removed
        (docs/benchmarks.md, "Cost of each mechanism": a run-time flag alone cost ~5 %)."""
        return True if self.thermal is not None else None

    def _phases(self, phases, nsteps=1, s0=None):
        """dem.step.advance over ``nsteps`` steps from step number s0 (by default the step in
        progress: a force evaluation alone is at the current time), the given phases only."""
        st = self.state
        b = st.bundles()
        s0 = self.step_count - 1 if s0 is None else s0
        ent = self.__dict__.get("_entry")
        if ent is not None and ent[0] is b and ent[1] is self._hon:
            # the compiled form found for these very bundles: called without the dispatcher's type
            # resolution of the ~60 arrays (25 us -> 12 us a call; an MPI step makes 2-3 calls)
            return ent[2](nsteps, s0, st.n, st.n_owned, *b, self._hon, phases)
        args = (nsteps, s0, st.n, st.n_owned, *b, self._hon, phases)
        res = K.advance(*args)
        self._entry = (b, self._hon, K.advance.get_overload(tuple(K.advance.typeof_pyval(a) for a in args)))
        return res

    def _advance(self, nsteps):
        if self.par is not None:
            return self._advance_parallel(nsteps)
        if not self._forces_ready:
            self._compute_forces()
            self._forces_ready = True
        phases = K.PH_STEP if self.ip[K.IP.mech] else K.PH_HEAT  # frozen packing: heat on fixed conductances
        done, status, who, other, value, nc, nreb, C = self._phases(phases, nsteps, self.step_count)
        self._set_pairs(C)
        self.step_count += done
        self.time = self.step_count * self.dt
        if self.ip[K.IP.mech]:  # frozen packings keep the contact count of their set-up
            self._nc2 = nc
            self.last_contacts = nc // 2
        if status != K.OK:
            self._instability(status, who, other, value)
        return done

    def _instability(self, status, i, j, value):
        raise SimulationError(self._instability_message(status, i, j, value))

    def _instability_message(self, status, i, j, value):
        st = self.state
        pid = int(st.id[i])
        where = f"at t = {self.time:.9g} s (step {self.step_count})"
        pos = np.array2string(st.position[i], precision=6)
        if status == K.OVERLAP:
            other = f"wall {self.scene.walls[-1 - j]['name']}" if j < 0 else f"particle id {int(st.id[j])}"
            msg = (f"particle id {pid} at {pos} and {other} overlap by {value:.3g} of the radius {where}, "
                   f"beyond simulation.max_overlap_ratio = {self.fp[K.FP.maxov]:g}. Lower time_step "
                   f"(now {self.dt:g} s), raise youngs_modulus, or lower the impact speeds")
        elif status == K.NONFINITE:
            msg = (f"particle id {pid} got a non-finite velocity {where}: the run is unstable. "
                   f"Lower time_step (now {self.dt:g} s; see `dem check`), or check forces and properties")
        elif status == K.BAD_TEMPERATURE:
            integ = self.thermal.cfg["integrator"] if self.thermal is not None else "euler"
            advice = ("use thermal.integrator = \"exponential\" or a step below the network and "
                      "radiation limits printed by `dem check`" if integ == "euler" else
                      "lower the thermal step: heat sources, fixed wall fluxes or friction heat are "
                      "explicit and outrun the particle's heat capacity")
            msg = (f"particle id {pid} reached temperature {value:.6g} K {where}: the heat step "
                   f"({integ}, dt = {self.dt:g} s) is unstable; {advice}")
        else:
            msg = (f"particle id {pid} left the domain {where} at {pos} (domain {self.lo.tolist()} to "
                   f"{self.hi.tolist()}). Add walls, enlarge [domain], or make the axis periodic")
        return msg

    # ------------------------------------------------------------------ parallel stepping
    def _par_rebuild(self, step, initial=False, rec=None, weights_from_list=True):
        """Exchange particles and ghosts with the other ranks, then the rebuild phase
        (dem.step.rebuild, the same as a serial run's) and the contact history brought back
        from its id-keyed records (dem.parallel.records)."""
        from .parallel import records
        par = self.par
        st = self.state
        weights = None
        if not initial:
            nown = st.n_owned
            i, k = K.outside(st.position, self.lo, self.hi, self.periodic, nown)
            if i >= 0 and self._pending is None:
                self._pending = (K.LEFT_DOMAIN, self._instability_message(K.LEFT_DOMAIN, int(i), -1,
                                                                          float(st.position[i, k])))
            if rec is None:
                rec = records.extract(st)
            if weights_from_list:
                weights = 1.0 + self.scene.parallel["pair_weight"] * st.nnb[:nown]
        resort_vor = par.sort_pending and self.thermal is not None and self.thermal.voronoi
        rec = par.exchange(self, rec, weights)
        glo, ghi, gwrap = par.grid_box(self)
        self._rebuild(step, glo, ghi, gwrap, initial=initial)
        records.restore(rec, st, par.key_base)
        self.ip[K.IP.nown] = st.n_owned
        if self.thermal is not None and not initial:
            from .thermal.heat import TI
            if self.thermal.thi[TI.localpor] == 1:
                par.forward(self, motion=False, porosity=True)
            elif resort_vor:
                self.thermal.update_porosity(self.time)
                par.forward(self, motion=False, porosity=True)

    def _advance_parallel(self, nsteps):
        """The phases of dem.step.advance (drift, rebuild, interact, kick + guards, heat),
        one step at a time with the ghost messages between them (one Allreduce per step
        carries the rebuild decision and the previous step's stability status)."""
        from .thermal.heat import cross_rates, TI
        par = self.par
        st = self.state
        expo_cross = self.thermal is not None and self.thermal.thi[TI.integ] != 0
        if not self._forces_ready:
            self._compute_forces()
            self._forces_ready = True
        dt = self.dt
        mech = bool(self.ip[K.IP.mech])
        heat = self.thermal is not None
        done = 0
        for _ in range(nsteps):
            need = 0.0
            if mech:
                need = 1.0 if self._phases(K.PH_DRIFT, s0=self.step_count)[1] == K.REBUILD_DUE else 0.0
            code, need = par.flags(self._pending[0] if self._pending else 0.0, need)
            if code:
                self._raise_collective()
            if mech:
                if need:
                    self._par_rebuild(self.step_count + 1)
                else:
                    par.forward(self, motion=True, temperature=heat)
                # without the exponential update's cross-rank rates the heat phase needs no message
                # first: one call for interact, kick and heat
                fused = heat and not expo_cross
                ph = K.PH_FORCES | K.PH_KICK | (K.PH_HEAT if fused else 0)
                _, status, who, other, value, nc, _, _ = self._phases(ph, s0=self.step_count)
                self._nc2 = nc
                if status != K.OK and self._pending is None:
                    self._pending = (status, self._instability_message(status, who, other, value))
            elif heat:
                par.forward(self, motion=False, temperature=True)
                fused = False
            else:
                fused = False
            if heat and not fused:
                if expo_cross:
                    cross_rates(st.n_owned, st.inv_heat_capacity, st.nb, st.nnb, st.Hd, st.Hi, st.work)
                    par.forward(self, motion=False, rate=True)
                _, status, who, _, value, _, _, _ = self._phases(K.PH_HEAT, s0=self.step_count)
                if status != K.OK and self._pending is None:
                    self._pending = (status, self._instability_message(status, who, -1, value))
            self.step_count += 1
            self.time = self.step_count * dt
            done += 1
        code, _ = par.flags(self._pending[0] if self._pending else 0.0, 0.0)
        if code:
            self._raise_collective()
        return done

    def _raise_collective(self):
        msgs = self.par.comm.allgather(self._pending[1] if self._pending else None)
        msg = next(m for m in msgs if m)
        raise SimulationError(msg)

    def sort_particles(self):
        """Reorder particles by cell for cache locality; every sorted array of dem.schema
        follows (neighbour rows renumbered), so the physics is unchanged."""
        if self.par is not None:  # done at the next exchange with the other ranks
            self.par.sort_pending = True
            return
        st = self.state
        cell = 2 * float(st.radius.max()) + self.reach + self.fp[K.FP.skin]
        st.permute(sort_permutation(st.position, self.lo, self.hi, cell))
        if self.thermal is not None and self.thermal.voronoi and self.scene.simulation["mechanics"]:
            self.thermal.update_porosity(self.time)

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
        st = self.state
        k = st.n_owned
        if force is not None:
            if not st.features.get("fluid"):
                st.enable(fluid=True)
            st.external_force[:k] = force
            st.external_force[k:] = 0.0
            st.drag_beta[:k] = 0.0 if drag is None else drag
            st.drag_beta[k:] = 0.0
        if torque is not None:
            if not st.features.get("fluid_torque"):
                st.enable(fluid_torque=True)
            st.external_torque[:k] = torque
            st.external_torque[k:] = 0.0
            st.rot_drag[:k] = 0.0 if torque_drag is None else torque_drag
            st.rot_drag[k:] = 0.0
        if added_mass is not None:
            if not st.features.get("virtual_mass"):
                st.enable(virtual_mass=True)
            st.inv_mass_eff[:k] = 1.0 / (st.mass[:k] + added_mass)
            st.inv_mass_eff[k:] = st.inv_mass[k:]
        th = self.thermal
        if th is None:
            return
        if velocity is not None:
            st.uf[:k] = velocity
        if temperature is not None:
            st.tf[:k] = temperature
        if porosity is not None:
            st.por[:k] = porosity
            th.local_porosity = False
            from .thermal.heat import TI
            th.thi[TI.localpor] = 0  # the CFD void fraction is used instead
            if self.par is not None:
                self.par.forward(self, motion=False, porosity=True)

    def warmup(self):
        """Compile (or load from Numba's cache) the kernels; returns seconds spent."""
        t0 = time.perf_counter()
        self._advance(0)
        self.compile_seconds = time.perf_counter() - t0
        return self.compile_seconds

    def step(self, nsteps=1):
        return self._advance(nsteps)

    # ------------------------------------------------------------------ stats / output
    @property
    def is_root(self):
        """True on the rank that writes files (always in a serial run)."""
        return self.par is None or self.par.rank == 0

    @property
    def n_particles(self):
        """Particles in the whole run (all ranks; constant: no particle is added or removed)."""
        return self.n_total

    def history_row(self):
        """One row of history.csv (collective in a parallel run: sums, minima, maxima)."""
        st = self.state
        et, er = st.kinetic_energy()
        maxov = self._overlap_stats()
        if self.par is None:
            row = dict(time=self.time, kinetic_energy=et, rotational_energy=er,
                       contacts=self.last_contacts, max_overlap_ratio=maxov)
            if self.thermal is not None:
                row.update(self.thermal.history_row())
            return row
        p = self.par
        th = self.thermal
        n = st.n_owned
        vals = [et, er, float(self._nc2), float(n)]
        if th is not None:
            T = st.temperature[:n]
            vals += [float(np.sum(T / st.inv_heat_capacity[:n])), float(T.sum())]
            vals += list(th.tot[:len(THERMAL_MECHANISMS)]) + list(th.wtot[:len(self.scene.walls)])
        tot = p.allsum(np.array(vals))
        row = dict(time=self.time, kinetic_energy=tot[0], rotational_energy=tot[1],
                   contacts=int(tot[2]) // 2, max_overlap_ratio=p.allmax(maxov))
        if th is not None:
            T = st.temperature[:n]
            tmin = p.allmin(float(T.min()) if n else math.inf)
            tmax = p.allmax(float(T.max()) if n else -math.inf)
            row.update(thermal_energy=tot[4], T_mean=tot[5] / max(tot[3], 1), T_min=tmin, T_max=tmax)
            k = 6
            for m in THERMAL_MECHANISMS:
                row[f"E_{m}"] = tot[k]
                k += 1
            for w in self.scene.walls:
                row[f"E_wall_{w['name']}"] = tot[k]
                k += 1
        return row

    def _overlap_stats(self):
        from .stats import max_overlap_ratio
        st = self.state
        return max_overlap_ratio(st.n, st.position, st.radius, st.nb, st.nnb, self.lo, self.hi,
                                 self.periodic, self.wf, self.wi, self.nwalls, self.time)

    def wall_heat_totals(self):
        """Heat through each wall since the start (J), summed over the ranks (collective):
        [n_walls, 3] of (all paths, across the gas gap, by radiation); None without heat or
        walls."""
        nw = len(self.scene.walls)
        if self.thermal is None or nw == 0:
            return None
        st = self.state
        a = np.c_[st.wtot[:nw], st.wgap[:nw], st.wrad[:nw]].astype(float)
        if self.par is not None:
            a = np.asarray(self.par.allsum(a.ravel()), float).reshape(nw, 3)
        return a

    def history_columns(self):
        cols = ["time", "kinetic_energy", "rotational_energy", "contacts", "max_overlap_ratio"]
        if self.thermal is not None:
            cols += self.thermal.history_columns()
        return cols

    def _output_arrays(self):
        """The owned rows of every enabled array declared with an output name (dem.schema)."""
        st = self.state
        n = st.n_owned
        return {f.output: getattr(st, f.name)[:n] for f in S.FIELDS
                if f.output and f.owner == "particle" and S.enabled(f, st.features)}

    def particle_fields(self):
        """Per-particle fields of the VTK output (float64; the position goes apart)."""
        f = {k: (a if a.dtype == np.float64 else a.astype(np.float64))
             for k, a in self._output_arrays().items() if k != "position"}
        if self.par is not None:
            f["rank"] = np.full(self.state.n_owned, float(self.par.rank))
        return f

    def _gather_by_id(self, arrays):
        """Owned rows of every rank, concatenated and ordered by particle id, on the root
        (None elsewhere); a serial run just orders its rows."""
        parts = [arrays] if self.par is None else self.par.gather(arrays)
        return None if parts is None else self._gather_by_id_parts(parts)

    def final_arrays(self):
        """Per-particle results ordered by id (collective; None on ranks other than the root)."""
        out = self._gather_by_id(self._output_arrays())
        if out is not None:
            out["time"] = np.float64(self.time)
        return out

    # ------------------------------------------------------------------ checkpoints
    def _checkpointed(self, owner):
        """The enabled arrays of ``owner`` with a checkpoint key (dem.schema)."""
        st = self.state
        return [f for f in S.of(owner) if f.checkpoint and S.enabled(f, st.features)]

    def checkpoint_arrays(self):
        """Everything needed to continue the run, as declared in dem.schema. A serial
        checkpoint holds the neighbour list and its history slots (bit-exact restart); every
        checkpoint also holds the per-particle arrays ordered by id and the contact history as
        id-keyed records, so that any number of ranks can continue it (collective; None off
        the root)."""
        from .parallel import records
        st = self.state
        n = st.n_owned
        rec = records.extract(st)
        rec = {f"rec_{k}": v for k, v in rec.items() if v is not None}
        common = dict(fp_tbuild=np.float64(self.fp[K.FP.tbuild]), step_count=np.int64(self.step_count),
                      dt=np.float64(self.dt), forces_ready=np.bool_(self._forces_ready),
                      scene_file=np.str_(os.path.abspath(self.scene.file)),
                      ranks=np.int64(1 if self.par is None else self.par.size))
        totals = {f.checkpoint: getattr(st, f.name) for f in self._checkpointed("wall") + self._checkpointed("param")
                  if self.thermal is not None}
        if self.par is None:
            arr = {f.checkpoint: getattr(st, f.name) for f in self._checkpointed("particle") + self._checkpointed("pair")}
            arr.update(**common, **rec, **totals)
            return arr
        local = {f.checkpoint: getattr(st, f.name)[:n] for f in self._checkpointed("particle")}
        local["id"] = st.id[:n]
        parts = self.par.gather((local, rec))  # records travel beside, not ordered by id
        totals = {k: self.par.allsum(v) for k, v in totals.items()}
        if parts is None:
            return None
        arr = self._gather_by_id_parts([p[0] for p in parts])
        arr.pop("id")
        rkeys = sorted(set().union(*(p[1] for p in parts)))  # a rank owning no particle has no
        for k in rkeys:                                      # record, nor the optional fields
            arr[k] = np.concatenate([p[1][k] for p in parts if k in p[1]])
        if "rec_a" in arr:  # a pair across ranks was recorded by both: keep one
            _, first = np.unique(arr["rec_a"] * self.par.key_base + arr["rec_b"], return_index=True)
            for k in rkeys:
                arr[k] = arr[k][first]
        arr.update(**common, **totals)
        return arr

    @staticmethod
    def _gather_by_id_parts(parts):
        out = {k: np.concatenate([p[k] for p in parts]) for k in parts[0]}
        order = np.argsort(out["id"], kind="stable")
        return {k: np.ascontiguousarray(v[order]) for k, v in out.items()}

    def write_checkpoint(self, path):
        """Write a checkpoint (collective): the arrays of :meth:`checkpoint_arrays` with a
        format version, the scene's record and a checksum (dem.checkpoint)."""
        from . import checkpoint as ckpt
        arr = self.checkpoint_arrays()
        if arr is not None:
            record = ckpt.scene_record(self)
            self.root_write(lambda: ckpt.write(path, arr, record))

    def prepare_restart(self, path):
        """Read and verify a checkpoint and plan the restart with this scene: raises
        dem.scene.SceneError (bad file, or a refused scene edit) before any output is
        written or any kernel compiled. :meth:`load_checkpoint` uses the result."""
        from . import checkpoint as ckpt
        arrays, record = ckpt.read(path)
        ckpt.validate(path, arrays, record)
        plan = ckpt.plan_restart(self, path, arrays, record)
        self._restart_ready = (os.fspath(path), arrays, record, plan)
        return plan

    def load_checkpoint(self, path):
        """Continue from a checkpoint. Unchanged scene: the serial layout restarts
        bit-exact. Edited scene: the changes of dem.checkpoint.plan_restart are applied to
        the checkpoint's arrays and listed on stdout ("restart: applied ...")."""
        from . import checkpoint as ckpt
        ready = getattr(self, "_restart_ready", None)
        if ready is None or ready[0] != os.fspath(path):
            self.prepare_restart(path)
            ready = self._restart_ready
        self._restart_ready = None
        _, arrays, record, plan = ready
        ckpt.apply_edits(arrays, plan, self)
        z = ckpt.ArrayView(arrays)
        self._recompute_after_load = False
        if self.par is not None or int(z["ranks"]) != 1 or "nb" not in z.files or plan.rebuild:
            self._load_portable(path, z)
        else:
            self._load_serial(z)
        if plan.recompute_forces or self._recompute_after_load:
            self._recompute_forces_keeping_history()
        self.restart_changes = plan.applied
        if self.is_root:
            for line in plan.applied:
                print(f"restart: applied {line}", flush=True)

    def _load_serial(self, z):
        """The serial layout: every checkpointed array as written (bit-exact continuation)."""
        st = self.state
        for f in self._checkpointed("particle") + self._checkpointed("pair"):
            if f.checkpoint not in z.files:
                if self._added_later(f):
                    continue
                raise SimulationError(f"checkpoint lacks {f.checkpoint!r} (thermal or contact settings changed?)")
            setattr(st, f.name, np.ascontiguousarray(z[f.checkpoint], f.dtype))
        st.allocate()  # what an older checkpoint lacks (dem.checkpoint.ADDED_LATER)
        self._load_totals(z, root=True)
        self.fp[K.FP.tbuild] = float(z["fp_tbuild"])
        self.step_count = int(z["step_count"])
        self.time = self.step_count * self.dt
        self._forces_ready = bool(z["forces_ready"])

    def _load_totals(self, z, root):
        """Run totals (heat per mechanism and per wall): on the root only, zero elsewhere."""
        if self.thermal is None:
            return
        st = self.state
        for f in self._checkpointed("wall") + self._checkpointed("param"):
            getattr(st, f.name)[:] = z[f.checkpoint] if root and f.checkpoint in z.files else 0.0

    def _added_later(self, f):
        """True for an array that an older checkpoint may lack (dem.checkpoint.ADDED_LATER);
        a conductance among them makes load_checkpoint recompute the forces and conductances."""
        from .checkpoint import ADDED_LATER
        if f.checkpoint not in ADDED_LATER:
            return False
        if f.owner == "particle":
            self._recompute_after_load = True
        return True

    def _recompute_forces_keeping_history(self):
        """Forces at the restart time with the edited physics (masses, tables, walls,
        gravity); the contact springs, ages and temperatures stay as in the checkpoint so
        that the next step increments them once, as an uninterrupted run does (collective
        in a parallel run: the ghosts were exchanged by the loader)."""
        st = self.state
        keep = [(f.name, getattr(st, f.name).copy()) for f in S.FIELDS
                if f.record or f.name in ("whist", "wrhist", "temperature", "heat_rate")]
        self._compute_forces()
        for name, a in keep:
            getattr(st, name)[...] = a
        self._forces_ready = True

    def _load_portable(self, path, z):
        """Continue from a checkpoint written on any number of ranks: per-particle arrays by
        id, the neighbour list rebuilt here, the contact history restored from its records."""
        from .parallel import records
        st = self.state
        pos = z["state_position"]
        if self.par is not None:
            rows = np.nonzero(self.par.dec.owner(pos) == self.par.rank)[0]
        else:
            rows = np.arange(pos.shape[0])
        st.enable(fluid=False)  # the coupling sets the fluid data again
        for f in self._checkpointed("particle"):
            if f.checkpoint not in z.files:
                if self._added_later(f):
                    continue
                raise SimulationError(f"{path}: checkpoint lacks {f.checkpoint!r} (thermal or contact settings "
                                      f"changed?)")
            setattr(st, f.name, np.ascontiguousarray(z[f.checkpoint][rows], f.dtype))
        st.n_owned = rows.size
        st.n_ghost = 0
        st.allocate()  # the arrays a checkpoint does not hold (scratch), sized for these rows
        self.ip[K.IP.nown] = rows.size
        rec = {k: (z[f"rec_{k}"] if f"rec_{k}" in z.files else None) for k in records.FIELDS}
        if rec["a"] is None:
            rec = None
        self.step_count = int(z["step_count"])
        self.time = self.step_count * self.dt
        self._forces_ready = bool(z["forces_ready"])
        self._load_totals(z, root=self.is_root)
        if self.par is not None:
            self._par_rebuild(self.step_count, rec=rec, weights_from_list=False)
        else:
            self._init_neighbors()
            records.restore(rec, st, int(st.id.max(initial=0)) + 1)
        th = self.thermal
        if th is not None:
            th.update_porosity(self.time)
            if self.par is not None:
                self.par.forward(self, motion=False, porosity=True)
            if not self.scene.simulation["mechanics"]:
                self._compute_forces()  # the frozen packing's conductances

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
        self._write_failure = None
        self._hold_writes = True
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
            ops.execute(self, plan, end_step)
            return self
        finally:
            self._hold_writes = False

    def root_write(self, write):
        """A write done by the root alone. Inside run() under MPI an OutputError is held (the
        other ranks are on their way to the next collective call) until settle_writes
        raises it on every rank; elsewhere it is raised at once."""
        try:
            write()
        except OutputError as exc:
            if self.par is None or not getattr(self, "_hold_writes", False):
                raise
            if self._write_failure is None:
                self._write_failure = exc


    def settle_writes(self):
        """Raise the held OutputError of the root on every rank (collective under MPI)."""
        if self.par is None:
            return
        msg = self.par.comm.bcast(str(self._write_failure) if self._write_failure else None, root=0)
        if msg:
            self._write_failure = None
            self._hold_writes = False
            raise OutputError(message=msg)

    def write_vtk(self, vtk, **extra):
        """One VTK output of the owned particles of every rank (collective; ``vtk`` is the
        root's VTKSeries, None elsewhere); ``extra``: more per-particle fields."""
        st = self.state
        f = dict(self.particle_fields(), **extra)
        f["position"] = st.position[:st.n_owned]
        f = self._gather_by_id(f)
        if vtk is not None:
            pos = f.pop("position")
            self.root_write(lambda: vtk.write(self.time, self.step_count, pos, f))


# a periodic length below this many parcel diameters orders a coarse-grained packing through its
# periodic images (docs/benchmarks.md, "Coarse graining": over 3 to 6 parcel diameters the
# coordination number of poured parcel beds was 6 to 15 % above the fine bed's, at 12 within 2 %)
PARCEL_PERIOD_DIAMETERS = 10.0


def _parcel_period_warnings(sc):
    """Warnings for periodic axes only a few parcel diameters long (a scene with parcels)."""
    cg = scene_mod.parcel_factors(sc)
    if cg is None:
        return []
    d = 2.0 * float(sc.radius[cg != 1.0].max())
    lo, hi, per = sc.domain["min"], sc.domain["max"], sc.domain["periodic"]
    out = []
    for ax in range(3):
        L = float(hi[ax] - lo[ax])
        if per[ax] and L < PARCEL_PERIOD_DIAMETERS * d:
            out.append(f"axis {'xyz'[ax]} is periodic over {L:g} m, {L / d:.3g} parcel diameters: the periodic "
                       f"images order a packing of parcels this few across (a poured bed's coordination number, "
                       f"and its contact conduction, came out 6 to 15 % high over 3 to 6 parcel diameters, within "
                       f"2 % over 12; docs/benchmarks.md, Coarse graining); make the domain along {'xyz'[ax]} at "
                       f"least {PARCEL_PERIOD_DIAMETERS:g} parcel diameters ({PARCEL_PERIOD_DIAMETERS * d:.3g} m)")
    return out
