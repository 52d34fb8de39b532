"""The void fraction around each particle, for its drag (coupling.toml ``drag_void_fraction``).

The gas keeps the cell void fraction of ``coupling.voidfraction`` (continuity, and the cell
value the exchange is written against); the drag law of a particle is evaluated at the void
fraction of its own neighbourhood, so that a cell that the bed fills only in part (the bed's
top, its floor layer) no longer turns the smeared solid into almost no resistance
(docs/models.md, "The void fraction a particle's drag sees").

Methods
-------
``cell``
    the cell void fraction at the particle (its stencil's mean): the drag as before.
``voronoi``
    the particle's cell of the radical Voronoi tessellation (Voronoi 1908; radical planes for
    spheres of several sizes, Gellatly & Finney 1982), measured by integrating its radius
    function over 128 fixed directions (:func:`voronoi_1908_cell`):
    ``V = 1/3 sum_m rho_m^3 dOmega``, ``rho_m`` the distance from the centre to the nearest
    radical plane of a neighbour, a wall or a non-periodic face of the domain along direction
    m (about 1 % rms from the exact cell volume in a random packing, -0.3 % on average:
    docs/notebook.md). The cell is the particle's cage: the planes of
    its first shell, neighbours to ``r_i + r_j + 1.2 r_max`` (the first minimum of a dense
    packing's pair distribution, 1.5-1.6 d), so every ray shorter than ``lim_i``
    (:func:`exact_reach`, 1.6 r for one size) is exact. A ray the cage leaves open (the open
    side of a particle at the bed's top) takes the length of the opposite ray if a neighbour
    ends that one (the cell the particle would have if its packing went on as behind it: the
    mirror the box faces give in ``dem.thermal.voronoi``); the directions left over (a
    particle in dilute gas) see the gas cell's mixture: their share ``(1 - f) V_p`` of the
    particle fills ``(1 - f) V_p / (1 - eps_cell)``. A lone particle therefore sees its cell's
    void fraction, a particle in a packing its surroundings'.
    The cells are averaged as a ratio, sum of solid over sum of cell volumes, over two hops of
    the first shell (the particle, its first shell and theirs: some 3 d across, stated by
    ``coupling check``): the packing around the particle, without the scatter of single
    cells, which the convex laws would turn into 2-5 % more drag.
``kernel``
    the solid fraction at the particle of the Wendland (1995) C2 kernel of support ``l``
    (``drag_averaging_length``, default 3 d_max): ``phi_i = sum_j V_j W(|x_j - x_i|) / eta_i``,
    self included, ``eta_i`` the part of the kernel inside the walls and the domain (same
    directions as above). Smooth and of stated length, but it smears the bed's ends over l.

Both read the DEM's rows (owned and ghosts): under MPI the ghost layer is widened to the
method's reach (``ParticleVoidFraction.reach``: three hops of the first shell for voronoi),
so each rank sees every neighbour a serial run sees, and the result does not depend on the
layout. Cost (docs/benchmarks.md): about 4.7 us per particle and coupling step for voronoi
(the main example's coupled loop 1.2-1.5 times as long as with cell).
"""
from __future__ import annotations

import math
from collections import namedtuple

import numpy as np
from numba import njit

from dem.contact.walls import wall_distance
from dem.neighbors import Box, _axis_cell, _key_range, _lower_bound, cell_grid

__all__ = ["METHODS", "VORONOI_REACH", "N_DIRECTIONS", "directions", "exact_reach", "neighbour_vectors",
           "voronoi_1908_cell", "wendland_1995_fraction", "ParticleVoidFraction", "KERNEL_LENGTH_D"]

METHODS = ("cell", "voronoi", "kernel")
# what bounds a particle's surroundings: the domain (its non-periodic faces), the walls (Walls
# tables wf, wi of dem.contact.walls) at time t
Bounds = namedtuple("Bounds", "lo hi periodic wf wi t")
# the neighbours of each listed row (CSR): start[i]..start[i + 1] into the vectors x_j - x_i,
# the radii r_j and the rows j
Neighbours = namedtuple("Neighbours", "start vec rj jr")
VORONOI_REACH = 1.2        # the planes of the first shell: neighbours to 1.2 r_max beyond contact (rays to 1.6 r)
N_DIRECTIONS = 128         # about 1 % rms error of a cell volume against the exact tessellation (docs/notebook.md)
KERNEL_LENGTH_D = 3.0      # default support of the kernel method, in largest diameters


