"""Per-step heat kernels: the thermal update over stored conductances, local porosity.

Conductances are computed where the geometry is (in the contact loop of
dem.step.compute_forces, or once for frozen packings) and stored per neighbour slot:
Hd (direct) and Hi (indirect) per pair, Hw per particle-wall candidate (for a
fixed-heat-flux wall Hw holds the contact area instead). ``heat_step`` then advances
the temperatures with either

* ``euler``: T += dt Q / (m c), Q the sum of all heat rates (the references' scheme;
  stable for dt below the network limit min_i m_i c_i / sum_j H_ij), or
* ``implicit``: backward Euler over the whole conductance network,
  (C/dt + K + L)(T^{n+1} - T^n) = Q(T^n), solved by Jacobi-preconditioned conjugate
  gradients (dem.thermal.implicit; see _implicit_step), or
* ``trbdf2``: the second-order, L-stable TR-BDF2 (a trapezoidal stage, then BDF2) on the same
  network and solver, two solves a step, steady state exact at any step (_trbdf2_step), or
* ``exponential``: each pair (and each particle-reservoir link: fixed-temperature
  wall, convection) is advanced with its exact two-body solution
  dT = (T_j - T_i)(1 - exp(-H (1/C_i + 1/C_j) dt)) in sequence; explicit terms
  (generation, sources, fixed flux) are added after. Every update is a
  convex combination, so it is stable for any step, conserves sum(C T) exactly, and is
  exact for two bodies. Radiation is treated the same way, as an exact relaxation towards
  its environment temperature with the secant conductance eps sigma A (Te^2+T^2)(Te+T).
"""
import math

import numpy as np
from numba import njit, prange

from .convection import convection_conductance, nusselt_gas
from .radiation import (SIGMA_SB, radiation_accumulate, radiation_env_temperature, radiation_heat,
                        radiation_wall_weight, radiation_wall_accumulate, radiation_env_temperature_walls,
                        radiation_wall_omega, radiation_wall_rate)
from .registry import EMISSIVITY, KF, RHO_F, MU_F, PR, RAD_KRAUSE_2017
from .implicit import jacobi_pcg, jacobi_pcg_blocks, pair_heat_blocks, pair_heat_rows, CG_RTOL
from ..neighbors import pair_distance
from ..contact.walls import WF, WI, PLANE, MESH, wall_distance
from ..contact.mesh import mesh_caps, MMI
from ..blocks import add_buffered, block_bounds, cross_counts, kept_cross_counts
from ..schema import slots

# integer thermal parameters (Params.thi; -1: the model is off)
TI = slots("TI", (
    ("heat", "1: heat on"),
    ("direct", "direct conduction model (dem.thermal.registry)"),
    ("cr", "contact radius model (dem.thermal.contact_radius)"),
    ("corr", "contact radius correction"),
    ("indirect", "indirect conduction model"),
    ("conv", "convection model"),
    ("rad", "radiation model"),
    ("fric", "friction heat model (dem.thermal.generation)"),
    ("part", "friction heat partition model"),
    ("integ", "integrator: 0 euler, 1 exponential, 2 implicit, 3 trbdf2"),
    ("age", "1: contact age and impact speed are kept"),
    ("localpor", "1: the local porosity is measured at each neighbour build"),
    ("fused", "1: pairs and walls accumulated in the force loop (mechanics + euler)"),
    ("wrad", "1: a fixed-temperature wall with an emissivity takes part in the radiation"),
    ("cg_own", "1: parcels exchange heat by their own laws ([thermal] parcel_heat = \"own\", a comparison)"),
))
# float thermal parameters (Params.thf)
TF = slots("TF", (
    ("dfactor", "direct conduction factor"),
    ("radrange", "radiation range (radii)"),
    ("ct", "impact heat coefficient c_t"),
    ("cn", "impact heat coefficient c_n"),
    ("chi", "friction heat fraction chi"),
), size=8)
# run totals (Params.tot, J since the start; checkpointed as th_tot)
TOT = slots("TOT", (
    ("direct", "exchanged by direct conduction"),
    ("indirect", "exchanged by indirect conduction"),
    ("conv", "convection"),
    ("rad", "radiation (the walls' parts excluded)"),
    ("gen", "generation (friction, impacts)"),
    ("src", "sources"),
    ("wall", "through the walls"),
), size=8)
# the heat of each particle by mechanism ([output] heat_by_mechanism; the columns of P.qmech, W):
# what each mechanism gave it in the last step, as a rate; their sum is its heat_rate, and their
# sums over the particles are the run totals' increments over that step (direct and indirect:
# the pairs' net, zero in a closed set of particles; TOT counts |heat exchanged| instead)
QM = slots("QM", (
    ("direct", "direct conduction with the other particles"),
    ("indirect", "indirect conduction (gas gap) with the other particles"),
    ("wall", "the walls: conduction, gas gap, fixed flux, radiation to a radiating wall"),
    ("conv", "convection with the gas"),
    ("rad", "radiation with the other particles and the environment"),
    ("gen", "generation (friction, impacts)"),
    ("src", "sources"),
))
QM_SIZE = QM.SIZE
# wall thermal columns (Walls.wth)
WT = slots("WT", (
    ("cond", "condition: 0 adiabatic, 1 fixed temperature, 2 fixed flux"),
    ("t", "temperature (K)"),
    ("q", "heat flux (W/m^2)"),
    ("ntab", "length of the temperature table (0: constant)"),
    ("emis", "emissivity (radiation with the particles)"),
))


@njit(cache=True, error_model="numpy")
def wall_temperature(wth, wtab, w, t):
    """Wall temperature at time t (constant, or linear in a [time, T] table, held at the ends)."""
    nt = int(wth[w, WT.ntab])
    if nt == 0:
        return wth[w, WT.t]
    if t <= wtab[w, 0, 0]:
        return wtab[w, 0, 1]
    for k in range(nt - 1):
        if t <= wtab[w, k + 1, 0]:
            a = (t - wtab[w, k, 0]) / (wtab[w, k + 1, 0] - wtab[w, k, 0])
            return wtab[w, k, 1] + a * (wtab[w, k + 1, 1] - wtab[w, k, 1])
    return wtab[w, nt - 1, 1]


@njit(cache=True, error_model="numpy", inline="always")
def heat_cg(cg, thi):
    """The coarse-graining factors the heat laws scale by: ``cg`` (empty without parcels), or
    none when the scene asks for the parcels' own laws (thi[TI.cg_own], a comparison)."""
    if thi[TI.cg_own] == 1:
        return cg[:0]
    return cg


@njit(cache=True, error_model="numpy", inline="always")
def own_emissivity(tmat, mat, cg, i):
    """Particle i's emissivity in its own radiation, times its coarse-graining factor when the run
    has parcels: a parcel radiates as its cg^3 real particles, whose surface is cg^3 A_real =
    cg A_parcel (docs/models.md, "Coarse graining")."""
    e = tmat[mat[i], EMISSIVITY]
    if cg.shape[0] > 0:
        return e * cg[i]
    return e


@njit(cache=True, error_model="numpy")
def radiation_accumulators(rad, rows, n, T, r, mat, tmat, nb, nnb, rnear):
    """The radiation accumulators (acc0, acc1) [n] of every particle from its neighbours within
    the range (rnear) over the half list of rows [0, rows) (dem.thermal.radiation)."""
    acc0 = np.zeros(n)
    acc1 = np.zeros(n)
    for i in range(rows):
        for s in range(nnb[i]):
            if rnear[i, s]:
                j = nb[i, s]
                a0, a1 = radiation_accumulate(rad, acc0[i], acc1[i], T[j], tmat[mat[j], EMISSIVITY], r[j])
                acc0[i] = a0
                acc1[i] = a1
                a0, a1 = radiation_accumulate(rad, acc0[j], acc1[j], T[i], tmat[mat[i], EMISSIVITY], r[i])
                acc0[j] = a0
                acc1[j] = a1
    return acc0, acc1


