"""Fluid-particle drag closures for unresolved CFD-DEM.

Convention (all models)
-----------------------
Every model returns the **particle drag coefficient** ``beta_p`` [N s/m] of
one particle, such that the drag force on it is

    F_drag = beta_p * (u_f - u_p),

with ``u_f`` the *interstitial* (physical, not superficial) gas velocity at
the particle and ``u_p`` the particle velocity.  Inputs are always
``(d, eps, rho_f, mu_f, ur)`` with ``ur = |u_f - u_p|``.

This drag is the part of the fluid-particle force **without** the
pressure-gradient (buoyancy) contribution, which is added separately as

    F_p = -V_p grad(p)          (pressure_gradient_force; includes buoyancy
                                 when grad p contains the hydrostatic part)

("model A"/"set II" coupling as in CFDEMcoupling's ``gradPForce`` + drag or
MFiX-DEM).  If the pressure solved by the CFD excludes the hydrostatic head
(p_rgh), add ``buoyancy_force`` explicitly.

Many correlations are published as an inter-phase momentum exchange
coefficient per unit volume of mixture, ``beta`` [kg/(m^3 s)], such that
the force per unit mixture volume is ``beta (u_f - u_p)``.  With
``n = (1 - eps)/V_p`` particles per unit volume the per-particle coefficient
is

    beta_p = beta * V_p / (1 - eps).

Others are published as a normalised force ``F = f_d / (3 pi mu d U_s)``
with ``U_s = eps |u_f - u_p|`` the superficial slip velocity; then
``beta_p = 3 pi mu d eps F``.

In the single-particle limit eps -> 1 every model reduces to
``beta_p = 1/2 C_d rho_f (pi d^2 / 4) ur`` with its own C_d(Re).

Integer ids (for Numba dispatch) and names are in :data:`DRAG_MODELS`; use
:func:`drag_model_id` to map a name (aliases accepted) to an id and
:func:`drag_coefficient` (njit) to evaluate any model by id.
"""
from __future__ import annotations

import math

import numpy as np
from numba import njit

__all__ = [
    "schiller_naumann_cd", "dallavalle_cd",
    "di_felice_1994", "gidaspow_1994", "huilin_gidaspow_2003", "beetstra_2007",
    "ergun_beta", "wen_yu_beta",
    "drag_coefficient", "drag_coefficients", "drag_model_id", "DRAG_MODELS",
    "pressure_gradient_force", "buoyancy_force", "wen_yu_1966_umf",
]

_PI = math.pi


# --------------------------------------------------------------------------
# Single-sphere drag coefficients
# --------------------------------------------------------------------------
@njit(cache=True, error_model="numpy")
def schiller_naumann_cd(re):
    """Schiller & Naumann (1933): C_d = 24/Re (1 + 0.15 Re^0.687) for
    Re < 1000, 0.44 above (the form used inside Wen & Yu / Gidaspow)."""
    if re < 1000.0:
        return 24.0 / re * (1.0 + 0.15 * re ** 0.687)
    return 0.44


@njit(cache=True, error_model="numpy")
def dallavalle_cd(re):
    """Dallavalle (1948): C_d = (0.63 + 4.8 / sqrt(Re))^2, the single
    particle law used by Di Felice (1994, eq. 4)."""
    return (0.63 + 4.8 / math.sqrt(re)) ** 2


