"""Fluid forces and torque on a particle besides drag and pressure gradient (issue 13, item 3).

Selected by name in coupling.toml, each off by default (docs/models.md, "Fluid torque, lift
and virtual mass"):

``torque = "rotational_drag"``
    :func:`rotational_drag_dennis_1980`: torque of the relative rotation
    Omega_rel = curl(u_f)/2 - omega_p, T = k_rot Omega_rel.
``lift = "saffman_mei"``
    :func:`saffman_mei_1992`: shear lift of Saffman (1965) with Mei's (1992) correction.
``lift = "magnus"``
    :func:`magnus_oesterle_bui_dinh_1998`: rotational lift of Rubinow & Keller (1961) with
    the Reynolds-number correction of Oesterle & Bui Dinh (1998).
``virtual_mass = true``
    C_vm rho_f V_p (Du_f/Dt - dv/dt), C_vm = 0.5 (:data:`C_VM`); the DEM takes the dv/dt part
    implicitly as an added mass (coupling.interface).

All vectors are per particle; ``ur = u_f - v`` the slip velocity, ``om`` the gas vorticity
curl(u_f) at the particle. Reynolds numbers: particle Re_p = rho |ur| d / mu, shear
Re_s = rho |om| d^2 / mu, rotation Re_R = rho |Omega_rel| d^2 / mu.
"""
from __future__ import annotations

import math

from numba import njit

__all__ = ["rotational_drag_dennis_1980", "saffman_mei_1992", "magnus_oesterle_bui_dinh_1998",
           "C_VM", "TORQUE_MODELS", "LIFT_MODELS", "RE_R_STOKES"]

C_VM = 0.5                 # virtual-mass coefficient of a sphere (potential flow; Auton et al. 1988)
RE_R_STOKES = 32.0         # Re_R = rho |Omega| d^2 / mu below which the Stokes torque is used

TORQUE_NONE, TORQUE_ROTATIONAL_DRAG = 0, 1
LIFT_NONE, LIFT_SAFFMAN_MEI, LIFT_MAGNUS = 0, 1, 2
TORQUE_MODELS = {"none": TORQUE_NONE, "rotational_drag": TORQUE_ROTATIONAL_DRAG}
LIFT_MODELS = {"none": LIFT_NONE, "saffman_mei": LIFT_SAFFMAN_MEI, "magnus": LIFT_MAGNUS}


@njit(cache=True, error_model="numpy")
def rotational_drag_dennis_1980(d, rho, mu, om_rel):
    """k_rot (N m s) of the fluid torque T = k_rot Omega_rel on a sphere of diameter d turning at
    |Omega_rel| = om_rel relative to the fluid (Omega_rel = curl(u_f)/2 - omega_p):

        T = (rho/2) (d/2)^5 C_R |Omega_rel| Omega_rel,   Re_R = rho |Omega_rel| d^2 / mu,
        C_R = 64 pi / Re_R                       Re_R <= 32  (Stokes / Rubinow & Keller 1961:
                                                              T = pi mu d^3 Omega_rel),
        C_R = 12.9 / Re_R^0.5 + 128.4 / Re_R     Re_R > 32   (Dennis, Singh & Ingham 1980),

    i.e. k_rot = pi mu d^3 (Stokes) or (rho/2) (d/2)^5 C_R |Omega_rel|. Dennis et al. give
    C_M = 6.45/Re^0.5 + 32.1/Re with Re = a^2 Omega / nu (a = d/2) = Re_R / 4, hence the factors 2
    and 4 above; their fit is for 20 <= Re <= 1000 (Re_R 80..4000), the two branches meet at
    Re_R = 32 within 0.2 %; above Re_R = 4000 the fit is extrapolated. (With Re_R written as
    rho |Omega| d^2 / (4 mu), C_R = 64 pi / Re_R would be 4 x the Stokes torque: the
    Re_R of these coefficients has no factor 4.) J. Fluid Mech. 101 (1980) 257-279;
    S.I. Rubinow, J.B. Keller, J. Fluid Mech. 11 (1961) 447-459."""
    re = rho * om_rel * d * d / mu
    if re <= RE_R_STOKES:
        return math.pi * mu * d * d * d
    cr = 12.9 / math.sqrt(re) + 128.4 / re
    r = 0.5 * d
    return 0.5 * rho * r ** 5 * cr * om_rel


