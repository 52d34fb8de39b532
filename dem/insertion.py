"""Random sequential insertion of non-overlapping spheres into a box or a cylinder,
reproducible from the scene seed (NumPy PCG64 stream feeding a Numba grid test)."""
import math
import numpy as np
from numba import njit


def sample_radii(spec, count, rng):
    """Radii from a distribution spec (already validated): constant, uniform, normal,
    lognormal; normal and lognormal are truncated to [min, max] by rejection."""
    kind = spec["distribution"]
    if kind == "constant":
        return np.full(count, float(spec["value"]))
    lo, hi = float(spec["min"]), float(spec["max"])
    if kind == "uniform":
        return rng.uniform(lo, hi, count)
    out = np.empty(0)
    while out.size < count:
        if kind == "normal":
            s = rng.normal(spec["mean"], spec["std"], 2 * count)
        else:  # lognormal with the given mean and std of the radius itself
            m, sd = float(spec["mean"]), float(spec["std"])
            s2 = math.log(1.0 + (sd / m) ** 2)
            s = rng.lognormal(math.log(m) - 0.5 * s2, math.sqrt(s2), 2 * count)
        out = np.concatenate([out, s[(s >= lo) & (s <= hi)]])
    return out[:count]


@njit(cache=True, error_model="numpy")
def _place(cand, radii, existing_x, existing_r, lo, hi, cell):
    """Accept candidates in order; cand[k] holds the random attempts of sphere k."""
    n_ex = existing_x.shape[0]
    count = radii.shape[0]
    ntry = cand.shape[1]
    nc = np.empty(3, np.int64)
    for k in range(3):
        nc[k] = max(1, int((hi[k] - lo[k]) / cell))
    ncell = nc[0] * nc[1] * nc[2]
    cap = n_ex + count
    head = np.full(ncell, -1, np.int64)
    nxt = np.full(cap, -1, np.int64)
    px = np.empty((cap, 3))
    pr = np.empty(cap)
    npl = 0

    def cid(p0, p1, p2):
        c0 = min(max(int((p0 - lo[0]) / cell), 0), nc[0] - 1)
        c1 = min(max(int((p1 - lo[1]) / cell), 0), nc[1] - 1)
        c2 = min(max(int((p2 - lo[2]) / cell), 0), nc[2] - 1)
        return c0, c1, c2

    for q in range(n_ex):
        px[npl] = existing_x[q]
        pr[npl] = existing_r[q]
        c0, c1, c2 = cid(px[npl, 0], px[npl, 1], px[npl, 2])
        c = (c0 * nc[1] + c1) * nc[2] + c2
        nxt[npl] = head[c]
        head[c] = npl
        npl += 1
    placed = np.empty((count, 3))
    for k in range(count):
        ok = False
        for a in range(ntry):
            p0 = cand[k, a, 0]
            p1 = cand[k, a, 1]
            p2 = cand[k, a, 2]
            c0, c1, c2 = cid(p0, p1, p2)
            clash = False
            for o0 in range(max(c0 - 1, 0), min(c0 + 2, nc[0])):
                for o1 in range(max(c1 - 1, 0), min(c1 + 2, nc[1])):
                    for o2 in range(max(c2 - 1, 0), min(c2 + 2, nc[2])):
                        q = head[(o0 * nc[1] + o1) * nc[2] + o2]
                        while q >= 0:
                            d0 = px[q, 0] - p0
                            d1 = px[q, 1] - p1
                            d2 = px[q, 2] - p2
                            rr = pr[q] + radii[k]
                            if d0 * d0 + d1 * d1 + d2 * d2 < rr * rr:
                                clash = True
                                break
                            q = nxt[q]
                        if clash:
                            break
                    if clash:
                        break
                if clash:
                    break
            if not clash:
                ok = True
                break
        if not ok:
            return placed[:k], k
        placed[k, 0] = p0
        placed[k, 1] = p1
        placed[k, 2] = p2
        px[npl, 0] = p0
        px[npl, 1] = p1
        px[npl, 2] = p2
        pr[npl] = radii[k]
        c = (c0 * nc[1] + c1) * nc[2] + c2
        nxt[npl] = head[c]
        head[c] = npl
        npl += 1
    return placed, count


ATTEMPTS = 200   # random candidates per sphere (dem.memory.INSERTION_ATTEMPTS)


