"""Indirect conduction through the interstitial fluid (particle-fluid-particle
and particle-fluid-wall), conductances H [W/K] with Q_i = H (T_j - T_i).

Main source: Rangel (2021) survey, reference 002 ("Indirect conduction"):
Voronoi polyhedron models A and B (Cheng et al. 1999; Gan et al. 2016;
Chen et al. 2019; Zhou et al. 2009 porosity estimates), surrounding layer
(Rong & Horio 1999; Musser 2011; closed wall form of reference 003), and
Vargas & McCarthy (2002).

Common conventions of the dispatchers (indirect_pp / indirect_pw):
* cut-off (Zhou et al. 2009): H = 0 when the surface gap d - Ri - Rj is
  >= cutoff * min(Ri, Rj) (wall: d - R >= cutoff * R); cutoff = inf disables.
* Lower integration radius of the Voronoi and surrounding-layer models:
  r_low = max(rc, Rc_geo), Rc_geo = radius of the geometric intersection
  circle (0 when apart), so that no fluid path of negative length (and no
  spurious 1/S contribution of the overlapped region) is integrated; ref 002
  uses Rc_geo for Musser's model and "Rc" (0 when apart) for the others.
* Voronoi face radius from the local porosity (Zhou et al. 2009):
  A_n = 0.985 R^2 (1-eps)^(-2/3), r_ij = sqrt(A_n/pi) = 0.560 R (1-eps)^(-1/3);
  for a pair eps = (eps_i + eps_j)/2 and R = (Ri+Rj)/2 for the Cheng models
  (mono-size formulas applied with the average radius, Norouzi et al. 2016),
  R = min(Ri, Rj) for the Gan/Chen multi-size models (ref 002 uses R_i; the
  symmetric choice keeps H_ij = H_ji so that energy is conserved).

The dispatchers indirect_pp / indirect_pw are generated from the records (``RECORDS`` at the
end) by dem.thermal.dispatch: they apply the cut-off, compute r_low, the clamped porosity and
the conductivities, then call the record's ``pp`` law
(Ri, Rj, d, rc, r_low, por, Rmin, kf, ki, kj, mi, mj, tmat, gas) or ``pw`` law
(R, d, rc, r_low, por, kf, kp, mp, mw, tmat, gas); -1 for unknown ids.
"""
import math

import numba

from ._quad import KIND_VORONOI_A_PP, KIND_VORONOI_A_PW, gk_adaptive
from ._surrounding_layer import surrounding_layer_log
from .contact_radius import geometric_pp, geometric_pw
from .direct import gas_parameter_m, series_conductivity
from .records import ModelRecord
from .registry import (ACCOM, CORE_RATIO, CUTOFF, FILL_ANGLE, GAMMA_RATIO, INDIRECT_CHEN_VORONOI_B,
                       INDIRECT_CHENG_VORONOI_A, INDIRECT_CHENG_VORONOI_B, INDIRECT_GAN_VORONOI_A,
                       INDIRECT_MUSSER, INDIRECT_RONG_HORIO, INDIRECT_VARGAS_MCCARTHY, K_COND, K_LIQ, KF,
                       LAYER, MEAN_FREE_PATH, MIN_SEP, PR, QUAD_TOL)

EPSREL = 1e-4  # default quadrature tolerance of the pure model functions (scene: quadrature_tolerance)


# ----------------------------------------------------------------- Zhou 2009 estimates
@numba.njit(cache=True, error_model="numpy")
def zhou_2009_face_area(R, por):
    """Voronoi face area A_n = 0.985 R^2 (1 - eps)^(-2/3) [m^2] (Zhou et al. 2009; ref 002)."""
    return 0.985 * R * R * (1.0 - por) ** (-2.0 / 3.0)


@numba.njit(cache=True, error_model="numpy")
def zhou_2009_face_radius(R, por):
    """Voronoi face (double cone base) radius r_ij = sqrt(A_n/pi) = 0.560 R (1-eps)^(-1/3) [m]."""
    return math.sqrt(zhou_2009_face_area(R, por) / math.pi)