def directions(m: int = N_DIRECTIONS) -> np.ndarray:
    """``m`` (even) unit vectors of equal solid angle: a Fibonacci lattice on the upper
    hemisphere and their opposites (row k + m/2 is -row k), so the set has no first moment."""
    h = m // 2
    k = np.arange(h) + 0.5
    z = 1.0 - k / h
    phi = math.pi * (3.0 - math.sqrt(5.0)) * k
    s = np.sqrt(1.0 - z * z)
    up = np.stack([s * np.cos(phi), s * np.sin(phi), z], axis=1)
    return np.ascontiguousarray(np.concatenate([up, -up]))


@njit(cache=True, error_model="numpy")
def exact_reach(ri, rmin, a):
    """Length below which a ray of particle i (radius ri) is bounded exactly when the
    neighbours are searched to the centre distance ri + rj + a: the radical plane of an
    unseen particle j lies at (D^2 + ri^2 - rj^2) / (2 D), D >= ri + rj + a, which grows with
    rj; its least value, at rj = rmin, is (u (a + ri) + a^2/2) / (u + a), u = ri + rmin."""
    u = ri + rmin
    return (u * (a + ri) + 0.5 * a * a) / (u + a)


@njit(cache=True, error_model="numpy")
def _near_image(d, length, periodic):
    """Minimum image of a separation of two rows of the domain (|d| < length): one
    comparison instead of a floor."""
    if periodic:
        if d > 0.5 * length:
            return d - length
        if d < -0.5 * length:
            return d + length
    return d


@njit(cache=True, error_model="numpy")
def _append(vec, rj, jr, m, d0, d1, d2, r, j):
    """Entry m of the list (grown by doubling when full); returns the arrays and m + 1."""
    if m == vec.shape[0]:
        cap = 2 * vec.shape[0]
        v2 = np.empty((cap, 3))
        v2[:m] = vec[:m]
        r2 = np.empty(cap)
        r2[:m] = rj[:m]
        j2 = np.empty(cap, np.int64)
        j2[:m] = jr[:m]
        vec, rj, jr = v2, r2, j2
    vec[m, 0] = d0
    vec[m, 1] = d1
    vec[m, 2] = d2
    rj[m] = r
    jr[m] = j
    return vec, rj, jr, m + 1


@njit(cache=True, error_model="numpy")
def neighbour_vectors(x, r, n, nown, dom, grid, a):
    """For each owned row i the vectors x_j - x_i and radii r_j of every row j < n (owned or
    ghost) with |x_j - x_i| < r_i + r_j + a: minimum image on periodic axes, and the further
    images along a periodic axis shorter than two search reaches (a thin slab sees a
    neighbour on both sides, and itself). Returns CSR (start[nown + 1], vec[m, 3], rj[m]), each
    row's entries in the order of the 27 cells around it (x, then y, then z) and, in a cell, of
    the cell grid's (stable) order."""
    lo, hi, periodic = dom.lo, dom.hi, dom.periodic
    gwrap = grid.periodic
    grid_cells = cell_grid(x, r, n, grid.lo, grid.hi, gwrap, a, 0.0)
    order = grid_cells[4]
    length = hi - lo
    rmax = 0.0
    for i in range(n):
        rmax = max(rmax, r[i])
    short = np.zeros(3, np.bool_)
    for k in range(3):
        short[k] = periodic[k] and length[k] < 2.0 * (2.0 * rmax + a)
    # the rows in cell order: the candidates of a cell are contiguous in memory
    xs = np.empty((n, 3))
    rs = np.empty(n)
    for q in range(n):
        xs[q, 0] = x[order[q], 0]
        xs[q, 1] = x[order[q], 1]
        xs[q, 2] = x[order[q], 2]
        rs[q] = r[order[q]]
    if short[0] or short[1] or short[2]:
        return _neighbour_images(x, r, nown, grid_cells, gwrap, (xs, rs), (length, periodic), short, a)
    cap = 24 * nown + 16   # a dense packing has about 15 a row; more: the rows again, to the count
    while True:
        start = np.zeros(nown + 1, np.int64)
        vec = np.empty((cap, 3))
        rj = np.empty(cap)
        jr = np.empty(cap, np.int64)
        m = _neighbour_rows(x, r, nown, grid_cells, gwrap, (xs, rs), (length, periodic), a, (start, vec, rj, jr))
        if m <= cap:
            return Neighbours(start, vec[:m], rj[:m], jr[:m])
        cap = m


