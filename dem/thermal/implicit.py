"""Sparse symmetric solver of the implicit (backward Euler) heat step.

The step solves, for the temperature increment d = T^{n+1} - T^n of the particles,

    (C/dt + K + L) d = Q(T^n)                                              (1)

with C = diag(m_i c_i), L the weighted graph Laplacian of the pair conductances
H_ij = Hd_ij + Hi_ij (L_ii = sum_j H_ij, L_ij = -H_ij), K = diag(k_i) the conductances of
each particle's reservoir links (fixed-temperature walls, gas convection h A, and the
radiation tangent 4 eps sigma A T_i^3), and Q(T^n) the net heat rate of every particle at
the start of the step (reservoirs at the end of the step). The matrix A = C/dt + K + L is
symmetric positive definite (C > 0, K >= 0, L positive semi-definite), so (1) is solved by
the preconditioned conjugate-gradient method (Hestenes & Stiefel 1952; Shewchuk 1994,
"An introduction to the conjugate gradient method without the agonizing pain", section
B3; Saad 2003, "Iterative methods for sparse linear systems", 2nd ed., algorithm 9.1)
with the Jacobi preconditioner M = diag(A) (Saad 2003, section 10.2).

A is never formed: its product with a vector is one pass over the half neighbour list
(each pair once, scattered to both rows) plus the diagonal, so the memory is that of a
few vectors. Under MPI (dem.thermal.implicit_mpi) the rows [0, n) are a rank's owned particles
and the rows [n, ng) its ghosts: a pair of an owned particle and a ghost is listed on both
ranks, and each adds its share to its own row only (the ghost's entry of the vector comes from
its owner), so the product over the ranks is that of the whole matrix. The functions below are pure (they write only into the arrays they are
given) and compiled once (no literal-argument specialisations).
"""
import math

import numpy as np
from numba import njit, prange

from ..blocks import add_buffered, block_bounds, block_sum, cross_counts

# relative residual at which the conjugate gradients stop (||r|| <= CG_RTOL ||b||, b the heat
# rates Q(T^n)): the energy defect of a step is dt sum(r) <= dt sqrt(n) CG_RTOL ||Q(T^n)||, far
# below the heat exchanged; the steady state does not depend on it (a fixed point d = 0 is
# reached when Q(T) = 0, where the residual scales with Q); 1e-10 stays above the round-off
# floor eps cond(A) of the systems met (cond(A) < 1e5 for dt up to 1000 network steps).
CG_RTOL = 1e-10


@njit(cache=True, error_model="numpy")
def laplacian_apply(n, nb, nnb, Hd, Hi, has_ind, dg, x, y):
    """y = (diag(dg) + L) x over the rows [0, n): L the graph Laplacian of the pair
    conductances H_ij = Hd[i, s] + Hi[i, s] (j = nb[i, s], each pair listed once, in the
    half list): (L x)_i = sum_j H_ij (x_i - x_j). A pair with a ghost, n <= j < len(x), adds
    to row i only (x_j the ghost's value); pairs with j >= len(x) are ignored."""
    zero = n - n  # row 0, slot 0 and the mode as run-time values: a literal argument compiles _apply_rows again
    _apply_rows(zero, n, n, x.shape[0], (nb, nnb, Hd, Hi), has_ind, dg, x, y,
                (np.empty(0, np.int64), np.empty(0)), zero, zero > 0)


@njit(cache=True, error_model="numpy")
def laplacian_diagonal(n, ng, nb, nnb, Hd, Hi, has_ind, dg, out):
    """out = dg + diag(L): dg_i plus the sum of particle i's pair conductances (the Jacobi
    preconditioner of diag(dg) + L), the pairs with the ghosts [n, ng) included."""
    zero = n - n  # (run-time values, as in laplacian_apply)
    _apply_rows(zero, n, n, ng, (nb, nnb, Hd, Hi), has_ind, dg, dg, out, (np.empty(0, np.int64), np.empty(0)),
                zero, zero == 0)


@njit(cache=True, error_model="numpy")
def jacobi_pcg(n, nb, nnb, Hd, Hi, has_ind, dg, b, x, rtol, maxit):
    """Solve (diag(dg) + L) x = b (symmetric positive definite: dg > 0) by conjugate gradients
    with the Jacobi preconditioner (Saad 2003, algorithm 9.1; Shewchuk 1994, B3), from x = 0.

    Stops when the recursively updated residual r = b - A x has ||r||_2 <= rtol ||b||_2, or
    after maxit iterations. Returns (iterations, ||r||_2 / ||b||_2) (0, 0.0 when b = 0)."""
    bb = 0.0
    for i in range(n):
        x[i] = 0.0
        bb += b[i] * b[i]
    if bb == 0.0:
        return 0, 0.0
    dinv = np.empty(n)
    laplacian_diagonal(n, n, nb, nnb, Hd, Hi, has_ind, dg, dinv)
    for i in range(n):
        dinv[i] = 1.0 / dinv[i]
    r = b.copy()
    z = np.empty(n)
    p = np.empty(n)
    q = np.empty(n)
    rz = 0.0
    for i in range(n):
        z[i] = dinv[i] * r[i]
        p[i] = z[i]
        rz += r[i] * z[i]
    stop = rtol * rtol * bb
    rr = bb
    it = 0
    while it < maxit and rr > stop:
        laplacian_apply(n, nb, nnb, Hd, Hi, has_ind, dg, p, q)
        pq = 0.0
        for i in range(n):
            pq += p[i] * q[i]
        if not (pq > 0.0):  # p = 0 in floating point: nothing left to reduce
            break
        alpha = rz / pq
        rr = 0.0
        rz_new = 0.0
        for i in range(n):
            x[i] += alpha * p[i]
            r[i] -= alpha * q[i]
            rr += r[i] * r[i]
            z[i] = dinv[i] * r[i]
            rz_new += r[i] * z[i]
        beta = rz_new / rz
        rz = rz_new
        for i in range(n):
            p[i] = z[i] + beta * p[i]
        it += 1
    return it, math.sqrt(rr / bb)


