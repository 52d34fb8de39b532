"""Cell-centre gas fields -> particle positions.

Methods (``interpolate(..., method=...)``):

``cell``
    value of the cell containing the particle (CFDEMcoupling's default
    ``interpolation off``).
``idw``
    inverse-distance weighting (power 2) over the containing cell and its
    face neighbours; bounded by the stencil's min/max, not exact for linear
    fields.
``linear``
    ``phi_c + G_c . (x - x_c)`` with G_c the weighted least-squares gradient
    from the face neighbours (weights 1/|dx|^2).  Exact for linear fields on
    any mesh (interior cells and boundary cells with >= 3 independent
    neighbours); in a one-cell-thick (2-D) direction the pseudo-inverse
    gives zero gradient.  ``limit=True`` clips the result to the min/max of
    the stencil (no new extrema, loses exactness near extrema and corners).

Particles outside the mesh (cell -1) get ``fill`` (NaN by default).
"""
from __future__ import annotations

import numpy as np
from numba import njit, prange

from .mesh import PolyMesh

__all__ = ["interpolate", "cell_gradient", "lsq_matrices", "METHODS"]

METHODS = ("cell", "idw", "linear")


@njit(cache=True, error_model="numpy")
def _lsq_matrices(cc, nb_off, nb):
    n = cc.shape[0]
    out = np.zeros((n, 3, 3))
    for c in range(n):
        A = np.zeros((3, 3))
        for s in range(nb_off[c], nb_off[c + 1]):
            o = nb[s]
            dx = cc[o] - cc[c]
            w = 1.0 / (dx[0] * dx[0] + dx[1] * dx[1] + dx[2] * dx[2])
            for i in range(3):
                for j in range(3):
                    A[i, j] += w * dx[i] * dx[j]
        # scale to O(1) before the pseudo-inverse so the rank cut is relative
        sc = max(A[0, 0] + A[1, 1] + A[2, 2], 1e-300)
        out[c] = np.linalg.pinv(A / sc, rcond=1e-10) / sc
    return out


def lsq_matrices(mesh: PolyMesh) -> np.ndarray:
    """(nCells, 3, 3) pseudo-inverses of the least-squares normal matrices
    (cached on the mesh)."""
    M = getattr(mesh, "lsq_inv", None)
    if M is None:
        off, nb = mesh.face_neighbours()
        M = _lsq_matrices(mesh.cell_centres, off, nb)
        mesh.lsq_inv = M
    return M


@njit(cache=True, parallel=True)
def _lsq_gradient(cc, nb_off, nb, Minv, phi):
    n, m = phi.shape
    g = np.zeros((n, m, 3))
    for c in prange(n):
        for k in range(m):
            b0 = 0.0
            b1 = 0.0
            b2 = 0.0
            for s in range(nb_off[c], nb_off[c + 1]):
                o = nb[s]
                d0 = cc[o, 0] - cc[c, 0]
                d1 = cc[o, 1] - cc[c, 1]
                d2 = cc[o, 2] - cc[c, 2]
                w = (phi[o, k] - phi[c, k]) / (d0 * d0 + d1 * d1 + d2 * d2)
                b0 += w * d0
                b1 += w * d1
                b2 += w * d2
            for i in range(3):
                g[c, k, i] = Minv[c, i, 0] * b0 + Minv[c, i, 1] * b1 + Minv[c, i, 2] * b2
    return g


def cell_gradient(mesh: PolyMesh, phi) -> np.ndarray:
    """Least-squares gradient at cell centres: (nCells, 3) for a scalar
    field, (nCells, m, 3) for an m-component field (row = component)."""
    a = np.asarray(phi, np.float64)
    scalar = a.ndim == 1
    a2 = np.ascontiguousarray(a.reshape(mesh.n_cells, -1))
    off, nb = mesh.face_neighbours()
    g = _lsq_gradient(mesh.cell_centres, off, nb, lsq_matrices(mesh), a2)
    return g[:, 0, :] if scalar else g


