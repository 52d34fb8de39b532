"""Walls of both phases and the coupled run's energy ledger (issue 14).

**Tied walls.** A DEM wall and a boundary patch of the gas mesh are one wall when
coupling.toml ties them::

    [[walls]]
    dem = "tube"          # a [[walls]] name of dem.toml
    patch = "tube"        # a patch of the gas mesh, of type wall
    # tolerance = 1e-4    # m: largest distance of the patch's points from the DEM wall
    #                     # (default: a tenth of the smallest particle diameter)

The pair must coincide: every point of the patch lies on the DEM wall's surface within the
tolerance, and the two areas agree within ``AREA_RTOL`` plus what a polygonal patch of a
cylinder loses to its chords; and its thermal condition must be one: a fixed temperature on
both sides (fixedValue of the same value in 0/T; a temperature table: uniformFixedValue), or
adiabatic on both (zeroGradient), or a fixed heat flux (fixedGradient on the gas patch, whose
gradient the solver sets: :class:`FluxSplit`). Otherwise the check names both. A tied wall's heat is written
per path in wall_heat.csv: the particles' ``contact`` and ``gas_gap`` (DEM), the gas's own
``gas_convection`` (the solver's wall conduction, below) and their ``total``.

**The gas's ledger.** Each frame of the solver ends with the step's energy ledger
(openfoam_cases/solver/thermoDemFoam/energyBalance.H): per boundary patch the heat into the
gas by conduction (the laplacian's wall flux, rho cp eps_f (alpha + alpha_t) dT/dn) and by
advection (-rho cp phi_b T_b), then the gas's energy rho cp sum(eps T V), the continuity
residual the non-conservative energy equation adds back, and the particles' heat
sum((Sexp - Simp T) V). The rates are those of the step's end (implicit Euler), so rate x dt
is exactly what the step's discrete balance used. :class:`EnergyLedger` integrates them over
the run and writes coupling.csv's balance:

    balance_error = (E_particles - E_particles(0)) + (E_gas - E_gas(0))
                    - (E_walls_particles + E_walls_gas + E_open + E_sources_particles
                       + E_flow_particles)

(E_flow_particles: the enthalpy m c T of the particles the inlets brought less what the outlets
took, dem.flow),

which is made of two known parts and a residual:

* ``E_exchange_mismatch``: the particles' convective heat (integrated in the DEM's steps with
  the gas temperature of the interval's start) plus the gas's heat from the particles
  (the sources of the solver's steps); the explicit exchange does not make them opposite
  exactly;
* ``E_continuity``: the gas's continuity residual times its temperature (solver tolerance);
* ``balance_residual`` = balance_error - E_exchange_mismatch - E_continuity: what the
  bookkeeping does not explain (the linear solvers' tolerance and round-off).
"""
from __future__ import annotations

import math

import numpy as np

from .errors import CaseConfigError, CouplingError

AREA_RTOL = 0.03          # tied pair: |A_patch / A_wall - 1| allowed beyond the chord loss
TIE_KEYS = ("dem", "patch", "tolerance")


# --------------------------------------------------------------------------- tied walls

def parse_ties(path, raw) -> list[dict]:
    """coupling.toml [[walls]] -> [{dem, patch, tolerance}]; CaseConfigError naming the key."""
    if not isinstance(raw, list) or not all(isinstance(t, dict) for t in raw):
        raise CaseConfigError(path, "must be an array of tables [[walls]] with dem = \"<DEM wall name>\" and "
                                    "patch = \"<gas patch name>\"", "walls")
    ties = []
    for k, t in enumerate(raw):
        key = f"walls[{k}]"
        extra = sorted(set(t) - set(TIE_KEYS))
        if extra:
            raise CaseConfigError(path, f"unknown key(s) {extra}; valid keys: {', '.join(TIE_KEYS)}", key)
        for name in ("dem", "patch"):
            if not isinstance(t.get(name), str) or not t[name]:
                raise CaseConfigError(path, f"missing or not a name (a string), got {t.get(name)!r}; "
                                            f"{'dem: a [[walls]] name of dem.toml' if name == 'dem' else 'patch: a boundary patch of the gas mesh'}",
                                      f"{key}.{name}")
        tol = t.get("tolerance")
        if tol is not None and (isinstance(tol, bool) or not isinstance(tol, (int, float))
                                or not math.isfinite(tol) or tol <= 0):
            raise CaseConfigError(path, f"must be a length > 0 in m, got {tol!r}", f"{key}.tolerance")
        for other in ties:
            for name in ("dem", "patch"):
                if other[name] == t[name]:
                    raise CaseConfigError(path, f"{name} {t[name]!r} is tied twice (a wall is tied to one "
                                                f"patch, a patch to one wall)", f"{key}.{name}")
        ties.append(dict(dem=t["dem"], patch=t["patch"], tolerance=None if tol is None else float(tol)))
    return ties