@njit(cache=True, error_model="numpy")
def _neighbour_rows(x, r, nown, grid, gwrap, cell_rows, box, a, out):
    """neighbour_vectors without periodic images beyond the nearest, into (start, vec, rj, jr):
    the entries that fit are stored, every one counted; returns the count (more than the
    arrays hold: call again with arrays of that size). The z cells of a column are scanned as
    runs of consecutive keys, and neither a call taking an array nor an array that may be
    replaced sits in the scan (either counts the array's references up and down at each use:
    5 us a particle instead of 0.7; dem.neighbors._rows_block). ``grid``: :func:`dem.neighbors.cell_grid`'s
    result; ``cell_rows``: (xs, rs), the positions and radii in its order; ``box``: (length,
    periodic) of the minimum image; ``out``: (start, vec, rj, jr)."""
    ncell, cc, cmin, ext, order, table, dense = grid
    xs, rs = cell_rows
    length, periodic = box
    start, vec, rj, jr = out
    l0, l1, l2 = length[0], length[1], length[2]
    p0, p1, p2 = periodic[0], periodic[1], periodic[2]
    cap = rj.shape[0]
    zc = np.empty(3, np.int64)
    m = 0
    for i in range(nown):
        xi0 = x[i, 0]
        xi1 = x[i, 1]
        xi2 = x[i, 2]
        ri = r[i]
        for ox in range(-1, 2):
            ax = _axis_cell(cc[i, 0], ox, ncell[0], gwrap[0], cmin[0], ext[0])
            if ax < 0:
                continue
            for oy in range(-1, 2):
                ay = _axis_cell(cc[i, 1], oy, ncell[1], gwrap[1], cmin[1], ext[1])
                if ay < 0:
                    continue
                nz = 0
                for oz in range(-1, 2):
                    az = _axis_cell(cc[i, 2], oz, ncell[2], gwrap[2], cmin[2], ext[2])
                    if az >= 0:
                        zc[nz] = az
                        nz += 1
                base = ((ax - cmin[0]) * ext[1] + (ay - cmin[1])) * ext[2] - cmin[2]
                t = 0
                while t < nz:
                    za = zc[t]
                    zb = za
                    while t + 1 < nz and zc[t + 1] == zb + 1:
                        t += 1
                        zb = zc[t]
                    t += 1
                    if dense:
                        q0 = table[base + za]
                        q1 = table[base + zb + 1]
                    else:
                        q0 = _lower_bound(table, base + za)
                        q1 = _lower_bound(table, base + zb + 1)
                    for q in range(q0, q1):
                        d0 = _near_image(xs[q, 0] - xi0, l0, p0)
                        d1 = _near_image(xs[q, 1] - xi1, l1, p1)
                        d2 = _near_image(xs[q, 2] - xi2, l2, p2)
                        rc = ri + rs[q] + a
                        if d0 * d0 + d1 * d1 + d2 * d2 < rc * rc:
                            j = order[q]
                            if j == i:
                                continue
                            if m < cap:
                                vec[m, 0] = d0
                                vec[m, 1] = d1
                                vec[m, 2] = d2
                                rj[m] = rs[q]
                                jr[m] = j
                            m += 1
        start[i + 1] = m
    return m


