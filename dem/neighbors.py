"""Cell-linked lists and a Verlet half list with per-pair history slots.

Each pair (i, j) is stored once, in row i or row j of ``nb`` (as many slots per particle as
the longest row of the build holds): the rows of the pairs j > i are scanned first, then each pair
goes to the row of the two that holds fewer so far (:func:`balance_rows`), which halves the
longest row and so the slots every row carries (issue 28: a shorter row of the contact history
made the shared 50k bed 7-10 % faster). Contact history (tangential spring, rolling spring,
contact age) lives in arrays aligned with ``nb`` and is carried over at every rebuild by
looking the pair up in the previous list (row i, or row j with the sign of vectors
flipped), so a contact keeps its history through rebuilds and reorderings.
The list covers pairs with surface gap < ``reach`` + skin; it is rebuilt when the
largest displacement since the last build exceeds half the skin. The skin is the scene's, or
(``neighbor_skin = "auto"``, the default) chosen at each build by :func:`adaptive_skin` from
the displacement measured since the last build and the pairs the list held beyond contact.
"""
import math
from collections import namedtuple

import numpy as np
from numba import njit, prange

from .blocks import block_bounds

# a box: lower and upper corner and its periodic (wrapped) axes: the domain of the minimum
# image, or the region a cell grid covers
Box = namedtuple("Box", "lo hi periodic")

# The adaptive skin (neighbor_skin = "auto"). A rebuild costs about as much per particle as
# SKIN_REBUILD_COST listed pairs that do not touch: 404-1,145 ns per particle against 7-11 ns
# per such pair on the shared 10k and 50k beds, heat off and on (docs/notebook.md, "Where a
# step goes": 46-104); the optimum below moves with the square root of it, and a cost 1.4x off
# puts a step's list overhead only 6 % above its least. The skin stays within
# [SKIN_MIN_FRACTION, 1] x the largest, 0.2 r_max (the fixed default it replaced: never a wider
# list or ghost halo than before).
SKIN_REBUILD_COST = 70.0
SKIN_MIN_FRACTION = 0.05


@njit(cache=True, error_model="numpy")
def adaptive_skin(rate, gap_density, skin_max):
    """The skin that costs a step least: listed pairs that do not touch cost g s per particle
    (g = ``gap_density``: such pairs per particle and per metre of skin, measured at the last
    build), and a rebuild, every s / (2 v) steps (v = ``rate``: the largest displacement per
    step, m), costs K of them per particle (K = SKIN_REBUILD_COST). The cost per step and
    particle, in units of one such pair, g s + 2 K v / s, is least at

        s* = sqrt(2 K v / g)

    (the Verlet buffer as a balance of list length against rebuild frequency, chosen from the
    measured motion rather than from a timed trial, so that a run's results never depend on the
    machine's load).
    Clamped to [SKIN_MIN_FRACTION skin_max, skin_max]; ``skin_max`` when nothing was measured."""
    lo = SKIN_MIN_FRACTION * skin_max
    if not gap_density > 0.0:
        return skin_max
    s = math.sqrt(2.0 * SKIN_REBUILD_COST * max(rate, 0.0) / gap_density)
    return min(max(s, lo), skin_max)


@njit(cache=True, error_model="numpy")
def pairs_beyond(x, r, nb, nnb, nown, lo, hi, periodic, reach):
    """The listed pairs of rows [0, nown) whose surface gap is at least ``reach`` (beyond every
    interaction: what the skin alone brought into the list). A pair with a ghost (j >= nown)
    counts one half: the rank that owns the ghost lists it too, so that the sum over the ranks
    counts each pair once, as a serial run does."""
    length = np.empty(3)
    for k in range(3):
        length[k] = hi[k] - lo[k]
    far = 0.0
    for i in range(nown):
        for q in range(nnb[i]):
            j = nb[i, q]
            dx = _min_image(x[j, 0] - x[i, 0], length[0], periodic[0])
            dy = _min_image(x[j, 1] - x[i, 1], length[1], periodic[1])
            dz = _min_image(x[j, 2] - x[i, 2], length[2], periodic[2])
            rc = r[i] + r[j] + reach
            if dx * dx + dy * dy + dz * dz >= rc * rc:
                far += 1.0 if j < nown else 0.5
    return far


@njit(cache=True, error_model="numpy")
def _min_image(d, length, periodic):
    if periodic:
        d -= length * math.floor(d / length + 0.5)
    return d