@njit(cache=True, error_model="numpy")
def _apply_rows(i0, i1, n, ng, pairs, has_ind, dg, x, y, buf, k, diag):
    """Rows [i0, i1) of :func:`laplacian_apply` (``diag`` False: y_i = dg_i x_i plus the row's
    pairs, each pair's q = H_ij (x_i - x_j) added to row i and subtracted from row j) or of
    :func:`laplacian_diagonal` (``diag`` True: y_i = dg_i, each pair's H_ij added to both rows;
    x unused). A pair with a ghost (n <= j < ng) adds to row i only. A pair whose j lies in
    another block writes j's share at buf[k], k + 1, ..., added later in block order. Returns
    the next free k."""
    nb, nnb, Hd, Hi = pairs
    xj, xq = buf
    sgn = 1.0 if diag else -1.0
    for i in range(i0, i1):
        y[i] = dg[i] if diag else dg[i] * x[i]
    for iu in range(i0, i1):  # rows as uint32: no wrap-around of a negative index (dem.step.interact_rows)
        i = np.uint32(iu)
        xi = 0.0 if diag else x[i]
        acc = 0.0
        for s in range(nnb[i]):
            j = np.uint32(nb[i, s])
            if j >= ng:
                continue
            h = Hd[i, s] + (Hi[i, s] if has_ind else 0.0)
            if h <= 0.0:
                continue
            q = h if diag else h * (xi - x[j])
            if diag:  # (the diagonal's sums in the order of the serial pass before blocks)
                y[i] += q
            else:
                acc += q
            if j >= n:  # a ghost: its owner adds its share
                continue
            if i0 <= j < i1:
                y[j] += sgn * q
            else:
                if k < xj.shape[0]:
                    xj[k] = j
                    xq[k] = sgn * q
                k += 1
        if not diag:
            y[i] += acc
    return k


@njit(cache=True, error_model="numpy", parallel=True)
def _apply_blocks(n, pairs, has_ind, dg, x, y, bounds, cnt, buf, diag):
    """:func:`_apply_rows` on the blocks ``bounds`` at once, then the shares buffered for rows of
    other blocks added in block and pair order (``cnt``: each block's range of ``buf``)."""
    nblk = bounds.shape[0] - 1
    end = np.empty(nblk, np.int64)
    for c in prange(nblk):
        end[c] = _apply_rows(bounds[c], bounds[c + 1], n, n, pairs, has_ind, dg, x, y, buf, cnt[c], diag)
    if not add_buffered(y, buf[0], buf[1], cnt, end):  # a list changed without after_build or dem.state
        raise RuntimeError("internal error: more pairs across blocks of rows than counted "
                           "(dem.thermal.implicit._apply_blocks)")