@njit(cache=True, error_model="numpy", parallel=True)
def _radiation_accumulators_blocks(rad, n, nown, xcnt, T, r, mat, tmat, C, nblk):
    """:func:`radiation_accumulators` of every row on ``nblk`` blocks of rows at once
    (dem.blocks). A block adds each pair to its own rows and keeps what a pair gives a row of a
    other block in its own range of a buffer, added after in block and
    pair order: no two threads write one row, and the order of every sum is fixed by the block
    count (a row of a later block adds the earlier blocks' shares last: round-off against one
    thread, as in the interact phase). The ranges are the
    pairs across blocks that the interact phase kept for this list
    (``xcnt``, dem.blocks.kept_cross_counts: a superset of the pairs in range), else counted."""
    bounds = block_bounds(nown, n, nblk)
    cnt = _radiation_offsets(xcnt, n, nown, C, bounds)
    acc = (np.zeros(n), np.zeros(n))
    buf = (np.empty(cnt[nblk], np.int64), np.empty(cnt[nblk]), np.empty(cnt[nblk]))
    end = np.empty(nblk, np.int64)
    for b in prange(nblk):
        end[b] = _radiation_rows(rad, bounds[b], bounds[b + 1], acc, T, r, mat, tmat, C, buf, cnt[b])
    acc0, acc1 = acc
    xj, xa0, xa1 = buf
    # (a neighbour list changed without after_build or dem.state, if not)
    if not (add_buffered(acc0, xj, xa0, cnt, end) and add_buffered(acc1, xj, xa1, cnt, end)):
        raise RuntimeError("internal error: more pairs across blocks of rows in radiation range than "
                           "the list has (dem.thermal.heat._radiation_accumulators_blocks)")
    return acc0, acc1


@njit(cache=True, error_model="numpy")
def _radiation_offsets(xcnt, n, nown, C, bounds):
    """Each block's range of the buffer of :func:`_radiation_accumulators_blocks`: the pairs
    across blocks kept for this list, else those in radiation range, counted."""
    kept = kept_cross_counts(xcnt, n, nown, bounds.shape[0] - 1)
    if kept.shape[0] == bounds.shape[0]:
        return kept
    return cross_counts(C.nb, C.nnb, C.rnear, bounds)


@njit(cache=True, error_model="numpy")
def _radiation_rows(rad, i0, i1, acc, T, r, mat, tmat, C, buf, k):
    """The radiation accumulators of the pairs of rows [i0, i1) (see
    :func:`_radiation_accumulators_blocks`): a pair with j in [i0, i1) adds to both rows, another
    writes j's share at buf[k], k + 1, ... Returns the next free k."""
    nb, nnb, rnear = C.nb, C.nnb, C.rnear
    acc0, acc1 = acc
    xj, xa0, xa1 = buf
    for i in range(i0, i1):
        ai0 = acc0[i]
        ai1 = acc1[i]
        ti = T[i]
        ei = tmat[mat[i], EMISSIVITY]
        ri = r[i]
        for s in range(nnb[i]):
            if rnear[i, s]:
                j = nb[i, s]
                ai0, ai1 = radiation_accumulate(rad, ai0, ai1, T[j], tmat[mat[j], EMISSIVITY], r[j])
                if i0 <= j < i1:
                    a0, a1 = radiation_accumulate(rad, acc0[j], acc1[j], ti, ei, ri)
                    acc0[j] = a0
                    acc1[j] = a1
                elif k < xj.shape[0]:
                    a0, a1 = radiation_accumulate(rad, 0.0, 0.0, ti, ei, ri)
                    xj[k] = j
                    xa0[k] = a0
                    xa1[k] = a1
                    k += 1
                else:
                    k += 1  # no room: counted, for the caller's check
        acc0[i] = ai0
        acc1[i] = ai1
    return k


@njit(cache=True, error_model="numpy")
def wall_radiation_now(P, C, W, TB, prm, nown, t, k, out):
    """out[i] = the radiation wall k gives owned particle i now (W; 0 out of reach), at the
    current temperatures: the part of the heat step's radiation (heat_step) that is wall k's."""
    rad = prm.thi[TI.rad]
    if rad < 0 or prm.thi[TI.wrad] != 1:
        return
    T, r, mat, x, por, tf = P.temperature, P.radius, P.material, P.position, P.por, P.tf
    cgv = heat_cg(P.cg, prm.thi)
    wth, wtab, tmat = W.wth, W.wtab, TB.tmat
    n = T.shape[0]
    acc0, acc1 = radiation_accumulators(rad, n, n, T, r, mat, tmat, C.nb, C.nnb, C.rnear)
    wgt = np.zeros((nown, wth.shape[0]))
    aw0 = np.zeros(nown)
    aw1 = np.zeros(nown)
    wall_radiation_weights(rad, 0, nown, P, W, t, prm.thf[TF.radrange], wgt, aw0, aw1)
    for i in range(nown):
        if wgt[i, k] <= 0.0:
            continue
        te = radiation_env_temperature_walls(rad, acc0[i], acc1[i], aw0[i], aw1[i], por[i], tf[i], T[i])
        om = radiation_wall_omega(rad, wgt[i, k], acc1[i], aw1[i])
        out[i] = radiation_wall_rate(rad, own_emissivity(tmat, mat, cgv, i), r[i], T[i], te, om,
                                     wall_temperature(wth, wtab, k, t))


@njit(cache=True, error_model="numpy")
def wall_radiation_weights(rad, i0, i1, P, W, t, srange, wgt, aw0, aw1):
    """The radiating walls ``W`` (dem.schema Walls) in each sphere of influence
    (dem.thermal.radiation, walls): for rows [i0, i1) of the particles ``P``, wgt[i, w] the weight
    of wall row w (fixed temperature, emissivity > 0, its surface within srange r_i of the centre)
    and the wall accumulators (aw0, aw1) of particle i. A mesh wall is its tangent plane at the
    nearest of the particle's contact records (P.mcon, written by dem.contact.mesh.mesh_contacts
    out to srange r_i when a wall radiates), on its first row (the others weigh nothing): one
    surface, as a plane."""
    wf, wi, wth, wtab, mmi = W.wf, W.wi, W.wth, W.wtab, W.mmi
    x, r, mcon = P.position, P.radius, P.mcon
    nw = wth.shape[0]
    for i in range(i0, i1):
        s = srange * r[i]
        for w in range(nw):
            ew = wth[w, WT.emis]
            if ew <= 0.0 or wth[w, WT.cond] != 1.0:
                continue
            if wi[w, WI.type] == MESH:
                m = wi[w, WI.mesh]
                if w != mmi[m, MMI.row0]:
                    continue
                d = math.inf
                for q in range(mmi[m, MMI.nslot]):
                    d = min(d, mcon[i, w + q, 0])
            else:
                d, _, _, _ = wall_distance(wf, wi, w, x[i, 0], x[i, 1], x[i, 2], t)
            g = radiation_wall_weight(rad, ew, d, s)
            if g > 0.0:
                wgt[i, w] = g
                a0, a1 = radiation_wall_accumulate(rad, aw0[i], aw1[i], g, wall_temperature(wth, wtab, w, t))
                aw0[i] = a0
                aw1[i] = a1


@njit(cache=True, error_model="numpy")
def wall_radiation_parts(rad, eps_i, R_i, T_i, T_e, acc1_i, aw1_i, wgt_i, W, rec, t, scale):
    """Add each wall's part of particle i's radiation rate (radiation_wall_rate), times
    ``scale``, to the walls' records ``rec`` = (wtot, wrad): W.wtot and W.wrad of the walls ``W``
    (dem.schema Walls), or a block's share of them. Returns the sum of the parts (W, before the
    scale)."""
    wth, wtab = W.wth, W.wtab
    wtot, wrad = rec
    q = 0.0
    for w in range(wgt_i.shape[0]):
        g = wgt_i[w]
        if g <= 0.0:
            continue
        om = radiation_wall_omega(rad, g, acc1_i, aw1_i)
        qw = radiation_wall_rate(rad, eps_i, R_i, T_i, T_e, om, wall_temperature(wth, wtab, w, t))
        wtot[w] += qw * scale
        wrad[w] += qw * scale
        q += qw
    return q


