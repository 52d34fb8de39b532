"""Spatial domain decomposition: recursive coordinate bisection (RCB) or slabs.

Each rank owns an axis-aligned box; the boxes tile the domain (outer faces are open to
+-infinity on non-periodic axes, so a particle a little outside the domain still has an
owner until the guard reports it). A cut is placed at the weighted median of the particles
(weight 1 + pair_weight x pairs, the cost of a particle in the step), found with global
histograms refined three times (collective: every rank takes part in every cut; typed float64
Allgather of one histogram per rank, added in a fixed order: no pickled message), so the
decomposition needs no gathering of particles and scales to many ranks.

``slabs`` cuts along one axis only (the longest, or ``slab_axis``); ``rcb`` cuts the box
with the most ranks along the longest extent of the particles inside it, recursively, giving
compact 3-D boxes (fewer ghosts per owned particle than slabs once there are more than a few
ranks; a settled flat bed is cut across, not into thin layers).

Any box width is valid on a non-periodic axis: a rank receives as ghosts the particles of
every rank within one halo of its box, not only of the next one, so a box narrower than the
halo (or an empty one) is slower, never wrong. On a periodic axis a box that does not span
the axis must leave at least two halos of the axis to the others (L - w >= 2 halo), else a
particle would be needed as two periodic images by the same rank, or a rank's own pair would
cross the periodic boundary outside its grid. Only the first cut of a box spanning a periodic
axis can break that: the cut is kept at least two halos from the box ends, and when the axis
is shorter than four halos the cut moves to another axis; when no axis can be cut (every
axis periodic and short) the lower half of the ranks get an empty box ("merge": those ranks
own no particle, a legal state).
"""
import numpy as np

HIST_BINS = 256
REFINE = 3


def global_sum(comm, x):
    """The sum over the ranks of the float64 array ``x`` (collective): every rank's ``x`` by one
    typed Allgather, added in the order of mpi4py's pickled ``allreduce`` (a binomial tree over
    the ranks, lower rank on the left), so the cuts keep the bits they had with it."""
    x = np.ascontiguousarray(x, np.float64)
    allx = np.empty((comm.Get_size(),) + x.shape, np.float64)
    comm.Allgather(x, allx)
    parts = list(allx)
    size, mask = len(parts), 1
    while mask < size:
        for r in range(0, size, 2 * mask):
            if r + mask < size:
                parts[r] = parts[r] + parts[r + mask]
        mask <<= 1
    return parts[0]


def _weighted_cut(comm, xs, ws, a, b, frac):
    """Coordinate c in [a, b] with a fraction ``frac`` of the global weight of xs below it."""
    tot = float(ws.sum())
    if comm is not None:
        tot = float(global_sum(comm, np.array([tot]))[0])
    if tot <= 0.0:
        return 0.5 * (a + b)
    target = frac * tot
    below = 0.0
    lo, hi = a, b
    for _ in range(REFINE):
        edges = np.linspace(lo, hi, HIST_BINS + 1)
        sel = (xs >= lo) & (xs < hi)
        h, _ = np.histogram(np.clip(xs[sel], lo, hi), bins=edges, weights=ws[sel])
        if comm is not None:
            h = global_sum(comm, h)
        c = below + np.cumsum(h)
        k = int(np.searchsorted(c, target))
        k = min(k, HIST_BINS - 1)
        below = c[k - 1] if k > 0 else below
        lo, hi = edges[k], edges[k + 1]
    return 0.5 * (lo + hi)


