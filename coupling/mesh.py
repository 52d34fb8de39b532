"""OpenFOAM polyMesh geometry and point location: ``PolyMesh``, built by ``read_polymesh`` from
the ASCII files that coupling.polymesh_files reads (and writes; re-exported here).

Everything here works on arbitrary polyhedral meshes given as OpenFOAM's
face-based description:

* ``points``     (nPoints, 3) float
* ``faces``      list of point-index loops (stored as CSR ``face_offsets`` /
  ``face_points``); the right-hand-rule normal of a face points from its owner
  to its neighbour (outwards for boundary faces)
* ``owner``      (nFaces,)  cell on the normal's tail side
* ``neighbour``  (nInternalFaces,) cell on the normal's head side; internal
  faces come first, boundary faces afterwards, grouped by patch.

Geometry follows OpenFOAM's ``primitiveMesh`` decomposition:

* face centre / area vector: triangle fan around the face's point average;
  the area vector is half the sum of the triangle cross products, the centre
  is the triangle-centroid average weighted by each triangle's area projected
  on the face normal (as ``primitiveMeshFaceCentresAndAreas`` does);
* cell centre / volume: pyramids from an estimated centre (average of the
  face centres) to every face; volume = sum of pyramid volumes, centre =
  volume-weighted pyramid centroids (3/4 face centre + 1/4 apex).

Point location (``PolyMesh.locate``) uses the face-plane inside test: x is in
cell c when, for every face f of c, ``(x - C_f) . n_f <= tol`` with ``n_f`` the
outward unit normal of f seen from c (``+S_f`` for the owner, ``-S_f`` for the
neighbour).  The search is

1. the hint cell (previous cell of the particle): one inside test;
2. a face-to-face walk from the hint towards the point, always crossing the
   face whose plane the point violates most;
3. if there is no hint or the walk hits a boundary / does not converge: a
   uniform bucket grid over the domain's bounding box, each bucket listing the
   cells whose bounding box overlaps it; the candidates in the point's bucket
   are inside-tested (nearest centre first is unnecessary: the test is exact),
   so the result does not depend on the walk succeeding (non-convex domains).

For a uniform axis-aligned grid (blockMesh with one block or several blocks of
the same spacing) ``PolyMesh.uniform_grid`` detects the lattice and
``locate`` uses a direct index computation.

Binary polyMesh files are not supported (clear error): convert them with
``foamFormatConvert`` after setting ``writeFormat ascii`` in controlDict.
"""
from __future__ import annotations

import os
import time
from collections import namedtuple
from dataclasses import dataclass

import numpy as np
from numba import njit, prange

from .polymesh_files import read_boundary, read_foam_list, structured_hex_mesh, write_polymesh

__all__ = [
    "PolyMesh",
    "read_polymesh",
    "read_foam_list",
    "read_boundary",
    "write_polymesh",
    "structured_hex_mesh",
    "UniformGrid",
    "locate",
    "benchmark_locate",
]