def insert(region, radii, rng, existing_x, existing_r, attempts=ATTEMPTS):
    """Place spheres of the given radii inside ``region`` without overlaps.

    Returns (positions, number placed). Spheres are placed largest first.
    """
    count = radii.size
    order = np.argsort(-radii, kind="stable")
    rs = np.ascontiguousarray(radii[order])
    u = rng.random((count, attempts, 3))
    if region["type"] == "box":
        lo = np.asarray(region["min"], float)
        hi = np.asarray(region["max"], float)
        span = (hi - lo)[None, None, :] - 2 * rs[:, None, None]
        cand = lo[None, None, :] + rs[:, None, None] + u * np.maximum(span, 0.0)
        blo, bhi = lo, hi
    else:
        c = np.asarray(region["center"], float)
        ax = np.asarray(region["axis"], float)
        ax = ax / np.linalg.norm(ax)
        e1 = np.cross(ax, [1.0, 0, 0] if abs(ax[0]) < 0.9 else [0, 1.0, 0])
        e1 /= np.linalg.norm(e1)
        e2 = np.cross(ax, e1)
        R = float(region["radius"])
        L = float(region["length"])
        rad = np.sqrt(u[..., 0]) * np.maximum(R - rs[:, None], 0.0)
        th = 2 * np.pi * u[..., 1]
        h = (u[..., 2] - 0.5) * np.maximum(L - 2 * rs[:, None], 0.0)
        cand = (c[None, None, :] + rad[..., None] * (np.cos(th)[..., None] * e1 + np.sin(th)[..., None] * e2)
                + h[..., None] * ax)
        ext = np.abs(ax) * L / 2 + np.sqrt(np.maximum(0, 1 - ax ** 2)) * R
        blo, bhi = c - ext, c + ext
    ex_x = np.ascontiguousarray(existing_x, float).reshape(-1, 3)
    ex_r = np.ascontiguousarray(existing_r, float).reshape(-1)
    if ex_x.shape[0]:
        blo = np.minimum(blo, ex_x.min(0))
        bhi = np.maximum(bhi, ex_x.max(0))
    cell = 2 * max(rs.max(), ex_r.max() if ex_r.size else 0.0)
    placed, k = _place(np.ascontiguousarray(cand), rs, ex_x, ex_r, blo, bhi, cell)
    out = np.empty((count, 3))
    out[order[:k]] = placed[:k]
    keep = np.zeros(count, bool)
    keep[order[:k]] = True
    return out, keep, k


@njit(cache=True, error_model="numpy", inline="always")
def _beside(a, dims, length):
    """A neighbour cell's index along one axis: wrapped on a periodic axis (``length`` > 0),
    else (index, whether it is inside the grid)."""
    if length > 0.0:
        return a % dims, True
    return a, 0 <= a < dims


@njit(cache=True, error_model="numpy")
def max_overlap(x, r, box):
    """The largest overlap of two spheres relative to the smaller radius, (r_i + r_j - d) /
    min(r_i, r_j), and its pair: (ratio, i, j), or (-inf, -1, -1) when no two spheres are
    within 2 r_max of each other. ``box``: the domain's length along each periodic axis (its
    spheres meet across it, by the nearest image), 0 along the others. A cell list of side at
    least 2 r_max, sorted by cell: the cost of n log n, the memory of n, whatever the domain."""
    n = x.shape[0]
    best, bi, bj = -np.inf, -1, -1
    if n < 2:
        return best, bi, bj
    cell = 2.0 * r.max()
    lo = np.empty(3)
    dims = np.empty(3, np.int64)
    size = np.empty(3)
    y = np.empty((n, 3))
    for k in range(3):
        if box[k] > 0.0:
            lo[k] = 0.0
            dims[k] = max(np.int64(box[k] // cell), 1)
            size[k] = box[k] / dims[k]
            for i in range(n):
                y[i, k] = x[i, k] % box[k]
        else:
            lo[k] = x[:, k].min()
            hi = x[:, k].max()
            size[k] = max(cell, (hi - lo[k]) / 1048576.0)   # at most 2^20 cells along an axis
            dims[k] = np.int64((hi - lo[k]) // size[k]) + 1
            for i in range(n):
                y[i, k] = x[i, k]
    c = np.empty((n, 3), np.int64)
    keys = np.empty(n, np.int64)
    for i in range(n):
        for k in range(3):
            c[i, k] = min(np.int64((y[i, k] - lo[k]) // size[k]), dims[k] - 1)
        keys[i] = c[i, 0] + dims[0] * (c[i, 1] + dims[1] * c[i, 2])
    order = np.argsort(keys, kind="mergesort")
    sk = keys[order]
    for i in range(n):
        for o0 in range(-1, 2):
            a0, in0 = _beside(c[i, 0] + o0, dims[0], box[0])
            if not in0:
                continue
            for o1 in range(-1, 2):
                a1, in1 = _beside(c[i, 1] + o1, dims[1], box[1])
                if not in1:
                    continue
                for o2 in range(-1, 2):
                    a2, in2 = _beside(c[i, 2] + o2, dims[2], box[2])
                    if not in2:
                        continue
                    key = a0 + dims[0] * (a1 + dims[1] * a2)
                    s = np.searchsorted(sk, key)
                    while s < n and sk[s] == key:
                        j = order[s]
                        s += 1
                        if j <= i:
                            continue
                        d2 = 0.0
                        for k in range(3):
                            dk = y[j, k] - y[i, k]
                            if box[k] > 0.0:
                                dk -= box[k] * np.round(dk / box[k])
                            d2 += dk * dk
                        if d2 > cell * cell:
                            continue
                        ov = (r[i] + r[j] - math.sqrt(d2)) / min(r[i], r[j])
                        if ov > best:
                            best, bi, bj = ov, i, j
    return best, bi, bj
