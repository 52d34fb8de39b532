"""Set-up of a coupled run whose gas is decomposed (``gas_processes > 1``, many-to-many
transport) without the whole gas mesh on any DEM rank.

Rank 0 decomposes the meshed case first (OpenFOAM's decomposePar, on the fields of the
case's 0/ folder: 0/eps is still the template's); then, collectively:

* :class:`PieceTable`: each rank reads the processor meshes k = rank, rank + M, ... (one at a
  time) and tells, per piece, its box, its cell count, its largest cell diagonal, its largest
  |U| of 0/U and how many of its cells each DEM rank owns (the box at start-up holding the
  centre: dem.parallel.decomposition); one Allreduce of a float64 table (pieces x (9 + M)).
* :meth:`PieceTable.local_mesh`: each rank reads the pieces overlapping its box plus its view
  (the particle halo plus the stencil's reach, coupling.cells) and the pieces holding cells it
  owns (coupling.mesh.MeshPieces): every cell is then read by its owner, so every cell has
  exactly one owner. The whole mesh's location tolerance and uniform lattice (which a local
  mesh keeps, bit for bit) come from reductions over the owned cells.
* :func:`write_eps_pieces`: processor k's 0/eps is written by DEM rank k mod M from the owners'
  values (an Alltoallv of (piece, cell or face, value) triples): its cells and, on each
  processor patch, the value of the cell across the face, as decomposePar writes them (bit
  for bit, tests/test_coupled_pieces.py).

No rank ever holds an array of all cells; what each rank read is in timings.json
(``setup_pieces_read``, ``setup_cells_read``, ``table_pieces_read``).
"""
from __future__ import annotations

import os
import re
from pathlib import Path

import numpy as np

from .mesh import MeshPieces, UniformGrid
from .polymesh_files import read_boundary, read_foam_list

_BOX, _N, _DIAG, _UMAX = slice(0, 6), 6, 7, 8
_OWN = 9


def _run_error(rank: int, e: Exception):
    """A file this rank could not read or write (missing, unparsable, a gap in the cells) as
    one line naming the rank and the file (CouplingRunError: exit 2)."""
    from .errors import CouplingRunError
    if isinstance(e, CouplingRunError):
        return e
    name = getattr(e, "filename", None)
    return CouplingRunError(f"DEM rank {rank}: {name + ': ' if name else ''}{e} (the set-up reads the gas "
                            "processor folders decomposePar wrote in --out; if one is damaged, run the "
                            "case again with --overwrite)")


def agree(comm, rank: int, err) -> None:
    """Before a collective: every rank learns whether one failed (one Allreduce of a number);
    then every rank raises the failure of the lowest failing rank (its message gathered on
    this failure path only), so no rank waits in a collective the others left."""
    from mpi4py import MPI
    mine = np.array([0.0 if err is None else 1.0])
    anyf = np.empty(1)
    comm.Allreduce(mine, anyf, op=MPI.MAX)
    if anyf[0] == 0.0:
        return
    msgs = comm.allgather(None if err is None else str(_run_error(rank, err)))
    from .errors import CouplingRunError
    raise CouplingRunError(next(m for m in msgs if m is not None))


def on_rank(rank: int, fn, *a, **kw):
    """fn(*a, **kw), its failure as one line naming this DEM rank and the file (the caller,
    coupling.transport.Ranks.everywhere, raises the first failure on every rank)."""
    from dem.output import DISK_ERRNOS, OutputError
    try:
        return fn(*a, **kw)
    except OSError as e:
        if e.errno in DISK_ERRNOS:   # disk full, quota, read-only: an output failure (exit 4)
            raise OutputError(e.filename or "(unnamed file)", e) from None
        raise _run_error(rank, e) from None
    except (ValueError, RuntimeError, IndexError, KeyError) as e:
        raise _run_error(rank, e) from None


def decompose_first(out: Path, n: int) -> None:
    """Rank 0: decompose the meshed case before any DEM rank reads the mesh (fresh start)."""
    from dem import outdir
    from . import foam_case as fc
    for name in ["log.decomposePar"] + [f"processor{i}" for i in range(n)]:
        outdir.claim(out / name)
    fc.set_entries(out / "system" / "controlDict", {"writePrecision": 17})   # as prepare_gas
    fc.decompose(out, n)