@njit(cache=True, error_model="numpy")
def explicit_heat(i0, i1, n, x, r, qgen, qsrc, srcbox, dt, Q, tot, qm):
    """Add the explicit heat rates of rows [i0, i1) to Q (W): friction/impact generation qgen,
    per-particle sources qsrc, and the volumetric source boxes of srcbox (rows
    [xlo, ylo, zlo, xhi, yhi, zhi, W/m3]); their energies over dt go to the run totals
    (TOT.gen, TOT.src), and their rates to the columns QM.gen, QM.src of ``qm`` when it has n
    rows (P.qmech). qgen / qsrc are empty (not of n rows) when off. Serves every integrator."""
    eg = 0.0
    es = 0.0
    has_gen = qgen.shape[0] == n
    has_src = qsrc.shape[0] == n
    split = qm.shape[0] == n
    nbox = srcbox.shape[0]
    for i in range(i0, i1):
        if has_gen:
            Q[i] += qgen[i]
            eg += qgen[i] * dt
            if split:
                qm[i, QM.gen] += qgen[i]
        if has_src:
            Q[i] += qsrc[i]
            es += qsrc[i] * dt
            if split:
                qm[i, QM.src] += qsrc[i]
        for k in range(nbox):
            if (srcbox[k, 0] <= x[i, 0] <= srcbox[k, 3] and srcbox[k, 1] <= x[i, 1] <= srcbox[k, 4]
                    and srcbox[k, 2] <= x[i, 2] <= srcbox[k, 5]):
                qq = srcbox[k, 6] * 4.0 / 3.0 * math.pi * r[i] ** 3
                Q[i] += qq
                es += qq * dt
                if split:
                    qm[i, QM.src] += qq
    tot[TOT.gen] += eg
    tot[TOT.src] += es


@njit(cache=True, error_model="numpy", no_cpython_wrapper=True, no_cfunc_wrapper=True)
def heat_step(P, C, W, TB, prm, n, nown, dt, t, nblk):
    """Advance the temperatures of rows [0, nown) by dt (rows [nown, n) are ghosts: another
    rank advances them). Q receives the net heat rate of each particle (W).

    A pair with a ghost is on two ranks: Euler takes its rate from the temperatures at the
    start of the step on both (antisymmetric, so conservative, as in a serial run). The
    exponential update exchanges e = H (T_j - T_i) phi over such a pair from the
    start-of-step temperatures, phi = (1 - exp(-lam dt)) / lam with lam the larger of the
    two particles' cross-rank rates lam_i = sum_cross H / C_i (work[:, 1], filled for ghosts
    by the caller): both ranks compute the same e (conservative), phi -> dt for small steps,
    and for any step each particle moves by a convex combination (bounded).

    The links of each particle to its reservoirs (walls, gas, radiation environment) and the
    explicit terms are updated row by row on ``nblk`` blocks of rows at once (dem.blocks;
    _heat_blocks): a row's arithmetic is the same on any number of threads; the run totals are
    summed per block, then in block order. The radiation accumulators are summed on the blocks
    too (_radiation_accumulators_blocks: their order, and so the temperatures of a run with
    radiation, depend on the thread count at round-off). The pair sweeps stay serial.
    P, C, W, TB, prm: the bundles of dem.schema (particles, pairs, walls, tables, parameters)."""
    T, cinv, Q = P.temperature, P.inv_heat_capacity, P.heat_rate
    qgen, qsrc, work = P.qgen, P.qsrc, P.work
    nb, nnb, Hd, Hi, rnear = C.nb, C.nnb, C.Hd, C.Hi, C.rnear
    wth, tmat = W.wth, TB.tmat
    thi, tot, srcbox = prm.thi, prm.tot, prm.srcbox
    integ = thi[TI.integ]
    has_ind = Hi.shape[0] == n
    qm = P.qmech
    if qm.shape[0] == n:   # [output] heat_by_mechanism: this step's rates by mechanism (QM)
        for i in range(n):
            for k in range(QM_SIZE):
                qm[i, k] = 0.0
    rdt = 1.0 / dt
    if integ == 2:
        return _implicit_step(P, C, W, TB, prm, nown, dt, t, has_ind, nblk)
    if integ == 3:
        return _trbdf2_step(P, C, W, TB, prm, nown, dt, t, has_ind, nblk)
    conv = thi[TI.conv]
    rad = thi[TI.rad]
    fused = thi[TI.fused] == 1
    if (fused and integ == 0 and conv < 0 and rad < 0 and qgen.shape[0] != n and qsrc.shape[0] != n
            and srcbox.shape[0] == 0):
        # conduction only, already summed in the force loop: one pass
        bad = -1
        for i in range(nown):
            T[i] += dt * Q[i] * cinv[i]
            if not (T[i] > 0.0) or not math.isfinite(T[i]):
                bad = i
        return bad
    for i in range(n):
        work[i, 0] = T[i]
        if not fused:
            Q[i] = 0.0
    # ---- particle pairs (already in Q when fused into the force loop). The exponential
    # update sweeps the pairs forward over dt/2 and backward over dt/2 around the
    # particle-reservoir links (Strang splitting: second order, so the steady state of a
    # conduction chain is off by O(dt^2) only; Euler's steady state is exact).
    expo = integ != 0
    fwd = np.int64(1)  # the sweep direction as a run-time value: one compiled _pair_sweep (a literal
    # argument compiles one form per constant); so are row 0 of _link_rows and _finish_rows (the
    # blocks call them with run-time rows) and the stages of _heat_blocks (fwd - 1 is 0)
    hs = np.zeros(n if expo else 0)    # sum of a particle's reservoir conductances (W/K)
    hts = np.zeros(n if expo else 0)   # and of conductance x reservoir temperature (W)
    if expo and nown < n and not fused:
        _cross_exchange(nown, dt, T, cinv, nb, nnb, Hd, Hi, has_ind, work, tot, qm)
    if not fused:
        if integ == 0:
            _pair_sweep(nown, dt, T, cinv, Q, C, has_ind, integ, fwd, tot, qm, rdt)
        else:
            _pair_sweep(nown, 0.5 * dt, T, cinv, Q, C, has_ind, integ, fwd, tot, qm, rdt)
    # ---- radiation environment (from the temperatures after the first pair half-sweep)
    if rad >= 0 and nblk > 1:
        acc0, acc1 = _radiation_accumulators_blocks(rad, n, nown, prm.xcnt, T, P.radius, P.material, tmat, C, nblk)
    elif rad >= 0:
        acc0, acc1 = radiation_accumulators(rad, n, n, T, P.radius, P.material, tmat, nb, nnb, rnear)
    else:
        acc0 = np.zeros(0)
        acc1 = np.zeros(0)
    # radiating walls (fixed temperature, emissivity > 0) in the spheres of influence
    wr = rad >= 0 and thi[TI.wrad] == 1
    wgt = np.zeros((nown if wr else 0, wth.shape[0]))
    aw0 = np.zeros(nown if wr else 0)
    aw1 = np.zeros(nown if wr else 0)
    hconv = np.zeros(n if conv >= 0 else 0)
    hrad = np.zeros(n if rad >= 0 else 0)
    tenv = np.zeros(n if rad >= 0 else 0)
    links = (acc0, acc1, wgt, aw0, aw1, hs, hts, hconv, hrad, tenv)
    # ---- reservoir links, row by row (_link_rows)
    if nblk == 1:
        _link_rows(P, W, TB, prm, fwd - 1, nown, dt, t, fused, expo, links, (tot, W.wtot, W.wgap, W.wrad))
    else:
        _heat_blocks(P, W, TB, prm, nown, dt, t, fused, expo, links, nblk, fwd - 1)  # stage 0
    if not fused and expo:
        _pair_sweep(nown, 0.5 * dt, T, cinv, Q, C, has_ind, integ, -fwd, tot, qm, rdt)
    # ---- explicit terms (generation, sources, fixed fluxes), the update and its guard, row by row
    if nblk == 1:
        return _finish_rows(P, prm, fwd - 1, nown, n, dt, expo, tot)
    return _heat_blocks(P, W, TB, prm, nown, dt, t, fused, expo, links, nblk, fwd)  # stage 1