class Decomposition:
    """Boxes of ``nranks`` ranks over the domain [lo, hi] (periodic axes flagged)."""

    def __init__(self, nranks, lo, hi, periodic, method="rcb", slab_axis="auto"):
        self.nranks = nranks
        self.lo = np.asarray(lo, float)
        self.hi = np.asarray(hi, float)
        self.periodic = np.asarray(periodic, bool)
        self.method = method
        self.slab_axis = slab_axis
        self.blo = np.zeros((nranks, 3))
        self.bhi = np.zeros((nranks, 3))
        self.nodes = []  # (axis, cut, left, right); a child < 0 is the leaf of rank -1 - child
        self.halo = 0.0

    def _root_box(self):
        blo = np.where(self.periodic, self.lo, -np.inf)
        bhi = np.where(self.periodic, self.hi, np.inf)
        return blo, bhi

    def _axis(self, blo, bhi):
        if self.method == "slabs":
            if self.slab_axis != "auto":
                return "xyz".index(self.slab_axis)
            return int(np.argmax(self.hi - self.lo))
        ext = np.minimum(bhi, self.hi) - np.maximum(blo, self.lo)
        return int(np.argmax(ext))

    def build(self, comm, x, weights, halo=0.0):
        """Collective: cut the domain so that every rank gets an equal share of the weight.
        ``x`` and ``weights`` are this rank's particles (any disjoint split of all of them,
        a rank may hold none); ``halo``: the ghost layer width the periodic cuts respect."""
        self.nodes = []
        self.halo = float(halo)
        blo, bhi = self._root_box()
        self._split(comm, x, weights, 0, self.nranks, blo, bhi)
        return self

    def _candidate_axes(self, comm, xin, blo, bhi):
        """Axes to cut box [blo, bhi], best first: slabs its one axis; rcb by decreasing
        extent of the particles inside the box (global), the box's own extent breaking ties
        and serving when the box holds no particle."""
        if self.method == "slabs":
            return [self._axis(blo, bhi)]
        ext = np.minimum(bhi, self.hi) - np.maximum(blo, self.lo)
        lohi = np.concatenate([-xin.min(axis=0), xin.max(axis=0)]) if xin.shape[0] else np.full(6, -np.inf)
        if comm is not None:
            glob = np.empty(6)
            comm.Allreduce(np.ascontiguousarray(lohi, float), glob, op=_mpi_max())
            lohi = glob
        pext = lohi[3:] + lohi[:3]
        pext = np.where(np.isfinite(pext), pext, 0.0)
        return sorted(range(3), key=lambda k: (-pext[k], -ext[k], k))

    def _cut_range(self, ax, blo, bhi):
        """Interval where a cut of box [blo, bhi] along ``ax`` keeps both halves valid (see
        the module docstring), or None."""
        a = max(blo[ax], self.lo[ax])
        b = min(bhi[ax], self.hi[ax])
        if self.periodic[ax] and blo[ax] <= self.lo[ax] and bhi[ax] >= self.hi[ax]:
            h2 = 2.0 * self.halo
            return (a + h2, b - h2) if b - a >= 2.0 * h2 else None
        return a, b

    def _split(self, comm, x, w, r0, r1, blo, bhi):
        if r1 - r0 == 1:
            self.blo[r0] = blo
            self.bhi[r0] = bhi
            return -1 - r0
        nl = (r1 - r0) // 2
        inside = np.all((x >= blo) & (x < bhi), axis=1)
        axes = self._candidate_axes(comm, x[inside], blo, bhi)
        ax, rng = next(((k, r) for k in axes for r in [self._cut_range(k, blo, bhi)] if r is not None),
                       (axes[0], None))
        if rng is None:  # nothing can be cut: the lower ranks get an empty box at the domain's start
            cut = float(self.lo[ax])
        else:
            a, b = max(blo[ax], self.lo[ax]), min(bhi[ax], self.hi[ax])
            xs = np.clip(x[inside, ax], a, b)
            cut = _weighted_cut(comm, xs, w[inside], a, b, nl / (r1 - r0))
            cut = float(min(max(cut, rng[0]), rng[1]))
        me = len(self.nodes)
        self.nodes.append([ax, cut, 0, 0])
        lhi = bhi.copy()
        lhi[ax] = cut
        rlo = blo.copy()
        rlo[ax] = cut
        self.nodes[me][2] = self._split(comm, x, w, r0, r0 + nl, blo, lhi)
        self.nodes[me][3] = self._split(comm, x, w, r0 + nl, r1, rlo, bhi)
        return me

    def owner(self, x):
        """Rank owning each position (tree descent, vectorised)."""
        n = x.shape[0]
        if self.nranks == 1:
            return np.zeros(n, np.int64)
        node = np.zeros(n, np.int64)
        nodes = np.array(self.nodes, float)
        axis = nodes[:, 0].astype(np.int64)
        cut = nodes[:, 1]
        left = nodes[:, 2].astype(np.int64)
        right = nodes[:, 3].astype(np.int64)
        active = node >= 0
        while np.any(active):
            k = node[active]
            xv = x[np.nonzero(active)[0], axis[k]]
            node[active] = np.where(xv < cut[k], left[k], right[k])
            active = node >= 0
        return -1 - node

    def box_distance(self, x, q):
        """Distance from each position to box q, and the periodic shift (per axis) that
        brings the position nearest to it."""
        L = self.hi - self.lo
        d2 = np.zeros(x.shape[0])
        shift = np.zeros_like(x)
        for k in range(3):
            lo_k, hi_k = self.blo[q, k], self.bhi[q, k]
            best = np.maximum(np.maximum(lo_k - x[:, k], x[:, k] - hi_k), 0.0)
            if self.periodic[k] and not (lo_k <= self.lo[k] and hi_k >= self.hi[k]):
                for s in (-L[k], L[k]):
                    xs = x[:, k] + s
                    dk = np.maximum(np.maximum(lo_k - xs, xs - hi_k), 0.0)
                    better = dk < best
                    best = np.where(better, dk, best)
                    shift[:, k] = np.where(better, s, shift[:, k])
            d2 += best * best
        return np.sqrt(d2), shift

    def neighbours(self, me, halo):
        """Ranks whose box lies within ``halo`` of box ``me`` (periodic images included).
        Symmetric to the last bit (q is a neighbour of me exactly when me is one of q: the
        distance of a pair is computed in one order, lower rank first), as the ghost messages,
        which go only between neighbours, need."""
        out = []
        L = self.hi - self.lo
        for q in range(self.nranks):
            if q == me:
                continue
            i, j = min(me, q), max(me, q)
            d2 = 0.0
            for k in range(3):
                best = max(self.blo[j, k] - self.bhi[i, k], self.blo[i, k] - self.bhi[j, k], 0.0)
                if self.periodic[k]:
                    for s in (-L[k], L[k]):
                        best = min(best, max(self.blo[j, k] - self.bhi[i, k] - s,
                                             self.blo[i, k] + s - self.bhi[j, k], 0.0))
                d2 += best * best
            if d2 < halo * halo:
                out.append(q)
        return out

    def spans(self, me):
        """Axes along which box ``me`` covers the whole (periodic) domain."""
        return (self.blo[me] <= self.lo) & (self.bhi[me] >= self.hi)

    def min_width(self):
        """Narrowest box extent along a cut axis (inside the domain)."""
        w = np.minimum(self.bhi, self.hi) - np.maximum(self.blo, self.lo)
        return float(w.min())

    def periodic_ok(self, halo):
        """True when every box leaves at least two halos of each periodic axis it does not
        span to the other boxes (see the module docstring)."""
        L = self.hi - self.lo
        w = np.minimum(self.bhi, self.hi) - np.maximum(self.blo, self.lo)
        spans = (self.blo <= self.lo) & (self.bhi >= self.hi)
        bad = self.periodic[None, :] & ~spans & (L[None, :] - w < 2.0 * halo * (1 - 1e-12))
        return not bool(np.any(bad))

    def describe(self):
        names = "xyz"
        cuts = ", ".join(f"{names[int(a)]}={c:.4g}" for a, c, _, _ in self.nodes)
        return f"{self.method} over {self.nranks} ranks (cuts {cuts})"


def _mpi_max():
    from mpi4py import MPI
    return MPI.MAX