# --------------------------------------------------------------------------
# Reader (the files: coupling.polymesh_files)
# --------------------------------------------------------------------------
class MeshPieces:
    """The gas mesh of a decomposed case read by pieces: the processor meshes
    (``processor<g>/constant/polyMesh`` with their cell, face and point addressing, written by
    decomposePar) whose box overlaps a region. ``grid`` and ``tol``: the whole mesh's uniform
    lattice (or None) and location tolerance, kept by the caller from set-up so that a local
    mesh cut from the pieces locates exactly as one cut from the whole mesh."""

    def __init__(self, case_dir, n_cells: int, grid=None, tol: float = 0.0):
        self.case = str(case_dir)
        self.n_global = int(n_cells)
        self.grid, self.tol = grid, float(tol)
        self._boxes = None
        self._pieces = None
        self.last_read = []

    @staticmethod
    def procs(case_dir) -> list:
        """The processor folders of a decomposed case (sorted by number), or [] when the mesh
        is not decomposed (no cellProcAddressing)."""
        ps = sorted((p for p in os.listdir(case_dir) if p.startswith("processor") and p[9:].isdigit()),
                    key=lambda p: int(p[9:]))
        ok = all(os.path.exists(os.path.join(case_dir, p, "constant", "polyMesh", "cellProcAddressing"))
                 for p in ps)
        return [os.path.join(case_dir, p, "constant", "polyMesh") for p in ps] if ps and ok else []

    def boxes(self):
        """Each piece's box (its points' bounds), read once (the points files only)."""
        if self._boxes is None:
            self._pieces = self.procs(self.case)
            b = []
            for d in self._pieces:
                x = read_foam_list(os.path.join(d, "points"))
                b.append((x.min(axis=0), x.max(axis=0)) if len(x) else (np.full(3, np.inf), np.full(3, -np.inf)))
            self._boxes = b
        return self._boxes

    def read(self, regions) -> "PolyMesh":
        """The mesh of the pieces whose box overlaps one of ``regions`` [(lo, hi)]: cells and
        faces in the whole mesh's numbering and orientation, in its order (so every cell's
        geometry is the whole mesh's, bit for bit), a phantom last cell on the far side of the
        faces to pieces not read; ``global_ids`` gives each real cell's global id. Meant for
        :meth:`PolyMesh.subset` (the phantom is never one of the cells kept)."""
        boxes = self.boxes()
        which = [k for k, (blo, bhi) in enumerate(boxes)
                 if any(np.all(blo <= hi) and np.all(bhi >= lo) for lo, hi in regions)]
        return self.read_pieces(which)

    def read_pieces(self, which) -> "PolyMesh":
        """The mesh of the pieces ``which`` (processor numbers, sorted), as :meth:`read`."""
        if self._pieces is None:
            self._pieces = self.procs(self.case)
        which = sorted(int(k) for k in which)
        self.last_read = [os.path.basename(os.path.dirname(os.path.dirname(self._pieces[k]))) for k in which]
        gf, go, gn, gpatch, loops, lens, cells, pts, pids = [], [], [], [], [], [], [], [], []
        names = None
        for k in which:
            d = self._pieces[k]
            x = read_foam_list(os.path.join(d, "points"))
            off, fp = read_foam_list(os.path.join(d, "faces"))
            own = read_foam_list(os.path.join(d, "owner"))
            nb = read_foam_list(os.path.join(d, "neighbour"))
            bnd = read_boundary(os.path.join(d, "boundary"))
            cpa = read_foam_list(os.path.join(d, "cellProcAddressing"))
            fpa = read_foam_list(os.path.join(d, "faceProcAddressing"))
            ppa = read_foam_list(os.path.join(d, "pointProcAddressing"))
            real = [p for p in bnd if p.get("type") != "processor"]
            if names is None:
                names = real
            nf, ni = len(own), len(nb)
            flip = fpa < 0
            # each face's point loop in global points and the whole mesh's orientation
            # (decomposePar turns a face with reverseFace: the first point stays)
            ln = np.diff(off)
            first = np.repeat(off[:-1], ln)
            kk = np.arange(off[-1]) - first
            fl = np.repeat(flip, ln)
            lnr = np.repeat(ln, ln)
            src = first + np.where(fl & (kk > 0), lnr - kk, kk)
            loops.append(ppa[fp[src]])
            lens.append(ln)
            co = cpa[own]
            cn = np.full(nf, -1, np.int64)
            cn[:ni] = cpa[nb]
            o = np.where(flip, cn, co)
            n_ = np.where(flip, co, cn)
            pat = np.full(nf, -1, np.int64)
            for j, p in enumerate(real):
                f0 = int(p["startFace"])
                pat[f0:f0 + int(p["nFaces"])] = j
            # a processor face: the local cell is the global owner (kept turn) or neighbour (turned)
            gf.append(np.abs(fpa) - 1)
            go.append(o)
            gn.append(n_)
            gpatch.append(pat)
            cells.append(cpa)
            pts.append(x)
            pids.append(ppa)
        gf = np.concatenate(gf)
        go, gn, gpatch = np.concatenate(go), np.concatenate(gn), np.concatenate(gpatch)
        lens = np.concatenate(lens)
        loops = np.concatenate(loops)
        rec_off = np.zeros(lens.size + 1, np.int64)
        np.cumsum(lens, out=rec_off[1:])
        order = np.argsort(gf, kind="stable")
        uf, first_rec = np.unique(gf[order], return_index=True)
        nrec = np.diff(np.r_[first_rec, order.size])
        rec = order[first_rec]
        o = np.maximum.reduceat(go[order], first_rec)
        nb_ = np.maximum.reduceat(gn[order], first_rec)
        pat = gpatch[rec]
        del nrec
        gcell = np.unique(np.concatenate(cells))
        gpt_all = np.concatenate(pids)
        xp_all = np.concatenate(pts)
        gpt, ip = np.unique(gpt_all, return_index=True)
        xp = xp_all[ip]
        n = gcell.size
        internal = pat < 0
        n_int = int(internal.sum())
        if not np.all(internal[:n_int]):
            raise ValueError(f"{self.case}: the pieces' faces are not ordered internal first")
        lo_ = np.where(o >= 0, np.searchsorted(gcell, np.maximum(o, 0)), n)
        ln_ = np.where(nb_ >= 0, np.searchsorted(gcell, np.maximum(nb_, 0)), n)
        rl = lens[rec]
        foff = np.zeros(rec.size + 1, np.int64)
        np.cumsum(rl, out=foff[1:])
        idx = np.repeat(rec_off[rec] - foff[:-1], rl) + np.arange(foff[-1])
        fpts = np.searchsorted(gpt, loops[idx]).astype(np.int64)
        boundary, start = [], n_int
        for j, p in enumerate(names):
            cnt = int(np.sum(pat == j))
            boundary.append(dict(p, startFace=start, nFaces=cnt))
            start += cnt
        phantom = bool(np.any(lo_[:n_int] == n) or np.any(ln_[:n_int] == n))
        m = PolyMesh(xp, foff, fpts, lo_, ln_[:n_int], boundary, phantom=phantom)
        m.global_ids = gcell
        m.pieces = list(self.last_read)
        m.n_global = self.n_global
        m.tol = self.tol
        m._uniform = None if self.grid is None else UniformGrid(self.grid.origin, self.grid.h, self.grid.dims,
                                                                np.zeros(0, np.int64))
        return m


def read_polymesh(case_or_dir: str) -> "PolyMesh":
    """Read an ASCII polyMesh from a case directory, its ``constant`` dir or
    the ``polyMesh`` directory itself."""
    d = case_or_dir
    for cand in (os.path.join(d, "constant", "polyMesh"), os.path.join(d, "polyMesh"), d):
        if os.path.exists(os.path.join(cand, "owner")) or \
                os.path.exists(os.path.join(cand, "owner.gz")):
            d = cand
            break
    else:
        raise FileNotFoundError(f"no polyMesh (owner file) found under {case_or_dir}")
    points = read_foam_list(os.path.join(d, "points"))
    face_offsets, face_points = read_foam_list(os.path.join(d, "faces"))
    owner = read_foam_list(os.path.join(d, "owner"))
    neighbour = read_foam_list(os.path.join(d, "neighbour"))
    bpath = os.path.join(d, "boundary")
    boundary = read_boundary(bpath) if (os.path.exists(bpath) or os.path.exists(bpath + ".gz")) else []
    return PolyMesh(points, face_offsets, face_points, owner, neighbour, boundary)


