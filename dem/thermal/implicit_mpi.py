"""The implicit heat steps (backward Euler, TR-BDF2) of a frozen packing on several MPI ranks.

The same step as dem.thermal.heat._implicit_step / _trbdf2_step, with the linear system
(dem.thermal.implicit, eq. 1) split over the ranks by rows: a rank holds the rows of its owned
particles and the pairs they are in, a pair of an owned particle and a ghost on both ranks
(each adds its share to its own row). The conjugate gradients need per iteration the ghosts'
entries of the search direction (one message per neighbour rank, 8 bytes a ghost:
ParallelDomain.forward_vector) and two global sums (p.Ap, then r.r and r.z together: one
Allreduce each, of one and of two float64), so every rank takes the same steps to the same
tolerance, on the norms of the whole system: the temperatures are those of one process to
the solver's tolerance (CG_RTOL relative to the heat rates) whatever the rank count, and the
steady state is exact (d = 0 at Q(T) = 0) as on one process. The assembly and the totals are
the compiled functions of the serial step, on the owned rows with the ghosts' temperatures.
"""
import numpy as np

from ..step import FP
from .heat import _implicit_assemble, _implicit_totals, _wall_source_shift, has_wall_tables, trbdf2_coefficients, TI
from .implicit import CG_RTOL, cg_direction, cg_product, cg_update, dot, laplacian_diagonal


def pcg(par, m, n, C, has_ind, dg, b, x):
    """x = (diag(dg) + L)^-1 b over the ranks (rows [0, m) owned, [m, n) ghosts; b, dg of the
    owned rows, x of every row): the Jacobi-preconditioned conjugate gradients of
    dem.thermal.implicit.jacobi_pcg with the ghosts' entries of the direction sent before each
    product and the dot products summed over the ranks. Stops at ||r|| <= CG_RTOL ||b|| (norms
    of the whole system) or after 10 M + 100 iterations (M particles in all). The ghost
    entries of x are sent at the end. Counts the solve, its iterations and the bytes sent in
    ``par`` (cg_solves, cg_iterations, cg_bytes). Returns (iterations, ||r|| / ||b||)."""
    nb, nnb, Hd, Hi = C.nb, C.nnb, C.Hd, C.Hi
    x[:] = 0.0
    bb, mglob = par.sums(dot(b, b), m)
    if bb == 0.0:
        return 0, 0.0
    dinv = np.empty(m)
    laplacian_diagonal(m, n, nb, nnb, Hd, Hi, has_ind, dg, dinv)
    dinv = 1.0 / dinv
    r = b.copy()
    z = dinv * r
    p = np.zeros(n)
    p[:m] = z
    q = np.empty(m)
    (rz,) = par.sums(dot(r, z))
    stop = CG_RTOL * CG_RTOL * bb
    rr = bb
    it = 0
    sent = 0
    maxit = 10 * int(mglob) + 100
    while it < maxit and rr > stop:
        sent += par.forward_vector(p)
        (pq,) = par.sums(cg_product(m, nb, nnb, Hd, Hi, has_ind, dg, p, q))
        if not (pq > 0.0):  # p = 0 in floating point (on every rank: the sum is global)
            break
        rr, rz_new = par.sums(*cg_update(m, rz / pq, x, p, r, q, z, dinv))
        cg_direction(m, rz_new / rz, p, z)
        rz = rz_new
        it += 1
    sent += par.forward_vector(x)
    par.cg_solves += 1
    par.cg_iterations += it
    par.cg_bytes += sent
    return it, float(np.sqrt(rr / bb))


def _bad(T, m):
    """The first owned row with a non-finite or non-positive temperature, or -1."""
    bad = np.flatnonzero(~(T[:m] > 0.0) | ~np.isfinite(T[:m]))
    return int(bad[0]) if bad.size else -1


def heat_step(par, st, t):
    """One implicit heat step (thermal.integrator "implicit" or "trbdf2") of this rank's owned
    rows at the end time t, the ghosts' temperatures current (sent before the call). Returns the
    first owned row with a bad temperature, or -1. Collective: every rank calls it."""
    P, C, W, TB, prm = st.bundles()
    m = st.n_owned
    n = st.n
    dt = float(prm.fp[FP.dt])
    has_ind = C.Hi.shape[0] == n
    if P.qmech.shape[0] == n:   # [output] heat_by_mechanism: this step's rates by mechanism
        P.qmech[:] = 0.0
    T, cinv, Q = P.temperature, P.inv_heat_capacity, P.heat_rate
    b = np.zeros(m)
    dg = np.empty(m)
    if prm.thi[TI.integ] == 2:   # backward Euler (heat._implicit_step)
        links = _implicit_assemble(P, C, W, TB, prm, m, dt, dt, t, has_ind, b, dg)
        d = np.empty(n)
        pcg(par, m, n, C, has_ind, dg, b, d)
        T[:n] += d   # (the ghosts too: the same bits as their owners')
        Q[:m] = d[:m] / (cinv[:m] * dt)
        _implicit_totals(P, C, W, prm, m, T[:n], d[:m], t, (dt, 1.0 / dt), has_ind, links, 1)
        return _bad(T, m)
    # TR-BDF2 (heat._trbdf2_step)
    dt1, w, a, c2, t0, tg = trbdf2_coefficients(dt, t)
    links = _implicit_assemble(P, C, W, TB, prm, m, dt1, dt, t, has_ind, b, dg)
    rhs = 2.0 * b
    if has_wall_tables(W):
        _wall_source_shift(P, W, m, t0, t, rhs)
        _wall_source_shift(P, W, m, tg, t, rhs)
    d1 = np.empty(n)
    pcg(par, m, n, C, has_ind, dg, rhs, d1)
    ci = 1.0 / cinv[:m]
    dg += ci / w - ci / dt1
    rhs = b + ci * d1[:m] * c2
    d2 = np.empty(n)
    pcg(par, m, n, C, has_ind, dg, rhs, d2)
    Tn = T[:n].copy()
    Tg = Tn + d1
    T[:n] += d2
    Q[:m] = d2[:m] / (cinv[:m] * dt)
    _implicit_totals(P, C, W, prm, m, Tn, np.zeros(m), t0, (a, 1.0 / dt), has_ind, links, 1)
    _implicit_totals(P, C, W, prm, m, Tg, d1[:m], tg, (a, 1.0 / dt), has_ind, links, 1)
    _implicit_totals(P, C, W, prm, m, T[:n], d2[:m], t, (w, 1.0 / dt), has_ind, links, 1)
    return _bad(T, m)
