"""The time-step kernel: contact forces, walls, velocity-Verlet integration,
neighbour-list maintenance and the stability guards, run for many steps inside one
compiled call (no Python per step).

The kernel is one cached Numba function with integer model switches (contact law,
rolling model) rather than code generated per scene: every scene reuses the same cached
machine code, so a new scene starts in about a second instead of recompiling. Two switches
are types instead, each compiling a form without the code it turns off: ``hon`` (heat or
not) and ``xon`` (:func:`full_form`: rolling, periodic images and the heat models beyond
direct conduction, or none of them), so at most four forms of the step, all compiled by the
set-up (dem.compile). A run-time switch is a well-predicted branch, but in the pair loop, which
is bound by the instructions it issues, the lean form's constants made the shared heat beds
about 12 % faster.
The force loop is compiled with the fast-math flags that reorder and contract arithmetic
(nsz, arcp, contract, afn, reassoc: 12 % faster on the shared 10k bed) but not with
nnan/ninf, so infinities (unbounded walls) and the NaN guards keep their meaning.
Parts a scene does not enable are skipped: no rolling history arrays without a rolling
model, no wall loop without walls, no heat terms without a thermal section
(see dem.thermal.kernel for the heat part).
"""
import math
from collections import namedtuple

import numpy as np
from numba import njit, prange

from .contact.hertz_mindlin import hertz_mindlin
from .contact.linear import linear_spring_dashpot
from .contact.rolling import constant_torque, epsd
from .contact.tangential import luding_2008_turn, silbert_2001_turn, TANGENTIAL_PROJECTED
from .contact.walls import wall_distance, wall_velocity, WI, MESH
from .contact.mesh import mesh_contacts, mesh_candidates, mesh_motion, mesh_point_velocity, MMI, MO
from .blocks import block_bounds, block_count, cross_counts, keep_cross_counts, kept_cross_counts
from .neighbors import build_half_list, Box, adaptive_skin, pairs_beyond
from .schema import Pairs, XC, slots
from .thermal.contact_radius import (contact_radius_pw, hertz_force, hertz_overlap, geometric_pp_inv,
                                     apply_correction, lean_radius, HERTZ_FORCE, HERTZ_OVERLAP, GEOMETRIC)
from .thermal.direct import direct_pp, direct_pw, direct_cg_pp, direct_cg_pw, batchelor_obrien_keff
from .thermal.registry import DIRECT_BATCHELOR_OBRIEN
from .thermal.indirect import indirect_pp, indirect_pw
from .thermal.generation import friction_heat, partition
from .thermal.heat import heat_step, local_porosity, TI, TF, WT, TOT, wall_temperature, heat_cg

# integer parameters (Params.ip)
IP = slots("IP", (
    ("contact", "contact law (dem.contact.registry CONTACT_MODELS: 0 Hertz-Mindlin, 1 linear)"),
    ("rolling", "rolling model (ROLLING_MODELS: 0 none, 1 constant torque, 2 EPSD)"),
    ("nwalls", "number of walls"),
    ("mech", "1: mechanics on; 0: a frozen packing (heat alone)"),
    ("nown", "owned rows (the rest are ghosts)"),
    ("threads", "threads of this process: blocks of rows the kernels run at once (1: one block, serial order)"),
    ("tangential", "tangential spring (TANGENTIAL_MODELS: 0 rescaled, Luding 2008; 1 projected, Silbert 2001 as "
                   "LAMMPS / LIGGGHTS; dem.contact.tangential)"),
    ("autoskin", "1: the skin chosen at each build (neighbor_skin = \"auto\", dem.neighbors.adaptive_skin); "
                 "0: the scene's"),
    ("nmesh", "triangle-mesh walls (dem.contact.mesh; each is WI rows of type MESH)"),
    ("openfaces", "faces of the domain that are outlets (dem.flow): bit 2 axis + (0 min, 1 max); a particle "
                  "beyond one is not 'outside' (the outlet removes it)"),
), size=12)
# float parameters (Params.fp)
FP = slots("FP", (
    ("dt", "time step (s)"),
    ("gx", "gravity x (m/s^2)"),
    ("gy", "gravity y (m/s^2)"),
    ("gz", "gravity z (m/s^2)"),
    ("skin", "neighbour-list skin (m)"),
    ("reach", "list reach beyond contact: the heat models' range (m)"),
    ("vchar", "characteristic velocity of the linear law's Hertz-equivalent stiffness (m/s)"),
    ("ktratio", "tangential / normal stiffness of the linear law"),
    ("linkn", "linear normal stiffness (N/m; <= 0: Hertz-equivalent at vchar)"),
    ("etar", "EPSD rolling damping ratio"),
    ("maxov", "largest overlap ratio before the overlap guard stops the run"),
    ("vwall", "fastest wall speed (m/s, the rebuild test)"),
    ("tbuild", "time of the last neighbour build (s; checkpointed as fp_tbuild)"),
    ("skinmax", "largest skin (m): the scene's fixed skin, or the adaptive skin's bound"),
    ("gapd", "listed pairs beyond contact per owned particle and metre of skin at the last build, over "
             "every rank (the adaptive skin's measure; checkpointed as fp_gapd)"),
    ("nfar", "this rank's listed pairs beyond contact at the last build"),
), size=16)
# pair tables (Tables.tab[slot, material, material])
TAB = slots("TAB", (
    ("estar", "effective Young's modulus E* (Pa)"),
    ("gstar", "effective shear modulus G* (Pa)"),
    ("damp", "damping coefficient (dem.contact.damping)"),
    ("mu", "sliding friction coefficient"),
    ("mur", "rolling friction coefficient"),
    ("ctr", "Hertz-Mindlin tangential / normal damping ratio sqrt(4 G* / E*) (dem.contact.hertz_mindlin)"),
))
# what a pair gives its other particle j when j is in another block of rows (interact_rows' xv)
XV = slots("XV", (
    ("fx", "x of the force on i (j gets minus it)"),
    ("fy", "y of the force on i"),
    ("fz", "z of the force on i"),
    ("cx", "x of n x F_t (j's torque gets r_j times it)"),
    ("cy", "y of n x F_t"),
    ("cz", "z of n x F_t"),
    ("mx", "x of the rolling torque on i (j gets minus it)"),
    ("my", "y of the rolling torque on i"),
    ("mz", "z of the rolling torque on i"),
    ("q", "fused heat rate into j (W)"),
    ("psi", "share of the friction heat that goes to j"),
    ("qf", "friction heat of the contact (W)"),
))
# (xv holds the factors of what j gets, not their products: a product written on both sides of
# the block test would be computed once before it, and j's own sum would lose its fused
# multiply-add: one block would then no longer be the serial loop bit for bit)
XV_SIZE = XV.SIZE
# one block of rows for interact_rows: rows [i0, i1), the cross-block buffer (xj, xv) and its
# first row k0, and where the block's fused wall heat adds up (wtot, wgap)
Block = namedtuple("Block", "i0 i1 k0 xj xv wtot wgap")
# the largest overlap ratio's pre-test in interact_rows: delta > maxov r (1 - 1e-12) before dividing
OV_MARGIN = 1.0 - 1e-12
# status
OK, OVERLAP, NONFINITE, LEFT_DOMAIN, BAD_TEMPERATURE, REBUILD_DUE = 0, 1, 2, 3, 4, 5
# phases of one step (advance's ``phases`` bits): a serial run asks for all of them, an MPI run
# for one group at a time with the ghost messages between the calls (dem.simulation)
PH_DRIFT, PH_REBUILD, PH_FORCES, PH_KICK, PH_HEAT, PH_AFTER_BUILD = 1, 2, 4, 8, 16, 32
PH_CANDIDATES = 64   # (alone, no step: the mesh walls' candidate triangles of the last build, found again)
PH_STEP = PH_DRIFT | PH_REBUILD | PH_FORCES | PH_KICK | PH_HEAT


# the run's contact-law constants, one record for every contact of a force evaluation
ContactLaw = namedtuple("ContactLaw", "model dt lin_kn vchar kt_ratio")
ContactLaw.__doc__ = ("Contact law (ip[IP.contact]: 0 Hertz-Mindlin, 1 linear), time step, linear normal stiffness "
                      "(<= 0: Hertz-equivalent at vchar), characteristic velocity, tangential / normal stiffness.")
# the material-pair constants of one contact (rows of the pair table ``tab``)
PairMaterial = namedtuple("PairMaterial", "estar gstar damp mu")
PairMaterial.__doc__ = "E*, G*, damping coefficient and friction coefficient of a material pair (dem.step TAB)."


@njit(cache=True, error_model="numpy", inline="always")
def contact_law(ip, fp):
    """The :class:`ContactLaw` of the run's switches and parameters."""
    return ContactLaw(ip[IP.contact], fp[FP.dt], fp[FP.linkn], fp[FP.vchar], fp[FP.ktratio])


