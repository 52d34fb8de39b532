"""What a coupled run reports: the output of an output step (history.csv, VTK, coupling.csv,
wall_heat.csv and wall_heat_angle.csv: :class:`Outputs`; coupling.csv's rows:
:class:`Diagnostics`), coupling.png (:func:`plot`), timings.json and the closing summary,
the guard on every gas frame (:func:`check_gas_fields`, GasFieldError) and the run's
warnings (:class:`RunWatch`: eps clipping, sudden void fraction changes, fast gas).
"""
from __future__ import annotations

import json
import time
from pathlib import Path

import numpy as np

from .errors import GasFieldError


class Diagnostics:
    """coupling.csv rows: energies, heat rate, pressure drop and the bed's weight over the
    bottom area (its reference), bed height, timings. ``area``: :meth:`bottom_area`."""

    COLUMNS = ["time", "step", "T_particles", "T_gas", "E_particles", "E_gas", "Q_to_gas",
               "E_conv_particles", "dp", "weight_per_area", "bed_height", "v_max", "n_outside", "eps_raw_min",
               "eps_clipped_cells", "wall"]

    def __init__(self, path, keep_until=None, ledger=None, area=float("nan")):
        from dem.output import History
        from .energy import BALANCE_COLUMNS
        self.ledger = ledger
        self.area = area
        self.hist = History(str(path), self.COLUMNS + (BALANCE_COLUMNS if ledger is not None else []), keep_until)

    @staticmethod
    def particle_records(sim):
        """[E_particles, E_conv, E_walls, E_sources, E_flow] (J) of the particles, summed over the
        ranks (collective): their thermal energy sum(C T) and what they received since the DEM's
        start by convection, through the walls, by radiation, generation and sources, and the
        enthalpy the inlets brought less what the outlets took (dem.flow)."""
        from dem.thermal.heat import TOT
        a = np.zeros(5)
        if sim.thermal is not None:
            st, tot = sim.state, sim.thermal.tot
            n = st.n_owned
            a[:4] = (float((st.temperature[:n] / st.inv_heat_capacity[:n]).sum()), tot[TOT.conv], tot[TOT.wall],
                     tot[TOT.rad] + tot[TOT.gen] + tot[TOT.src])
            flow = sim.world.flow
            if flow is not None:
                ni = len(flow.inlets)
                a[4] = float(st.flow[:ni, 2].sum() - st.flow[ni:, 2].sum())
        if sim.par is not None:
            a = np.asarray(sim.par.allsum(a), float)
        return a

    @staticmethod
    def sums_of(sim, iface, fluid, frame, ends):
        """The sums a coupling.csv row needs, over the ranks (collective): (particle sums,
        particle_records, gas_sums). The particles' energy and convective heat are
        particle_records' (the balance's own)."""
        st = sim.state
        n = st.n_owned
        loc = np.zeros(7)
        if n:
            loc[2] = float(st.mass[:n].sum())
            loc[3] = float(st.position[:n, 2].sum())
            loc[5] = float(np.sqrt((st.velocity[:n] ** 2).sum(1)).max())
        loc[4] = n
        loc[6] = iface.n_lost
        if sim.thermal is not None:
            loc[1] = float((1.0 / st.inv_heat_capacity[:n]).sum())
        gas = Diagnostics.gas_sums(iface, fluid, frame, ends)   # this rank's owned cells
        if sim.par is not None:
            vmax = sim.par.allmax(loc[5])
            loc = sim.par.allsum(loc)
            loc[5] = vmax
            gas = sim.par.allsum(gas)
        precs = Diagnostics.particle_records(sim)
        return loc, precs, gas

    @staticmethod
    def owned_ends(iface):
        """(bottom, top): the cells of the mesh's lowest and highest layer of cell centres that
        this rank owns (the pressure drop's ends; local cells; collective: the layers are the
        whole mesh's)."""
        cs = iface.cells
        z = np.round(iface.mesh.cell_centres[:, 2], 12)
        own = cs.owned_mask
        zo = z[own]
        lo = cs.allmin(float(zo.min(initial=np.inf)))
        hi = cs.allmax(float(zo.max(initial=-np.inf)))
        return np.flatnonzero((z == lo) & own), np.flatnonzero((z == hi) & own)

    @staticmethod
    def bottom_area(iface):
        """The area (m^2) of the gas domain's bottom: its boundary faces (of any patch but a
        processor patch) whose outward normal points down (within 2.6 degrees of -z) at the
        mesh's lowest z; for a column, the cross-section the pressure drop acts on (collective:
        each rank its owned cells' faces, summed over the ranks)."""
        mesh, cs = iface.mesh, iface.cells
        z0 = float(cs.allmin(float(mesh.points[:, 2].min(initial=np.inf))))
        z1 = float(cs.allmax(float(mesh.points[:, 2].max(initial=-np.inf))))
        tol = 1e-6 * max(z1 - z0, 1e-300)
        own = cs.owned_mask
        area = 0.0
        for p in mesh.boundary:
            if p.get("type") == "processor":
                continue
            f = np.arange(int(p["startFace"]), int(p["startFace"]) + int(p["nFaces"]))
            f = f[mesh.owner[f] < own.size]      # (not a local mesh's phantom cell)
            f = f[own[mesh.owner[f]]]
            a = mesh.face_areas[f]
            mag = np.linalg.norm(a, axis=1)
            down = (a[:, 2] < -0.999 * mag) & (np.abs(mesh.face_centres[f, 2] - z0) <= tol)
            area += float(mag[down].sum())
        return float(cs.allsum(area))

    @staticmethod
    def gas_sums(iface, fluid, frame, ends):
        """[E_gas, sum rho cp eps V, Q_to_gas, sum p bottom, n bottom, sum p top, n top] over the
        cells this rank owns (coupling.cells; serial: every cell); ``ends``: owned_ends."""
        own = iface.cells.owned
        g = iface.gas
        V = iface.V[own]
        T = fluid["T"][own]
        mg = g.rho * g.cp * frame["eps"][own] * V
        p = fluid["p"]
        bot, top = ends
        return np.array([float((mg * T).sum()), float(mg.sum()),
                         float(((frame["Sexp"][own] - frame["Simp"][own] * T) * V).sum()),
                         float(p[bot].sum()), float(bot.size), float(p[top].sum()), float(top.size)])

    def row(self, t, step, sim, iface, fluid, frame, wall, sums, precs, gas):
        """One coupling.csv row: ``sums`` = [-, sum C, sum m, sum z, n, max |v|, n lost] over the
        ranks, ``precs`` = particle_records, ``gas`` = gas_sums over the ranks."""
        if sim.thermal is not None:
            Ep = float(precs[0])
            Tp = float(precs[0] / sums[1])
            Ec = float(precs[1])
        else:
            Tp = Ep = Ec = float("nan")
        Eg = float(gas[0])
        Tg = float(Eg / gas[1])
        q = float(gas[2])
        dp = float(gas[3] / gas[4] - gas[5] / gas[6])
        zb = float(sums[3] / sums[4]) if sums[4] else 0.0
        w = float(sums[2] * np.linalg.norm(iface.gravity) / self.area) if self.area > 0 else float("nan")
        row = dict(time=t, step=step, T_particles=Tp, T_gas=Tg, E_particles=Ep, E_gas=Eg,
                   Q_to_gas=q, E_conv_particles=Ec, dp=dp, weight_per_area=w, bed_height=zb, v_max=float(sums[5]),
                   n_outside=int(sums[6]), eps_raw_min=iface.clip["eps_raw_min"],
                   eps_clipped_cells=iface.clip["cells"], wall=wall)
        if self.ledger is not None:
            row.update(self.ledger.row(fluid["scalars"], precs))
        self.hist.add(row)


