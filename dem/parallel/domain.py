"""ParallelDomain: what one rank does to share a run with the others.

* Ownership: each rank owns the particles inside its box (dem.parallel.decomposition).
* Exchange (at every neighbour-list rebuild, like LAMMPS' reneighbouring): ghosts are
  dropped, the load is measured and the boxes re-cut when the imbalance exceeds
  [parallel] balance_threshold, particles that left their box migrate to their new owner
  with every per-particle array and the contact history that involves them (as id-keyed
  records), then each rank sends as ghosts its particles within one halo
  (2 r_max + reach + skin) of a neighbour's box, shifted by the periodic image that
  brings them next to it.
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
        self.sort_pending = False
        self.imbalance = 1.0
        self._bufs = {}

    # ------------------------------------------------------------------ collectives
    def allmax(self, x):
        return self.comm.allreduce(x, op=_mpi().MAX)

    def allmin(self, x):
        return self.comm.allreduce(x, op=_mpi().MIN)

    def allsum(self, x):
        return self.comm.allreduce(x, op=_mpi().SUM)

    def flags(self, a, b):
        """Element-wise max over ranks of two numbers (one message per step)."""
        buf = np.array([a, b], float)
        out = np.empty(2)
        self.comm.Allreduce(buf, out, op=_mpi().MAX)
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
        """Every rank holds every particle of the scene at start-up: cut the boxes on a
        disjoint split (row % size) and keep the owned rows (possibly none)."""
        st = world.state
        x = st.position
        part = np.arange(self.rank, st.n, self.size)
        halo = world.halo()
        self.dec.build(self.comm, x[part], np.ones(part.size), halo)
        own = np.nonzero(self.dec.owner(x) == self.rank)[0]
        self._take(st, own)
        st.n_owned = own.size
        st.n_ghost = 0
        self.neigh = self.dec.neighbours(self.rank, halo)

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
        costs = self.comm.allgather((cost, err))
        _raise_shared([e for _, e in costs])
        self._rebalance(world, np.array([c for c, _ in costs]), weights, halo)
        rec = self._migrate(world, rec)
        self._send_ghosts(world, halo)
        self.exchanges += 1
        self._bufs = {}
        return rec

    def _rebalance(self, world, costs, weights, halo):
        """Re-cut the boxes (collective) when the largest rank cost exceeds the mean by more
        than [parallel] balance_threshold. Every cut is legal (decomposition.py), so the new
        cuts are always taken."""
        cmean = float(costs.sum()) / self.size
        self.imbalance = float(costs.max()) / max(cmean, 1e-300)
        if self.imbalance <= self.cfg["balance_threshold"]:
            return
        before = [list(n) for n in self.dec.nodes]
        self.dec.build(self.comm, world.state.position, weights, halo)
        if self.dec.nodes != before:
            self.rebalances += 1
        self.neigh = self.dec.neighbours(self.rank, halo)

    def _migrate(self, world, rec):
        """Send the particles that left this rank's box to their owners, with their contact
        records; take in the particles that arrive."""
        st = world.state
        out = [None] * self.size
        leave = np.zeros(0, bool)
        try:
            dest = self.dec.owner(st.position)
            leave = dest != self.rank
            for q in np.unique(dest[leave]):
                rows = np.nonzero(dest == q)[0]
                pkg = {name: a[rows] for name, a in self._moving(st)}
                pkg["__records"] = R.involving(rec, st.id[rows]) if rec is not None else None
                out[q] = pkg
        except Exception as exc:  # noqa: BLE001
            out = [{"__error": self._error_text(world, exc, "packing the migrating particles")}] * self.size
        inc = self.comm.alltoall(out)
        _raise_shared([p.get("__error") if p is not None else None for p in inc])
        inc = [p for p in inc if p is not None]
        keep = np.nonzero(~leave)[0]
        self.migrated += int(leave.sum())
        for name, a in list(self._moving(st)):
            parts = [a[keep]] + [p[name] for p in inc]
            setattr(st, name, np.ascontiguousarray(np.concatenate(parts)))
        if rec is not None:
            rec = R.concat([rec] + [p["__records"] for p in inc])
        st.n_owned = st.id.shape[0]
        if self.sort_pending:  # spatial sort of the owned rows (cache locality)
            from ..neighbors import sort_permutation
            self._take(st, sort_permutation(st.position, world.state.lo, world.state.hi, world.halo()))
            self.sort_pending = False
        return rec

    def _send_ghosts(self, world, halo):
        """Send every neighbour rank this rank's particles within one halo of its box
        (shifted by the periodic image nearest to it); append the ghosts received."""
        st = world.state
        nown = st.n_owned
        self.sends = []
        out = [None] * self.size
        try:
            ghost = {name: a for name, a in self._moving(st) if S.BY_NAME[name].ghost}
            for q in self.neigh:
                d, shift = self.dec.box_distance(st.position, q)
                rows = np.nonzero(d < halo)[0]
                sh = np.ascontiguousarray(shift[rows])
                self.sends.append((q, rows, sh))
                out[q] = {name: (a[rows] + sh if name == "position" else a[rows]) for name, a in ghost.items()}
        except Exception as exc:  # noqa: BLE001
            out = [{"__error": self._error_text(world, exc, "packing the ghosts")}] * self.size
        inc = self.comm.alltoall(out)
        _raise_shared([p.get("__error") if p is not None else None for p in inc])
        self.recvs = []
        off = nown
        got = []
        for q in self.neigh:
            pkg = inc[q]
            cnt = pkg["id"].shape[0]
            self.recvs.append((q, off, cnt))
            off += cnt
            got.append(pkg)
        for name, a in list(self._moving(st)):
            if S.BY_NAME[name].ghost:
                parts = [a] + [p[name] for p in got]
            else:
                parts = [a, np.zeros((off - nown,) + a.shape[1:], a.dtype)]
            setattr(st, name, np.ascontiguousarray(np.concatenate(parts)))
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
        from mpi4py import MPI
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
        messages per step, exchanges, migrations, re-balancings, current imbalance."""
        st = world.state
        loc = np.array([st.n_ghost, self.halo_bytes(world.thermal is not None), len(self.sends),
                        self.migrated], float)
        tot = self.allsum(loc)
        own = np.array(self.comm.allgather(st.n_owned), float)
        return dict(ghosts=int(tot[0]), halo_bytes=float(tot[1]), messages=int(tot[2]),
                    migrated=int(tot[3]), exchanges=self.exchanges, rebalances=self.rebalances,
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