def pieced(out: Path, cfg, restart: bool, m2m: bool) -> bool:
    """The set-up by pieces: decomposed gas, many-to-many transport, and on a restart a
    decomposition of this run's gas_processes already in --out (else the whole-mesh set-up,
    which moves the gas to the new layout)."""
    if cfg.gas_processes <= 1 or not m2m:
        return False
    return not restart or len(MeshPieces.procs(str(out))) == cfg.gas_processes


class PieceTable:
    """What every DEM rank knows of every gas processor's piece (collective)."""

    def __init__(self, out: Path, comm, dec0, rank: int, size: int):
        from mpi4py import MPI
        from .case import _max_speed_of_field
        self.out, self.comm, self.rank, self.size = Path(out), comm, rank, size
        self.procs = MeshPieces.procs(str(out))
        P = len(self.procs)
        tab = np.zeros((P, _OWN + size))
        reader = MeshPieces(out, 0)
        self.table_read = []
        err = None
        try:
            self._rows(tab, reader, rank, size, P, dec0, _max_speed_of_field)
        except Exception as e:  # noqa: BLE001  (agreed with every rank before the Allreduce)
            err = e
        agree(comm, rank, err)
        self.tab = np.empty_like(tab)
        comm.Allreduce(tab, self.tab, op=MPI.SUM)
        self.n_global = int(self.tab[:, _N].sum())
        self.boxes = [(self.tab[k, 0:3].copy(), self.tab[k, 3:6].copy()) for k in range(P)]
        self.cell_diag = float(self.tab[:, _DIAG].max(initial=0.0))
        self.umax = float(self.tab[:, _UMAX].max(initial=0.0))

    def _rows(self, tab, reader, rank, size, P, dec0, _max_speed_of_field):
        """This rank's rows of the table: pieces rank, rank + size, ..."""
        for k in range(rank, P, size):
            m = reader.read_pieces([k])
            nreal = m.global_ids.size
            self.table_read.append(k)
            tab[k, 0:3] = m.points.min(axis=0)
            tab[k, 3:6] = m.points.max(axis=0)
            tab[k, _N] = nreal
            h = np.sqrt(((m.cell_vhi[:nreal] - m.cell_vlo[:nreal]) ** 2).sum(axis=1))
            tab[k, _DIAG] = h.max(initial=0.0)
            u = Path(self.procs[k]).parent.parent / "0" / "U"
            tab[k, _UMAX] = _max_speed_of_field(u, nreal) if u.exists() else 0.0
            tab[k, _OWN:] = np.bincount(dec0.owner(m.cell_centres[:nreal]), minlength=size)
            del m

    def owned_by(self, rank):
        """The pieces holding cells that ``rank`` owns."""
        return np.flatnonzero(self.tab[:, _OWN + rank] > 0).tolist()

    def pieces(self, grid=None, tol=0.0) -> MeshPieces:
        """A reader of the pieces with this table's boxes (nobody reads every points file)."""
        mp = MeshPieces(self.out, self.n_global, grid, tol)
        mp._pieces, mp._boxes = list(self.procs), list(self.boxes)
        return mp

    def local_mesh(self, box, reach: float, dec0):
        """The mesh of the pieces overlapping ``box`` (lo, hi) grown by ``reach`` and of the
        pieces with cells this rank owns, with the whole mesh's tolerance and lattice."""
        lo, hi = box
        which = {k for k, (blo, bhi) in enumerate(self.boxes)
                 if np.all(blo <= hi + reach) and np.all(bhi >= lo - reach)}
        which |= set(self.owned_by(self.rank))
        m, err = None, None
        try:
            m = self.pieces().read_pieces(sorted(which))
        except Exception as e:  # noqa: BLE001  (agreed before the reductions)
            err = e
        agree(self.comm, self.rank, err)
        nreal = m.global_ids.size
        own = dec0.owner(m.cell_centres[:nreal]) == self.rank
        self.grid, self.tol = _whole_mesh_lattice(self, m, nreal, own)
        m.tol = self.tol
        m._uniform = self.grid
        m.n_global = self.n_global
        self.setup_read = dict(pieces=list(m.pieces), cells=int(nreal))
        return m

    # reductions of O(1) over the ranks (float64 buffers)
    def _red(self, x, op):
        a = np.atleast_1d(np.asarray(x, np.float64))
        b = np.empty_like(a)
        self.comm.Allreduce(np.ascontiguousarray(a), b, op=op)
        return b


