"""Registry of the thermal models: names, integer ids, needed material keys,
parameters (defaults and allowed ranges), and the table layouts passed to
the njit kernels.

Material table ``tmat[n_materials, N_TPROP]`` (float64, SI units). Column
indices (module constants) and the material-dictionary key of each column:

    K_COND         0  "thermal_conductivity"       W/(m K)   (inf: perfect conductor)
    CP             1  "heat_capacity"              J/(kg K)
    DENSITY        2  "density"                    kg/m^3
    EMISSIVITY     3  "emissivity"                 -
    MICROHARDNESS  4  "microhardness"              Pa
    ROUGHNESS      5  "roughness"                  m (RMS surface roughness)
    ASPERITY_SLOPE 6  "asperity_slope"             - (RMS asperity slope)
    YOUNG          7  "youngs_modulus"             Pa (value used in the simulation)
    POISSON        8  "poisson_ratio"              -
    REAL_YOUNG     9  "real_youngs_modulus"        Pa (physical value; 0: same as YOUNG)
    ACCOM         10  "accommodation_coefficient"  - (thermal, surface-gas)

Missing entries are NaN (except REAL_YOUNG -> 0 meaning "not given" and
ACCOM -> gas "accommodation_coefficient" default).

Gas / global parameter array ``gas[N_GAS]`` (float64), index and key:

    KF              0 "conductivity"             W/(m K)  fluid conductivity k_f
    RHO_F           1 "density"                  kg/m^3
    MU_F            2 "viscosity"                Pa s
    CP_F            3 "heat_capacity"            J/(kg K)
    PR              4 "prandtl"                  -  (default mu_f cp_f / k_f)
    MEAN_FREE_PATH  5 "mean_free_path"           m  (molecular mean free path Lambda)
    GAMMA_RATIO     6 "heat_capacity_ratio"      -  (cp/cv of the gas)
    ACCOMMODATION   7 "accommodation_coefficient" - default for materials
    T_F             8 "temperature"              K
    U_F             9 "velocity"                 m/s (slip velocity magnitude |u_f - v_p|)
    POROSITY_GLOBAL 10 "porosity"                -  (used when no local porosity)
    CUTOFF         11 "cutoff"                   -  indirect conduction cut-off: surface gap / min(Ri,Rj)
    LAYER          12 "layer"                    -  surrounding layer thickness / R
    MIN_SEP        13 "min_separation"           m  minimum conduction distance S
    CORE_RATIO     14 "core_ratio"               -  isothermal core radius / R (Voronoi B)
    VISC_RATIO     15 "viscosity_ratio"          -  mu_f/mu_fs (Whitaker)
    LM_EXPONENT    16 "li_mason_exponent"        -  m of Li & Mason
    K_LIQ          17 "liquid_conductivity"      W/(m K) (Vargas & McCarthy bridge)
    FILL_ANGLE     18 "filling_angle"            rad (liquid bridge filling angle, 0: dry)
    RAD_RANGE      19 "radiation_range"          -  radius of radiative influence / R
"""
import math

import numpy as np

from . import contact_radius as _cr

# ---------------------------------------------------------------- material table
K_COND = 0
CP = 1
DENSITY = 2
EMISSIVITY = 3
MICROHARDNESS = 4
ROUGHNESS = 5
ASPERITY_SLOPE = 6
YOUNG = 7
POISSON = 8
REAL_YOUNG = 9
ACCOM = 10
N_TPROP = 11

MATERIAL_KEYS = {
    "thermal_conductivity": K_COND,
    "heat_capacity": CP,
    "density": DENSITY,
    "emissivity": EMISSIVITY,
    "microhardness": MICROHARDNESS,
    "roughness": ROUGHNESS,
    "asperity_slope": ASPERITY_SLOPE,
    "youngs_modulus": YOUNG,
    "poisson_ratio": POISSON,
    "real_youngs_modulus": REAL_YOUNG,
    "accommodation_coefficient": ACCOM,
}

