"""Diagnostics computed at output time (not in the step)."""
import numpy as np
from numba import njit
from .contact.walls import wall_distance, WI, MESH
from .neighbors import pair_distance


@njit(cache=True, error_model="numpy")
def max_overlap_ratio(n, x, r, nb, nnb, lo, hi, periodic, wf, wi, nwalls, t):
    """Largest overlap / smaller radius over particle pairs and walls."""
    best = 0.0
    for i in range(n):
        for s in range(nnb[i]):
            j = nb[i, s]
            d = pair_distance(x, i, j, lo, hi, periodic)
            rs = r[i] + r[j]
            if d < rs:
                ov = (rs - d) / min(r[i], r[j])
                if ov > best:
                    best = ov
        for w in range(nwalls):
            dist, a, b, c = wall_distance(wf, wi, w, x[i, 0], x[i, 1], x[i, 2], t)
            if dist < r[i] and dist > -r[i]:
                ov = (r[i] - dist) / r[i]
                if ov > best:
                    best = ov
    return best


@njit(cache=True, error_model="numpy")
def _touching(x, r, nb, nnb, nown, box, fill, out_i, out_j, out_d, out_s):
    """The touching pairs (centre distance below the radii's sum) of the half list from the owned
    rows [0, nown): counts them per row; with ``fill``, also writes each pair's rows i, j,
    distance and slot in list order. ``box`` = (lo, hi, periodic): the minimum image."""
    lo, hi, periodic = box
    cnt = np.zeros(nb.shape[0], np.int64)
    k = 0
    for i in range(nown):
        for s in range(nnb[i]):
            j = nb[i, s]
            d = pair_distance(x, i, j, lo, hi, periodic)
            if d < r[i] + r[j]:
                cnt[i] += 1
                cnt[j] += 1
                if fill:
                    out_i[k] = i
                    out_j[k] = j
                    out_d[k] = d
                    out_s[k] = s
                k += 1
    return cnt, k


def touching_pairs(st):
    """(rows i, rows j, centre distances, slots, touching pairs per row) of the touching pairs
    listed from this rank's owned particles (a pair with a ghost is listed by both ranks that
    hold it)."""
    box = (st.lo, st.hi, st.periodic)
    none = np.empty(0, np.int64)
    cnt, k = _touching(st.position, st.radius, st.nb, st.nnb, st.n_owned, box, False, none, none, np.empty(0), none)
    ii, jj, dd, ss = np.empty(k, np.int64), np.empty(k, np.int64), np.empty(k), np.empty(k, np.int64)
    _touching(st.position, st.radius, st.nb, st.nnb, st.n_owned, box, True, ii, jj, dd, ss)
    return ii, jj, dd, ss, cnt


@njit(cache=True, error_model="numpy")
def wall_touches(x, r, wnb, wnn, wf, wi, mcon, nown, t):
    """How many wall contacts each owned particle has (a plane's or cylinder's distance, a mesh
    row's contact record, below its radius)."""
    out = np.zeros(nown, np.int64)
    for i in range(nown):
        for q in range(wnn[i]):
            w = wnb[i, q]
            if wi[w, WI.type] == MESH:
                d = mcon[i, w, 0] if mcon.shape[0] > i else np.inf
            else:
                d, a, b, c = wall_distance(wf, wi, w, x[i, 0], x[i, 1], x[i, 2], t)
            if d < r[i] and d > -r[i]:
                out[i] += 1
    return out
