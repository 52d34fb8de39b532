"""Thermal model library of the DEM code (heat transfer between particles,
walls and the fluid). See docs/models.md, "Heat transfer models".

Layout
------
records.py         ModelRecord / Input: what a model declares next to its law
registry.py        the record modules (MODEL_MODULES); names -> ids, inputs, defaults, table
                   layouts ``tmat[n_mat, N_TPROP]`` and ``gas[N_GAS]``, history width, reach,
                   all derived from the records
dispatch.py        generates direct_pp/direct_pw/indirect_pp/indirect_pw from the records
docs.py            writes the model/input tables of docs/models.md from the records
bahrami_2006.py    Bahrami-Yovanovich-Culham rough-sphere conduction (one file per new model)
contact_radius.py  contact radius (Hertz force / overlap / geometric) and the
                   low-stiffness corrections (Zhou 2010, Lu 2017, Morris 2016)
direct.py          direct (contact) conduction
indirect.py        indirect conduction through the fluid
convection.py      Nusselt correlations
radiation.py       continuum radiation
generation.py      friction / impact heat and partition coefficients

Dispatchers for the solver kernel (all ``numba.njit(cache=True)``, integer
switch; conductances in W/K with Q_i = H (T_j - T_i)):

  direct_pp(model, Ri, Rj, d, rc, mi, mj, tmat, gas, t_contact, vn_impact)
  direct_pw(model, R, d, rc, mp, mw, tmat, gas, t_contact, vn_impact)
  indirect_pp(model, Ri, Rj, d, rc, mi, mj, por_i, por_j, tmat, gas)
  indirect_pw(model, R, d, rc, mp, mw, por, tmat, gas)
  contact_radius_pp(method, correction, Ri, Rj, d, Fn, Estar, Estar_real)
  contact_radius_pw(method, correction, R, d, Fn, Estar, Estar_real)
  nusselt_id(corr, Re, Pr, por)
  nusselt_gas(corr, Re, Pr, por, gas)            (options from the gas table)
  nusselt_id_opt(corr, Re, Pr, por, visc_ratio, lm_exponent)
  convection_conductance(R, k_f, Nu)
  radiation_accumulate(model, acc0, acc1, Tj, eps_j, Rj) -> (acc0, acc1)
  radiation_env_temperature(model, acc0, acc1, por, T_f, T_i)
  radiation_pp_heat(model, eps_i, R_i, T_i, acc0, acc1, por, T_f)   [W]
  friction_heat(model, mu_dyn, chi, vt, Fn, vt_dot_ft, ct, cn, ft_vt, fn_vn)  [W]
  partition(model, mi, mj, tmat)                 fraction psi_i of the heat for body i

Notes on the signatures (differences from the brief): contact_radius_pw has
no Rj (the wall radius is infinite); the nusselt options (Whitaker viscosity
ratio, Li-Mason exponent) are passed by ``nusselt_gas``/``nusselt_id_opt``
because ``nusselt_id`` has no slot for them (it uses 1 and 4.75). Dispatchers
return -1.0 for an unknown integer id (the scene validator rejects unknown
names before). zhou_2008_collisional is not symmetric in i and j (fit of
Zhou et al. 2008): evaluate it once per pair and apply +Q/-Q.

Python API (builds the tables from keywords and calls the same dispatchers):
  pair_conductance(model, **inputs)   W/K
  wall_conductance(model, **inputs)   W/K
  nusselt(correlation, Re, Pr, porosity, **options)
"""
import math

import numpy as np

from . import registry
from .contact_radius import contact_radius_pp, contact_radius_pw, geometric_pp, geometric_pw
from .convection import convection_conductance, nusselt_gas, nusselt_id, nusselt_id_opt, reynolds
from .direct import direct_pp, direct_pw
from .generation import friction_heat, partition
from .indirect import indirect_pp, indirect_pw
from .radiation import radiation_accumulate, radiation_env_temperature, radiation_pp_heat
from .registry import build_gas_table, build_material_table, build_tables, model_id, valid_names

__all__ = [
    "pair_conductance", "wall_conductance", "nusselt", "registry", "build_tables",
    "build_material_table", "build_gas_table", "model_id", "valid_names",
    "direct_pp", "direct_pw", "indirect_pp", "indirect_pw", "contact_radius_pp", "contact_radius_pw",
    "nusselt_id", "nusselt_gas", "nusselt_id_opt", "convection_conductance", "reynolds",
    "radiation_accumulate", "radiation_env_temperature", "radiation_pp_heat",
    "friction_heat", "partition",
]