@njit(cache=True, error_model="numpy")
def _face_geometry(points, face_offsets, face_points):
    nf = face_offsets.shape[0] - 1
    fc = np.zeros((nf, 3))
    fa = np.zeros((nf, 3))
    for f in range(nf):
        s = face_offsets[f]
        n = face_offsets[f + 1] - s
        if n == 3:
            a = points[face_points[s]]
            b = points[face_points[s + 1]]
            c = points[face_points[s + 2]]
            for d in range(3):
                fc[f, d] = (a[d] + b[d] + c[d]) / 3.0
            e1 = b - a
            e2 = c - a
            fa[f, 0] = 0.5 * (e1[1] * e2[2] - e1[2] * e2[1])
            fa[f, 1] = 0.5 * (e1[2] * e2[0] - e1[0] * e2[2])
            fa[f, 2] = 0.5 * (e1[0] * e2[1] - e1[1] * e2[0])
            continue
        pavg = np.zeros(3)
        for j in range(n):
            pavg += points[face_points[s + j]]
        pavg /= n
        sumN = np.zeros(3)
        for j in range(n):
            p = points[face_points[s + j]]
            q = points[face_points[s + (j + 1) % n]]
            e1 = q - p
            e2 = pavg - p
            sumN[0] += e1[1] * e2[2] - e1[2] * e2[1]
            sumN[1] += e1[2] * e2[0] - e1[0] * e2[2]
            sumN[2] += e1[0] * e2[1] - e1[1] * e2[0]
        sumA = 0.0
        sumAc = np.zeros(3)
        for j in range(n):
            p = points[face_points[s + j]]
            q = points[face_points[s + (j + 1) % n]]
            e1 = q - p
            e2 = pavg - p
            nx = e1[1] * e2[2] - e1[2] * e2[1]
            ny = e1[2] * e2[0] - e1[0] * e2[2]
            nz = e1[0] * e2[1] - e1[1] * e2[0]
            a = nx * sumN[0] + ny * sumN[1] + nz * sumN[2]  # projected area (x |sumN|)
            sumA += a
            for d in range(3):
                sumAc[d] += a * (p[d] + q[d] + pavg[d])
        if sumA < 1e-300:
            fc[f] = pavg
        else:
            fc[f] = sumAc / (3.0 * sumA)
        fa[f] = 0.5 * sumN
    return fc, fa


@njit(cache=True, error_model="numpy")
def _cell_geometry(fc, fa, owner, neighbour, n_cells):
    n_int = neighbour.shape[0]
    nf = owner.shape[0]
    cest = np.zeros((n_cells, 3))
    nfc = np.zeros(n_cells)
    for f in range(nf):
        cest[owner[f]] += fc[f]
        nfc[owner[f]] += 1.0
    for f in range(n_int):
        cest[neighbour[f]] += fc[f]
        nfc[neighbour[f]] += 1.0
    for c in range(n_cells):
        cest[c] /= max(nfc[c], 1.0)
    cc = np.zeros((n_cells, 3))
    cv = np.zeros(n_cells)
    for f in range(nf):
        o = owner[f]
        v = 0.0
        for d in range(3):
            v += fa[f, d] * (fc[f, d] - cest[o, d])
        for d in range(3):
            cc[o, d] += v * (0.75 * fc[f, d] + 0.25 * cest[o, d])
        cv[o] += v
    for f in range(n_int):
        nb = neighbour[f]
        v = 0.0
        for d in range(3):
            v += fa[f, d] * (cest[nb, d] - fc[f, d])
        for d in range(3):
            cc[nb, d] += v * (0.75 * fc[f, d] + 0.25 * cest[nb, d])
        cv[nb] += v
    for c in range(n_cells):
        if abs(cv[c]) > 1e-300:
            cc[c] /= cv[c]
        else:
            cc[c] = cest[c]
        cv[c] /= 3.0
    return cc, cv


@njit(cache=True, error_model="numpy")
def _cell_bboxes(points, face_offsets, face_points, owner, neighbour, n_cells):
    lo = np.full((n_cells, 3), np.inf)
    hi = np.full((n_cells, 3), -np.inf)
    n_int = neighbour.shape[0]
    for f in range(owner.shape[0]):
        o = owner[f]
        nb = neighbour[f] if f < n_int else -1
        for k in range(face_offsets[f], face_offsets[f + 1]):
            p = points[face_points[k]]
            for d in range(3):
                if p[d] < lo[o, d]:
                    lo[o, d] = p[d]
                if p[d] > hi[o, d]:
                    hi[o, d] = p[d]
                if nb >= 0:
                    if p[d] < lo[nb, d]:
                        lo[nb, d] = p[d]
                    if p[d] > hi[nb, d]:
                        hi[nb, d] = p[d]
    return lo, hi


# --------------------------------------------------------------------------
# Bucket grid
# --------------------------------------------------------------------------
@njit(cache=True, error_model="numpy")
def _bucket_range(lo, hi, origin, h, dims, pad, c, i0, i1):
    for d in range(3):
        a = int(np.floor((lo[c, d] - pad - origin[d]) / h[d]))
        b = int(np.floor((hi[c, d] + pad - origin[d]) / h[d]))
        i0[d] = min(max(a, 0), dims[d] - 1)
        i1[d] = min(max(b, 0), dims[d] - 1)


@njit(cache=True, error_model="numpy")
def _build_buckets(lo, hi, origin, h, dims, pad):
    nb = dims[0] * dims[1] * dims[2]
    counts = np.zeros(nb + 1, np.int64)
    n_cells = lo.shape[0]
    i0 = np.empty(3, np.int64)
    i1 = np.empty(3, np.int64)
    for c in range(n_cells):
        _bucket_range(lo, hi, origin, h, dims, pad, c, i0, i1)
        for k in range(i0[2], i1[2] + 1):
            for j in range(i0[1], i1[1] + 1):
                for i in range(i0[0], i1[0] + 1):
                    counts[i + dims[0] * (j + dims[1] * k) + 1] += 1
    for b in range(nb):
        counts[b + 1] += counts[b]
    fill = counts[:-1].copy()
    cells = np.empty(counts[nb], np.int64)
    for c in range(n_cells):
        _bucket_range(lo, hi, origin, h, dims, pad, c, i0, i1)
        for k in range(i0[2], i1[2] + 1):
            for j in range(i0[1], i1[1] + 1):
                for i in range(i0[0], i1[0] + 1):
                    b = i + dims[0] * (j + dims[1] * k)
                    cells[fill[b]] = c
                    fill[b] += 1
    return counts, cells


