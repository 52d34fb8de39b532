"""Per-wall heat records by path: wall_heat.csv (issue 14).

Each thermal wall's heat since the start is kept per path in the run's state (dem.schema:
``wtot``, all paths, ``wgap``, indirect conduction across the gas gap, and ``wrad``, radiation
(a fixed-temperature wall with an emissivity, dem.thermal.radiation); the rest went through
the contacts: the direct model's wall form at a fixed-temperature wall, A_c q_w at a fixed-flux
wall, reference 001). ``WallHeatFile`` writes them as rows

    time, wall, mechanism, energy_J, heat_rate_W, heat_flux_W_m2, area_m2

with mechanism ``contact``, ``gas_gap``, ``radiation`` (a wall in the radiation environment
only), for a wall tied to a patch of the gas
mesh in a coupled run (coupling.energy) ``gas_convection`` (the gas's own heat from the wall:
the solver's wall conduction), and ``total`` (their sum); heat_rate_W is the mean over the
interval since the previous row (energy difference over time difference; 0 on the first row),
heat_flux_W_m2 = heat_rate_W / area_m2, and the sign is that of the heat given to the
particles (positive: the wall heats the bed). energy_J is written to 17 digits, so that a
continued run (--restart) takes exactly the interval means of an uninterrupted one.
"""
from __future__ import annotations

import math
import os

import numpy as np

MECHANISMS = ("contact", "gas_gap", "radiation", "gas_convection", "total")
COLUMNS = ("time", "wall", "mechanism", "energy_J", "heat_rate_W", "heat_flux_W_m2", "area_m2")


def _box_corners(lo, hi):
    return np.array([[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1]) for z in (lo[2], hi[2])], float)


_EDGES = [(0, 1), (2, 3), (4, 5), (6, 7), (0, 2), (1, 3), (4, 6), (5, 7), (0, 4), (1, 5), (2, 6), (3, 7)]


def plane_section_area(point, normal, lo, hi):
    """Area of the section of the box [lo, hi] by the plane through ``point`` with ``normal``
    (0 when they do not meet): the convex polygon of the plane's crossings of the box edges."""
    n = np.asarray(normal, float)
    n = n / np.linalg.norm(n)
    c = _box_corners(lo, hi)
    s = (c - np.asarray(point, float)) @ n
    pts = []
    for a, b in _EDGES:
        if s[a] == 0.0:
            pts.append(c[a])
        if s[a] * s[b] < 0.0:
            pts.append(c[a] + (c[b] - c[a]) * (s[a] / (s[a] - s[b])))
    if s[-1] == 0.0:
        pts.append(c[-1])
    if len(pts) < 3:
        return 0.0
    p = np.unique(np.round(np.array(pts), 15), axis=0)
    if len(p) < 3:
        return 0.0
    u = np.cross(n, [1.0, 0.0, 0.0] if abs(n[0]) < 0.9 else [0.0, 1.0, 0.0])
    u /= np.linalg.norm(u)
    v = np.cross(n, u)
    m = p.mean(axis=0)
    q = np.c_[(p - m) @ u, (p - m) @ v]
    order = np.argsort(np.arctan2(q[:, 1], q[:, 0]))
    q = q[order]
    x, y = q[:, 0], q[:, 1]
    return float(0.5 * abs(np.dot(x, np.roll(y, -1)) - np.dot(y, np.roll(x, -1))))


def line_length_in_box(point, axis, lo, hi):
    """Length of the line through ``point`` along ``axis`` inside the box [lo, hi]."""
    p = np.asarray(point, float)
    a = np.asarray(axis, float)
    a = a / np.linalg.norm(a)
    t0, t1 = -math.inf, math.inf
    for k in range(3):
        if abs(a[k]) < 1e-300:
            if not (lo[k] <= p[k] <= hi[k]):
                return 0.0
            continue
        ta, tb = (lo[k] - p[k]) / a[k], (hi[k] - p[k]) / a[k]
        t0, t1 = max(t0, min(ta, tb)), min(t1, max(ta, tb))
    return max(0.0, t1 - t0)


def _clip(poly, k, bound, sign):
    """The convex polygon ``poly`` (a list of points) clipped to sign (x_k - bound) >= 0
    (Sutherland & Hodgman 1974)."""
    out = []
    for i in range(len(poly)):
        a, b = poly[i], poly[(i + 1) % len(poly)]
        sa, sb = sign * (a[k] - bound), sign * (b[k] - bound)
        if sa >= 0.0:
            out.append(a)
        if (sa >= 0.0) != (sb >= 0.0):
            out.append(a + (b - a) * (sa / (sa - sb)))
    return out


