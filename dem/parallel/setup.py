"""The collectives of a scene set up per rank (``mpirun -np N``, N > 1): dem.scene reads each
packing file by slices, keeps a slice of every explicit list and inserts each ``count``
group on one rank, so no rank holds an array of all particles. What needs the whole scene
is a reduced scalar or an agreed first problem:

* :meth:`SetupComm.sum` / ``max`` / ``min`` / ``exscan``: typed ``Allreduce`` / ``Exscan`` of
  a few numbers (totals, offsets, the largest radius);
* :meth:`SetupComm.agree`: every rank gives the ordering key of its first problem (the row or
  line in file order, a check index in front) or None; the smallest key wins, the rank that
  holds it sends its message (``Bcast`` of its UTF-8 bytes) and every rank gets the same text,
  so every rank raises the same SceneError and the CLI prints one line;
* :meth:`SetupComm.duplicates`: the first repeated id of a distributed column (ids hashed to
  ranks by ``id % N``: an ``Alltoall`` of counts, then typed ``Alltoallv``).

Set-up runs once per run: nothing here is on a repeating path.
"""
import numpy as np

BIG = np.iinfo(np.int64).max


def _mpi():
    from mpi4py import MPI
    return MPI


class SetupComm:
    """One communicator's set-up collectives (see the module docstring)."""

    def __init__(self, comm):
        self.comm = comm
        self.rank = comm.Get_rank()
        self.size = comm.Get_size()
        self.rows_read = 0      # packing-file rows this rank read
        self.largest_read = 0   # rows of the largest particle array this rank built (an insertion)

    def _red(self, x, op, dtype):
        a = np.ascontiguousarray(np.atleast_1d(np.asarray(x, dtype)))
        out = np.empty_like(a)
        self.comm.Allreduce(a, out, op=op)
        return out if np.ndim(x) else out[0]

    def sum(self, x, dtype=np.int64):
        return self._red(x, _mpi().SUM, dtype)

    def max(self, x, dtype=float):
        return self._red(x, _mpi().MAX, dtype)

    def min(self, x, dtype=float):
        return self._red(x, _mpi().MIN, dtype)

    def exscan(self, x):
        """Sum of ``x`` (int64, scalar or vector) over the lower ranks (0 on rank 0)."""
        a = np.ascontiguousarray(np.atleast_1d(np.asarray(x, np.int64)))
        out = np.zeros_like(a)
        self.comm.Exscan(a, out, op=_mpi().SUM)
        if self.rank == 0:
            out[:] = 0
        return out if np.ndim(x) else int(out[0])

    def allgather(self, x):
        """int64 ``x`` of every rank, in rank order."""
        a = np.ascontiguousarray(np.atleast_1d(np.asarray(x, np.int64)))
        out = np.empty((self.size,) + a.shape, np.int64)
        self.comm.Allgather(a, out)
        return out

    def agree(self, key, text):
        """The message of the smallest ``key`` over the ranks (None: no problem on this rank),
        the same str on every rank, or None when no rank has a problem. ``text``: this rank's
        message (a str, or a callable giving it, only called on the winning rank)."""
        mine = BIG if key is None else int(key)
        best = int(self.min(mine, np.int64))
        if best == BIG:
            return None
        owner = int(self.min(self.rank if mine == best else self.size, np.int64))
        if self.rank == owner:
            msg = (text() if callable(text) else text).encode("utf-8")
            n = np.array([len(msg)], np.int64)
        else:
            n = np.zeros(1, np.int64)
        self.comm.Bcast(n, root=owner)
        buf = np.frombuffer(msg, np.uint8).copy() if self.rank == owner else np.empty(int(n[0]), np.uint8)
        self.comm.Bcast(buf, root=owner)
        return buf.tobytes().decode("utf-8")

    def duplicates(self, ids, rows, extra=None):
        """The first repeated value of a distributed int64 column: (later row, earlier row,
        id, extra of the later, extra of the earlier) of the smallest global row whose id
        appeared on an earlier row (the earlier: the last one before it), the same on every
        rank, or None. ``rows``: the global rows of this rank's ``ids``; ``extra``: an int64
        per row carried along (a CSV line number)."""
        ids = np.ascontiguousarray(ids, np.int64)
        rows = np.ascontiguousarray(rows, np.int64)
        extra = rows if extra is None else np.ascontiguousarray(extra, np.int64)
        dest = ids % self.size
        order = np.argsort(dest, kind="stable")
        send = np.ascontiguousarray(np.stack([ids, rows, extra], 1)[order])
        cnt = np.bincount(dest, minlength=self.size).astype(np.int64)
        inc = np.empty_like(cnt)
        self.comm.Alltoall(cnt, inc)
        got = np.empty((int(inc.sum()), 3), np.int64)
        soff = np.concatenate([[0], np.cumsum(cnt)[:-1]]) * 3
        roff = np.concatenate([[0], np.cumsum(inc)[:-1]]) * 3
        self.comm.Alltoallv([send, cnt * 3, soff, _mpi().INT64_T], [got, inc * 3, roff, _mpi().INT64_T])
        s = np.lexsort((got[:, 1], got[:, 0]))
        g = got[s]
        eq = np.nonzero(g[1:, 0] == g[:-1, 0])[0]
        found = np.zeros(5, np.int64)
        key = None
        if eq.size:
            k = eq[np.argmin(g[eq + 1, 1])]
            key = int(g[k + 1, 1])
            found[:] = (g[k + 1, 1], g[k, 1], g[k, 0], g[k + 1, 2], g[k, 2])
        best = int(self.min(BIG if key is None else key, np.int64))
        if best == BIG:
            return None
        owner = int(self.min(self.rank if key == best else self.size, np.int64))
        self.comm.Bcast(found, root=owner)
        return tuple(int(v) for v in found)

    def gather_near(self, x, r, lo, hi, root):
        """Positions and radii of this rank's rows inside the box [lo, hi] collected on
        ``root`` (typed ``Gatherv``); None on the other ranks."""
        inside = np.nonzero(np.all((x >= lo) & (x <= hi), axis=1))[0]
        loc = np.ascontiguousarray(np.concatenate([x[inside], r[inside, None]], 1), float).reshape(-1)
        cnt = np.empty(self.size, np.int64)
        self.comm.Allgather(np.array([loc.size], np.int64), cnt)
        if self.rank == root:
            out = np.empty(int(cnt.sum()))
            off = np.concatenate([[0], np.cumsum(cnt)[:-1]])
            self.comm.Gatherv(loc, [out, cnt, off, _mpi().DOUBLE], root=root)
            out = out.reshape(-1, 4)
            return np.ascontiguousarray(out[:, :3]), np.ascontiguousarray(out[:, 3])
        self.comm.Gatherv(loc, None, root=root)
        return None