# --------------------------------------------------------------------------
# Correlations
# --------------------------------------------------------------------------
@njit(cache=True, error_model="numpy")
def di_felice_1994(d, eps, rho_f, mu_f, ur):
    """Di Felice (1994).

    R. Di Felice, "The voidage function for fluid-particle interaction
    systems", Int. J. Multiphase Flow 20(1) 153-159, 1994.

    Force on one particle in a suspension (Di Felice eqs. 6, 21, 30):

        f   = f0 * eps^(-chi),
        f0  = 1/2 C_d0 rho_f (pi d^2/4) U_s^2,   U_s = eps ur (superficial),
        C_d0 = (0.63 + 4.8 Re^-1/2)^2 (Dallavalle),  Re = rho_f d eps ur / mu_f,
        chi = 3.7 - 0.65 exp(-(1.5 - log10 Re)^2 / 2),

    hence  beta_p = 1/2 C_d0 rho_f (pi d^2/4) eps^(2 - chi) ur  (per particle).
    Re is based on the superficial velocity (Di Felice's definition); the
    eps^2 comes from U_s^2 = eps^2 ur^2.  Used here as the drag without the
    pressure-gradient force (as in CFDEMcoupling/Lethe).  At ur = 0 the
    product C_d0 * ur is evaluated in its finite form.
    """
    us = eps * ur
    re = rho_f * d * us / mu_f
    # C_d0 * ur written without 1/sqrt(Re) singularity:
    # (0.63 + 4.8/sqrt(Re))^2 ur = (0.63 sqrt(ur) + 4.8 sqrt(mu/(rho d eps)))^2
    cd_ur = (0.63 * math.sqrt(ur) + 4.8 * math.sqrt(mu_f / (rho_f * d * eps))) ** 2
    lre = math.log10(max(re, 1e-300))
    chi = 3.7 - 0.65 * math.exp(-0.5 * (1.5 - lre) ** 2)
    return 0.5 * cd_ur * rho_f * (_PI * d * d / 4.0) * eps ** (2.0 - chi)


@njit(cache=True, error_model="numpy")
def ergun_beta(d, eps, rho_f, mu_f, ur):
    """Ergun (1952) momentum-exchange coefficient per unit mixture volume as
    used by Gidaspow (1994, ch. 5):
    beta = 150 (1-eps)^2 mu / (eps d^2) + 1.75 (1-eps) rho_f ur / d.
    With beta ur = eps * (Ergun pressure drop per length) at U_s = eps ur."""
    es = 1.0 - eps
    return 150.0 * es * es * mu_f / (eps * d * d) + 1.75 * es * rho_f * ur / d


@njit(cache=True, error_model="numpy")
def wen_yu_beta(d, eps, rho_f, mu_f, ur):
    """Wen & Yu (1966) coefficient per unit mixture volume (Gidaspow 1994):
    beta = 3/4 C_d eps (1-eps) rho_f ur / d * eps^-2.65,
    C_d = Schiller-Naumann(Re), Re = eps rho_f d ur / mu_f."""
    re = eps * rho_f * d * ur / mu_f
    if re < 1000.0:
        # C_d * ur = 24 mu/(eps rho d) (1 + 0.15 Re^0.687): finite at ur = 0
        cd_ur = 24.0 * mu_f / (eps * rho_f * d) * (1.0 + 0.15 * re ** 0.687)
    else:
        cd_ur = 0.44 * ur
    return 0.75 * cd_ur * eps * (1.0 - eps) * rho_f / d * eps ** -2.65


@njit(cache=True, error_model="numpy")
def _beta_vol_to_particle(beta, d, eps):
    vp = _PI * d ** 3 / 6.0
    return beta * vp / (1.0 - eps)


@njit(cache=True, error_model="numpy")
def gidaspow_1994(d, eps, rho_f, mu_f, ur):
    """Gidaspow (1994): Ergun for eps < 0.8, Wen & Yu for eps >= 0.8.

    D. Gidaspow, "Multiphase Flow and Fluidization", Academic Press, 1994
    (ch. 5); S. Ergun, Chem. Eng. Prog. 48 (1952) 89-94; C.Y. Wen, Y.H. Yu,
    Chem. Eng. Prog. Symp. Ser. 62 (1966) 100-111.

    Published per unit mixture volume (see ergun_beta, wen_yu_beta); per
    particle beta_p = beta V_p / (1 - eps).  For eps -> 1 the Wen-Yu branch
    gives beta_p = 1/2 C_d(Schiller-Naumann) rho_f (pi d^2/4) ur.

    Not continuous at eps = 0.8: in the Stokes limit Ergun gives
    beta = 7.5 mu/d^2 and Wen-Yu 3.6 * 0.8^-2.65 mu/d^2 = 6.503 mu/d^2
    (ratio 0.8671, Wen-Yu 13.3 % lower); the jump changes with Re (see docs/models.md and
    the test).  Use huilin_gidaspow_2003 for a continuous blend.
    """
    if eps < 0.8:
        b = ergun_beta(d, eps, rho_f, mu_f, ur)
    else:
        b = wen_yu_beta(d, eps, rho_f, mu_f, ur)
    return _beta_vol_to_particle(b, d, eps)


