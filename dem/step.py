"""The time-step kernel: contact forces, walls, velocity-Verlet integration,
neighbour-list maintenance and the stability guards, run for many steps inside one
compiled call (no Python per step).

The kernel is one cached Numba function with integer model switches (contact law,
rolling model) rather than code generated per scene: the switch is a perfectly
predicted branch (no measurable cost), and every scene reuses the same cached machine
code, so a new scene starts in about a second instead of recompiling.
Parts a scene does not enable are skipped: no rolling history arrays without a rolling
model, no wall loop without walls, no heat terms without a thermal section
(see dem.thermal.kernel for the heat part).
"""
import math
import numpy as np
from numba import njit

from .contact.hertz_mindlin import hertz_mindlin
from .contact.linear import linear_spring_dashpot
from .contact.rolling import constant_torque, epsd
from .contact.walls import wall_distance, wall_velocity, WMAT
from .neighbors import build_half_list

# integer parameters
I_CONTACT, I_ROLLING, I_NWALLS, I_MECH = 0, 1, 2, 3
NIP = 8
# float parameters
F_DT, F_GX, F_GY, F_GZ, F_SKIN, F_REACH, F_VCHAR, F_KTRATIO, F_LINKN, F_ETAR, F_MAXOV, F_VWALL, F_TBUILD = range(13)
NFP = 16
# pair tables
T_ESTAR, T_GSTAR, T_DAMP, T_MU, T_MUR = range(5)
NTAB = 5
# status
OK, OVERLAP, NONFINITE, LEFT_DOMAIN = 0, 1, 2, 3


@njit(cache=True, error_model="numpy")
def _pair_law(model, delta, vn, vtx, vty, vtz, hx, hy, hz, rstar, mstar, estar, gstar,
              damp, mu, dt, lin_kn, vchar, kt_ratio):
    if model == 0:
        return hertz_mindlin(delta, vn, vtx, vty, vtz, hx, hy, hz,
                             rstar, mstar, estar, gstar, damp, mu, dt)
    kn = lin_kn
    if kn <= 0.0:  # Hertz-equivalent stiffness at the characteristic velocity
        sr = math.sqrt(rstar)
        kn = 16.0 / 15.0 * sr * estar * (15.0 * mstar * vchar * vchar / (16.0 * sr * estar)) ** 0.2
    return linear_spring_dashpot(delta, vn, vtx, vty, vtz, hx, hy, hz,
                                 mstar, kn, kt_ratio, damp, mu, dt)


@njit(cache=True, error_model="numpy")
def _rotate_history(h, i, s, nx, ny, nz):
    """Project a stored spring onto the current tangent plane, keeping its length."""
    hx = h[i, s, 0]
    hy = h[i, s, 1]
    hz = h[i, s, 2]
    old2 = hx * hx + hy * hy + hz * hz
    if old2 == 0.0:
        return 0.0, 0.0, 0.0
    hn = hx * nx + hy * ny + hz * nz
    hx -= hn * nx
    hy -= hn * ny
    hz -= hn * nz
    new2 = hx * hx + hy * hy + hz * hz
    if new2 > 0.0:
        sc = math.sqrt(old2 / new2)
        return hx * sc, hy * sc, hz * sc
    return 0.0, 0.0, 0.0