def check_tie_names(case) -> None:
    """Before anything is written: each tied DEM wall exists in dem.toml and each patch in the
    gas case (constant/polyMesh/boundary or system/blockMeshDict)."""
    from . import foam_case as fc
    ties = case.config.walls
    if not ties:
        return
    names = [w["name"] for w in case.sim.scene.walls] if case.sim is not None else None
    patches = fc.patch_names(case.dir)
    for k, t in enumerate(ties):
        if names is not None and t["dem"] not in names:
            raise CaseConfigError(case.config_file, f"no DEM wall {t['dem']!r} in {case.dem_file.name}; its walls: "
                                                    f"{', '.join(names) or 'none'}", f"walls[{k}].dem")
        if t["patch"] not in patches:
            raise CaseConfigError(case.config_file, f"no gas patch {t['patch']!r}; the mesh's patches: "
                                                    f"{', '.join(patches)}", f"walls[{k}].patch")
        if case.sim is not None:
            w = case.sim.scene.walls[names.index(t["dem"])]
            if w["type"] == "mesh":
                raise CaseConfigError(case.config_file, f"DEM wall {t['dem']!r} is a mesh wall; a tie to a gas "
                                                        "patch needs a plane or a cylinder (the gas heat is "
                                                        "placed by the wall's nearest points); untie it",
                                      f"walls[{k}].dem")
            _check_condition(case, k, t, w)


def _gas_condition(case, patch):
    """The boundary condition of 0/T on ``patch`` (exact name first, then regex keys)."""
    import re
    from . import foam_case as fc
    bf = fc.parse_foam_dict(case.dir / "0" / "T").get("boundaryField", {})
    if patch in bf:
        return bf[patch]
    for key, spec in bf.items():
        if re.fullmatch(key.strip('"'), patch):
            return spec
    return {}


def _check_condition(case, k, t, w):
    """A tied wall is one wall: the gas patch's temperature condition (0/T) must be the DEM
    wall's (the same fixed temperature, or adiabatic on both sides)."""
    spec = w.get("thermal") or {"condition": "adiabatic"}
    cond = spec.get("condition", "adiabatic")
    gas = _gas_condition(case, t["patch"])
    gtype = str(gas.get("type", "?"))
    both = (f"DEM wall {t['dem']!r} ({case.dem_file.name}: {cond}) and gas patch {t['patch']!r} "
            f"(0/T: {gtype})")
    key = f"walls[{k}]"
    if cond == "fixed_heat_flux":
        if gtype != "fixedGradient":
            raise CaseConfigError(case.config_file, f"{both}: a tied fixed-heat-flux wall needs type fixedGradient "
                                                    f"(gradient uniform 0) on the gas patch: the solver sets each "
                                                    f"face's gradient so that the gas takes the part of q_w the "
                                                    f"particles' contacts do not", key)
        return
    if cond == "adiabatic":
        ok = gtype == "zeroGradient" or (gtype == "fixedGradient" and _uniform(gas.get("gradient")) == 0.0)
        if not ok:
            raise CaseConfigError(case.config_file, f"{both}: one wall needs one condition: an adiabatic DEM wall "
                                                    f"needs zeroGradient on the gas patch", key)
        return
    if "table" in spec:
        if gtype != "uniformFixedValue":
            raise CaseConfigError(case.config_file, f"{both}: a DEM wall temperature table needs the same table on "
                                                    f"the gas patch (type uniformFixedValue)", key)
        return
    Tw = float(spec.get("temperature", math.nan))
    Tg = _uniform(gas.get("value")) if gtype == "fixedValue" else None
    if Tg is None or not math.isclose(Tg, Tw, rel_tol=1e-9, abs_tol=0.0):
        raise CaseConfigError(case.config_file, f"{both}: one wall needs one condition: the gas patch must be "
                                                f"fixedValue uniform {Tw:g} (the DEM wall's temperature)"
                                                + (f", it is {Tg:g} K" if Tg is not None else ""), key)


