"""Particle-to-mesh mapping: void fraction and conservative exchange terms.

Every model produces a *stencil* (:class:`ParticleWeights`): for particle p
a short list of (cell, weight) pairs whose weights sum to exactly 1 (for a
particle located in the mesh).  The weight is the fraction of the particle's
volume - and of every particle quantity - assigned to that cell.  All
per-cell quantities (solid volume, drag coefficient sum, mean particle
velocity, heat source terms) are accumulated with the *same* stencil, so
what leaves the particles enters the gas exactly (up to round-off):
``sum_c V_c * S_c = sum_p q_p`` for every accumulated quantity q.

Models
------
``centre``
    the whole particle volume goes to the cell containing its centre.
``divided``
    the sphere is represented by ``n_satellites`` points (default 29, as in
    CFDEMcoupling's ``divided`` model; here a deterministic set, see
    :func:`satellite_points`), each carrying an equal share of the volume and
    located in the mesh.  If the sphere lies entirely inside its centre's
    (convex) cell - distance from the centre to every face plane >= radius -
    the satellites are skipped (one cell, weight 1).  Satellites outside the
    mesh (sphere overlapping a wall) are dropped and the remaining weights
    renormalised, so the particle volume stays in the domain.
``smoothed``
    compact polynomial kernel ``K(q) = (1 - q^2)^3`` for ``q = r/h < 1``, with
    ``h = kernel_width * V_c^(1/3)`` (default kernel_width = 1.5) from the
    cell c containing the centre, sampled at the centres of c and of its
    point neighbours (27 cells in a hex grid).  Weights
    ``w_i = V_i K(|x_i - x_p| / h) / sum_j V_j K_j`` so the deposited solid
    *fraction* in cell i is proportional to K and the total volume is
    conserved exactly.  On a uniform grid h = 1.5 dx means every cell with
    K > 0 is in the point-neighbour ring, so the mapping is continuous in the
    particle position (no jump when crossing a face).

Lower bound of the void fraction
--------------------------------
``EPS_MIN = 0.3`` (default of ``void_fraction(eps_min=...)``).  Random close
packing of monodisperse spheres gives eps ~ 0.36 and the loosest
polydisperse/dense random packings rarely go below ~0.3, so physical packed
beds are not clipped; values below 0.3 are mapping artefacts (particles
larger than cells, centre model with several particles in a small cell)
and would make the drag closures blow up (Ergun ~ (1-eps)^2/eps, Di Felice
~ eps^(2-chi) with chi up to 3.7).  The clipping is reported (count and
solid volume removed) because it breaks exact conservation of the void
fraction; the exchange terms are never clipped.
"""
from __future__ import annotations

import math
import warnings
from dataclasses import dataclass

import numpy as np
from numba import njit

from .mesh import PolyMesh, _locate_one, _max_violation

__all__ = [
    "EPS_MIN",
    "MODELS",
    "ParticleWeights",
    "satellite_points",
    "compute_weights",
    "solid_volume",
    "void_fraction",
    "accumulate",
    "drag_coefficient_sum",
    "mean_particle_velocity",
    "heat_sources",
    "check_cell_size",
    "averaging_volume",
]

EPS_MIN = 0.3
MODELS = ("centre", "divided", "smoothed")
KERNEL_WIDTH = 1.5     # smoothed model: h = KERNEL_WIDTH * V_c^(1/3)