@njit(cache=True, error_model="numpy")
def compute_forces(n, x, v, w, r, m, mat, f, tq, fext, nb, nnb, hist, rhist,
                   wf, wi, wnb, wnn, whist, wrhist, tab, ip, fp, lo, hi, periodic, t):
    """Contact + wall + body forces. Returns (max overlap ratio, i, j (-1-wall), contacts)."""
    dt = fp[F_DT]
    model = ip[I_CONTACT]
    rolling = ip[I_ROLLING]
    nwalls = ip[I_NWALLS]
    lin_kn = fp[F_LINKN]
    vchar = fp[F_VCHAR]
    ktr = fp[F_KTRATIO]
    etar = fp[F_ETAR]
    gx = fp[F_GX]
    gy = fp[F_GY]
    gz = fp[F_GZ]
    Lx = hi[0] - lo[0]
    Ly = hi[1] - lo[1]
    Lz = hi[2] - lo[2]
    px = periodic[0]
    py = periodic[1]
    pz = periodic[2]
    has_ext = fext.shape[0] == n
    for i in range(n):
        f[i, 0] = m[i] * gx
        f[i, 1] = m[i] * gy
        f[i, 2] = m[i] * gz
        if has_ext:
            f[i, 0] += fext[i, 0]
            f[i, 1] += fext[i, 1]
            f[i, 2] += fext[i, 2]
        tq[i, 0] = 0.0
        tq[i, 1] = 0.0
        tq[i, 2] = 0.0
    maxov = 0.0
    who_i = -1
    who_j = -1
    ncont = 0
    for i in range(n):
        xi0 = x[i, 0]
        xi1 = x[i, 1]
        xi2 = x[i, 2]
        ri = r[i]
        mi = mat[i]
        for s in range(nnb[i]):
            j = nb[i, s]
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
                if rolling == 2:
                    rhist[i, s, 0] = 0.0
                    rhist[i, s, 1] = 0.0
                    rhist[i, s, 2] = 0.0
                continue
            ncont += 1
            d = math.sqrt(d2)
            delta = rs - d
            nx = dx / d
            ny = dy / d
            nz = dz / d
            rj = r[j]
            mj = mat[j]
            ov = delta / min(ri, rj)
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
            hx, hy, hz = _rotate_history(hist, i, s, nx, ny, nz)
            rstar = ri * rj / rs
            mstar = m[i] * m[j] / (m[i] + m[j])
            fn, ftx, fty, ftz, hx, hy, hz, kn = _pair_law(
                model, delta, vn, vtx, vty, vtz, hx, hy, hz, rstar, mstar,
                tab[T_ESTAR, mi, mj], tab[T_GSTAR, mi, mj], tab[T_DAMP, mi, mj],
                tab[T_MU, mi, mj], dt, lin_kn, vchar, ktr)
            hist[i, s, 0] = hx
            hist[i, s, 1] = hy
            hist[i, s, 2] = hz
            fx = -fn * nx + ftx
            fy = -fn * ny + fty
            fz = -fn * nz + ftz
            f[i, 0] += fx
            f[i, 1] += fy
            f[i, 2] += fz
            f[j, 0] -= fx
            f[j, 1] -= fy
            f[j, 2] -= fz
            # torques: (r n) x Ft on both particles
            cx = ny * ftz - nz * fty
            cy = nz * ftx - nx * ftz
            cz = nx * fty - ny * ftx
            tq[i, 0] += ri * cx
            tq[i, 1] += ri * cy
            tq[i, 2] += ri * cz
            tq[j, 0] += rj * cx
            tq[j, 1] += rj * cy
            tq[j, 2] += rj * cz
            if rolling != 0:
                mur = tab[T_MUR, mi, mj]
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
                    qx, qy, qz = _rotate_history(rhist, i, s, nx, ny, nz)
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
                tq[j, 0] -= mx
                tq[j, 1] -= my
                tq[j, 2] -= mz
    # walls (candidates from the wall list built with the neighbour list)
    for i in range(n):
        ri = r[i]
        mi = mat[i]
        for q in range(wnn[i]):
            wl = wnb[i, q]
            dist, nx, ny, nz = wall_distance(wf, wi, wl, x[i, 0], x[i, 1], x[i, 2], t)
            if not (dist < ri) or dist < -ri:
                whist[i, wl, 0] = 0.0
                whist[i, wl, 1] = 0.0
                whist[i, wl, 2] = 0.0
                if rolling == 2:
                    wrhist[i, wl, 0] = 0.0
                    wrhist[i, wl, 1] = 0.0
                    wrhist[i, wl, 2] = 0.0
                continue
            ncont += 1
            delta = ri - dist
            ov = delta / ri
            if ov > maxov:
                maxov = ov
                who_i = i
                who_j = -1 - wl
            mw = wi[wl, WMAT]
            cpx = x[i, 0] + dist * nx
            cpy = x[i, 1] + dist * ny
            cpz = x[i, 2] + dist * nz
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
            hx, hy, hz = _rotate_history(whist, i, wl, nx, ny, nz)
            fn, ftx, fty, ftz, hx, hy, hz, kn = _pair_law(
                model, delta, vn, vtx, vty, vtz, hx, hy, hz, ri, m[i],
                tab[T_ESTAR, mi, mw], tab[T_GSTAR, mi, mw], tab[T_DAMP, mi, mw],
                tab[T_MU, mi, mw], dt, lin_kn, vchar, ktr)
            whist[i, wl, 0] = hx
            whist[i, wl, 1] = hy
            whist[i, wl, 2] = hz
            f[i, 0] += -fn * nx + ftx
            f[i, 1] += -fn * ny + fty
            f[i, 2] += -fn * nz + ftz
            tq[i, 0] += ri * (ny * ftz - nz * fty)
            tq[i, 1] += ri * (nz * ftx - nx * ftz)
            tq[i, 2] += ri * (nx * fty - ny * ftx)
            if rolling != 0:
                mur = tab[T_MUR, mi, mw]
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
                    qx, qy, qz = _rotate_history(wrhist, i, wl, nx, ny, nz)
                    ir = 1.4 * m[i] * ri * ri
                    mx, my, mz, qx, qy, qz = epsd(wx, wy, wz, qx, qy, qz, ri, fn, kn,
                                                  mur, etar, ir, dt)
                    wrhist[i, wl, 0] = qx
                    wrhist[i, wl, 1] = qy
                    wrhist[i, wl, 2] = qz
                tq[i, 0] += mx
                tq[i, 1] += my
                tq[i, 2] += mz
    return maxov, who_i, who_j, ncont


