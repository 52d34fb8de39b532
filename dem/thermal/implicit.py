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
few vectors. The functions below are pure (they write only into the arrays they are
given) and compiled once (no literal-argument specialisations).
"""
import math

import numpy as np
from numba import njit

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
    half list): (L x)_i = sum_j H_ij (x_i - x_j). Pairs with j >= n are ignored (ghosts)."""
    for i in range(n):
        y[i] = dg[i] * x[i]
    for i in range(n):
        xi = x[i]
        acc = 0.0
        for s in range(nnb[i]):
            j = nb[i, s]
            if j >= n:
                continue
            h = Hd[i, s] + (Hi[i, s] if has_ind else 0.0)
            if h <= 0.0:
                continue
            q = h * (xi - x[j])
            acc += q
            y[j] -= q
        y[i] += acc


@njit(cache=True, error_model="numpy")
def laplacian_diagonal(n, nb, nnb, Hd, Hi, has_ind, dg, out):
    """out = dg + diag(L): dg_i plus the sum of particle i's pair conductances (the Jacobi
    preconditioner of diag(dg) + L)."""
    for i in range(n):
        out[i] = dg[i]
    for i in range(n):
        for s in range(nnb[i]):
            j = nb[i, s]
            if j >= n:
                continue
            h = Hd[i, s] + (Hi[i, s] if has_ind else 0.0)
            if h <= 0.0:
                continue
            out[i] += h
            out[j] += h


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
    laplacian_diagonal(n, nb, nnb, Hd, Hi, has_ind, dg, dinv)
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