def heat_moved(d):
    """The scale of coupling.csv's heat balance, per row (J): the heat that moved since the
    run's start, through the boundaries (|E_walls_particles| + |E_walls_gas| + |E_open| +
    |E_sources_particles|) and between the phases (|E_conv_particles|, the particles'
    convective heat). coupling.png draws the balance's error and residual over it."""
    return (np.abs(d["E_walls_particles"]) + np.abs(d["E_walls_gas"]) + np.abs(d["E_open"])
            + np.abs(d["E_sources_particles"]) + np.abs(d["E_conv_particles"]))


BALANCE_TITLE = ("Heat balance of both phases: |error| relative to the heat moved since the start\n"
                 "(through the walls, inlet and outlet, and between the phases: coupling.diagnostics.heat_moved)")


def plot(out: Path, title: str) -> Path | None:
    """coupling.png (:func:`figure`), written atomically; None without matplotlib or with
    fewer than two rows of coupling.csv."""
    fig = figure(out, title)
    if fig is None:
        return None
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from dem.output import atomic_write
    FigureCanvasAgg(fig)
    p = out / "coupling.png"
    atomic_write(str(p), lambda tmp: fig.savefig(tmp, dpi=100, format="png", pil_kwargs={"compress_level": 1}))
    return p


def figure(out: Path, title: str):
    """The figure of coupling.png from coupling.csv, a panel for each: the mean temperatures of
    the particles and the gas; the heat from the particles to the gas; the pressure drop with
    the bed's weight over the bottom area (the drop a fluidized bed carries); the mean height
    of the particle centres; the heat balance's error and residual relative to the heat moved
    (:func:`heat_moved`). Each panel's title says what its traces are. Drawn with matplotlib's
    Figure alone (no pyplot, no layout engine: fixed margins that hold the two-line titles),
    about a second less at the end of every coupled run than through pyplot's constrained
    layout."""
    try:
        from matplotlib.figure import Figure
    except ImportError:
        return None
    f = out / "coupling.csv"
    if not f.exists():
        return None
    d = np.atleast_1d(np.genfromtxt(f, delimiter=",", names=True))
    if d.size < 2:
        return None
    names = d.dtype.names
    fig = Figure(figsize=(11, 11))
    grid = fig.add_gridspec(3, 2, left=0.075, right=0.97, bottom=0.05, top=0.915, wspace=0.26, hspace=0.42)
    ax = [fig.add_subplot(grid[0, 0]), fig.add_subplot(grid[0, 1]), fig.add_subplot(grid[1, 0]),
          fig.add_subplot(grid[1, 1]), fig.add_subplot(grid[2, :])]
    t = d["time"]
    small = dict(fontsize=9, loc="left")
    a = ax[0]
    a.plot(t, d["T_particles"], label="particles: sum(C T) / sum(C), C = m c_p")
    a.plot(t, d["T_gas"], label="gas: sum(rho c_p eps V T) / sum(rho c_p eps V)")
    a.set_ylabel("T [K]")
    a.set_title("Mean temperature of each phase (K)", **small)
    a.legend(fontsize=8)
    a = ax[1]
    a.plot(t, d["Q_to_gas"])
    a.axhline(0.0, color="0.5", lw=0.8)
    a.set_ylabel("heat to the gas [W]")
    a.set_title("Heat from the particles to the gas (W): sum of (Sexp - Simp T) V\n"
                "over the cells; negative: the gas heats the particles", **small)
    a = ax[2]
    a.plot(t, d["dp"], label="p(bottom cell layer) - p(top cell layer)")
    if "weight_per_area" in names and np.isfinite(d["weight_per_area"]).any():
        a.plot(t, d["weight_per_area"], "--", color="C3", label="bed weight / bottom area, sum(m) g / A")
    a.set_ylabel("pressure drop [Pa]")
    a.set_title("Pressure drop across the bed (Pa), layer means of p, vs bed weight / area\n"
                "(a fluidized bed carries its weight; the drop also holds the gas's own head)", **small)
    a.legend(fontsize=8)
    a = ax[3]
    a.plot(t, 1e3 * d["bed_height"])
    a.set_ylabel("mean particle height [mm]")
    a.set_title("Bed height: mean height z of the particle centres (mm)\n"
                "(about half the height of a uniform bed)", **small)
    a = ax[4]
    a.set_title(BALANCE_TITLE, **small)
    a.set_ylabel("|error| / heat moved")
    drawn = False
    if "balance_residual" in names:
        with np.errstate(invalid="ignore", divide="ignore"):
            scale = heat_moved(d)
            for col, label in (("balance_error", "balance_error: change of both phases' energy - heat in "
                                                 "(the explicit exchange's mismatch + continuity + residual)"),
                               ("balance_residual", "balance_residual: what the bookkeeping does not explain "
                                                    "(round-off)")):
                r = np.abs(d[col]) / scale
                r[~(np.isfinite(r) & (r > 0))] = np.nan
                if np.isfinite(r).any():
                    a.plot(t, r, label=label)
                    drawn = True
    if drawn:
        a.set_yscale("log")
        a.legend(fontsize=8)
    else:
        a.text(0.5, 0.5, "no heat balance: no heat exchanged in this run (coupling.toml heat = false, "
                         "or no heat yet)", transform=a.transAxes, ha="center", va="center")
    from matplotlib.ticker import MaxNLocator
    for a in ax:
        a.xaxis.set_major_locator(MaxNLocator(5 if a is not ax[4] else 10))
        a.set_xlabel("t [s]")
        a.set_xlim(t[0], t[-1])
        a.grid(alpha=0.3)
    fig.suptitle(title, y=0.985)
    return fig