@njit(cache=True, error_model="numpy")
def build_wall_list(x, r, n, wf, wi, nwalls, reach, t, wnb, wnn, whist, wrhist):
    """Walls within reach of each particle; histories of the others are cleared."""
    rolling = wrhist.shape[0] == n
    for i in range(n):
        c = 0
        for wl in range(nwalls):
            dist, nx, ny, nz = wall_distance(wf, wi, wl, x[i, 0], x[i, 1], x[i, 2], t)
            if dist < r[i] + reach and dist > -r[i]:
                wnb[i, c] = wl
                c += 1
            else:
                for k in range(3):
                    whist[i, wl, k] = 0.0
                    if rolling:
                        wrhist[i, wl, k] = 0.0
        wnn[i] = c


@njit(cache=True, error_model="numpy")
def advance(nsteps, t0, n, x, v, w, r, m, inv_m, inv_i, mat, f, tq, fext, xb,
            nb, nnb, hist, rhist, age, wf, wi, wnb, wnn, whist, wrhist, tab, ip, fp, lo, hi, periodic):
    """Advance ``nsteps`` velocity-Verlet steps from time t0 (f, tq hold the forces at t0).

    Returns (steps done, status, particle, other (j, or -1-wall), value, contacts,
    rebuilds, nb, nnb, hist, rhist, age): the neighbour arrays may have been reallocated.
    """
    dt = fp[F_DT]
    half = 0.5 * dt
    skin = fp[F_SKIN]
    lim2 = 0.25 * skin * skin
    maxov_bound = fp[F_MAXOV]
    L0 = hi[0] - lo[0]
    L1 = hi[1] - lo[1]
    L2 = hi[2] - lo[2]
    nreb = 0
    ncont = 0
    nwalls = ip[I_NWALLS]
    for step in range(nsteps):
        t = t0 + (step + 1) * dt
        maxd2 = 0.0
        for i in range(n):
            for k in range(3):
                v[i, k] += half * f[i, k] * inv_m[i]
                w[i, k] += half * tq[i, k] * inv_i[i]
                x[i, k] += dt * v[i, k]
            if periodic[0]:
                x[i, 0] -= L0 * math.floor((x[i, 0] - lo[0]) / L0)
            if periodic[1]:
                x[i, 1] -= L1 * math.floor((x[i, 1] - lo[1]) / L1)
            if periodic[2]:
                x[i, 2] -= L2 * math.floor((x[i, 2] - lo[2]) / L2)
            ddx = x[i, 0] - xb[i, 0]
            ddy = x[i, 1] - xb[i, 1]
            ddz = x[i, 2] - xb[i, 2]
            if periodic[0]:
                ddx -= L0 * math.floor(ddx / L0 + 0.5)
            if periodic[1]:
                ddy -= L1 * math.floor(ddy / L1 + 0.5)
            if periodic[2]:
                ddz -= L2 * math.floor(ddz / L2 + 0.5)
            d2 = ddx * ddx + ddy * ddy + ddz * ddz
            if d2 > maxd2:
                maxd2 = d2
        if math.sqrt(maxd2) + fp[F_VWALL] * (t - fp[F_TBUILD]) > 0.5 * skin:
            for i in range(n):
                for k in range(3):
                    if not periodic[k] and (x[i, k] < lo[k] or x[i, k] > hi[k]):
                        return (step + 1, LEFT_DOMAIN, i, -1, x[i, k], ncont, nreb,
                                nb, nnb, hist, rhist, age)
            nb, nnb, hist, rhist, age, _ = build_half_list(
                x, r, n, lo, hi, periodic, fp[F_REACH], skin, nb.shape[1],
                nb, nnb, hist, rhist, age)
            build_wall_list(x, r, n, wf, wi, nwalls, fp[F_REACH] + skin, t, wnb, wnn, whist, wrhist)
            xb[:n] = x[:n]
            fp[F_TBUILD] = t
            nreb += 1
        maxov, wi_, wj_, ncont = compute_forces(
            n, x, v, w, r, m, mat, f, tq, fext, nb, nnb, hist, rhist,
            wf, wi, wnb, wnn, whist, wrhist, tab, ip, fp, lo, hi, periodic, t)
        bad = -1
        for i in range(n):
            for k in range(3):
                v[i, k] += half * f[i, k] * inv_m[i]
                w[i, k] += half * tq[i, k] * inv_i[i]
            if not (math.isfinite(v[i, 0] + v[i, 1] + v[i, 2])
                    and math.isfinite(w[i, 0] + w[i, 1] + w[i, 2])):
                bad = i
        if bad >= 0:
            return (step + 1, NONFINITE, bad, -1, 0.0, ncont, nreb, nb, nnb, hist, rhist, age)
        if maxov > maxov_bound:
            return (step + 1, OVERLAP, wi_, wj_, maxov, ncont, nreb, nb, nnb, hist, rhist, age)
    return nsteps, OK, -1, -1, 0.0, ncont, nreb, nb, nnb, hist, rhist, age