@njit(cache=True, error_model="numpy", parallel=True)
def jacobi_pcg_blocks(n, pairs, has_ind, dg, b, x, rtol, maxit, nblk):
    """:func:`jacobi_pcg` on ``nblk`` blocks of rows at once (dem.blocks): the products with A
    and its diagonal by :func:`_apply_blocks` (the pairs across blocks buffered, then added in
    block and pair order), the vector updates per row, and every dot product summed per block
    and then in block order, so a solve is deterministic for a thread count (round-off against
    one thread: the sums run in another order). ``pairs`` = (nb, nnb, Hd, Hi)."""
    nb, nnb = pairs[0], pairs[1]
    bounds = block_bounds(n, n, nblk)
    part = np.zeros((nblk, 3))
    for c in prange(nblk):
        bbb = 0.0
        for i in range(bounds[c], bounds[c + 1]):
            x[i] = 0.0
            bbb += b[i] * b[i]
        part[c, 0] = bbb
    bb = block_sum(part, 0)
    if bb == 0.0:
        return 0, 0.0
    cnt = cross_counts(nb, nnb, np.empty((0, 0), np.uint8), bounds)
    buf = (np.empty(cnt[nblk], np.int64), np.empty(cnt[nblk]))
    dinv = np.empty(n)
    _apply_blocks(n, pairs, has_ind, dg, x, dinv, bounds, cnt, buf, nblk > 0)  # (the modes as run-time values)
    r = np.empty(n)
    z = np.empty(n)
    p = np.empty(n)
    q = np.empty(n)
    for c in prange(nblk):
        rzb = 0.0
        for i in range(bounds[c], bounds[c + 1]):
            dinv[i] = 1.0 / dinv[i]
            r[i] = b[i]
            z[i] = dinv[i] * r[i]
            p[i] = z[i]
            rzb += r[i] * z[i]
        part[c, 0] = rzb
    rz = block_sum(part, 0)
    stop = rtol * rtol * bb
    rr = bb
    it = 0
    while it < maxit and rr > stop:
        _apply_blocks(n, pairs, has_ind, dg, p, q, bounds, cnt, buf, nblk < 0)
        for c in prange(nblk):
            pqb = 0.0
            for i in range(bounds[c], bounds[c + 1]):
                pqb += p[i] * q[i]
            part[c, 0] = pqb
        pq = block_sum(part, 0)
        if not (pq > 0.0):  # p = 0 in floating point: nothing left to reduce
            break
        alpha = rz / pq
        for c in prange(nblk):
            rrb = 0.0
            rzb = 0.0
            for i in range(bounds[c], bounds[c + 1]):
                x[i] += alpha * p[i]
                r[i] -= alpha * q[i]
                rrb += r[i] * r[i]
                z[i] = dinv[i] * r[i]
                rzb += r[i] * z[i]
            part[c, 1] = rrb
            part[c, 2] = rzb
        rr = block_sum(part, 1)
        rz_new = block_sum(part, 2)
        beta = rz_new / rz
        rz = rz_new
        for c in prange(nblk):
            for i in range(bounds[c], bounds[c + 1]):
                p[i] = z[i] + beta * p[i]
        it += 1
    return it, math.sqrt(rr / bb)


@njit(cache=True, error_model="numpy")
def pair_heat_rows(i0, i1, n, pairs, has_ind, T, f):
    """The heat over f seconds of the pairs of the rows [i0, i1) at the temperatures T,
    sum |H_ij (T_j - T_i)| f split into its direct and indirect (Hd and Hi) parts; a pair with
    a ghost (n <= j < len(T): listed on its owner's rank too) counts one half, so that the sum
    over the ranks counts each pair once. Returns (direct, indirect) in J."""
    nb, nnb, Hd, Hi = pairs
    ng = T.shape[0]
    ed = 0.0
    ei = 0.0
    for i in range(i0, i1):
        for s in range(nnb[i]):
            j = nb[i, s]
            if j >= ng:
                continue
            hd = Hd[i, s]
            hi = Hi[i, s] if has_ind else 0.0
            h = hd + hi
            if h <= 0.0:
                continue
            e = abs(h * (T[j] - T[i])) * (f if j < n else 0.5 * f)
            ed += e * hd / h
            ei += e * hi / h
    return ed, ei


@njit(cache=True, error_model="numpy", parallel=True)
def pair_heat_blocks(n, pairs, has_ind, T, f, nblk):
    """:func:`pair_heat_rows` of the rows [0, n) on ``nblk`` blocks of rows at once: each block's
    sums apart, then added in block order. Returns (direct, indirect) in J."""
    bounds = block_bounds(n, n, nblk)
    part = np.zeros((nblk, 2))
    for c in prange(nblk):
        ed, ei = pair_heat_rows(bounds[c], bounds[c + 1], n, pairs, has_ind, T, f)
        part[c, 0] = ed
        part[c, 1] = ei
    return block_sum(part, 0), block_sum(part, 1)


@njit(cache=True, error_model="numpy")
def dot(a, b):
    """sum_i a_i b_i in row order (the same sum on every call: a restart continues bit for bit)."""
    s = 0.0
    for i in range(a.shape[0]):
        s += a[i] * b[i]
    return s


@njit(cache=True, error_model="numpy")
def cg_product(n, nb, nnb, Hd, Hi, has_ind, dg, p, q):
    """One rank's part of a conjugate-gradient iteration under MPI (dem.thermal.implicit_mpi):
    q = (diag(dg) + L) p over the owned rows [0, n) (the ghosts' entries of p current), and the
    rank's share of p.q."""
    laplacian_apply(n, nb, nnb, Hd, Hi, has_ind, dg, p, q)
    s = 0.0
    for i in range(n):
        s += p[i] * q[i]
    return s


@njit(cache=True, error_model="numpy")
def cg_update(n, alpha, x, p, r, q, z, dinv):
    """x += alpha p, r -= alpha q, z = dinv r over the rows [0, n): the rank's shares of r.r and
    r.z (dem.thermal.implicit_mpi)."""
    rr = 0.0
    rz = 0.0
    for i in range(n):
        x[i] += alpha * p[i]
        r[i] -= alpha * q[i]
        z[i] = dinv[i] * r[i]
        rr += r[i] * r[i]
        rz += r[i] * z[i]
    return rr, rz


@njit(cache=True, error_model="numpy")
def cg_direction(n, beta, p, z):
    """p = z + beta p over the rows [0, n)."""
    for i in range(n):
        p[i] = z[i] + beta * p[i]
