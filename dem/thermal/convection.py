"""Particle-fluid convection: Nusselt correlations and heat rate.

Q_i = h A_s (T_f - T_i) = 2 pi R_i k_f Nu (T_f - T_i), h = Nu k_f/(2 R_i)
(ref 002, "Convective heat transfer"), i.e. conductance H = 2 pi R k_f Nu [W/K].
Re = eps rho_f |u_f - v_p| (2R) / mu_f (particle Reynolds number based on the
superficial slip velocity), Pr = c_f mu_f / k_f.

Correlations (ref 002 table, from Peng et al. 2020):
  0 ranz_marshall (1952): Nu = 2 + 0.6 Re^(1/2) Pr^(1/3)
  1 whitaker (1972):      Nu = 2 + (0.4 Re^(1/2) + 0.06 Re^(2/3)) Pr^(2/5) (mu_f/mu_fs)^(1/4)
  2 gunn (1978):          Nu = (7 - 10 e + 5 e^2)(1 + 0.7 Re^(1/5) Pr^(1/3))
                               + (1.33 - 2.4 e + 1.2 e^2) Re^(7/10) Pr^(1/3)
                          (the exponents of Re are +1/5 and +7/10; the extracted
                          text of ref 002 shows them negative - extraction error)
  3 li_mason (2000):      Nu = 2 + 0.6 e^m Re^(1/2) Pr^(1/3)                 Re < 200
                          Nu = 2 + e^m (0.5 Re^(1/2) + 0.02 Re^(4/5)) Pr^(1/3)  200 <= Re < 1500
                          Nu = 2 + 4.5e-5 e^m Re^(9/5)                          Re >= 1500
                          m = 3.5 (dilute) or 4.75 (dense); default 4.75.
Stagnant limit (Re = 0): Nu = 2 for Ranz-Marshall, Whitaker and Li-Mason;
Gunn gives Nu = 7 - 10 e + 5 e^2, which is 2 only at e = 1 (3.8 at e = 0.4).
"""
import math

import numba

from .records import ModelRecord
from .registry import (LM_EXPONENT, NU_GUNN, NU_LI_MASON, NU_RANZ_MARSHALL, NU_WHITAKER, VISC_RATIO)

LI_MASON_DENSE = 4.75
LI_MASON_DILUTE = 3.5


@numba.njit(cache=True, error_model="numpy")
def reynolds(por, rho_f, u_rel, diameter, mu_f):
    """Particle Reynolds number Re = eps rho_f |u_rel| d_p / mu_f [-]."""
    return por * rho_f * abs(u_rel) * diameter / mu_f


@numba.njit(cache=True, error_model="numpy")
def prandtl(cp_f, mu_f, k_f):
    """Pr = c_f mu_f / k_f [-]."""
    return cp_f * mu_f / k_f


@numba.njit(cache=True, error_model="numpy")
def ranz_marshall_1952(Re, Pr):
    """Ranz & Marshall (1952): Nu = 2 + 0.6 Re^(1/2) Pr^(1/3) (Re 1-1e4, Pr 0.6-380)."""
    return 2.0 + 0.6 * math.sqrt(max(Re, 0.0)) * Pr ** (1.0 / 3.0)


@numba.njit(cache=True, error_model="numpy")
def whitaker_1972(Re, Pr, visc_ratio):
    """Whitaker (1972): Nu = 2 + (0.4 Re^(1/2) + 0.06 Re^(2/3)) Pr^0.4 (mu_f/mu_fs)^(1/4)."""
    Re = max(Re, 0.0)
    return 2.0 + (0.4 * math.sqrt(Re) + 0.06 * Re ** (2.0 / 3.0)) * Pr ** 0.4 * visc_ratio ** 0.25


@numba.njit(cache=True, error_model="numpy")
def gunn_1978(Re, Pr, por):
    """Gunn (1978): Nu = (7 - 10e + 5e^2)(1 + 0.7 Re^0.2 Pr^(1/3)) + (1.33 - 2.4e + 1.2e^2) Re^0.7 Pr^(1/3)."""
    Re = max(Re, 0.0)
    e = por
    p3 = Pr ** (1.0 / 3.0)
    return (7.0 - 10.0 * e + 5.0 * e * e) * (1.0 + 0.7 * Re ** 0.2 * p3) + \
        (1.33 - 2.4 * e + 1.2 * e * e) * Re ** 0.7 * p3


