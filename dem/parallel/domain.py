"""ParallelDomain: what one rank does to share a run with the others.

* Ownership: each rank owns the particles inside its box (dem.parallel.decomposition).
* Exchange (at every neighbour-list rebuild, like LAMMPS' reneighbouring): ghosts are
  dropped, the load is measured and the boxes re-cut when the imbalance exceeds
  [parallel] balance_threshold, particles that left their box migrate to their new owner
  with every per-particle array and the contact history that involves them (as id-keyed
  records), then each rank sends as ghosts its particles within one halo
  (2 r_max + reach + skin) of a neighbour's box, shifted by the periodic image that
  brings them next to it.
  Nothing is pickled on this path: migration sends an ``Alltoall`` of int64 counts (particles,
  records and which record fields, per rank pair), then typed buffers (one per dtype, the
  particles' declared arrays and their records) only between ranks with something to send;
  ghosts go only to and from the neighbour ranks (``neigh``), first one count per
  neighbour, then one typed buffer per dtype. A failure on one rank is agreed on through the
  counts (migration) or one flag (``Allreduce``: ghosts, cost), and only then are the
  messages gathered, so that every rank raises the same error.
* Forward communication (every step): positions, velocities, angular velocities (and
  temperatures) of the ghosts, one message per neighbour rank.
A pair of an owned particle and a ghost is computed on both ranks ("newton off" across
ranks); forces on ghosts are discarded, so no reverse communication is needed.
"""
import numpy as np

from .decomposition import Decomposition
from . import records as R
from .. import schema as S


class ParallelError(RuntimeError):
    pass


# message tags (the per-step forward message uses 11); a typed buffer's tag is its base plus
# the index of its dtype in the exchange's dtype order
_TAG_GHOST_COUNT = 21
_TAG_GHOST = 30
_TAG_MIGRATE = 50


class _Rows:
    """Where the values of one row (a particle, a contact record) sit in typed buffers: the
    arrays' columns grouped by dtype, one 2-D buffer ``(rows, width[dtype])`` per dtype, so that
    every value travels with its own MPI datatype and arrives bit for bit (ids as int64,
    materials as int32, ...). ``specs``: (name, dtype, shape after the first axis), in the
    declared order; ``width`` keeps the dtypes in the order first met."""

    def __init__(self, specs):
        self.width = {}
        self.cols = []  # (name, dtype, first column, columns, shape after the first axis)
        for name, dt, tail in specs:
            dt = np.dtype(dt)
            tail = tuple(int(t) for t in tail)
            w = int(np.prod(tail, dtype=np.int64))
            c = self.width.get(dt, 0)
            self.cols.append((name, dt, c, w, tail))
            self.width[dt] = c + w

    def pack(self, bufs, values):
        """Copy ``values`` (name -> array with one row per row of the buffers) into ``bufs``."""
        for name, dt, c, w, _ in self.cols:
            v = values[name]
            bufs[dt][:, c:c + w] = v.reshape(v.shape[0], w)

    def unpack(self, bufs, n):
        """name -> the ``n`` rows of each array, as views of ``bufs``."""
        return {name: bufs[dt][:, c:c + w].reshape((n,) + tail) for name, dt, c, w, tail in self.cols}


_ALL_RECORD_FIELDS = (1 << len(R.HISTORY)) - 1


def _record_mask(rec):
    """The history fields a set of records holds, one bit per :data:`records.HISTORY` field
    (a field is None on a rank whose arrays had no rows: records.extract)."""
    if rec is None:
        return 0
    return sum(1 << k for k, f in enumerate(R.HISTORY) if rec.get(f.name) is not None)


_RECORD_ROWS = {}


def _record_rows(mask):
    """Layout of a contact record: the two ids (int64), then the fields of ``mask`` (a
    pair array's shape without its slot axis: ``hist`` (S, 3) -> 3 columns)."""
    rows = _RECORD_ROWS.get(mask)
    if rows is None:
        rows = _RECORD_ROWS[mask] = _Rows([("a", S.I8, ()), ("b", S.I8, ())] + [
            (f.name, f.dtype, f.tail[1:]) for k, f in enumerate(R.HISTORY) if mask >> k & 1])
    return rows


def _union(*layouts):
    """The dtypes of the layouts, in the order first met (one message per dtype and peer)."""
    out = []
    for lay in layouts:
        out += [dt for dt in lay.width if dt not in out]
    return out