# ---------------------------------------------------------------- gas / global table
KF = 0
RHO_F = 1
MU_F = 2
CP_F = 3
PR = 4
MEAN_FREE_PATH = 5
GAMMA_RATIO = 6
ACCOMMODATION = 7
T_F = 8
U_F = 9
POROSITY_GLOBAL = 10
CUTOFF = 11
LAYER = 12
MIN_SEP = 13
CORE_RATIO = 14
VISC_RATIO = 15
LM_EXPONENT = 16
K_LIQ = 17
FILL_ANGLE = 18
RAD_RANGE = 19
QUAD_TOL = 20
N_GAS = 21

# key -> (index, default, (min, max), unit, description); default None = required
# by the models that use it (NaN when absent).
GAS_KEYS = {
    "conductivity": (KF, None, (0.0, math.inf), "W/(m K)", "fluid thermal conductivity k_f"),
    "density": (RHO_F, None, (0.0, math.inf), "kg/m^3", "fluid density"),
    "viscosity": (MU_F, None, (0.0, math.inf), "Pa s", "fluid dynamic viscosity"),
    "heat_capacity": (CP_F, None, (0.0, math.inf), "J/(kg K)", "fluid specific heat"),
    "prandtl": (PR, None, (0.0, math.inf), "-", "Prandtl number (default mu cp / k)"),
    "mean_free_path": (MEAN_FREE_PATH, 6.8e-8, (0.0, math.inf), "m", "gas molecular mean free path"),
    "heat_capacity_ratio": (GAMMA_RATIO, 1.4, (1.0, 5.0 / 3.0 + 1e-12), "-", "gas cp/cv"),
    "accommodation_coefficient": (ACCOMMODATION, 0.9, (1e-6, 1.0), "-", "default thermal accommodation coefficient"),
    "temperature": (T_F, None, (0.0, math.inf), "K", "fluid temperature"),
    "velocity": (U_F, 0.0, (0.0, math.inf), "m/s", "fluid-particle slip velocity magnitude"),
    "porosity": (POROSITY_GLOBAL, 0.4, (0.0, 1.0), "-", "porosity used when no local value"),
    "cutoff": (CUTOFF, 1.0, (0.0, math.inf), "-", "indirect conduction cut-off gap / min(Ri,Rj) (Zhou 2009: 1)"),
    "layer": (LAYER, 0.4, (0.0, math.inf), "-", "surrounding fluid layer thickness / R (ref 003)"),
    "min_separation": (MIN_SEP, 2.75e-8, (0.0, math.inf), "m", "minimum conduction distance S (ref 003)"),
    "core_ratio": (CORE_RATIO, 0.5, (1e-6, 1.0), "-", "isothermal core radius / R (Cheng 1999: 0.5)"),
    "viscosity_ratio": (VISC_RATIO, 1.0, (0.0, math.inf), "-", "mu_f / mu_f(surface) in Whitaker"),
    "li_mason_exponent": (LM_EXPONENT, 4.75, (3.5, 4.75), "-", "Li & Mason porosity exponent m (3.5 dilute, 4.75 dense)"),
    "liquid_conductivity": (K_LIQ, 0.0, (0.0, math.inf), "W/(m K)", "liquid bridge conductivity"),
    "filling_angle": (FILL_ANGLE, 0.0, (0.0, math.pi / 2), "rad", "liquid bridge filling angle (0 = dry)"),
    "radiation_range": (RAD_RANGE, 3.0, (1.0, math.inf), "-", "radius of radiative influence / R"),
    # numerical: relative tolerance of the adaptive Gauss-Kronrod quadrature of the integral
    # indirect models (Voronoi A, surrounding layer); default chosen from the work-precision
    # sweep of benchmarks/accuracy (docs/benchmarks.md, "Quadrature tolerance")
    "quadrature_tolerance": (QUAD_TOL, 1e-4, (1e-14, 0.1), "-",
                             "relative tolerance of the integral indirect models' quadrature"),
}