def _uniform(text):
    """The number of 'uniform X' (None if not of that form)."""
    parts = str(text or "").split()
    if len(parts) == 2 and parts[0] == "uniform":
        try:
            return float(parts[1])
        except ValueError:
            return None
    return None


def _surface_distance(w, x):
    """Distance of points x (n, 3) from the surface of scene wall w (a bounded plane: from its
    rectangle; a cylinder of finite length: from its lateral surface between its ends)."""
    p = np.asarray(w["point"], float)
    r = x - p
    if w["type"] == "plane":
        n = np.asarray(w["normal"], float)
        d = np.abs(r @ n)
        ext = w.get("extent")
        if ext is not None:
            u = np.asarray(w["u_axis"], float)
            v = np.cross(n, u)
            over = np.maximum(np.abs(r @ u) - ext[0], 0.0) ** 2 + np.maximum(np.abs(r @ v) - ext[1], 0.0) ** 2
            d = np.sqrt(d * d + over)
        return d
    a = np.asarray(w["axis"], float)
    s = r @ a
    rho = np.linalg.norm(r - s[:, None] * a, axis=1)
    d = np.abs(rho - float(w["radius"]))
    if math.isfinite(w["length"]):
        d = np.sqrt(d * d + np.maximum(np.abs(s) - 0.5 * w["length"], 0.0) ** 2)
    return d


def _patches(mesh):
    """The mesh's patches without processor patches: the order of the solver's ledger."""
    return [p for p in mesh.boundary if p.get("type") != "processor"]


def _patch(mesh, name):
    for k, p in enumerate(_patches(mesh)):
        if p["name"] == name:
            return k, p
    return None, None


def tie_walls(case, mesh, ranks=None) -> dict[int, int]:
    """Check the tied pairs on the gas mesh; returns {DEM wall index: patch index (in the
    boundary's order, the ledger's)}. CaseConfigError naming both when a pair does not
    coincide. ``ranks``: coupling.cells.CellShare when ``mesh`` is a DEM rank's local mesh
    (coupling.pieces): each rank checks the patch faces of the cells it owns (every boundary
    face once over the ranks), the farthest point, the area and the face count are reduced
    over the ranks (the same answer on each); None: one process, the whole mesh."""
    from .cells import CellShare
    red = ranks if ranks is not None else CellShare.serial(mesh.n_cells)
    from dem.thermal.wall_heat import wall_area
    ties = case.config.walls
    if not ties:
        return {}
    sc = case.sim.scene
    names = [w["name"] for w in sc.walls]
    dmin = 2.0 * float(sc.rmin if getattr(sc, "distributed", False) else np.min(sc.radius))
    out = {}
    for k, t in enumerate(ties):
        key = f"walls[{k}]"
        wi = names.index(t["dem"])
        w = sc.walls[wi]
        pi, p = _patch(mesh, t["patch"])
        if p is None:
            raise CaseConfigError(case.config_file, f"no gas patch {t['patch']!r} in the mesh", f"{key}.patch")
        if p.get("type") != "wall":
            raise CaseConfigError(case.config_file, f"gas patch {t['patch']!r} is of type {p.get('type')!r}; a tied "
                                                    f"patch must be of type wall (constant/polyMesh/boundary, "
                                                    f"blockMeshDict)", f"{key}.patch")
        f0, nf = int(p["startFace"]), int(p["nFaces"])
        fs = f0 + np.flatnonzero(red.owned_mask[mesh.owner[f0:f0 + nf]])
        off = mesh.face_offsets
        ln = off[fs + 1] - off[fs]
        idx = np.repeat(off[fs] - np.r_[0, np.cumsum(ln)[:-1]], ln) + np.arange(int(ln.sum()))
        x = mesh.points[np.unique(mesh.face_points[idx])]
        tol = t["tolerance"] if t["tolerance"] is not None else 0.1 * dmin
        both = f"DEM wall {t['dem']!r} ({case.dem_file.name}) and gas patch {t['patch']!r}"
        if int(red.allsum(float(fs.size))) == 0:
            raise CaseConfigError(case.config_file, f"{both}: the patch has no faces", key)
        d = _surface_distance(w, x) if x.size else np.zeros(0)
        j = int(np.argmax(d)) if d.size else -1
        dj, xj = red.best(float(d[j]) if j >= 0 else -np.inf, x[j] if j >= 0 else np.zeros(3))
        if dj > tol:
            raise CaseConfigError(case.config_file, f"{both} do not coincide: the patch's point "
                                                    f"{np.array2string(xj, precision=6)} is {dj:.3g} m from the "
                                                    f"DEM wall (tolerance {tol:.3g} m); move one of them or set "
                                                    f"{key}.tolerance", key)
        a_wall = wall_area(w, sc.domain["min"], sc.domain["max"])
        a_patch = float(red.allsum(float(np.linalg.norm(mesh.face_areas[fs], axis=1).sum())))
        chord = 0.0
        if w["type"] == "cylinder":
            chord = min(max(1.0 - a_patch / max(a_wall, 1e-300), 0.0), 0.05)
        if a_wall <= 0 or abs(a_patch / a_wall - 1.0) > AREA_RTOL + chord:
            raise CaseConfigError(case.config_file, f"{both} do not coincide: the patch's area is {a_patch:.6g} m^2, "
                                                    f"the DEM wall's {a_wall:.6g} m^2 within the DEM domain "
                                                    f"(allowed: {100 * AREA_RTOL:g} %); the patch must cover the "
                                                    f"wall the particles touch", key)
        out[wi] = pi
    return out


