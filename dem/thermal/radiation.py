"""Continuum radiation models (ref 002, "DEM radiation models - continuum").

Q_r,i = eps_i A_s,i sigma (T_e^4 - T_i^4) [W], A_s = 4 pi R^2, where the
environment temperature T_e is built from the particles whose centres lie
within the radiative influence sphere (radius 3 R_i by default) and the fluid:

  0 zhou_2009:   T_e = eps T_f + (1 - eps) (1/n_p) sum_j T_j
  1 krause_2017: T_e = [ sum_j eps_j A_j sigma T_j^4 / 2 / sum_j eps_j A_j sigma / 2 ]^(1/4)
                 (half of the surface of each neighbour faces the particle; sigma cancels)

Usage: for each neighbour j in range call ``radiation_accumulate`` to update
the two accumulators (acc0, acc1) starting from (0, 0), then
``radiation_env_temperature`` and ``radiation_heat``. Without any neighbour:
Zhou's T_e = T_f (all fluid), Krause's T_e = T_i (no exchange).

Walls (issue 14; docs/models.md "Radiation to walls"). A fixed-temperature wall with an
emissivity eps_w > 0 that cuts the sphere of influence (radius s = radiation_range R_i, the
centre at distance h < s from the wall surface) is part of the environment, in each model's
own terms (``radiation_wall_weight``; the wall taken as its tangent plane at the nearest point):

  zhou_2009:   Zhou's T_e is a volume average over the sphere, so the wall takes the share of
               the sphere behind it, the cap fraction c^2 (3 s - c) / (4 s^3), c = s - h, times
               eps_w: a grey wall's radiosity eps_w sigma T_w^4 + (1 - eps_w) G is, linearised,
               the temperature eps_w T_w + (1 - eps_w) T_e, so the part (1 - eps_w) reflects the
               rest of the environment. With g_w these weights (G = sum g_w, scaled to 1 if
               larger):  T_e = (1 - G) T_e,particles+fluid + sum g_w T_w.
  krause_2017: Krause's T_e^4 weights each surface in the sphere by its emissivity and the area
               facing the particle (half of a neighbour's); a wall faces it with the disc
               pi (s^2 - h^2), so a_w = eps_w pi (s^2 - h^2) joins the sums:
               T_e^4 = (sum_j eps_j A_j T_j^4 / 2 + sum_w a_w T_w^4) / (sum_j eps_j A_j / 2 + sum_w a_w).

Both make T_e - T_i (Zhou) or T_e^4 - T_i^4 (Krause) a weighted sum over the environment's
parts with weights omega summing to one, so the particle's radiation splits exactly into a
part per wall (``radiation_wall_omega``, ``radiation_wall_rate``) and the rest (neighbours and
fluid, the run total E_radiation). Adiabatic and fixed-flux walls (no temperature known to the
DEM) are taken as reradiating: not in the environment.
"""
import math

import numba

from .records import ModelRecord
from .registry import RAD_KRAUSE_2017, RAD_ZHOU_2009

SIGMA_SB = 5.670374419e-8  # W/(m^2 K^4)


@numba.njit(cache=True, error_model="numpy")
def zhou_2009_accumulate(acc0, acc1, Tj):
    """Zhou et al. (2009) accumulators: (sum T_j, n_p)."""
    return acc0 + Tj, acc1 + 1.0


@numba.njit(cache=True, error_model="numpy")
def zhou_2009_env_temperature(por, T_f, sum_T, n):
    """T_e = eps T_f + (1 - eps) sum_T / n [K] (T_f if n = 0)."""
    if n <= 0.0:
        return T_f
    return por * T_f + (1.0 - por) * sum_T / n


@numba.njit(cache=True, error_model="numpy")
def krause_2017_accumulate(acc0, acc1, Tj, eps_j, Aj):
    """Krause et al. (2017) accumulators: (sum eps_j A_j T_j^4/2, sum eps_j A_j/2)."""
    return acc0 + 0.5 * eps_j * Aj * Tj ** 4, acc1 + 0.5 * eps_j * Aj


@numba.njit(cache=True, error_model="numpy")
def krause_2017_env_temperature(num, den, T_i):
    """T_e = (num/den)^(1/4) [K] (T_i if no neighbour)."""
    if den <= 0.0:
        return T_i
    return (num / den) ** 0.25


@numba.njit(cache=True, error_model="numpy")
def radiation_heat(eps_i, R_i, T_e, T_i):
    """Q = eps_i (4 pi R_i^2) sigma (T_e^4 - T_i^4) [W] (grey body)."""
    return eps_i * 4.0 * math.pi * R_i * R_i * SIGMA_SB * (T_e ** 4 - T_i ** 4)


@numba.njit(cache=True, error_model="numpy")
def zhou_2009_radiation(eps_i, R_i, T_i, por, T_f, sum_T, n):
    """Zhou et al. (2009) continuum radiation heat rate [W]."""
    return radiation_heat(eps_i, R_i, zhou_2009_env_temperature(por, T_f, sum_T, n), T_i)


@numba.njit(cache=True, error_model="numpy")
def krause_2017_radiation(eps_i, R_i, T_i, num, den):
    """Krause et al. (2017) continuum radiation heat rate [W]."""
    return radiation_heat(eps_i, R_i, krause_2017_env_temperature(num, den, T_i), T_i)


@numba.njit(cache=True, error_model="numpy")
def radiation_accumulate(model, acc0, acc1, Tj, eps_j, Rj):
    """Dispatcher: add neighbour j (temperature Tj, emissivity eps_j, radius Rj)."""
    if model == RAD_ZHOU_2009:
        return zhou_2009_accumulate(acc0, acc1, Tj)
    return krause_2017_accumulate(acc0, acc1, Tj, eps_j, 4.0 * math.pi * Rj * Rj)