@njit(cache=True, error_model="numpy")
def pair_distance(x, i, j, lo, hi, periodic):
    """Centre distance of particles i and j (minimum image on periodic axes)."""
    d2 = 0.0
    for k in range(3):
        d = x[j, k] - x[i, k]
        if periodic[k]:
            L = hi[k] - lo[k]
            d -= L * math.floor(d / L + 0.5)
        d2 += d * d
    return math.sqrt(d2)


# The cell grid keeps the geometry of a grid over the whole box [glo, ghi] (cells of at least
# the cut-off, at most MAX_CELLS_PER_AXIS along an axis), but stores only the box of occupied
# cells: a dense table of cell starts when that box holds at most
# DENSE_CELLS_PER_PARTICLE * n + DENSE_MIN_CELLS cells (a bed: the usual case, one lookup per
# cell), else the sorted cell keys of the particles (binary search). Memory is O(n) either way,
# whatever the size of the domain; the neighbour rows come out in the same order as with a
# table over the whole box (particles by cell, then by index).
DENSE_CELLS_PER_PARTICLE = 8
DENSE_MIN_CELLS = 4096
MAX_CELLS_PER_AXIS = 1 << 20


@njit(cache=True, error_model="numpy")
def cell_grid(x, r, n, glo, ghi, gwrap, reach, skin):
    """Cells of the particles and the table to find each cell's particles.

    Returns (ncell, cc, cmin, ext, order, table, dense): ncell cells per axis over [glo, ghi]
    (1 on a wrapped axis shorter than 3 cut-offs: all pairs by minimum image there), cc the
    cell of each particle (clamped into the grid), cmin/ext the first cell and the number of
    cells of the box of occupied cells (neighbour cells outside it are empty, wrapped or not:
    they are skipped), order the particles
    sorted by cell key (stable), table the start of each key of the box (dense, size box + 1)
    or the sorted keys (sparse, size n).
    """
    rmax = 0.0
    for i in range(n):
        if r[i] > rmax:
            rmax = r[i]
    cut = 2.0 * rmax + reach + skin
    ncell = np.empty(3, np.int64)
    inv_cell = np.empty(3)
    for k in range(3):
        glen = ghi[k] - glo[k]
        q = glen / cut
        nc = MAX_CELLS_PER_AXIS if q >= MAX_CELLS_PER_AXIS else int(math.floor(q))
        if nc < 1:
            nc = 1
        if gwrap[k] and nc < 3:
            nc = 1  # all pairs by minimum image along this axis
        ncell[k] = nc
        inv_cell[k] = nc / glen
    cc = np.empty((n, 3), np.int64)
    cmin = np.zeros(3, np.int64)
    ext = np.ones(3, np.int64)
    for k in range(3):
        lo_c = ncell[k] - 1
        hi_c = 0
        for i in range(n):
            c = int(math.floor((x[i, k] - glo[k]) * inv_cell[k]))
            if c < 0:
                c = 0
            elif c >= ncell[k]:
                c = ncell[k] - 1
            cc[i, k] = c
            lo_c = min(lo_c, c)
            hi_c = max(hi_c, c)
        if n > 0:  # the box of occupied cells (on a wrapped axis too: the cells beyond are empty)
            cmin[k] = lo_c
            ext[k] = hi_c - lo_c + 1
    key = np.empty(n, np.int64)
    for i in range(n):
        key[i] = ((cc[i, 0] - cmin[0]) * ext[1] + (cc[i, 1] - cmin[1])) * ext[2] + (cc[i, 2] - cmin[2])
    nbox = ext[0] * ext[1] * ext[2]
    dense = nbox <= DENSE_CELLS_PER_PARTICLE * n + DENSE_MIN_CELLS
    order = np.empty(n, np.int64)
    if dense:  # counting sort: table[c] = first slot of cell c in ``order``
        table = np.zeros(nbox + 1, np.int64)
        for i in range(n):
            table[key[i] + 1] += 1
        for c in range(nbox):
            table[c + 1] += table[c]
        for i in range(n - 1, -1, -1):  # backwards: each cell keeps its particles in index order
            table[key[i] + 1] -= 1
            order[table[key[i] + 1]] = i
        # table[c + 1] now holds the start of cell c; shift down by one
        for c in range(nbox):
            table[c] = table[c + 1]
        table[nbox] = n
    else:
        order[:] = np.argsort(key, kind="mergesort")
        table = np.empty(n, np.int64)
        for q in range(n):
            table[q] = key[order[q]]
    return ncell, cc, cmin, ext, order, table, dense


