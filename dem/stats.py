"""Diagnostics computed at output time (not in the step)."""
import math
from numba import njit
from .contact.walls import wall_distance


@njit(cache=True, error_model="numpy")
def max_overlap_ratio(n, x, r, nb, nnb, lo, hi, periodic, wf, wi, nwalls, t):
    """Largest overlap / smaller radius over particle pairs and walls."""
    best = 0.0
    for i in range(n):
        for s in range(nnb[i]):
            j = nb[i, s]
            d2 = 0.0
            for k in range(3):
                d = x[j, k] - x[i, k]
                if periodic[k]:
                    L = hi[k] - lo[k]
                    d -= L * math.floor(d / L + 0.5)
                d2 += d * d
            rs = r[i] + r[j]
            if d2 < rs * rs:
                ov = (rs - math.sqrt(d2)) / min(r[i], r[j])
                if ov > best:
                    best = ov
        for w in range(nwalls):
            dist, a, b, c = wall_distance(wf, wi, w, x[i, 0], x[i, 1], x[i, 2], t)
            if dist < r[i] and dist > -r[i]:
                ov = (r[i] - dist) / r[i]
                if ov > best:
                    best = ov
    return best