@numba.njit(cache=True, error_model="numpy")
def radiation_env_temperature(model, acc0, acc1, por, T_f, T_i):
    """Dispatcher: environment temperature [K] from the accumulators."""
    if model == RAD_ZHOU_2009:
        return zhou_2009_env_temperature(por, T_f, acc0, acc1)
    return krause_2017_env_temperature(acc0, acc1, T_i)


@numba.njit(cache=True, error_model="numpy")
def radiation_pp_heat(model, eps_i, R_i, T_i, acc0, acc1, por, T_f):
    """Dispatcher: radiative heat rate into particle i [W]."""
    return radiation_heat(eps_i, R_i, radiation_env_temperature(model, acc0, acc1, por, T_f, T_i), T_i)


@numba.njit(cache=True, error_model="numpy")
def cap_volume_fraction(h, s):
    """The fraction of a sphere of radius s cut off by a plane at distance h from its centre
    (0 <= h): c^2 (3 s - c) / (4 s^3), c = s - h (0 for h >= s, 1/2 for h = 0)."""
    if h >= s:
        return 0.0
    c = s - max(h, 0.0)
    return c * c * (3.0 * s - c) / (4.0 * s * s * s)


@numba.njit(cache=True, error_model="numpy")
def radiation_wall_weight(model, eps_w, h, s):
    """The weight of a wall of emissivity eps_w whose surface is at distance h from the centre
    of the sphere of influence of radius s: Zhou (2009) eps_w times the cap volume fraction,
    Krause (2017) eps_w times the disc area pi (s^2 - h^2) [m^2]; 0 if the wall does not cut
    the sphere."""
    if h >= s or eps_w <= 0.0:
        return 0.0
    if model == RAD_ZHOU_2009:
        return eps_w * cap_volume_fraction(h, s)
    hh = max(h, 0.0)
    return eps_w * math.pi * (s * s - hh * hh)


@numba.njit(cache=True, error_model="numpy")
def radiation_wall_accumulate(model, aw0, aw1, wgt, T_w):
    """Add a wall of weight ``wgt`` (radiation_wall_weight) at T_w to the wall accumulators:
    Zhou (sum g_w T_w, sum g_w), Krause (sum a_w T_w^4, sum a_w)."""
    if model == RAD_ZHOU_2009:
        return aw0 + wgt * T_w, aw1 + wgt
    return aw0 + wgt * T_w ** 4, aw1 + wgt


@numba.njit(cache=True, error_model="numpy")
def radiation_env_temperature_walls(model, acc0, acc1, aw0, aw1, por, T_f, T_i):
    """T_e [K] of the neighbours and fluid (acc0, acc1) and the walls (aw0, aw1):
    Zhou (1 - G) T_e,0 + sum g_w T_w (G = aw1, scaled to 1 if larger), Krause
    ((acc0 + aw0) / (acc1 + aw1))^(1/4)."""
    if model == RAD_ZHOU_2009:
        te0 = zhou_2009_env_temperature(por, T_f, acc0, acc1)
        if aw1 >= 1.0:
            return aw0 / aw1
        return (1.0 - aw1) * te0 + aw0
    return krause_2017_env_temperature(acc0 + aw0, acc1 + aw1, T_i)


@numba.njit(cache=True, error_model="numpy")
def radiation_wall_omega(model, wgt, acc1, aw1):
    """The wall's weight omega in the environment (the weights of all parts sum to one)."""
    if model == RAD_ZHOU_2009:
        return wgt / aw1 if aw1 > 1.0 else wgt
    return wgt / (acc1 + aw1)


@numba.njit(cache=True, error_model="numpy")
def radiation_wall_rate(model, eps_i, R_i, T_i, T_e, omega, T_w):
    """The part of particle i's radiation that comes from a wall of weight omega at T_w [W]:
    Zhou h_sec omega (T_w - T_i), h_sec = eps_i A_i sigma (T_e^2 + T_i^2)(T_e + T_i) the secant
    conductance of the whole exchange; Krause eps_i A_i sigma omega (T_w^4 - T_i^4). The parts
    of all walls and the rest sum to radiation_heat(eps_i, R_i, T_e, T_i)."""
    a = eps_i * 4.0 * math.pi * R_i * R_i * SIGMA_SB
    if model == RAD_ZHOU_2009:
        return a * (T_e * T_e + T_i * T_i) * (T_e + T_i) * omega * (T_w - T_i)
    return a * omega * (T_w ** 4 - T_i ** 4)


# ----------------------------------------------------------------- records
# (the accumulate / environment-temperature switches are written by hand). The neighbour reach
# is radiation_range - 2 radii beyond contact (centres within radiation_range R).
RECORDS = (
    ModelRecord("zhou_2009", "radiation", RAD_ZHOU_2009, aliases=("zhou_2009_radiation",),
                material=("emissivity",), gas=("temperature", "porosity", "radiation_range"),
                reach="radiation_range", reach_offset=-2.0, law=zhou_2009_radiation,
                reference="Zhou et al. (2009) continuum radiation; ref 002",
                summary="T_e = eps T_f + (1 - eps) mean T_j"),
    ModelRecord("krause_2017", "radiation", RAD_KRAUSE_2017, aliases=("krause_2017_radiation",),
                material=("emissivity",), gas=("radiation_range",),
                reach="radiation_range", reach_offset=-2.0, law=krause_2017_radiation,
                reference="Krause et al. (2017) continuum radiation; ref 002",
                summary="T_e^4 = emissivity-area weighted mean of T_j^4"),
)