@numba.njit(cache=True, error_model="numpy")
def li_mason_2000(Re, Pr, por, m):
    """Li & Mason (2000), three Re ranges (see module doc); m porosity exponent."""
    Re = max(Re, 0.0)
    em = por ** m
    if Re < 200.0:
        return 2.0 + 0.6 * em * math.sqrt(Re) * Pr ** (1.0 / 3.0)
    elif Re < 1500.0:
        return 2.0 + em * (0.5 * math.sqrt(Re) + 0.02 * Re ** 0.8) * Pr ** (1.0 / 3.0)
    return 2.0 + 4.5e-5 * em * Re ** 1.8


@numba.njit(cache=True, error_model="numpy")
def nusselt_id_opt(corr, Re, Pr, por, visc_ratio, lm_exponent):
    """Nusselt number for correlation id ``corr`` with explicit options; -1 if unknown."""
    if corr == NU_RANZ_MARSHALL:
        return ranz_marshall_1952(Re, Pr)
    elif corr == NU_WHITAKER:
        return whitaker_1972(Re, Pr, visc_ratio)
    elif corr == NU_GUNN:
        return gunn_1978(Re, Pr, por)
    elif corr == NU_LI_MASON:
        return li_mason_2000(Re, Pr, por, lm_exponent)
    return -1.0


@numba.njit(cache=True, error_model="numpy")
def nusselt_id(corr, Re, Pr, por):
    """Nusselt number, default options (viscosity ratio 1, Li-Mason m = 4.75)."""
    return nusselt_id_opt(corr, Re, Pr, por, 1.0, LI_MASON_DENSE)


@numba.njit(cache=True, error_model="numpy")
def nusselt_gas(corr, Re, Pr, por, gas):
    """Nusselt number with the options read from the gas table (VISC_RATIO, LM_EXPONENT)."""
    return nusselt_id_opt(corr, Re, Pr, por, gas[VISC_RATIO], gas[LM_EXPONENT])


@numba.njit(cache=True, error_model="numpy")
def convection_conductance(R, k_f, Nu):
    """H = h A_s = (Nu k_f/(2R)) 4 pi R^2 = 2 pi R k_f Nu [W/K]; Q = H (T_f - T_p)."""
    return 2.0 * math.pi * R * k_f * Nu


# Lumped-capacitance limit Bi = h L_c / k_p < 0.1 with L_c = V/A (Incropera & DeWitt,
# Fundamentals of Heat and Mass Transfer, 6th ed., section 5.1, eq. 5.10). For a sphere in the
# quasi-steady (parabolic) profile the mean temperature differs from the surface one by
# (3/5) Bi (T_s - T_gas): 6 % of the surface-to-gas difference at the limit.
BIOT_LUMPED = 0.1


@numba.njit(cache=True, error_model="numpy")
def biot_lumped(h, R, k_p):
    """Biot number of a sphere with the lumped-capacitance length L_c = V/A = R/3
    (Incropera & DeWitt, Fundamentals of Heat and Mass Transfer, 6th ed., eq. 5.10):
    Bi = h L_c / k_p = h R / (3 k_p) [-]; the lumped (uniform) temperature holds for Bi < 0.1.
    Scalars or arrays."""
    return h * R / (3.0 * k_p)


# ----------------------------------------------------------------- records
# (the switch nusselt_id_opt is written by hand: records give names, ids and inputs)
_CONV = ("conductivity", "prandtl", "density", "viscosity", "temperature", "velocity", "porosity")
RECORDS = (
    ModelRecord("ranz_marshall", "convection", NU_RANZ_MARSHALL, aliases=("ranz_marshall_1952",),
                gas=_CONV, law=ranz_marshall_1952, reference="Ranz & Marshall (1952); ref 002",
                summary="Nu = 2 + 0.6 Re^(1/2) Pr^(1/3)"),
    ModelRecord("whitaker", "convection", NU_WHITAKER, aliases=("whitaker_1972",),
                gas=_CONV + ("viscosity_ratio",), law=whitaker_1972, reference="Whitaker (1972); ref 002",
                summary="Nu = 2 + (0.4 Re^(1/2) + 0.06 Re^(2/3)) Pr^0.4 (mu/mu_s)^(1/4)"),
    ModelRecord("gunn", "convection", NU_GUNN, aliases=("gunn_1978",), gas=_CONV,
                law=gunn_1978, reference="Gunn (1978); ref 002 (exponents +1/5, +7/10)",
                summary="porosity-dependent packed/fluidised bed correlation"),
    ModelRecord("li_mason", "convection", NU_LI_MASON, aliases=("li_mason_2000",),
                gas=_CONV + ("li_mason_exponent",), law=li_mason_2000,
                reference="Li & Mason (2000); ref 002", summary="three Re ranges, porosity exponent m"),
)