# short keyword -> material key (suffix _i/_j for pairs, _p/_w for walls)
_MAT_SHORT = {
    "k": "thermal_conductivity", "cp": "heat_capacity", "rho": "density",
    "emissivity": "emissivity", "hardness": "microhardness", "roughness": "roughness",
    "slope": "asperity_slope", "E": "youngs_modulus", "nu": "poisson_ratio",
    "E_real": "real_youngs_modulus", "alpha": "accommodation_coefficient",
}
# short keyword -> gas/global key
_GAS_SHORT = {
    "kf": "conductivity", "rho_f": "density", "mu_f": "viscosity", "cp_f": "heat_capacity",
    "Pr": "prandtl", "mean_free_path": "mean_free_path", "gamma": "heat_capacity_ratio",
    "alpha_gas": "accommodation_coefficient", "porosity": "porosity", "cutoff": "cutoff",
    "layer": "layer", "min_separation": "min_separation", "core_ratio": "core_ratio",
    "k_liquid": "liquid_conductivity", "filling_angle": "filling_angle",
    "quadrature_tolerance": "quadrature_tolerance",
}


def _mechanism_of(model):
    for mech in ("direct", "indirect"):
        try:
            return mech, registry.canonical_name(mech, model)
        except ValueError:
            pass
    names = valid_names("direct") + valid_names("indirect")
    raise ValueError(f"unknown conduction model '{model}', valid: {', '.join(names)}")


def _keywords():
    """(material keyword -> key, gas keyword -> key): the short names above plus the full key of
    every input declared by the model records (so a model's new input needs no entry here)."""
    d = registry.derived()
    mat = dict(_MAT_SHORT)
    for inp in d["material_inputs"]:
        mat.setdefault(inp.key, inp.key)
    gas = dict(_GAS_SHORT)
    for inp in d["gas_inputs"]:
        if inp.key not in mat:  # density, heat_capacity, ...: the material meaning wins with a suffix
            gas.setdefault(inp.key, inp.key)
    return mat, gas


def _split_inputs(inputs, geom_keys, suffixes, extra):
    geom, mats, gas = {}, [dict(), dict()], {}
    mat_short, gas_short = _keywords()
    valid = list(geom_keys) + list(extra) + list(gas_short) + \
        [f"{s}{suf}" for s in mat_short for suf in suffixes] + ["k" + suffixes[0][1:], "k" + suffixes[1][1:]]
    for key, val in inputs.items():
        if key in geom_keys or key in extra:
            geom[key] = val
            continue
        if key in gas_short:
            gas[gas_short[key]] = val
            continue
        done = False
        for n, suf in enumerate(suffixes):
            if key.endswith(suf) and key[: -len(suf)] in mat_short:
                mats[n][mat_short[key[: -len(suf)]]] = val
                done = True
                break
            # ki/kj, kp/kw shorthand
            if key == "k" + suf[1:]:
                mats[n]["thermal_conductivity"] = val
                done = True
                break
        if not done:
            raise ValueError(f"unknown input '{key}', valid: {', '.join(sorted(set(valid)))}")
    return geom, mats, gas


def _require(geom, keys, model):
    missing = [k for k in keys if k not in geom]
    if missing:
        raise ValueError(f"missing input(s) {', '.join(missing)} for model '{model}'")


def _check_model_inputs(mech, name, mats, labels, gas):
    for m, label in zip(mats, labels):
        req = registry.required_material_keys(mech, name)
        missing = [k for k in req if k not in m]
        if missing:
            shorts = {v: k for k, v in _keywords()[0].items() if k == v or v not in _MAT_SHORT.values()}
            shorts.update({v: k for k, v in _MAT_SHORT.items()})
            raise ValueError(f"missing material key(s) {', '.join(missing)} "
                             f"(inputs {', '.join(shorts[k] + label for k in missing)}) "
                             f"required by {mech} model '{name}'")
    registry.check_params(mech, name, gas)