@njit(cache=True, error_model="numpy", inline="always")
def pair_material(tab, mi, mj):
    """The :class:`PairMaterial` of materials mi and mj."""
    return PairMaterial(tab[TAB.estar, mi, mj], tab[TAB.gstar, mi, mj], tab[TAB.damp, mi, mj], tab[TAB.mu, mi, mj])


@njit(cache=True, error_model="numpy", fastmath={"nsz", "arcp", "contract", "afn", "reassoc"}, inline="always")
def _pair_law(model, delta, vn, vtx, vty, vtz, hx, hy, hz, rstar, mstar, estar, gstar,
              damp, mu, ctr, dt, lin_kn, vchar, kt_ratio, ton):
    """The contact law of the run (``model``: ip[IP.contact], 0 Hertz-Mindlin, 1 linear spring-
    dashpot) with its scalars and the tangential model ``ton`` (a type: None rescaled, True
    projected; dem.contact.tangential): normal and tangential force of one contact. It keeps the laws'
    scalar parameter list (tests/test_architecture.py, SCALAR_LAWS): taking the records
    ContactLaw / PairMaterial and 3-tuples through the call ran the shared 10k heat bed 7-10 %
    slower (benchmarks/loop_time.py, alternated pairs).

    Inlined into both contact loops (issue 28): as a called function every contact spilled the
    loop's live doubles around the call (x86-64 keeps no vector register across a call) and
    returned its 8 values through memory; inlined, the pair loop of the shared beds runs 5-8 %
    faster (docs/notebook.md, "Where a step goes"). The shared beds stay bitwise; scenes that
    slide or roll (the rotating drum) change by round-off, as fastmath may now fuse across the
    former call boundary."""
    if model == 0:
        return hertz_mindlin(delta, vn, vtx, vty, vtz, hx, hy, hz,
                             rstar, mstar, estar, gstar, damp, mu, ctr, dt, ton)
    kn = lin_kn
    if kn <= 0.0:  # Hertz-equivalent stiffness at the characteristic velocity
        sr = math.sqrt(rstar)
        kn = 16.0 / 15.0 * sr * estar * (15.0 * mstar * vchar * vchar / (16.0 * sr * estar)) ** 0.2
    return linear_spring_dashpot(delta, vn, vtx, vty, vtz, hx, hy, hz,
                                 mstar, kn, kt_ratio, damp, mu, dt, ton)


@njit(cache=True, error_model="numpy")
def _contact_age(age, i, s, vn, dt):
    """Time since the contact in slot (i, s) began and its normal speed at impact
    (zhou_2008_collisional); the slot is reset when the contact opens."""
    if age[i, s, 0] == 0.0:
        age[i, s, 1] = vn
    age[i, s, 0] += dt
    return age[i, s, 0], age[i, s, 1]


@njit(cache=True, error_model="numpy")
def _contact_heat(fric, mu, thf, vtx, vty, vtz, ftx, fty, ftz, fn, vn):
    """Heat generated at a contact (W) by the friction model ``fric`` (dem.thermal.generation)."""
    vtm = math.sqrt(vtx * vtx + vty * vty + vtz * vtz)
    ftv = abs(ftx * vtx + fty * vty + ftz * vtz)
    return friction_heat(fric, mu, thf[TF.chi], vtm, fn, ftv, thf[TF.ct], thf[TF.cn], ftv, abs(fn * vn))


@njit(cache=True, error_model="numpy", inline="always")
def _rotate_history(h0, h1, h2, ux, uy, uz, inv_u2, ton):
    """The spring (h0, h1, h2) turned onto the plane normal to (ux, uy, uz), whose squared
    length is 1 / inv_u2, by the tangential model ``ton`` (dem.contact.tangential: None keeping
    its length, Luding 2008; True projected, Silbert 2001). The pair loop gives the centre line
    and 1/d^2 (the turn then waits neither for the root of d^2 nor for a division by d); the
    walls and the rolling spring give the unit normal and 1. The rolling spring always keeps
    its length (None). Scalars in and out: in the contact loops a function taking an array
    counts its references up and down at each call."""
    if ton is not None:   # (removed before typing for the other model)
        return silbert_2001_turn(h0, h1, h2, ux, uy, uz, inv_u2)
    return luding_2008_turn(h0, h1, h2, ux, uy, uz, inv_u2)


@njit(cache=True, error_model="numpy")
def full_form(ip, thi, periodic):
    """Whether a scene needs the full form of the interact phase (``xon`` = True): rolling
    resistance, a periodic direction, or with heat the models the lean form (``xon`` = None)
    leaves out (a triangle-mesh wall runs in both forms: its rows are a run-time branch of the wall
    loop, a few per particle near it): indirect conduction, radiation, frictional heating, contact age, a direct
    conduction law other than Batchelor & O'Brien (the default), and the contact radii that are
    not a pair constant times sqrt(R* delta) or the geometric radius
    (dem.thermal.contact_radius.lean_radius: under the linear law the force-based radii, and a
    geometric radius with a force-based correction). Like ``hon``,
    ``xon`` is a type, so that Numba compiles the lean form without that code and without
    its run-time switches: the shared heat beds, whose scene uses none of them, run their
    interact phase about 10 % faster (docs/notebook.md, "The lean form of the contact loops").
    dem.stepper.Stepper.xon asks this; dem.step.compute_forces refuses the lean form for a
    scene that needs the full one."""
    if ip[IP.rolling] != 0 or periodic[0] or periodic[1] or periodic[2]:
        return True
    if thi[TI.heat] == 0:
        return False
    if thi[TI.indirect] >= 0 or thi[TI.rad] >= 0 or thi[TI.fric] >= 0 or thi[TI.age] != 0:
        return True
    if thi[TI.direct] < 0:
        return False
    return thi[TI.direct] != DIRECT_BATCHELOR_OBRIEN or not lean_radius(thi[TI.cr], thi[TI.corr], ip[IP.contact])


@njit(cache=True, error_model="numpy", fastmath={"nsz", "arcp", "contract", "afn", "reassoc"},
      no_cpython_wrapper=True, no_cfunc_wrapper=True)