class Outputs:
    """The writers of an output step (rank 0 writes, every rank its VTK piece; built before the
    first step, on every rank):
    history.csv, VTK, coupling.csv, and with heat and DEM walls wall_heat.csv (and
    wall_heat_angle.csv when wanted). ``outputs(fluid, frame, t, step)`` writes one output
    step (collective over the DEM ranks). ``keep``: the time up to which earlier rows are
    kept (a restart), else None."""

    def __init__(self, root, iface, case, ledger, out: Path, keep, t_wall0):
        from dem.output import History
        sim = iface.sim
        self.sim, self.iface, self.ledger, self.t_wall0 = sim, iface, ledger, t_wall0
        self.hist = self.vtk = self.diag = self.walls = self.walls_by_angle = None
        self.ends = Diagnostics.owned_ends(iface)   # every rank: its cells of the pressure drop's ends
        area = Diagnostics.bottom_area(iface)       # collective: the bed weight's area
        self._plans = iface.cells.plans
        if sim.scene.output["vtk"]:   # every rank: under MPI each writes its own piece (collective)
            self.vtk = sim.vtk_series(str(out))
        if not root:
            return
        self.hist = History(str(out / "history.csv"), sim.history_columns(), keep)
        if sim.thermal is not None and sim.scene.walls:
            from dem.thermal.wall_heat import WallAngleFile, WallHeatFile
            self.walls = WallHeatFile(str(out / "wall_heat.csv"), sim.scene, keep)
            if WallAngleFile.wanted(sim.scene):
                self.walls_by_angle = WallAngleFile(str(out / "wall_heat_angle.csv"), sim.scene, keep)
        self.diag = Diagnostics(out / "coupling.csv", keep, ledger, area)

    def __call__(self, fluid, frame, t, step):
        """One output step (collective): the sums over the ranks first, then rank 0's files; a
        write failure there (disk full) stops every rank with the same error, naming the rank."""
        sim, iface = self.sim, self.iface
        with iface.timer("output"):
            if self._plans != iface.cells.plans:   # a re-cut (collective): the local numbering may have changed
                self.ends = Diagnostics.owned_ends(iface)
                self._plans = iface.cells.plans
            row = sim.history_row()
            if sim.scene.output["vtk"]:   # every rank its own piece (a failure raised on all)
                sim.write_vtk(self.vtk, **_fluid_fields_now(sim, iface))
            diag = Diagnostics.sums_of(sim, iface, fluid, frame, self.ends)   # collective
        totals = sim.wall_heat_totals()   # collective over the DEM ranks
        from dem.thermal.wall_heat import WallAngleFile, cylinder_flux_by_angle
        by_angle = cylinder_flux_by_angle(sim) if WallAngleFile.wanted(sim.scene) else None   # collective
        wall = time.perf_counter() - self.t_wall0

        def write():
            if self.hist is None:   # not rank 0
                return
            self.hist.add(row)
            self.diag.row(t, step, sim, iface, fluid, frame, wall, *diag)
            if self.walls is not None:
                self.walls.add(t, totals, gas=self.ledger.gas_wall_energy(len(sim.scene.walls)))
            if self.walls_by_angle is not None:
                self.walls_by_angle.add(t, by_angle)

        with iface.timer("output"):
            sim.writers.each_rank_write(write)