def pair_conductance(model, **inputs):
    """Particle-particle conductance [W/K] of a direct or indirect model.

    Inputs (SI): Ri, Rj, d (centre distance), rc (contact radius; default: the
    geometric intersection radius, 0 when apart), t_contact, vn_impact
    (zhou_2008_collisional), por_i, por_j (local porosities; default
    ``porosity``); material properties with suffix _i/_j: k (ki/kj), cp, rho,
    hardness, roughness, slope, E, nu, E_real, alpha, emissivity; gas and
    model parameters: kf, porosity, layer, min_separation, core_ratio, cutoff,
    mean_free_path, gamma, Pr, alpha_gas, rho_f, mu_f, cp_f, k_liquid,
    filling_angle; the full scene key of any input a model record declares (material keys
    with the suffix). The model and the inputs it needs come from its record
    (dem.thermal.registry). Calls the njit dispatchers direct_pp / indirect_pp.
    """
    mech, name = _mechanism_of(model)
    geom, mats, gas = _split_inputs(inputs, ("Ri", "Rj", "d", "rc"), ("_i", "_j"),
                                    ("t_contact", "vn_impact", "por_i", "por_j"))
    _require(geom, ("Ri", "Rj", "d"), name)
    _check_model_inputs(mech, name, mats, ("_i", "_j"), gas)
    tmat, garr, _ = build_tables(mats, gas)
    Ri, Rj, d = float(geom["Ri"]), float(geom["Rj"]), float(geom["d"])
    if Ri <= 0 or Rj <= 0 or d <= 0:
        raise ValueError("Ri, Rj and d must be > 0")
    rc = float(geom["rc"]) if "rc" in geom else float(geometric_pp(Ri, Rj, d))
    mid = registry.model_id(mech, name)
    if mech == "direct":
        return float(direct_pp(mid, Ri, Rj, d, rc, 0, 1, tmat, garr,
                               float(geom.get("t_contact", 0.0)), float(geom.get("vn_impact", 0.0))))
    por = garr[registry.POROSITY_GLOBAL]
    return float(indirect_pp(mid, Ri, Rj, d, rc, 0, 1, float(geom.get("por_i", por)),
                             float(geom.get("por_j", por)), tmat, garr))


def wall_conductance(model, **inputs):
    """Particle-wall conductance [W/K] of a direct or indirect model.

    Inputs: R (particle radius), d (centre-to-wall distance), rc (default
    sqrt(R^2 - d^2) if d < R else 0), t_contact, vn_impact, por (default
    ``porosity``); particle/wall material properties with suffix _p/_w
    (kp, kw; kw defaults to inf = perfectly conducting wall, ref 001), and
    the gas/model parameters of pair_conductance.
    """
    mech, name = _mechanism_of(model)
    geom, mats, gas = _split_inputs(inputs, ("R", "d", "rc"), ("_p", "_w"),
                                    ("t_contact", "vn_impact", "por"))
    _require(geom, ("R", "d"), name)
    mats[1].setdefault("thermal_conductivity", math.inf)
    _check_model_inputs(mech, name, mats, ("_p", "_w"), gas)
    tmat, garr, _ = build_tables(mats, gas)
    R, d = float(geom["R"]), float(geom["d"])
    if R <= 0 or d <= 0:
        raise ValueError("R and d must be > 0")
    rc = float(geom["rc"]) if "rc" in geom else float(geometric_pw(R, d))
    mid = registry.model_id(mech, name)
    if mech == "direct":
        return float(direct_pw(mid, R, d, rc, 0, 1, tmat, garr,
                               float(geom.get("t_contact", 0.0)), float(geom.get("vn_impact", 0.0))))
    por = float(geom.get("por", garr[registry.POROSITY_GLOBAL]))
    return float(indirect_pw(mid, R, d, rc, 0, 1, por, tmat, garr))


def nusselt(correlation, Re, Pr, porosity=1.0, **options):
    """Nusselt number of a correlation (ranz_marshall, whitaker, gunn, li_mason).

    options: viscosity_ratio (Whitaker, default 1), li_mason_exponent (alias m;
    default 4.75 = dense, 3.5 = dilute).
    """
    cid = registry.model_id("convection", correlation)
    valid = ("viscosity_ratio", "li_mason_exponent", "m")
    for k in options:
        if k not in valid:
            raise ValueError(f"unknown option '{k}', valid: {', '.join(valid)}")
    vr = float(options.get("viscosity_ratio", 1.0))
    m = float(options.get("li_mason_exponent", options.get("m", 4.75)))
    if Re < 0 or Pr <= 0 or not (0.0 <= porosity <= 1.0):
        raise ValueError("need Re >= 0, Pr > 0 and 0 <= porosity <= 1")
    return float(nusselt_id_opt(cid, float(Re), float(Pr), float(porosity), vr, m))