def _head(bufs, rows, n):
    """2-D views of the first ``n`` rows of layout ``rows`` in the 1-D per-dtype buffers."""
    return {dt: bufs[dt][:n * w].reshape(n, w) for dt, w in rows.width.items()}


def _tail(bufs, rows, n, recs, m):
    """2-D views of the ``m`` records (layout ``recs``) after ``n`` rows of layout ``rows``."""
    return {dt: bufs[dt][n * rows.width.get(dt, 0):n * rows.width.get(dt, 0) + m * w].reshape(m, w)
            for dt, w in recs.width.items()}


class ParallelDomain:
    def __init__(self, comm, world):
        self.comm = comm
        self.rank = comm.Get_rank()
        self.size = comm.Get_size()
        cfg = world.scene.parallel
        self.cfg = cfg
        self.dec = Decomposition(self.size, world.state.lo, world.state.hi, world.state.periodic, cfg["decomposition"],
                                 cfg["slab_axis"])
        self.key_base = int(comm.allreduce(int(world.state.id.max(initial=0)), op=_mpi().MAX)) + 1
        self.sends = []  # (rank, rows, shift)
        self.recvs = []  # (rank, first ghost row, count)
        self.neigh = []
        self.exchanges = 0
        self.rebalances = 0
        self.migrated = 0
        self.setup_migrated = 0  # rows sent to their owners when a scene set up per rank was distributed
        self.records_migrated = 0  # contact records sent with the migrating particles
        self.bytes_migrated = 0  # typed payload this rank sent in migrations (particles + records)
        self.bytes_ghosts = 0  # typed payload this rank sent as ghosts at the exchanges
        self.sort_pending = False
        self.recut_pending = False   # cut the boxes at the next exchange whatever the load (a restart)
        self.imbalance = 1.0
        self.cg_solves = 0      # the implicit heat steps' solves (dem.thermal.implicit_mpi), their
        self.cg_iterations = 0  # conjugate-gradient iterations and the bytes of ghost values this
        self.cg_bytes = 0       # rank sent for them
        self._bufs = {}

    # ------------------------------------------------------------------ collectives
    def allmax(self, x):
        return self.comm.allreduce(x, op=_mpi().MAX)

    def allmin(self, x):
        return self.comm.allreduce(x, op=_mpi().MIN)

    def allsum(self, x):
        return self.comm.allreduce(x, op=_mpi().SUM)

    def _reduce(self, values, op):
        """Element-wise reduction over ranks of a few float64 in one buffer message (nothing
        pickled): what a step or a rebuild needs agreed by every rank."""
        buf = np.array(values, float)
        out = np.empty(len(buf))
        self.comm.Allreduce(buf, out, op=op)
        return out

    def sums(self, *values):
        """Element-wise sum over ranks of a few float64 (one buffer message)."""
        return self._reduce(values, _mpi().SUM)

    def flags(self, a, b):
        """Element-wise max over ranks of two numbers (one message per step)."""
        out = self._reduce((a, b), _mpi().MAX)
        return out[0], out[1]

    def gather(self, obj):
        return self.comm.gather(obj, root=0)

    # ------------------------------------------------------------------ arrays
    @staticmethod
    def _moving(st):
        """(name, array) of the per-particle arrays that travel with a particle (dem.schema
        ``migrate``) and that this run enables: the disabled ones are empty arrays on every
        rank, never cut, sent or padded, whatever the particles a rank owns."""
        for f in S.of("particle"):
            if f.migrate and S.enabled(f, st.features):
                yield f.name, getattr(st, f.name)

    def _take(self, st, rows):
        for name, a in list(self._moving(st)):
            setattr(st, name, np.ascontiguousarray(a[rows]))

    def select_initial(self, world):
        """The first boxes. A scene set up per rank (dem.scene, ``distributed``): cut them on
        the rows each rank holds, send every row to its owner through the migration of
        :meth:`exchange` and order the owned rows by id. A scene held whole by every rank:
        cut them on a disjoint split (row % size) and keep the owned rows (possibly none)."""
        st = world.state
        if getattr(world.scene, "distributed", False):
            halo = world.halo(bound=True)
            self.dec.build(self.comm, st.position, np.ones(st.n_owned), halo)
            self.neigh = self.dec.neighbours(self.rank, halo)
            st.n_ghost = 0
            self._migrate(world, None)
            self._take(st, np.argsort(st.id, kind="stable"))
            self.setup_migrated, self.migrated, self.bytes_migrated = self.migrated, 0, 0
            self._hold_mesh(world)
            return
        x = st.position
        part = np.arange(self.rank, st.n, self.size)
        halo = world.halo(bound=True)
        self.dec.build(self.comm, x[part], np.ones(part.size), halo)
        own = np.nonzero(self.dec.owner(x) == self.rank)[0]
        self._take(st, own)
        st.n_owned = own.size
        st.n_ghost = 0
        self.neigh = self.dec.neighbours(self.rank, halo)
        self._hold_mesh(world)

    def _hold_mesh(self, world):
        """The mesh triangles near this rank's box, after a cut of the boxes (World.hold_mesh_near)."""
        if world.nmeshes:
            world.hold_mesh_near(self.dec.blo[self.rank], self.dec.bhi[self.rank])

    # ------------------------------------------------------------------ exchange
    def exchange(self, world, rec, weights=None):
        """Drop ghosts, re-balance if needed, migrate, sort if asked, send ghosts.
        ``rec``: contact records of this rank (dem.parallel.records); returns the records
        this rank needs after the exchange. Any rank may own no particle before or after.
        A failure on one rank reaches every rank through the next collective of the
        exchange, and all of them raise the same SimulationError (no rank is left waiting)."""
        st = world.state
        halo = world.halo()
        err = None
        cost = 0.0
        try:
            self._take(st, np.arange(st.n_owned))
            st.n_ghost = 0
            if weights is None:
                weights = np.ones(st.n_owned)
            cost = float(weights.sum())
        except Exception as exc:  # noqa: BLE001 - shared below, raised on every rank
            err = self._error_text(world, exc, "dropping the ghosts")
        costs = np.empty((self.size, 2))
        self.comm.Allgather(np.array([cost, 1.0 if err else 0.0]), costs)
        if np.any(costs[:, 1] != 0.0):
            _raise_shared(self.comm.allgather(err))
        # the cuts and the neighbour ranks for the largest skin (an adaptive skin may grow back
        # between two re-cuts), the ghosts for the skin of this build
        cut = self._rebalance(world, np.ascontiguousarray(costs[:, 0]), weights, world.halo(bound=True))
        if world.nmeshes and (cut or world.time >= world.mesh_until):
            self._hold_mesh(world)   # (before the build after this exchange finds the candidates)
        rec = self._migrate(world, rec)
        self._send_ghosts(world, halo)
        self.exchanges += 1
        self._bufs = {}
        return rec

    def _rebalance(self, world, costs, weights, halo):
        """Re-cut the boxes (collective) when the largest rank cost exceeds the mean by more
        than [parallel] balance_threshold, or when asked (``recut_pending``: a restart read its
        particles by slices, evenly spread but not in the scene's boxes). Every cut is legal (decomposition.py), so the new
        cuts are always taken. Returns whether the boxes were cut."""
        cmean = float(costs.sum()) / self.size
        self.imbalance = float(costs.max()) / max(cmean, 1e-300)
        if self.imbalance <= self.cfg["balance_threshold"] and not self.recut_pending:
            return False
        self.recut_pending = False
        before = [list(n) for n in self.dec.nodes]
        self.dec.build(self.comm, world.state.position, weights, halo)
        if self.dec.nodes != before:
            self.rebalances += 1
        self.neigh = self.dec.neighbours(self.rank, halo)
        return True

    def _migrate(self, world, rec):
        """Send the particles that left this rank's box to their owners, with their contact
        records; take in the particles that arrive (after the owned ones that stay, in the
        order of the source ranks).

        An ``Alltoall`` of three int64 per rank pair (particles, records, the record fields
        the sender holds: a bit per :data:`records.HISTORY` field; particles = -1: the sender
        failed), then, only between the ranks that send something, one buffer per dtype
        holding the particles' declared arrays (:class:`_Rows`) followed by their records."""
        MPI = _mpi()
        st = world.state
        counts = np.zeros((self.size, 3), np.int64)
        out = {}
        leave = np.zeros(0, bool)
        err = None
        try:
            moving = list(self._moving(st))
            rows_of = _Rows((name, a.dtype, a.shape[1:]) for name, a in moving)
            dtypes = _union(rows_of, _record_rows(_ALL_RECORD_FIELDS))
            dest = self.dec.owner(st.position)
            leave = dest != self.rank
            mask = _record_mask(rec)
            rrows = _record_rows(mask)
            arrays = dict(moving)
            for q in np.unique(dest[leave]):
                rows = np.nonzero(dest == q)[0]
                sub = R.involving(rec, st.id[rows]) if rec is not None else None
                m = sub["a"].shape[0] if sub is not None else 0
                bufs = {dt: np.empty(rows.size * rows_of.width.get(dt, 0) + m * rrows.width.get(dt, 0), dt)
                        for dt in dtypes}
                rows_of.pack(_head(bufs, rows_of, rows.size), {k: a[rows] for k, a in arrays.items()})
                if m:
                    rrows.pack(_tail(bufs, rows_of, rows.size, rrows, m), sub)
                out[int(q)] = bufs
                counts[q] = (rows.size, m, mask)
        except Exception as exc:  # noqa: BLE001 - shared below, raised on every rank
            err = self._error_text(world, exc, "packing the migrating particles")
            counts[:] = (-1, 0, 0)
            out = {}
        inc = np.empty_like(counts)
        self.comm.Alltoall(counts, inc)
        if np.any(inc[:, 0] < 0):  # the failing rank sent -1 to every rank, itself included
            _raise_shared(self.comm.allgather(err))
        got = {}
        reqs = []
        for q in range(self.size):
            n, m, qmask = (int(v) for v in inc[q])
            if n > 0:
                rr = _record_rows(qmask)
                bufs = {dt: np.empty(n * rows_of.width.get(dt, 0) + m * rr.width.get(dt, 0), dt) for dt in dtypes}
                got[q] = (n, m, rr, bufs)
                reqs += [self.comm.Irecv(b, source=q, tag=_TAG_MIGRATE + k)
                         for k, (dt, b) in enumerate(bufs.items()) if b.size]
        for q, bufs in out.items():
            reqs += [self.comm.Isend(b, dest=q, tag=_TAG_MIGRATE + k)
                     for k, (dt, b) in enumerate(bufs.items()) if b.size]
            self.bytes_migrated += sum(b.nbytes for b in bufs.values())
            self.records_migrated += int(counts[q, 1])
        MPI.Request.Waitall(reqs)
        parts, recs = [], []
        for q in sorted(got):
            n, m, rr, bufs = got[q]
            parts.append(rows_of.unpack(_head(bufs, rows_of, n), n))
            r = rr.unpack(_tail(bufs, rows_of, n, rr, m), m)
            recs.append({k: r.get(k) for k in R.FIELDS})
        keep = np.nonzero(~leave)[0]
        self.migrated += int(leave.sum())
        for name, a in moving:
            setattr(st, name, np.ascontiguousarray(np.concatenate([a[keep]] + [p[name] for p in parts])))
        if rec is not None:
            rec = R.concat([rec] + recs)
        st.n_owned = st.id.shape[0]
        if self.sort_pending:  # spatial sort of the owned rows (cache locality)
            from ..neighbors import sort_permutation
            self._take(st, sort_permutation(st.position, world.state.lo, world.state.hi, world.halo(bound=True)))
            self.sort_pending = False
        return rec

    def _send_ghosts(self, world, halo):
        """Send every neighbour rank this rank's particles within one halo of its box
        (shifted by the periodic image nearest to it); append the ghosts received, in the
        order of ``neigh``.

        One flag (``Allreduce``: did any rank fail to pack?), then to and from each neighbour
        one int64 count and one buffer per dtype of the declared ghost arrays (:class:`_Rows`)."""
        MPI = _mpi()
        st = world.state
        nown = st.n_owned
        self.sends = []
        out = []
        err = None
        try:
            ghost = [(name, a) for name, a in self._moving(st) if S.BY_NAME[name].ghost]
            rows_of = _Rows((name, a.dtype, a.shape[1:]) for name, a in ghost)
            for q in self.neigh:
                d, shift = self.dec.box_distance(st.position, q)
                rows = np.nonzero(d < halo)[0]
                sh = np.ascontiguousarray(shift[rows])
                self.sends.append((q, rows, sh))
                bufs = {dt: np.empty((rows.size, w), dt) for dt, w in rows_of.width.items()}
                rows_of.pack(bufs, {name: (a[rows] + sh if name == "position" else a[rows]) for name, a in ghost})
                out.append(bufs)
        except Exception as exc:  # noqa: BLE001 - shared below, raised on every rank
            err = self._error_text(world, exc, "packing the ghosts")
        failed = np.empty(1, np.int64)
        self.comm.Allreduce(np.array([1 if err else 0], np.int64), failed, op=MPI.MAX)
        if failed[0]:
            _raise_shared(self.comm.allgather(err))
        nq = len(self.neigh)
        sent = np.array([rows.size for _, rows, _ in self.sends], np.int64)
        cnt = np.zeros(nq, np.int64)
        reqs = [self.comm.Irecv(cnt[k:k + 1], source=q, tag=_TAG_GHOST_COUNT) for k, q in enumerate(self.neigh)]
        reqs += [self.comm.Isend(sent[k:k + 1], dest=q, tag=_TAG_GHOST_COUNT) for k, q in enumerate(self.neigh)]
        MPI.Request.Waitall(reqs)
        got = [{dt: np.empty((int(cnt[k]), w), dt) for dt, w in rows_of.width.items()} for k in range(nq)]
        reqs = []
        for k, q in enumerate(self.neigh):
            reqs += [self.comm.Irecv(b, source=q, tag=_TAG_GHOST + g) for g, b in enumerate(got[k].values()) if b.size]
        for k, q in enumerate(self.neigh):
            reqs += [self.comm.Isend(b, dest=q, tag=_TAG_GHOST + g) for g, b in enumerate(out[k].values()) if b.size]
            self.bytes_ghosts += sum(b.nbytes for b in out[k].values())
        MPI.Request.Waitall(reqs)
        self.recvs = []
        off = nown
        parts = []
        for k, q in enumerate(self.neigh):
            c = int(cnt[k])
            self.recvs.append((q, off, c))
            off += c
            parts.append(rows_of.unpack(got[k], c))
        for name, a in list(self._moving(st)):
            if S.BY_NAME[name].ghost:
                pieces = [a] + [p[name] for p in parts]
            else:
                pieces = [a, np.zeros((off - nown,) + a.shape[1:], a.dtype)]
            setattr(st, name, np.ascontiguousarray(np.concatenate(pieces)))
        st.n_ghost = off - nown

    def _error_text(self, world, exc, doing):
        return (f"rank {self.rank} failed while {doing} at t = {world.time:.9g} s (step {world.step_count}): "
                f"{type(exc).__name__}: {exc}")

    def grid_box(self, world):
        """Cell-grid box of this rank: the domain on periodic axes the box spans (the grid
        wraps there), else the extent of its owned particles and ghosts."""
        x = world.state.position
        spans = self.dec.spans(self.rank) & world.state.periodic
        glo = np.where(spans, world.state.lo, x.min(axis=0) if x.shape[0] else world.state.lo)
        ghi = np.where(spans, world.state.hi, x.max(axis=0) if x.shape[0] else world.state.hi)
        pad = 1e-9 * np.maximum(world.state.hi - world.state.lo, 1e-300)
        ghi = np.maximum(ghi, glo + pad)
        return np.ascontiguousarray(glo, float), np.ascontiguousarray(ghi + pad, float), \
            np.ascontiguousarray(spans, np.bool_)

    # ------------------------------------------------------------------ forward
    def forward(self, world, motion=True, temperature=False, porosity=False, rate=False):
        """Copy the owners' current values into the ghost rows."""
        st = world.state
        key = (motion, temperature, porosity, rate)
        b = st.bundles()  # the same object until an array of the state is replaced
        cache = self.__dict__.get("_cols")
        if cache is None or cache[0] is not b:
            cache = self._cols = (b, {})
        cols = cache[1].get(key)
        if cols is None:
            want = {"motion": motion, "temperature": temperature, "porosity": porosity, "rate": rate}
            cols = []
            for f in S.of("particle"):  # the arrays declared with that forward message (dem.schema)
                if f.forward and want[f.forward]:
                    a = getattr(st, f.name)
                    if f.forward == "rate":  # cross-rank conductance rates of the exponential heat update
                        a = a[:, 1]
                    cols.append((a, a.shape[1] if a.ndim == 2 else 1, f.name == "position"))
            cache[1][key] = cols
        return self._forward_cols(key, cols)

    def forward_vector(self, v):
        """Copy the owners' entries of one float64 value per row (``v``: owned rows, then the
        ghost rows) into its ghost rows: one message per neighbour rank, of 8 bytes a ghost
        (the conjugate gradients of an implicit heat step under MPI, dem.thermal.implicit_mpi).
        Returns the bytes this rank sent."""
        return self._forward_cols("vector", [(v, 1, False)])

    def _forward_cols(self, key, cols):
        """Send the sending rows of each array of ``cols`` ((array, columns, shifted by the
        periodic image)) to the neighbour ranks and write what arrives into the ghost rows."""
        from mpi4py import MPI
        nf = sum(c[1] for c in cols)
        if nf == 0 or not self.neigh:
            return 0
        bufs = self._bufs.get(key)
        if bufs is None:
            bufs = ([np.empty((rows.size, nf)) for _, rows, _ in self.sends],
                    [np.empty((cnt, nf)) for _, _, cnt in self.recvs])
            self._bufs[key] = bufs
        sb, rb = bufs
        reqs = []
        for k, (q, off, cnt) in enumerate(self.recvs):
            reqs.append(self.comm.Irecv(rb[k], source=q, tag=11))
        for k, (q, rows, sh) in enumerate(self.sends):
            c = 0
            for a, w, shifted in cols:
                if w == 1:
                    sb[k][:, c] = a[rows]
                else:
                    sb[k][:, c:c + w] = a[rows]
                    if shifted:
                        sb[k][:, c:c + w] += sh
                c += w
            reqs.append(self.comm.Isend(sb[k], dest=q, tag=11))
        MPI.Request.Waitall(reqs)
        for k, (q, off, cnt) in enumerate(self.recvs):
            c = 0
            for a, w, _ in cols:
                if w == 1:
                    a[off:off + cnt] = rb[k][:, c]
                else:
                    a[off:off + cnt] = rb[k][:, c:c + w]
                c += w
        return sum(b.nbytes for b in sb)

    def halo_bytes(self, thermal):
        """Bytes this rank sends per step in the forward communication."""
        nf = 9 + (1 if thermal else 0)
        return 8 * nf * sum(rows.size for _, rows, _ in self.sends)

    def describe(self):
        return self.dec.describe()

    def stats(self, world):
        """Run totals over the ranks (collective): ghosts, forward-communication bytes and
        messages per step, exchanges, migrations (particles, contact records and the bytes
        of their typed buffers), bytes sent as ghosts at the exchanges, re-balancings,
        current imbalance, the fewest and most mesh triangles a rank holds (World.hold_mesh_near),
        the implicit heat solves (the same count on every rank), their iterations and the bytes
        of ghost values sent for them."""
        st = world.state
        loc = np.array([st.n_ghost, self.halo_bytes(world.thermal is not None), len(self.sends),
                        self.migrated, self.records_migrated, self.bytes_migrated, self.bytes_ghosts,
                        self.cg_bytes], float)
        tot = self.allsum(loc)
        own = np.array(self.comm.allgather(st.n_owned), float)
        held = np.array(self.comm.allgather(world.mesh_held if world.nmeshes else 0))
        return dict(mesh_held=(int(held.min()), int(held.max())), ghosts=int(tot[0]), halo_bytes=float(tot[1]), messages=int(tot[2]),
                    migrated=int(tot[3]), records_migrated=int(tot[4]), bytes_migrated=int(tot[5]),
                    bytes_ghosts=int(tot[6]), exchanges=self.exchanges, rebalances=self.rebalances,
                    cg_solves=self.cg_solves, cg_iterations=self.cg_iterations, cg_bytes=int(tot[7]),
                    imbalance=float(own.max() / max(own.mean(), 1e-300)))


def _mpi():
    from mpi4py import MPI
    return MPI


def _raise_shared(errors):
    """Raise on every rank the first error any rank reported in a collective (the same
    message everywhere, so that the run stops on all ranks at the same point)."""
    msg = next((e for e in errors if e), None)
    if msg is not None:
        from ..errors import SimulationError
        raise SimulationError(msg)