@njit(cache=True, error_model="numpy")
def _link_rows(P, W, TB, prm, i0, i1, dt, t, fused, expo, links, rec):
    """The links of the rows [i0, i1) to their reservoirs: fixed-temperature walls, gas
    (convection), radiation environment (heat_step). Euler: explicit rates into Q. Exponential:
    all links of a particle together relax it exactly towards their conductance-weighted
    temperature (steady state exact, bounded, any step); radiation enters with its secant
    conductance eps sigma A (Te^2+T^2)(Te+T). Reads and writes rows [i0, i1) only (``links``:
    heat_step's per-row arrays); the run totals and the walls' records go to ``rec`` = (tot,
    wtot, wgap, wrad): prm.tot and W's own records on one block, the block's share else."""
    tot, wtot, wgap, wrad = rec
    T, cinv, Q, v, r, x, mat = (P.temperature, P.inv_heat_capacity, P.heat_rate, P.velocity, P.radius,
                                P.position, P.material)
    wnb, wnn, Hw, tf, uf, por = P.wnb, P.wnn, P.Hw, P.tf, P.uf, P.por
    wth, wtab, tmat, gas = W.wth, W.wtab, TB.tmat, TB.gas
    Hwg, cgv = P.Hwg, heat_cg(P.cg, prm.thi)
    has_wg = Hwg.shape[0] == T.shape[0]
    thi = prm.thi
    conv = thi[TI.conv]
    rad = thi[TI.rad]
    wr = rad >= 0 and thi[TI.wrad] == 1
    acc0, acc1, wgt, aw0, aw1, hs, hts, hconv, hrad, tenv = links
    qm = P.qmech
    split = qm.shape[0] == T.shape[0]
    rdt = 1.0 / dt
    if wr:
        wall_radiation_weights(rad, i0, i1, P, W, t, prm.thf[TF.radrange], wgt, aw0, aw1)
    if not fused:
        for i in range(i0, i1):
            for q in range(wnn[i]):
                h = Hw[i, q]
                if h <= 0.0:
                    continue
                w = wnb[i, q]
                cond = wth[w, WT.cond]
                if cond == 1.0:
                    tw = wall_temperature(wth, wtab, w, t)
                    if expo:
                        hs[i] += h
                        hts[i] += h * tw
                        continue
                    qq = h * (tw - T[i])
                    if has_wg:
                        wgap[w] += Hwg[i, q] * (tw - T[i]) * dt
                elif cond == 2.0:
                    qq = h * wth[w, WT.q]  # fixed flux: explicit in both schemes
                else:
                    continue
                Q[i] += qq
                wtot[w] += qq * dt
                tot[TOT.wall] += qq * dt
                if split:
                    qm[i, QM.wall] += qq
    if conv >= 0:
        _convection_rows(i0, i1, v, r, cgv, uf, por, gas, conv, hconv)
        ec = 0.0
        for i in range(i0, i1):
            h = hconv[i]
            if expo:
                hs[i] += h
                hts[i] += h * tf[i]
            else:
                qq = h * (tf[i] - T[i])
                Q[i] += qq
                ec += qq * dt
                if split:
                    qm[i, QM.conv] += qq
        tot[TOT.conv] += ec
    if rad >= 0:
        er = 0.0
        for i in range(i0, i1):
            walls_i = wr and aw1[i] > 0.0
            if walls_i:
                te = radiation_env_temperature_walls(rad, acc0[i], acc1[i], aw0[i], aw1[i], por[i], tf[i], T[i])
            else:
                te = radiation_env_temperature(rad, acc0[i], acc1[i], por[i], tf[i], T[i])
            eps_i = own_emissivity(tmat, mat, cgv, i)
            if expo:
                ti = T[i]
                h = eps_i * SIGMA_SB * 4.0 * math.pi * r[i] * r[i] * (te * te + ti * ti) * (te + ti)
                hrad[i] = h
                tenv[i] = te
                hs[i] += h
                hts[i] += h * te
            else:
                qq = radiation_heat(eps_i, r[i], te, T[i])
                Q[i] += qq
                qw = 0.0   # the walls' parts go to their records, the rest to TOT.rad
                if walls_i:
                    qw = wall_radiation_parts(rad, eps_i, r[i], T[i], te, acc1[i], aw1[i], wgt[i], W,
                                              (wtot, wrad), t, dt)
                    tot[TOT.wall] += qw * dt
                er += (qq - qw) * dt
                if split:
                    qm[i, QM.rad] += qq - qw
                    qm[i, QM.wall] += qw
        tot[TOT.rad] += er
    if expo:
        for i in range(i0, i1):
            if hs[i] <= 0.0:
                continue
            ti = T[i]
            tstar = hts[i] / hs[i]
            tn = tstar + (ti - tstar) * math.exp(-hs[i] * cinv[i] * dt)
            e = (tn - ti) / cinv[i]
            T[i] = tn
            # share of each link: proportional to its rate h_k (T_k - T_i) at the start
            den = hts[i] - hs[i] * ti
            if den == 0.0:
                continue
            f = e / den
            if not fused:
                for q in range(wnn[i]):
                    w = wnb[i, q]
                    if Hw[i, q] > 0.0 and wth[w, WT.cond] == 1.0:
                        dtw = wall_temperature(wth, wtab, w, t) - ti
                        ew = f * Hw[i, q] * dtw
                        wtot[w] += ew
                        tot[TOT.wall] += ew
                        if split:
                            qm[i, QM.wall] += ew * rdt
                        if has_wg:
                            wgap[w] += f * Hwg[i, q] * dtw
            if conv >= 0:
                tot[TOT.conv] += f * hconv[i] * (tf[i] - ti)
                if split:
                    qm[i, QM.conv] += f * hconv[i] * (tf[i] - ti) * rdt
            if rad >= 0:
                if wr and aw1[i] > 0.0:
                    qw = wall_radiation_parts(rad, own_emissivity(tmat, mat, cgv, i), r[i], ti, tenv[i], acc1[i],
                                              aw1[i], wgt[i], W, (wtot, wrad), t, f)
                    tot[TOT.wall] += f * qw
                    tot[TOT.rad] += f * (hrad[i] * (tenv[i] - ti) - qw)
                    if split:
                        qm[i, QM.wall] += f * qw * rdt
                        qm[i, QM.rad] += f * (hrad[i] * (tenv[i] - ti) - qw) * rdt
                else:
                    tot[TOT.rad] += f * hrad[i] * (tenv[i] - ti)
                    if split:
                        qm[i, QM.rad] += f * hrad[i] * (tenv[i] - ti) * rdt