# ----------------------------------------------------------------- Voronoi model A
@numba.njit(cache=True, error_model="numpy")
def cheng_1999_voronoi_a(Rp, d, r_low, ki, kj, kf, rij, tol=EPSREL):
    """Cheng, Yu & Zulli (1999) Voronoi model A, mono-size [W/K] (ref 002):

    H = int_{r_low}^{r_sf} 2 pi r dr / [ (sqrt(Rp^2 - r^2) - d r/(2 r_ij))/k_bar
                                         + (d - 2 sqrt(Rp^2 - r^2))/k_f ]
    r_sf = Rp r_ij / sqrt(r_ij^2 + (d/2)^2); 1/k_bar = 1/ki + 1/kj (the solid
    path length d_p counted in both particles, 2 d_p/k_p for one material).
    For multi-size pairs call with Rp = (Ri + Rj)/2 (Norouzi et al. 2016).
    """
    rsf = Rp * rij / math.sqrt(rij * rij + 0.25 * d * d)
    if rsf <= r_low:
        return 0.0
    p = (ki, kj, kf, d, Rp, Rp, 0.5 * d, 0.5 * d, rij, rij)
    return gk_adaptive(KIND_VORONOI_A_PP, r_low, rsf, p, tol)


@numba.njit(cache=True, error_model="numpy")
def gan_2016_voronoi_a(Ri, Rj, d, r_low, ki, kj, kf, rij, tol=EPSREL):
    """Gan, Zhou & Yu (2016) Voronoi model A for multi-size spheres [W/K] (ref 002):

    H = int_{r_low}^{r_sf} 2 pi r dr / [ (b_i - D_i r/r_i')/k_i + (b_j - D_j r/r_j')/k_j
                                         + (d - b_i - b_j)/k_f ],  b = sqrt(R^2 - r^2)
    D_i = (Ri^2 - Rj^2 + d^2)/(2 d) (distance to the radical plane; equal to
    sqrt(Ri^2 - Rc^2) for the geometric contact radius), D_j = d - D_i.
    The upper radius is set by the smaller sphere s: r_sf = R_s r_ij/sqrt(r_ij^2 + D_s^2),
    its cone uses r_ij, the larger sphere's cone uses r' = D_l r_sf/sqrt(R_l^2 - r_sf^2)
    so that both solid paths vanish at r_sf (ref 002 with i <-> j symmetrised).
    """
    Di = (Ri * Ri - Rj * Rj + d * d) / (2.0 * d)
    Dj = d - Di
    if Ri <= Rj:
        rsf = Ri * rij / math.sqrt(rij * rij + Di * Di)
        rci = rij
        rcj = Dj * rsf / math.sqrt(Rj * Rj - rsf * rsf) if Rj > rsf else rij
    else:
        rsf = Rj * rij / math.sqrt(rij * rij + Dj * Dj)
        rcj = rij
        rci = Di * rsf / math.sqrt(Ri * Ri - rsf * rsf) if Ri > rsf else rij
    if rsf <= r_low or Di <= 0.0 or Dj <= 0.0:
        return 0.0
    p = (ki, kj, kf, d, Ri, Rj, Di, Dj, rci, rcj)
    return gk_adaptive(KIND_VORONOI_A_PP, r_low, rsf, p, tol)


@numba.njit(cache=True, error_model="numpy")
def voronoi_a_wall(R, d, r_low, kp, kf, rij, tol=EPSREL):
    """Voronoi model A, particle-wall [W/K] (ref 002, interaction with walls):

    H = int_{r_low}^{r_sf} 2 pi r dr / [ (sqrt(R^2 - r^2) - d r/r_ij)/k_p + (d - sqrt(R^2 - r^2))/k_f ]
    r_sf = R r_ij/sqrt(r_ij^2 + d^2); d = centre-to-wall distance; no conduction in the wall.
    """
    rsf = R * rij / math.sqrt(rij * rij + d * d)
    if rsf <= r_low:
        return 0.0
    p = (kp, kf, d, R, rij, 0.0, 0.0, 0.0, 0.0, 0.0)
    return gk_adaptive(KIND_VORONOI_A_PW, r_low, rsf, p, tol)


