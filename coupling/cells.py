"""The gas cells shared out between the DEM ranks of a coupled run (many-to-many coupling).

Each gas cell has one *owner*: the DEM rank whose box holds the cell's centre when the run
starts (dem.parallel.decomposition, fixed for the whole run, also when the DEM boxes are
re-cut later). The owner alone exchanges the cell with the gas processor that holds it
(coupling.m2m): it sends the cell's summed exchange terms and receives its gas fields.

Each rank also *sees* the cells its particles' stencils can reach: the cells whose centre
lies within the particle halo (dem.world.World.halo: the farthest an owned particle's surface
can be from its box between two neighbour rebuilds, with margin) plus two cell diagonals of
its box. A stencil reaches the particle's cell and the cells its volume overlaps (divided,
centre) or the cells sharing a point with its cell (smoothed): centres within 1.5 diagonals;
the gradient and the interpolations read the face neighbours of the particle's cell, within
the same distance. :meth:`CellShare.check_stencil` refuses a stencil that reaches farther
(never seen; it would lose that cell's sum). The cells a rank sees but does not own are
its *halo cells*; the pattern (which cells each pair of neighbouring ranks shares) is built
once, collectively, and again only when the DEM boxes are re-cut.

Per coupling step two exchanges replace what used to be an Allreduce over every cell:

* :meth:`CellShare.assemble`: the per-cell sums of the particles (solid volume, drag, heat)
  go from every rank that sees a cell to its owner, the owner adds them in rank order and
  sends the totals back; every rank then holds the same totals on every cell it sees;
* :meth:`CellShare.update`: the owner's values (the relaxed void fraction, the gas fields)
  go to the ranks that see the cell.

Messages go only between ranks that share cells, as raw float64 buffers (no pickling);
their size is the number of shared cells, which grows with a rank's surface, not with the
mesh. ``bytes_sent`` counts them. Per-cell arrays are still indexed by global cell number on
every rank (the mesh is read whole on every DEM rank at set-up: docs/scaling.md); only the
entries of the cells a rank sees are valid there.
"""
from __future__ import annotations

import numpy as np


class _Cells:
    """A mesh of n cells, for a serial CellShare."""

    def __init__(self, n):
        self.n_cells = n


# MPI's DOUBLE_INT pair (a value and the cell it belongs to) as a NumPy record
_VALUE_CELL = np.dtype([("v", "f8"), ("c", "i4")], align=True)