# --------------------------------------------------------------------------
# Satellite points of the divided model
# --------------------------------------------------------------------------
def satellite_points(n: int = 29) -> np.ndarray:
    """Deterministic quasi-uniform set of ``n`` points in the unit ball, each
    representing 1/n of the ball's volume.

    Construction: one point at the centre represents the core ball of volume
    fraction 1/n; the remaining n-1 points are split over ``n_shells``
    concentric shells of equal point count (volume fraction = count/n, so all
    weights are equal).  In a shell [ra, rb] the points sit at the radius
    that reproduces the shell's second moment,
    ``r^2 = 3/5 (rb^5 - ra^5) / (rb^3 - ra^3)``, so the set has the ball's
    exact second moments; directions are a Fibonacci lattice on a
    hemisphere plus the antipodal points (first moment exactly zero: the
    satellite centroid is the particle centre), each shell rotated by the
    golden angle to decorrelate shells.  n = 29 gives 1 + 2 x 14 points.
    The shells need an even count; an odd remainder is put into the outer
    shell by moving it to the centre point (weights stay equal).
    """
    if n < 1:
        raise ValueError("n_satellites must be >= 1")
    if n == 1:
        return np.zeros((1, 3))
    m = n - 1
    n_shells = max(1, int(round(m ** (1.0 / 3.0) / 1.5)))
    counts = [m // n_shells] * n_shells
    for i in range(m - sum(counts)):
        counts[-1 - i] += 1
    # make every shell count even (antipodal pairs); move leftovers to centre
    n_centre = 1
    for i, c in enumerate(counts):
        if c % 2:
            counts[i] -= 1
            n_centre += 1
    pts = [np.zeros((n_centre, 3))]
    cum = n_centre / n
    ra = cum ** (1 / 3)
    golden = math.pi * (3.0 - math.sqrt(5.0))
    for s, c in enumerate(counts):
        if c == 0:
            continue
        cum += c / n
        rb = min(cum, 1.0) ** (1 / 3)
        r = math.sqrt(0.6 * (rb ** 5 - ra ** 5) / (rb ** 3 - ra ** 3))
        h = c // 2
        k = np.arange(h)
        z = 1.0 - (k + 0.5) / h          # upper hemisphere, z in (0, 1)
        rho = np.sqrt(1.0 - z * z)
        phi = golden * k + s * golden * 0.5 * h
        d = np.stack([rho * np.cos(phi), rho * np.sin(phi), z], axis=1)
        # tilt successive shells about x to avoid aligned poles
        a = 0.5 * s
        R = np.array([[1, 0, 0], [0, math.cos(a), -math.sin(a)], [0, math.sin(a), math.cos(a)]])
        d = d @ R.T
        pts.append(r * np.concatenate([d, -d]))
        ra = rb
    out = np.concatenate(pts)
    assert len(out) == n
    return out


# --------------------------------------------------------------------------
# Stencil
# --------------------------------------------------------------------------
@dataclass
class ParticleWeights:
    """Particle -> cell stencil.

    ``cells[p, k]`` (int64, -1 = unused slot) and ``weights[p, k]`` (fraction
    of particle p assigned to that cell; each row sums to 1, or 0 for a
    particle outside the mesh).  ``centre_cell[p]`` is the cell containing
    the particle centre (use it as the locate hint next time).
    """
    model: str
    cells: np.ndarray
    weights: np.ndarray
    centre_cell: np.ndarray
    n_cells: int

    @property
    def n_lost(self) -> int:
        """Number of particles not mapped to any cell (outside the mesh)."""
        return int(np.sum(self.weights.sum(axis=1) == 0.0))


@njit(cache=True, error_model="numpy")
def _divided_kernel(pos, rad, cc, sat, L, tol, max_walk):
    """Satellite weights of each particle (L: the mesh's coupling.mesh.Locator)."""
    cf_off, cf_centre, cf_normal = L.cf_off, L.cf_centre, L.cf_normal
    n = pos.shape[0]
    ns = sat.shape[0]
    cells = np.full((n, ns), -1, np.int64)
    weights = np.zeros((n, ns))
    tmp = np.empty(ns, np.int64)
    for p in range(n):
        c0 = cc[p]
        r = rad[p]
        if c0 >= 0:
            dmax, kb = _max_violation(pos[p, 0], pos[p, 1], pos[p, 2], c0, cf_off,
                                      cf_centre, cf_normal)
            if dmax <= -r:  # whole sphere inside the (convex) centre cell
                cells[p, 0] = c0
                weights[p, 0] = 1.0
                continue
        n_in = 0
        for s in range(ns):
            c = _locate_one(pos[p, 0] + r * sat[s, 0], pos[p, 1] + r * sat[s, 1],
                            pos[p, 2] + r * sat[s, 2], c0, L, tol, max_walk)
            tmp[s] = c
            if c >= 0:
                n_in += 1
        if n_in == 0:
            continue
        w = 1.0 / n_in
        k = 0
        for s in range(ns):
            c = tmp[s]
            if c < 0:
                continue
            found = False
            for j in range(k):
                if cells[p, j] == c:
                    weights[p, j] += w
                    found = True
                    break
            if not found:
                cells[p, k] = c
                weights[p, k] = w
                k += 1
    return cells, weights


@njit(cache=True, error_model="numpy")
def _smoothed_kernel(pos, cc, cell_centres, cell_volumes, nb_off, nb_cells, width, kmax):
    n = pos.shape[0]
    cells = np.full((n, kmax), -1, np.int64)
    weights = np.zeros((n, kmax))
    for p in range(n):
        c0 = cc[p]
        if c0 < 0:
            continue
        h = width * cell_volumes[c0] ** (1.0 / 3.0)
        tot = 0.0
        k = 0
        for s in range(nb_off[c0], nb_off[c0 + 1]):
            c = nb_cells[s]
            d2 = 0.0
            for d in range(3):
                t = cell_centres[c, d] - pos[p, d]
                d2 += t * t
            q2 = d2 / (h * h)
            if q2 < 1.0:
                t = 1.0 - q2
                w = cell_volumes[c] * t * t * t
                cells[p, k] = c
                weights[p, k] = w
                tot += w
                k += 1
        if tot > 0.0:
            for j in range(k):
                weights[p, j] /= tot
        else:  # degenerate (very skewed cell): fall back to centre
            cells[p, 0] = c0
            weights[p, 0] = 1.0
    return cells, weights


@njit(cache=True, error_model="numpy")
def _kernel_hh(cell_volumes, width):
    """(width V_c^(1/3))^2 per cell, the same arithmetic as in _smoothed_kernel."""
    nc = cell_volumes.shape[0]
    out = np.empty(nc)
    for c in range(nc):
        h = width * cell_volumes[c] ** (1.0 / 3.0)
        out[c] = h * h
    return out


@njit(cache=True, error_model="numpy")
def _smoothed_weights_into(pos, cc, cell_centres, cell_volumes, hh, nb_off, nb_cells, cells, weights):
    """_smoothed_kernel with the per-cell h^2 precomputed (``_kernel_hh``), writing into
    preallocated (n, kmax) arrays. Bitwise equal to _smoothed_kernel. Serial on purpose:
    it runs right after the (serial) DEM interval, when numba's worker threads sleep and,
    on a busy machine, the second core is taken by the gas solver or other jobs (a
    prange loop then waits for a descheduled thread)."""
    n = pos.shape[0]
    kmax = cells.shape[1]
    for p in range(n):
        for j in range(kmax):
            cells[p, j] = -1
            weights[p, j] = 0.0
        c0 = cc[p]
        if c0 < 0:
            continue
        h2 = hh[c0]
        tot = 0.0
        k = 0
        for s in range(nb_off[c0], nb_off[c0 + 1]):
            c = nb_cells[s]
            d2 = 0.0
            for d in range(3):
                t = cell_centres[c, d] - pos[p, d]
                d2 += t * t
            q2 = d2 / h2
            if q2 < 1.0:
                t = 1.0 - q2
                w = cell_volumes[c] * t * t * t
                cells[p, k] = c
                weights[p, k] = w
                tot += w
                k += 1
        if tot > 0.0:
            for j in range(k):
                weights[p, j] /= tot
        else:  # degenerate (very skewed cell): fall back to centre
            cells[p, 0] = c0
            weights[p, 0] = 1.0


@njit(cache=True, error_model="numpy")
def _scatter1(cells, weights, values, n_cells):
    """_scatter for one quantity (same summation order: particle, then slot)."""
    out = np.zeros(n_cells)
    n, k = cells.shape
    for p in range(n):
        v = values[p]
        for j in range(k):
            c = cells[p, j]
            if c >= 0:
                out[c] += weights[p, j] * v
    return out


_SAT_CACHE: dict = {}


def _smoothed_tables(mesh: PolyMesh, kernel_width: float):
    """(nb_off, nb_cells, kmax, h^2 per cell) of the smoothed model, cached on the mesh."""
    cache = mesh.__dict__.setdefault("_smoothed_cache", {})
    t = cache.get(kernel_width)
    if t is None:
        off, nbrs = mesh.point_neighbours()
        kmax = int(np.diff(off).max())
        hh = _kernel_hh(np.ascontiguousarray(mesh.cell_volumes, np.float64), float(kernel_width))
        t = cache[kernel_width] = (off, nbrs, kmax, hh)
    return t


def compute_weights(mesh: PolyMesh, positions, radii, model: str = "divided",
                    cell_hint=None, n_satellites: int = 29,
                    kernel_width: float = KERNEL_WIDTH, located=None, out=None) -> ParticleWeights:
    """Build the particle -> cell stencil for ``model`` in
    ('centre', 'divided', 'smoothed').  ``cell_hint`` = previous centre cells
    (speeds up location); ``located`` = the centre cells already located
    (``mesh.locate(positions)``: skips locating again).  ``out`` = a previous
    ParticleWeights of the same model and shape whose arrays may be overwritten
    (smoothed model; saves the allocation)."""
    if model not in MODELS:
        raise ValueError(f"unknown void fraction model {model!r}; valid: {', '.join(MODELS)}")
    pos = np.ascontiguousarray(np.asarray(positions, np.float64).reshape(-1, 3))
    rad = np.ascontiguousarray(np.broadcast_to(np.asarray(radii, np.float64), (len(pos),)))
    if located is not None:
        cc = np.ascontiguousarray(located, dtype=np.int64)
        if cc.shape != (len(pos),):
            raise ValueError("located must have one entry per particle")
    else:
        cc = mesh.locate(pos, hint=cell_hint)
    n = len(pos)
    if model == "centre":
        cells = cc.reshape(n, 1).copy()
        weights = (cc >= 0).astype(np.float64).reshape(n, 1)
    elif model == "divided":
        sat = _SAT_CACHE.get(n_satellites)
        if sat is None:
            sat = _SAT_CACHE[n_satellites] = satellite_points(n_satellites)
        cells, weights = _divided_kernel(pos, rad, cc, sat, mesh.locator(), mesh.tol, 64)
    else:
        off, nbrs, kmax, hh = _smoothed_tables(mesh, float(kernel_width))
        if (out is not None and out.model == "smoothed" and out.cells.shape == (n, kmax)
                and out.n_cells == mesh.n_cells):
            cells, weights = out.cells, out.weights
        else:
            cells, weights = np.empty((n, kmax), np.int64), np.empty((n, kmax))
        _smoothed_weights_into(pos, cc, mesh.cell_centres, mesh.cell_volumes, hh, off, nbrs,
                               cells, weights)
    return ParticleWeights(model, cells, weights, cc, mesh.n_cells)


# --------------------------------------------------------------------------
# Accumulation (scatter) - same stencil for every quantity
# --------------------------------------------------------------------------
@njit(cache=True, error_model="numpy")
def _scatter(cells, weights, values, n_cells):
    n, k = cells.shape
    m = values.shape[1]
    out = np.zeros((n_cells, m))
    for p in range(n):
        for j in range(k):
            c = cells[p, j]
            if c < 0:
                continue
            w = weights[p, j]
            for i in range(m):
                out[c, i] += w * values[p, i]
    return out


def accumulate(pw: ParticleWeights, values, cell_volumes=None) -> np.ndarray:
    """Per-cell sum of ``weight * value`` over particles; divided by the cell
    volume when ``cell_volumes`` is given.  ``values`` is (n,) or (n, m)."""
    v = np.asarray(values, np.float64)
    scalar = v.ndim == 1
    v2 = np.ascontiguousarray(v.reshape(len(v), -1))
    if len(v2) != len(pw.cells):
        raise ValueError("values must have one row per particle")
    out = _scatter(pw.cells, pw.weights, v2, pw.n_cells)
    if cell_volumes is not None:
        out /= np.asarray(cell_volumes)[:, None]
    return out[:, 0] if scalar else out


def particle_volumes(radii) -> np.ndarray:
    return (4.0 / 3.0) * np.pi * np.asarray(radii, np.float64) ** 3


def solid_volume(pw: ParticleWeights, radii, volumes=None) -> np.ndarray:
    """Per-cell solid volume [m^3] (sum equals the total particle volume of
    the mapped particles to round-off).  ``volumes`` = the particle volumes
    (``particle_volumes(radii)``) if already known."""
    vp = particle_volumes(radii) if volumes is None else volumes
    vp = np.ascontiguousarray(np.broadcast_to(np.asarray(vp, np.float64), (len(pw.cells),)))
    return _scatter1(pw.cells, pw.weights, vp, pw.n_cells)


def void_fraction(mesh: PolyMesh, positions, radii, model: str = "divided",
                  eps_min: float = EPS_MIN, cell_hint=None, return_weights: bool = False,
                  warn: bool = True, **kw):
    """Fluid volume fraction per cell, ``max(1 - V_solid/V_cell, eps_min)``.

    Returns ``eps`` or ``(eps, ParticleWeights)`` when ``return_weights``.
    Extra keywords (``n_satellites``, ``kernel_width``) go to
    :func:`compute_weights`.  A warning reports clipped cells and particles
    outside the mesh.
    """
    pw = compute_weights(mesh, positions, radii, model, cell_hint=cell_hint, **kw)
    alpha_s = solid_volume(pw, radii) / mesh.cell_volumes
    eps = 1.0 - alpha_s
    clipped = eps < eps_min
    if warn and np.any(clipped):
        lost = float(np.sum((eps_min - eps[clipped]) * mesh.cell_volumes[clipped]))
        warnings.warn(f"void fraction clipped to eps_min={eps_min} in {int(clipped.sum())} "
                      f"cells (solid volume removed {lost:.3e} m^3); cells too small for "
                      "the particles? use 'divided'/'smoothed' or a coarser mesh",
                      RuntimeWarning, stacklevel=2)
    if warn and pw.n_lost:
        warnings.warn(f"{pw.n_lost} particles outside the mesh are not mapped",
                      RuntimeWarning, stacklevel=2)
    eps = np.maximum(eps, eps_min)
    return (eps, pw) if return_weights else eps


def drag_coefficient_sum(pw: ParticleWeights, beta_p, cell_volumes) -> np.ndarray:
    """Ksl per cell [kg/(m^3 s)] = sum_p w_pc beta_p / V_c, with beta_p the
    particle drag coefficient (N per m/s; F_p = beta_p (u_f - u_p)), i.e.
    the per-volume coefficient Ksl_p times V_p.  The implicit momentum
    source on the gas is ``-Ksl (U_f - U_s)``."""
    return accumulate(pw, np.broadcast_to(np.asarray(beta_p, float), (len(pw.cells),)),
                      cell_volumes)


def mean_particle_velocity(pw: ParticleWeights, radii, velocities, weights=None) -> np.ndarray:
    """Volume-weighted mean particle velocity Us per cell (zero in empty
    cells).  Pass ``weights=beta_p`` to get the drag-weighted mean that makes
    ``Ksl (U_f - Us)`` equal to the summed particle drags for a uniform U_f."""
    wp = particle_volumes(radii) if weights is None else np.asarray(weights, float)
    wp = np.broadcast_to(wp, (len(pw.cells),))
    v = np.asarray(velocities, float).reshape(-1, 3)
    num = accumulate(pw, v * wp[:, None])
    den = accumulate(pw, wp)
    out = np.zeros_like(num)
    nz = den > 0
    out[nz] = num[nz] / den[nz, None]
    return out


def heat_sources(pw: ParticleWeights, hA, T_p, cell_volumes):
    """Gas energy sources from particle-gas convection Q_p = hA_p (T_p - T_g):
    ``Simp = sum w hA / V_c`` [W/(m^3 K)], ``Sexp = sum w hA T_p / V_c``
    [W/m^3]; the gas source is ``Sexp - Simp T_g`` (implicit in T_g)."""
    n = len(pw.cells)
    hA = np.broadcast_to(np.asarray(hA, float), (n,))
    T_p = np.broadcast_to(np.asarray(T_p, float), (n,))
    out = accumulate(pw, np.stack([hA, hA * T_p], axis=1), cell_volumes)
    return out[:, 0].copy(), out[:, 1].copy()


def check_cell_size(cell_volumes, radii, factor: float = 3.0, warn: bool = True) -> bool:
    """True if the smallest cell (cube-root of volume) is at least ``factor``
    largest particle diameters; otherwise warn (unresolved CFD-DEM assumes
    cells several particle diameters wide; with smaller cells use the
    divided or smoothed model)."""
    cv = np.asarray(cell_volumes, float)
    r = np.asarray(radii, float)
    if cv.size == 0 or r.size == 0:
        return True
    lmin = float(np.cbrt(cv.min()))
    dmax = 2.0 * float(r.max())
    ok = lmin >= factor * dmax
    if not ok and warn:
        n_small = int(np.sum(np.cbrt(cv) < factor * dmax))
        warnings.warn(f"{n_small} cells are smaller than {factor:g} particle diameters "
                      f"(smallest cell size {lmin:.3g} m, d_max {dmax:.3g} m = "
                      f"{lmin / dmax:.2f} d): void fraction from 'centre' will be noisy; "
                      "use 'divided' or 'smoothed' or coarsen the mesh",
                      RuntimeWarning, stacklevel=2)
    return ok


def averaging_volume(mesh: PolyMesh, model: str, radius: float, n_satellites: int = 29,
                     kernel_width: float = KERNEL_WIDTH) -> np.ndarray:
    """Per cell c, the volume over which ``model`` averages the solid volume of one particle
    of ``radius`` centred in c: ``V_c / w_cc``, with w_cc the weight the model gives c itself
    (the real stencil, on this mesh). One particle then changes the solid fraction of a cell
    by at most ``V_p / averaging_volume``. 'centre' (and 'divided' for a particle inside the
    cell): V_c. 'smoothed': about 2.1 V_c on a uniform hex grid (the kernel volume
    int K dV = 64 pi h^3 / 315 = 2.15 V_c at h = 1.5 V_c^(1/3), discretely 1 + 6 K(2/3) +
    12 K(sqrt(2)/1.5) = 2.05). Used by the cell-size check (coupling.case)."""
    pos = np.ascontiguousarray(mesh.cell_centres, np.float64)
    pw = compute_weights(mesh, pos, np.full(len(pos), float(radius)), model, n_satellites=n_satellites,
                         kernel_width=kernel_width, located=np.arange(mesh.n_cells, dtype=np.int64))
    own = np.where(pw.cells == np.arange(mesh.n_cells)[:, None], pw.weights, 0.0).sum(axis=1)
    return np.asarray(mesh.cell_volumes, float) / np.maximum(own, 1e-300)