def _fluid_fields_now(sim, iface):
    """The VTK fields of the fluid force on each owned particle at the last frame (iface.last),
    in the current row order: ``fluid_force`` and its terms ``fluid_drag`` (beta (u_f - u_p)),
    ``fluid_pressure`` (-V_p grad p, model A; the buoyancy -rho_f V_p g, model B) and, when on,
    ``fluid_lift`` and ``fluid_virtual_mass`` (C_vm rho_f V_p Du_f/Dt), which add up to it.
    Under MPI particles may have moved between ranks during the interval: a particle that
    arrived has no frame force here and shows as its ``fluid_force`` the force the DEM applies
    to it now, F_exp - beta_imp v (dem.schema: external_force, drag_beta), and NaN as its terms
    (their frame values stayed on the rank it left)."""
    st = sim.state
    n = st.n_owned
    last = iface.last
    force, ids = last.get("force"), last.get("ids")
    parts = last.get("parts") or {}
    # the same fields on every rank (the VTK pieces of a frame share one field list)
    names = ["drag", "pressure"] + (["lift"] if iface.lift_id else []) + (["virtual_mass"] if iface.virtual_mass
                                                                         else [])
    same = ids is None or (ids.shape[0] == n and np.array_equal(ids, st.id[:n]))
    if force is None or set(parts) != set(names) or (same and force.shape[0] != n):
        return dict(fluid_force=np.zeros((n, 3)), **{f"fluid_{k}": np.zeros((n, 3)) for k in names})
    if same:
        out = dict(fluid_force=np.ascontiguousarray(force))
        out.update((f"fluid_{k}", np.ascontiguousarray(v)) for k, v in parts.items())
        return out
    cur = st.id[:n]
    k = np.zeros(n, np.int64)
    found = np.zeros(n, bool)
    if ids.size:
        order = np.argsort(ids)
        k = np.minimum(np.searchsorted(ids[order], cur), ids.size - 1)
        found = ids[order][k] == cur
        k = order[k]
    miss = ~found
    out = {}
    for name, v in dict(force=force, **parts).items():
        a = np.full((n, 3), np.nan)
        a[found] = v[k[found]]
        out[f"fluid_{name}"] = a
    out["fluid_force"][miss] = (st.external_force[:n][miss]
                                - st.drag_beta[:n][miss, None] * st.velocity[:n][miss])
    return out


