"""Bahrami-Yovanovich-Culham rough-sphere contact conductance (direct conduction, vacuum).

The contact of two rough spheres, as used by Bahrami, Yovanovich & Culham (2006) for packed
beds of rough spheres (the paper reference 000 cites for its gas resistances), built from
  * the compact rough-sphere contact model of Bahrami, Yovanovich & Culham (2005), "A compact
    model for spherical rough contacts", J. Tribol. 127, 884-889: roughness spreads the load
    over a macrocontact of radius a_L larger than the Hertz radius a_H;
  * the thermal joint model of Bahrami, Culham, Yovanovich & Schneider (2004), "Thermal contact
    resistance of nonconforming rough surfaces, part 2: thermal model", J. Thermophys. Heat
    Transfer 18(2): microcontact resistance R_s = 0.565 H_mic (sigma/m)/(k_s F) in series with
    the macrocontact constriction resistance R_L of the two bodies.

    tau   = rho / a_H                         (geometric parameter, rho = R*)
    alpha = sigma rho / a_H^2                 (roughness parameter)
    P0'   = P0/P0,H = 1 / (1 + 1.37 alpha tau^(-0.075))
    a_L   = a_H 1.605 / sqrt(P0')             0.01 <= P0' <= 0.47
    a_L   = a_H (3.51 - 2.51 P0')             0.47 <= P0' <= 1
    R_L   = 1/(2 k_s a_L)                     (constriction of two half-spaces: 1/(4 k_i a_L) + 1/(4 k_j a_L))
    R_s   = 0.565 H_mic (sigma/m) / (k_s F)
    H     = 1/(R_L + R_s)                     [W/K]
k_s = 2 k_i k_j/(k_i + k_j); sigma = sqrt(sigma_i^2 + sigma_j^2) (RMS roughness), m =
sqrt(m_i^2 + m_j^2) (RMS asperity slope), H_mic the microhardness of the softer surface (Bahrami
2004), F the normal load. The equations were taken from the two papers above (not from the
reference documents, which only cite Bahrami 2006); the flux-tube factor (1 - a_L/b_L)^1.5 of
Bahrami 2004 is 1 here (b_L -> inf: a contact much smaller than the particle, as in
Batchelor & O'Brien). Below P0' = 0.01 the first branch is extrapolated; at P0' = 0.47 the two
fitted branches differ by 0.5 % (2.341 vs 2.330), as published.

DEM inputs: the solver passes the contact radius r_c (Hertz, possibly corrected for a softened
modulus); it is the smooth Hertz radius a_H of the load F = 4 E*_real r_c^3/(3 R*) (Hertz with the
real modulus, as the Beaulieu network's P0). Smooth surfaces (sigma = 0): alpha = 0, P0' = 1,
a_L = a_H, R_s = 0, so H = 2 k_s r_c = 4 k_bar r_c, Batchelor & O'Brien exactly.
Wall: R* = R, k_w = inf gives k_s = 2 k_p (perfectly conducting wall).
"""
import math

import numba

from .contact_radius import effective_modulus
from .direct import harmonic_mean, real_modulus
from .records import ModelRecord
from .registry import ASPERITY_SLOPE, K_COND, MICROHARDNESS, POISSON, ROUGHNESS

DIRECT_BAHRAMI_2006 = 6


@numba.njit(cache=True, error_model="numpy")
def bahrami_2005_relative_pressure(a_H, rho, sigma):
    """P0' = P0/P0,H = 1/(1 + 1.37 alpha tau^(-0.075)), alpha = sigma rho/a_H^2, tau = rho/a_H
    (Bahrami, Yovanovich & Culham 2005, compact model) [-]."""
    alpha = sigma * rho / (a_H * a_H)
    tau = rho / a_H
    return 1.0 / (1.0 + 1.37 * alpha * tau ** -0.075)


