"""ThermalModel: the thermal part of a Simulation (arrays, tables, reports, output).

Built only when the scene has a [thermal] section: a scene without heat allocates no
thermal arrays and its step runs no heat code (the kernel tests one flag per step).
"""
import math

import numpy as np

from . import registry as R
from ..contact.damping import mixed_tables
from .contact_radius import hertz_radius_factor
from .convection import BIOT_LUMPED
from .heat import TI, TF, TOT, WT, local_porosity

MECHANISMS = ("direct", "indirect", "convection", "radiation", "generation", "sources")
INTEGRAL_INDIRECT = ("cheng_1999_voronoi_a", "gan_2016_voronoi_a", "rong_horio_1999_surrounding_layer",
                     "musser_2011_surrounding_layer")


def zero_wall_totals(st, nw):
    """Every per-wall total of dem.schema (the checkpointed wall arrays: all paths, gas gap,
    radiation) at zero for nw walls."""
    from .. import schema as S
    for f in S.of("wall"):
        if f.checkpoint:
            setattr(st, f.name, np.zeros(nw))


def no_heat_tables(st):
    """The tables and parameters of a scene without heat (dem.schema rows of owner wall, table
    and param): tiny arrays of the types a scene with heat has, so one kernel serves both."""
    nw = st.walls
    thi = np.full(TI.SIZE, -1, np.int64)
    thi[TI.heat] = 0
    st.thi, st.thf, st.tmat, st.gas = thi, np.zeros(TF.SIZE), np.zeros((1, R.N_TPROP)), np.zeros(R.N_GAS)
    st.ereal, st.keff, st.rcf = np.zeros((1, 1)), np.zeros((1, 1)), np.ones((1, 1))
    st.wth, st.wtab = np.zeros((nw, WT.SIZE)), np.zeros((nw, 1, 2))
    zero_wall_totals(st, nw)
    st.srcbox, st.tot = np.zeros((0, 7)), np.zeros(TOT.SIZE)


