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
from .neighbors import build_half_list, sort_permutation
from .output import History, VTKSeries, save_npz
from .state import State
from . import step as K


class SimulationError(RuntimeError):
    """The run went unstable or cannot continue; the message says who, when and what to change."""


class Simulation:
    def __init__(self, scene):
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
        self._init_neighbors()
        if self.thermal is not None:
            self.TH = self.thermal.th_tuple()
            self.Hd, self.Hi, self.rnear = self.thermal.slot_arrays(self.nb.shape[1])
            self.thermal.update_porosity()
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

    def _init_neighbors(self):
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
        rep = {"particles": st.n, "walls": self.nwalls, "materials": len(sc.materials)}
        rep["mass_total"] = float(st.mass.sum())
        rep["mass_min"] = float(st.mass.min())
        rep["mass_max"] = float(st.mass.max())
        rep["radius_min"] = float(st.radius.min())
        rep["radius_max"] = float(st.radius.max())
        vchar = self.fp[K.F_VCHAR]
        tr, th = math.inf, math.inf
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
        # largest Hertz overlap of an impact at the characteristic velocity (smallest, softest particle)
        ovmax = 0.0
        for k, m in enumerate(sc.materials):
            sel = st.material == k
            if not np.any(sel):
                continue
            rmin = float(st.radius[sel].min())
            mmin = 4 / 3 * math.pi * rmin ** 3 * m["density"]
            estar = self.tab[K.T_ESTAR, k, k]
            d = (15 * (mmin / 2) * vchar ** 2 / (16 * estar * math.sqrt(rmin / 2))) ** 0.4
            ovmax = max(ovmax, d / rmin)
        rep["impact_overlap_ratio"] = ovmax
        rep["rayleigh_time"] = tr
        rep["hertz_time"] = th
        rep["characteristic_velocity"] = vchar
        rep["dt"] = self.dt
        rep["dt_over_rayleigh"] = self.dt / tr
        rep["dt_over_hertz"] = self.dt / th
        rep["steps"] = int(round(self.end_time / self.dt))
        mem = st.memory_bytes() + self.nb.nbytes + self.nnb.nbytes + self.hist.nbytes + self.rhist.nbytes \
            + self.whist.nbytes + self.wrhist.nbytes + self.age.nbytes + self.Hd.nbytes + self.Hi.nbytes \
            + self.rnear.nbytes
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
        if self.thermal is None:
            skipped.append("heat transfer: no [thermal] section (no thermal arrays, no thermal cost)")
        else:
            r, s = self.thermal.models_report()
            runs += r
            skipped += s
        return runs, skipped

    # ------------------------------------------------------------------ stepping
    def _compute_forces(self):
        st = self.state
        if self.thermal is not None:  # the initial force evaluation exchanges no heat
            saved = (self.thermal.tot.copy(), self.thermal.wtot.copy())
        maxov, i, j, nc = K.compute_forces(
            st.n, st.position, st.velocity, st.angular_velocity, st.radius, st.mass, st.material,
            st.force, st.torque, self._fext(), self.nb, self.nnb, self.hist, self.rhist,
            self.wf, self.wi, self.wnb, self.wnn, self.whist, self.wrhist, self.tab, self.ip, self.fp,
            self.lo, self.hi, self.periodic, self.time, self.age, self.Hd, self.Hi, self.rnear, self.TH)
        if self.thermal is not None:
            self.thermal.tot[:], self.thermal.wtot[:] = saved
        self.last_contacts = nc // 2
        return maxov

    def _fext(self):
        f = getattr(self, "external_force", None)
        return f if f is not None else np.zeros((0, 3))

    def _advance(self, nsteps):
        st = self.state
        if not self._forces_ready:
            self._compute_forces()
            self._forces_ready = True
        res = K.advance(nsteps, self.step_count * self.dt, st.n, st.position, st.velocity,
                        st.angular_velocity, st.radius, st.mass, st.inv_mass, st.inv_inertia,
                        st.material, st.force, st.torque, self._fext(), st.x_build,
                        self.nb, self.nnb, self.hist, self.rhist, self.age, self.wf, self.wi,
                        self.wnb, self.wnn, self.whist, self.wrhist, self.tab, self.ip, self.fp, self.lo, self.hi,
                        self.periodic, self.Hd, self.Hi, self.rnear, self.TH)
        done, status, who, other, value, nc, nreb = res[:7]
        self.nb, self.nnb, self.hist, self.rhist, self.age, self.Hd, self.Hi, self.rnear = res[7:15]
        self.step_count += done
        self.time = self.step_count * self.dt
        if self.ip[K.I_MECH]:  # frozen packings keep the contact count of their set-up
            self.last_contacts = nc // 2
        if status != K.OK:
            self._instability(status, who, other, value)
        return done

    def _instability(self, status, i, j, value):
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
        raise SimulationError(msg)

    def sort_particles(self):
        """Reorder particles by cell for cache locality; neighbour rows and every history
        follow, so the physics is unchanged."""
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
        """Fluid data at each particle (current order of ``state``) for the next steps of a
        coupled run: force (N, drag + pressure gradient + buoyancy, added every step),
        gas velocity (m/s) and temperature (K) for convection, void fraction (replaces the
        locally measured porosity in the heat models)."""
        n = self.state.n
        if force is not None:
            if getattr(self, "external_force", None) is None:
                self.external_force = np.zeros((n, 3))
            self.external_force[:] = force
        th = self.thermal
        if th is None:
            return
        if velocity is not None:
            th.uf[:] = velocity
        if temperature is not None:
            th.tf[:] = temperature
        if porosity is not None:
            th.por[:] = porosity
            th.local_porosity = False
            from .thermal.heat import TI_LOCALPOR
            th.thi[TI_LOCALPOR] = 0  # the CFD void fraction is used instead

    def warmup(self):
        """Compile (or load from Numba's cache) the kernels; returns seconds spent."""
        t0 = time.perf_counter()
        self._advance(0)
        self.compile_seconds = time.perf_counter() - t0
        return self.compile_seconds

    def step(self, nsteps=1):
        return self._advance(nsteps)

    # ------------------------------------------------------------------ stats / output
    def history_row(self):
        st = self.state
        et, er = st.kinetic_energy()
        maxov = self._overlap_stats()
        row = dict(time=self.time, kinetic_energy=et, rotational_energy=er,
                   contacts=self.last_contacts, max_overlap_ratio=maxov)
        if self.thermal is not None:
            row.update(self.thermal.history_row())
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
        return f

    def final_arrays(self):
        st = self.state
        n = st.n_owned
        order = np.argsort(st.id[:n], kind="stable")
        out = dict(id=st.id[:n][order], position=st.position[:n][order], velocity=st.velocity[:n][order],
                   angular_velocity=st.angular_velocity[:n][order], radius=st.radius[:n][order],
                   material=st.material[:n][order], time=np.float64(self.time))
        if self.thermal is not None:
            out["temperature"] = st.temperature[:n][order]
            out["heat_rate"] = st.heat_rate[:n][order]
        return out

    # ------------------------------------------------------------------ checkpoints
    def checkpoint_arrays(self):
        st = self.state
        arr = {f"state_{k}": getattr(st, k) for k in st.fields()}
        arr.update(nb=self.nb, nnb=self.nnb, hist=self.hist, rhist=self.rhist, age=self.age,
                   whist=self.whist, wrhist=self.wrhist, wnb=self.wnb, wnn=self.wnn,
                   Hd=self.Hd, Hi=self.Hi, rnear=self.rnear,
                   fp_tbuild=np.float64(self.fp[K.F_TBUILD]), step_count=np.int64(self.step_count),
                   dt=np.float64(self.dt), forces_ready=np.bool_(self._forces_ready),
                   scene_file=np.str_(os.path.abspath(self.scene.file)))
        if self.thermal is not None:
            arr.update(self.thermal.checkpoint_arrays())
        return arr

    def write_checkpoint(self, path):
        save_npz(path, **self.checkpoint_arrays())

    def load_checkpoint(self, path):
        try:
            z = np.load(path)
        except Exception as exc:  # noqa: BLE001
            raise SimulationError(f"{path}: cannot read checkpoint: {exc}") from None
        with z:
            if float(z["dt"]) != self.dt:
                raise SimulationError(f"{path}: checkpoint was written with time_step {float(z['dt'])}, "
                                      f"the scene has {self.dt}; restart with the same time_step")
            st = self.state
            if int(z["state_id"].size) != st.n:
                raise SimulationError(f"{path}: checkpoint holds {z['state_id'].size} particles, "
                                      f"the scene {st.n}")
            for k in st.fields():
                key = f"state_{k}"
                if key not in z.files:
                    raise SimulationError(f"{path}: checkpoint lacks {k!r} (thermal settings changed?)")
                setattr(st, k, np.ascontiguousarray(z[key]))
            for k in ("nb", "nnb", "hist", "rhist", "age", "whist", "wrhist", "wnb", "wnn", "Hd", "Hi", "rnear"):
                setattr(self, k, np.ascontiguousarray(z[k]))
            self.fp[K.F_TBUILD] = float(z["fp_tbuild"])
            self.step_count = int(z["step_count"])
            self.time = self.step_count * self.dt
            self._forces_ready = bool(z["forces_ready"])
            if self.thermal is not None:
                self.thermal.load_checkpoint(z)
                self.TH = self.thermal.th_tuple()

    # ------------------------------------------------------------------ run
    def run(self, end_time=None, out_dir=None, progress=None, restart=None, log=None):
        """Run to ``end_time`` (default: the scene's). Writes output when out_dir is given."""
        from .progress import Progress
        if restart is not None:
            self.load_checkpoint(restart)
        end_time = self.end_time if end_time is None else float(end_time)
        end_step = int(round(end_time / self.dt))
        sim = self.scene.simulation
        out_every = max(1, int(round(sim["output_interval"] / self.dt)))
        ck = sim["checkpoint_interval"]
        ck_every = int(round(ck / self.dt)) if ck > 0 else 0
        sort_every = sim["sort_interval"]
        if self.compile_seconds is None:
            self.warmup()
        writers = None
        if out_dir is not None:
            os.makedirs(out_dir, exist_ok=True)
            keep = self.time if restart is not None else None
            writers = dict(hist=History(os.path.join(out_dir, "history.csv"), self.history_columns(), keep),
                           vtk=VTKSeries(out_dir) if self.scene.output["vtk"] else None)
            if self.step_count == 0 or restart is None:
                self._write_output(writers)
        prog = Progress(self.step_count, end_step, self.dt, self.state.n, self.compile_seconds,
                        enabled=progress, stream=log or sys.stderr)
        try:
            while self.step_count < end_step:
                s = self.step_count
                nxt = end_step
                for every in (out_every, ck_every, sort_every):
                    if every:
                        nxt = min(nxt, (s // every + 1) * every)
                self._advance(nxt - s)
                s = self.step_count
                if sort_every and s % sort_every == 0:
                    self.sort_particles()
                if writers is not None and s % out_every == 0:
                    self._write_output(writers)
                if writers is not None and ck_every and s % ck_every == 0:
                    self.write_checkpoint(os.path.join(out_dir, "checkpoint.npz"))
                prog.update(self.step_count)
        except SimulationError:
            if out_dir is not None:
                save_npz(os.path.join(out_dir, "failed_state.npz"), **self.final_arrays())
            prog.close()
            raise
        prog.close()
        if writers is not None:
            if self.step_count % out_every != 0:
                self._write_output(writers)
            save_npz(os.path.join(out_dir, "final.npz"), **self.final_arrays())
            self.write_checkpoint(os.path.join(out_dir, "checkpoint.npz"))
        self.wall_seconds = prog.elapsed
        return self

    def _write_output(self, writers):
        row = self.history_row()
        writers["hist"].add(row)
        if writers["vtk"] is not None:
            st = self.state
            writers["vtk"].write(self.time, self.step_count, st.position[:st.n_owned], self.particle_fields())