# ----------------------------------------------------------------- Voronoi model B
@numba.njit(cache=True, error_model="numpy")
def _voronoi_b_log(a, b, h, rij, r_low):
    """(pi/b) ln[(a - b cos th0)/(a - b cos thc)] with cos th = h/sqrt(r^2 + h^2) at r = r_ij
    and r = r_low (h: half the centre distance for pairs, the wall distance for walls);
    0 where the logarithm's argument is not positive. Shared by the pair and wall forms."""
    num = a - b * h / math.sqrt(rij * rij + h * h)
    den = a - b * h / math.sqrt(r_low * r_low + h * h)
    if den <= 0.0 or num <= 0.0:
        return 0.0
    return math.pi / b * math.log(num / den)


@numba.njit(cache=True, error_model="numpy")
def cheng_1999_voronoi_b(Rp, d, r_low, ki, kj, kf, rij, core):
    """Cheng, Yu & Zulli (1999) Voronoi model B, mono-size [W/K] (ref 002):

    H = (pi/b) ln[(a - b cos th0)/(a - b cos thc)],
    a = (1/(2 k_bar)) (1/r_c - 1/Rp) + 1/(k_f Rp), b = 2/(k_f d),
    cos th0 = (d/2)/sqrt(r_ij^2 + (d/2)^2), cos thc = (d/2)/sqrt(Rc^2 + (d/2)^2),
    r_c = core * Rp the isothermal core radius (Cheng: 0.5 Rp), 1/k_bar = 1/ki + 1/kj.
    """
    if rij <= r_low:
        return 0.0
    rcore = core * Rp
    kbar = series_conductivity(ki, kj)
    a = (1.0 / rcore - 1.0 / Rp) / (2.0 * kbar) + 1.0 / (kf * Rp)
    return _voronoi_b_log(a, 2.0 / (kf * d), 0.5 * d, rij, r_low)


@numba.njit(cache=True, error_model="numpy")
def voronoi_b_wall(R, d, r_low, kp, kf, rij, core):
    """Voronoi model B, particle-wall [W/K] (ref 002, interaction with walls):

    H = (pi/b) ln[(a - b cos th0)/(a - b cos thc)],
    a = (1/(2 k_p))(1/r_c - 1/R) + 1/(2 k_f R), b = 1/(2 k_f d),
    cos th0 = d/sqrt(r_ij^2 + d^2), cos thc = d/sqrt(Rc^2 + d^2).
    """
    if rij <= r_low:
        return 0.0
    rcore = core * R
    a = (1.0 / rcore - 1.0 / R) / (2.0 * kp) + 1.0 / (2.0 * kf * R)
    return _voronoi_b_log(a, 1.0 / (2.0 * kf * d), d, rij, r_low)