@njit(cache=True, error_model="numpy", parallel=True)
def _heat_blocks(P, W, TB, prm, nown, dt, t, fused, expo, links, nblk, stage):
    """A stage of heat_step on ``nblk`` blocks of the owned rows at once: 0 the links
    (:func:`_link_rows`), 1 the explicit heat, the update and the guard (:func:`_finish_rows`).
    Each block's totals and wall records are kept apart, then added in block order
    (deterministic for a thread count). Returns the first bad row of the first block that has
    one (the same row as on one thread), or -1. (One parallel function for both stages: each
    costs seconds of compile on the bundles.)"""
    n = P.temperature.shape[0]
    bounds = block_bounds(nown, nown, nblk)
    tb = np.zeros((nblk, prm.tot.shape[0]))
    wtb = np.zeros((nblk, W.wtot.shape[0]))
    wgb = np.zeros((nblk, W.wgap.shape[0]))
    wrb = np.zeros((nblk, W.wrad.shape[0]))
    bad = np.full(nblk, -1, np.int64)
    for b in prange(nblk):
        if stage == 0:
            _link_rows(P, W, TB, prm, bounds[b], bounds[b + 1], dt, t, fused, expo, links,
                       (tb[b], wtb[b], wgb[b], wrb[b]))
        else:
            bad[b] = _finish_rows(P, prm, bounds[b], bounds[b + 1], n, dt, expo, tb[b])
    _add_block_records(prm.tot, W.wtot, W.wgap, W.wrad, tb, wtb, wgb, wrb)
    for b in range(nblk):
        if bad[b] >= 0:
            return bad[b]
    return -1


@njit(cache=True, error_model="numpy")
def _add_block_records(tot, wtot, wgap, wrad, tb, wtb, wgb, wrb):
    """Add the blocks' totals and wall records, in block order."""
    for b in range(tb.shape[0]):
        for k in range(tot.shape[0]):
            tot[k] += tb[b, k]
        for k in range(wtot.shape[0]):
            wtot[k] += wtb[b, k]
        for k in range(wgap.shape[0]):
            wgap[k] += wgb[b, k]
        for k in range(wrad.shape[0]):
            wrad[k] += wrb[b, k]


@njit(cache=True, error_model="numpy")
def _finish_rows(P, prm, i0, i1, n, dt, expo, tot):
    """The end of heat_step for rows [i0, i1): the explicit heat (generation, sources, fixed
    fluxes) and the temperature update, then the guard: the first of these rows with a
    non-finite or non-positive temperature, or -1."""
    T, cinv, Q, x, r, work = P.temperature, P.inv_heat_capacity, P.heat_rate, P.position, P.radius, P.work
    if expo:
        for i in range(i0, i1):
            work[i, 2] = Q[i]  # explicit wall flux so far
            Q[i] = 0.0
    explicit_heat(i0, i1, n, x, r, P.qgen, P.qsrc, prm.srcbox, dt, Q, tot, P.qmech)
    if not expo:
        for i in range(i0, i1):
            T[i] += dt * Q[i] * cinv[i]
    else:
        for i in range(i0, i1):
            T[i] += dt * (Q[i] + work[i, 2]) * cinv[i]
            Q[i] = (T[i] - work[i, 0]) / (cinv[i] * dt)
    for i in range(i0, i1):
        if not (T[i] > 0.0) or not math.isfinite(T[i]):
            return i
    return -1


@njit(cache=True, error_model="numpy")
def _implicit_assemble(P, C, W, TB, prm, m, dt_diag, dt, t, has_ind, b, dg):
    """The linear system of an implicit heat step of the rows [0, m) (every row owned):
    b = Q(T^n), the net heat rate of each particle at the start of the step with the
    fixed-temperature walls at time t (W), and dg = C/dt_diag + K (W/K), K the conductances
    of the reservoir links (fixed-temperature walls, gas convection h A, the radiation
    tangent 4 eps sigma A T_i^3). The explicit heat (fixed wall fluxes, generation, sources)
    is in b and its energy over dt goes to the totals. Returns the link data the totals
    need (_implicit_totals): (hconv, qrad, krad, wgt, aw1, qw, om)."""
    T, cinv, v, r, x, mat = P.temperature, P.inv_heat_capacity, P.velocity, P.radius, P.position, P.material
    wnb, wnn, Hw, tf, uf, por, qgen, qsrc = P.wnb, P.wnn, P.Hw, P.tf, P.uf, P.por, P.qgen, P.qsrc
    nb, nnb, Hd, Hi, rnear = C.nb, C.nnb, C.Hd, C.Hi, C.rnear
    wth, wtab, wtot, tmat, gas = W.wth, W.wtab, W.wtot, TB.tmat, TB.gas
    thi, tot, srcbox = prm.thi, prm.tot, prm.srcbox
    conv = thi[TI.conv]
    rad = thi[TI.rad]
    n = T.shape[0]
    cgv = heat_cg(P.cg, thi)
    for i in range(m):
        dg[i] = 1.0 / (cinv[i] * dt_diag)
    # pairs (a pair with a ghost, j >= m: to row i only, its owner's rank adds the other share)
    for i in range(m):
        ti = T[i]
        for s in range(nnb[i]):
            j = nb[i, s]
            if j >= n:
                continue
            h = Hd[i, s] + (Hi[i, s] if has_ind else 0.0)
            if h <= 0.0:
                continue
            q = h * (T[j] - ti)
            b[i] += q
            if j < m:
                b[j] -= q
    # walls: fixed temperature (implicit, at time t), fixed flux (explicit)
    for i in range(m):
        for q in range(wnn[i]):
            h = Hw[i, q]
            if h <= 0.0:
                continue
            w = wnb[i, q]
            cond = wth[w, WT.cond]
            if cond == 1.0:
                dg[i] += h
                b[i] += h * (wall_temperature(wth, wtab, w, t) - T[i])
            elif cond == 2.0:
                qq = h * wth[w, WT.q]
                b[i] += qq
                wtot[w] += qq * dt
                tot[TOT.wall] += qq * dt
                if P.qmech.shape[0] == n:
                    P.qmech[i, QM.wall] += qq
    # convection
    hconv = np.zeros(m if conv >= 0 else 0)
    if conv >= 0:
        convection_conductances(m, v, r, cgv, uf, por, gas, conv, hconv)
        for i in range(m):
            dg[i] += hconv[i]
            b[i] += hconv[i] * (tf[i] - T[i])
    # radiation, linearised about T^n (environment temperatures from T^n)
    qrad = np.zeros(m if rad >= 0 else 0)
    krad = np.zeros(m if rad >= 0 else 0)
    if rad >= 0:
        acc0, acc1 = radiation_accumulators(rad, m, n, T, r, mat, tmat, nb, nnb, rnear)
    # radiating walls: their parts of each particle's rate at T^n (qw) and weights omega (om)
    wr = rad >= 0 and thi[TI.wrad] == 1
    nw = wth.shape[0]
    wgt = np.zeros((m if wr else 0, nw))
    aw0 = np.zeros(m if wr else 0)
    aw1 = np.zeros(m if wr else 0)
    qw = np.zeros((m if wr else 0, nw))
    om = np.zeros((m if wr else 0, nw))
    if wr:
        wall_radiation_weights(rad, 0, m, P, W, t, prm.thf[TF.radrange], wgt, aw0, aw1)
    if rad >= 0:
        for i in range(m):
            walls_i = wr and aw1[i] > 0.0
            if walls_i:
                te = radiation_env_temperature_walls(rad, acc0[i], acc1[i], aw0[i], aw1[i], por[i], tf[i], T[i])
            else:
                te = radiation_env_temperature(rad, acc0[i], acc1[i], por[i], tf[i], T[i])
            eps_i = own_emissivity(tmat, mat, cgv, i)
            qrad[i] = radiation_heat(eps_i, r[i], te, T[i])
            if walls_i:
                for w in range(nw):
                    if wgt[i, w] > 0.0:
                        om[i, w] = radiation_wall_omega(rad, wgt[i, w], acc1[i], aw1[i])
                        qw[i, w] = radiation_wall_rate(rad, eps_i, r[i], T[i], te, om[i, w],
                                                       wall_temperature(wth, wtab, w, t))
            # (krause with nothing in range: T_e = T_i, no heat and no tangent)
            if walls_i or not (rad == RAD_KRAUSE_2017 and acc1[i] == 0.0):
                krad[i] = 4.0 * eps_i * SIGMA_SB * 4.0 * math.pi * r[i] * r[i] * T[i] ** 3
            dg[i] += krad[i]
            b[i] += qrad[i]
    # explicit heat: generation, sources
    explicit_heat(0, m, n, x, r, qgen, qsrc, srcbox, dt, b, tot, P.qmech)
    return hconv, qrad, krad, wgt, aw1, qw, om