# ---------------------------------------------------------------------------- after the distribution
def check_overlaps(world, par):
    """Initial overlaps beyond [simulation] initial_overlap_ratio, on this rank's owned rows and
    their ghosts after the first exchange (the ghosts sit at the periodic image next to the
    box): the largest overlap over the ranks, ties to the pair of smallest ids, named as the
    serial check names it. SceneError on every rank."""
    from scipy.spatial import cKDTree
    from ..errors import SceneError
    sc, st = world.scene, world.state
    comm = SetupComm(par.comm)
    n, nown = st.n, st.n_owned
    x, r = st.position[:n], st.radius[:n]
    ov_max, pair = -np.inf, None
    if n >= 2 and nown:
        # a periodic axis this rank's box spans has no ghost images: the tree wraps it
        wrap = par.dec.spans(par.rank) & np.asarray(st.periodic, bool)
        box, xx = None, x
        if wrap.any():
            L = st.hi - st.lo
            xx = x - st.lo
            xx = np.where(wrap, np.mod(xx, np.where(wrap, L, 1.0)), xx)
            span = xx.max(0) - xx.min(0) + 10 * r.max()
            box = np.where(wrap, L, span + 1.0)
            xx = xx - np.where(wrap, 0.0, xx.min(0) - 1e-9)
        pairs = cKDTree(xx, boxsize=box).query_pairs(2 * world.rmax, output_type="ndarray")
        if pairs.size:
            pairs = pairs[np.minimum(pairs[:, 0], pairs[:, 1]) < nown]
        if pairs.size:
            dv = xx[pairs[:, 0]] - xx[pairs[:, 1]]
            if box is not None:
                dv -= box * np.round(dv / box)
            d = np.linalg.norm(dv, axis=1)
            ov = (r[pairs[:, 0]] + r[pairs[:, 1]] - d) / np.minimum(r[pairs[:, 0]], r[pairs[:, 1]])
            ov_max = float(ov.max())
            cand = pairs[ov == ov_max]
            a = np.minimum(st.id[cand[:, 0]], st.id[cand[:, 1]])
            b = np.maximum(st.id[cand[:, 0]], st.id[cand[:, 1]])
            k = np.lexsort((b, a))[0]
            i, j = (cand[k, 0], cand[k, 1]) if st.id[cand[k, 0]] < st.id[cand[k, 1]] else (cand[k, 1], cand[k, 0])
            pair = (int(st.id[i]), int(st.id[j]), int(st.group[i]))
    best = float(comm.max(ov_max))
    allowed = sc.simulation["initial_overlap_ratio"]
    if not best > allowed:
        return
    mine = pair is not None and ov_max == best
    first = int(comm.min(pair[0] if mine else BIG, np.int64))
    key = pair[1] if mine and pair[0] == first else None
    msg = comm.agree(key, lambda: f"{pair[2]}\nparticles id {pair[0]} and id {pair[1]} overlap by {best:.3g} of the "
                                  f"smaller radius initially (allowed: simulation.initial_overlap_ratio = {allowed})")
    g, text = msg.split("\n", 1)
    raise SceneError(sc.file, f"particles[{g}]", text)