@njit(cache=True, error_model="numpy")
def huilin_gidaspow_2003(d, eps, rho_f, mu_f, ur):
    """Huilin & Gidaspow (2003) smooth blend of Ergun and Wen-Yu.

    L. Huilin, D. Gidaspow, Chem. Eng. Sci. 58 (2003) 3777-3792:
    phi = 1/2 + arctan(262.5 (eps_s - 0.2)) / pi  (262.5 = 150 * 1.75),
    beta = phi beta_Ergun + (1 - phi) beta_WenYu,  eps_s = 1 - eps.
    Continuous in eps (the plain Gidaspow switch is not).
    """
    phi = 0.5 + math.atan(262.5 * ((1.0 - eps) - 0.2)) / _PI
    b = phi * ergun_beta(d, eps, rho_f, mu_f, ur) + (1.0 - phi) * wen_yu_beta(d, eps, rho_f, mu_f, ur)
    return _beta_vol_to_particle(b, d, eps)


@njit(cache=True, error_model="numpy")
def beetstra_2007(d, eps, rho_f, mu_f, ur):
    """Beetstra, van der Hoef & Kuipers (2007), monodisperse arrays.

    R. Beetstra, M.A. van der Hoef, J.A.M. Kuipers, "Drag force of
    intermediate Reynolds number flow past mono- and bidisperse arrays of
    spheres", AIChE J. 53(2) 489-501, 2007 (eq. 9 for monodisperse).

    Normalised drag F = f_d / (3 pi mu d U_s), U_s = eps ur, phi = 1 - eps,
    Re = rho_f d U_s / mu_f:

        F = 10 phi/eps^2 + eps^2 (1 + 1.5 sqrt(phi))
            + 0.413 Re / (24 eps^2) * (1/eps + 3 phi eps + 8.4 Re^-0.343)
                                    / (1 + 10^(3 phi) Re^(-(1 + 4 phi)/2))

    F is the drag without the mean-pressure-gradient share (its Stokes part
    10 phi/eps^2 is eps times the Carman-Kozeny total force 10 phi/eps^3),
    so beta_p = 3 pi mu d eps F, i.e. beta = 18 mu eps (1-eps) F / d^2 per
    mixture volume (MFiX ``BVK`` form).
    """
    phi = 1.0 - eps
    re = rho_f * d * eps * ur / mu_f
    F = 10.0 * phi / (eps * eps) + eps * eps * (1.0 + 1.5 * math.sqrt(phi))
    if re > 0.0:
        F += (0.413 * re / (24.0 * eps * eps)
              * (1.0 / eps + 3.0 * phi * eps + 8.4 * re ** -0.343)
              / (1.0 + 10.0 ** (3.0 * phi) * re ** (-(1.0 + 4.0 * phi) / 2.0)))
    return 3.0 * _PI * mu_f * d * eps * F


# --------------------------------------------------------------------------
# Dispatch
# --------------------------------------------------------------------------
DI_FELICE_1994 = 0
GIDASPOW_1994 = 1
BEETSTRA_2007 = 2
HUILIN_GIDASPOW_2003 = 3

DRAG_MODELS = {
    "di_felice_1994": DI_FELICE_1994,
    "gidaspow_1994": GIDASPOW_1994,
    "beetstra_2007": BEETSTRA_2007,
    "huilin_gidaspow_2003": HUILIN_GIDASPOW_2003,
}
_ALIASES = {
    "difelice": "di_felice_1994", "di_felice": "di_felice_1994", "DiFelice": "di_felice_1994",
    "gidaspow": "gidaspow_1994", "Gidaspow": "gidaspow_1994",
    "beetstra": "beetstra_2007", "Beetstra": "beetstra_2007", "bvk": "beetstra_2007",
    "huilin_gidaspow": "huilin_gidaspow_2003",
}