def mesh_area_in_box(verts, faces, lo, hi):
    """Area of the triangles ``verts[faces]`` inside the box [lo, hi]: the triangles wholly
    inside summed at once, those crossing a face clipped by the box's six half-spaces (a
    mesh longer than a periodic domain, a vessel cut by the domain box)."""
    lo, hi = np.asarray(lo, float), np.asarray(hi, float)
    tri = np.asarray(verts, float)[np.asarray(faces)]
    inside = np.all((tri >= lo) & (tri <= hi), axis=(1, 2))
    beyond = np.any(np.all(tri < lo, axis=1) | np.all(tri > hi, axis=1), axis=1)
    t = tri[inside]
    total = float(0.5 * np.linalg.norm(np.cross(t[:, 1] - t[:, 0], t[:, 2] - t[:, 0]), axis=1).sum())
    for t in tri[~inside & ~beyond]:
        poly = list(t)
        for k in range(3):
            for bound, sign in ((lo[k], 1.0), (hi[k], -1.0)):
                if len(poly) >= 3:
                    poly = _clip(poly, k, bound, sign)
        if len(poly) >= 3:
            p = np.array(poly)
            total += 0.5 * float(np.linalg.norm(np.cross(p[1:-1] - p[0], p[2:] - p[0]).sum(axis=0)))
    return total


def wall_area(w, lo, hi):
    """Area (m^2) of scene wall ``w`` (dem.scene) that particles in the domain box [lo, hi]
    can touch: a mesh's triangles inside the box (at their place at t = 0), a bounded plane's rectangle (one face, 4 e_u e_v), an unbounded plane's section
    of the box, a cylinder's lateral surface 2 pi R L over its length (an unbounded one: over
    the part of its axis inside the box)."""
    if w["type"] == "mesh":
        return mesh_area_in_box(w["surface"].verts, w["surface"].faces, lo, hi)
    if w["type"] == "plane":
        ext = w.get("extent")
        if ext is not None:
            return 4.0 * float(ext[0]) * float(ext[1])
        return plane_section_area(w["point"], w["normal"], lo, hi)
    length = float(w["length"])
    if not math.isfinite(length):
        length = line_length_in_box(w["point"], w["axis"], lo, hi)
    return 2.0 * math.pi * float(w["radius"]) * length


def radiating_walls(scene):
    """[n_walls] bool: the walls in the particles' radiation environment (a radiation model, a
    fixed-temperature wall with an emissivity > 0)."""
    th = scene.thermal
    if th is None or th.get("radiation_id", -1) < 0:
        return [False] * len(scene.walls)
    return [w["emissivity"] > 0.0 for w in th["walls"]]


class WallHeatFile:
    """wall_heat.csv, rewritten atomically at each output (dem.output.write_text). A continued
    run keeps the rows up to its restart time and takes its interval means from them."""

    def __init__(self, path, scene, keep_until=None):
        """The file of ``scene``'s walls (their areas within its domain box)."""
        self.path = path
        lo, hi = scene.domain["min"], scene.domain["max"]
        self.names = [w["name"] for w in scene.walls]
        self.areas = [wall_area(w, lo, hi) for w in scene.walls]
        self.radiates = radiating_walls(scene)
        self.lines = []
        self.last = None  # (time, energies[n_walls, 3]) of the previous row
        if keep_until is not None and os.path.exists(path):
            self._keep(keep_until)

    def _keep(self, keep_until):
        import csv
        with open(self.path, newline="") as f:
            rows = [r for r in csv.DictReader(f) if float(r["time"]) <= keep_until + 1e-15]
        last = {}
        for r in rows:
            self.lines.append(",".join(r[c] for c in COLUMNS) + "\n")
            last[(r["wall"], r["mechanism"])] = (float(r["time"]), float(r["energy_J"]))
        if rows:
            t = float(rows[-1]["time"])
            e = np.zeros((len(self.names), len(MECHANISMS)))
            for k, name in enumerate(self.names):
                for j, mech in enumerate(MECHANISMS):
                    te = last.get((name, mech))
                    if te is None and mech == "radiation":   # a file from before the radiation records
                        e[k, j] = 0.0
                    else:
                        e[k, j] = te[1] if te is not None and te[0] == t else math.nan
            self.last = (t, e)

    def add(self, t, totals, gas=None):
        """totals: [n_walls, 3] of the particles' (all paths, gas gap, radiation) in J since the start;
        gas: [n_walls] the gas's own heat from each tied wall in J (NaN: not tied; None: no
        tied walls)."""
        from ..output import write_text
        tot = np.asarray(totals, float)
        g = np.full(len(tot), math.nan) if gas is None else np.asarray(gas, float)
        tied = np.isfinite(g)
        e = np.c_[tot[:, 0] - tot[:, 1] - tot[:, 2], tot[:, 1], tot[:, 2], g, tot[:, 0] + np.where(tied, g, 0.0)]
        # the time as written (12 digits) and the energies exactly (17): a continued run reads
        # them back and takes the same interval means as an uninterrupted one
        t = float(f"{t:.12g}")
        if self.last is not None and t > self.last[0]:
            rate = (e - self.last[1]) / (t - self.last[0])
        else:
            rate = np.zeros_like(e)
        for k, name in enumerate(self.names):
            a = self.areas[k]
            for j, mech in enumerate(MECHANISMS):
                if (mech == "gas_convection" and not tied[k]) or (mech == "radiation" and not self.radiates[k]):
                    continue
                q = rate[k, j] / a if a > 0 else math.nan
                self.lines.append(f"{t:.12g},{name},{mech},{float(e[k, j])!r},{rate[k, j]:.12g},{q:.12g},{a:.12g}\n")
        self.last = (t, e)
        write_text(self.path, ",".join(COLUMNS) + "\n" + "".join(self.lines))