# --------------------------------------------------------------------------- ledger

class EnergyLedger:
    """The run's energy bookkeeping (the same on every DEM rank; rank 0 writes): the
    solver's ledger integrated over the coupling steps, and the references of the balance."""

    def __init__(self, mesh, ties: dict[int, int]):
        pats = _patches(mesh)
        self.patch_names = [p["name"] for p in pats]
        self.wall = np.array([p.get("type") == "wall" for p in pats], bool)
        self.n_patches = len(pats)
        self.size = 2 * self.n_patches + 3
        self.ties = dict(ties)
        self.acc = np.zeros(self.size)        # J: the rates' integrals (the energy slot unused)
        self.ref = None                       # [E_gas(0), E_particles(0), particle records at 0 ...]

    # ledger entries
    def _cond(self):
        return slice(0, 2 * self.n_patches, 2)

    def _adv(self):
        return slice(1, 2 * self.n_patches, 2)

    def check(self, scalars, step):
        """The ledger of a received frame must have this mesh's size and be finite."""
        s = np.asarray(scalars)
        if s.size != self.size:
            raise CouplingError(f"the frame's energy ledger has {s.size} entries; this mesh's "
                                f"{self.n_patches} patches need {self.size} (a solver built from other sources?)",
                                peer="CFD solver", step=step)
        if not np.all(np.isfinite(s)):
            raise CouplingError("the frame's energy ledger is not finite (the gas energy equation diverged: "
                                "see log.thermoDemFoam)", peer="CFD solver", step=step)

    def begin(self, scalars, particles):
        """References at the run's start (or at a restart whose state has no ledger)."""
        if self.ref is None:
            self.ref = np.r_[float(scalars[2 * self.n_patches]), np.asarray(particles, float)]

    def add(self, scalars, dt):
        """Integrate the step's rates (W) over the CFD step dt."""
        s = np.asarray(scalars, float)
        e = 2 * self.n_patches
        self.acc[:e] += dt * s[:e]
        self.acc[e + 1:] += dt * s[e + 1:]

    def gas_wall_energy(self, n_walls):
        """[n_walls] J: each tied DEM wall's gas path since the start (NaN for untied walls)."""
        g = np.full(n_walls, math.nan)
        cond = self.acc[self._cond()]
        for wi, pi in self.ties.items():
            g[wi] = cond[pi]
        return g

    def state(self) -> dict:
        return dict(ledger_acc=self.acc.copy(), ledger_ref=np.zeros(0) if self.ref is None else self.ref.copy())

    def restore(self, d: dict):
        a, r = d.get("ledger_acc"), d.get("ledger_ref")
        if a is not None and np.asarray(a).shape == (self.size,) and r is not None and np.asarray(r).size:
            self.acc = np.asarray(a, float).copy()
            self.ref = np.asarray(r, float).copy()

    def row(self, scalars, particles) -> dict:
        """coupling.csv's balance columns. ``particles`` = [E_particles, E_conv, E_walls,
        E_sources, E_flow] of the particles (J, the DEM's records since its start)."""
        e = 2 * self.n_patches
        s = np.asarray(scalars, float)
        ref = self.ref if self.ref is not None else np.r_[s[e], np.asarray(particles, float)]
        if ref.size < np.asarray(particles).size + 1:   # a restart point written before the inlets' column
            ref = np.r_[ref, np.zeros(np.asarray(particles).size + 1 - ref.size)]
        P = np.asarray(particles, float) - ref[1:]
        dEg = float(s[e] - ref[0])
        cond, adv = self.acc[self._cond()], self.acc[self._adv()]
        walls_gas = float(cond[self.wall].sum())
        open_ = float(cond[~self.wall].sum() + adv.sum())
        bal = P[0] + dEg - (P[2] + walls_gas + open_ + P[3] + P[4])
        mism = P[1] + float(self.acc[e + 2])
        cont = float(self.acc[e + 1])
        return dict(E_gas_solver=float(s[e]), E_walls_particles=float(P[2]), E_walls_gas=walls_gas,
                    E_open=open_, E_sources_particles=float(P[3]), E_flow_particles=float(P[4]), balance_error=bal,
                    E_exchange_mismatch=mism, E_continuity=cont, balance_residual=bal - mism - cont)