@njit(cache=True, error_model="numpy")
def mei_1992_factor(re_p, re_s):
    """Mei (1992) correction F_L / F_Saffman of the shear lift at finite Reynolds numbers,
    alpha = Re_s / (2 Re_p) (= G a / |ur|):

        (1 - 0.3314 alpha^0.5) exp(-Re_p / 10) + 0.3314 alpha^0.5   Re_p <= 40,
        0.0524 (alpha Re_p)^0.5                                     Re_p > 40.

    R. Mei, Int. J. Multiphase Flow 18 (1992) 145-147 (fit of Dandy & Dwyer 1990 for
    0.005 < alpha < 0.4, 0.1 <= Re_p <= 100). 1 at Re_p -> 0 (Saffman)."""
    alpha = 0.5 * re_s / re_p
    sa = math.sqrt(alpha)
    if re_p <= 40.0:
        return (1.0 - 0.3314 * sa) * math.exp(-0.1 * re_p) + 0.3314 * sa
    return 0.0524 * math.sqrt(alpha * re_p)


@njit(cache=True, error_model="numpy")
def saffman_mei_1992(d, rho, mu, ur0, ur1, ur2, om0, om1, om2):
    """Shear lift on a sphere (N), Saffman (1965) with Mei's (1992) correction:

        F = 1.615 d^2 (rho mu / |om|)^0.5 f(Re_p, Re_s) (ur x om),

    ur = u_f - v, om = curl(u_f). For ur perpendicular to om, |F| = 1.615 mu d |ur| Re_s^0.5 f,
    Saffman's 6.46 mu a^2 |ur| (G / nu)^0.5 at f = 1; a particle lagging the gas is lifted
    towards the faster gas. P.G. Saffman, J. Fluid Mech. 22 (1965) 385-400 (and corrigendum
    31 (1968) 624); f: :func:`mei_1992_factor`. Zero without shear or slip."""
    w = math.sqrt(om0 * om0 + om1 * om1 + om2 * om2)
    u = math.sqrt(ur0 * ur0 + ur1 * ur1 + ur2 * ur2)
    if w == 0.0 or u == 0.0:
        return 0.0, 0.0, 0.0
    re_p = rho * u * d / mu
    re_s = rho * w * d * d / mu
    c = 1.615 * d * d * math.sqrt(rho * mu / w) * mei_1992_factor(re_p, re_s)
    return (c * (ur1 * om2 - ur2 * om1), c * (ur2 * om0 - ur0 * om2), c * (ur0 * om1 - ur1 * om0))


@njit(cache=True, error_model="numpy")
def magnus_oesterle_bui_dinh_1998(d, rho, mu, ur0, ur1, ur2, w0, w1, w2):
    """Rotational (Magnus) lift on a sphere (N) turning at Omega_rel = (w0, w1, w2) =
    curl(u_f)/2 - omega_p relative to the gas, slip ur = u_f - v:

        F = (pi/8) rho d^2 C_L |ur| (Omega_rel x ur) / |Omega_rel|,
        C_L = 0.45 + (Re_R / Re_p - 0.45) exp(-0.05684 Re_R^0.4 Re_p^0.3)   (Re_p < 140),

    which at low Re (C_L -> Re_R / Re_p = d |Omega_rel| / |ur|) is Rubinow & Keller's (1961)
    F = (pi/8) d^3 rho Omega_rel x ur = pi a^3 rho omega_p x (v - u_f) in still gas; a ball
    moving along +x with backspin (omega_p along -y) is lifted along +z. B. Oesterle,
    T. Bui Dinh, Exp. Fluids 25 (1998) 16-22 (fitted for Re_p < 140; extrapolated above).
    C_L |ur| is written without 1/Re_p so that it is finite at zero slip."""
    w = math.sqrt(w0 * w0 + w1 * w1 + w2 * w2)
    u = math.sqrt(ur0 * ur0 + ur1 * ur1 + ur2 * ur2)
    if w == 0.0 or u == 0.0:
        return 0.0, 0.0, 0.0
    re_p = rho * u * d / mu
    re_r = rho * w * d * d / mu
    e = math.exp(-0.05684 * re_r ** 0.4 * re_p ** 0.3)
    # C_L |ur| / |Omega_rel| = 0.45 |ur| / w + (d - 0.45 |ur| / w) e
    clu = 0.45 * u / w + (d - 0.45 * u / w) * e
    c = math.pi / 8.0 * rho * d * d * clu
    return (c * (w1 * ur2 - w2 * ur1), c * (w2 * ur0 - w0 * ur2), c * (w0 * ur1 - w1 * ur0))