@njit(cache=True, error_model="numpy")
def _neighbour_images(x, r, nown, grid, gwrap, cell_rows, box, short, a):
    """neighbour_vectors on a domain with a periodic axis shorter than two search reaches: the
    further images along the short axes too (and the particle's own images); the arguments
    as :func:`_neighbour_rows`'."""
    ncell, cc, cmin, ext, order, table, dense = grid
    xs, rs = cell_rows
    length, periodic = box
    start = np.zeros(nown + 1, np.int64)
    cap = 32 * nown + 16
    vec = np.empty((cap, 3))
    rj = np.empty(cap)
    jr = np.empty(cap, np.int64)
    m = 0
    for i in range(nown):
        xi0 = x[i, 0]
        xi1 = x[i, 1]
        xi2 = x[i, 2]
        ri = r[i]
        for ox in range(-1, 2):
            ax = _axis_cell(cc[i, 0], ox, ncell[0], gwrap[0], cmin[0], ext[0])
            if ax < 0:
                continue
            for oy in range(-1, 2):
                ay = _axis_cell(cc[i, 1], oy, ncell[1], gwrap[1], cmin[1], ext[1])
                if ay < 0:
                    continue
                for oz in range(-1, 2):
                    az = _axis_cell(cc[i, 2], oz, ncell[2], gwrap[2], cmin[2], ext[2])
                    if az < 0:
                        continue
                    key = ((ax - cmin[0]) * ext[1] + (ay - cmin[1])) * ext[2] + (az - cmin[2])
                    q0, q1 = _key_range(table, dense, key, key)
                    for q in range(q0, q1):
                        j = order[q]
                        d0 = _near_image(xs[q, 0] - xi0, length[0], periodic[0])
                        d1 = _near_image(xs[q, 1] - xi1, length[1], periodic[1])
                        d2 = _near_image(xs[q, 2] - xi2, length[2], periodic[2])
                        rc = ri + rs[q] + a
                        for s0 in range(-1, 2):
                            if s0 != 0 and not short[0]:
                                continue
                            for s1 in range(-1, 2):
                                if s1 != 0 and not short[1]:
                                    continue
                                for s2 in range(-1, 2):
                                    if s2 != 0 and not short[2]:
                                        continue
                                    if j == i and s0 == 0 and s1 == 0 and s2 == 0:
                                        continue
                                    e0 = d0 + s0 * length[0]
                                    e1 = d1 + s1 * length[1]
                                    e2 = d2 + s2 * length[2]
                                    if e0 * e0 + e1 * e1 + e2 * e2 < rc * rc:
                                        vec, rj, jr, m = _append(vec, rj, jr, m, e0, e1, e2, rs[q], j)
        start[i + 1] = m
    return Neighbours(start, vec[:m], rj[:m], jr[:m])


@njit(cache=True, error_model="numpy")
def _bound_by_plane(dx, dy, dz, w0, w1, w2, inv):
    """A plane at distance h from the centre along the unit vector n, given as w = n / h:
    the ray u meets it at h / (u.n) where u.n > 0, so its inverse length is
    max(inv, u.w) (a plane behind the ray, u.n <= 0, never wins). The directions are those of
    :func:`directions`, row k + m/2 the opposite of row k: one dot product serves both rays
    (-u.w for the opposite one, the same bits), and the stores are unconditional, so the loop
    runs as vector instructions."""
    h = inv.shape[0] // 2
    for m in range(h):
        v = dx[m] * w0 + dy[m] * w1 + dz[m] * w2
        a = inv[m]
        inv[m] = v if v > a else a
        b = inv[m + h]
        inv[m + h] = -v if -v > b else b


@njit(cache=True, error_model="numpy")
def _walls_and_faces(i, x, B, dx, dy, dz, lim, inv):
    """The walls and the non-periodic faces of the domain nearer than ``lim`` as planes of
    particle i's cell (a wall by its tangent plane at its nearest point); B: Bounds."""
    lo, hi, periodic, wf, wi, t = B.lo, B.hi, B.periodic, B.wf, B.wi, B.t
    for w in range(wf.shape[0]):
        dist, nx, ny, nz = wall_distance(wf, wi, w, x[i, 0], x[i, 1], x[i, 2], t)
        if dist < lim and dist > 0.0:
            _bound_by_plane(dx, dy, dz, nx / dist, ny / dist, nz / dist, inv)
    for k in range(3):
        if periodic[k]:
            continue
        for side in range(2):
            dist = x[i, k] - lo[k] if side == 0 else hi[k] - x[i, k]
            if dist < lim and dist > 0.0:
                w0 = 0.0
                w1 = 0.0
                w2 = 0.0
                sg = (-1.0 if side == 0 else 1.0) / dist
                if k == 0:
                    w0 = sg
                elif k == 1:
                    w1 = sg
                else:
                    w2 = sg
                _bound_by_plane(dx, dy, dz, w0, w1, w2, inv)