def interact_rows(P, C, W, TB, prm, n, t, hon, xon, ton, blk):
    """The interact phase of the rows [i0, i1) of ``blk`` (:data:`Block`): body forces, the pairs of the half list that start
    at those rows, and their walls; with heat, the conductances of every neighbour slot and wall
    candidate for the heat step (Hd, Hi, Hw, the radiation neighbour flags) and the friction
    heat. ``hon``: True with heat, None without (a type, so that the mechanics-only
    specialisation is compiled without the heat code); ``ton``: the tangential spring model as a
    type, None for the rescaled one (the default), True for the projected one
    (dem.contact.tangential; as a run-time switch it cost the pair loop 5-15 %); ``xon``: True for the full form, None
    for the lean one, without rolling, periodic images and the heat models beyond direct
    conduction (:func:`full_form`). Rows >= ip[IP.nown] are ghosts (copies
    of another rank's particles, no pairs of their own); a pair with a ghost is computed on both
    ranks, so it counts 1 (of 2) and half its exchanged heat goes into the totals.

    A pair whose other particle j lies outside [i0, i1) does not touch j's rows: what it gives
    j (force, torque, fused heat rate, friction heat) is written to row k of ``xj`` (j) and
    ``xv`` (8 values, :data:`XV`), k counting from ``k0`` in loop order, for the caller to add
    once every block is done (:func:`interact_blocks`). With [i0, i1) = [0, n) (one block) no
    pair goes there, and the arithmetic is the serial loop's, in its order. ``wtot``, ``wgap``:
    where the fused wall heat of these rows adds up (the walls' own totals, or a block's part).

    Returns (max overlap ratio, i, j (-1-wall), 2 x contacts, direct, indirect and wall heat
    rates exchanged (W, fused mode; the caller adds them to the totals), the row of xv after the
    block's last)."""
    i0, i1, k0, xj, xv, wtot, wgap = blk.i0, blk.i1, blk.k0, blk.xj, blk.xv, blk.wtot, blk.wgap
    x, v, w, r, m, mat, f, tq = (P.position, P.velocity, P.angular_velocity, P.radius, P.mass, P.material,
                                 P.force, P.torque)
    inv_m = P.inv_mass
    fext, wnb, wnn, whist, wrhist, mcon = P.external_force, P.wnb, P.wnn, P.whist, P.wrhist, P.mcon
    mo = mesh_motion(W.mm, t)   # (each mesh's motion as numbers: no array through a call per contact)
    nb, nnb, hist, rhist, age, Hd, Hi, rnear = C.nb, C.nnb, C.hist, C.rhist, C.age, C.Hd, C.Hi, C.rnear
    wf, wi, tab, ip, fp, lo, hi, periodic = W.wf, W.wi, TB.tab, prm.ip, prm.fp, prm.lo, prm.hi, prm.periodic
    thi = prm.thi
    heat = hon is not None and thi[TI.heat] != 0
    # each heat block tests `hon is not None` first: Numba removes those blocks before typing
    # when hon is None, so the mechanics-only form neither types nor compiles the heat models;
    # likewise `xon is not None` for the optional physics (:func:`full_form`): the lean form
    # (xon None) has neither their code nor their run-time switches
    dmodel = thi[TI.direct]
    crm = thi[TI.cr]
    crc = thi[TI.corr]
    imodel = -1
    radon = False
    fric = -1
    use_age = False
    rolling = 0
    px = False
    py = False
    pz = False
    if xon is not None:
        imodel = thi[TI.indirect]
        radon = thi[TI.rad] >= 0
        fric = thi[TI.fric]
        use_age = thi[TI.age] != 0
        rolling = ip[IP.rolling]
        px = periodic[0]
        py = periodic[1]
        pz = periodic[2]
    pmodel = thi[TI.part]
    thf = prm.thf
    tmat = TB.tmat
    gas = TB.gas
    ereal = TB.ereal
    Hw = P.Hw
    Hwg = P.Hwg
    has_wg = Hwg.shape[0] == n
    # coarse graining (docs/models.md, "Coarse graining"): a parcel's conductances are its real
    # particles' laws at the real size (lengths / cg), times cg for a pair (the bed's effective
    # conductivity) and cg^2 for a wall contact (the wall's conductance per area); one cg per
    # scene (dem.thermal.scene refuses mixed factors with conduction)
    cgv = heat_cg(P.cg, thi) if hon is not None else P.cg
    has_cg = cgv.shape[0] > 0
    wth = W.wth
    por = P.por
    qgen = P.qgen
    wage = P.wage
    dfac = thf[TF.dfactor]
    radrange = thf[TF.radrange]
    fused = heat and thi[TI.fused] == 1
    T = P.temperature
    Q = P.heat_rate
    wtab = W.wtab
    keff = TB.keff
    rcf = TB.rcf
    bo = dmodel == DIRECT_BATCHELOR_OBRIEN
    # a contact's heat terms: in the lean form only Batchelor & O'Brien conduction (full_form),
    # and the conductance of the slot for the heat step when not fused (0 without conduction)
    pheat = heat and (xon is not None or bo or not fused)
    e_dir = 0.0
    e_ind = 0.0
    e_wall = 0.0
    if hon is not None and xon is not None and heat and fric >= 0:
        for i in range(i0, i1):
            qgen[i] = 0.0
    if fused:
        for i in range(i0, i1):
            Q[i] = 0.0
    dt = fp[FP.dt]
    model = ip[IP.contact]
    law = contact_law(ip, fp)
    etar = fp[FP.etar]
    gx = fp[FP.gx]
    gy = fp[FP.gy]
    gz = fp[FP.gz]
    Lx = hi[0] - lo[0]
    Ly = hi[1] - lo[1]
    Lz = hi[2] - lo[2]
    has_ext = fext.shape[0] == n
    text = P.external_torque
    has_text = text.shape[0] == n
    nown = ip[IP.nown]
    for i in range(i0, i1):
        f[i, 0] = m[i] * gx
        f[i, 1] = m[i] * gy
        f[i, 2] = m[i] * gz
        if has_ext:
            f[i, 0] += fext[i, 0]
            f[i, 1] += fext[i, 1]
            f[i, 2] += fext[i, 2]
        if has_text:
            tq[i, 0] = text[i, 0]
            tq[i, 1] = text[i, 1]
            tq[i, 2] = text[i, 2]
        else:
            tq[i, 0] = 0.0
            tq[i, 1] = 0.0
            tq[i, 2] = 0.0
    maxov = 0.0
    who_i = -1
    who_j = -1
    ncont = 0
    k = k0
    kcap = xv.shape[0]
    # rows as uint32: Numba wraps a signed index around the array's length at every access
    # (docs/architecture.md, "Unsigned row indices in the contact loops")
    for iu in range(i0, i1):
        i = np.uint32(iu)
        xi0 = x[i, 0]
        xi1 = x[i, 1]
        xi2 = x[i, 2]
        ri = r[i]
        mi = np.uint32(mat[i])
        for s in range(nnb[i]):
            j = np.uint32(nb[i, s])
            wgt = 1.0 if j < nown else 0.5
            loc = j >= i0 and j < i1
            kx = k
            if not loc:  # j in another block: its share waits in row kx of xv
                k += 1
                if kx >= kcap:  # more than counted (see interact_blocks): into the spare row
                    kx = kcap - 1
                xj[kx] = j
                for q in range(XV_SIZE):
                    xv[kx, q] = 0.0
            dx = x[j, 0] - xi0
            dy = x[j, 1] - xi1
            dz = x[j, 2] - xi2
            if px:
                dx -= Lx * math.floor(dx / Lx + 0.5)
            if py:
                dy -= Ly * math.floor(dy / Ly + 0.5)
            if pz:
                dz -= Lz * math.floor(dz / Lz + 0.5)
            d2 = dx * dx + dy * dy + dz * dz
            rs = ri + r[j]
            if d2 >= rs * rs:
                hist[i, s, 0] = 0.0
                hist[i, s, 1] = 0.0
                hist[i, s, 2] = 0.0
                if xon is not None and rolling == 2:
                    rhist[i, s, 0] = 0.0
                    rhist[i, s, 1] = 0.0
                    rhist[i, s, 2] = 0.0
                if hon is not None and heat:
                    if not fused:
                        Hd[i, s] = 0.0
                    if xon is not None and use_age:
                        age[i, s, 0] = 0.0
                    if xon is not None and (imodel >= 0 or radon):
                        d = math.sqrt(d2)
                        if imodel >= 0:
                            if has_cg:
                                c = cgv[i]
                                hind = c * indirect_pp(imodel, ri / c, r[j] / c, d / c, 0.0, mi, mat[j], por[i],
                                                       por[j], tmat, gas)
                            else:
                                hind = indirect_pp(imodel, ri, r[j], d, 0.0, mi, mat[j], por[i], por[j],
                                                   tmat, gas)
                            if fused:
                                qq = hind * (T[j] - T[i])
                                Q[i] += qq
                                if loc:
                                    Q[j] -= qq
                                else:
                                    xv[kx, XV.q] = -qq
                                e_ind += wgt * abs(qq)
                            else:
                                Hi[i, s] = hind
                        if radon:
                            rnear[i, s] = 1 if d < radrange * max(ri, r[j]) else 0
                continue
            ncont += 2 if j < nown else 1
            invd2 = 1.0 / d2
            d = math.sqrt(d2)
            delta = rs - d
            invd = d * invd2
            nx = dx * invd
            ny = dy * invd
            nz = dz * invd
            rj = r[j]
            mj = np.uint32(mat[j])
            # the largest overlap ratio, divided only where it may be the largest: fl(delta / r) >
            # maxov implies delta > maxov r, which the test below keeps (its rounding is 2e-16 of
            # it), so maxov and its pair are those of dividing at every contact (a division is
            # ~15 cycles of a contact's latency-bound chain; docs/benchmarks.md, "Hopper discharge")
            rmin = min(ri, rj)
            if delta > maxov * rmin * OV_MARGIN:
                ov = delta / rmin
                if ov > maxov:
                    maxov = ov
                    who_i = i
                    who_j = j
            # relative velocity of the contact point of i with respect to j
            sx = ri * w[i, 0] + rj * w[j, 0]
            sy = ri * w[i, 1] + rj * w[j, 1]
            sz = ri * w[i, 2] + rj * w[j, 2]
            vrx = v[i, 0] - v[j, 0] + sy * nz - sz * ny
            vry = v[i, 1] - v[j, 1] + sz * nx - sx * nz
            vrz = v[i, 2] - v[j, 2] + sx * ny - sy * nx
            vn = vrx * nx + vry * ny + vrz * nz
            vtx = vrx - vn * nx
            vty = vry - vn * ny
            vtz = vrz - vn * nz
            hx, hy, hz = _rotate_history(hist[i, s, 0], hist[i, s, 1], hist[i, s, 2], dx, dy, dz, invd2, ton)
            rstar = ri * rj / rs
            mstar = 1.0 / (inv_m[i] + inv_m[j])
            fn, ftx, fty, ftz, hx, hy, hz, kn = _pair_law(
                law.model, delta, vn, vtx, vty, vtz, hx, hy, hz, rstar, mstar,
                tab[TAB.estar, mi, mj], tab[TAB.gstar, mi, mj], tab[TAB.damp, mi, mj],
                tab[TAB.mu, mi, mj], tab[TAB.ctr, mi, mj], law.dt, law.lin_kn, law.vchar, law.kt_ratio, ton)
            hist[i, s, 0] = hx
            hist[i, s, 1] = hy
            hist[i, s, 2] = hz
            if hon is not None and pheat:
                tc = 0.0
                vimp = 0.0
                if xon is not None and use_age:
                    tc, vimp = _contact_age(age, i, s, vn, dt)
                if xon is None:
                    # the lean form (full_form): Batchelor & O'Brien conduction or none, the
                    # radius sqrt(R* delta) or the geometric one, times the pair's constant of a
                    # correction (dem.thermal.contact_radius.hertz_radius_factor): no call in the
                    # loop (a cube root or a dispatcher made the shared heat beds 4-6 % slower)
                    hdir = 0.0
                    if bo:
                        if crm == GEOMETRIC:
                            rc = geometric_pp_inv(ri, rj, d, invd)
                        else:
                            rc = math.sqrt(rstar * delta)
                        if crc != 0:
                            rc *= rcf[mi, mj]
                        hdir = dfac * batchelor_obrien_keff(rc, keff[mi, mj])
                    hind = 0.0
                else:
                    fel = (2.0 / 3.0) * kn * delta if model == 0 else kn * delta
                    # contact radius (the dispatcher of dem.thermal.contact_radius, with R* at hand)
                    if crm == HERTZ_OVERLAP:
                        rc = hertz_overlap(rstar, delta)
                    elif crm == HERTZ_FORCE:
                        rc = hertz_force(fel, rstar, tab[TAB.estar, mi, mj])
                    else:
                        rc = geometric_pp_inv(ri, rj, d, invd)
                    if crc != 0:
                        rc = apply_correction(crm, crc, rc, rstar, fel, tab[TAB.estar, mi, mj], ereal[mi, mj])
                    if bo:  # Batchelor & O'Brien with the tabulated series conductivity (linear in
                        # r_c: the same for a parcel as its real law times cg)
                        hdir = dfac * batchelor_obrien_keff(rc, keff[mi, mj])
                    elif dmodel >= 0:
                        if has_cg:   # the real particles' law at the real size and age, scaled
                            c = cgv[i]
                            hdir = dfac * direct_cg_pp(dmodel, c, ri / c, rj / c, d / c, rc / c, mi, mj, tmat, gas,
                                                       tc / c, vimp) \
                                * direct_pp(dmodel, ri / c, rj / c, d / c, rc / c, mi, mj, tmat, gas, tc / c, vimp)
                        else:
                            hdir = dfac * direct_pp(dmodel, ri, rj, d, rc, mi, mj, tmat, gas, tc, vimp)
                    else:
                        hdir = 0.0
                    if xon is None or imodel < 0:
                        hind = 0.0
                    elif has_cg:
                        c = cgv[i]
                        hind = c * indirect_pp(imodel, ri / c, rj / c, d / c, rc / c, mi, mj, por[i], por[j], tmat, gas)
                    else:
                        hind = indirect_pp(imodel, ri, rj, d, rc, mi, mj, por[i], por[j], tmat, gas)
                if fused:
                    dtij = T[j] - T[i]
                    qd = hdir * dtij
                    qsum = qd
                    if xon is not None:
                        qi = hind * dtij
                        qsum = qd + qi
                        e_ind += wgt * abs(qi)
                    Q[i] += qsum
                    if loc:
                        Q[j] -= qsum
                    else:
                        xv[kx, XV.q] = -qsum
                    e_dir += wgt * abs(qd)
                else:
                    Hd[i, s] = hdir
                    if xon is not None and imodel >= 0:
                        Hi[i, s] = hind
                if xon is not None and radon:
                    rnear[i, s] = 1
                if xon is not None and fric >= 0:
                    qf = _contact_heat(fric, tab[TAB.mu, mi, mj], thf, vtx, vty, vtz, ftx, fty, ftz, fn, vn)
                    psi = partition(pmodel, mi, mj, tmat)
                    qgen[i] += psi * qf
                    if loc:
                        qgen[j] += (1.0 - psi) * qf
                    else:
                        xv[kx, XV.psi] = 1.0 - psi
                        xv[kx, XV.qf] = qf
            fx = -fn * nx + ftx
            fy = -fn * ny + fty
            fz = -fn * nz + ftz
            f[i, 0] += fx
            f[i, 1] += fy
            f[i, 2] += fz
            if loc:
                f[j, 0] -= fx
                f[j, 1] -= fy
                f[j, 2] -= fz
            else:
                xv[kx, XV.fx] = fx
                xv[kx, XV.fy] = fy
                xv[kx, XV.fz] = fz
            # torques: (r n) x Ft on both particles
            cx = ny * ftz - nz * fty
            cy = nz * ftx - nx * ftz
            cz = nx * fty - ny * ftx
            tq[i, 0] += ri * cx
            tq[i, 1] += ri * cy
            tq[i, 2] += ri * cz
            if loc:
                tq[j, 0] += rj * cx
                tq[j, 1] += rj * cy
                tq[j, 2] += rj * cz
            else:
                xv[kx, XV.cx] = cx
                xv[kx, XV.cy] = cy
                xv[kx, XV.cz] = cz
            if xon is not None and rolling != 0:
                mur = tab[TAB.mur, mi, mj]
                wx = w[i, 0] - w[j, 0]
                wy = w[i, 1] - w[j, 1]
                wz = w[i, 2] - w[j, 2]
                wn = wx * nx + wy * ny + wz * nz
                wx -= wn * nx
                wy -= wn * ny
                wz -= wn * nz
                if rolling == 1:
                    mx, my, mz = constant_torque(wx, wy, wz, rstar, fn, mur)
                else:
                    qx, qy, qz = _rotate_history(rhist[i, s, 0], rhist[i, s, 1], rhist[i, s, 2], nx, ny, nz, 1.0, None)
                    ii = 1.4 * m[i] * ri * ri
                    ij = 1.4 * m[j] * rj * rj
                    ir = 1.0 / (1.0 / ii + 1.0 / ij)
                    mx, my, mz, qx, qy, qz = epsd(wx, wy, wz, qx, qy, qz, rstar, fn, kn,
                                                  mur, etar, ir, dt)
                    rhist[i, s, 0] = qx
                    rhist[i, s, 1] = qy
                    rhist[i, s, 2] = qz
                tq[i, 0] += mx
                tq[i, 1] += my
                tq[i, 2] += mz
                if loc:
                    tq[j, 0] -= mx
                    tq[j, 1] -= my
                    tq[j, 2] -= mz
                else:
                    xv[kx, XV.mx] = mx
                    xv[kx, XV.my] = my
                    xv[kx, XV.mz] = mz
    # walls (candidates from the wall list built with the neighbour list)
    for iu in range(i0, i1):
        i = np.uint32(iu)
        ri = r[i]
        mi = np.uint32(mat[i])
        for q in range(wnn[i]):
            wl = np.uint32(wnb[i, q])
            if wi[wl, WI.type] == MESH:   # the particle's own contact record (P.mcon;
                # read here: a function taking the arrays would count their references at each row)
                dist = mcon[i, wl, 0]
                nx = mcon[i, wl, 1]
                ny = mcon[i, wl, 2]
                nz = mcon[i, wl, 3]
            else:
                dist, nx, ny, nz = wall_distance(wf, wi, wl, x[i, 0], x[i, 1], x[i, 2], t)
            if not (dist < ri) or dist < -ri:
                whist[i, wl, 0] = 0.0
                whist[i, wl, 1] = 0.0
                whist[i, wl, 2] = 0.0
                if xon is not None and rolling == 2:
                    wrhist[i, wl, 0] = 0.0
                    wrhist[i, wl, 1] = 0.0
                    wrhist[i, wl, 2] = 0.0
                if hon is not None and heat:
                    if xon is not None and use_age:
                        wage[i, wl, 0] = 0.0
                    hw = 0.0
                    if xon is not None and imodel >= 0 and wth[wl, WT.cond] == 1.0 and ri <= dist < math.inf:
                        if has_cg:
                            c = cgv[i]
                            hw = c * c * indirect_pw(imodel, ri / c, dist / c, 0.0, mi, np.int32(wi[wl, WI.mat]),
                                                     por[i], tmat, gas)
                        else:
                            hw = indirect_pw(imodel, ri, dist, 0.0, mi, np.int32(wi[wl, WI.mat]), por[i], tmat, gas)
                    if fused:
                        if hw > 0.0:
                            qq = hw * (wall_temperature(wth, wtab, wl, t) - T[i])
                            Q[i] += qq
                            wtot[wl] += qq * dt
                            wgap[wl] += qq * dt  # no contact: all across the gas gap
                            e_wall += qq
                    # kept in both modes: the heat step reads them (not fused), the records by
                    # face and angle do (dem.thermal.wall_heat, coupling.energy)
                    Hw[i, q] = hw
                    if has_wg:
                        Hwg[i, q] = hw
                continue
            ncont += 2
            delta = ri - dist
            if delta > maxov * ri * OV_MARGIN:   # (as for the pairs above)
                ov = delta / ri
                if ov > maxov:
                    maxov = ov
                    who_i = i
                    who_j = -1 - wl
            mw = np.int32(wi[wl, WI.mat])  # a material index like the particles' (one compiled form per model)
            cpx = x[i, 0] + dist * nx
            cpy = x[i, 1] + dist * ny
            cpz = x[i, 2] + dist * nz
            if wi[wl, WI.type] == MESH:   # a mesh may also oscillate
                mw_ = wi[wl, WI.mesh]
                uwx, uwy, uwz = mesh_point_velocity(mo[mw_, MO.ex], mo[mw_, MO.ex + 1], mo[mw_, MO.ex + 2], mo[mw_, MO.ox],
                                                    mo[mw_, MO.ox + 1], mo[mw_, MO.ox + 2], mo[mw_, MO.ux],
                                                    mo[mw_, MO.ux + 1], mo[mw_, MO.ux + 2], cpx, cpy, cpz)
            else:
                uwx, uwy, uwz = wall_velocity(wf, wl, cpx, cpy, cpz, t)
            sx = ri * w[i, 0]
            sy = ri * w[i, 1]
            sz = ri * w[i, 2]
            vrx = v[i, 0] - uwx + sy * nz - sz * ny
            vry = v[i, 1] - uwy + sz * nx - sx * nz
            vrz = v[i, 2] - uwz + sx * ny - sy * nx
            vn = vrx * nx + vry * ny + vrz * nz
            vtx = vrx - vn * nx
            vty = vry - vn * ny
            vtz = vrz - vn * nz
            hx, hy, hz = _rotate_history(whist[i, wl, 0], whist[i, wl, 1], whist[i, wl, 2], nx, ny, nz, 1.0, ton)
            fn, ftx, fty, ftz, hx, hy, hz, kn = _pair_law(
                law.model, delta, vn, vtx, vty, vtz, hx, hy, hz, ri, m[i],
                tab[TAB.estar, mi, mw], tab[TAB.gstar, mi, mw], tab[TAB.damp, mi, mw],
                tab[TAB.mu, mi, mw], tab[TAB.ctr, mi, mw], law.dt, law.lin_kn, law.vchar, law.kt_ratio, ton)
            whist[i, wl, 0] = hx
            whist[i, wl, 1] = hy
            whist[i, wl, 2] = hz
            if hon is not None and heat:
                cond = wth[wl, WT.cond]
                fel = (2.0 / 3.0) * kn * delta if model == 0 else kn * delta
                tc = 0.0
                vimp = 0.0
                if xon is not None and use_age:
                    tc, vimp = _contact_age(wage, i, wl, vn, dt)
                hw = 0.0
                hwg = 0.0  # the part across the gas gap
                if cond != 0.0:
                    rc = contact_radius_pw(crm, crc, ri, dist, fel, tab[TAB.estar, mi, mw], ereal[mi, mw])
                    if cond == 1.0 and has_cg:
                        c = cgv[i]
                        if dmodel >= 0:
                            hw = dfac * direct_cg_pw(dmodel, c, ri / c, dist / c, rc / c, mi, mw, tmat, gas,
                                                     tc / c, vimp) \
                                * direct_pw(dmodel, ri / c, dist / c, rc / c, mi, mw, tmat, gas, tc / c, vimp)
                        if xon is not None and imodel >= 0:
                            hwg = c * c * indirect_pw(imodel, ri / c, dist / c, rc / c, mi, mw, por[i], tmat, gas)
                            hw += hwg
                    elif cond == 1.0:
                        if dmodel >= 0:
                            hw = dfac * direct_pw(dmodel, ri, dist, rc, mi, mw, tmat, gas, tc, vimp)
                        if xon is not None and imodel >= 0:
                            hwg = indirect_pw(imodel, ri, dist, rc, mi, mw, por[i], tmat, gas)
                            hw += hwg
                    else:
                        hw = math.pi * rc * rc
                if fused:
                    if cond == 1.0:
                        dtw = wall_temperature(wth, wtab, wl, t) - T[i]
                        qq = hw * dtw
                        wgap[wl] += hwg * dtw * dt
                    elif cond == 2.0:
                        qq = hw * wth[wl, WT.q]
                    else:
                        qq = 0.0
                    Q[i] += qq
                    wtot[wl] += qq * dt
                    e_wall += qq
                Hw[i, q] = hw   # both modes (see above)
                if has_wg:
                    Hwg[i, q] = hwg
                if xon is not None and fric >= 0:
                    qf = _contact_heat(fric, tab[TAB.mu, mi, mw], thf, vtx, vty, vtz, ftx, fty, ftz, fn, vn)
                    qgen[i] += partition(pmodel, mi, mw, tmat) * qf
            f[i, 0] += -fn * nx + ftx
            f[i, 1] += -fn * ny + fty
            f[i, 2] += -fn * nz + ftz
            tq[i, 0] += ri * (ny * ftz - nz * fty)
            tq[i, 1] += ri * (nz * ftx - nx * ftz)
            tq[i, 2] += ri * (nx * fty - ny * ftx)
            if xon is not None and rolling != 0:
                mur = tab[TAB.mur, mi, mw]
                wx = w[i, 0]
                wy = w[i, 1]
                wz = w[i, 2]
                wn = wx * nx + wy * ny + wz * nz
                wx -= wn * nx
                wy -= wn * ny
                wz -= wn * nz
                if rolling == 1:
                    mx, my, mz = constant_torque(wx, wy, wz, ri, fn, mur)
                else:
                    qx, qy, qz = _rotate_history(wrhist[i, wl, 0], wrhist[i, wl, 1], wrhist[i, wl, 2], nx, ny, nz, 1.0,
                                                 None)
                    ir = 1.4 * m[i] * ri * ri
                    mx, my, mz, qx, qy, qz = epsd(wx, wy, wz, qx, qy, qz, ri, fn, kn,
                                                  mur, etar, ir, dt)
                    wrhist[i, wl, 0] = qx
                    wrhist[i, wl, 1] = qy
                    wrhist[i, wl, 2] = qz
                tq[i, 0] += mx
                tq[i, 1] += my
                tq[i, 2] += mz
    return maxov, who_i, who_j, ncont, e_dir, e_ind, e_wall, k