def _whole_mesh_lattice(t: PieceTable, m, nreal, own):
    """(UniformGrid or None, tolerance) of the whole mesh (coupling.mesh.PolyMesh: bbox,
    tol = 1e-12 L, _detect_uniform) from each rank's owned cells: the same numbers."""
    from mpi4py import MPI
    vlo, vhi = m.cell_vlo[:nreal][own], m.cell_vhi[:nreal][own]
    vol = m.cell_volumes[:nreal][own]
    lo = t._red(vlo.min(axis=0, initial=np.inf), MPI.MIN)
    hi = t._red(vhi.max(axis=0, initial=-np.inf), MPI.MAX)
    tol = 1e-12 * float(np.max(hi - lo))
    ext = vhi - vlo
    gids = m.global_ids[own]
    first = np.flatnonzero(gids == 0)
    h = t._red(ext[first[0]] if first.size else np.zeros(3), MPI.SUM)   # the extent of cell 0
    if np.any(h <= 0):
        return None, tol
    ok = bool(np.allclose(ext, h[None, :], rtol=1e-9, atol=0)
              and np.allclose(vol, np.prod(ext, axis=1), rtol=1e-8, atol=0))
    origin = lo
    tt = (vlo - origin) / h
    idx = np.rint(tt).astype(np.int64)
    ok = ok and (not idx.size or np.max(np.abs(tt - idx)) <= 1e-6)
    dims = t._red(idx.max(axis=0, initial=-1) + 1, MPI.MAX).astype(np.int64)
    ok = bool(t._red(1.0 if ok else 0.0, MPI.MIN)[0] > 0)
    # a valid mesh's cells do not overlap: n_global lattice boxes of the lattice's count cover it
    if not ok or int(np.prod(dims)) != t.n_global:
        return None, tol
    hh = (hi - origin) / dims
    return UniformGrid(origin, hh, dims, np.zeros(0, np.int64)), tol


# --------------------------------------------------------------------------- 0/eps per piece

def _foam_scalars(v: np.ndarray) -> str:
    """A scalar Field entry as OpenFOAM writes it (Field::writeEntry, precision 17)."""
    if v.size and np.all(v == v[0]):
        return "uniform " + "%.17g" % v[0]
    if v.size == 0:
        return "nonuniform 0()"
    body = [("%.17g" % x) for x in v.tolist()]
    if v.size <= 10:
        return f"nonuniform List<scalar> {v.size}(" + " ".join(body) + ")"
    return f"nonuniform List<scalar> \n{v.size}\n(\n" + "\n".join(body) + "\n)\n"


def _replace_value(text: str, start: int, value: str) -> str:
    """Replace the entry's value that begins at ``start`` (up to its ';')."""
    end = text.index(")", start) if text.startswith("nonuniform", start) else start
    end = text.index(";", end)
    return text[:start] + value + text[end:]


def _piece_files(proc_mesh_dir):
    d = proc_mesh_dir
    return (read_foam_list(os.path.join(d, "cellProcAddressing")), read_foam_list(os.path.join(d, "owner")),
            read_foam_list(os.path.join(d, "faceProcAddressing")), read_boundary(os.path.join(d, "boundary")))