# --------------------------------------------------------------------------
# Location kernels
# --------------------------------------------------------------------------
@njit(cache=True, inline="always")
def _max_violation(x0, x1, x2, c, cf_off, cf_centre, cf_normal):
    """Largest signed distance of x to the (outward) face planes of cell c,
    and the local face slot that attains it."""
    dmax = -np.inf
    kbest = -1
    for k in range(cf_off[c], cf_off[c + 1]):
        d = ((x0 - cf_centre[k, 0]) * cf_normal[k, 0]
             + (x1 - cf_centre[k, 1]) * cf_normal[k, 1]
             + (x2 - cf_centre[k, 2]) * cf_normal[k, 2])
        if d > dmax:
            dmax = d
            kbest = k
    return dmax, kbest


# The tables the compiled location reads, one record (a named tuple of arrays: one compiled
# signature): the per-cell face table (CSR offsets, face centres, outward unit normals, cell
# across each face), the cells' bounding boxes and the cell buckets (PolyMesh.buckets).
Locator = namedtuple("Locator", "cf_off cf_centre cf_normal cf_nbr cell_lo cell_hi "
                                "b_origin b_h b_dims b_off b_cells")


@njit(cache=True, error_model="numpy")
def _locate_one(x0, x1, x2, hint, L, tol, max_walk):
    """Cell of point x (-1 outside): the walk from ``hint`` across the faces it lies beyond,
    else the exact test of the cells of its bucket (L: the mesh's Locator)."""
    cf_off, cf_centre, cf_normal, cf_nbr = L.cf_off, L.cf_centre, L.cf_normal, L.cf_nbr
    cell_lo, cell_hi, b_origin, b_h, b_dims, b_off, b_cells = (L.cell_lo, L.cell_hi, L.b_origin, L.b_h,
                                                                L.b_dims, L.b_off, L.b_cells)
    # 1. hint + walk
    c = hint
    if c >= 0:
        for _ in range(max_walk):
            dmax, kbest = _max_violation(x0, x1, x2, c, cf_off, cf_centre, cf_normal)
            if dmax <= tol:
                return c
            nb = cf_nbr[kbest]
            if nb < 0:
                break
            c = nb
    # 2. bucket search (exact among the cells whose bbox overlaps the bucket)
    i = int(np.floor((x0 - b_origin[0]) / b_h[0]))
    j = int(np.floor((x1 - b_origin[1]) / b_h[1]))
    k = int(np.floor((x2 - b_origin[2]) / b_h[2]))
    # points on the far boundary of the bounding box belong to the last bucket
    if i == b_dims[0] and x0 <= b_origin[0] + b_dims[0] * b_h[0] + tol:
        i -= 1
    if j == b_dims[1] and x1 <= b_origin[1] + b_dims[1] * b_h[1] + tol:
        j -= 1
    if k == b_dims[2] and x2 <= b_origin[2] + b_dims[2] * b_h[2] + tol:
        k -= 1
    if i < 0 or j < 0 or k < 0 or i >= b_dims[0] or j >= b_dims[1] or k >= b_dims[2]:
        return -1
    b = i + b_dims[0] * (j + b_dims[1] * k)
    for s in range(b_off[b], b_off[b + 1]):
        c = b_cells[s]
        if (x0 < cell_lo[c, 0] - tol or x0 > cell_hi[c, 0] + tol or
                x1 < cell_lo[c, 1] - tol or x1 > cell_hi[c, 1] + tol or
                x2 < cell_lo[c, 2] - tol or x2 > cell_hi[c, 2] + tol):
            continue
        dmax, kbest = _max_violation(x0, x1, x2, c, cf_off, cf_centre, cf_normal)
        if dmax <= tol:
            return c
    return -1


@njit(cache=True, parallel=True)
def _locate_many(pts, hint, L, tol, max_walk):
    n = pts.shape[0]
    out = np.empty(n, np.int64)
    for p in prange(n):
        out[p] = _locate_one(pts[p, 0], pts[p, 1], pts[p, 2], hint[p], L, tol, max_walk)
    return out


@njit(cache=True, parallel=True)
def _locate_uniform(pts, origin, h, dims, first, sub, lattice, tol):
    """Cell of each point on a uniform lattice of ``dims`` cells from ``origin`` (spacing h):
    the lattice index of the whole mesh, then the entry of ``lattice``, which covers the
    sub-block of ``sub`` cells from index ``first`` (a local mesh: -1 where the cell is not
    one of its cells; the whole mesh: first = 0, sub = dims)."""
    n = pts.shape[0]
    out = np.empty(n, np.int64)
    for p in prange(n):
        idx = np.empty(3, np.int64)
        ok = True
        for d in range(3):
            t = (pts[p, d] - origin[d]) / h[d]
            i = int(np.floor(t))
            if i == dims[d] and pts[p, d] <= origin[d] + dims[d] * h[d] + tol:
                i = dims[d] - 1
            if i == -1 and pts[p, d] >= origin[d] - tol:
                i = 0
            i -= first[d]
            if i < 0 or i >= sub[d]:
                ok = False
            idx[d] = i
        if ok:
            out[p] = lattice[idx[0] + sub[0] * (idx[1] + sub[1] * idx[2])]
        else:
            out[p] = -1
    return out