@numba.njit(cache=True, error_model="numpy")
def chen_2019_voronoi_b(Ri, Rj, d, r_low, ki, kj, kf, An, core):
    """Chen et al. (2019) Voronoi model B for multi-size spheres [W/K] (ref 002):

    g_i = Ri/d, g_j = Rj/d, dg = g_j - g_i,
    A = (k_i + k_f (Ri/r_c,i - 1))/(k_i g_i), B = (k_j + k_f (Rj/r_c,j - 1))/(k_j g_j),
    Lam = (1 + dg A)(1 - dg B),
    del_max = (sqrt(1 + 4 A_n/(pi d^2 (1 - dg^2))) - dg)/2,
    del_min = (sqrt(1 + 4 Rc^2/(d^2 (1 - dg^2))) - dg)/2,
    X = ((A + B) del + dg B - 1)/sqrt|Lam|,
    Lam > 0: H = pi k_f d (1 - dg^2)/(2 sqrt|Lam|) ln|(1 - Y1)/(1 + Y1)|, Y1 = (Xmax - Xmin)/(1 - Xmax Xmin)
    Lam < 0: H = pi k_f d (1 - dg^2)/(2 sqrt|Lam|) atan(Y2),                Y2 = (Xmax - Xmin)/(1 + Xmax Xmin)
    Lam = 0: H = pi k_f d (1 - dg^2)/(A + B) (1/del_min - 1/del_max).
    r_c = core * R (isothermal core). Reduces to cheng_1999_voronoi_b for Ri = Rj.
    """
    rij2 = An / math.pi
    if rij2 <= r_low * r_low:
        return 0.0
    gi = Ri / d
    gj = Rj / d
    dg = gj - gi
    om = 1.0 - dg * dg
    if om <= 0.0:
        return 0.0
    A = (ki + kf * (1.0 / core - 1.0)) / (ki * gi)
    B = (kj + kf * (1.0 / core - 1.0)) / (kj * gj)
    lam = (1.0 + dg * A) * (1.0 - dg * B)
    dmax = 0.5 * (math.sqrt(1.0 + 4.0 * An / (math.pi * d * d * om)) - dg)
    dmin = 0.5 * (math.sqrt(1.0 + 4.0 * r_low * r_low / (d * d * om)) - dg)
    pref = math.pi * kf * d * om
    if lam == 0.0:
        return pref / (A + B) * (1.0 / dmin - 1.0 / dmax)
    sl = math.sqrt(abs(lam))
    xmax = ((A + B) * dmax + dg * B - 1.0) / sl
    xmin = ((A + B) * dmin + dg * B - 1.0) / sl
    if lam > 0.0:
        y1 = (xmax - xmin) / (1.0 - xmax * xmin)
        return pref / (2.0 * sl) * math.log(abs((1.0 - y1) / (1.0 + y1)))
    y2 = (xmax - xmin) / (1.0 + xmax * xmin)
    return pref / (2.0 * sl) * math.atan(y2)


# ----------------------------------------------------------------- surrounding layer
@numba.njit(cache=True, error_model="numpy")
def surrounding_layer_upper_radius(Ri, Rj, d, layer):
    """Upper radius R_f [m] of the surrounding-layer integral (ref 002, Musser 2011):

    R_f = sqrt((Rk + dk)^2 - (((Rk + dk)^2 - Rl^2 + d^2)/(2 d))^2), Rk = max, Rl = min,
    dk = layer * Rk; bounded by the smaller sphere: R_f = Rl if d <= sqrt((Rk+dk)^2 - Rl^2).
    0 if the layer does not reach the other sphere.
    """
    Rk = max(Ri, Rj)
    Rl = min(Ri, Rj)
    L2 = (Rk + layer * Rk) ** 2
    if d <= math.sqrt(max(L2 - Rl * Rl, 0.0)):
        return Rl
    x = (L2 - Rl * Rl + d * d) / (2.0 * d)
    v = L2 - x * x
    if v <= 0.0:
        return 0.0
    return min(math.sqrt(v), Rl)


@numba.njit(cache=True, error_model="numpy")
def _gap_floor_radius(Ri, Rj, d, S):
    # radius where the gap d - sqrt(Ri^2-r^2) - sqrt(Rj^2-r^2) equals S:
    # intersection circle of the two spheres brought to centre distance d - S
    D = d - S
    if D >= Ri + Rj:
        return 0.0
    if D <= abs(Ri - Rj):
        return min(Ri, Rj)
    return geometric_pp(Ri, Rj, D)


@numba.njit(cache=True, error_model="numpy", inline="always")
def _surrounding_layer_pp(Ri, Rj, d, r_low, kf, layer, S, tol):
    Rf = surrounding_layer_upper_radius(Ri, Rj, d, layer)
    if Rf <= r_low:
        return 0.0
    rS = min(_gap_floor_radius(Ri, Rj, d, S), Rf)
    H = 0.0
    if rS > r_low:
        H += kf * math.pi * (rS * rS - r_low * r_low) / S  # gap <= S: uniform layer S
    a = max(r_low, rS)
    if Rf > a:
        # gap >= S on [a, R_f]: integrate in ln(gap), where the integrand is smooth
        ga = max(d - math.sqrt(max(Ri * Ri - a * a, 0.0)) - math.sqrt(max(Rj * Rj - a * a, 0.0)), S)
        gf = d - math.sqrt(max(Ri * Ri - Rf * Rf, 0.0)) - math.sqrt(max(Rj * Rj - Rf * Rf, 0.0))
        if gf > ga:
            H += kf * math.pi * surrounding_layer_log(math.log(ga), math.log(gf), d, Ri, Rj, tol)
    return H