@njit(cache=True, error_model="numpy")
def _implicit_totals(P, C, W, prm, m, Ts, d, t, fw, has_ind, links, nblk):
    """Add to the run totals the heat of every linear link at the temperatures Ts (rows
    [0, m)) times the weight f (s; ``fw`` = (f, 1 / the step)): pairs |H (T_j - T_i)|, fixed-temperature walls at time t,
    convection, and the linearised radiation qrad - krad d (d = Ts - T^n), a radiating wall's
    part qw - omega krad d (``links`` = (hconv, qrad, krad, wgt, aw1, qw, om) of
    _implicit_assemble). The pairs' sum on ``nblk`` blocks of rows when nblk > 1
    (dem.thermal.implicit.pair_heat_blocks). With P.qmech (of every row) each link's rate
    times f / the step (the stages' weights f sum to the step) goes to its particles' columns
    (QM)."""
    f, rdt = fw
    hconv, qrad, krad, wgt, aw1, qw, om = links
    qm = P.qmech
    split = qm.shape[0] == P.temperature.shape[0]
    fr = f * rdt
    nb, nnb, Hd, Hi = C.nb, C.nnb, C.Hd, C.Hi
    wnb, wnn, Hw, tf = P.wnb, P.wnn, P.Hw, P.tf
    wth, wtab, wtot, wgap, wrad = W.wth, W.wtab, W.wtot, W.wgap, W.wrad
    tot = prm.tot
    Hwg = P.Hwg
    has_wg = Hwg.shape[0] == P.temperature.shape[0]
    conv = prm.thi[TI.conv]
    rad = prm.thi[TI.rad]
    wr = rad >= 0 and prm.thi[TI.wrad] == 1
    nw = wth.shape[0]
    if nblk > 1:
        ed, ei = pair_heat_blocks(m, (nb, nnb, Hd, Hi), has_ind, Ts, f, nblk)
    else:
        ed, ei = pair_heat_rows(m - m, m, m, (nb, nnb, Hd, Hi), has_ind, Ts, f)  # (row 0 at run time)
    tot[TOT.direct] += ed
    tot[TOT.indirect] += ei
    if split:
        ng = Ts.shape[0]
        for i in range(m):
            for s in range(nnb[i]):
                j = nb[i, s]
                if j >= ng:
                    continue
                dT = Ts[j] - Ts[i]
                qd = Hd[i, s] * dT * fr
                qi = Hi[i, s] * dT * fr if has_ind else 0.0
                qm[i, QM.direct] += qd
                qm[i, QM.indirect] += qi
                if j < m:  # (a ghost's share is its owner's)
                    qm[j, QM.direct] -= qd
                    qm[j, QM.indirect] -= qi
    for i in range(m):
        for q in range(wnn[i]):
            h = Hw[i, q]
            w = wnb[i, q]
            if h > 0.0 and wth[w, WT.cond] == 1.0:
                dtw = wall_temperature(wth, wtab, w, t) - Ts[i]
                ew = h * dtw * f
                wtot[w] += ew
                tot[TOT.wall] += ew
                if split:
                    qm[i, QM.wall] += h * dtw * fr
                if has_wg:
                    wgap[w] += Hwg[i, q] * dtw * f
    if conv >= 0:
        ec = 0.0
        for i in range(m):
            ec += hconv[i] * (tf[i] - Ts[i]) * f
            if split:
                qm[i, QM.conv] += hconv[i] * (tf[i] - Ts[i]) * fr
        tot[TOT.conv] += ec
    if rad >= 0:
        # the linearised rate qrad - krad d at Ts; a wall's part qw - omega krad d
        er = 0.0
        for i in range(m):
            e = (qrad[i] - krad[i] * d[i]) * f
            if wr and aw1[i] > 0.0:
                for w in range(nw):
                    if wgt[i, w] > 0.0:
                        ew = (qw[i, w] - om[i, w] * krad[i] * d[i]) * f
                        wtot[w] += ew
                        wrad[w] += ew
                        tot[TOT.wall] += ew
                        e -= ew
                        if split:
                            qm[i, QM.wall] += ew * rdt
            er += e
            if split:
                qm[i, QM.rad] += e * rdt
        tot[TOT.rad] += er


@njit(cache=True, error_model="numpy")
def _temperature_guard(T, m):
    """The first of the rows [0, m) with a non-finite or non-positive temperature, or -1."""
    for i in range(m):
        if not (T[i] > 0.0) or not math.isfinite(T[i]):
            return i
    return -1


@njit(cache=True, error_model="numpy", no_cpython_wrapper=True, no_cfunc_wrapper=True)
def _implicit_step(P, C, W, TB, prm, m, dt, t, has_ind, nblk):
    """Backward Euler heat step of the rows [0, m) (``integrator = "implicit"``; the scene
    parser refuses it under MPI, so every row is owned): with d = T^{n+1} - T^n,

        (C/dt + K + L) d = Q(T^n)                                   (dem.thermal.implicit, eq. 1)

    i.e. C (T^{n+1} - T^n) / dt = Q(T^{n+1}) for the linear links: pair conduction (L),
    fixed-temperature walls at their end-of-step temperature, gas convection h A (T_f - T)
    (K), and explicit heat rates (generation, sources, fixed wall fluxes). Radiation is
    linearised about T^n: Q_r(T^{n+1}) ~ Q_r(T^n) - 4 eps sigma A T_i^3 d_i with the
    environment temperature T_e of T^n (the error of one step is
    6 eps sigma A T^2 d^2 / 2 in heat rate; nothing at steady state, where d = 0).

    Backward Euler is L-stable (every mode decays, stiff ones at once, no ringing) for any
    step, and its fixed point (d = 0) is Q(T) = 0: the steady state of the network itself,
    whatever dt. Energy: sum C d = dt sum(reservoir and explicit heat at T^{n+1}) + dt sum(r)
    with r the CG residual, ||r|| <= CG_RTOL ||Q(T^n)||, so the balance holds to that
    tolerance (the pair terms cancel exactly). The totals count the heats at T^{n+1}.
    Returns the first particle with a non-finite or non-positive temperature, or -1."""
    T, cinv, Q = P.temperature, P.inv_heat_capacity, P.heat_rate
    b = np.zeros(m)   # Q(T^n), W
    dg = np.empty(m)  # C/dt + K, W/K
    links = _implicit_assemble(P, C, W, TB, prm, m, dt, dt, t, has_ind, b, dg)
    # solve, update
    d = np.empty(m)
    _solve(m, C, has_ind, dg, b, d, nblk)
    for i in range(m):
        T[i] += d[i]
        Q[i] = d[i] / (cinv[i] * dt)
    # totals at T^{n+1}
    _implicit_totals(P, C, W, prm, m, T, d, t, (dt, 1.0 / dt), has_ind, links, nblk)
    return _temperature_guard(T, m)


@njit(cache=True, error_model="numpy")
def _solve(m, C, has_ind, dg, rhs, out, nblk):
    """out = (diag(dg) + L)^-1 rhs over the rows [0, m) (dem.thermal.implicit): the Jacobi
    preconditioned conjugate gradients, on ``nblk`` blocks of rows at once when nblk > 1."""
    if nblk > 1:
        return jacobi_pcg_blocks(m, (C.nb, C.nnb, C.Hd, C.Hi), has_ind, dg, rhs, out, CG_RTOL, 10 * m + 100, nblk)
    return jacobi_pcg(m, C.nb, C.nnb, C.Hd, C.Hi, has_ind, dg, rhs, out, CG_RTOL, 10 * m + 100)