@njit(cache=True, error_model="numpy")
def _lower_bound(a, v):
    """First index q with a[q] >= v (a sorted)."""
    lo = 0
    hi = a.shape[0]
    while lo < hi:
        mid = (lo + hi) >> 1
        if a[mid] < v:
            lo = mid + 1
        else:
            hi = mid
    return lo


@njit(cache=True, error_model="numpy")
def _key_range(table, dense, k0, k1):
    """Slots [q0, q1) of ``order`` holding the particles of cell keys k0..k1 (the cages of
    coupling.particle_void; the neighbour rows search inline: :func:`_rows_block`)."""
    if dense:
        return table[k0], table[k1 + 1]
    return _lower_bound(table, k0), _lower_bound(table, k1 + 1)


@njit(cache=True, error_model="numpy")
def _axis_cell(c, o, ncell, wrap, cmin, ext):
    """Neighbour cell c + o along an axis (wrapped), or -1 when it holds no particle."""
    if ncell == 1 and o != 0:
        return -1
    a = c + o
    if wrap:
        a %= ncell
    if a < cmin or a >= cmin + ext:
        return -1
    return a


@njit(cache=True, error_model="numpy")
def _rows_block(i0, i1, grid, x, r, box, cutoff, nb, nnb, rowc):
    """Rows [i0, i1) of the half list: row i the particles j > i of the 27 cells around i's
    within the list cut-off, in cell order (the z cells of a column scanned as runs of
    consecutive keys); rowc[i] how many there are, nnb[i] how many fit in nb's slots (those
    beyond are counted, not stored). Writes rows [i0, i1) only, so blocks can be built at once
    on several threads. ``grid``: (cc, ncell, gwrap, cmin, ext, table, dense, order) of
    :func:`cell_grid`; ``box``: (length, periodic) of the minimum image; ``cutoff``: (reach,
    skin). The arrays are taken once for the block and the scan calls no function taking an
    array: in this loop each array a called function takes counts its references up and down,
    which made the build 2.4 times as long (docs/benchmarks.md, "Hopper discharge")."""
    cc, ncell, gwrap, cmin, ext, table, dense, order = grid
    length, periodic = box
    reach, skin = cutoff
    slots = nb.shape[1]
    zc = np.empty(3, np.int64)
    l0, l1, l2 = length[0], length[1], length[2]
    p0, p1, p2 = periodic[0], periodic[1], periodic[2]
    for i in range(i0, i1):
        cnt = np.int64(0)
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
                    k0 = base + za
                    k1 = base + zb
                    if dense:
                        q0 = table[k0]
                        q1 = table[k1 + 1]
                    else:   # sparse keys (rare: a grid with many empty cells): the binary searches
                        q0 = _lower_bound(table, k0)
                        q1 = _lower_bound(table, k1 + 1)
                    for q in range(q0, q1):
                        j = order[q]
                        if j <= i:
                            continue
                        dx = _min_image(x[j, 0] - xi0, l0, p0)
                        dy = _min_image(x[j, 1] - xi1, l1, p1)
                        dz = _min_image(x[j, 2] - xi2, l2, p2)
                        rc = ri + r[j] + reach + skin
                        if dx * dx + dy * dy + dz * dz < rc * rc:
                            if cnt < slots:
                                nb[i, cnt] = j
                            cnt += 1
        rowc[i] = cnt
        nnb[i] = min(cnt, slots)


@njit(cache=True, error_model="numpy")
def _carry_block(i0, i1, nb, nnb, hist, rhist, age, nb_old, nnb_old, hist_old, rhist_old, age_old):
    """The history of rows [i0, i1) from the old list: the same pair in row i, else the pair
    stored the other way round in row j (the spring with its sign turned). Writes those rows
    only. (A block, not a row, a call: each array a call takes counts its references.)"""
    rolling = rhist.shape[0] > 0
    use_age = age.shape[0] > 0
    for i in range(i0, i1):
        for s in range(nnb[i]):
            j = nb[i, s]
            found = False
            for so in range(nnb_old[i]):
                if nb_old[i, so] == j:
                    for k in range(3):
                        hist[i, s, k] = hist_old[i, so, k]
                        if rolling:
                            rhist[i, s, k] = rhist_old[i, so, k]
                    if use_age:
                        age[i, s, 0] = age_old[i, so, 0]
                        age[i, s, 1] = age_old[i, so, 1]
                    found = True
                    break
            if not found:
                for so in range(nnb_old[j]):
                    if nb_old[j, so] == i:
                        for k in range(3):
                            hist[i, s, k] = -hist_old[j, so, k]
                            if rolling:
                                rhist[i, s, k] = -rhist_old[j, so, k]
                        if use_age:
                            age[i, s, 0] = age_old[j, so, 0]
                            age[i, s, 1] = age_old[j, so, 1]
                        break