@numba.njit(cache=True, error_model="numpy")
def musser_2011_surrounding_layer(Ri, Rj, d, r_low, kf, layer, S, tol=EPSREL):
    """Surrounding layer model, Musser (2011) multi-size form [W/K] (ref 002, ref 003):

    H = k_f int_{Rc}^{R_f} 2 pi r dr / max(S, d - sqrt(Ri^2 - r^2) - sqrt(Rj^2 - r^2))
    Rc = contact radius (0 when apart; the contact area is left to direct
    conduction), R_f = surrounding_layer_upper_radius (layer of the larger
    sphere, bounded by the smaller sphere), S = minimum conduction distance.
    Evaluated as k_f pi (r_S^2 - Rc^2)/S over the part where the gap is < S
    (r_S in closed form) plus adaptive Gauss-Kronrod quadrature of the rest in the
    variable w = ln(gap), where the integrand is smooth (exact change of variables:
    u = r^2, du/dgap = 2 b_i b_j / (d - gap), see _surrounding_layer.py): one
    15-point panel gives ~1e-15.
    """
    return _surrounding_layer_pp(Ri, Rj, d, r_low, kf, layer, S, tol)


@numba.njit(cache=True, error_model="numpy")
def rong_horio_1999_surrounding_layer(Ri, Rj, d, kf, layer, S, tol=EPSREL):
    """Surrounding layer model of Rong & Horio (1999) [W/K] (ref 002):

    H = k_f int_0^{R_f} 2 pi r dr / max(S, d - sqrt(Ri^2 - r^2) - sqrt(Rj^2 - r^2)).
    R&H (mono-size) integrate over theta from theta_1 to theta_2 and add the
    uniform conduction k_f pi (Rp sin theta_1)^2 / S across the central area
    where the surfaces are closer than S; this is the same integral written
    in r = Rp sin theta with the max(S, .) floor (which also keeps it finite
    for overlaps larger than S, where the original theta_1 gives a divergent
    integrand). Unlike Musser, the contact area is included (lower limit 0),
    so it should not be combined with a direct conduction model.
    """
    return _surrounding_layer_pp(Ri, Rj, d, 0.0, kf, layer, S, tol)


@numba.njit(cache=True, error_model="numpy")
def surrounding_layer_wall(R, d, r_low, kf, layer, S):
    """Surrounding layer, particle-wall [W/K] (ref 002 "contact with walls", ref 003):

    H = k_f int_{Rc}^{R_f} 2 pi r dr / max(S, d - sqrt(R^2 - r^2)),
    R_f = sqrt((R + delta)^2 - d^2) (R_f = R if d <= sqrt((R+delta)^2 - R^2)).
    Closed form (refs 002/003, Morris 2015, Lattanzi & Hrenya 2017, Lu 2017):
    int_{r_in}^{r_out} = 2 pi k_f R ((a+1) ln(|b - a - 1|/|a - c + 1|) + b - c),
    a = (d - R)/R, b = sqrt(1 - r_out^2), c = sqrt(1 - r_in^2), r_out = R_f/R,
    r_in = sqrt(1 - (S/R - a - 1)^2) if d <= R + S else 0. The closed form of
    ref 003 omits the central part where the gap is < S; we add it,
    k_f pi (r_in^2 R^2 - Rc^2)/S, so that the result equals the integral above.
    """
    delta = layer * R
    if d >= R + delta:
        return 0.0
    L2 = (R + delta) ** 2
    if d <= math.sqrt(max(L2 - R * R, 0.0)):
        rout = 1.0
    else:
        rout = math.sqrt(L2 - d * d) / R
    a = (d - R) / R
    if d > R + S:
        rin = 0.0
    else:
        t = S / R - a - 1.0
        rin = math.sqrt(max(1.0 - t * t, 0.0))
    rlo = r_low / R
    H = 0.0
    if rin > rlo:
        rr = min(rin, rout)
        H += kf * math.pi * R * R * (rr * rr - rlo * rlo) / S
    rin = max(rin, rlo)
    if rout <= rin:
        return H
    b = math.sqrt(max(1.0 - rout * rout, 0.0))
    c = math.sqrt(max(1.0 - rin * rin, 0.0))
    H += 2.0 * math.pi * kf * R * ((a + 1.0) * math.log(abs(b - a - 1.0) / abs(a - c + 1.0)) + b - c)
    return H