# TR-BDF2's stage fraction gamma = 2 - sqrt(2) (Hosea & Shampine 1996): both stages then have
# the same matrix up to the coefficient of C, and the scheme is L-stable
TRBDF2_GAMMA = 2.0 - math.sqrt(2.0)


@njit(cache=True)
def trbdf2_coefficients(dt, t):
    """The coefficients of a TR-BDF2 step of length dt ending at t (_trbdf2_step's docstring;
    shared with the step under MPI, dem.thermal.implicit_mpi): the trapezoid's dt1 = gamma dt / 2
    (its matrix C / dt1 + A), w = (1 - gamma) / (2 - gamma) dt (BDF2's C / w + A), the energy
    weight a = dt / (2 (2 - gamma)) of the links at T^n and T^g (2 a + w = dt), BDF2's factor
    c2 = 1 / (w gamma (2 - gamma)) of C d1, the step's start t0 = t - dt and stage time
    tg = t0 + gamma dt."""
    g = TRBDF2_GAMMA
    w = (1.0 - g) / (2.0 - g) * dt
    t0 = t - dt
    return 0.5 * g * dt, w, 0.5 * dt / (2.0 - g), 1.0 / (w * g * (2.0 - g)), t0, t0 + g * dt


@njit(cache=True)
def has_wall_tables(W):
    """True when a fixed-temperature wall follows a temperature table (the walls' sources then
    change between a step's stage times: _wall_source_shift)."""
    wth = W.wth
    for k in range(wth.shape[0]):
        if wth[k, WT.cond] == 1.0 and wth[k, WT.ntab] > 0:
            return True
    return False


@njit(cache=True, error_model="numpy")
def _wall_source_shift(P, W, m, t, t0, out):
    """out[i] += sum_w H_w (T_w(t) - T_w(t0)) over particle i's fixed-temperature walls (rows
    [0, m)): the change of the wall heat rates between the times t0 and t of a wall table."""
    wnb, wnn, Hw = P.wnb, P.wnn, P.Hw
    wth, wtab = W.wth, W.wtab
    for i in range(m):
        for q in range(wnn[i]):
            h = Hw[i, q]
            w = wnb[i, q]
            if h > 0.0 and wth[w, WT.cond] == 1.0 and wth[w, WT.ntab] > 0:
                out[i] += h * (wall_temperature(wth, wtab, w, t) - wall_temperature(wth, wtab, w, t0))


@njit(cache=True, error_model="numpy", no_cpython_wrapper=True, no_cfunc_wrapper=True)
def _trbdf2_step(P, C, W, TB, prm, m, dt, t, has_ind, nblk):
    """TR-BDF2 heat step of the rows [0, m) (``integrator = "trbdf2"``; every row owned, as for
    "implicit"): the trapezoidal rule to t_n + gamma dt, then the second-order backward
    difference formula through t_n, t_n + gamma dt and t_n + dt (Bank, Coughran, Fichtner,
    Grosse, Rose & Smith 1985, IEEE Trans. Electron Devices 32, 1992; Hosea & Shampine 1996,
    Appl. Numer. Math. 20, 21), gamma = 2 - sqrt(2). For C dT/dt = Q(T) = b - A T, A = K + L
    (dem.thermal.implicit, eq. 1) and d1 = T^g - T^n, d2 = T^{n+1} - T^n:

        trapezoid:  (2 C / (gamma dt) + A) d1 = Q(T^n, t_n) + Q(T^n, t_n + gamma dt)
        BDF2:       (C / w + A) d2 = Q(T^n, t_n+1) + C d1 / (w gamma (2 - gamma)),
                    w = (1 - gamma) / (2 - gamma) dt

    (the BDF2 stage T^{n+1} = (T^g - (1-gamma)^2 T^n) / (gamma (2-gamma)) + w C^-1 Q(T^{n+1})
    written for the increment, using 1 - (1-gamma)^2 = gamma (2-gamma)). Both systems are the
    symmetric positive definite one of backward Euler with another coefficient of C, solved by
    the same Jacobi-preconditioned conjugate gradients on the half list (two solves a step, no
    history: a restart continues exactly). Walls at their temperatures at each stage's time
    (tables), radiation linearised about T^n as in _implicit_step (the environment
    temperatures from T^n).

    Second order (local error -(3 gamma^2 - 4 gamma + 2) / (12 (2 - gamma)) dt^3 T''' = 0.040
    dt^3 |T'''|, half the trapezoidal rule's), L-stable (amplification 0 for infinitely stiff
    modes, |R(z)| < 1 for every z > 0: no growth and no lasting ringing, unlike Crank-Nicolson),
    and its fixed point is Q(T) = 0: d1 = 0 and d2 = 0 when Q(T^n) = 0, so the steady state is
    that of the network itself at any step (to the CG tolerance, relative to Q, which vanishes
    there). Energy: C d2 = a (Q^n + Q^g) + w Q^{n+1} with a = dt / (2 (2 - gamma)), 2 a + w = dt;
    the totals count each link with these weights at T^n, T^g and T^{n+1}. Returns the first
    particle with a non-finite or non-positive temperature, or -1."""
    T, cinv, Q = P.temperature, P.inv_heat_capacity, P.heat_rate
    dt1, w, a, c2, t0, tg = trbdf2_coefficients(dt, t)
    b = np.zeros(m)   # Q(T^n) with the walls at t_n+1
    dg = np.empty(m)  # C/dt1 + K
    links = _implicit_assemble(P, C, W, TB, prm, m, dt1, dt, t, has_ind, b, dg)
    tables = has_wall_tables(W)
    # trapezoid to t_n + gamma dt
    rhs = np.empty(m)
    for i in range(m):
        rhs[i] = 2.0 * b[i]
    if tables:
        _wall_source_shift(P, W, m, t0, t, rhs)
        _wall_source_shift(P, W, m, tg, t, rhs)
    d1 = np.empty(m)
    _solve(m, C, has_ind, dg, rhs, d1, nblk)
    # BDF2 to t_n + dt
    for i in range(m):
        ci = 1.0 / cinv[i]
        dg[i] += ci / w - ci / dt1
        rhs[i] = b[i] + ci * d1[i] * c2
    d2 = np.empty(m)
    _solve(m, C, has_ind, dg, rhs, d2, nblk)
    Tn = np.empty(m)
    Tg = np.empty(m)
    zero = np.zeros(m)
    for i in range(m):
        Tn[i] = T[i]
        Tg[i] = T[i] + d1[i]
        T[i] += d2[i]
        Q[i] = d2[i] / (cinv[i] * dt)
    # totals: the links at T^n (walls at t_n), T^g (t_n + gamma dt) and T^{n+1} (t_n+1)
    _implicit_totals(P, C, W, prm, m, Tn, zero, t0, (a, 1.0 / dt), has_ind, links, nblk)
    _implicit_totals(P, C, W, prm, m, Tg, d1, tg, (a, 1.0 / dt), has_ind, links, nblk)
    _implicit_totals(P, C, W, prm, m, T, d2, t, (w, 1.0 / dt), has_ind, links, nblk)
    return _temperature_guard(T, m)