@njit(cache=True, parallel=True)
def _interp_cell(phi, cells, fill):
    n = cells.shape[0]
    m = phi.shape[1]
    out = np.empty((n, m))
    for p in prange(n):
        c = cells[p]
        for k in range(m):
            out[p, k] = phi[c, k] if c >= 0 else fill
    return out


@njit(cache=True, parallel=True)
def _interp_idw(phi, cells, pos, cc, nb_off, nb, fill):
    n = cells.shape[0]
    m = phi.shape[1]
    out = np.empty((n, m))
    for p in prange(n):
        c = cells[p]
        if c < 0:
            for k in range(m):
                out[p, k] = fill
            continue
        d2 = 0.0
        for i in range(3):
            t = pos[p, i] - cc[c, i]
            d2 += t * t
        scale = 0.0
        for s in range(nb_off[c], nb_off[c + 1]):
            o = nb[s]
            for i in range(3):
                t = cc[o, i] - cc[c, i]
                scale += t * t
        tiny = 1e-24 * max(scale, 1e-300)
        w = 1.0 / (d2 + tiny)
        tot = w
        for k in range(m):
            out[p, k] = w * phi[c, k]
        for s in range(nb_off[c], nb_off[c + 1]):
            o = nb[s]
            d2 = 0.0
            for i in range(3):
                t = pos[p, i] - cc[o, i]
                d2 += t * t
            w = 1.0 / (d2 + tiny)
            tot += w
            for k in range(m):
                out[p, k] += w * phi[o, k]
        for k in range(m):
            out[p, k] /= tot
    return out


@njit(cache=True, parallel=True)
def _interp_linear(phi, grad, cells, pos, cc, nb_off, nb, limit, fill):
    n = cells.shape[0]
    m = phi.shape[1]
    out = np.empty((n, m))
    for p in prange(n):
        c = cells[p]
        if c < 0:
            for k in range(m):
                out[p, k] = fill
            continue
        for k in range(m):
            v = phi[c, k]
            for i in range(3):
                v += grad[c, k, i] * (pos[p, i] - cc[c, i])
            if limit:
                lo = phi[c, k]
                hi = phi[c, k]
                for s in range(nb_off[c], nb_off[c + 1]):
                    q = phi[nb[s], k]
                    lo = min(lo, q)
                    hi = max(hi, q)
                v = min(max(v, lo), hi)
            out[p, k] = v
    return out


def interpolate(mesh: PolyMesh, field, positions, cells, method: str = "cell",
                grad=None, limit: bool = False, fill: float = np.nan) -> np.ndarray:
    """Interpolate a cell-centred field to particle positions.

    Parameters
    ----------
    field : (nCells,) or (nCells, m) array (e.g. T, U, grad p)
    positions : (n, 3) particle positions
    cells : (n,) containing cells (from ``mesh.locate``; -1 = outside)
    method : 'cell', 'idw' or 'linear'
    grad : optional precomputed gradient for 'linear' ((nCells, 3) or
        (nCells, m, 3)); computed by least squares when None.
    Returns (n,) or (n, m).
    """
    if method not in METHODS:
        raise ValueError(f"unknown interpolation method {method!r}; valid: {', '.join(METHODS)}")
    a = np.asarray(field, np.float64)
    scalar = a.ndim == 1
    phi = np.ascontiguousarray(a.reshape(mesh.n_cells, -1))
    cells = np.ascontiguousarray(cells, np.int64)
    pos = np.ascontiguousarray(np.asarray(positions, np.float64).reshape(-1, 3))
    if len(pos) != len(cells):
        raise ValueError("positions and cells must have the same length")
    if method == "cell":
        out = _interp_cell(phi, cells, fill)
    else:
        off, nb = mesh.face_neighbours()
        if method == "idw":
            out = _interp_idw(phi, cells, pos, mesh.cell_centres, off, nb, fill)
        else:
            if grad is None:
                g = _lsq_gradient(mesh.cell_centres, off, nb, lsq_matrices(mesh), phi)
            else:
                g = np.ascontiguousarray(np.asarray(grad, np.float64).reshape(mesh.n_cells, phi.shape[1], 3))
            out = _interp_linear(phi, g, cells, pos, mesh.cell_centres, off, nb, bool(limit), fill)
    return out[:, 0] if scalar else out
