"""Registry of the thermal models, derived from their records (dem.thermal.records).

Adding a model: write its law and its ``ModelRecord`` in its own module, and add the module to
``MODEL_MODULES`` below (docs/architecture.md, "Adding a model"). Everything else - names, ids,
aliases, required inputs, defaults and ranges, the table layouts, the per-contact history width,
the neighbour reach and the njit dispatchers - is derived from the records.

The columns below are the fixed part of the table layouts (the kernels index them by these
constants); a model's ``new_inputs`` are appended after them, in ``MODEL_MODULES`` order.

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
import importlib
import math

import numpy as np

from .records import GAS, MATERIAL, Input

# the modules holding the model records (one line per model file)
MODEL_MODULES = (
    "dem.thermal.direct",
    "dem.thermal.indirect",
    "dem.thermal.convection",
    "dem.thermal.radiation",
    "dem.thermal.generation",
    "dem.thermal.contact_radius",
    "dem.thermal.bahrami_2006",
)

# mechanism -> (thermal scene key, label in `dem check`)
MECHANISMS = {
    "direct": ("direct", "direct conduction"),
    "indirect": ("indirect", "indirect conduction"),
    "convection": ("convection", "convection"),
    "radiation": ("radiation", "radiation"),
    "friction": ("friction_heat", "friction heat"),
    "partition": ("partition", "heat partition"),
    "contact_radius": ("contact_radius", "contact radius"),
    "correction": ("correction", "contact radius correction"),
}

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

_INF = math.inf
# fixed material columns, in column order (a table column per input)
BASE_MATERIAL_INPUTS = (
    Input("thermal_conductivity", MATERIAL, "W/(m K)", None, (0.0, _INF), "thermal conductivity (inf: perfect conductor)"),
    Input("heat_capacity", MATERIAL, "J/(kg K)", None, (0.0, _INF), "specific heat capacity"),
    Input("density", MATERIAL, "kg/m^3", None, (0.0, _INF), "density"),
    Input("emissivity", MATERIAL, "-", None, (0.0, _INF), "grey-body emissivity"),
    Input("microhardness", MATERIAL, "Pa", None, (0.0, _INF), "surface microhardness"),
    Input("roughness", MATERIAL, "m", None, (0.0, _INF), "RMS surface roughness"),
    Input("asperity_slope", MATERIAL, "-", None, (0.0, _INF), "RMS asperity slope"),
    Input("youngs_modulus", MATERIAL, "Pa", None, (0.0, _INF), "Young's modulus used in the simulation"),
    Input("poisson_ratio", MATERIAL, "-", None, (0.0, _INF), "Poisson's ratio"),
    Input("real_youngs_modulus", MATERIAL, "Pa", 0.0, (0.0, _INF), "physical Young's modulus (0: same as youngs_modulus)"),
    Input("accommodation_coefficient", MATERIAL, "-", None, (0.0, _INF),
          "thermal accommodation coefficient surface-gas (default: the gas one)"),
)

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

# fixed gas/global columns, in column order; default None = required by the models that use it
BASE_GAS_INPUTS = (
    Input("conductivity", GAS, "W/(m K)", None, (0.0, _INF), "fluid thermal conductivity k_f"),
    Input("density", GAS, "kg/m^3", None, (0.0, _INF), "fluid density"),
    Input("viscosity", GAS, "Pa s", None, (0.0, _INF), "fluid dynamic viscosity"),
    Input("heat_capacity", GAS, "J/(kg K)", None, (0.0, _INF), "fluid specific heat"),
    Input("prandtl", GAS, "-", None, (0.0, _INF), "Prandtl number (default mu cp / k)"),
    Input("mean_free_path", GAS, "m", 6.8e-8, (0.0, _INF), "gas molecular mean free path"),
    Input("heat_capacity_ratio", GAS, "-", 1.4, (1.0, 5.0 / 3.0 + 1e-12), "gas cp/cv"),
    Input("accommodation_coefficient", GAS, "-", 0.9, (1e-6, 1.0), "default thermal accommodation coefficient"),
    Input("temperature", GAS, "K", None, (0.0, _INF), "fluid temperature"),
    Input("velocity", GAS, "m/s", 0.0, (0.0, _INF), "fluid-particle slip velocity magnitude"),
    Input("porosity", GAS, "-", 0.4, (0.0, 1.0), "porosity used when no local value"),
    Input("cutoff", GAS, "-", 1.0, (0.0, _INF), "indirect conduction cut-off gap / min(Ri,Rj) (Zhou 2009: 1)"),
    Input("layer", GAS, "-", 0.4, (0.0, _INF), "surrounding fluid layer thickness / R (ref 003)"),
    Input("min_separation", GAS, "m", 2.75e-8, (0.0, _INF), "minimum conduction distance S (ref 003)"),
    Input("core_ratio", GAS, "-", 0.5, (1e-6, 1.0), "isothermal core radius / R (Cheng 1999: 0.5)"),
    Input("viscosity_ratio", GAS, "-", 1.0, (0.0, _INF), "mu_f / mu_f(surface) in Whitaker"),
    Input("li_mason_exponent", GAS, "-", 4.75, (3.5, 4.75), "Li & Mason porosity exponent m (3.5 dilute, 4.75 dense)"),
    Input("liquid_conductivity", GAS, "W/(m K)", 0.0, (0.0, _INF), "liquid bridge conductivity"),
    Input("filling_angle", GAS, "rad", 0.0, (0.0, math.pi / 2), "liquid bridge filling angle (0 = dry)"),
    Input("radiation_range", GAS, "-", 3.0, (1.0, _INF), "radius of radiative influence / R"),
    # numerical: relative tolerance of the adaptive Gauss-Kronrod quadrature of the integral
    # indirect models (Voronoi A, surrounding layer); default chosen from the work-precision
    # sweep of benchmarks/accuracy (docs/benchmarks/accuracy.md, "Quadrature tolerance")
    Input("quadrature_tolerance", GAS, "-", 1e-4, (1e-14, 0.1),
          "relative tolerance of the integral indirect models' quadrature"),
)

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


# ---------------------------------------------------------------- derived from the records
_DERIVED = None


def _collect(modules=MODEL_MODULES, base_material=BASE_MATERIAL_INPUTS, base_gas=BASE_GAS_INPUTS):
    """Derive every table from the records of ``modules`` (pure: used by the tests with a
    synthetic module list). Raises ValueError on a duplicate name, alias or id, an unknown
    input key, or a new input that redefines an existing column."""
    records = []
    for modname in modules:
        records.extend(importlib.import_module(modname).RECORDS)
    mat_inputs = list(base_material)
    gas_inputs = list(base_gas)
    for rec in records:
        for inp in rec.new_inputs:
            cols = mat_inputs if inp.table == MATERIAL else gas_inputs
            if any(c.key == inp.key for c in cols):
                raise ValueError(f"model '{rec.name}' declares input '{inp.key}' that already exists")
            cols.append(inp)
    mat_keys = {i.key: n for n, i in enumerate(mat_inputs)}
    gas_keys = {i.key: n for n, i in enumerate(gas_inputs)}
    by_mech = {m: {} for m in MECHANISMS}
    aliases = {m: {} for m in MECHANISMS}
    for rec in records:
        if rec.mechanism not in by_mech:
            raise ValueError(f"model '{rec.name}': unknown mechanism '{rec.mechanism}'")
        names = by_mech[rec.mechanism]
        if rec.name in names or rec.name in aliases[rec.mechanism]:
            raise ValueError(f"duplicate {rec.mechanism} model name '{rec.name}'")
        if any(r.id == rec.id for r in names.values()):
            raise ValueError(f"duplicate {rec.mechanism} model id {rec.id} ('{rec.name}')")
        mat, gas = rec.inputs()
        for k in mat:
            if k not in mat_keys:
                raise ValueError(f"model '{rec.name}' needs unknown material key '{k}'")
        for k in gas:
            if k not in gas_keys:
                raise ValueError(f"model '{rec.name}' reads unknown gas key '{k}'")
        if rec.reach is not None and rec.reach not in gas_keys:
            raise ValueError(f"model '{rec.name}': reach key '{rec.reach}' is not a gas key")
        names[rec.name] = rec
        for a in rec.aliases:
            if a in names or a in aliases[rec.mechanism]:
                raise ValueError(f"duplicate {rec.mechanism} alias '{a}'")
            aliases[rec.mechanism][a] = rec.name
    return dict(records=tuple(records), material_inputs=tuple(mat_inputs), gas_inputs=tuple(gas_inputs),
                material_keys=mat_keys, gas_keys=gas_keys, by_mech=by_mech, aliases=aliases)


def derived():
    """The tables derived from the records of MODEL_MODULES (built once)."""
    global _DERIVED
    if _DERIVED is None:
        d = _collect()
        fixed_m = {i.key: n for n, i in enumerate(BASE_MATERIAL_INPUTS)}
        fixed_g = {i.key: n for n, i in enumerate(BASE_GAS_INPUTS)}
        assert all(d["material_keys"][k] == n for k, n in fixed_m.items())
        assert all(d["gas_keys"][k] == n for k, n in fixed_g.items())
        _DERIVED = d
    return _DERIVED


def __getattr__(name):
    # tables derived lazily from the records (the model modules import this module's constants)
    if name == "MATERIAL_KEYS":
        return dict(derived()["material_keys"])
    if name == "GAS_KEYS":
        # key -> (index, default, (min, max), unit, description)
        d = derived()
        return {i.key: (d["gas_keys"][i.key], i.default, i.bounds, i.unit, i.description)
                for i in d["gas_inputs"]}
    if name == "N_TPROP":
        return len(derived()["material_inputs"])
    if name == "N_GAS":
        return len(derived()["gas_inputs"])
    if name == "MODELS":
        # mechanism -> name -> dict(id, material keys, gas/global parameter keys)
        return {m: {n: dict(id=r.id, material=r.inputs()[0], params=r.inputs()[1]) for n, r in recs.items()}
                for m, recs in derived()["by_mech"].items()}
    if name == "ALIASES":
        return {m: dict(a) for m, a in derived()["aliases"].items()}
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


def records(mechanism=None):
    """All model records, or those of one mechanism (name -> record)."""
    if mechanism is None:
        return derived()["records"]
    if mechanism not in MECHANISMS:
        raise ValueError(f"unknown mechanism '{mechanism}', valid: {', '.join(sorted(MECHANISMS))}")
    return dict(derived()["by_mech"][mechanism])


def valid_names(mechanism):
    """Sorted list of the canonical model names of a mechanism."""
    return sorted(records(mechanism))


def canonical_name(mechanism, name):
    names = valid_names(mechanism)
    key = str(name).strip().lower()
    key = derived()["aliases"][mechanism].get(key, key)
    if key not in names:
        raise ValueError(f"unknown {mechanism} model '{name}', valid: {', '.join(names)}")
    return key


def record(mechanism, name):
    """The record of model ``name`` (canonical name or alias) of ``mechanism``."""
    return derived()["by_mech"][mechanism][canonical_name(mechanism, name)]


def model_id(mechanism, name):
    """Integer id of ``name`` for ``mechanism``; ValueError listing valid names."""
    return record(mechanism, name).id


def required_material_keys(mechanism, name):
    return record(mechanism, name).inputs()[0]


def required_params(mechanism, name):
    return record(mechanism, name).inputs()[1]


def gas_input(key):
    """The ``Input`` declaration of gas/global key ``key``."""
    d = derived()
    return d["gas_inputs"][d["gas_keys"][key]]


def check_material(mechanism, name, material, material_name="material"):
    """Raise ValueError('missing material key ...') if ``material`` lacks a needed key."""
    missing = [k for k in required_material_keys(mechanism, name) if k not in material]
    if missing:
        raise ValueError(f"missing material key(s) {', '.join(missing)} in '{material_name}' "
                         f"required by {mechanism} model '{canonical_name(mechanism, name)}'")


def missing_params(mechanism, name, gas):
    """Gas/global keys the model needs that have no default and are absent from ``gas``."""
    missing = []
    for k in required_params(mechanism, name):
        if k not in gas and gas_input(k).default is None:
            if k == "prandtl" and all(x in gas for x in ("viscosity", "heat_capacity", "conductivity")):
                continue
            missing.append(k)
    return missing


def check_params(mechanism, name, gas):
    """Raise ValueError if a needed gas/global parameter without default is missing."""
    missing = missing_params(mechanism, name, gas)
    if missing:
        raise ValueError(f"missing parameter(s) {', '.join(missing)} required by {mechanism} model "
                         f"'{canonical_name(mechanism, name)}'")


def history_width(selected):
    """Floats stored per contact by the selected models: ``selected`` maps mechanism -> name
    (or "none"); the largest ``history`` of their records (0: no per-contact state)."""
    width = 0
    for mech, name in selected.items():
        if name and name != "none":
            width = max(width, record(mech, name).history)
    return width


def neighbour_reach(selected, gas, rmax):
    """How far beyond contact [m] the selected models need neighbours: the largest
    (gas[reach key] + reach_offset) * rmax over their records (0: contacts only)."""
    reach = 0.0
    for mech, name in selected.items():
        if name and name != "none":
            rec = record(mech, name)
            if rec.reach is not None:
                reach = max(reach, (gas[derived()["gas_keys"][rec.reach]] + rec.reach_offset) * rmax)
    return reach


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
    d = derived()
    keys = d["material_keys"]
    tmat = np.full((len(mats), len(keys)), np.nan)
    for i, m in enumerate(mats):
        for k, v in m.items():
            if k not in keys:
                raise ValueError(f"unknown material key '{k}', valid: {', '.join(sorted(keys))}")
            v = float(v)
            if v < 0.0:
                raise ValueError(f"material key '{k}' must be >= 0, got {v}")
            tmat[i, keys[k]] = v
        for inp in d["material_inputs"]:  # declared defaults (real_youngs_modulus: 0 = not given)
            if inp.default is not None and np.isnan(tmat[i, keys[inp.key]]):
                tmat[i, keys[inp.key]] = inp.default
    return tmat, names


def build_gas_table(gas=None):
    """Build ``gas[N_GAS]`` from a dict (keys of ``GAS_KEYS``), filling defaults.

    Missing keys without default are NaN; the Prandtl number defaults to
    mu_f cp_f / k_f when those are given.
    """
    gas = dict(gas or {})
    d = derived()
    keys = d["gas_keys"]
    arr = np.full(len(keys), np.nan)
    for k, v in gas.items():
        if k not in keys:
            raise ValueError(f"unknown gas/global parameter '{k}', valid: {', '.join(sorted(keys))}")
        lo, hi = d["gas_inputs"][keys[k]].bounds
        v = float(v)
        _check_range(k, v, lo, hi)
        arr[keys[k]] = v
    for inp in d["gas_inputs"]:
        if inp.key not in gas and inp.default is not None:
            arr[keys[inp.key]] = inp.default
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