# ---------------------------------------------------------------------------- restart digests
_GOLD = np.uint64(0x9E3779B97F4A7C15)


def _mix(h):
    """splitmix64's finaliser on uint64 arrays (wrapping arithmetic)."""
    h = (h ^ (h >> np.uint64(30))) * np.uint64(0xBF58476D1CE4E5B9)
    h = (h ^ (h >> np.uint64(27))) * np.uint64(0x94D049BB133111EB)
    return h ^ (h >> np.uint64(31))


def _row_hashes(ids, a):
    """One uint64 per row of ``a``, from its id and the row's bytes."""
    a = np.ascontiguousarray(a)
    n = a.shape[0]
    raw = a.reshape(n, -1).view(np.uint8) if n else np.zeros((0, 8), np.uint8)
    pad = (-raw.shape[1]) % 8
    if pad:
        raw = np.concatenate([raw, np.zeros((n, pad), np.uint8)], 1)
    words = np.ascontiguousarray(raw).view(np.uint64)
    with np.errstate(over="ignore"):
        h = _mix(ids.astype(np.uint64) + _GOLD)
        for c in range(words.shape[1]):
            h = _mix(h ^ (words[:, c] + _GOLD))
    return h


def particle_digests(sc, comm):
    """The particle definitions' digests of a scene set up per rank (dem.checkpoint's restart
    comparison): per array the sum over all particles (mod 2^64, a typed Allreduce) of a hash of
    (id, row), so the same on any number of ranks. Their keys end in ``_sum``: a restart compares
    them with a checkpoint written under MPI; the serial digests (id-ordered sha256) have other
    keys, and neither is compared with the other."""
    import hashlib
    from ..parcels import parcel_factors
    ids = np.asarray(sc.id, np.int64)
    names = np.array([int.from_bytes(hashlib.sha256(m["name"].encode()).digest()[:8], "little")
                      for m in sc.materials], np.uint64)
    arrays = dict(ids=ids, radius=sc.radius, material=names[sc.material], position=sc.position,
                  velocity=sc.velocity, angular_velocity=sc.angular_velocity, group=np.asarray(sc.group, np.int32))
    if sc.thermal is not None:
        arrays["temperature"] = np.asarray(sc.thermal["temperature"], float)
    cg = parcel_factors(sc)
    if cg is not None:
        arrays["coarse_graining"] = np.asarray(cg, float)
    MPI = _mpi()
    loc = np.array([_row_hashes(ids, a).sum(dtype=np.uint64) for a in arrays.values()], np.uint64)
    tot = np.empty_like(loc)
    comm.comm.Allreduce(loc, tot, op=MPI.SUM)
    sc.particle_digests = {f"{k}_sum": f"{int(v):016x}" for k, v in zip(arrays, tot)}
    return sc.particle_digests