@njit(cache=True, error_model="numpy", inline="always")
def blocks(ip):
    """How many blocks of rows the kernels run at once (dem.blocks.block_count) for the threads
    asked for (ip[IP.threads]) and the owned rows (ip[IP.nown])."""
    return block_count(ip[IP.threads], ip[IP.nown])


@njit(cache=True, error_model="numpy", parallel=True, no_cpython_wrapper=True, no_cfunc_wrapper=True)
def interact_blocks(P, C, W, TB, prm, n, t, hon, xon, ton, nblk, heat_flags):
    """The interact phase on ``nblk`` threads: the rows cut into blocks (:func:`block_bounds`),
    each block's pairs and walls by :func:`interact_rows` at once, then, in block order, what
    the pairs across two blocks give their other particle, and the blocks' wall heat. No two
    threads write the same row, and every sum runs in an order fixed by the block count: the
    result depends on the thread count (the order of a row's sum), not on the timing.
    ``heat_flags``: (fused conduction, frictional heating) of :func:`compute_forces`."""
    fused, fgen = heat_flags
    nown = prm.ip[IP.nown]
    bounds = block_bounds(nown, n, nblk)
    nb, nnb = C.nb, C.nnb
    kept = kept_cross_counts(prm.xcnt, n, nown, nblk)
    if kept.shape[0] == nblk + 1:
        cnt = kept
    else:  # the pairs across blocks, counted: each block's rows of xj / xv
        cnt = cross_counts(nb, nnb, np.empty((0, 0), np.uint8), bounds)
        keep_cross_counts(prm.xcnt, cnt, n, nown, nblk)
    # one spare row: a block that met more pairs across blocks than counted writes its surplus
    # there (never past the array), and the check below stops before anything is added
    xj = np.empty(cnt[nblk] + 1, np.int64)
    xv = np.empty((cnt[nblk] + 1, XV_SIZE))
    wt = np.zeros((nblk, W.wtot.shape[0]))
    wg = np.zeros((nblk, W.wgap.shape[0]))
    res = np.empty((nblk, 8))
    for b in prange(nblk):
        r = interact_rows(P, C, W, TB, prm, n, t, hon, xon, ton,
                          Block(bounds[b], bounds[b + 1], cnt[b], xj, xv, wt[b], wg[b]))
        res[b, 0] = r[0]
        res[b, 1] = r[1]
        res[b, 2] = r[2]
        res[b, 3] = r[3]
        res[b, 4] = r[4]
        res[b, 5] = r[5]
        res[b, 6] = r[6]
        res[b, 7] = r[7]
    for b in range(nblk):
        if res[b, 7] != cnt[b + 1]:  # a neighbour list changed without after_build or dem.state
            raise RuntimeError("internal error: the pairs across blocks of rows were not those counted "
                               "for this neighbour list (dem.step.interact_blocks)")
    f, tq, Q, qgen, r = P.force, P.torque, P.heat_rate, P.qgen, P.radius
    for k in range(cnt[nblk]):
        j = xj[k]
        f[j, 0] -= xv[k, XV.fx]
        f[j, 1] -= xv[k, XV.fy]
        f[j, 2] -= xv[k, XV.fz]
        rj = r[j]
        tq[j, 0] += rj * xv[k, XV.cx] - xv[k, XV.mx]
        tq[j, 1] += rj * xv[k, XV.cy] - xv[k, XV.my]
        tq[j, 2] += rj * xv[k, XV.cz] - xv[k, XV.mz]
        if fused:
            Q[j] += xv[k, XV.q]
        if fgen:
            qgen[j] += xv[k, XV.psi] * xv[k, XV.qf]
    for b in range(nblk):
        for q in range(wt.shape[1]):
            W.wtot[q] += wt[b, q]
        for q in range(wg.shape[1]):
            W.wgap[q] += wg[b, q]
    maxov = 0.0
    who_i = -1
    who_j = -1
    ncont = 0
    e_dir = 0.0
    e_ind = 0.0
    e_wall = 0.0
    for b in range(nblk):
        if res[b, 0] > maxov:
            maxov = res[b, 0]
            who_i = int(res[b, 1])
            who_j = int(res[b, 2])
        ncont += int(res[b, 3])
        e_dir += res[b, 4]
        e_ind += res[b, 5]
        e_wall += res[b, 6]
    return maxov, who_i, who_j, ncont, e_dir, e_ind, e_wall


