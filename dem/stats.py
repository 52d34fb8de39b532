"""Diagnostics computed at output time (not in the step)."""
from numba import njit
from .contact.walls import wall_distance
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