class CellShare:
    """Ownership and halo of the gas cells among the DEM ranks (serial: one rank owns every
    cell, nothing is sent)."""

    def __init__(self, mesh, par=None, *, halo: float = 0.0, reach_cells: float = 2.0):
        """``mesh``: the gas mesh (coupling.mesh.PolyMesh; serial: anything with ``n_cells``),
        ``par``: the DEM's ParallelDomain or None, ``halo``: the particle halo (m,
        dem.world.World.halo), ``reach_cells``: the stencil's reach in cell diagonals."""
        self.n_cells = int(mesh.n_cells)
        self.par = par
        self.bytes_sent = 0          # bytes this rank sent between DEM ranks (assemble, update)
        self.messages = 0
        if par is None:
            self.rank, self.size = 0, 1
            self.owner = np.zeros(self.n_cells, np.int32)
            self.owned = np.arange(self.n_cells, dtype=np.int64)
            self.owned_mask = np.ones(self.n_cells, bool)
            self.view_mask = self.owned_mask
            self.halo, self.serve = {}, {}
            return
        self.comm = par.comm
        self.rank, self.size = par.rank, par.size
        self.mesh = mesh
        self.owner = par.dec.owner(mesh.cell_centres).astype(np.int32)
        self.owned = np.flatnonzero(self.owner == self.rank).astype(np.int64)
        self.owned_mask = self.owner == self.rank
        h = np.sqrt(((mesh.cell_vhi - mesh.cell_vlo) ** 2).sum(axis=1))
        self.cell_reach = float(h.max(initial=0.0)) * float(reach_cells)
        self._planned = None
        self.plan(halo)

    @classmethod
    def serial(cls, n_cells: int):
        """One rank owning every one of ``n_cells`` cells (nothing is sent)."""
        return cls(_Cells(n_cells))

    # ------------------------------------------------------------------ the pattern
    def plan(self, halo):
        """Which cells this rank sees (within ``halo`` plus the stencil's reach of its box) and
        which ranks own them (collective; at start-up and after the DEM boxes were re-cut)."""
        par = self.par
        from mpi4py import MPI
        halo = float(halo)
        self.particle_halo = halo
        d, _ = par.dec.box_distance(self.mesh.cell_centres, self.rank)
        view = (d <= halo + self.cell_reach) | self.owned_mask
        need = np.flatnonzero(view & ~self.owned_mask)
        own = self.owner[need]
        counts = np.bincount(own, minlength=self.size).astype(np.int64)
        rcounts = np.empty(self.size, np.int64)
        self.comm.Alltoall(counts, rcounts)          # set-up only: one number per rank pair
        halo_ids = {int(q): need[own == q] for q in np.flatnonzero(counts)}
        serve = {int(q): np.empty(int(rcounts[q]), np.int64) for q in np.flatnonzero(rcounts)}
        reqs = [self.comm.Irecv([serve[q], MPI.INT64_T], source=q, tag=71) for q in serve]
        reqs += [self.comm.Isend([halo_ids[q], MPI.INT64_T], dest=q, tag=71) for q in halo_ids]
        MPI.Request.Waitall(reqs)
        bad = [q for q, ids in serve.items() if ids.size and not np.all(self.owned_mask[ids])]
        if bad:
            raise RuntimeError(f"DEM rank {self.rank}: ranks {bad} asked for cells it does not own")
        self.view_mask = view
        self.halo, self.serve = halo_ids, serve
        self._planned = par.rebalances

    def refresh(self, halo):
        """Re-plan when the DEM boxes were re-cut since the last plan (collective: every rank
        sees the same re-cut count)."""
        if self.par is not None and (self._planned != self.par.rebalances or halo > self.particle_halo):
            self.plan(halo)

    def check_stencil(self, cells):
        """Every cell a stencil touches must be one this rank sees (else its sum would be lost)."""
        if self.par is None:
            return
        c = cells[cells >= 0]
        if c.size and not np.all(self.view_mask[c]):
            bad = int(c[~self.view_mask[c]][0])
            raise RuntimeError(
                f"DEM rank {self.rank}: a particle's stencil reaches gas cell {bad} at "
                f"{np.array2string(self.mesh.cell_centres[bad], precision=6)}, beyond the cells this rank "
                f"sees ({self.cell_reach:g} m around its box plus the particle halo {self.particle_halo:g} m)")

    @property
    def halo_cells(self) -> int:
        """Cells this rank sees and other ranks own (it receives their totals)."""
        return int(sum(ids.size for ids in self.halo.values()))

    @property
    def served_cells(self) -> int:
        """Owned cells other ranks see, counted once per such rank (it sends them the totals)."""
        return int(sum(ids.size for ids in self.serve.values()))

    # ------------------------------------------------------------------ per step
    @staticmethod
    def _cols(a):
        return 1 if a.ndim == 1 else int(np.prod(a.shape[1:]))

    def _round(self, arrays, send_ids, recv_ids, tag, combine):
        """One round: a[send_ids[q]] of every array to q; what q sends for recv_ids[q] is
        added (combine=True, in rank order) or copied into a[recv_ids[q]]."""
        from mpi4py import MPI
        ncol = sum(self._cols(a) for a in arrays)
        rbufs = {q: np.empty(ids.size * ncol) for q, ids in recv_ids.items()}
        reqs = [self.comm.Irecv([rbufs[q], MPI.DOUBLE], source=q, tag=tag) for q in sorted(rbufs)]
        sbufs = []
        for q in sorted(send_ids):
            ids = send_ids[q]
            buf = np.concatenate([a[ids].reshape(ids.size, -1) for a in arrays], axis=1).ravel() \
                if ids.size else np.empty(0)
            sbufs.append(buf)
            reqs.append(self.comm.Isend([buf, MPI.DOUBLE], dest=q, tag=tag))
            self.bytes_sent += buf.nbytes
            self.messages += 1
        MPI.Request.Waitall(reqs)
        for q in sorted(rbufs):
            ids = recv_ids[q]
            if not ids.size:
                continue
            blk = rbufs[q].reshape(ids.size, ncol)
            j = 0
            for a in arrays:
                k = self._cols(a)
                part = blk[:, j:j + k].reshape((ids.size,) + a.shape[1:])
                if combine:
                    a[ids] += part
                else:
                    a[ids] = part
                j += k

    def assemble(self, *arrays):
        """Sum per-cell partial sums (arrays indexed by global cell, modified in place) over the
        ranks that see each cell: every rank ends with the owner's total on every cell it sees.
        The owner adds the partials in rank order, so the totals are the same on every rank."""
        if self.par is None or self.size == 1:
            return arrays
        arrays = [np.ascontiguousarray(a) for a in arrays]
        # partials of the halo cells go to their owners; the owner adds them (rank order)
        self._round(arrays, self.halo, self.serve, 72, combine=True)
        # the owners' totals back to the ranks that see the cells
        self._round(arrays, self.serve, self.halo, 73, combine=False)
        return arrays

    def update(self, *arrays):
        """Copy the owners' values into the halo cells of every rank (arrays modified in place)."""
        if self.par is None or self.size == 1:
            return arrays
        self._round(list(arrays), self.serve, self.halo, 74, combine=False)
        return arrays

    # ------------------------------------------------------------------ reductions of O(1)
    def _reduce(self, x, op):
        """x (a number or a small array) reduced over the ranks as a float64 buffer."""
        if self.par is None:
            return x
        a = np.atleast_1d(np.asarray(x, dtype=np.float64))
        out = np.empty_like(a)
        self.comm.Allreduce(np.ascontiguousarray(a), out, op=op)
        return out if np.ndim(x) else float(out[0])

    def allsum(self, x):
        from mpi4py import MPI
        return self._reduce(x, MPI.SUM) if self.par is not None else x

    def allmax(self, x):
        from mpi4py import MPI
        return self._reduce(x, MPI.MAX) if self.par is not None else x

    def allmin(self, x):
        from mpi4py import MPI
        return self._reduce(x, MPI.MIN) if self.par is not None else x

    def _loc(self, value, cell, op):
        from mpi4py import MPI
        a = np.zeros(1, _VALUE_CELL)
        a["v"], a["c"] = float(value), int(cell)
        b = np.zeros(1, _VALUE_CELL)
        self.comm.Allreduce([a, MPI.DOUBLE_INT], [b, MPI.DOUBLE_INT], op=op)
        return float(b["v"][0]), int(b["c"][0])

    def argmax(self, value, cell):
        """(largest value, its cell) over the ranks (MAXLOC of one double-int pair)."""
        if self.par is None:
            return value, cell
        from mpi4py import MPI
        return self._loc(value, cell, MPI.MAXLOC)

    def argmin(self, value, cell):
        """(smallest value, its cell) over the ranks (MINLOC)."""
        if self.par is None:
            return value, cell
        from mpi4py import MPI
        return self._loc(value, cell, MPI.MINLOC)

    def best(self, key, record, largest=True):
        """(key, record) of the rank whose ``key`` is the largest (``largest=False``: the
        smallest), ties to the lowest rank: one Allgather of a float64 vector per rank. A rank
        with nothing to offer passes key = -inf (+inf) and a record of the same length. For the
        worst particle of a check (its value and what its message names)."""
        rec = np.asarray(record, dtype=np.float64).ravel()
        if self.par is None:
            return float(key), rec
        buf = np.concatenate([[float(key)], rec])
        every = np.empty((self.size, buf.size))
        self.comm.Allgather(buf, every)
        k = int(np.argmax(every[:, 0]) if largest else np.argmin(every[:, 0]))
        return float(every[k, 0]), every[k, 1:].copy()

    def gather_owned(self, a, root=0):
        """The whole per-cell array on ``root`` from each rank's owned cells (restart points
        only; None elsewhere)."""
        a = np.asarray(a)
        if self.par is None:
            return a
        parts = self.comm.gather((self.owned, np.ascontiguousarray(a[self.owned])), root=root)
        if self.rank != root:
            return None
        out = np.zeros((self.n_cells,) + a.shape[1:], a.dtype)
        for ids, vals in parts:
            out[ids] = vals
        return out