@njit(cache=True, error_model="numpy", parallel=True)
def _rows_threaded(nown, nthreads, grid, x, r, box, cutoff, nb, nnb, rowc):
    """The rows of the half list (:func:`_rows_block`) on ``nthreads`` threads: equal blocks
    of rows, each row written by one thread only, so the list is the same bit for bit as on one
    thread."""
    bounds = block_bounds(nown, nown, nthreads)
    for b in prange(nthreads):
        _rows_block(bounds[b], bounds[b + 1], grid, x, r, box, cutoff, nb, nnb, rowc)


@njit(cache=True, error_model="numpy", parallel=True)
def _carry_threaded(n, nthreads, nb, nnb, hist, rhist, age, old):
    """The history carried over (:func:`_carry_block`) on ``nthreads`` threads, blocks of rows."""
    nb_old, nnb_old, hist_old, rhist_old, age_old = old
    bounds = block_bounds(n, n, nthreads)
    for b in prange(nthreads):
        _carry_block(bounds[b], bounds[b + 1], nb, nnb, hist, rhist, age, nb_old, nnb_old, hist_old, rhist_old, age_old)


@njit(cache=True, error_model="numpy")
def balance_rows(raw, nraw, n, nown):
    """The half list with each pair in the shorter of its two rows: the pairs of ``raw`` (row i
    holding the j > i of :func:`_rows_block`, ``nraw`` of them), taken in row order, each
    into row j when j is owned (a ghost has no row) and row j holds fewer pairs so far than row
    i, else into row i; then, while it shortens the longest rows, a pair of a longest row moves
    to its other row when that one holds at least 2 fewer; then each row sorted by the other
    particle's row. Serial passes over the pairs, the same on any number of threads (the raw
    rows are). The rows of the shared 50k bed hold 1-5 pairs instead of 0-11, so the contact
    history (3 doubles a slot) and the list take 5 slots instead of 13: less memory for the pair
    loop to stream through at every step.

    Returns (nb, nnb, the longest row): the rows as wide as the longest (no spare slots: a row
    that grows at the next build widens the next list, which is allocated anew anyway)."""
    cnt = np.zeros(n, np.int32)
    total = 0
    for i in range(nown):
        total += nraw[i]
    to_j = np.zeros(total, np.bool_)
    p = 0
    for i in range(nown):
        for s in range(nraw[i]):
            j = raw[i, s]
            if j < nown and cnt[j] < cnt[i]:
                cnt[j] += 1
                to_j[p] = True
            else:
                cnt[i] += 1
            p += 1
    maxc = cnt[:nown].max() if nown > 0 else 0
    # then, while it shortens the longest rows: each pair of a longest row moves to its other
    # row when that one holds at least 2 fewer (the greedy pass leaves a few dozen rows one
    # longer than needed on the shared 50k bed)
    while maxc > 1:
        p = 0
        for i in range(nown):
            for s in range(nraw[i]):
                j = raw[i, s]
                if j < nown:
                    a, b = (j, i) if to_j[p] else (i, j)
                    if cnt[a] == maxc and cnt[b] <= maxc - 2:
                        cnt[a] -= 1
                        cnt[b] += 1
                        to_j[p] = not to_j[p]
                p += 1
        longest = cnt[:nown].max()
        if longest == maxc:
            break
        maxc = longest
    nb = np.empty((n, max(maxc, 1)), np.int32)
    nnb = np.zeros(n, np.int32)
    p = 0
    for i in range(nown):
        for s in range(nraw[i]):
            j = raw[i, s]
            if to_j[p]:
                nb[j, nnb[j]] = i
                nnb[j] += 1
            else:
                nb[i, nnb[i]] = j
                nnb[i] += 1
            p += 1
    for i in range(nown):   # each row by the other's row (insertion sort: rows of a few pairs)
        for a in range(1, nnb[i]):
            v = nb[i, a]
            b = a - 1
            while b >= 0 and nb[i, b] > v:
                nb[i, b + 1] = nb[i, b]
                b -= 1
            nb[i, b + 1] = v
    return nb, nnb, maxc