# --------------------------------------------------------------------------- by angle

ANGLE_COLUMNS = ("time", "wall", "angle_deg", "contact_W_m2", "gas_gap_W_m2", "radiation_W_m2")
ANGLE_BINS = 24   # 15 degree sectors


def _angle_frame(w, gravity):
    """Unit vectors (e0, e1) normal to the cylinder's axis: e0 points up (against gravity,
    projected; a vertical cylinder takes any normal), e1 = axis x e0; the angle is measured
    from e0 and turns about the axis by the right-hand rule (0 deg: the top of a horizontal
    tube, 180 deg: its bottom, facing the rising gas)."""
    a = np.asarray(w["axis"], float)
    up = -np.asarray(gravity, float)
    e0 = up - (up @ a) * a
    if np.linalg.norm(e0) < 1e-12 * max(np.linalg.norm(up), 1.0):
        e0 = np.cross(a, [1.0, 0.0, 0.0] if abs(a[0]) < 0.9 else [0.0, 1.0, 0.0])
    e0 = e0 / np.linalg.norm(e0)
    return e0, np.cross(a, e0)


def particle_wall_heat(sim, k):
    """The heat (W) wall ``k`` gives each owned particle it touches or reaches now, by path:
    (rows, contact, gas_gap, radiation). Each wall conductance (dem.schema ``Hw``, its gas-gap
    part ``Hwg``) times T_w - T_i at a fixed-temperature wall, A_c q_w (all through the contact)
    at a fixed-flux wall; the wall's part of each particle's radiation (dem.thermal.heat.
    wall_radiation_now) at a fixed-temperature wall with an emissivity; empty arrays without
    heat, at an adiabatic wall or with no particle in reach."""
    from .heat import WT, TI, wall_temperature, wall_radiation_now
    st = sim.state
    n = st.n_owned
    none = np.zeros(0, np.int64), np.zeros(0), np.zeros(0), np.zeros(0)
    if sim.thermal is None or not n:
        return none
    r0 = int(sim.world.wall_first[k])            # the wall's first row; a mesh has several
    ns = int(sim.scene.walls[k].get("slots", 1))
    cond = int(st.wth[r0, WT.cond])
    if cond == 0:
        return none
    wnb, wnn = st.wnb[:n], st.wnn[:n]
    rows, cols = np.nonzero((wnb >= r0) & (wnb < r0 + ns) & (np.arange(wnb.shape[1])[None, :] < wnn[:, None]))
    if ns > 1:   # a particle touching a mesh at several rows: one entry, the rows' sum
        order = np.argsort(rows, kind="stable")
        rows, cols = rows[order], cols[order]
    H = st.Hw[rows, cols]
    Hg = st.Hwg[rows, cols] if st.Hwg.shape[0] >= n else np.zeros_like(H)   # Hwg: indirect models only
    if ns > 1:
        u, at = np.unique(rows, return_index=True)
        H, Hg, rows = np.add.reduceat(H, at) if H.size else H, np.add.reduceat(Hg, at) if Hg.size else Hg, u
    if cond == 2:   # fixed flux: Hw holds the contact area
        return rows, H * st.wth[r0, WT.q], np.zeros_like(H), np.zeros_like(H)
    dT = wall_temperature(st.wth, st.wtab, r0, sim.time) - st.temperature[rows]
    qc, qg = (H - Hg) * dT, Hg * dT
    if st.thi[TI.wrad] != 1:
        return rows, qc, qg, np.zeros_like(H)
    qr = np.zeros(n)
    P, C, W, TB, prm = st.bundles()
    wall_radiation_now(P, C, W, TB, prm, n, sim.time, r0, qr)
    allr = np.union1d(rows, np.flatnonzero(qr))
    out = np.zeros((3, allr.size))
    pos = np.searchsorted(allr, rows)
    np.add.at(out[0], pos, qc)
    np.add.at(out[1], pos, qg)
    out[2] = qr[allr]
    return allr, out[0], out[1], out[2]