@njit(cache=True, error_model="numpy")
def _pair_sweep(n, dt, T, cinv, Q, C, has_ind, integ, direction, tot, qm, rdt):
    """Pair conduction over dt through the conductances of the pairs ``C`` (dem.schema Pairs:
    Hd, and Hi when has_ind): Euler (into Q) or exact two-body exponential updates of T
    in particle order (direction 1) or reverse order (-1), over the rows [0, n) of owned
    particles. Pairs with a ghost (j >= n): Euler counts half their heat in the totals (the
    other rank counts the other half); the exponential update leaves them to the
    reservoir relaxation (_ghost_links). ``qm`` (P.qmech, when of the pairs' rows): each
    particle's share by mechanism, as a rate (energy x ``rdt`` = 1 / the step)."""
    nb, nnb, Hd, Hi = C.nb, C.nnb, C.Hd, C.Hi
    split = qm.shape[0] == T.shape[0]
    ed = 0.0
    ei = 0.0
    for k in range(n):
        i = k if direction > 0 else n - 1 - k
        cnt = nnb[i]
        for ss in range(cnt):
            s = ss if direction > 0 else cnt - 1 - ss
            hd = Hd[i, s]
            hi = Hi[i, s] if has_ind else 0.0
            h = hd + hi
            if h <= 0.0:
                continue
            j = nb[i, s]
            if integ == 0:
                q = h * (T[j] - T[i])
                Q[i] += q
                Q[j] -= q
                if split:
                    qm[i, QM.direct] += q * hd / h
                    qm[i, QM.indirect] += q * hi / h
                    qm[j, QM.direct] -= q * hd / h
                    qm[j, QM.indirect] -= q * hi / h
                e = abs(q) * dt
                if j >= n:
                    e *= 0.5
            else:
                if j >= n:
                    continue
                a = cinv[i] + cinv[j]
                e = (T[j] - T[i]) * (-math.expm1(-h * a * dt)) / a
                T[i] += e * cinv[i]
                T[j] -= e * cinv[j]
                if split:
                    qm[i, QM.direct] += e * rdt * hd / h
                    qm[i, QM.indirect] += e * rdt * hi / h
                    qm[j, QM.direct] -= e * rdt * hd / h
                    qm[j, QM.indirect] -= e * rdt * hi / h
                e = abs(e)
            ed += e * hd / h
            ei += e * hi / h
    tot[TOT.direct] += ed
    tot[TOT.indirect] += ei


@njit(cache=True, error_model="numpy")
def cross_rates(nown, cinv, nb, nnb, Hd, Hi, work):
    """lam_i = sum of the conductances of particle i's pairs with ghosts / C_i, into work[:, 1]."""
    has_ind = Hi.shape[0] > 0
    for i in range(nown):
        h = 0.0
        for s in range(nnb[i]):
            if nb[i, s] >= nown:
                h += Hd[i, s] + (Hi[i, s] if has_ind else 0.0)
        work[i, 1] = h * cinv[i]


@njit(cache=True, error_model="numpy")
def _cross_exchange(nown, dt, T, cinv, nb, nnb, Hd, Hi, has_ind, work, tot, qm):
    """Exponential update of the pairs with a ghost (see heat_step), from the start-of-step
    temperatures; half of each exchange goes into the totals (the other rank counts the rest),
    and the whole of it, as a rate, to the particle's columns of ``qm`` (P.qmech) when kept."""
    rdt = 1.0 / dt
    dT = np.zeros(nown)
    ed = 0.0
    ei = 0.0
    for i in range(nown):
        for s in range(nnb[i]):
            j = nb[i, s]
            if j < nown:
                continue
            hd = Hd[i, s]
            hi = Hi[i, s] if has_ind else 0.0
            h = hd + hi
            if h <= 0.0:
                continue
            lam = max(work[i, 1], work[j, 1])
            phi = -math.expm1(-lam * dt) / lam if lam > 0.0 else dt
            e = h * (T[j] - T[i]) * phi
            dT[i] += e * cinv[i]
            if qm.shape[0] == T.shape[0]:
                qm[i, QM.direct] += e * rdt * hd / h
                qm[i, QM.indirect] += e * rdt * hi / h
            ed += 0.5 * abs(e) * hd / h
            ei += 0.5 * abs(e) * hi / h
    for i in range(nown):
        T[i] += dT[i]
    tot[TOT.direct] += ed
    tot[TOT.indirect] += ei


@njit(cache=True, error_model="numpy")
def local_porosity(P, C, W, prm, n, reach, t, floor):
    """Porosity in a measuring sphere of radius R_m = R_i + reach around each particle of
    rows [0, n), into P.por: 1 - (own volume + exact lens volumes of the neighbours inside
    (the half list of ``C``)) / (sphere volume minus the caps cut off by the plane walls of
    ``W`` among each particle's candidates, and by the mesh walls at their contacts). Floor applied (a measuring sphere that is mostly
    wall). P, C, W, prm: the bundles of dem.schema."""
    x, r, wnb, wnn, out = P.position, P.radius, P.wnb, P.wnn, P.por
    nb, nnb, wf, wi = C.nb, C.nnb, W.wf, W.wi
    lo, hi, periodic = prm.lo, prm.hi, prm.periodic
    vs = np.zeros(n)
    for i in range(n):
        vs[i] += 4.0 / 3.0 * math.pi * r[i] ** 3
    for i in range(n):
        for s in range(nnb[i]):
            j = nb[i, s]
            d = pair_distance(x, i, j, lo, hi, periodic)
            vs[i] += _lens(r[i] + reach, r[j], d)
            vs[j] += _lens(r[j] + reach, r[i], d)
    for i in range(n):
        rm = r[i] + reach
        vm = 4.0 / 3.0 * math.pi * rm ** 3
        for q in range(wnn[i]):
            w = wnb[i, q]
            if wi[w, WI.type] == MESH:   # the mesh's caps, once (at its first row)
                m = wi[w, WI.mesh]
                if w == W.mmi[m, MMI.row0]:
                    vm -= mesh_caps(W, m, x[i, 0], x[i, 1], x[i, 2], rm, t)
                continue
            if wi[w, WI.type] != PLANE:
                continue
            dist = 0.0  # signed distance to the plane at time t (a moving wall where it is now)
            for k in range(3):
                dist += (x[i, k] - wf[w, WF.px + k] - wf[w, WF.vx + k] * t) * wf[w, WF.nx + k]
            if dist < rm:
                hcap = rm - max(dist, -rm)
                vm -= math.pi * hcap * hcap * (3.0 * rm - hcap) / 3.0
        p = 1.0 - vs[i] / max(vm, 1e-300)
        out[i] = min(max(p, floor), 1.0)


@njit(cache=True, error_model="numpy")
def _lens(R, r, d):
    """Volume of sphere r (centre at distance d) inside sphere R."""
    if d >= R + r:
        return 0.0
    if d <= R - r:
        return 4.0 / 3.0 * math.pi * r ** 3
    if d <= r - R:
        return 4.0 / 3.0 * math.pi * R ** 3
    return math.pi * (R + r - d) ** 2 * (d * d + 2 * d * r - 3 * r * r + 2 * d * R + 6 * r * R - 3 * R * R) / (12 * d)


@njit(cache=True, error_model="numpy")
def convection_conductances(n, v, r, cg, uf, por, gas, conv, out):
    """h A = 2 pi R k_f Nu(Re, Pr, eps) of each particle (W/K), Re = eps rho_f |u_f - v| d / mu_f:
    the same numbers heat_step uses, for the gas-side source terms of a coupled run. A parcel
    (cg, empty without coarse graining) takes its real particles' law, R = r / cg in Re and
    h A, times their number cg^3 (docs/models.md, "Coarse graining")."""
    _convection_rows(0, n, v, r, cg, uf, por, gas, conv, out)


@njit(cache=True, error_model="numpy")
def _convection_rows(i0, i1, v, r, cg, uf, por, gas, conv, out):
    """:func:`convection_conductances` of the rows [i0, i1)."""
    has_cg = cg.shape[0] > 0
    for i in range(i0, i1):
        ux = uf[i, 0] - v[i, 0]
        uy = uf[i, 1] - v[i, 1]
        uz = uf[i, 2] - v[i, 2]
        ur = math.sqrt(ux * ux + uy * uy + uz * uz)
        R = r[i] / cg[i] if has_cg else r[i]
        re = por[i] * gas[RHO_F] * ur * 2.0 * R / gas[MU_F]
        h = convection_conductance(R, gas[KF], nusselt_gas(conv, re, gas[PR], por[i], gas))
        out[i] = h * cg[i] ** 3 if has_cg else h