@njit(cache=True, error_model="numpy")
def build_half_list(x, r, n, nown, dom, grid, reach, skin, slots, old, nthreads):
    """Build the half list and carry the history over from ``old`` (dem.schema Pairs: its
    nb, nnb, hist, rhist, age; empty arrays for none).

    Rows [nown, n) are ghosts (another rank's particles): they get no row of their own, so
    ghost-ghost pairs are never listed. Distances use the minimum image of the domain
    ``dom`` (a :class:`Box`); the cell grid covers the box ``grid`` and wraps on its periodic
    axes (in a serial run the grid is the domain; a rank's grid is its box plus the halo); only
    the box of occupied cells is stored (``cell_grid``), so memory grows with n, not with
    the domain. Returns (nb, nnb, hist, rhist, age, max_count): the rows as wide as the longest
    balanced row (:func:`balance_rows`); ``slots``, the last list's width, sizes the buffer of
    the pairs j > i (twice as wide plus 2, grown and scanned again when a row does not fit).

    ``nthreads`` > 1: the rows and their history on that many threads (the binning stays
    serial); every row is written by one thread only, so the list and the history are the same
    bit for bit as on one thread.
    """
    lo, hi, periodic = dom.lo, dom.hi, dom.periodic
    glo, ghi, gwrap = grid.lo, grid.hi, grid.periodic
    nb_old, nnb_old, hist_old, rhist_old, age_old = old.nb, old.nnb, old.hist, old.rhist, old.age
    ncell, cc, cmin, ext, order, table, dense = cell_grid(x, r, n, glo, ghi, gwrap, reach, skin)
    length = np.empty(3)
    for k in range(3):
        length[k] = hi[k] - lo[k]
    rolling = rhist_old.shape[0] == nb_old.shape[0] and rhist_old.shape[0] > 0
    use_age = age_old.shape[0] == nb_old.shape[0] and age_old.shape[0] > 0
    threaded = nthreads > 1 and nown >= 2 * nthreads
    grid = (cc, ncell, gwrap, cmin, ext, table, dense, order)
    box = (length, periodic)
    cutoff = (reach, skin)
    # the rows of the pairs j > i, in a buffer about twice as wide as the balanced rows (``slots``:
    # the width of the last list; grown and scanned again when a row does not fit)
    width = 2 * slots + 2
    while True:
        raw = np.empty((n, width), np.int32)
        nraw = np.zeros(n, np.int32)
        maxr = 0
        rowc = np.zeros(nown, np.int64)
        if threaded:
            _rows_threaded(nown, nthreads, grid, x, r, box, cutoff, raw, nraw, rowc)
        else:
            _rows_block(0, nown, grid, x, r, box, cutoff, raw, nraw, rowc)
        for i in range(nown):
            if rowc[i] > maxr:
                maxr = rowc[i]
        if maxr <= width:
            break
        width = maxr + 2
    nb, nnb, maxc = balance_rows(raw, nraw, n, nown)
    slots = nb.shape[1]
    # carry the history over
    hist = np.zeros((n, slots, 3))
    if rolling:
        rhist = np.zeros((n, slots, 3))
    else:
        rhist = np.zeros((0, 1, 3))
    if use_age:
        age = np.zeros((n, slots, 2))
    else:
        age = np.zeros((0, 1, 2))
    if nb_old.shape[0] == n:
        if threaded:
            _carry_threaded(n, nthreads, nb, nnb, hist, rhist, age, (nb_old, nnb_old, hist_old, rhist_old, age_old))
        else:
            _carry_block(0, n, nb, nnb, hist, rhist, age, nb_old, nnb_old, hist_old, rhist_old, age_old)
    return nb, nnb, hist, rhist, age, maxc


def sort_permutation(x, lo, hi, cell):
    """Permutation that orders particles by cell (z, then y, then x; stable) for cache
    locality. O(n) memory: a lexicographic sort of the cell coordinates, no table of cells."""
    ncell = np.maximum(1, np.floor((hi - lo) / cell)).astype(np.int64)
    c = np.clip(np.floor((x - lo) / cell).astype(np.int64), 0, ncell - 1)
    return np.lexsort((c[:, 0], c[:, 1], c[:, 2]))


def grid_bytes(x, r, n, glo, ghi, gwrap, reach, skin):
    """Bytes of the transient arrays of one neighbour build (cells, keys, order, table)."""
    ncell, cc, cmin, ext, order, table, dense = cell_grid(x, r, n, glo, ghi, gwrap, reach, skin)
    return int(cc.nbytes + order.nbytes + table.nbytes + 8 * n)  # + the keys (int64 per particle)


def raw_rows_bytes(n, slots):
    """Bytes of the rows of the pairs j > i that a build fills before :func:`balance_rows`
    (about twice the balanced rows' width) and its pass's flags (a byte a pair)."""
    return int(n * (2 * slots + 2) * (4 + 1) + 4 * n)