# ---------------------------------------------------------------- model ids
# direct conduction
DIRECT_BATCHELOR_OBRIEN = 0
DIRECT_THERMAL_PIPE = 1
DIRECT_QUINTANA_RUIZ_CAMPELLO = 2
DIRECT_ROJEK = 3
DIRECT_ZHOU_COLLISIONAL = 4
DIRECT_BEAULIEU = 5
# indirect conduction
INDIRECT_CHENG_VORONOI_A = 0
INDIRECT_GAN_VORONOI_A = 1
INDIRECT_CHENG_VORONOI_B = 2
INDIRECT_CHEN_VORONOI_B = 3
INDIRECT_RONG_HORIO = 4
INDIRECT_MUSSER = 5
INDIRECT_VARGAS_MCCARTHY = 6
# convection
NU_RANZ_MARSHALL = 0
NU_WHITAKER = 1
NU_GUNN = 2
NU_LI_MASON = 3
# radiation
RAD_ZHOU_2009 = 0
RAD_KRAUSE_2017 = 1
# friction heat
FRIC_NGUYEN_2009 = 0
FRIC_ROJEK_2014 = 1
FRIC_IMPACT_001 = 2
# partition
PART_VARADI_1996 = 0
PART_ROJEK_2014 = 1
PART_EQUAL = 2

_K = "thermal_conductivity"
_COLL = ("thermal_conductivity", "heat_capacity", "density", "youngs_modulus", "poisson_ratio")
_BEAU = ("thermal_conductivity", "microhardness", "roughness", "asperity_slope",
         "youngs_modulus", "poisson_ratio")


def _p(*names):
    return tuple(names)


# mechanism -> name -> dict(id, material keys, gas/global parameter keys)
MODELS = {
    "direct": {
        "batchelor_obrien": dict(id=DIRECT_BATCHELOR_OBRIEN, material=(_K,), params=()),
        "thermal_pipe": dict(id=DIRECT_THERMAL_PIPE, material=(_K,), params=()),
        "quintana_ruiz_campello_2020": dict(id=DIRECT_QUINTANA_RUIZ_CAMPELLO, material=(_K,), params=()),
        "rojek_2014": dict(id=DIRECT_ROJEK, material=(_K,), params=()),
        "zhou_2008_collisional": dict(id=DIRECT_ZHOU_COLLISIONAL, material=_COLL, params=()),
        "beaulieu_2020": dict(id=DIRECT_BEAULIEU, material=_BEAU,
                              params=_p("conductivity", "mean_free_path", "heat_capacity_ratio",
                                        "prandtl", "accommodation_coefficient")),
    },
    "indirect": {
        "cheng_1999_voronoi_a": dict(id=INDIRECT_CHENG_VORONOI_A, material=(_K,),
                                     params=_p("conductivity", "porosity", "cutoff")),
        "gan_2016_voronoi_a": dict(id=INDIRECT_GAN_VORONOI_A, material=(_K,),
                                   params=_p("conductivity", "porosity", "cutoff")),
        "cheng_1999_voronoi_b": dict(id=INDIRECT_CHENG_VORONOI_B, material=(_K,),
                                     params=_p("conductivity", "porosity", "cutoff", "core_ratio")),
        "chen_2019_voronoi_b": dict(id=INDIRECT_CHEN_VORONOI_B, material=(_K,),
                                    params=_p("conductivity", "porosity", "cutoff", "core_ratio")),
        "rong_horio_1999_surrounding_layer": dict(id=INDIRECT_RONG_HORIO, material=(),
                                                  params=_p("conductivity", "layer", "min_separation", "cutoff")),
        "musser_2011_surrounding_layer": dict(id=INDIRECT_MUSSER, material=(),
                                              params=_p("conductivity", "layer", "min_separation", "cutoff")),
        "vargas_mccarthy_2002": dict(id=INDIRECT_VARGAS_MCCARTHY, material=(),
                                     params=_p("conductivity", "mean_free_path", "heat_capacity_ratio",
                                               "prandtl", "accommodation_coefficient",
                                               "liquid_conductivity", "filling_angle")),
    },
    "convection": {
        "ranz_marshall": dict(id=NU_RANZ_MARSHALL, material=(), params=_p("conductivity", "prandtl")),
        "whitaker": dict(id=NU_WHITAKER, material=(), params=_p("conductivity", "prandtl", "viscosity_ratio")),
        "gunn": dict(id=NU_GUNN, material=(), params=_p("conductivity", "prandtl", "porosity")),
        "li_mason": dict(id=NU_LI_MASON, material=(),
                         params=_p("conductivity", "prandtl", "porosity", "li_mason_exponent")),
    },
    "radiation": {
        "zhou_2009": dict(id=RAD_ZHOU_2009, material=("emissivity",),
                          params=_p("temperature", "porosity", "radiation_range")),
        "krause_2017": dict(id=RAD_KRAUSE_2017, material=("emissivity",), params=_p("radiation_range")),
    },
    "friction": {
        "nguyen_2009": dict(id=FRIC_NGUYEN_2009, material=(), params=()),
        "rojek_2014": dict(id=FRIC_ROJEK_2014, material=(), params=()),
        "impact_heat": dict(id=FRIC_IMPACT_001, material=(), params=()),
    },
    "partition": {
        "varadi_1996": dict(id=PART_VARADI_1996, material=(_K,), params=()),
        "rojek_2014": dict(id=PART_ROJEK_2014, material=(_K, "density", "heat_capacity"), params=()),
        "equal": dict(id=PART_EQUAL, material=(), params=()),
    },
    "contact_radius": {
        name: dict(id=i, material=(("youngs_modulus", "poisson_ratio") if name == "hertz_force" else ()),
                   params=())
        for name, i in _cr.METHODS.items()
    },
    "correction": {
        name: dict(id=i, material=(() if name == "none" else ("youngs_modulus", "poisson_ratio",
                                                               "real_youngs_modulus")),
                   params=())
        for name, i in _cr.CORRECTIONS.items()
    },
}