@njit(cache=True, error_model="numpy")
def _brute_force_locate(pts, cf_off, cf_centre, cf_normal, tol):
    """Reference implementation: first cell whose inside test passes."""
    n = pts.shape[0]
    n_cells = cf_off.shape[0] - 1
    out = np.full(n, -1, np.int64)
    cnt = np.zeros(n, np.int64)
    for p in range(n):
        for c in range(n_cells):
            dmax, kb = _max_violation(pts[p, 0], pts[p, 1], pts[p, 2], c, cf_off,
                                      cf_centre, cf_normal)
            if dmax <= tol:
                if out[p] < 0:
                    out[p] = c
                cnt[p] += 1
    return out, cnt


@dataclass
class UniformGrid:
    """Axis-aligned uniform lattice description of a mesh. A local mesh (PolyMesh.subset)
    keeps the lattice of the whole mesh (origin, h, dims) and maps only the block of it that
    holds its cells: ``first`` (its lowest lattice index), ``sub`` (its extent), ``lattice``
    the local cell of each lattice entry of that block, -1 for cells it does not hold."""
    origin: np.ndarray   # (3,) lower corner
    h: np.ndarray        # (3,) spacing
    dims: np.ndarray     # (3,) int64 cells per direction
    lattice: np.ndarray  # (prod(sub),) cell index of lattice (i + sx*(j + sy*k)), -1: not a cell here
    first: np.ndarray = None   # (3,) int64 lattice index of the block's first cell (default 0)
    sub: np.ndarray = None     # (3,) int64 cells of the block per direction (default dims)

    def __post_init__(self):
        if self.first is None:
            self.first = np.zeros(3, np.int64)
        if self.sub is None:
            self.sub = np.asarray(self.dims, np.int64).copy()