# gas speed above which the (incompressible) gas solution is taken as diverged: the
# speed of sound in air at 20 C (the model is invalid far below it, above Mach ~0.3)
GAS_SPEED_LIMIT = 343.0


class RunWatch:
    """Runtime warnings of a coupled run, each printed once (rank 0), the worst values kept
    for the summary: void fraction clipped at eps_min (solid volume the gas does not see),
    a sudden change of the void fraction between two coupling steps (the gas must displace
    that volume within one CFD step), a gas faster than Mach 0.3 (outside the
    incompressible model)."""

    EPS_CHANGE = 0.2          # void fraction change of a cell in one coupling step
    CLIPPED = 1e-3            # fraction of the particle volume hidden by the eps_min clipping
    GAS_SPEED = 100.0         # m/s, about Mach 0.3 in air

    def __init__(self, mesh, cfg, log, cells=None):
        self.mesh, self.cfg, self.log = mesh, cfg, log
        self.cells = cells   # coupling.cells.CellShare (the cells this rank owns); None: every cell
        self.clip = None
        self.eps_change = 0.0
        self.gas_speed = 0.0
        self._said = set()

    def _at(self, c):
        """Cell ``c`` (global id) and its centre (collective: every rank calls it alike)."""
        x = self.cells.centre(c) if self.cells is not None else self.mesh.cell_centres[c]
        return f"cell {c} at {np.array2string(x, precision=6)}"

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
        own = self.cells.owned if self.cells is not None else np.arange(u.shape[0])
        u = u[own]
        s2 = (u * u).sum(axis=1)
        c = int(np.argmax(s2)) if s2.size else -1
        gid = self.cells.global_ids if self.cells is not None else np.arange(u.shape[0])
        v, c = float(np.sqrt(s2[c])) if c >= 0 else 0.0, int(gid[own[c]]) if c >= 0 else -1
        if self.cells is not None:
            v, c = self.cells.argmax(v, c)
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