# ----------------------------------------------------------------- Vargas & McCarthy
@numba.njit(cache=True, error_model="numpy")
def _seg_area(Rp, x):
    # area between the sphere profile and its tangent plane for 0 <= r <= x:
    # int_0^x (Rp - sqrt(Rp^2 - r^2)) dr
    return x * Rp - 0.5 * (Rp * Rp * math.asin(min(x / Rp, 1.0)) + x * math.sqrt(max(Rp * Rp - x * x, 0.0)))


@numba.njit(cache=True, error_model="numpy")
def vargas_mccarthy_2002(Rp, rc, kg, M, k_liq, phi):
    """Vargas & McCarthy (2002) stagnant interstitial fluid conductance [W/K] (ref 002).

    H = k_l A_l / l_l + k_g* A_g / l_g,  k_g* = k_g / (1 + M/l_g)  (M: gas parameter, m).
    Dry (phi = 0, ref 002 "only gas"):  A_g = 2 pi Rp^2 - pi Rc^2,
        l_g = Rp^2 (1 - pi/4)/(Rp - Rc), i.e.
        H = k_g* 2 pi (1 - (Rc/Rp)^2/2)(Rp - Rc)/(1 - pi/4).
    Liquid bridge of filling angle phi (R_cap = Rp sin phi; ref 002 prints
    R_c in place of Rp in R_cap, an extraction error):
        A_c = pi Rc^2, A_l = 2 pi Rp^2 (1 - cos phi) - A_c (wetted cap),
        A_g = 2 pi Rp^2 - A_l - A_c,
        l_l = [R_cap Rp - (phi Rp^2 + R_cap sqrt(Rp^2 - R_cap^2))/2]/(R_cap - Rc),
        l_g = [Rp^2 (1 - pi/4) - (l_l (R_cap - Rc))]/(Rp - R_cap)
    (each l = meridian area between the sphere and the mid-plane divided by the
    width of the strip). The printed A_l and l_g of ref 002 are garbled; this
    reconstruction reduces to the printed dry limit at phi = 0 and to the
    printed l_l = Rp^2 (1 - pi/4)/(Rp - Rc) at phi = pi/2. Identical spheres
    (use Rp = (Ri+Rj)/2 otherwise); only for touching particles (rc > 0).
    """
    if rc <= 0.0 or rc >= Rp:
        return 0.0
    total = Rp * Rp * (1.0 - 0.25 * math.pi)
    Rcap = Rp * math.sin(phi) if phi > 0.0 else 0.0
    Ac = math.pi * rc * rc
    H = 0.0
    if Rcap > rc and k_liq > 0.0:
        Al = 2.0 * math.pi * Rp * Rp * (1.0 - math.cos(phi)) - Ac
        area_l = _seg_area(Rp, Rcap)
        ll = area_l / (Rcap - rc)
        if ll > 0.0 and Al > 0.0:
            H += k_liq * Al / ll
        Ag = 2.0 * math.pi * Rp * Rp - max(Al, 0.0) - Ac
        if Rp - Rcap > 0.0:
            lg = (total - area_l) / (Rp - Rcap)
        else:
            lg = 0.0
    else:
        Ag = 2.0 * math.pi * Rp * Rp - Ac
        lg = total / (Rp - rc)
    if Ag > 0.0 and lg > 0.0 and kg > 0.0:
        kgs = kg / (1.0 + M / lg)
        H += kgs * Ag / lg
    return H


# ----------------------------------------------------------------- dispatcher laws
@numba.njit(cache=True, error_model="numpy", inline="always")
def _cheng_a_pp(Ri, Rj, d, rc, r_low, por, Rmin, kf, ki, kj, mi, mj, tmat, gas):
    Rp = 0.5 * (Ri + Rj)
    return cheng_1999_voronoi_a(Rp, d, r_low, ki, kj, kf, zhou_2009_face_radius(Rp, por), gas[QUAD_TOL])