@njit(cache=True, error_model="numpy", inline="always")
def compute_forces(P, C, W, TB, prm, n, t, hon, xon, ton):
    """The interact phase (:func:`interact_rows`) of every row, on one thread (one block, the
    serial order) or on ip[IP.threads] blocks at once (:func:`interact_blocks`); adds the fused
    heat exchanged to the totals. Returns (max overlap ratio, i, j (-1-wall), 2 x contacts)."""
    thi = prm.thi
    fused = hon is not None and thi[TI.heat] != 0 and thi[TI.fused] == 1
    fgen = hon is not None and xon is not None and thi[TI.heat] != 0 and thi[TI.fric] >= 0
    if xon is None and full_form(prm.ip, thi, prm.periodic):
        raise ValueError("internal error: the lean form of the interact phase was called for a scene "
                         "that uses rolling, periodic images or heat models it leaves out (dem.step.full_form)")
    if (ton is not None) != (prm.ip[IP.tangential] == TANGENTIAL_PROJECTED):
        raise ValueError("internal error: the interact phase was compiled for the other tangential model "
                         "than the scene's (ip[IP.tangential], dem.stepper.Stepper.ton)")
    if prm.ip[IP.nmesh] > 0:   # the mesh walls' contacts of this step
        mesh_contacts(P, W, prm.ip[IP.nown], prm.fp[FP.reach], mesh_radiation_range(prm), t,
                      prm.ip[IP.rolling] == 2, P.wage.shape[0] > 0)
    nblk = blocks(prm.ip)
    if nblk == 1:
        maxov, who_i, who_j, ncont, e_dir, e_ind, e_wall, _ = interact_rows(
            P, C, W, TB, prm, n, t, hon, xon, ton,
            Block(np.int64(0), n, np.int64(0), np.empty(0, np.int64), np.empty((0, XV_SIZE)), W.wtot, W.wgap))
    else:
        maxov, who_i, who_j, ncont, e_dir, e_ind, e_wall = interact_blocks(P, C, W, TB, prm, n, t, hon, xon, ton, nblk,
                                                                           (fused, fgen))
    if fused:
        dt = prm.fp[FP.dt]
        tot = prm.tot
        tot[TOT.direct] += e_dir * dt
        tot[TOT.indirect] += e_ind * dt
        tot[TOT.wall] += e_wall * dt
    return maxov, who_i, who_j, ncont