class ThermalModel:
    """The thermal configuration of a run: switches, tables, reports and output columns. The
    arrays themselves live in the run's state (dem.state.State, declared in dem.schema)."""

    def __init__(self, scene, state, rmax):
        self.scene = scene
        sc = scene
        th = sc.thermal
        self.cfg = th
        st = state
        self.state = state
        n = st.n
        mats = [dict((k, m[k]) for k in R.MATERIAL_KEYS if k in m) for m in sc.materials]
        self.tmat, self.gas, _ = R.build_tables(mats, th["gas"])
        st.enable_thermal(th["temperature"], self.tmat[:, R.CP])
        thi = np.full(TI.SIZE, -1, np.int64)
        thi[TI.heat] = 1
        thi[TI.direct] = th["direct_id"]
        thi[TI.cr] = th["cr_id"]
        thi[TI.corr] = th["corr_id"]
        thi[TI.indirect] = th["indirect_id"]
        thi[TI.conv] = th["convection_id"]
        thi[TI.rad] = th["radiation_id"]
        thi[TI.fric] = th["friction_id"] if sc.simulation["mechanics"] else -1
        thi[TI.part] = th["partition_id"]
        thi[TI.integ] = th["integrator_id"]
        # per-contact history (contact age and impact speed) when a selected model's record asks
        self.needs_age = R.history_width({m: th[m] for m in ("direct", "indirect", "convection",
                                                             "radiation")}) > 0
        thi[TI.age] = 1 if self.needs_age else 0
        uses_por = th["indirect_id"] >= 0 or th["convection_id"] >= 0 or th["radiation"] == "zhou_2009"
        self.local_porosity = uses_por and th["porosity"] in ("local", "voronoi")
        self.voronoi = uses_por and th["porosity"] == "voronoi"
        # the kernel re-measures the local porosity at each neighbour rebuild; the Voronoi
        # porosity is computed in Python at start-up and at each spatial reordering
        thi[TI.localpor] = 1 if (self.local_porosity and not self.voronoi) else 0
        # [output] heat_by_mechanism: the heat step sums every mechanism (the force loop stores
        # the conductances; its fused sum has no column per mechanism)
        split = bool(getattr(sc, "output", {}).get("heat_by_mechanism"))
        per_pair = split or bool(getattr(sc, "output", {}).get("contacts"))   # (the network's heat flows too)
        thi[TI.fused] = 1 if (sc.simulation["mechanics"] and th["integrator"] == "euler" and not per_pair) else 0
        from .wall_heat import radiating_walls
        thi[TI.wrad] = 1 if any(radiating_walls(sc)) else 0
        thi[TI.cg_own] = 1 if th["parcel_heat"] == "own" else 0
        self.thi = thi
        thf = np.zeros(TF.SIZE)
        thf[TF.dfactor] = th["direct_factor"]
        thf[TF.radrange] = self.gas[R.RAD_RANGE]
        thf[TF.ct] = th["impact_ct"]
        thf[TF.cn] = th["impact_cn"]
        thf[TF.chi] = th["chi"]
        self.thf = thf
        # real effective modulus per material pair (softened-stiffness corrections): the contact
        # law's E* formula on the real Young's moduli
        self.ereal = mixed_tables([dict(m, youngs_modulus=m.get("real_youngs_modulus", m["youngs_modulus"]))
                                   for m in sc.materials])["estar"]
        from .direct import series_conductivity
        k = self.tmat[:, R.K_COND]
        nm = len(k)
        self.keff = np.array([[series_conductivity(k[a], k[b]) for b in range(nm)] for a in range(nm)]).reshape(nm, nm)
        # the pair constant of a contact-radius correction, rc = rcf sqrt(R* delta) under the Hertz
        # law (the lean contact loops: no cube root per contact; dem.step.full_form)
        estar = mixed_tables(sc.materials)["estar"]   # the contact law's E* (dem.world.pair_tables)
        self.rcf = np.array([[hertz_radius_factor(thi[TI.corr], estar[a, b], self.ereal[a, b]) for b in range(nm)]
                             for a in range(nm)]).reshape(nm, nm)
        # reach of the neighbour list: the largest of the selected models' records (indirect
        # cut-off, radiation range, in radii), and one radius for the local porosity
        selected = {m: th[m] for m in ("direct", "indirect", "convection", "radiation")}
        reach = R.neighbour_reach(selected, self.gas, rmax)
        if self.local_porosity:
            reach = max(reach, rmax)
        self.reach = reach
        # walls
        from ..contact.walls import wall_rows
        _, row_wall = wall_rows(sc.walls)   # a mesh wall is several rows, each with its condition
        nw = max(row_wall.size, 1)
        wth = np.zeros((nw, WT.SIZE))
        ntab = max([len(w["table"]) for w in th["walls"] if w["table"] is not None], default=1)
        wtab = np.zeros((nw, ntab, 2))
        for k, kw in enumerate(row_wall):
            w = th["walls"][kw]
            wth[k, WT.cond] = w["cond_id"]
            wth[k, WT.t] = w["temperature"]
            wth[k, WT.q] = w["heat_flux"]
            wth[k, WT.emis] = w["emissivity"]
            if w["table"] is not None:
                wth[k, WT.ntab] = len(w["table"])
                wtab[k, :len(w["table"])] = w["table"]
        qsrc = np.zeros(n)
        boxes = []
        for s in th["sources"]:
            if "power" in s:
                # W per real particle: a parcel holds cg^3 of them
                sel = st.group == s["group"]
                scaled = st.cg.shape[0] and th["parcel_heat"] == "scaled"
                qsrc[sel] += s["power"] * (st.cg[sel] ** 3 if scaled else 1.0)
            else:
                boxes.append(list(s["min"]) + list(s["max"]) + [s["power_density"]])
        st.enable(heat=True, contact_age=self.needs_age, friction_heat=bool(thi[TI.fric] >= 0),
                  group_sources=bool(np.any(qsrc != 0)), indirect=bool(thi[TI.indirect] >= 0),
                  radiation=bool(thi[TI.rad] >= 0), heat_output=split)
        st.wth, st.wtab = wth, wtab
        zero_wall_totals(st, nw)
        st.thi, st.thf, st.tmat, st.gas, st.ereal, st.keff = thi, thf, self.tmat, self.gas, self.ereal, self.keff
        st.rcf = self.rcf
        st.srcbox, st.tot = np.array(boxes, float).reshape(-1, 7), np.zeros(TOT.SIZE)
        st.por[:], st.tf[:], st.uf[:] = self.gas_at_start()
        if st.qsrc.shape[0]:
            st.qsrc[:] = qsrc
        self.E0 = None
        self.auto = None   # auto's choice on a frozen packing (choose_integrator)

    def gas_at_start(self):
        """(porosity, gas temperature, gas velocity) a particle starts with: the scene's global
        porosity and [gas] (gas temperature 0 without one); the local porosity, the Voronoi cells
        and a coupled run's gas replace them."""
        T_f = self.gas[R.T_F]
        return self.gas[R.POROSITY_GLOBAL], T_f if math.isfinite(T_f) else 0.0, self.cfg["gas_velocity"]

    # -------------------------------------------------------------- run totals
    @property
    def tot(self):
        """Heat per mechanism since the start (J; slots: dem.thermal.heat TOT)."""
        return self.state.tot

    @property
    def wtot(self):
        """Heat through each wall since the start (J)."""
        return self.state.wtot

    @property
    def wth(self):
        return self.state.wth

    def update_porosity(self, time):
        """Local (or Voronoi) porosity of every particle at ``time`` (after a build or a sort)."""
        if not self.local_porosity:
            return
        st = self.state
        P, C, W, _, prm = st.bundles()
        local_porosity(P, C, W, prm, st.n, self.reach, time, 0.2)
        if self.voronoi:
            from .voronoi import voronoi_porosity
            pv = voronoi_porosity(st.position, st.radius, st.lo, st.hi)
            ok = np.isfinite(pv)
            st.por[ok] = np.clip(pv[ok], 0.2, 1.0)

    def convection_h(self):
        """Per-particle convective conductance h A (W/K) with the current fluid data."""
        from .heat import convection_conductances
        st = self.state
        out = np.zeros(st.n)
        if self.thi[TI.conv] >= 0:
            cg = st.cg if self.thi[TI.cg_own] == 0 else st.cg[:0]
            convection_conductances(st.n, st.velocity, st.radius, cg, st.uf, st.por, self.gas,
                                    int(self.thi[TI.conv]), out)
        return out

    # -------------------------------------------------------------- reports
    def mechanism_columns(self):
        """The columns of P.qmech (dem.thermal.heat.QM) of the mechanisms this scene runs: the
        [output] heat_by_mechanism fields it writes (the others stay zero)."""
        from .heat import QM
        thi, st = self.thi, self.state
        cols = []
        if thi[TI.direct] >= 0:
            cols.append(QM.direct)
        if thi[TI.indirect] >= 0:
            cols.append(QM.indirect)
        if st.wth.shape[0] and np.any(st.wth[:, WT.cond] != 0.0):
            cols.append(QM.wall)
        if thi[TI.conv] >= 0:
            cols.append(QM.conv)
        if thi[TI.rad] >= 0:
            cols.append(QM.rad)
        if thi[TI.fric] >= 0:
            cols.append(QM.gen)
        if st.qsrc.shape[0] or st.srcbox.shape[0]:
            cols.append(QM.src)
        return cols

    def critical_step(self):
        """Thermal critical step rho c R / k of the particles (smallest), ref 002."""
        st = self.state
        k = self.tmat[st.material, R.K_COND]
        rho = self.tmat[st.material, R.DENSITY]
        c = self.tmat[st.material, R.CP]
        return float(np.min(rho * c * st.radius / k))

    def network_limit(self):
        """Euler stability limit of the conduction network: min_i C_i / sum_j H_ij."""
        st = self.state
        hsum = np.zeros(st.n)
        H = st.Hd + (st.Hi if st.Hi.shape[0] == st.n else 0.0)
        mask = np.arange(H.shape[1])[None, :] < st.nnb[:, None]
        H = np.where(mask, H, 0.0)
        np.add.at(hsum, np.repeat(np.arange(st.n), H.shape[1]), H.ravel())
        np.add.at(hsum, st.nb.ravel()[mask.ravel()], H.ravel()[mask.ravel()])
        wmask = (np.arange(st.Hw.shape[1])[None, :] < st.wnn[:, None]) & (st.wth[st.wnb, WT.cond] == 1.0)
        hsum += (st.Hw * wmask).sum(1)
        C = 1.0 / st.inv_heat_capacity
        with np.errstate(divide="ignore"):
            lim = np.where(hsum > 0, C / hsum, np.inf)
        return float(lim.min())

    def radiation_limit(self):
        """(C / (4 eps sigma A T_max^3) of the particles (s, smallest), T_max): the explicit
        radiation step limit at the hottest temperature in play (walls, particles, gas)."""
        from .radiation import SIGMA_SB
        st = self.state
        tw = [w["temperature"] for w in self.cfg["walls"]] + [float(np.max(st.temperature))]
        if np.isfinite(self.gas[R.T_F]):
            tw.append(self.gas[R.T_F])
        tmax = max(tw)
        eps_r = self.tmat[st.material, R.EMISSIVITY]
        C = 1.0 / st.inv_heat_capacity
        with np.errstate(divide="ignore"):
            rl = float(np.min(C / (4 * eps_r * SIGMA_SB * 4 * np.pi * st.radius ** 2 * tmax ** 3), initial=np.inf))
        return rl, tmax

    def choose_integrator(self, dt, par=None):
        """``integrator = "auto"`` on a frozen packing, once its conductances are computed: the
        integrator whose error at this step is smallest (dem.thermal.step_error.choose) from the
        step, the network limit min C_i / sum H_ij and the radiation limit (over every rank,
        ``par``); sets the kernel switch and self.auto (integrator, reason, expected errors)."""
        if not self.cfg.get("integrator_auto") or self.scene.simulation["mechanics"]:
            return
        from .scene import INTEGRATORS
        from .step_error import choose
        lim = self.network_limit()
        rl = self.radiation_limit()[0] if self.thi[TI.rad] >= 0 else math.inf
        if par is not None:
            lim, rl = par.allmin(lim), par.allmin(rl)
        self.auto = choose(dt, lim, rl)
        name = self.auto["integrator"]
        self.cfg["integrator"] = name
        self.cfg["integrator_id"] = INTEGRATORS[name]
        self.thi[TI.integ] = INTEGRATORS[name]

    def check(self, dt, compute_forces):
        """Thermal time-step report and warnings; ``compute_forces()`` evaluates the
        conductances of every slot at the current state (the network limit needs them)."""
        st = self.state
        rep = {}
        tcrit = self.critical_step()
        rep["thermal_critical_step"] = tcrit
        rep["thermal_step"] = dt
        rep["thermal_step_ratio"] = dt / tcrit
        warnings = []
        # conductances stored per slot (the fused Euler path does not store them)
        fused = self.thi[TI.fused]
        saved = (st.heat_totals(), st.heat_rate.copy(), st.force.copy(), st.torque.copy())
        self.thi[TI.fused] = 0
        compute_forces()
        self.thi[TI.fused] = fused
        st.restore_heat_totals(saved[0])
        st.heat_rate[:], st.force[:], st.torque[:] = saved[1:]
        lim = self.network_limit()
        rep["network_step_limit"] = lim
        if self.cfg["integrator"] == "euler" and dt > lim:
            warnings.append(f"euler thermal step {dt:.3g} s exceeds the network stability limit "
                            f"min C_i/sum H_ij = {lim:.3g} s: use thermal.integrator = \"exponential\" "
                            f"or a smaller step")
        if self.auto is not None:
            rep.update(self.auto)
        else:
            rep["integrator"] = self.cfg["integrator"]
        if self.thi[TI.rad] >= 0:
            rl, tmax = self.radiation_limit()
            rep["radiation_step_limit"] = rl
            if self.cfg["integrator"] == "euler" and dt > rl:
                warnings.append(f"euler thermal step {dt:.3g} s exceeds the radiation limit "
                                f"C / (4 eps sigma A T^3) = {rl:.3g} s at {tmax:.0f} K: use "
                                f"thermal.integrator = \"exponential\" or a smaller step")
            if self.cfg["integrator"] == "exponential" and dt > rl:
                from .step_error import expected_radiation_error
                err = expected_radiation_error(dt / rl)
                rep["radiation_expected_error"] = err
                warnings.append(f"exponential thermal step {dt:.3g} s is {dt / rl:.3g} times the radiation "
                                f"accuracy limit {rl:.3g} s at {tmax:.0f} K: expected error up to {err:.2g} % of "
                                f"the temperature change (measured for radiation alone, "
                                f"benchmarks/radiation_step_error.py); lower thermal.time_step for accuracy")
        if self.thi[TI.conv] >= 0:
            g = self.gas
            n = st.n
            ur = np.linalg.norm(st.uf[:n] - st.velocity[:n], axis=1)
            re = st.por[:n] * g[R.RHO_F] * ur * 2 * st.radius[:n] / g[R.MU_F]
            _, _, bi = self.convection_biot(re, st.por[:n])
            bi = float(bi.max()) if bi.size else 0.0
            rep["biot_max"] = bi
            if bi > BIOT_LUMPED:
                warnings.append(f"Biot number h (V/A) / k_p = h R / (3 k_p) = {bi:.3g} > {BIOT_LUMPED:g}: the "
                                f"lumped (uniform) particle temperature ignores the temperature gradients inside "
                                f"the particles; use a higher thermal_conductivity only if the material has it, "
                                f"or smaller particles")
        rep["warnings"] = warnings
        return rep

    def convection_biot(self, re, por):
        """Nusselt number, heat transfer coefficient h = Nu k_f / d [W/(m2 K)] and Biot number
        Bi = h L_c / k_p with the lumped-capacitance length L_c = V/A = R/3 of each particle,
        for the particle Reynolds numbers ``re`` and void fractions ``por`` (arrays over the
        first len(re) particles), with the selected convection correlation and the gas table (the compiled
        function the heat step uses). A check, not a step: a Python loop is fine here."""
        from .convection import biot_lumped, nusselt_gas
        st, g = self.state, self.gas
        corr = int(self.thi[TI.conv])
        re = np.asarray(re, float)
        por = np.asarray(por, float)
        n = re.shape[0]
        nu = np.array([nusselt_gas(corr, float(re[i]), g[R.PR], float(por[i]), g) for i in range(n)])
        r = st.real_radius(n)   # a parcel's real particles
        h = nu * g[R.KF] / (2 * r)
        kp = self.tmat[st.material[:n], R.K_COND]
        return nu, h, biot_lumped(h, r, kp)

    def models_report(self):
        """`dem check`'s runs/skipped lines: one per mechanism of registry.MECHANISMS that the step
        runs (labels, porosity and quadrature notes from the selected model's record)."""
        c = self.cfg
        runs, skipped = [], []
        integ = f"{c['integrator']} thermal integration"
        if self.auto is not None:
            a = self.auto
            integ += (f" (auto, chosen by the step: {a['integrator_reason'].split(':')[0]}; steady state "
                      f"{'exact' if a['auto_steady'] == 0.0 else 'not exact'}: see `thermal integrator`)")
        elif c.get("integrator_auto"):
            integ += " (auto: euler with mechanics, fused into the force loop)"
        runs.append(integ)
        for mech in ("direct", "indirect", "convection", "radiation", "friction"):
            key, label = R.MECHANISMS[mech]
            name = c[key]
            if name != "none" and not (mech == "friction" and self.thi[TI.fric] < 0):
                rec = R.record(mech, name)
                gas_keys = rec.inputs()[1]
                extra = ""
                if mech == "direct":
                    how = ""
                    if c.get("correction_auto"):
                        how = (" chosen because youngs_modulus is softened below real_youngs_modulus"
                               if c["correction"] != "none" else " (auto: youngs_modulus not softened)")
                    extra = f" (contact radius {c['contact_radius']}, correction {c['correction']}{how})"
                # the kernel measures the porosity for every indirect model
                if "porosity" in gas_keys or mech == "indirect":
                    kind = ("Voronoi cells (scipy)" if self.voronoi else "local, measured around each particle"
                            if self.local_porosity else "global")
                    extra = f" (porosity {kind})"
                if "quadrature_tolerance" in gas_keys:
                    extra += f", quadrature tolerance {self.gas[R.QUAD_TOL]:g}"
                runs.append(f"{label}: {rec.name}{extra}")
            else:
                why = f"thermal.{key} = 'none'"
                if mech == "friction" and name != "none":
                    why = "mechanics frozen: no sliding"
                if mech in ("indirect", "convection") and "gas" not in self.scene.raw:
                    why += " (no [gas] section)"
                skipped.append(f"{label}: {why}")
        if len(self.cfg["sources"]):
            runs.append(f"heat sources: {len(self.cfg['sources'])}")
        for k, w in enumerate(self.cfg["walls"]):
            runs.append(f"wall {self.scene.walls[k]['name']}: {w['condition']}")
        return runs, skipped

    # -------------------------------------------------------------- output
    def history_columns(self):
        cols = ["thermal_energy", "T_mean", "T_min", "T_max"]
        cols += [f"E_{m}" for m in MECHANISMS]
        cols += [f"E_wall_{w['name']}" for w in self.scene.walls]
        return cols

    def history_row(self):
        st = self.state
        n = st.n_owned
        C = 1.0 / st.inv_heat_capacity[:n]
        T = st.temperature[:n]
        nan = float("nan")   # (no particle left: every outlet took them)
        row = dict(thermal_energy=float(np.sum(C * T)), T_mean=float(T.mean()) if n else nan,
                   T_min=float(T.min()) if n else nan, T_max=float(T.max()) if n else nan)
        for k, m in enumerate(MECHANISMS):
            row[f"E_{m}"] = float(self.tot[k])
        from ..contact.walls import per_wall
        for w, e in zip(self.scene.walls, per_wall(self.wtot, self.scene.walls)):
            row[f"E_wall_{w['name']}"] = float(e)
        return row