@njit(cache=True, error_model="numpy")
def voronoi_1908_cell(ri, vec, rj, k0, k1, dx, dy, dz, lim, inv):
    """Inverse radius function 1 / rho(u) of particle i's radical Voronoi cell along the
    directions (dx, dy, dz) (Voronoi 1908; radical planes, Gellatly & Finney 1982): for each
    neighbour j at D = |x_j - x_i| along n, the plane {y : |y - x_i|^2 - ri^2 = |y - x_j|^2 -
    rj^2} lies at h = (D^2 + ri^2 - rj^2)/(2 D) from x_i, and a ray u with u.n > 0 meets it at
    h / (u.n). ``inv`` (0: no plane yet) is updated in place; planes at h >= lim are skipped
    (they end no ray shorter than lim). The directions are those of :func:`directions` (row
    k + m/2 opposite to row k: one dot product serves both rays, the same bits;
    :func:`_bound_by_plane` inlined, so that no call taking an array sits in the loop over the
    neighbours)."""
    half = inv.shape[0] // 2
    for k in range(k0, k1):
        v0 = vec[k, 0]
        v1 = vec[k, 1]
        v2 = vec[k, 2]
        dd = v0 * v0 + v1 * v1 + v2 * v2
        if dd <= 0.0:
            continue
        d = math.sqrt(dd)
        h = (dd + ri * ri - rj[k] * rj[k]) / (2.0 * d)
        if h >= lim or h <= 0.0:
            continue
        s = 1.0 / (h * d)
        w0 = v0 * s
        w1 = v1 * s
        w2 = v2 * s
        for m in range(half):
            v = dx[m] * w0 + dy[m] * w1 + dz[m] * w2
            a = inv[m]
            inv[m] = v if v > a else a
            b = inv[m + half]
            inv[m + half] = -v if -v > b else b


@njit(cache=True, error_model="numpy")
def _enclosed_cells(x, r, rows, nb, B, dirs, rmin, a):
    """Pass 1, rows [0, rows): the part of each particle's cell its neighbours enclose.

    Returns (ve, vs): ve the volume of the cones of the directions that a neighbour, a wall or
    a face ends within lim (or whose opposite ray a neighbour ends: reflected), vs the
    particle's own volume in them, f V_p (f their share of the directions). nb: Neighbours,
    B: Bounds."""
    start, vec, rj = nb.start, nb.vec, nb.rj
    m_dirs = dirs.shape[0]
    half = m_dirs // 2
    dx = np.ascontiguousarray(dirs[:, 0])
    dy = np.ascontiguousarray(dirs[:, 1])
    dz = np.ascontiguousarray(dirs[:, 2])
    ve = np.zeros(rows)
    vs = np.zeros(rows)
    inv_nb = np.empty(m_dirs)
    inv = np.empty(m_dirs)
    for i in range(rows):
        ri = r[i]
        lim = exact_reach(ri, rmin, a)
        ilim = 1.0 / lim
        inv_nb[:] = 0.0
        voronoi_1908_cell(ri, vec, rj, start[i], start[i + 1], dx, dy, dz, lim, inv_nb)
        inv[:] = inv_nb
        _walls_and_faces(i, x, B, dx, dy, dz, lim, inv)
        s3 = 0.0
        nb = 0
        for m in range(m_dirs):
            if inv[m] >= ilim:
                s3 += 1.0 / inv[m] ** 3
                nb += 1
            else:
                o = m + half if m < half else m - half   # the opposite ray, if a neighbour ends it
                if inv_nb[o] >= ilim:
                    s3 += 1.0 / inv[o] ** 3
                    nb += 1
        ve[i] = 4.0 / 3.0 * math.pi * s3 / m_dirs
        vs[i] = 4.0 / 3.0 * math.pi * ri ** 3 * nb / m_dirs
    return ve, vs


@njit(cache=True, error_model="numpy")
def _average(rows, nb, ve, vs, hop):
    """One hop of the average, rows [0, rows): the particle's own (ve, vs) plus its
    neighbours' nearer than ``hop`` (its first shell), with equal weights. Two hops average
    over the first shells of the first shell, some 3 diameters across: the sums of cell and
    solid volumes, a ratio estimator, so a particle's law sees the packing of its
    surroundings, not the few-percent scatter of its own cell (which, through the convex
    laws, would raise the bed's drag by 2-5 %). nb: Neighbours."""
    start, vec, jr = nb.start, nb.vec, nb.jr
    ae = np.empty(rows)
    av = np.empty(rows)
    h2 = hop * hop
    for i in range(rows):
        se = ve[i]
        sv = vs[i]
        for k in range(start[i], start[i + 1]):
            if vec[k, 0] ** 2 + vec[k, 1] ** 2 + vec[k, 2] ** 2 < h2:
                se += ve[jr[k]]
                sv += vs[jr[k]]
        ae[i] = se
        av[i] = sv
    return ae, av


