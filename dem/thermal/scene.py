"""[thermal] and [gas] sections of a scene, and the thermal conditions of walls.

    [thermal]
    initial_temperature = 300.0          # K, for groups without their own temperature
    initial_regions = [{min = [..], max = [..], temperature = 400.0}]   # override in boxes
    direct = "batchelor_obrien"          # or "none"; see docs/models.md for all names
    contact_radius = "hertz_overlap"     # hertz_force | hertz_overlap | geometric
    correction = "auto"                  # lu_2017 if youngs_modulus is softened (real_youngs_modulus
                                         # given), else none | zhou_2010 | lu_2017 | morris_2016_area | ...
    direct_factor = 1.0                  # multiplies the direct conductance
    indirect = "none"                    # voronoi_a, voronoi_b, surrounding_layer, ...
    porosity = "local"                   # local | global | voronoi (true tessellation, scipy)
    quadrature_tolerance = 1e-4          # relative tolerance of the integral indirect models
    convection = "none"                  # ranz_marshall | whitaker | gunn | li_mason
    radiation = "none"                   # zhou_2009 | krause_2017
    friction_heat = "none"               # nguyen_2009 | rojek_2014 | impact_heat
    partition = "equal"                  # varadi_1996 | rojek_2014 | equal
    integrator = "auto"                  # euler | exponential | implicit | trbdf2 | auto
    time_step = 1.0                      # thermal step, only with simulation.mechanics = false
    [[thermal.sources]]                  # W per particle of a group, or W/m3 in a box
    group = 0 ; power = 0.01
    [gas]                                # conductivity, density, viscosity, heat_capacity,
    conductivity = 0.026                 # temperature, velocity = [ux, uy, uz], ...

Walls: ``thermal = { condition = "adiabatic" | "fixed_temperature" | "fixed_heat_flux",
temperature = 400.0 | table = [[t0, T0], [t1, T1], ...], heat_flux = 1000.0, emissivity = 0.8 }``
(emissivity: a fixed-temperature wall in the particles' radiation environment, with a
radiation model; default 0, the wall takes no part in the radiation).
"""
import math

import numpy as np

from . import registry as R

THERMAL_KEYS = {"initial_temperature", "direct", "contact_radius", "correction", "direct_factor",
                "indirect", "porosity", "convection", "radiation", "friction_heat", "partition",
                "integrator", "time_step", "sources", "impact_heat_ct", "impact_heat_cn",
                "friction_heat_chi", "initial_regions", "quadrature_tolerance", "parcel_heat"}
INTEGRATORS = {"euler": 0, "exponential": 1, "implicit": 2, "trbdf2": 3}
WALL_CONDITIONS = {"adiabatic": 0, "fixed_temperature": 1, "fixed_heat_flux": 2}


def _model(v, t, key, mech, default):
    name = t.get(key, default)
    if not isinstance(name, str):
        v.err(f"thermal.{key}", f"must be a string, got {name!r}")
    if name == "none":
        return "none", -1
    try:
        rec = R.record(mech, name)
    except ValueError:
        v.err(f"thermal.{key}", f"unknown {mech} model {name!r}; valid: none, "
              f"{', '.join(n for n in R.valid_names(mech) if n != 'none')}")
    return rec.name, rec.id


def _materials_used(sc):
    """Indices of the materials the particles use (over every rank of a scene set up per rank)."""
    used = getattr(sc, "materials_used", None)
    return used if used is not None else np.unique(sc.material).tolist()