@numba.njit(cache=True, error_model="numpy")
def bahrami_2005_macrocontact_radius(a_H, rho, sigma):
    """Macrocontact radius a_L [m] of rough spheres (Bahrami et al. 2005):
    a_H 1.605/sqrt(P0') for P0' <= 0.47, a_H (3.51 - 2.51 P0') above; a_H for smooth surfaces."""
    if sigma <= 0.0:
        return a_H
    p = bahrami_2005_relative_pressure(a_H, rho, sigma)
    if p <= 0.47:
        return a_H * 1.605 / math.sqrt(p)
    return a_H * (3.51 - 2.51 * p)


@numba.njit(cache=True, error_model="numpy")
def bahrami_2006_rough_sphere(rc, Rstar, Estar_real, ki, kj, sigma, slope, Hmic):
    """Rough-sphere contact conductance H = 1/(R_L + R_s) [W/K] (module docstring).

    rc: Hertz contact radius [m]; Rstar: effective radius [m]; Estar_real: effective real
    modulus [Pa]; ki, kj [W/(m K)] (inf: perfect conductor); sigma: combined RMS roughness [m];
    slope: combined RMS asperity slope [-]; Hmic: microhardness of the softer surface [Pa].
    """
    if rc <= 0.0:
        return 0.0
    ks = harmonic_mean(ki, kj)
    aL = bahrami_2005_macrocontact_radius(rc, Rstar, sigma)
    R = 1.0 / (2.0 * ks * aL)
    if sigma > 0.0:
        F = 4.0 * Estar_real * rc ** 3 / (3.0 * Rstar)
        R += 0.565 * Hmic * (sigma / slope) / (ks * F)
    return 1.0 / R


@numba.njit(cache=True, error_model="numpy")
def _surfaces(tmat, mi, mj):
    # combined roughness and slope, microhardness of the softer surface
    sig = math.sqrt(tmat[mi, ROUGHNESS] ** 2 + tmat[mj, ROUGHNESS] ** 2)
    slope = math.sqrt(tmat[mi, ASPERITY_SLOPE] ** 2 + tmat[mj, ASPERITY_SLOPE] ** 2)
    return sig, slope, min(tmat[mi, MICROHARDNESS], tmat[mj, MICROHARDNESS])


@numba.njit(cache=True, error_model="numpy", inline="always")
def _pp(Ri, Rj, d, rc, mi, mj, tmat, gas, t_contact, vn_impact):
    Es = effective_modulus(real_modulus(tmat, mi), tmat[mi, POISSON], real_modulus(tmat, mj), tmat[mj, POISSON])
    sig, slope, hmic = _surfaces(tmat, mi, mj)
    return bahrami_2006_rough_sphere(rc, Ri * Rj / (Ri + Rj), Es, tmat[mi, K_COND], tmat[mj, K_COND],
                                     sig, slope, hmic)


@numba.njit(cache=True, error_model="numpy", inline="always")
def _pw(R, d, rc, mp, mw, tmat, gas, t_contact, vn_impact):
    Es = effective_modulus(real_modulus(tmat, mp), tmat[mp, POISSON], real_modulus(tmat, mw), tmat[mw, POISSON])
    sig, slope, hmic = _surfaces(tmat, mp, mw)
    return bahrami_2006_rough_sphere(rc, R, Es, tmat[mp, K_COND], tmat[mw, K_COND], sig, slope, hmic)


RECORDS = (
    ModelRecord("bahrami_2006_rough_sphere", "direct", DIRECT_BAHRAMI_2006,
                aliases=("bahrami_2006", "bahrami_yovanovich_culham", "byc"),
                material=("thermal_conductivity", "microhardness", "roughness", "asperity_slope",
                          "youngs_modulus", "poisson_ratio"),
                laws=dict(pp=_pp, pw=_pw), law=bahrami_2006_rough_sphere,
                reference="Bahrami, Yovanovich & Culham (2005) compact model; Bahrami et al. (2004) "
                          "part 2 R_s; applied to packed beds in Bahrami et al. (2006), cited by ref 000",
                summary="rough-sphere macrocontact a_L and microcontact resistance, in vacuum"),
)