@njit(cache=True, error_model="numpy", inline="always")
def mesh_radiation_range(prm):
    """How far (in radii) a mesh wall's contact records must reach: the sphere of influence of
    the radiation (thermal.radiation_range) when a wall radiates, else 0 (the heat models' reach
    alone: dem.contact.mesh.mesh_contacts)."""
    thi = prm.thi
    if thi[TI.heat] == 1 and thi[TI.rad] >= 0 and thi[TI.wrad] == 1:
        return prm.thf[TF.radrange]
    return 0.0


@njit(cache=True, error_model="numpy")
def build_wall_list(P, n, W, nwalls, reach, skin, srange, t):
    """Walls within reach of each particle; histories of the others are cleared. A mesh wall's
    rows are listed together, when a point of its surface is within reach (dem.contact.mesh; with
    a radiating wall, within ``srange`` radii too: :func:`mesh_radiation_range`); without, their
    contact records end (``mcon``). ``reach`` beyond contact, plus the ``skin``."""
    wf, wi = W.wf, W.wi
    x, r, wnb, wnn, whist, wrhist, mcon = P.position, P.radius, P.wnb, P.wnn, P.whist, P.wrhist, P.mcon
    rolling = wrhist.shape[0] > 0
    rs = reach + skin
    near_mesh = np.zeros((n, W.mmi.shape[0]), np.bool_)
    if P.mtn.shape[0] >= n:   # the triangles the contacts look at until the next build
        mesh_candidates(P, W, n, x, t, reach, skin, srange, near_mesh)
    for i in range(n):
        c = 0
        for wl in range(nwalls):
            if wi[wl, WI.type] == MESH:   # a mesh's rows together, when a point of it is near
                if near_mesh[i, wi[wl, WI.mesh]]:
                    wnb[i, c] = wl
                    c += 1
                else:
                    mcon[i, wl, 0] = math.inf
                    for k in range(3):
                        whist[i, wl, k] = 0.0
                        if rolling:
                            wrhist[i, wl, k] = 0.0
                continue
            dist, nx, ny, nz = wall_distance(wf, wi, wl, x[i, 0], x[i, 1], x[i, 2], t)
            if dist < r[i] + rs and dist > -r[i]:
                wnb[i, c] = wl
                c += 1
            else:
                for k in range(3):
                    whist[i, wl, k] = 0.0
                    if rolling:
                        wrhist[i, wl, k] = 0.0
        wnn[i] = c


@njit(cache=True, error_model="numpy")
def candidates_at_build(P, W, prm, nown):
    """The mesh walls' candidate triangles of every owned particle (P.mtri, P.mtn) found again
    as the last neighbour build found them (:func:`build_wall_list`): from the positions and the
    time of that build (P.x_build, fp[FP.tbuild]) and its skin. A restart calls this
    (advance's PH_CANDIDATES) instead of saving them: the same triangles, in the same order."""
    if P.mtn.shape[0] < nown:
        return
    fp = prm.fp
    mesh_candidates(P, W, nown, P.x_build, fp[FP.tbuild], fp[FP.reach], fp[FP.skin], mesh_radiation_range(prm),
                    np.zeros((nown, W.mmi.shape[0]), np.bool_))


@njit(cache=True, error_model="numpy", inline="always")
def half_kick_implicit(v, f, inv_m, beta, i, h):
    """Half kick of particle i with its fluid drag taken implicitly (semi-implicit drag of a
    coupled run): the drag beta (u_f - v) is evaluated at the new velocity,

        v_new = (v + h (F + beta u_f) / m) / (1 + h beta / m),

    where ``f`` holds F + beta u_f (contacts, gravity, the explicit part of the fluid force)
    and beta, u_f come from the last gas frame. Unconditionally stable for the drag (the
    factor 1 / (1 + h beta / m) is in (0, 1] for any step) and exact at the terminal velocity
    v = u_f + F / beta for any step; to first order in h beta / m the same as the explicit kick.
    (Semi-implicit drag as in e.g. Xiao & Sun 2011, J. Comput. Phys. 230, 7222; docs/models.md.)"""
    a = h * inv_m[i]
    den = 1.0 + a * beta[i]
    for k in range(3):
        v[i, k] = (v[i, k] + a * f[i, k]) / den


@njit(cache=True, error_model="numpy", inline="always")
def half_kick_angular_implicit(w, tq, inv_i, kr, i, h):
    """Half kick of the angular velocity of particle i with the fluid's rotational drag
    torque k_rot (Omega_f - omega) taken implicitly (coupling.toml torque = "rotational_drag"):

        omega_new = (omega + h (T + k_rot Omega_f) / I) / (1 + h k_rot / I),

    ``tq`` holding T + k_rot Omega_f (contacts, the explicit part of the fluid torque). Stable
    for any step (the factor is in (0, 1]) and exact at the steady spin omega = Omega_f + T / k_rot,
    as :func:`half_kick_implicit` for the drag."""
    a = h * inv_i[i]
    den = 1.0 + a * kr[i]
    for k in range(3):
        w[i, k] = (w[i, k] + a * tq[i, k]) / den