def check_gas_fields(fluid, step, *, time_value=None, mesh=None, cfg=None, eps_change=None, cells=None,
                     global_ids=None):
    """Guard on every gas frame received from the solver (before the DEM sees it): U, T,
    grad p and p finite, T > 0, |U| <= GAS_SPEED_LIMIT. Raises :class:`GasFieldError`
    naming the field, the number of bad cells, the first one (index and centre), the time
    and what to change. ``cells``: the cell of ``mesh`` of each row (a many-to-many rank
    checks the cells it owns); None: row = cell. ``global_ids``: the global cell of each cell
    of ``mesh`` (a local mesh) for the message."""
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
            bad = (name, what, np.flatnonzero(m))
            break
    if bad is None:
        return fluid
    name, what, rows = bad
    val = np.asarray(fluid[name])[int(rows[0])]
    c = int(rows[0]) if cells is None else int(cells[int(rows[0])])
    where = f"cell {c if global_ids is None else int(global_ids[c])}"
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
        f"gas field {name} received from the solver is {what} in {rows.size} cell(s) (first: {where}, "
        f"{name} = {np.array2string(np.atleast_1d(val), precision=6)}) at {when}: {cause}; the field is not "
        f"passed to the particles. Check log.thermoDemFoam; {advice}",
        peer="CFD solver", step=step)


def timings(timer, t_wall0, sim, n_steps, k):
    wall = time.perf_counter() - t_wall0
    loop = sum(v for p, v in timer.total.items())
    d = {"wall_total": wall, "loop": loop, "phases": dict(timer.total),
         "coupling_steps": n_steps, "dem_steps": n_steps * k, "particles": sim.n_particles,
         "dem_ranks": 1 if sim.par is None else sim.par.size, "dem_threads": getattr(sim, "threads", 1)}
    d["particle_steps_per_s"] = sim.n_particles * n_steps * k / loop if loop > 0 else 0.0
    return d


def format_timings(s):
    lines = [f"done: {s['coupling_steps']} coupling steps ({s['dem_steps']} DEM steps, "
             f"{s['particles']} particles) to t = {s['time']:.6g} s in {s['wall_total']:.1f} s "
             f"(loop {s['loop']:.1f} s, {s['particle_steps_per_s']:.3g} particle-steps/s, "
             f"{s.get('dem_threads', 1)} DEM thread{'s' if s.get('dem_threads', 1) > 1 else ''}"
             f"{' per rank' if s.get('dem_ranks', 1) > 1 else ''})"]
    for p, v in s["phases"].items():
        lines.append(f"  {p:15s} {v:9.3f} s  {100 * v / max(s['loop'], 1e-12):5.1f} %")
    lines.append(f"output in {s['out']}" + (f" (plot {s['png']})" if s.get("png") else ""))
    return "\n".join(lines)


def write_timings(path, timings, failing):
    """timings.json, atomically (never a 0-byte file). While a run is already failing, a write
    error here is dropped so that the first error, the one the user needs, is the one reported."""
    from dem.output import OutputError, write_text
    try:
        write_text(str(path), json.dumps(timings, indent=1))
    except OutputError:
        if not failing:
            raise