def write_eps_pieces(table: PieceTable, cells, eps: np.ndarray, time: str = "0") -> list:
    """Write processor k's <time>/eps for every k from the owners' values (collective; ``cells``:
    coupling.cells.CellShare, ``eps``: of its local mesh). Returns the pieces this rank wrote."""
    from mpi4py import MPI
    comm, size, rank = table.comm, table.size, table.rank
    eps = np.asarray(eps, np.float64)
    send = [[] for _ in range(size)]
    err = None
    try:
        _eps_messages(table, cells, eps, send)
    except Exception as e:  # noqa: BLE001  (agreed before the Alltoall)
        err = e
    agree(comm, rank, err)
    bufs = [np.concatenate(s).ravel() if s else np.zeros(0) for s in send]
    counts = np.array([b.size for b in bufs], np.int64)
    rcounts = np.empty(size, np.int64)
    comm.Alltoall(counts, rcounts)
    sbuf = np.concatenate(bufs) if bufs else np.zeros(0)
    rbuf = np.empty(int(rcounts.sum()))
    sdis = np.r_[0, np.cumsum(counts)[:-1]]
    rdis = np.r_[0, np.cumsum(rcounts)[:-1]]
    comm.Alltoallv([sbuf, counts, sdis, MPI.DOUBLE], [rbuf, rcounts, rdis, MPI.DOUBLE])
    got = rbuf.reshape(-1, 3)
    wrote = []
    for k in range(rank, len(table.procs), size):
        mine = got[got[:, 0] == k]
        _write_piece(table.procs[k], mine[:, 1], mine[:, 2], time)
        wrote.append(k)
    return wrote


def _eps_messages(table, cells, eps, send):
    """This rank's (piece, key, value) triples for the writer of each piece."""
    size, rank = table.size, table.rank
    for j in table.owned_by(rank):           # the pieces holding cells this rank owns
        cpa, own, fpa, bnd = _piece_files(table.procs[j])
        loc = cells.local(cpa)
        mine = loc >= 0
        mine[mine] = cells.owned_mask[loc[mine]]
        send[j % size].append(np.column_stack([np.full(mine.sum(), j, float), cpa[mine].astype(float),
                                               eps[loc[mine]]]))
        for p in bnd:
            if p.get("type") != "processor":
                continue
            k = int(p["neighbProcNo"])
            f = np.arange(int(p["startFace"]), int(p["startFace"]) + int(p["nFaces"]))
            c = own[f]                        # this piece's cell on the face
            ok = mine[c]
            gface = np.abs(fpa[f[ok]]) - 1
            send[k % size].append(np.column_stack([np.full(ok.sum(), k, float), -1.0 - gface.astype(float),
                                                   eps[loc[c[ok]]]]))


def _write_piece(proc_mesh_dir, keys, vals, time):
    """processor k's <time>/eps: its cells' values (key: global cell) and each processor
    patch face's value (key: -1 - global face), into the file decomposePar wrote from the
    template."""
    cpa, own, fpa, bnd = _piece_files(proc_mesh_dir)
    f = Path(proc_mesh_dir).parent.parent / time / "eps"
    cell = keys >= 0
    ck, cv = keys[cell].astype(np.int64), vals[cell]
    fk, fv = (-1 - keys[~cell]).astype(np.int64), vals[~cell]

    def pick(ids, k, v, what):
        o = np.argsort(k, kind="stable")
        k, v = k[o], v[o]
        i = np.minimum(np.searchsorted(k, ids), max(k.size - 1, 0))
        if not k.size or np.any(k[i] != ids):
            raise RuntimeError(f"{f}: no owner sent the value of {int(np.sum(k[i] != ids)) if k.size else ids.size} "
                               f"{what} (a gap in the ownership of the gas cells)")
        return v[i]
    text = f.read_text()
    m = re.search(r"^internalField\s+", text, re.M)
    text = _replace_value(text, m.end(), _foam_scalars(pick(cpa, ck, cv, "cells")))
    for p in bnd:
        if p.get("type") != "processor":
            continue
        fs = np.arange(int(p["startFace"]), int(p["startFace"]) + int(p["nFaces"]))
        v = pick(np.abs(fpa[fs]) - 1, fk, fv, f"faces of {p['name']}")
        mp = re.search(r"^\s+" + re.escape(p["name"]) + r"\s*\{[^}]*?value\s+", text, re.M)
        if mp is None:
            raise RuntimeError(f"{f}: no value entry of patch {p['name']}")
        text = _replace_value(text, mp.end(), _foam_scalars(v))
    tmp = f.with_name(".eps.tmp")
    tmp.write_text(text)
    os.replace(tmp, f)