@njit(cache=True, error_model="numpy", no_cpython_wrapper=True, no_cfunc_wrapper=True)
def kick_drift_rows(P, prm, i0, i1, dt):
    """First half of velocity Verlet for rows [i0, i1) of the particles ``P`` (dem.schema
    Particles) in the domain of ``prm``: half kick, drift, periodic wrap.
    Returns the largest squared displacement since the last neighbour build (P.x_build).
    ``P.drag_beta`` (a coupled run; else empty): drag coefficients taken implicitly (:func:`half_kick`);
    ``P.rot_drag`` (coupled, fluid torque; else empty): rotational drag taken implicitly
    (:func:`half_kick_angular_implicit`); ``P.inv_mass_eff`` (coupled, virtual mass; else empty): the
    inverse effective mass m + C_vm rho_f V_p of the translational kick instead of 1/m."""
    x, v, w, f, tq, inv_m, inv_i = P.position, P.velocity, P.angular_velocity, P.force, P.torque, P.inv_mass, \
        P.inv_inertia
    beta, xb, kr, inv_me = P.drag_beta, P.x_build, P.rot_drag, P.inv_mass_eff
    lo, hi, periodic = prm.lo, prm.hi, prm.periodic
    half = 0.5 * dt
    L0 = hi[0] - lo[0]
    L1 = hi[1] - lo[1]
    L2 = hi[2] - lo[2]
    maxd2 = 0.0
    n = i1  # (the per-row arrays of a coupled run have every owned row)
    drag = beta.shape[0] >= n
    rdrag = kr.shape[0] >= n
    im = inv_me if inv_me.shape[0] >= n else inv_m
    p0 = periodic[0]  # (read once: the stores to x below could alias the flags for the compiler)
    p1 = periodic[1]
    p2 = periodic[2]
    for i in range(i0, i1):
        if drag:
            half_kick_implicit(v, f, im, beta, i, half)
        else:
            for k in range(3):
                v[i, k] += half * f[i, k] * im[i]
        if rdrag:
            half_kick_angular_implicit(w, tq, inv_i, kr, i, half)
        else:
            for k in range(3):
                w[i, k] += half * tq[i, k] * inv_i[i]
        for k in range(3):
            x[i, k] += dt * v[i, k]
        if p0:
            x[i, 0] -= L0 * math.floor((x[i, 0] - lo[0]) / L0)
        if p1:
            x[i, 1] -= L1 * math.floor((x[i, 1] - lo[1]) / L1)
        if p2:
            x[i, 2] -= L2 * math.floor((x[i, 2] - lo[2]) / L2)
        ddx = x[i, 0] - xb[i, 0]
        ddy = x[i, 1] - xb[i, 1]
        ddz = x[i, 2] - xb[i, 2]
        if p0:
            ddx -= L0 * math.floor(ddx / L0 + 0.5)
        if p1:
            ddy -= L1 * math.floor(ddy / L1 + 0.5)
        if p2:
            ddz -= L2 * math.floor(ddz / L2 + 0.5)
        d2 = ddx * ddx + ddy * ddy + ddz * ddz
        if d2 > maxd2:
            maxd2 = d2
    return maxd2


@njit(cache=True, error_model="numpy")
def kick_rows(i0, i1, v, w, f, tq, inv_m, inv_i, beta, dt, kr, inv_me):
    """Second half kick for rows [i0, i1); returns the last row with a non-finite velocity, or -1.
    ``beta``, ``kr``, ``inv_me`` (a coupled run; else empty): as in :func:`kick_drift`."""
    half = 0.5 * dt
    bad = -1
    n = i1
    drag = beta.shape[0] >= n
    rdrag = kr.shape[0] >= n
    im = inv_me if inv_me.shape[0] >= n else inv_m
    for i in range(i0, i1):
        if drag:
            half_kick_implicit(v, f, im, beta, i, half)
        else:
            for k in range(3):
                v[i, k] += half * f[i, k] * im[i]
        if rdrag:
            half_kick_angular_implicit(w, tq, inv_i, kr, i, half)
        else:
            for k in range(3):
                w[i, k] += half * tq[i, k] * inv_i[i]
        if not (math.isfinite(v[i, 0] + v[i, 1] + v[i, 2])
                and math.isfinite(w[i, 0] + w[i, 1] + w[i, 2])):
            bad = i
    return bad


@njit(cache=True, error_model="numpy", parallel=True)
def _kick_drift_blocks(P, prm, n, dt, nblk):
    bounds = block_bounds(n, n, nblk)
    part = np.zeros(nblk)
    for b in prange(nblk):
        part[b] = kick_drift_rows(P, prm, bounds[b], bounds[b + 1], dt)
    return part.max()


@njit(cache=True, error_model="numpy", inline="always")
def kick_drift(P, prm, n, dt):
    """:func:`kick_drift_rows` of rows [0, n), on ip[IP.threads] blocks of rows at once (the
    same arithmetic for each row: the result does not depend on the thread count)."""
    nblk = blocks(prm.ip)
    if nblk == 1:
        return kick_drift_rows(P, prm, 0, n, dt)
    return _kick_drift_blocks(P, prm, n, dt, nblk)


@njit(cache=True, error_model="numpy", parallel=True)
def _kick_blocks(n, v, w, f, tq, inv_m, inv_i, beta, dt, kr, inv_me, nblk):
    bounds = block_bounds(n, n, nblk)
    part = np.empty(nblk, np.int64)
    for b in prange(nblk):
        part[b] = kick_rows(bounds[b], bounds[b + 1], v, w, f, tq, inv_m, inv_i, beta, dt, kr, inv_me)
    return part.max()


@njit(cache=True, error_model="numpy")
def kick(n, v, w, f, tq, inv_m, inv_i, beta, dt, kr, inv_me, nblk):
    """:func:`kick_rows` of rows [0, n) on ``nblk`` blocks of rows at once (:func:`blocks`; the
    same arithmetic for each row, whatever the thread count)."""
    if nblk == 1:
        return kick_rows(0, n, v, w, f, tq, inv_m, inv_i, beta, dt, kr, inv_me)
    return _kick_blocks(n, v, w, f, tq, inv_m, inv_i, beta, dt, kr, inv_me, nblk)


@njit(cache=True, error_model="numpy", inline="always")
def drift(P, prm, nown, t):
    """Phase "kick-drift": half kick, drift and periodic wrap of the owned rows; returns True
    when the neighbour lists must be rebuilt before the forces at time t (a particle moved
    more than half the skin since the last build, counting the walls' motion)."""
    fp = prm.fp
    maxd2 = kick_drift(P, prm, nown, fp[FP.dt])
    return math.sqrt(maxd2) + fp[FP.vwall] * (t - fp[FP.tbuild]) > 0.5 * fp[FP.skin]


@njit(cache=True, error_model="numpy")
def outside(x, lo, hi, periodic, nown, openfaces):
    """(row, axis) of the first owned particle outside the domain along a closed axis, or (-1, -1);
    beyond a face that is an outlet (bit 2 k + side of ``openfaces``) is not outside."""
    for i in range(nown):
        for k in range(3):
            if periodic[k]:
                continue
            if (x[i, k] < lo[k] and not (openfaces >> (2 * k)) & 1) or \
                    (x[i, k] > hi[k] and not (openfaces >> (2 * k + 1)) & 1):
                return i, k
    return -1, -1


@njit(cache=True, error_model="numpy", no_cpython_wrapper=True, no_cfunc_wrapper=True)
def _slot_arrays(n, slots, C, heat, thi):
    """Per-slot heat arrays (Hd, Hi, rnear) for n rows of ``slots``: kept when the shape is
    unchanged (every used slot is rewritten by the next force evaluation), else new."""
    if not heat or (C.Hd.shape[0] == n and C.Hd.shape[1] == slots):
        return C.Hd, C.Hi, C.rnear
    Hi = np.zeros((n, slots)) if thi[TI.indirect] >= 0 else C.Hi
    rnear = np.zeros((n, slots), np.uint8) if thi[TI.rad] >= 0 else C.rnear
    return np.zeros((n, slots)), Hi, rnear