@numba.njit(cache=True, error_model="numpy", inline="always")
def _gan_a_pp(Ri, Rj, d, rc, r_low, por, Rmin, kf, ki, kj, mi, mj, tmat, gas):
    return gan_2016_voronoi_a(Ri, Rj, d, r_low, ki, kj, kf, zhou_2009_face_radius(Rmin, por), gas[QUAD_TOL])


@numba.njit(cache=True, error_model="numpy", inline="always")
def _voronoi_a_pw(R, d, rc, r_low, por, kf, kp, mp, mw, tmat, gas):
    return voronoi_a_wall(R, d, r_low, kp, kf, zhou_2009_face_radius(R, por), gas[QUAD_TOL])


@numba.njit(cache=True, error_model="numpy", inline="always")
def _cheng_b_pp(Ri, Rj, d, rc, r_low, por, Rmin, kf, ki, kj, mi, mj, tmat, gas):
    Rp = 0.5 * (Ri + Rj)
    return cheng_1999_voronoi_b(Rp, d, r_low, ki, kj, kf, zhou_2009_face_radius(Rp, por),
                                gas[CORE_RATIO])


@numba.njit(cache=True, error_model="numpy", inline="always")
def _chen_b_pp(Ri, Rj, d, rc, r_low, por, Rmin, kf, ki, kj, mi, mj, tmat, gas):
    return chen_2019_voronoi_b(Ri, Rj, d, r_low, ki, kj, kf, zhou_2009_face_area(Rmin, por),
                               gas[CORE_RATIO])


@numba.njit(cache=True, error_model="numpy", inline="always")
def _voronoi_b_pw(R, d, rc, r_low, por, kf, kp, mp, mw, tmat, gas):
    return voronoi_b_wall(R, d, r_low, kp, kf, zhou_2009_face_radius(R, por), gas[CORE_RATIO])


@numba.njit(cache=True, error_model="numpy", inline="always")
def _rong_horio_pp(Ri, Rj, d, rc, r_low, por, Rmin, kf, ki, kj, mi, mj, tmat, gas):
    return rong_horio_1999_surrounding_layer(Ri, Rj, d, kf, gas[LAYER], gas[MIN_SEP], gas[QUAD_TOL])


@numba.njit(cache=True, error_model="numpy", inline="always")
def _rong_horio_pw(R, d, rc, r_low, por, kf, kp, mp, mw, tmat, gas):
    return surrounding_layer_wall(R, d, 0.0, kf, gas[LAYER], gas[MIN_SEP])


@numba.njit(cache=True, error_model="numpy", inline="always")
def _musser_pp(Ri, Rj, d, rc, r_low, por, Rmin, kf, ki, kj, mi, mj, tmat, gas):
    return musser_2011_surrounding_layer(Ri, Rj, d, r_low, kf, gas[LAYER], gas[MIN_SEP], gas[QUAD_TOL])


@numba.njit(cache=True, error_model="numpy", inline="always")
def _musser_pw(R, d, rc, r_low, por, kf, kp, mp, mw, tmat, gas):
    return surrounding_layer_wall(R, d, r_low, kf, gas[LAYER], gas[MIN_SEP])


@numba.njit(cache=True, error_model="numpy", inline="always")
def _vargas_pp(Ri, Rj, d, rc, r_low, por, Rmin, kf, ki, kj, mi, mj, tmat, gas):
    M = gas_parameter_m(tmat[mi, ACCOM], tmat[mj, ACCOM], gas[GAMMA_RATIO],
                        gas[MEAN_FREE_PATH], gas[PR])
    return vargas_mccarthy_2002(0.5 * (Ri + Rj), rc, kf, M, gas[K_LIQ], gas[FILL_ANGLE])


@numba.njit(cache=True, error_model="numpy", inline="always")
def _vargas_pw(R, d, rc, r_low, por, kf, kp, mp, mw, tmat, gas):
    M = gas_parameter_m(tmat[mp, ACCOM], tmat[mw, ACCOM], gas[GAMMA_RATIO],
                        gas[MEAN_FREE_PATH], gas[PR])
    return vargas_mccarthy_2002(R, rc, kf, M, gas[K_LIQ], gas[FILL_ANGLE])