# convenient aliases accepted by model_id()
ALIASES = {
    "direct": {"batchelor_obrien_1977": "batchelor_obrien", "bob": "batchelor_obrien",
               "quintana_ruiz_campello": "quintana_ruiz_campello_2020", "zhou_2008": "zhou_2008_collisional",
               "collisional": "zhou_2008_collisional", "beaulieu_2020_network": "beaulieu_2020",
               "beaulieu": "beaulieu_2020"},
    "indirect": {"voronoi_a": "cheng_1999_voronoi_a", "voronoi_b": "cheng_1999_voronoi_b",
                 "surrounding_layer": "musser_2011_surrounding_layer",
                 "rong_horio_1999": "rong_horio_1999_surrounding_layer",
                 "musser_2011": "musser_2011_surrounding_layer", "vargas_mccarthy": "vargas_mccarthy_2002"},
    "convection": {"ranz_marshall_1952": "ranz_marshall", "whitaker_1972": "whitaker", "gunn_1978": "gunn",
                   "li_mason_2000": "li_mason"},
    "radiation": {"zhou_2009_radiation": "zhou_2009", "krause_2017_radiation": "krause_2017"},
    "friction": {"nguyen_2009_friction_heat": "nguyen_2009"},
    "partition": {"varadi_1996_partition": "varadi_1996"},
    "contact_radius": {},
    "correction": {},
}


def valid_names(mechanism):
    """Sorted list of the canonical model names of a mechanism."""
    if mechanism not in MODELS:
        raise ValueError(f"unknown mechanism '{mechanism}', valid: {', '.join(sorted(MODELS))}")
    return sorted(MODELS[mechanism])


def canonical_name(mechanism, name):
    names = valid_names(mechanism)
    key = str(name).strip().lower()
    key = ALIASES[mechanism].get(key, key)
    if key not in MODELS[mechanism]:
        raise ValueError(f"unknown {mechanism} model '{name}', valid: {', '.join(names)}")
    return key