@njit(cache=True, error_model="numpy", no_cpython_wrapper=True, no_cfunc_wrapper=True)
def after_build(P, C, W, prm, n, nown, t, carry):
    """Phase "rebuild", after the half list of ``C`` (nb, nnb and the history slots, from
    dem.neighbors.build_half_list) was built for rows [0, nown) over [0, n) (the rest are ghosts):
    the wall candidate lists, the per-slot heat arrays (``C``'s kept when their shape fits), the
    local porosity (when measured) and the build position and time. ``carry``: the history was
    carried over by the build (a serial rebuild); otherwise it starts empty here (a first build,
    or after an exchange with other ranks, where dem.parallel.records brings it back). Returns
    the new Pairs. One compiled form serves runs with and without heat (a rebuild is rare)."""
    fp = prm.fp
    ip = prm.ip
    thi = prm.thi
    heat = thi[TI.heat] != 0
    x = P.position
    nb, nnb, hist, rhist, age = C.nb, C.nnb, C.hist, C.rhist, C.age
    if prm.xcnt.shape[0] > 0:  # a new list: the pairs across blocks are counted again
        prm.xcnt[XC.nblk] = 0
    if not carry:
        if ip[IP.rolling] == 2:
            rhist = np.zeros(hist.shape)
        if heat and thi[TI.age] != 0:
            age = np.zeros((nb.shape[0], nb.shape[1], 2))
    build_wall_list(P, nown, W, ip[IP.nwalls], fp[FP.reach], fp[FP.skin], mesh_radiation_range(prm), t)
    if ip[IP.autoskin] != 0:  # what the skin alone brought into the list (a serial run's gap density;
        # a run on several ranks sums nfar and the owned rows over the ranks: dem.stepper)
        nfar = pairs_beyond(x, P.radius, nb, nnb, nown, prm.lo, prm.hi, prm.periodic, fp[FP.reach])
        fp[FP.nfar] = nfar
        fp[FP.gapd] = nfar / (max(nown, 1) * fp[FP.skin])
    for i in range(nown, n):
        P.wnn[i] = 0
    Hd, Hi, rnear = _slot_arrays(n, nb.shape[1], C, heat, thi)
    C = Pairs(nb, nnb, hist, rhist, age, Hd, Hi, rnear)
    if heat and thi[TI.localpor] == 1:
        local_porosity(P, C, W, prm, n, fp[FP.reach], t, 0.2)
    xb = P.x_build
    for i in range(nown):
        for k in range(3):
            xb[i, k] = x[i, k]
    fp[FP.tbuild] = t
    return C


@njit(cache=True, error_model="numpy")
def skin_rate(fp, t):
    """The largest displacement per step at a rebuild the displacement test asked for at time t:
    half the skin over the steps since the last build (what dem.neighbors.adaptive_skin weighs
    against the last build's gap density). An MPI run calls this and the law from Python, their
    ``py_func``: the same IEEE operations, the same skin, and nothing compiled for it."""
    return 0.5 * fp[FP.skin] * fp[FP.dt] / max(t - fp[FP.tbuild], fp[FP.dt])


@njit(cache=True, error_model="numpy", inline="always")
def rebuild(P, C, W, prm, n, t):
    """Phase "rebuild" of a serial run: the half list with the history carried over
    (dem.neighbors.build_half_list), then :func:`after_build`. A run on several ranks, and the
    first build, call the same two functions from dem.simulation around the exchange."""
    fp = prm.fp
    if prm.ip[IP.autoskin] != 0:
        fp[FP.skin] = adaptive_skin(skin_rate(fp, t), fp[FP.gapd], fp[FP.skinmax])
    dom = Box(prm.lo, prm.hi, prm.periodic)
    nb, nnb, hist, rhist, age, _ = build_half_list(P.position, P.radius, n, n, dom, dom, fp[FP.reach], fp[FP.skin],
                                                   C.nb.shape[1], C, prm.ip[IP.threads])
    carry = C.nb.shape[0] == n  # the history was carried over (same rows); a run-time value, so that
    # after_build has one compiled form (a literal True would make a second one)
    return after_build(P, Pairs(nb, nnb, hist, rhist, age, C.Hd, C.Hi, C.rnear), W, prm, n, n, t, carry)


@njit(cache=True, error_model="numpy", inline="always")
def kick_guard(P, prm, nown, maxov, who_i, who_j):
    """Phase "kick" and the mechanical guards: second half kick of the owned rows, then
    (status, particle, other, value): NONFINITE (a non-finite velocity), OVERLAP (the largest
    overlap ratio of the force evaluation above simulation.max_overlap_ratio) or OK."""
    bad = kick(nown, P.velocity, P.angular_velocity, P.force, P.torque, P.inv_mass, P.inv_inertia,
               P.drag_beta, prm.fp[FP.dt], P.rot_drag, P.inv_mass_eff, blocks(prm.ip))
    if bad >= 0:
        return NONFINITE, bad, -1, 0.0
    if maxov > prm.fp[FP.maxov]:
        return OVERLAP, who_i, who_j, maxov
    return OK, -1, -1, 0.0


@njit(cache=True, error_model="numpy", inline="always")
def heat_phase(P, C, W, TB, prm, n, nown, t):
    """Phase "heat": one thermal step of the owned rows on the conductances of the force
    evaluation (dem.thermal.heat.heat_step); (BAD_TEMPERATURE, particle, value) or (OK, -1, 0)."""
    badt = heat_step(P, C, W, TB, prm, n, nown, prm.fp[FP.dt], t, blocks(prm.ip))
    if badt >= 0:
        return BAD_TEMPERATURE, badt, P.temperature[badt]
    return OK, -1, 0.0


@njit(cache=True, error_model="numpy")
def advance(nsteps, s0, n, P, C, W, TB, prm, hon, xon, ton, phases):
    """Advance ``nsteps`` steps from step number s0, time s0 dt (the forces of that time are in
    P.force, P.torque), composing the phases of one step: drift (PH_DRIFT), rebuild when due
    (PH_REBUILD), interact (compute_forces, PH_FORCES), kick + guards (PH_KICK), heat (PH_HEAT).
    Step k ends at time (s0 + k) dt, computed from the step number alone, so that splitting a
    run into calls of any length gives the same arithmetic (bit-identical results).

    Rows [0, nown) are owned (nown = ip[IP.nown]), [nown, n) ghosts. A serial run asks for PH_STEP (every phase;
    mechanics off, a frozen packing: PH_HEAT only, on the conductances computed once). A run on
    several ranks calls one step with one group of phases at a time, the ghost messages between
    the calls: PH_DRIFT returns REBUILD_DUE (no step done) when the lists must be rebuilt,
    which the caller does around its exchange, ending with PH_AFTER_BUILD (after_build on the
    lists it built). Every caller goes through this one compiled function: the phases are
    compiled once per heat switch ``hon``, form ``xon`` (:func:`full_form`) and tangential model
    ``ton`` (dem.contact.tangential; the set-up compiles the default's), and
    compute_forces, after_build and heat_step have no Python entry of their own (each costs
    about 1.5 s of compile to unpack the bundles).

    Returns (steps done, status, particle, other (j, or -1-wall), value, contacts, rebuilds,
    Pairs): the neighbour arrays may have been reallocated. Without PH_KICK (a force evaluation
    alone) particle, other and value are the pair with the largest overlap ratio and that ratio.
    """
    nown = prm.ip[IP.nown]
    nreb = 0
    ncont = 0
    maxov = 0.0
    wi_ = -1
    wj_ = -1
    thi = prm.thi
    heat = hon is not None and thi[TI.heat] != 0
    if phases & PH_CANDIDATES:
        candidates_at_build(P, W, prm, nown)
    for step in range(nsteps):
        t = (s0 + step + 1) * prm.fp[FP.dt]
        if phases & PH_AFTER_BUILD:  # the lists of C were just built from Python (a first build, or
            # after an exchange with other ranks): the rest of the rebuild, history starting empty
            C = after_build(P, C, W, prm, n, nown, t, nsteps < 0)  # False, as a run-time bool: a
            # literal False is typed Literal[bool] or bool depending on what compiled first
        if phases & PH_DRIFT:
            if drift(P, prm, nown, t):
                if not phases & PH_REBUILD:
                    return step, REBUILD_DUE, -1, -1, 0.0, ncont, nreb, C
                i, k = outside(P.position, prm.lo, prm.hi, prm.periodic, nown, prm.ip[IP.openfaces])
                if i >= 0:
                    return step + 1, LEFT_DOMAIN, i, -1, P.position[i, k], ncont, nreb, C
                C = rebuild(P, C, W, prm, n, t)
                nreb += 1
        if phases & PH_FORCES:
            maxov, wi_, wj_, ncont = compute_forces(P, C, W, TB, prm, n, t, hon, xon, ton)
        if phases & PH_KICK:
            status, who, other, value = kick_guard(P, prm, nown, maxov, wi_, wj_)
            if status != OK:
                return step + 1, status, who, other, value, ncont, nreb, C
        if hon is not None:  # (a branch Numba removes before typing when hon is None: the
            # mechanics-only form compiles no heat code)
            if heat and phases & PH_HEAT:
                status, who, value = heat_phase(P, C, W, TB, prm, n, nown, t)
                if status != OK:
                    return step + 1, status, who, -1, value, ncont, nreb, C
    if not phases & PH_KICK:
        return nsteps, OK, wi_, wj_, maxov, ncont, nreb, C
    return nsteps, OK, -1, -1, 0.0, ncont, nreb, C