def parse_thermal(v, sc, data):
    t = data.get("thermal")
    if t is None:
        v.err("thermal", "a [gas] section needs a [thermal] section (heat transfer settings)")
    v.table(t, "thermal", THERMAL_KEYS)
    g = data.get("gas", {})
    v.table(g, "gas", set(R.GAS_KEYS) | {"velocity"})
    th = {}
    th["direct"], th["direct_id"] = _model(v, t, "direct", "direct", "batchelor_obrien")
    th["contact_radius"], th["cr_id"] = _model(v, t, "contact_radius", "contact_radius", "hertz_overlap")
    if t.get("correction", "auto") == "auto":
        # default chosen from the softening sweep (docs/benchmarks/accuracy.md, "Young's-modulus softening"):
        # with a softened modulus (real_youngs_modulus given and larger), lu_2017 keeps the static
        # contact conductance exact; without correction it is over-predicted (+115 % at E/10)
        used_m = set(_materials_used(sc))
        soft = any(float(sc.materials[k].get("real_youngs_modulus", sc.materials[k]["youngs_modulus"]))
                   != float(sc.materials[k]["youngs_modulus"]) for k in used_m)
        tt = dict(t, correction="lu_2017" if (soft and t.get("direct", "batchelor_obrien") != "none") else "none")
        th["correction"], th["corr_id"] = _model(v, tt, "correction", "correction", "none")
        th["correction_auto"] = True
    else:
        th["correction"], th["corr_id"] = _model(v, t, "correction", "correction", "none")
        th["correction_auto"] = False
    if th["corr_id"] < 0:
        th["corr_id"] = 0
    th["indirect"], th["indirect_id"] = _model(v, t, "indirect", "indirect", "none")
    th["convection"], th["convection_id"] = _model(v, t, "convection", "convection", "none")
    th["radiation"], th["radiation_id"] = _model(v, t, "radiation", "radiation", "none")
    th["friction_heat"], th["friction_id"] = _model(v, t, "friction_heat", "friction", "none")
    th["partition"], th["partition_id"] = _model(v, t, "partition", "partition", "equal")
    _check_coarse_graining(v, sc, th)
    # "scaled" (default): parcels exchange heat as their real particles do (docs/models.md, "Coarse
    # graining"); "own": by their own laws, as a particle of the parcel's size would (a comparison:
    # what a code without the thermal scaling computes)
    th["parcel_heat"] = v.string(t, "parcel_heat", "thermal", default="scaled", choices=["scaled", "own"])
    th["direct_factor"] = v.num(t, "direct_factor", "thermal", default=1.0, lo=0)
    th["porosity"] = v.string(t, "porosity", "thermal", default="local", choices=["local", "global", "voronoi"])
    th["impact_ct"] = v.num(t, "impact_heat_ct", "thermal", default=0.0, lo=0, hi=1)
    th["impact_cn"] = v.num(t, "impact_heat_cn", "thermal", default=0.0, lo=0, hi=1)
    th["chi"] = v.num(t, "friction_heat_chi", "thermal", default=1.0, lo=0, hi=1)
    integ = v.string(t, "integrator", "thermal", default="auto", choices=["auto"] + list(INTEGRATORS))
    mech = sc.simulation["mechanics"]
    th["integrator_auto"] = integ == "auto"
    if integ == "auto":
        # with mechanics: Euler, fused into the force loop. Frozen: TR-BDF2 until the conductances
        # are known, when dem.thermal.kernel.ThermalModel.choose_integrator picks by the step
        # (step_error.choose), on any number of ranks (dem.thermal.implicit_mpi under MPI)
        integ = "euler" if mech else "trbdf2"
    th["integrator"] = integ
    th["integrator_id"] = INTEGRATORS[integ]
    if "time_step" in t and mech:
        v.err("thermal.time_step", "a separate thermal step needs simulation.mechanics = false "
                                   "(with mechanics on, heat advances with the mechanical step)")
    th["time_step"] = v.num(t, "time_step", "thermal", default=None, lo=0, lo_open=True)
    if th["indirect"] == "rong_horio_1999_surrounding_layer" and th["direct_id"] >= 0:
        v.err("thermal.indirect", "rong_horio_1999_surrounding_layer already integrates over the contact "
                                  "region; use it with direct = \"none\" (or use musser_2011_surrounding_layer)")
    # gas
    gas = {}
    for k, val in g.items():
        if k == "velocity":
            continue
        gas[k] = v.num(g, k, "gas", lo=R.GAS_KEYS[k][2][0], hi=R.GAS_KEYS[k][2][1])
    uvec = v.vec(g, "velocity", "gas", default=np.zeros(3))
    gas["velocity"] = float(np.linalg.norm(uvec))
    th["gas_velocity"] = uvec
    # gas inputs without a default that the selected models read (from their records)
    for mechn, (key, _label) in R.MECHANISMS.items():
        name = th[key]
        if name == "none" or (mechn == "friction" and not mech) or (mechn == "partition" and th["friction_id"] < 0):
            continue
        missing = R.missing_params(mechn, name, gas)
        if missing and "gas" not in data:
            v.err("gas", f"missing [gas] section, needed by {mechn} model {name!r} ({', '.join(missing)}, ...)")
        for k in missing:
            inp = R.gas_input(k)
            if k == "prandtl":
                v.err("gas.prandtl", f"missing: give prandtl, or heat_capacity (Pr = mu cp / k), needed by "
                                     f"{mechn} model {name!r}")
            v.err(f"gas.{k}", f"missing required key ({inp.description}, {inp.unit}), needed by {mechn} "
                              f"model {name!r}")
    if "quadrature_tolerance" in t:
        if "quadrature_tolerance" in g:
            v.err("thermal.quadrature_tolerance", "given twice (also in [gas]); keep the one in [thermal]")
        lo, hi = R.GAS_KEYS["quadrature_tolerance"][2]
        gas["quadrature_tolerance"] = v.num(t, "quadrature_tolerance", "thermal", lo=lo, hi=hi)
    th["gas"] = gas
    # materials: thermal keys needed by the chosen models
    for k, m in enumerate(sc.materials):
        p = f"materials[{k}]"
        for inp in R.derived()["material_inputs"]:
            key = inp.key
            if key in m and key not in ("density", "youngs_modulus", "poisson_ratio"):
                v.num(m, key, p, lo=inp.bounds[0], hi=None if math.isinf(inp.bounds[1]) else inp.bounds[1],
                      lo_open=key in ("thermal_conductivity", "heat_capacity"))
        if "heat_capacity" not in m:
            v.err(p + ".heat_capacity", "missing required key for heat transfer (J/(kg K), > 0)")
    used = set(_materials_used(sc)) | {w["material"] for w in sc.walls}
    for mech_, (key_, _label) in R.MECHANISMS.items():
        name = th[key_]
        if name == "none" or (mech_ == "partition" and th["friction_id"] < 0):
            continue
        for k in sorted(used):
            m = sc.materials[k]
            missing = [key for key in R.required_material_keys(mech_, name) if key not in m]
            if missing:
                v.err(f"materials[{k}].{missing[0]}",
                      f"missing required key for {mech_} model {name!r} (material {m['name']!r})")
    if th["correction"] != "none":
        for k in sorted(used):
            if "real_youngs_modulus" not in sc.materials[k]:
                v.err(f"materials[{k}].real_youngs_modulus",
                      f"missing: correction {th['correction']!r} needs the physical Young's modulus")
    # temperatures
    T0 = v.num(t, "initial_temperature", "thermal", default=None, lo=0, lo_open=True)
    temps = []
    for k, (tg, n) in enumerate(zip(sc.temperature, np.bincount(sc.group, minlength=len(sc.temperature)))):
        if tg is None:
            if T0 is None:
                v.err(f"particles[{k}].temperature",
                      "missing: give a temperature for this group or thermal.initial_temperature")
            tg = np.full(n, T0)
        temps.append(np.asarray(tg, float))
    th["temperature"] = np.concatenate(temps) if temps else np.zeros(0)
    th["initial_temperature"] = T0
    for k, inlet in enumerate(getattr(sc, "inlets", [])):
        if inlet["temperature"] is None and T0 is None:
            v.err(f"inlets[{k}].temperature", "missing: give the inlet's particles a temperature or set "
                                              "thermal.initial_temperature")
    regs = t.get("initial_regions", [])
    if not isinstance(regs, list):
        v.err("thermal.initial_regions", "must be an array of tables {min, max, temperature}")
    for k, rg in enumerate(regs):
        p = f"thermal.initial_regions[{k}]"
        v.table(rg, p, {"min", "max", "temperature"}, required=("min", "max", "temperature"))
        a = v.vec(rg, "min", p, required=True)
        b = v.vec(rg, "max", p, required=True)
        tt = v.num(rg, "temperature", p, lo=0, lo_open=True, required=True)
        inside = np.all((sc.position >= a) & (sc.position <= b), axis=1)
        th["temperature"][inside] = tt
    # sources
    srcs = t.get("sources", [])
    if not isinstance(srcs, list):
        v.err("thermal.sources", "must be an array of tables [[thermal.sources]]")
    th["sources"] = []
    for k, s in enumerate(srcs):
        p = f"thermal.sources[{k}]"
        v.table(s, p, {"group", "power", "power_density", "region"})
        if ("power" in s) == ("power_density" in s):
            v.err(p, "give exactly one of power (W per particle, with group) or power_density (W/m3, with region)")
        if "power" in s:
            grp = v.integer(s, "group", p, required=True, lo=0)
            if grp >= len(sc.temperature):
                v.err(p + ".group", f"no particle group {grp} (groups 0..{len(sc.temperature) - 1})")
            th["sources"].append(dict(group=grp, power=v.num(s, "power", p)))
        else:
            reg = s.get("region")
            if reg is None:
                v.err(p + ".region", "missing required key (a box: {min = [..], max = [..]})")
            v.table(reg, p + ".region", {"min", "max", "type"})
            th["sources"].append(dict(power_density=v.num(s, "power_density", p),
                                      min=v.vec(reg, "min", p + ".region", required=True),
                                      max=v.vec(reg, "max", p + ".region", required=True)))
    # walls
    th["walls"] = []
    for k, w in enumerate(sc.walls):
        p = f"walls[{k}].thermal"
        spec = w.get("thermal") or {"condition": "adiabatic"}
        v.table(spec, p, {"condition", "temperature", "table", "heat_flux", "emissivity"}, required=("condition",))
        cond = v.string(spec, "condition", p, choices=list(WALL_CONDITIONS), required=True)
        W = dict(condition=cond, cond_id=WALL_CONDITIONS[cond], table=None, temperature=0.0, heat_flux=0.0,
                 emissivity=v.num(spec, "emissivity", p, default=0.0, lo=0.0, hi=1.0))
        if W["emissivity"] > 0.0 and cond != "fixed_temperature":
            v.err(p + ".emissivity", f"only a fixed_temperature wall radiates (the DEM knows no temperature of "
                                     f"a {cond} wall, which is taken as reradiating); remove the key")
        if W["emissivity"] > 0.0 and th["radiation_id"] < 0:
            v.err(p + ".emissivity", "needs a radiation model: [thermal] radiation = \"zhou_2009\" or "
                                     "\"krause_2017\"")
        if cond == "fixed_temperature":
            if ("temperature" in spec) == ("table" in spec):
                v.err(p, "fixed_temperature needs exactly one of temperature (K) or table ([[t, T], ...])")
            if "temperature" in spec:
                W["temperature"] = v.num(spec, "temperature", p, lo=0, lo_open=True)
            else:
                tab = spec["table"]
                ok = isinstance(tab, list) and len(tab) >= 1 and all(
                    isinstance(r, list) and len(r) == 2
                    and all(isinstance(e, (int, float)) and not isinstance(e, bool) for e in r) for r in tab)
                if not ok:
                    v.err(p + ".table", "must be a list of [time, temperature] pairs")
                tab = np.array(tab, float)
                for row, (tk, Tk) in enumerate(tab):
                    if not (math.isfinite(tk) and math.isfinite(Tk) and Tk > 0):
                        v.err(f"{p}.table[{row}]", f"[time, temperature] must be finite with temperature "
                                                   f"> 0 K, got [{tk}, {Tk}]")
                if np.any(np.diff(tab[:, 0]) <= 0):
                    k = int(np.argmax(np.diff(tab[:, 0]) <= 0)) + 1
                    v.err(f"{p}.table[{k}]", f"times must increase, got {tab[k, 0]} after {tab[k - 1, 0]}")
                W["table"] = tab
                W["temperature"] = float(tab[0, 1])
            conducts = th["direct_id"] >= 0 or th["indirect_id"] >= 0
            if not conducts and not (W["emissivity"] > 0.0 and th["radiation_id"] >= 0):
                v.err(p + ".condition", "fixed_temperature needs a direct or indirect conduction model, or an "
                                        "emissivity with a radiation model")
            m = sc.materials[w["material"]]
            if conducts and "thermal_conductivity" not in m:
                v.err(f"materials[{w['material']}].thermal_conductivity",
                      f"missing: wall {w['name']!r} conducts heat (fixed_temperature)")
        elif cond == "fixed_heat_flux":
            W["heat_flux"] = v.num(spec, "heat_flux", p, required=True)
        th["walls"].append(W)
    return th