# --------------------------------------------------------------------------
# Mesh class
# --------------------------------------------------------------------------
class PolyMesh:
    """Face-based polyhedral mesh with OpenFOAM geometry and point location.

    Attributes (all numpy): ``points``, ``face_offsets``, ``face_points``,
    ``owner``, ``neighbour``, ``face_centres``, ``face_areas`` (area vectors),
    ``cell_centres``, ``cell_volumes``, ``cell_lo``/``cell_hi`` (bounding
    boxes), and the per-cell face table ``cf_off`` (CSR offsets),
    ``cf_face``, ``cf_centre``, ``cf_normal`` (outward unit normals),
    ``cf_nbr`` (cell across the face, -1 on the boundary).
    """

    def __init__(self, points, face_offsets, face_points, owner, neighbour, boundary=None, phantom=False):
        self.points = np.ascontiguousarray(points, dtype=np.float64)
        self.face_offsets = np.ascontiguousarray(face_offsets, dtype=np.int64)
        self.face_points = np.ascontiguousarray(face_points, dtype=np.int64)
        self.owner = np.ascontiguousarray(owner, dtype=np.int64)
        self.neighbour = np.ascontiguousarray(neighbour, dtype=np.int64)
        self.boundary = list(boundary or [])
        self.n_faces = len(self.owner)
        self.n_internal_faces = len(self.neighbour)
        if len(self.face_offsets) - 1 != self.n_faces:
            raise ValueError(f"faces ({len(self.face_offsets) - 1}) and owner "
                             f"({self.n_faces}) sizes differ")
        self.n_cells = int(max(self.owner.max(initial=-1),
                               self.neighbour.max(initial=-1))) + 1
        fc, fa = _face_geometry(self.points, self.face_offsets, self.face_points)
        self.face_centres, self.face_areas = fc, fa
        cc, cv = _cell_geometry(fc, fa, self.owner, self.neighbour, self.n_cells)
        self.cell_centres, self.cell_volumes = cc, cv
        # phantom: the last cell stands for the cells beyond a piece (read_pieces), no real cell
        real = cv[:-1] if phantom else cv
        if np.any(real <= 0):
            raise ValueError(f"{int(np.sum(real <= 0))} cells with non-positive volume "
                             "(inverted faces / wrong owner-neighbour orientation?)")
        lo, hi = _cell_bboxes(self.points, self.face_offsets, self.face_points,
                              self.owner, self.neighbour, self.n_cells)
        #: vertex bounding boxes of the cells
        self.cell_vlo, self.cell_vhi = lo, hi
        # Search boxes: with warped (non-planar) faces the face-plane inside
        # region can extend slightly beyond the vertices; pad by 10 % of the
        # cell extent (exact for planar faces, where padding only costs time).
        pad = 0.1 * (hi - lo)
        self.cell_lo, self.cell_hi = lo - pad, hi + pad
        self._build_cell_faces()
        self.bbox_lo = self.cell_vlo.min(axis=0)
        self.bbox_hi = self.cell_vhi.max(axis=0)
        L = float(np.max(self.bbox_hi - self.bbox_lo))
        #: absolute tolerance of the inside test (points on a face belong to
        #: both cells; the first one found is returned)
        self.tol = 1e-12 * L
        self._buckets = None
        self._locator = None
        self.lsq_inv = None  # least-squares matrices of the gradient interpolation (coupling.interpolate)
        self._uniform = "unset"
        self._point_nbrs = None
        self._face_nbrs = None
        #: a local mesh (:meth:`subset`): the global cell of each cell, the cells of the whole
        #: mesh and its cut faces (after the patches' faces); the whole mesh: None, n_cells, 0
        self.global_ids = None
        self.n_global = self.n_cells
        self.n_cut_faces = 0

    # ---- a local mesh ----------------------------------------------------------
    def subset(self, cells) -> "PolyMesh":
        """The mesh of ``cells`` only (global cell ids; sorted, duplicates dropped), numbered
        0..n-1 in the order of their global ids; ``global_ids`` maps back.

        Faces between two of its cells stay internal (in their order); the faces of the
        boundary patches owned by its cells keep their patch (name, type, new start and
        size; a patch may hold no face here); faces to a cell outside become *cut* faces, last,
        outside every patch (``n_cut_faces``; the kept cell is their owner: a face whose
        neighbour was kept is turned round). A cut face is not a boundary of the domain: no
        patch logic sees it, and a point beyond it is simply not located (-1). The geometry is
        copied from this mesh, not recomputed, so every cell's centre, volume, box and face
        table (order included) are those of this mesh, bit for bit, and a point is located in
        the same cell; a uniform lattice keeps its spacing and maps the block of its cells."""
        cells = np.unique(np.asarray(cells, np.int64))
        n = cells.size
        if n and (cells[0] < 0 or cells[-1] >= self.n_cells):
            raise ValueError(f"cells outside 0..{self.n_cells - 1}")
        g2l = np.full(self.n_cells, -1, np.int64)
        g2l[cells] = np.arange(n)
        ni = self.n_internal_faces
        lo, ln = g2l[self.owner], g2l[self.neighbour]
        lo_i = lo[:ni]
        internal = np.flatnonzero((lo_i >= 0) & (ln >= 0))
        cut = np.flatnonzero((lo_i >= 0) ^ (ln >= 0))
        patches, pf = [], [internal]
        start = internal.size
        for p in self.boundary:
            f0, nf = int(p["startFace"]), int(p["nFaces"])
            keep = f0 + np.flatnonzero(lo[f0:f0 + nf] >= 0)
            patches.append(dict(p, startFace=start, nFaces=int(keep.size)))
            pf.append(keep)
            start += keep.size
        pf.append(cut)
        pf = np.concatenate(pf).astype(np.int64)
        nf_new = pf.size
        flip = np.zeros(nf_new, bool)
        flip[nf_new - cut.size:] = lo_i[cut] < 0
        own = np.where(flip, ln[np.minimum(pf, max(ni - 1, 0))] if ni else 0, lo[pf])
        nb = ln[internal]
        # faces' point loops (turned round where flipped), points renumbered in their order
        starts = self.face_offsets[pf]
        lens = self.face_offsets[pf + 1] - starts
        off = np.zeros(nf_new + 1, np.int64)
        np.cumsum(lens, out=off[1:])
        fe = np.repeat(np.arange(nf_new), lens)
        k = np.arange(off[-1]) - off[fe]
        src = starts[fe] + np.where(flip[fe], lens[fe] - 1 - k, k)
        gp = self.face_points[src]
        used = np.unique(gp)
        fpts = np.searchsorted(used, gp).astype(np.int64)
        m = PolyMesh.__new__(PolyMesh)
        m.points = np.ascontiguousarray(self.points[used])
        m.face_offsets, m.face_points = off, fpts
        m.owner, m.neighbour = np.ascontiguousarray(own, np.int64), np.ascontiguousarray(nb, np.int64)
        m.boundary = patches
        m.n_faces, m.n_internal_faces, m.n_cells = nf_new, int(internal.size), n
        sgn = np.where(flip, -1.0, 1.0)[:, None]
        m.face_centres = np.ascontiguousarray(self.face_centres[pf])
        m.face_areas = np.ascontiguousarray(self.face_areas[pf] * sgn)
        m.face_mag = self.face_mag[pf]
        for a in ("cell_centres", "cell_volumes", "cell_vlo", "cell_vhi", "cell_lo", "cell_hi"):
            setattr(m, a, np.ascontiguousarray(getattr(self, a)[cells]))
        # the face table: this mesh's rows of each cell, faces and cells renumbered
        f2l = np.full(self.n_faces, -1, np.int64)
        f2l[pf] = np.arange(nf_new)
        rs, re = self.cf_off[cells], self.cf_off[cells + 1]
        cnt = re - rs
        m.cf_off = np.zeros(n + 1, np.int64)
        np.cumsum(cnt, out=m.cf_off[1:])
        rows = np.repeat(rs - m.cf_off[:-1], cnt) + np.arange(m.cf_off[-1])
        m.cf_face = f2l[self.cf_face[rows]]
        m.cf_centre = np.ascontiguousarray(self.cf_centre[rows])
        m.cf_normal = np.ascontiguousarray(self.cf_normal[rows])
        nbr = self.cf_nbr[rows]
        m.cf_nbr = np.where(nbr >= 0, g2l[np.maximum(nbr, 0)], -1)
        m.bbox_lo = m.cell_vlo.min(axis=0) if n else self.bbox_lo.copy()
        m.bbox_hi = m.cell_vhi.max(axis=0) if n else self.bbox_hi.copy()
        m.tol = self.tol
        m._buckets = m._locator = m.lsq_inv = m._point_nbrs = m._face_nbrs = None
        m._uniform = "unset"
        ug = self.uniform_grid
        if ug is not None:
            idx = np.rint((m.cell_vlo - ug.origin) / ug.h).astype(np.int64)
            first = idx.min(axis=0) if n else np.zeros(3, np.int64)
            sub = (idx.max(axis=0) + 1 - first) if n else np.zeros(3, np.int64)
            lat = np.full(int(np.prod(sub)), -1, np.int64)
            r = idx - first
            lat[r[:, 0] + sub[0] * (r[:, 1] + sub[1] * r[:, 2])] = np.arange(n)
            m._uniform = UniformGrid(ug.origin, ug.h, ug.dims, lat, first.astype(np.int64), sub.astype(np.int64))
        else:
            m._uniform = None
        m.global_ids = cells if self.global_ids is None else self.global_ids[cells]
        m.n_global = self.n_global
        m.n_cut_faces = int(cut.size)
        return m

    def nbytes(self) -> int:
        """Bytes of the arrays this mesh holds (geometry, connectivity, location tables)."""
        tot = 0
        for v in self.__dict__.values():
            if isinstance(v, np.ndarray):
                tot += v.nbytes
            elif isinstance(v, tuple):
                tot += sum(a.nbytes for a in v if isinstance(a, np.ndarray))
            elif isinstance(v, UniformGrid):
                tot += v.lattice.nbytes
        return int(tot)

    # ---- connectivity --------------------------------------------------
    def _build_cell_faces(self):
        nf, ni = self.n_faces, self.n_internal_faces
        cells = np.concatenate([self.owner, self.neighbour])
        faces = np.concatenate([np.arange(nf), np.arange(ni)])
        sign = np.concatenate([np.ones(nf), -np.ones(ni)])
        other = np.concatenate([np.concatenate([self.neighbour, -np.ones(nf - ni, np.int64)]),
                                self.owner[:ni]])
        order = np.argsort(cells, kind="stable")
        self.cf_off = np.zeros(self.n_cells + 1, np.int64)
        np.cumsum(np.bincount(cells, minlength=self.n_cells), out=self.cf_off[1:])
        self.cf_face = faces[order].astype(np.int64)
        s = sign[order]
        mag = np.linalg.norm(self.face_areas, axis=1)
        self.face_mag = mag
        self.cf_centre = np.ascontiguousarray(self.face_centres[self.cf_face])
        self.cf_normal = np.ascontiguousarray(self.face_areas[self.cf_face]
                                              * (s / mag[self.cf_face])[:, None])
        self.cf_nbr = np.ascontiguousarray(other[order].astype(np.int64))

    def face_neighbours(self):
        """CSR (offsets, cells) of the face neighbours of each cell."""
        if self._face_nbrs is None:
            keep = self.cf_nbr >= 0
            cell_of = np.repeat(np.arange(self.n_cells), np.diff(self.cf_off))
            off = np.zeros(self.n_cells + 1, np.int64)
            np.cumsum(np.bincount(cell_of[keep], minlength=self.n_cells), out=off[1:])
            self._face_nbrs = (off, self.cf_nbr[keep].copy())
        return self._face_nbrs

    def point_neighbours(self):
        """CSR (offsets, cells) of all cells sharing at least one point with
        each cell, the cell itself first (27 cells inside a hex grid)."""
        if self._point_nbrs is None:
            self._point_nbrs = _point_neighbour_csr(
                self.face_offsets, self.face_points, self.owner, self.neighbour,
                self.n_cells, len(self.points))
        return self._point_nbrs

    @property
    def cell_size(self) -> np.ndarray:
        """Cube-root of the cell volume (length scale of each cell)."""
        return np.cbrt(self.cell_volumes)

    # ---- uniform-grid detection ------------------------------------------
    @property
    def uniform_grid(self):
        """``UniformGrid`` if the mesh is an axis-aligned uniform lattice of
        boxes (each cell's volume equals its bounding-box volume, all boxes
        equal, corners on a common lattice, lattice fully covered), else None."""
        if isinstance(self._uniform, str):
            self._uniform = self._detect_uniform()
        return self._uniform

    def _detect_uniform(self, rtol=1e-9):
        ext = self.cell_vhi - self.cell_vlo
        h = ext[0]
        if np.any(h <= 0):
            return None
        if not np.allclose(ext, h[None, :], rtol=rtol, atol=0):
            return None
        if not np.allclose(self.cell_volumes, np.prod(ext, axis=1), rtol=1e-8, atol=0):
            return None
        origin = self.cell_vlo.min(axis=0)
        t = (self.cell_vlo - origin) / h
        idx = np.rint(t).astype(np.int64)
        if np.max(np.abs(t - idx)) > 1e-6:
            return None
        dims = idx.max(axis=0) + 1
        if int(np.prod(dims)) != self.n_cells:
            return None
        lin = idx[:, 0] + dims[0] * (idx[:, 1] + dims[1] * idx[:, 2])
        lattice = np.full(self.n_cells, -1, np.int64)
        lattice[lin] = np.arange(self.n_cells)
        if np.any(lattice < 0):
            return None
        # use the exact extent to avoid drift over many cells
        h = (self.cell_vhi.max(axis=0) - origin) / dims
        return UniformGrid(origin, h, dims.astype(np.int64), lattice)

    # ---- locate --------------------------------------------------------------
    def buckets(self):
        """The cell buckets of the locator (built once): (origin, h, dims, offsets, cells)."""
        if self._buckets is None:
            lo, hi = self.cell_lo.min(axis=0), self.cell_hi.max(axis=0)
            ext = np.maximum(hi - lo, 1e-300)
            mean_size = float(np.mean(np.cbrt(self.cell_volumes)))
            target = np.maximum(np.ceil(ext / mean_size), 1).astype(np.int64)
            while np.prod(target) > max(8 * self.n_cells, 1000) or np.prod(target) > 2e7:
                target = np.maximum((target + 1) // 2, 1)
            h = ext / target
            pad = self.tol
            off, cells = _build_buckets(self.cell_lo, self.cell_hi, lo, h, target, pad)
            self._buckets = (lo.copy(), h, target, off, cells)
        return self._buckets

    def locator(self) -> Locator:
        """The location tables as one record for the compiled kernels (built once)."""
        if self._locator is None:
            self._locator = Locator(self.cf_off, self.cf_centre, self.cf_normal, self.cf_nbr,
                                    self.cell_lo, self.cell_hi, *self.buckets())
        return self._locator

    def locate(self, points, hint=None, method="auto", max_walk=64):
        """Cell index of each point (-1 outside the mesh).

        Parameters
        ----------
        points : (n, 3) array
        hint : (n,) int array, optional
            previous cell of each point (-1 = unknown).  A point still in its
            hint cell costs a single inside test.
        method : 'auto' (uniform fast path when the mesh is a uniform
            axis-aligned grid, general path otherwise), 'general' or 'uniform'.
        """
        pts = np.ascontiguousarray(np.asarray(points, dtype=np.float64).reshape(-1, 3))
        n = len(pts)
        if method not in ("auto", "general", "uniform"):
            raise ValueError("method must be 'auto', 'general' or 'uniform'")
        if method in ("auto", "uniform"):
            ug = self.uniform_grid
            if ug is not None:
                return _locate_uniform(pts, ug.origin, ug.h, ug.dims, ug.first, ug.sub, ug.lattice, self.tol)
            if method == "uniform":
                raise ValueError("mesh is not a uniform axis-aligned grid")
        if hint is None:
            hint = np.full(n, -1, np.int64)
        else:
            hint = np.ascontiguousarray(hint, dtype=np.int64)
            if hint.shape != (n,):
                raise ValueError("hint must have one entry per point")
            hint = np.where(hint < self.n_cells, hint, -1)
        return _locate_many(pts, hint, self.locator(), self.tol, max_walk)

    def locate_brute_force(self, points):
        """(cell, number_of_cells_containing) by testing every cell (tests)."""
        pts = np.ascontiguousarray(np.asarray(points, dtype=np.float64).reshape(-1, 3))
        return _brute_force_locate(pts, self.cf_off, self.cf_centre, self.cf_normal, self.tol)

    def summary(self) -> str:
        ug = self.uniform_grid
        return (f"PolyMesh: {len(self.points)} points, {self.n_faces} faces "
                f"({self.n_internal_faces} internal), {self.n_cells} cells, "
                f"volume {self.cell_volumes.sum():.6g}, "
                f"{'uniform grid ' + str(tuple(ug.dims)) if ug is not None else 'general'}")


@njit(cache=True, error_model="numpy")
def _point_neighbour_csr(face_offsets, face_points, owner, neighbour, n_cells, n_points):
    n_int = neighbour.shape[0]
    # point -> cells (with duplicates), then dedupe per cell row with a marker
    pc_cnt = np.zeros(n_points + 1, np.int64)
    for f in range(owner.shape[0]):
        m = 2 if f < n_int else 1
        for k in range(face_offsets[f], face_offsets[f + 1]):
            pc_cnt[face_points[k] + 1] += m
    for p in range(n_points):
        pc_cnt[p + 1] += pc_cnt[p]
    pc = np.empty(pc_cnt[n_points], np.int64)
    fill = pc_cnt[:-1].copy()
    for f in range(owner.shape[0]):
        for k in range(face_offsets[f], face_offsets[f + 1]):
            p = face_points[k]
            pc[fill[p]] = owner[f]
            fill[p] += 1
            if f < n_int:
                pc[fill[p]] = neighbour[f]
                fill[p] += 1
    # cell -> points via faces
    cp_cnt = np.zeros(n_cells + 1, np.int64)
    for f in range(owner.shape[0]):
        nn = face_offsets[f + 1] - face_offsets[f]
        cp_cnt[owner[f] + 1] += nn
        if f < n_int:
            cp_cnt[neighbour[f] + 1] += nn
    for c in range(n_cells):
        cp_cnt[c + 1] += cp_cnt[c]
    cp = np.empty(cp_cnt[n_cells], np.int64)
    fill2 = cp_cnt[:-1].copy()
    for f in range(owner.shape[0]):
        for k in range(face_offsets[f], face_offsets[f + 1]):
            cp[fill2[owner[f]]] = face_points[k]
            fill2[owner[f]] += 1
            if f < n_int:
                cp[fill2[neighbour[f]]] = face_points[k]
                fill2[neighbour[f]] += 1
    mark = np.full(n_cells, -1, np.int64)
    off = np.zeros(n_cells + 1, np.int64)
    for c in range(n_cells):
        mark[c] = c
        k = 1
        for s in range(cp_cnt[c], cp_cnt[c + 1]):
            p = cp[s]
            for t in range(pc_cnt[p], pc_cnt[p + 1]):
                o = pc[t]
                if mark[o] != c:
                    mark[o] = c
                    k += 1
        off[c + 1] = off[c] + k
    out = np.empty(off[n_cells], np.int64)
    mark[:] = -1
    for c in range(n_cells):
        out[off[c]] = c
        mark[c] = c
        k = 1
        for s in range(cp_cnt[c], cp_cnt[c + 1]):
            p = cp[s]
            for t in range(pc_cnt[p], pc_cnt[p + 1]):
                o = pc[t]
                if mark[o] != c:
                    mark[o] = c
                    out[off[c] + k] = o
                    k += 1
    return off, out


def benchmark_locate(mesh: PolyMesh, n: int = 100_000, seed: int = 0) -> dict:
    """Time locate for n random points (cold = no hint, warm = hint = answer,
    moved = small random displacement with hint)."""
    rng = np.random.default_rng(seed)
    lo, hi = mesh.bbox_lo, mesh.bbox_hi
    pts = lo + (hi - lo) * rng.random((n, 3))
    mesh.locate(pts[:10], method="general")  # compile
    t0 = time.perf_counter()
    cells = mesh.locate(pts, method="general")
    t1 = time.perf_counter()
    mesh.locate(pts, hint=cells, method="general")
    t2 = time.perf_counter()
    moved = pts + 0.2 * float(np.mean(mesh.cell_size)) * (rng.random((n, 3)) - 0.5)
    mesh.locate(moved, hint=cells, method="general")
    t3 = time.perf_counter()
    res = {"cold": t1 - t0, "hint_same": t2 - t1, "hint_moved": t3 - t2}
    if mesh.uniform_grid is not None:
        t4 = time.perf_counter()
        mesh.locate(pts, method="uniform")
        res["uniform"] = time.perf_counter() - t4
    return res


def locate(mesh: PolyMesh, points, hint=None, method: str = "auto") -> np.ndarray:
    """Function form of :meth:`PolyMesh.locate`."""
    return mesh.locate(points, hint=hint, method=method)