BALANCE_COLUMNS = ["E_gas_solver", "E_walls_particles", "E_walls_gas", "E_open", "E_sources_particles", "E_flow_particles",
                   "balance_error", "E_exchange_mismatch", "E_continuity", "balance_residual"]


# --------------------------------------------------------------------------- particle paths per face

NPATH = 3   # the particles' paths through a tied wall: contact, gas gap, radiation


class FluxSplit:
    """The particles' heat through each tied wall, per cell of the gas mesh, sent with each
    frame: three columns per tied wall (contact, gas gap, radiation; W through the wall faces of
    each cell over the coming interval). The solver writes them as per-face fields of the patch
    (wallHeatFluxContact, wallHeatFluxGasGap, wallHeatFluxRadiation: a cell's value over its
    faces on the patch, by area), and at a fixed-heat-flux wall it gives the gas the rest of q_w (reference 001's
    split: the contacts take A_c q_w, the gas the rest of each face's q_w A_f), so the wall
    delivers q_w A whatever the bed does.

    A column is the particles' heat at the interval's start (each particle's wall conductance
    Hw, its gap part Hwg, times T_w - T_i; A_c q_w at a fixed-flux wall; the wall's part of its
    radiation), each on the patch face nearest its contact point (the face's owner cell), plus what the particles took by that
    path in the intervals already done beyond what was sent for them (the DEM's exact wall
    records), spread like the estimate (or over the patch by area when no particle touches it).
    Summed over the run, what was sent is the particles' energy up to the last interval plus
    that interval's estimate: the fields integrate to the DEM's records, and a fixed-flux wall's
    total (gas + particles) is q_w A t, up to the estimate error of the last interval (zero for
    a bed at rest). Where the contacts take more than a face's q_w A_f the gas's flux there is
    negative (it gives the face heat), so the total stays exact."""

    def __init__(self, case, mesh, ties: dict[int, int]):
        sc = case.sim.scene
        pats = _patches(mesh)
        self.walls = []   # (DEM wall index, patch index, patch name, fixed flux?, q_w)
        for wi, pi in sorted(ties.items(), key=lambda kv: kv[1]):
            th = sc.walls[wi].get("thermal") or {}
            ff = th.get("condition") == "fixed_heat_flux"
            self.walls.append((wi, pi, pats[pi]["name"], ff, float(th.get("heat_flux", 0.0)) if ff else 0.0))
        self._on(mesh)
        self.sent = np.zeros((len(self.walls), NPATH))   # J: cumulative energy sent per path

    def _on(self, mesh):
        """The tied patches' faces on ``mesh`` (a DEM rank's local mesh: the faces its cells
        own): per wall (owner cells of the patch faces, their areas, kd-tree of centres)."""
        from scipy.spatial import cKDTree
        pats = _patches(mesh)
        self.faces = []
        for _wi, pi, *_rest in self.walls:
            f0, nf = int(pats[pi]["startFace"]), int(pats[pi]["nFaces"])
            self.faces.append((mesh.owner[f0:f0 + nf], np.linalg.norm(mesh.face_areas[f0:f0 + nf], axis=1),
                               cKDTree(mesh.face_centres[f0:f0 + nf])))
        self.n_cells = mesh.n_cells
        self.mesh = mesh

    def __bool__(self):
        return bool(self.walls)

    def couplingdict_entries(self) -> dict:
        return dict(patches=[w[2] for w in self.walls], fixed_flux=[w[3] for w in self.walls],
                    fluxes=[w[4] for w in self.walls])

    def state(self) -> dict:
        return dict(split_sent=self.sent.copy())

    def _records(self, sim):
        """[n_walls, 3] J: the particles' (contact, gas gap, radiation) heat through each tied wall."""
        tot = sim.wall_heat_totals()   # collective; [n_walls, 3] of (all, gap, radiation) or None
        r = np.zeros((len(self.walls), NPATH))
        if tot is not None:
            for k, (wi, *_rest) in enumerate(self.walls):
                r[k] = (tot[wi, 0] - tot[wi, 1] - tot[wi, 2], tot[wi, 1], tot[wi, 2])
        return r

    def restore(self, d: dict, sim):
        a = d.get("split_sent")
        rec = self._records(sim)   # collective
        if a is not None and np.asarray(a).shape == self.sent.shape:
            self.sent = np.asarray(a, float).copy()
        elif a is not None and np.asarray(a).shape == (len(self.walls), 2):   # before the radiation path
            self.sent = np.c_[np.asarray(a, float), rec[:, 2]]
        else:   # an older state: count the outstanding difference from the restart
            self.sent = rec

    def _estimate(self, sim, k):
        """[n_cells, 3] W: the particles' heat from tied wall k now by path (dem.thermal.wall_heat.
        particle_wall_heat), by owner cell of the patch face nearest each particle."""
        from dem.thermal.wall_heat import particle_wall_heat
        wi = self.walls[k][0]
        cells, _, tree = self.faces[k]
        est = np.zeros((self.n_cells, NPATH))
        rows, *q = particle_wall_heat(sim, wi)
        if rows.size:
            _, f = tree.query(_contact_points(sim.scene.walls[wi], sim.state.position[rows]))
            for p in range(NPATH):
                est[:, p] = np.bincount(cells[f], weights=q[p], minlength=self.n_cells)
        return est

    def columns(self, sim, dt, share=None):
        """[n_cells, 3 n_walls] W of the coming interval: (contact, gas gap, radiation) per tied
        wall (collective over the DEM ranks; ``share``: coupling.cells.CellShare, the cells
        each rank owns: valid there, each total summed over the ranks' owned cells)."""
        from .cells import CellShare
        cs = share if share is not None else CellShare.serial(self.n_cells)
        if share is not None and share.mesh is not self.mesh and share.par is not None:
            self._on(share.mesh)   # this rank's local mesh was rebuilt (a re-cut of the DEM boxes)
        m = len(self.walls)
        out = np.zeros((self.n_cells, NPATH * m))
        if not m:
            return out
        rec = self._records(sim)
        est = np.concatenate([self._estimate(sim, k) for k in range(m)], axis=1)
        (est,) = cs.assemble(est)
        own = cs.owned
        for k in range(m):
            cells, area, _ = self.faces[k]
            a_wall = area.sum() if cs.par is None else cs.allsum(float(area[cs.owned_mask[cells]].sum()))
            by_area = np.bincount(cells, weights=area, minlength=self.n_cells) / a_wall
            for p in range(NPATH):
                e = est[:, NPATH * k + p]
                owed = rec[k, p] - self.sent[k, p]        # taken beyond what was sent, J
                tot = float(cs.allsum(e[own].sum()))
                same_sign = bool(cs.allmin(int(np.all(e[own] * tot >= 0.0))))
                shape = e / tot if tot != 0.0 and same_sign else by_area
                out[:, NPATH * k + p] = e + shape * (owed / dt)
                self.sent[k, p] += float(cs.allsum(out[own, NPATH * k + p].sum())) * dt
        return out


def _contact_points(w, x):
    """The points of scene wall w nearest the particle centres x (n, 3)."""
    p = np.asarray(w["point"], float)
    r = x - p
    if w["type"] == "plane":
        n = np.asarray(w["normal"], float)
        return x - (r @ n)[:, None] * n
    a = np.asarray(w["axis"], float)
    s = r @ a
    radial = r - s[:, None] * a
    rho = np.maximum(np.linalg.norm(radial, axis=1), 1e-300)
    return p + s[:, None] * a + radial * (float(w["radius"]) / rho)[:, None]