# models whose coarse-grained form is not derived (docs/models.md, "Coarse graining"): refused
# with coarse_graining > 1, with the reason
CG_REFUSED = {}   # every model of the catalogue has its scaling


def _check_coarse_graining(v, sc, th):
    """Coarse-grained groups (issue 15): refuse what has no derived scaling, naming the model."""
    from ..parcels import parcel_factors
    cg = parcel_factors(sc)
    if cg is None:
        return
    gcg = getattr(sc, "group_cg", None)
    if gcg is not None:   # per group (every group holds particles): the same on every rank
        g = next(g for g, c in enumerate(gcg) if c != 1.0)
        cg_first, vals = gcg[g], np.unique(np.asarray(gcg, float))
    else:
        k = int(np.flatnonzero(cg != 1.0)[0])
        g, cg_first, vals = int(sc.group[k]), cg[k], np.unique(cg)
    where = f"particles[{g}].coarse_graining"
    for mech in ("direct", "indirect", "convection", "radiation", "friction_heat"):
        why = CG_REFUSED.get(th[mech])
        if why:
            v.err(where, f"{cg_first:g} with thermal.{mech} = \"{th[mech]}\": no coarse-grained form of this model "
                         f"({why}); use coarse_graining = 1 or another {mech} model")
    conducts = th["direct_id"] >= 0 or th["indirect_id"] >= 0
    if conducts and vals.size > 1:
        v.err(where, f"groups with different coarse-graining factors ({', '.join(f'{x:g}' for x in vals)}) "
                     f"in one scene with conduction: the scaling of a contact between parcels of different "
                     f"factors is not derived; give every group the same coarse_graining")
