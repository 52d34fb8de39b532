"""Simulation: owns the state, builds the step from the scene, runs it, writes output.

    sim = Simulation.from_file("examples/settle_box.toml")
    sim.run(end_time=0.2, out_dir="out/settle")
    sim.state.position, sim.state.velocity, ...
"""
import math
import os
import sys
import time

import numpy as np

from . import scene as scene_mod
from .contact.damping import damping_factor, mixed_tables, rayleigh_time, hertz_collision_time
from .contact.registry import CONTACT_MODELS, ROLLING_MODELS, DAMPING_MODELS
from .contact import walls as W
from .neighbors import build_half_list, grid_bytes, sort_permutation
from .output import History, OutputError, VTKSeries, prepare_output_folder, save_npz  # noqa: F401
from .outdir import claim_collective
from .state import State
from . import step as K
from .thermal.kernel import MECHANISMS as THERMAL_MECHANISMS


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
                           scene.radius, scene.material, scene.group, [m["density"] for m in mats])
        self.lo = np.ascontiguousarray(scene.domain["min"], float)
        self.hi = np.ascontiguousarray(scene.domain["max"], float)
        self.periodic = np.array(scene.domain["periodic"], np.bool_)
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
            self.thermal = ThermalModel(self)
        self.reach = self.thermal.reach if self.thermal is not None else 0.0
        self.fp[K.F_REACH] = self.reach
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
            self.TH = self.thermal.th_tuple()
            self.Hd, self.Hi, self.rnear = self.thermal.slot_arrays(self.nb.shape[1])
            self.thermal.update_porosity()
            if self.par is not None:
                self.par.forward(self, motion=False, porosity=True)
        else:
            self.TH = K.empty_thermal(self.nwalls)
            self.Hd, self.Hi, self.rnear = np.zeros((0, 1)), np.zeros((0, 1)), np.zeros((0, 1), np.uint8)
        self.compile_seconds = None
        self._forces_ready = False
        self.last_contacts = 0
        if self.thermal is not None and not sim["mechanics"]:
            # frozen packing: contacts, overlaps and conductances are computed once, here
            self._compute_forces()
            self._forces_ready = True

    # ------------------------------------------------------------------ construction
    @classmethod
    def from_file(cls, path):
        return cls(scene_mod.load(path))

    @classmethod
    def from_dict(cls, data, base_dir=".", name="<dict>"):
        return cls(scene_mod.parse(data, name, base_dir=base_dir))

    def _build_tables(self):
        sc = self.scene
        t = mixed_tables(sc.materials)
        nm = t["n"]
        model = CONTACT_MODELS[sc.contact["model"]]
        damping = DAMPING_MODELS[sc.contact["damping"]]
        tab = np.zeros((K.NTAB, nm, nm))
        tab[K.T_ESTAR] = t["estar"]
        tab[K.T_GSTAR] = t["gstar"]
        tab[K.T_MU] = t["friction"]
        tab[K.T_MUR] = t["rolling_friction"]
        for a in range(nm):
            for b in range(nm):
                tab[K.T_DAMP, a, b] = damping_factor(t["restitution"][a, b], model, damping)
        self.tab = np.ascontiguousarray(tab)
        self.pair_tables = t

    def _build_walls(self):
        walls = self.scene.walls
        nw = len(walls)
        wf = np.zeros((max(nw, 1), W.NWF))
        wi = np.zeros((max(nw, 1), W.NWI), np.int64)
        for k, w in enumerate(walls):
            wf[k, W.PX:W.PX + 3] = w["point"]
            wf[k, W.VX:W.VX + 3] = w["velocity"]
            wf[k, W.OX:W.OX + 3] = w["angular_velocity"]
            wf[k, W.CX:W.CX + 3] = w["rotation_center"]
            wi[k, W.WMAT] = w["material"]
            if w["type"] == "plane":
                wi[k, W.WTYPE] = W.PLANE
                wf[k, W.NX:W.NX + 3] = w["normal"]
                wf[k, W.UX:W.UX + 3] = w["u_axis"]
                ext = w["extent"]
                wf[k, W.EU] = math.inf if ext is None else ext[0]
                wf[k, W.EV] = math.inf if ext is None else ext[1]
            else:
                wi[k, W.WTYPE] = W.CYLINDER
                wf[k, W.NX:W.NX + 3] = w["axis"]
                wf[k, W.RAD] = w["radius"]
                wf[k, W.EU] = w["length"] / 2
                wf[k, W.SIDE] = 1.0 if w["inside"] else -1.0
        self.wf, self.wi, self.nwalls = wf, wi, nw
        n = self.state.n
        self.whist = np.zeros((n, max(nw, 1), 3))
        rolling = ROLLING_MODELS[self.scene.contact["rolling"]]
        self.wrhist = np.zeros((n, max(nw, 1), 3)) if rolling == 2 else np.zeros((0, 1, 3))
        self.wnb = np.zeros((n, max(nw, 1)), np.int32)
        self.wnn = np.zeros(n, np.int32)
        self.wall_speed = max([float(np.linalg.norm(w["velocity"])) for w in walls], default=0.0)

    def _build_params(self):
        sc = self.scene
        ip = np.zeros(K.NIP, np.int64)
        ip[K.I_CONTACT] = CONTACT_MODELS[sc.contact["model"]]
        ip[K.I_ROLLING] = ROLLING_MODELS[sc.contact["rolling"]]
        ip[K.I_NWALLS] = self.nwalls
        ip[K.I_MECH] = 1 if sc.simulation["mechanics"] else 0
        ip[K.I_NOWN] = self.state.n_owned
        fp = np.zeros(K.NFP)
        fp[K.F_DT] = self.dt
        fp[K.F_GX:K.F_GZ + 1] = sc.simulation["gravity"]
        fp[K.F_SKIN] = sc.simulation["neighbor_skin"]
        fp[K.F_VCHAR] = self.characteristic_velocity()
        fp[K.F_KTRATIO] = sc.contact["tangential_stiffness_ratio"]
        fp[K.F_LINKN] = sc.contact["normal_stiffness"]
        fp[K.F_ETAR] = sc.contact["rolling_damping"]
        fp[K.F_MAXOV] = sc.simulation["max_overlap_ratio"]
        fp[K.F_VWALL] = self.wall_speed
        self.ip, self.fp = ip, fp

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
        return 2.0 * self.rmax + self.reach + self.fp[K.F_SKIN]

    def per_particle_arrays(self):
        """Every array with one row per particle, by name (what migrates with a particle)."""
        st = self.state
        reg = {f"state.{f}": (st, f) for f in st.fields()}
        for k in ("whist", "wrhist", "wnb", "wnn"):
            reg[f"sim.{k}"] = (self, k)
        if getattr(self, "external_force", None) is not None:
            reg["sim.external_force"] = (self, "external_force")
        if self.thermal is not None:
            for k in ("Hw", "por", "qgen", "wage", "tf", "uf", "qsrc", "work"):
                reg[f"th.{k}"] = (self.thermal, k)
        return reg

    def _init_neighbors(self):
        if self.par is not None:
            self._par_rebuild(self.time, initial=True)
            return
        st = self.state
        n = st.n
        rolling = self.ip[K.I_ROLLING] == 2
        age = self.thermal.needs_age if self.thermal is not None else False
        nb0 = np.zeros((0, 1), np.int32)
        slots = 12
        for _ in range(2):  # second pass sizes the slots tightly (max count + 2)
            self.nb, self.nnb, self.hist, self.rhist, self.age, maxc = build_half_list(
                st.position, st.radius, n, n, self.lo, self.hi, self.periodic, self.lo, self.hi,
                self.periodic, self.reach,
                self.fp[K.F_SKIN], slots, nb0, np.zeros(0, np.int32), np.zeros((0, 1, 3)),
                np.zeros((0, 1, 3)), np.zeros((0, 1, 2)))
            if maxc + 2 >= slots:
                break
            slots = maxc + 2
        if rolling:
            self.rhist = np.zeros(self.hist.shape)
        if age:
            self.age = np.zeros(self.nb.shape + (2,))
        st.x_build[:] = st.position
        K.build_wall_list(st.position, st.radius, n, self.wf, self.wi, self.nwalls,
                          self.reach + self.fp[K.F_SKIN], self.time, self.wnb, self.wnn,
                          self.whist, self.wrhist)
        self.fp[K.F_TBUILD] = self.time

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
        vchar = self.fp[K.F_VCHAR]
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
        if sc.simulation["mechanics"] and ovmax > self.fp[K.F_MAXOV]:
            warnings.append(f"a Hertz impact at the characteristic velocity {vchar:.3g} m/s overlaps "
                            f"{ovmax:.3g} of the radius, above simulation.max_overlap_ratio = "
                            f"{self.fp[K.F_MAXOV]:g}: the overlap guard may stop the run (raise "
                            f"youngs_modulus, or the bound if such overlaps are acceptable)")
        if self.thermal is not None:
            rep.update(self.thermal.check())
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
        vchar = self.fp[K.F_VCHAR]
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
            estar = self.tab[K.T_ESTAR, k, k]
            th = min(th, hertz_collision_time(mmin / 2, rmin / 2, estar, vchar))
            for w in sc.walls:
                th = min(th, hertz_collision_time(mmin, rmin, self.tab[K.T_ESTAR, k, w["material"]], vchar))
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
        lists = self.nb.nbytes + self.nnb.nbytes + self.hist.nbytes + self.rhist.nbytes + self.age.nbytes
        if self.par is None:
            glo, ghi, gwrap = self.lo, self.hi, self.periodic
        else:
            glo, ghi, gwrap = self.par.grid_box(self)
        grid = grid_bytes(st.position, st.radius, st.n, glo, ghi, gwrap, self.reach, self.fp[K.F_SKIN])
        mem = st.memory_bytes() + lists + self.whist.nbytes + self.wrhist.nbytes + self.wnb.nbytes \
            + self.wnn.nbytes + self.Hd.nbytes + self.Hi.nbytes + self.rnear.nbytes
        return mem + lists + grid, lists + grid

    # ------------------------------------------------------------------ stepping
    def _compute_forces(self):
        st = self.state
        if self.thermal is not None:  # the initial force evaluation exchanges no heat
            saved = (self.thermal.tot.copy(), self.thermal.wtot.copy())
        maxov, i, j, nc = K.compute_forces(
            st.n, st.position, st.velocity, st.angular_velocity, st.radius, st.mass, st.material,
            st.force, st.torque, self._fext(), self.nb, self.nnb, self.hist, self.rhist,
            self.wf, self.wi, self.wnb, self.wnn, self.whist, self.wrhist, self.tab, self.ip, self.fp,
            self.lo, self.hi, self.periodic, self.time, self.age, self.Hd, self.Hi, self.rnear, self.TH,
            self._hon)
        if self.thermal is not None:
            self.thermal.tot[:], self.thermal.wtot[:] = saved
        self._nc2 = nc
        self.last_contacts = nc // 2
        return maxov

    @property
    def _hon(self):
        """The kernels' heat switch as a type: True with a [thermal] section, None without, so
        that Numba compiles a mechanics-only specialisation with the heat code removed
        (docs/benchmarks.md, "Cost of each mechanism": a run-time flag alone cost ~5 %)."""
        return True if self.thermal is not None else None

    def _fext(self):
        f = getattr(self, "external_force", None)
        return f if f is not None else np.zeros((0, 3))

    def _advance(self, nsteps):
        if self.par is not None:
            return self._advance_parallel(nsteps)
        st = self.state
        if not self._forces_ready:
            self._compute_forces()
            self._forces_ready = True
        res = K.advance(nsteps, self.step_count, st.n, st.position, st.velocity,
                        st.angular_velocity, st.radius, st.mass, st.inv_mass, st.inv_inertia,
                        st.material, st.force, st.torque, self._fext(), st.x_build,
                        self.nb, self.nnb, self.hist, self.rhist, self.age, self.wf, self.wi,
                        self.wnb, self.wnn, self.whist, self.wrhist, self.tab, self.ip, self.fp, self.lo, self.hi,
                        self.periodic, self.Hd, self.Hi, self.rnear, self.TH, self._hon)
        done, status, who, other, value, nc, nreb = res[:7]
        self.nb, self.nnb, self.hist, self.rhist, self.age, self.Hd, self.Hi, self.rnear = res[7:15]
        self.step_count += done
        self.time = self.step_count * self.dt
        if self.ip[K.I_MECH]:  # frozen packings keep the contact count of their set-up
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
                   f"beyond simulation.max_overlap_ratio = {self.fp[K.F_MAXOV]:g}. Lower time_step "
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
    def _par_rebuild(self, t, initial=False, rec=None, weights_from_list=True):
        """Exchange particles and ghosts with the other ranks, rebuild the neighbour and
        wall lists, bring the contact history back (dem.parallel.records)."""
        from .parallel import records
        from .thermal.heat import local_porosity, TI_LOCALPOR
        par = self.par
        st = self.state
        weights = None
        if not initial:
            nown = st.n_owned
            x = st.position[:nown]
            out = (~self.periodic) & ((x < self.lo) | (x > self.hi))
            if np.any(out) and self._pending is None:
                i, k = np.argwhere(out)[0]
                self._pending = (K.LEFT_DOMAIN, self._instability_message(K.LEFT_DOMAIN, int(i), -1,
                                                                          float(x[i, k])))
            if rec is None:
                rec = records.extract(st.id, self.nb, self.nnb, self.hist, self.rhist, self.age)
            if weights_from_list:
                weights = 1.0 + self.scene.parallel["pair_weight"] * self.nnb[:nown]
        resort_vor = par.sort_pending and self.thermal is not None and self.thermal.voronoi
        rec = par.exchange(self, rec, weights)
        n, nown = st.n, st.n_owned
        glo, ghi, gwrap = par.grid_box(self)
        slots = self.nb.shape[1] if not initial else 12
        e0 = np.zeros(0, np.int32)
        for _ in range(2):
            nb, nnb, hist, _r, _a, maxc = build_half_list(
                st.position, st.radius, n, nown, self.lo, self.hi, self.periodic, glo, ghi, gwrap,
                self.reach, self.fp[K.F_SKIN], slots, np.zeros((0, 1), np.int32), e0,
                np.zeros((0, 1, 3)), np.zeros((0, 1, 3)), np.zeros((0, 1, 2)))
            if not initial or maxc + 2 >= slots:
                break
            slots = maxc + 2
        rhist = np.zeros(hist.shape) if self.ip[K.I_ROLLING] == 2 else np.zeros((0, 1, 3))
        needs_age = self.thermal is not None and self.thermal.needs_age
        age = np.zeros(nb.shape + (2,)) if needs_age else np.zeros((0, 1, 2))
        records.restore(rec, st.id, nb, nnb, hist, rhist, age, par.key_base)
        self.nb, self.nnb, self.hist, self.rhist, self.age = nb, nnb, hist, rhist, age
        K.build_wall_list(st.position, st.radius, nown, self.wf, self.wi, self.nwalls,
                          self.reach + self.fp[K.F_SKIN], t, self.wnb, self.wnn, self.whist, self.wrhist)
        self.wnn[nown:] = 0
        st.x_build[:nown] = st.position[:nown]
        self.fp[K.F_TBUILD] = t
        self.ip[K.I_NOWN] = nown
        if self.thermal is not None and not initial:
            self.Hd, self.Hi, self.rnear = K.heat_slot_arrays(n, nb.shape[1], self.Hd, self.Hi, self.rnear)
            th = self.thermal
            if th.thi[TI_LOCALPOR] == 1:
                local_porosity(n, st.position, st.radius, nb, nnb, self.lo, self.hi, self.periodic, self.reach,
                               self.wf, self.wi, self.wnb, self.wnn, t, th.por, 0.2)
                par.forward(self, motion=False, porosity=True)
            elif resort_vor:
                th.update_porosity()
                par.forward(self, motion=False, porosity=True)
            self.TH = th.th_tuple()

    def _advance_parallel(self, nsteps):
        """The step of dem.step.advance, one step at a time with the ghost communication
        between the drift and the force evaluation (one Allreduce per step carries the
        rebuild decision and the previous step's stability status)."""
        from .thermal.heat import heat_step, cross_rates, TI_INTEG
        par = self.par
        self._expo_cross = self.thermal is not None and self.thermal.thi[TI_INTEG] != 0
        st = self.state
        if not self._forces_ready:
            self._compute_forces()
            self._forces_ready = True
        dt = self.dt
        fp = self.fp
        mech = bool(self.ip[K.I_MECH])
        heat = self.thermal is not None
        half_skin = 0.5 * fp[K.F_SKIN]
        done = 0
        for _ in range(nsteps):
            t = (self.step_count + 1) * dt
            need = 0.0
            if mech:
                maxd2 = K.kick_drift(st.n_owned, st.position, st.velocity, st.angular_velocity, st.force,
                                     st.torque, st.inv_mass, st.inv_inertia, st.x_build, self.lo, self.hi,
                                     self.periodic, dt)
                need = 1.0 if math.sqrt(maxd2) + fp[K.F_VWALL] * (t - fp[K.F_TBUILD]) > half_skin else 0.0
            code, need = par.flags(self._pending[0] if self._pending else 0.0, need)
            if code:
                self._raise_collective()
            if mech:
                if need:
                    self._par_rebuild(t)
                else:
                    par.forward(self, motion=True, temperature=heat)
                TH = self.TH
                maxov, wi_, wj_, nc = K.compute_forces(
                    st.n, st.position, st.velocity, st.angular_velocity, st.radius, st.mass, st.material,
                    st.force, st.torque, self._fext(), self.nb, self.nnb, self.hist, self.rhist,
                    self.wf, self.wi, self.wnb, self.wnn, self.whist, self.wrhist, self.tab, self.ip, fp,
                    self.lo, self.hi, self.periodic, t, self.age, self.Hd, self.Hi, self.rnear, TH, self._hon)
                self._nc2 = nc
                bad = K.kick(st.n_owned, st.velocity, st.angular_velocity, st.force, st.torque, st.inv_mass,
                             st.inv_inertia, dt)
                if self._pending is None:
                    if bad >= 0:
                        self._pending = (K.NONFINITE, self._instability_message(K.NONFINITE, bad, -1, 0.0))
                    elif maxov > fp[K.F_MAXOV]:
                        self._pending = (K.OVERLAP, self._instability_message(K.OVERLAP, wi_, wj_, maxov))
            elif heat:
                par.forward(self, motion=False, temperature=True)
            if heat:
                TH = self.TH
                if self._expo_cross:
                    cross_rates(st.n_owned, TH[K.H_CINV], self.nb, self.nnb, self.Hd, self.Hi, TH[K.H_WORK])
                    par.forward(self, motion=False, rate=True)
                badt = heat_step(st.n, st.n_owned, dt, t, TH[K.H_T], TH[K.H_CINV], TH[K.H_Q], st.velocity,
                                 st.radius, st.position, st.material, self.nb, self.nnb, self.Hd, self.Hi,
                                 self.rnear, self.wnb, self.wnn, TH[K.H_HW], TH[K.H_WTH], TH[K.H_WTAB],
                                 TH[K.H_TF], TH[K.H_UF], TH[K.H_POR], TH[K.H_QGEN], TH[K.H_QSRC],
                                 TH[K.H_SRCBOX], TH[K.H_TMAT], TH[K.H_GAS], TH[K.H_THI], TH[K.H_TOT],
                                 TH[K.H_WTOT], TH[K.H_WORK])
                if badt >= 0 and self._pending is None:
                    self._pending = (K.BAD_TEMPERATURE, self._instability_message(
                        K.BAD_TEMPERATURE, badt, -1, float(st.temperature[badt])))
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
        """Reorder particles by cell for cache locality; neighbour rows and every history
        follow, so the physics is unchanged."""
        if self.par is not None:  # done at the next exchange with the other ranks
            self.par.sort_pending = True
            return
        st = self.state
        cell = 2 * float(st.radius.max()) + self.reach + self.fp[K.F_SKIN]
        perm = sort_permutation(st.position, self.lo, self.hi, cell)
        inv = np.empty_like(perm)
        inv[perm] = np.arange(perm.size)
        st.permute(perm)
        nb = self.nb[perm]
        nnb = self.nnb[perm]
        mask = np.arange(nb.shape[1])[None, :] < nnb[:, None]
        nb = np.where(mask, inv[np.where(mask, nb, 0)], 0).astype(np.int32)
        self.nb, self.nnb = np.ascontiguousarray(nb), np.ascontiguousarray(nnb)
        self.hist = np.ascontiguousarray(self.hist[perm])
        if self.rhist.shape[0]:
            self.rhist = np.ascontiguousarray(self.rhist[perm])
        if self.age.shape[0]:
            self.age = np.ascontiguousarray(self.age[perm])
        self.whist = np.ascontiguousarray(self.whist[perm])
        self.wnb = np.ascontiguousarray(self.wnb[perm])
        self.wnn = np.ascontiguousarray(self.wnn[perm])
        if self.wrhist.shape[0]:
            self.wrhist = np.ascontiguousarray(self.wrhist[perm])
        if self.Hd.shape[0]:
            self.Hd = np.ascontiguousarray(self.Hd[perm])
        if self.Hi.shape[0]:
            self.Hi = np.ascontiguousarray(self.Hi[perm])
        if self.rnear.shape[0]:
            self.rnear = np.ascontiguousarray(self.rnear[perm])
        if self.thermal is not None:
            self.thermal.permute(perm)
            if self.thermal.voronoi and self.scene.simulation["mechanics"]:
                self.thermal.update_porosity()
            self.TH = self.thermal.th_tuple()
        if getattr(self, "external_force", None) is not None:
            self.external_force = np.ascontiguousarray(self.external_force[perm])

    def set_fluid(self, force=None, velocity=None, temperature=None, porosity=None):
        """Fluid data at each owned particle (rows of ``state``) for the next steps of a
        coupled run: force (N, drag + pressure gradient + buoyancy, added every step),
        gas velocity (m/s) and temperature (K) for convection, void fraction (replaces the
        locally measured porosity in the heat models)."""
        n = self.state.n
        k = self.state.n_owned
        if force is not None:
            if getattr(self, "external_force", None) is None or self.external_force.shape[0] != n:
                self.external_force = np.zeros((n, 3))
            self.external_force[:k] = force
            self.external_force[k:] = 0.0
        th = self.thermal
        if th is None:
            return
        if velocity is not None:
            th.uf[:k] = velocity
        if temperature is not None:
            th.tf[:k] = temperature
        if porosity is not None:
            th.por[:k] = porosity
            th.local_porosity = False
            from .thermal.heat import TI_LOCALPOR
            th.thi[TI_LOCALPOR] = 0  # the CFD void fraction is used instead
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
        return max_overlap_ratio(st.n, st.position, st.radius, self.nb, self.nnb, self.lo, self.hi,
                                 self.periodic, self.wf, self.wi, self.nwalls, self.time)

    def history_columns(self):
        cols = ["time", "kinetic_energy", "rotational_energy", "contacts", "max_overlap_ratio"]
        if self.thermal is not None:
            cols += self.thermal.history_columns()
        return cols

    def particle_fields(self):
        st = self.state
        n = st.n_owned
        f = {"id": st.id[:n].astype(np.float64), "radius": st.radius[:n],
             "material": st.material[:n].astype(np.float64), "velocity": st.velocity[:n],
             "angular_velocity": st.angular_velocity[:n]}
        if self.thermal is not None:
            f["temperature"] = st.temperature[:n]
            f["heat_rate"] = st.heat_rate[:n]
        if self.par is not None:
            f["rank"] = np.full(n, float(self.par.rank))
        return f

    def _gather_by_id(self, arrays):
        """Owned rows of every rank, concatenated and ordered by particle id, on the root
        (None elsewhere); a serial run just orders its rows."""
        parts = [arrays] if self.par is None else self.par.gather(arrays)
        return None if parts is None else self._gather_by_id_parts(parts)

    def final_arrays(self):
        """Per-particle results ordered by id (collective; None on ranks other than the root)."""
        st = self.state
        n = st.n_owned
        out = dict(id=st.id[:n], position=st.position[:n], velocity=st.velocity[:n],
                   angular_velocity=st.angular_velocity[:n], radius=st.radius[:n],
                   material=st.material[:n])
        if self.thermal is not None:
            out["temperature"] = st.temperature[:n]
            out["heat_rate"] = st.heat_rate[:n]
        out = self._gather_by_id(out)
        if out is not None:
            out["time"] = np.float64(self.time)
        return out

    # ------------------------------------------------------------------ checkpoints
    @staticmethod
    def _ck_key(name):
        kind, attr = name.split(".", 1)
        return {"state": "state_", "sim": "", "th": "th_"}[kind] + attr

    def checkpoint_arrays(self):
        """Everything needed to continue the run. A serial checkpoint holds the neighbour
        list and its history slots (bit-exact restart); every checkpoint also holds the
        per-particle arrays ordered by id and the contact history as id-keyed records, so
        that any number of ranks can continue it (collective; None off the root)."""
        from .parallel import records
        st = self.state
        n = st.n_owned
        rec = records.extract(st.id, self.nb, self.nnb, self.hist, self.rhist, self.age)
        rec = {f"rec_{k}": v for k, v in rec.items() if v is not None}
        common = dict(fp_tbuild=np.float64(self.fp[K.F_TBUILD]), step_count=np.int64(self.step_count),
                      dt=np.float64(self.dt), forces_ready=np.bool_(self._forces_ready),
                      scene_file=np.str_(os.path.abspath(self.scene.file)),
                      ranks=np.int64(1 if self.par is None else self.par.size))
        if self.par is None:
            arr = {f"state_{k}": getattr(st, k) for k in st.fields()}
            arr.update(nb=self.nb, nnb=self.nnb, hist=self.hist, rhist=self.rhist, age=self.age,
                       whist=self.whist, wrhist=self.wrhist, wnb=self.wnb, wnn=self.wnn,
                       Hd=self.Hd, Hi=self.Hi, rnear=self.rnear, **common, **rec)
            if self.thermal is not None:
                arr.update(self.thermal.checkpoint_arrays())
            return arr
        local = {}
        empties = {}  # arrays the run does not use: zero-row placeholders on every rank
        for name, (obj, attr) in self.per_particle_arrays().items():
            if name == "sim.external_force":
                continue
            a = getattr(obj, attr)
            if name in self.par.absent:
                empties[self._ck_key(name)] = a
            else:  # a rank that owns no particle contributes zero rows
                local[self._ck_key(name)] = a[:n]
        local["id"] = st.id[:n]
        parts = self.par.gather((local, rec))  # records travel beside, not ordered by id
        extra = {}
        if self.thermal is not None:
            extra = dict(th_tot=self.par.allsum(self.thermal.tot), th_wtot=self.par.allsum(self.thermal.wtot))
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
        arr.update(empties, **common, **extra)
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
            self._root_write(lambda: ckpt.write(path, arr, record))

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
        if self.par is not None or int(z["ranks"]) != 1 or "nb" not in z.files or plan.rebuild:
            self._load_portable(path, z)
        else:
            self._load_serial(z)
        if plan.recompute_forces:
            self._recompute_forces_keeping_history()
        self.restart_changes = plan.applied
        if self.is_root:
            for line in plan.applied:
                print(f"restart: applied {line}", flush=True)

    def _load_serial(self, z):
        """The serial layout: every array as written (bit-exact continuation)."""
        st = self.state
        for k in st.fields():
            setattr(st, k, np.ascontiguousarray(z[f"state_{k}"]))
        for k in ("nb", "nnb", "hist", "rhist", "age", "whist", "wrhist", "wnb", "wnn", "Hd", "Hi", "rnear"):
            setattr(self, k, np.ascontiguousarray(z[k]))
        self.fp[K.F_TBUILD] = float(z["fp_tbuild"])
        self.step_count = int(z["step_count"])
        self.time = self.step_count * self.dt
        self._forces_ready = bool(z["forces_ready"])
        if self.thermal is not None:
            self.thermal.load_checkpoint(z)
            self.TH = self.thermal.th_tuple()

    def _recompute_forces_keeping_history(self):
        """Forces at the restart time with the edited physics (masses, tables, walls,
        gravity); the contact springs, ages and temperatures stay as in the checkpoint so
        that the next step increments them once, as an uninterrupted run does (collective
        in a parallel run: the ghosts were exchanged by the loader)."""
        keep = [a.copy() for a in (self.hist, self.rhist, self.whist, self.wrhist, self.age)]
        st = self.state
        th = self.thermal
        if th is not None:
            tkeep = (st.temperature.copy(), st.heat_rate.copy())
        self._compute_forces()
        self.hist[...], self.rhist[...], self.whist[...], self.wrhist[...], self.age[...] = keep
        if th is not None:
            st.temperature[:], st.heat_rate[:] = tkeep
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
        self.external_force = None
        for name, (obj, attr) in self.per_particle_arrays().items():
            key = self._ck_key(name)
            if name == "th.work":  # scratch
                obj.work = np.zeros((rows.size, 3))
                continue
            if key not in z.files:
                raise SimulationError(f"{path}: checkpoint lacks {key!r} (thermal or contact settings changed?)")
            a = z[key]
            setattr(obj, attr, np.ascontiguousarray(a[rows]) if a.shape[0] else np.ascontiguousarray(a))
        st.n_owned = rows.size
        st.n_ghost = 0
        self.ip[K.I_NOWN] = rows.size
        rec = {k: (z[f"rec_{k}"] if f"rec_{k}" in z.files else None) for k in records.FIELDS}
        if rec["a"] is None:
            rec = None
        self.step_count = int(z["step_count"])
        self.time = self.step_count * self.dt
        self._forces_ready = bool(z["forces_ready"])
        th = self.thermal
        if th is not None:
            root = self.is_root
            th.tot = np.ascontiguousarray(z["th_tot"]) if root else np.zeros_like(z["th_tot"])
            th.wtot = np.ascontiguousarray(z["th_wtot"]) if root else np.zeros_like(z["th_wtot"])
        if self.par is not None:
            self._par_rebuild(self.time, rec=rec, weights_from_list=False)
        else:
            self._init_neighbors()
            records.restore(rec, st.id, self.nb, self.nnb, self.hist, self.rhist, self.age,
                            int(st.id.max(initial=0)) + 1)
        if th is not None:
            self.Hd, self.Hi, self.rnear = th.slot_arrays(self.nb.shape[1])
            self.TH = th.th_tuple()
            th.update_porosity()
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

    _root_write = root_write  # the name write_checkpoint and write_vtk call

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
            self._root_write(lambda: vtk.write(self.time, self.step_count, pos, f))