@njit(cache=True, error_model="numpy")
def _voronoi_all(r, nown, vs, se, sv, eps_cell, eps_min):
    """Owned rows: the enclosed solid fraction averaged around the particle,
    phi = sv / se (the averages of vs and ve), for the enclosed share f of the particle; the
    rest, (1 - f) V_p, in the cell's mixture: V_cell = f V_p / phi + (1 - f) V_p / (1 - eps_cell),
    eps = 1 - V_p / V_cell."""
    out = np.ones(nown)
    for i in range(nown):
        vp = 4.0 / 3.0 * math.pi * r[i] ** 3
        f = vs[i] / vp
        vcell = f * vp * se[i] / sv[i] if sv[i] > 0.0 else 0.0
        ec = eps_cell[i]
        if f < 1.0:
            if ec >= 1.0:
                continue   # out[i] = 1: part of the particle sees gas only
            vcell += (1.0 - f) * vp / (1.0 - ec)
        e = 1.0 - vp / vcell if vcell > 0.0 else 1.0
        out[i] = min(1.0, max(e, eps_min))
    return out


@njit(cache=True, error_model="numpy")
def _wendland_cumulative(q):
    """Share of the Wendland C2 kernel's volume within q = s / l of its centre:
    42 (q^3/3 - 2 q^5 + 10 q^6 / 3 - 15 q^7 / 7 + q^8 / 2), 1 at q = 1."""
    if q >= 1.0:
        return 1.0
    return 42.0 * (q ** 3 / 3.0 - 2.0 * q ** 5 + 10.0 * q ** 6 / 3.0 - 15.0 * q ** 7 / 7.0 + 0.5 * q ** 8)


@njit(cache=True, error_model="numpy")
def wendland_1995_fraction(ri, vec, rj, k0, k1, ell, eta):
    """Solid fraction at particle i of the Wendland (1995) C2 kernel of support ell,
    W(q) = 21 / (2 pi l^3) (1 - q)^4 (1 + 4 q), q = s / l < 1 (unit integral in 3-D), over
    the particle (W(0)) and its neighbours, each its volume at its centre; ``eta`` the part of
    the kernel inside the walls and the domain."""
    c = 21.0 / (2.0 * math.pi * ell ** 3)
    s = 4.0 / 3.0 * math.pi * ri ** 3
    for k in range(k0, k1):
        d = math.sqrt(vec[k, 0] ** 2 + vec[k, 1] ** 2 + vec[k, 2] ** 2)
        q = d / ell
        if q < 1.0:
            s += 4.0 / 3.0 * math.pi * rj[k] ** 3 * (1.0 - q) ** 4 * (1.0 + 4.0 * q)
        # (the particle itself: (1 - 0)^4 (1 + 0) = 1)
    return c * s / eta


@njit(cache=True, error_model="numpy")
def _kernel_all(x, r, nown, nb, B, dirs, ell, eps_min):
    """The kernel method's void fraction of the owned rows (nb: Neighbours, B: Bounds)."""
    start, vec, rj = nb.start, nb.vec, nb.rj
    m_dirs = dirs.shape[0]
    dx = np.ascontiguousarray(dirs[:, 0])
    dy = np.ascontiguousarray(dirs[:, 1])
    dz = np.ascontiguousarray(dirs[:, 2])
    out = np.ones(nown)
    inv = np.empty(m_dirs)
    for i in range(nown):
        inv[:] = 0.0
        _walls_and_faces(i, x, B, dx, dy, dz, ell, inv)
        eta = 0.0
        for m in range(m_dirs):
            eta += _wendland_cumulative(1.0 / (inv[m] * ell)) if inv[m] > 0.0 else 1.0
        eta /= m_dirs
        phi = wendland_1995_fraction(r[i], vec, rj, start[i], start[i + 1], ell, max(eta, 1e-12))
        out[i] = min(1.0, max(1.0 - phi, eps_min))
    return out