def cylinder_flux_by_angle(sim, n_bins=ANGLE_BINS):
    """The local heat flux from each thermal cylinder wall into the particles by angle, at the
    state's time: ``particle_wall_heat`` binned by the angle of the particle's centre around the
    axis (``_angle_frame``) and divided by the sector's area 2 pi R L / n_bins. Collective over
    the MPI ranks. Returns {wall index: (angles_deg [n_bins] (sector centres), contact [n_bins],
    gas_gap [n_bins], radiation [n_bins]) in W/m^2}; empty without heat."""
    from .heat import WT
    st, sc = sim.state, sim.scene
    out = {}
    if sim.thermal is None:
        return out
    lo, hi = sc.domain["min"], sc.domain["max"]
    edges = np.linspace(0.0, 360.0, n_bins + 1)
    centres = 0.5 * (edges[:-1] + edges[1:])
    for k, w in enumerate(sc.walls):
        if w["type"] != "cylinder" or int(st.wth[int(sim.world.wall_first[k]), WT.cond]) == 0:
            continue
        e0, e1 = _angle_frame(w, sc.simulation["gravity"])
        sums = np.zeros((3, n_bins))
        rows, *q = particle_wall_heat(sim, k)
        if rows.size:
            r = st.position[rows] - np.asarray(w["point"], float)
            ang = np.degrees(np.arctan2(r @ e1, r @ e0)) % 360.0
            b = np.minimum((ang / (360.0 / n_bins)).astype(np.int64), n_bins - 1)
            for p in range(3):
                sums[p] = np.bincount(b, weights=q[p], minlength=n_bins)
        if sim.par is not None:
            sums = np.asarray(sim.par.allsum(sums.ravel()), float).reshape(3, n_bins)
        area = wall_area(w, lo, hi) / n_bins
        out[k] = (centres, sums[0] / area, sums[1] / area, sums[2] / area)
    return out


class WallAngleFile:
    """wall_heat_angle.csv: at each output, the instantaneous local heat flux into the
    particles from each thermal cylinder wall by angle (``cylinder_flux_by_angle``); the
    time-averaged local coefficient is the mean of the rows over a window. Rewritten
    atomically; a continued run keeps the rows up to its restart time."""

    def __init__(self, path, scene, keep_until=None):
        self.path = path
        self.names = [w["name"] for w in scene.walls]
        self.lines = []
        if keep_until is not None and os.path.exists(path):
            with open(path) as f:
                next(f, None)
                self.lines = [ln for ln in f if ln.strip() and float(ln.split(",", 1)[0]) <= keep_until + 1e-15]
            # rows of a file from before the radiation column: no wall radiated then
            self.lines = [ln if ln.count(",") == len(ANGLE_COLUMNS) - 1 else ln.rstrip("\n") + ",0\n"
                          for ln in self.lines]

    @staticmethod
    def wanted(scene):
        return any(w["type"] == "cylinder" and (w.get("thermal") or {}).get("condition", "adiabatic") != "adiabatic"
                   for w in scene.walls)

    def add(self, t, by_angle):
        from ..output import write_text
        t = float(f"{t:.12g}")
        for k, (ang, qc, qg, qr) in by_angle.items():
            for a, c, g, rr in zip(ang, qc, qg, qr):
                self.lines.append(f"{t:.12g},{self.names[k]},{a:.6g},{c:.12g},{g:.12g},{rr:.12g}\n")
        write_text(self.path, ",".join(ANGLE_COLUMNS) + "\n" + "".join(self.lines))
