"""Cell-linked lists and a Verlet half list with per-pair history slots.

Each pair (i, j), i < j, is stored once, in row i of ``nb`` (fixed ``slots`` per particle,
grown automatically on overflow). Contact history (tangential spring, rolling spring,
contact age) lives in arrays aligned with ``nb`` and is carried over at every rebuild by
looking the pair up in the previous list (row i, or row j with the sign of vectors
flipped), so a contact keeps its history through rebuilds and reorderings.
The list covers pairs with surface gap < ``reach`` + skin; it is rebuilt when the
largest displacement since the last build exceeds half the skin.
"""
import math
import numpy as np
from numba import njit


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


@njit(cache=True, error_model="numpy")
def cell_index(x, lo, inv_cell, ncell, n):
    """Cell of each particle (clamped into the grid) and the flat index."""
    out = np.empty(n, np.int64)
    for i in range(n):
        c = 0
        for k in range(3):
            ck = int(math.floor((x[i, k] - lo[k]) * inv_cell[k]))
            if ck < 0:
                ck = 0
            elif ck >= ncell[k]:
                ck = ncell[k] - 1
            c = c * ncell[k] + ck
        out[i] = c
    return out


@njit(cache=True, error_model="numpy")
def build_half_list(x, r, n, nown, lo, hi, periodic, glo, ghi, gwrap, reach, skin, slots,
                    nb_old, nnb_old, hist_old, rhist_old, age_old):
    """Build the half list and carry the history over.

    Rows [nown, n) are ghosts (another rank's particles): they get no row of their own, so
    ghost-ghost pairs are never listed. Distances use the minimum image of the domain
    (lo, hi, periodic); the cell grid covers [glo, ghi] and wraps on the axes of ``gwrap``
    (in a serial run the grid is the domain; a rank's grid is its box plus the halo).
    Returns (nb, nnb, hist, rhist, age, max_count). When a row overflows the slots the
    build is redone with more slots (the arrays returned are then larger).
    """
    rmax = 0.0
    for i in range(n):
        if r[i] > rmax:
            rmax = r[i]
    cut = 2.0 * rmax + reach + skin
    ncell = np.empty(3, np.int64)
    inv_cell = np.empty(3)
    length = np.empty(3)
    glen = np.empty(3)
    for k in range(3):
        length[k] = hi[k] - lo[k]
        glen[k] = ghi[k] - glo[k]
        nc = int(math.floor(glen[k] / cut))
        if nc < 1:
            nc = 1
        if gwrap[k] and nc < 3:
            nc = 1  # all pairs by minimum image along this axis
        ncell[k] = nc
        inv_cell[k] = nc / glen[k]
    cidx = cell_index(x, glo, inv_cell, ncell, n)
    ntot = ncell[0] * ncell[1] * ncell[2]
    head = np.full(ntot + 1, 0, np.int64)
    for i in range(n):
        head[cidx[i] + 1] += 1
    for c in range(ntot):
        head[c + 1] += head[c]
    order = np.empty(n, np.int64)
    fill = head[:-1].copy()
    for i in range(n):
        order[fill[cidx[i]]] = i
        fill[cidx[i]] += 1

    rolling = rhist_old.shape[0] == nb_old.shape[0] and rhist_old.shape[0] > 0
    use_age = age_old.shape[0] == nb_old.shape[0] and age_old.shape[0] > 0
    while True:
        nb = np.empty((n, slots), np.int32)
        nnb = np.zeros(n, np.int32)
        maxc = 0
        for i in range(nown):
            ci = cidx[i]
            cz = ci % ncell[2]
            cy = (ci // ncell[2]) % ncell[1]
            cx = ci // (ncell[2] * ncell[1])
            cnt = 0
            for ox in range(-1, 2):
                ax = cx + ox
                if ncell[0] == 1 and ox != 0:
                    continue
                if ax < 0 or ax >= ncell[0]:
                    if not gwrap[0]:
                        continue
                    ax %= ncell[0]
                for oy in range(-1, 2):
                    ay = cy + oy
                    if ncell[1] == 1 and oy != 0:
                        continue
                    if ay < 0 or ay >= ncell[1]:
                        if not gwrap[1]:
                            continue
                        ay %= ncell[1]
                    for oz in range(-1, 2):
                        az = cz + oz
                        if ncell[2] == 1 and oz != 0:
                            continue
                        if az < 0 or az >= ncell[2]:
                            if not gwrap[2]:
                                continue
                            az %= ncell[2]
                        c = (ax * ncell[1] + ay) * ncell[2] + az
                        for q in range(head[c], head[c + 1]):
                            j = order[q]
                            if j <= i:
                                continue
                            dx = _min_image(x[j, 0] - x[i, 0], length[0], periodic[0])
                            dy = _min_image(x[j, 1] - x[i, 1], length[1], periodic[1])
                            dz = _min_image(x[j, 2] - x[i, 2], length[2], periodic[2])
                            rc = r[i] + r[j] + reach + skin
                            if dx * dx + dy * dy + dz * dz < rc * rc:
                                if cnt < slots:
                                    nb[i, cnt] = j
                                cnt += 1
            if cnt > maxc:
                maxc = cnt
            nnb[i] = min(cnt, slots)
        if maxc <= slots:
            break
        slots = maxc + 2
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
    nold = nb_old.shape[0]
    if nold == n:
        for i in range(n):
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
    return nb, nnb, hist, rhist, age, maxc


def sort_permutation(x, lo, hi, cell):
    """Permutation that orders particles by cell along a z-order-like key (cache locality)."""
    ncell = np.maximum(1, np.floor((hi - lo) / cell)).astype(np.int64)
    c = np.clip(np.floor((x - lo) / cell).astype(np.int64), 0, ncell - 1)
    key = (c[:, 2] * ncell[1] + c[:, 1]) * ncell[0] + c[:, 0]
    return np.argsort(key, kind="stable")