class ParticleVoidFraction:
    """The void fraction around each owned particle, by ``method`` (METHODS).

    ``length`` (kernel): the kernel's support (m), None for KERNEL_LENGTH_D largest diameters;
    voronoi averages its cells over two hops of the first shell, 2 (2 r_max + search) (3.2
    diameters of one size). ``reach``: how far beyond contact (r_i + r_j + reach)
    each rank must see particles, which the DEM's ghost layer covers (dem.world.World
    ghost_reach)."""

    def __init__(self, method: str, rmax: float, length: float | None = None, n_directions: int = N_DIRECTIONS):
        if method not in METHODS:
            raise ValueError(f"drag_void_fraction must be one of {', '.join(METHODS)}, got {method!r}")
        self.method = method
        self.rmax = float(rmax)
        self.dirs = directions(n_directions)
        self.length = None
        self.search = 0.0
        self.reach = 0.0
        if method == "voronoi":
            self.search = VORONOI_REACH * self.rmax          # the cells' planes: the first shell
            self.hop = 2.0 * self.rmax + self.search         # the neighbours of the average's hops
            self.length = 2.0 * self.hop
            # a neighbour's neighbour's cell: three hops of ghosts
            self.reach = 3.0 * self.hop - 2.0 * self.rmax
        elif method == "kernel":
            self.length = float(length) if length else KERNEL_LENGTH_D * 2.0 * self.rmax
            self.reach = self.length

    @staticmethod
    def ghost_reach(method: str, rmax: float, length: float | None = None) -> float:
        """The reach of ``method`` for particles of largest radius ``rmax``."""
        return ParticleVoidFraction(method, rmax, length, n_directions=2).reach

    def averaging(self) -> str:
        """What the method averages over, for the case's report."""
        d = 2.0 * self.rmax
        if self.method == "voronoi":
            return (f"the particles' radical Voronoi cells (planes of the first shell, neighbours to "
                    f"{VORONOI_REACH:g} r_max beyond contact) averaged over two hops of it, {self.length:.4g} m "
                    f"({self.length / d:.3g} d_max)")
        if self.method == "kernel":
            return f"a Wendland kernel of support {self.length:.4g} m ({self.length / d:.3g} d_max)"
        return "the gas cells' void fraction at each particle"

    def __call__(self, sim, eps_cell: np.ndarray, rmin: float, eps_min: float = 0.0) -> np.ndarray:
        """Local void fraction of the owned particles of ``sim`` (their current positions and
        the ghosts'); ``eps_cell``: the cell void fraction at each (voronoi: the directions no
        neighbour encloses); ``rmin``: the smallest radius of the run (over every rank); values
        below ``eps_min`` are raised to it (the lower bound of the cell void fraction)."""
        st = sim.state
        n, nown = st.n, st.n_owned
        if sim.par is not None:
            glo, ghi, gwrap = sim.par.grid_box(sim.world)
        else:
            glo, ghi, gwrap = st.lo, st.hi, st.periodic
        x = np.ascontiguousarray(st.position[:n])
        r = np.ascontiguousarray(st.radius[:n])
        B = Bounds(st.lo, st.hi, st.periodic, st.wf, st.wi, float(sim.world.time))
        dom, grid = Box(st.lo, st.hi, st.periodic), Box(glo, ghi, gwrap)
        ec = np.ascontiguousarray(eps_cell, dtype=np.float64)
        if self.method == "voronoi":
            nb = neighbour_vectors(x, r, n, n, dom, grid, self.search)
            ve, vs = _enclosed_cells(x, r, n, nb, B, self.dirs, float(rmin), self.search)
            ae, av = _average(n, nb, ve, vs, self.hop)       # every row: the ghosts' too
            se, sv = _average(nown, nb, ae, av, self.hop)    # the owned rows
            return _voronoi_all(r, nown, vs, se, sv, ec, float(eps_min))
        # every centre within the kernel's support
        nb = neighbour_vectors(x, r, n, nown, dom, grid, max(self.length - 2.0 * float(rmin), 0.0))
        return _kernel_all(x, r, nown, nb, B, self.dirs, self.length, float(eps_min))