def model_id(mechanism, name):
    """Integer id of ``name`` for ``mechanism``; ValueError listing valid names."""
    return MODELS[mechanism][canonical_name(mechanism, name)]["id"]


def required_material_keys(mechanism, name):
    return MODELS[mechanism][canonical_name(mechanism, name)]["material"]


def required_params(mechanism, name):
    return MODELS[mechanism][canonical_name(mechanism, name)]["params"]


def check_material(mechanism, name, material, material_name="material"):
    """Raise ValueError('missing material key ...') if ``material`` lacks a needed key."""
    missing = [k for k in required_material_keys(mechanism, name) if k not in material]
    if missing:
        raise ValueError(f"missing material key(s) {', '.join(missing)} in '{material_name}' "
                         f"required by {mechanism} model '{canonical_name(mechanism, name)}'")


def check_params(mechanism, name, gas):
    """Raise ValueError if a needed gas/global parameter without default is missing."""
    missing = []
    for k in required_params(mechanism, name):
        default = GAS_KEYS[k][1]
        if k not in gas and default is None:
            if k == "prandtl" and all(x in gas for x in ("viscosity", "heat_capacity", "conductivity")):
                continue
            missing.append(k)
    if missing:
        raise ValueError(f"missing parameter(s) {', '.join(missing)} required by {mechanism} model "
                         f"'{canonical_name(mechanism, name)}'")


def _check_range(key, value, lo, hi):
    if not (lo <= value <= hi):
        raise ValueError(f"parameter '{key}' = {value} outside allowed range [{lo}, {hi}]")


def build_material_table(materials):
    """Build ``tmat`` from a list of dicts or a dict name -> dict.

    Returns (tmat, names). Unknown keys raise ValueError listing valid keys.
    """
    if isinstance(materials, dict):
        names = list(materials)
        mats = [materials[n] for n in names]
    else:
        mats = list(materials)
        names = [str(i) for i in range(len(mats))]
    tmat = np.full((len(mats), N_TPROP), np.nan)
    for i, m in enumerate(mats):
        for k, v in m.items():
            if k not in MATERIAL_KEYS:
                raise ValueError(f"unknown material key '{k}', valid: {', '.join(sorted(MATERIAL_KEYS))}")
            v = float(v)
            if v < 0.0:
                raise ValueError(f"material key '{k}' must be >= 0, got {v}")
            tmat[i, MATERIAL_KEYS[k]] = v
        if np.isnan(tmat[i, REAL_YOUNG]):
            tmat[i, REAL_YOUNG] = 0.0
    return tmat, names


def build_gas_table(gas=None):
    """Build ``gas[N_GAS]`` from a dict (keys of ``GAS_KEYS``), filling defaults.

    Missing keys without default are NaN; the Prandtl number defaults to
    mu_f cp_f / k_f when those are given.
    """
    gas = dict(gas or {})
    arr = np.full(N_GAS, np.nan)
    for k, v in gas.items():
        if k not in GAS_KEYS:
            raise ValueError(f"unknown gas/global parameter '{k}', valid: {', '.join(sorted(GAS_KEYS))}")
        idx, _, (lo, hi), _, _ = GAS_KEYS[k]
        v = float(v)
        _check_range(k, v, lo, hi)
        arr[idx] = v
    for k, (idx, default, _, _, _) in GAS_KEYS.items():
        if k not in gas and default is not None:
            arr[idx] = default
    if "prandtl" not in gas and all(x in gas for x in ("viscosity", "heat_capacity", "conductivity")):
        arr[PR] = gas["viscosity"] * gas["heat_capacity"] / gas["conductivity"]
    return arr


def build_tables(materials, gas=None):
    """Build (tmat, gas_array, material_names); accommodation coefficients
    missing in a material are filled from the gas default."""
    tmat, names = build_material_table(materials)
    garr = build_gas_table(gas)
    for i in range(tmat.shape[0]):
        if np.isnan(tmat[i, ACCOM]):
            tmat[i, ACCOM] = garr[ACCOMMODATION]
    return tmat, garr, names
