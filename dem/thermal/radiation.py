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
