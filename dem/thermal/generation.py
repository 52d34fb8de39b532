"""Heat generation by friction / impact and its partition between the bodies
(ref 002 "Heat generation"; ref 001 "Impact heat model"). Heat rates in W.

Friction heat models (ids, registry FRIC_*):
  0 nguyen_2009: Q = mu_d |v_t F_n|       (Nguyen et al. 2009; Al-Arkawazi 2017)
  1 rojek_2014:  Q = chi |v_t . F_t|      (chi: fraction of friction work, 0..1;
                                           v_t: irreversible (sliding) tangential velocity)
  2 impact_heat: Q = c_t |F_t v_t| + c_n |F_n v_n|  (ref 001, eq. 3305: fractions of the
                                           frictional and damping work converted to heat;
                                           F_n is the damping part of the normal force)
Partition coefficients psi_i (Q_i = psi_i Q, Q_j = (1 - psi_i) Q):
  0 varadi_1996: psi_i = k_i/(k_i + k_j)
  1 rojek_2014:  psi_i = e_i/(e_i + e_j), e = sqrt(rho c k) (thermal effusivity)
  2 equal:       psi_i = 1/2
"""
import math

import numba

from .records import ModelRecord
from .registry import (CP, DENSITY, FRIC_IMPACT_001, FRIC_NGUYEN_2009, FRIC_ROJEK_2014, K_COND,
                       PART_EQUAL, PART_ROJEK_2014, PART_VARADI_1996)


@numba.njit(cache=True, error_model="numpy")
def nguyen_2009_friction_heat(mu_dyn, vt, Fn):
    """Q = mu_d |v_t F_n| [W]; vt [m/s] sliding speed, Fn [N] normal force."""
    return mu_dyn * abs(vt * Fn)


@numba.njit(cache=True, error_model="numpy")
def rojek_2014_friction_heat(chi, vt_dot_ft):
    """Q = chi |v_t . F_t| [W]; vt_dot_ft [W] = dot product of the irreversible
    tangential velocity and the tangential force."""
    return chi * abs(vt_dot_ft)


@numba.njit(cache=True, error_model="numpy")
def impact_heat_001(ct, cn, ft_vt, fn_vn):
    """Q = c_t |F_t v_t| + c_n |F_n v_n| [W] (ref 001 eq. 3305)."""
    return ct * abs(ft_vt) + cn * abs(fn_vn)


@numba.njit(cache=True, error_model="numpy")
def varadi_1996_partition(ki, kj):
    """psi_i = k_i/(k_i + k_j) (Varadi et al. 1996)."""
    if math.isinf(kj):
        return 0.0 if not math.isinf(ki) else 0.5
    if math.isinf(ki):
        return 1.0
    return ki / (ki + kj)


@numba.njit(cache=True, error_model="numpy")
def rojek_2014_partition(rho_i, c_i, k_i, rho_j, c_j, k_j):
    """psi_i = e_i/(e_i + e_j), e = sqrt(rho c k) (Rojek 2014)."""
    ei = math.sqrt(rho_i * c_i * k_i)
    ej = math.sqrt(rho_j * c_j * k_j)
    if math.isinf(ej):
        return 0.0 if not math.isinf(ei) else 0.5
    if math.isinf(ei):
        return 1.0
    return ei / (ei + ej)


@numba.njit(cache=True, error_model="numpy")
def friction_heat(model, mu_dyn, chi, vt, Fn, vt_dot_ft, ct, cn, ft_vt, fn_vn):
    """Dispatcher: generated heat rate [W] at a contact; -1 for unknown ids."""
    if model == FRIC_NGUYEN_2009:
        return nguyen_2009_friction_heat(mu_dyn, vt, Fn)
    elif model == FRIC_ROJEK_2014:
        return rojek_2014_friction_heat(chi, vt_dot_ft)
    elif model == FRIC_IMPACT_001:
        return impact_heat_001(ct, cn, ft_vt, fn_vn)
    return -1.0


@numba.njit(cache=True, error_model="numpy")
def partition(model, mi, mj, tmat):
    """Dispatcher: fraction psi_i of the generated heat absorbed by body i; -1 if unknown."""
    if model == PART_VARADI_1996:
        return varadi_1996_partition(tmat[mi, K_COND], tmat[mj, K_COND])
    elif model == PART_ROJEK_2014:
        return rojek_2014_partition(tmat[mi, DENSITY], tmat[mi, CP], tmat[mi, K_COND],
                                    tmat[mj, DENSITY], tmat[mj, CP], tmat[mj, K_COND])
    elif model == PART_EQUAL:
        return 0.5
    return -1.0


# ----------------------------------------------------------------- records
# (the friction_heat / partition switches are written by hand)
RECORDS = (
    ModelRecord("nguyen_2009", "friction", FRIC_NGUYEN_2009, aliases=("nguyen_2009_friction_heat",),
                law=nguyen_2009_friction_heat, reference="Nguyen et al. (2009); ref 002",
                summary="Q = mu_d |v_t F_n|"),
    ModelRecord("rojek_2014", "friction", FRIC_ROJEK_2014, law=rojek_2014_friction_heat,
                reference="Rojek (2014); ref 002", summary="Q = chi |v_t . F_t|"),
    ModelRecord("impact_heat", "friction", FRIC_IMPACT_001, law=impact_heat_001,
                reference="ref 001 eq. 3305", summary="Q = c_t |F_t v_t| + c_n |F_n v_n|"),
    ModelRecord("varadi_1996", "partition", PART_VARADI_1996, aliases=("varadi_1996_partition",),
                material=("thermal_conductivity",), law=varadi_1996_partition,
                reference="Varadi et al. (1996); ref 002", summary="psi_i = k_i/(k_i + k_j)"),
    ModelRecord("rojek_2014", "partition", PART_ROJEK_2014,
                material=("thermal_conductivity", "density", "heat_capacity"), law=rojek_2014_partition,
                reference="Rojek (2014); ref 002", summary="psi_i = e_i/(e_i + e_j), e = sqrt(rho c k)"),
    ModelRecord("equal", "partition", PART_EQUAL, reference="", summary="psi_i = 1/2"),
)