# ----------------------------------------------------------------- records
_K = ("thermal_conductivity",)
_VOR_A = ("conductivity", "porosity", "cutoff", "quadrature_tolerance")
_VOR_B = ("conductivity", "porosity", "cutoff", "core_ratio")
_LAYER = ("conductivity", "layer", "min_separation", "cutoff", "quadrature_tolerance")
RECORDS = (
    ModelRecord("cheng_1999_voronoi_a", "indirect", INDIRECT_CHENG_VORONOI_A, aliases=("voronoi_a",),
                material=_K, gas=_VOR_A, reach="cutoff",
                laws=dict(pp=_cheng_a_pp, pw=_voronoi_a_pw), law=cheng_1999_voronoi_a,
                reference="Cheng, Yu & Zulli (1999) Voronoi model A; ref 002",
                summary="integral over the double cone of the Voronoi face (mono-size, mean radius)"),
    ModelRecord("gan_2016_voronoi_a", "indirect", INDIRECT_GAN_VORONOI_A,
                material=_K, gas=_VOR_A, reach="cutoff",
                laws=dict(pp=_gan_a_pp, pw=_voronoi_a_pw), law=gan_2016_voronoi_a,
                reference="Gan, Zhou & Yu (2016); ref 002", summary="Voronoi model A for multi-size spheres"),
    ModelRecord("cheng_1999_voronoi_b", "indirect", INDIRECT_CHENG_VORONOI_B, aliases=("voronoi_b",),
                material=_K, gas=_VOR_B, reach="cutoff",
                laws=dict(pp=_cheng_b_pp, pw=_voronoi_b_pw), law=cheng_1999_voronoi_b,
                reference="Cheng, Yu & Zulli (1999) Voronoi model B; ref 002",
                summary="closed form with an isothermal core"),
    ModelRecord("chen_2019_voronoi_b", "indirect", INDIRECT_CHEN_VORONOI_B,
                material=_K, gas=_VOR_B, reach="cutoff",
                laws=dict(pp=_chen_b_pp, pw=_voronoi_b_pw), law=chen_2019_voronoi_b,
                reference="Chen et al. (2019); ref 002", summary="Voronoi model B for multi-size spheres"),
    ModelRecord("rong_horio_1999_surrounding_layer", "indirect", INDIRECT_RONG_HORIO,
                aliases=("rong_horio_1999",), gas=_LAYER, reach="cutoff",
                laws=dict(pp=_rong_horio_pp, pw=_rong_horio_pw), law=rong_horio_1999_surrounding_layer,
                reference="Rong & Horio (1999); ref 002",
                summary="fluid layer integral including the contact area (use without direct conduction)"),
    ModelRecord("musser_2011_surrounding_layer", "indirect", INDIRECT_MUSSER,
                aliases=("surrounding_layer", "musser_2011"), gas=_LAYER, reach="cutoff",
                laws=dict(pp=_musser_pp, pw=_musser_pw), law=musser_2011_surrounding_layer,
                reference="Musser (2011); refs 002, 003", summary="fluid layer integral outside the contact"),
    ModelRecord("vargas_mccarthy_2002", "indirect", INDIRECT_VARGAS_MCCARTHY,
                aliases=("vargas_mccarthy",),
                gas=("conductivity", "mean_free_path", "heat_capacity_ratio", "prandtl",
                     "accommodation_coefficient", "liquid_conductivity", "filling_angle", "cutoff"),
                reach="cutoff", laws=dict(pp=_vargas_pp, pw=_vargas_pw), law=vargas_mccarthy_2002,
                reference="Vargas & McCarthy (2002); ref 002",
                summary="gas gap (and liquid bridge) conductance of touching particles"),
)


def __getattr__(name):
    # indirect_pp / indirect_pw are generated from the records of all indirect models
    if name in ("indirect_pp", "indirect_pw"):
        from . import dispatch
        return getattr(dispatch.module(), name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