def drag_model_id(name) -> int:
    """Integer id of a drag model from its name (or an alias, or an id)."""
    if isinstance(name, (int, np.integer)):
        if int(name) in DRAG_MODELS.values():
            return int(name)
        raise ValueError(f"unknown drag model id {name}; valid ids: "
                         + ", ".join(f"{v} ({k})" for k, v in DRAG_MODELS.items()))
    key = _ALIASES.get(name, name)
    key = _ALIASES.get(str(key).lower(), key)
    if key in DRAG_MODELS:
        return DRAG_MODELS[key]
    raise ValueError(f"unknown drag model {name!r}; valid names: "
                     + ", ".join(DRAG_MODELS) + " (aliases: " + ", ".join(sorted(_ALIASES)) + ")")


@njit(cache=True, error_model="numpy")
def drag_coefficient(model_id, d, eps, rho_f, mu_f, ur):
    """beta_p of model ``model_id`` (see DRAG_MODELS) for one particle."""
    if model_id == 0:
        return di_felice_1994(d, eps, rho_f, mu_f, ur)
    elif model_id == 1:
        return gidaspow_1994(d, eps, rho_f, mu_f, ur)
    elif model_id == 2:
        return beetstra_2007(d, eps, rho_f, mu_f, ur)
    elif model_id == 3:
        return huilin_gidaspow_2003(d, eps, rho_f, mu_f, ur)
    return np.nan


@njit(cache=True, error_model="numpy")
def drag_coefficients(model_id, d, eps, rho_f, mu_f, ur):
    """Vectorised drag_coefficient over particles (arrays d, eps, ur;
    scalar fluid properties rho_f, mu_f)."""
    n = ur.shape[0]
    out = np.empty(n)
    for i in range(n):
        out[i] = drag_coefficient(model_id, d[i], eps[i], rho_f, mu_f, ur[i])
    return out


# --------------------------------------------------------------------------
# Other forces
# --------------------------------------------------------------------------
@njit(cache=True, error_model="numpy")
def pressure_gradient_force(d, grad_p):
    """F = -V_p grad p  [N]  (grad_p: length-3 array at the particle)."""
    vp = _PI * d ** 3 / 6.0
    out = np.empty(3)
    for i in range(3):
        out[i] = -vp * grad_p[i]
    return out


@njit(cache=True, error_model="numpy")
def buoyancy_force(d, rho_f, g):
    """Archimedes force F = -rho_f V_p g [N]; use only when the pressure
    gradient passed to pressure_gradient_force excludes the hydrostatic part
    (p_rgh), otherwise buoyancy is counted twice."""
    vp = _PI * d ** 3 / 6.0
    out = np.empty(3)
    for i in range(3):
        out[i] = -rho_f * vp * g[i]
    return out


@njit(cache=True, error_model="numpy")
def wen_yu_1966_umf(d, rho_p, rho_f, mu_f, g):
    """Minimum fluidization velocity [m/s] (superficial) of spheres of diameter d.

    Wen, C.Y. & Yu, Y.H. (1966), A generalized method for predicting the minimum
    fluidization velocity, AIChE J. 12(3) 610-612: Ergun's pressure drop equal to the bed
    weight, with 1/(phi eps_mf^3) ~ 14 and (1 - eps_mf)/(phi^2 eps_mf^3) ~ 11, gives
    Re_mf = sqrt(33.7^2 + 0.0408 Ar) - 33.7, Ar = rho_f (rho_p - rho_f) g d^3 / mu_f^2,
    U_mf = Re_mf mu_f / (rho_f d). Zero or negative buoyant weight (rho_p <= rho_f or g = 0):
    0 (nothing holds the particles down)."""
    ar = rho_f * (rho_p - rho_f) * g * d ** 3 / (mu_f * mu_f)
    if ar <= 0.0:
        return 0.0
    re_mf = math.sqrt(33.7 * 33.7 + 0.0408 * ar) - 33.7
    return re_mf * mu_f / (rho_f * d)
