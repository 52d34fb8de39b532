"""Model records (dem.thermal.records): the registry, table layouts, dispatchers, docs tables and
`dem check` lines derived from them, and the model added as the worked example
(Bahrami-Yovanovich-Culham rough-sphere conduction, dem/thermal/bahrami_2006.py)."""
import math
import os
import subprocess
import sys
import textwrap

import numpy as np
import pytest

from dem import Simulation
from dem.thermal import bahrami_2006 as byc
from dem.thermal import dispatch, docs, pair_conductance, registry, wall_conductance
from dem.thermal.records import GAS, MATERIAL, Input

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))

# the hand-written tables before the records (names -> ids): records must reproduce them
LEGACY = {
    "direct": {"batchelor_obrien": 0, "thermal_pipe": 1, "quintana_ruiz_campello_2020": 2, "rojek_2014": 3,
               "zhou_2008_collisional": 4, "beaulieu_2020": 5},
    "indirect": {"cheng_1999_voronoi_a": 0, "gan_2016_voronoi_a": 1, "cheng_1999_voronoi_b": 2,
                 "chen_2019_voronoi_b": 3, "rong_horio_1999_surrounding_layer": 4,
                 "musser_2011_surrounding_layer": 5, "vargas_mccarthy_2002": 6},
    "convection": {"ranz_marshall": 0, "whitaker": 1, "gunn": 2, "li_mason": 3},
    "radiation": {"zhou_2009": 0, "krause_2017": 1},
    "friction": {"nguyen_2009": 0, "rojek_2014": 1, "impact_heat": 2},
    "partition": {"varadi_1996": 0, "rojek_2014": 1, "equal": 2},
    "contact_radius": {"hertz_force": 0, "hertz_overlap": 1, "geometric": 2},
    "correction": {"none": 0, "zhou_2010": 1, "lu_2017": 2, "morris_2016_area": 3, "morris_2016_area_time": 4},
}
LEGACY_ALIASES = {"bob": ("direct", "batchelor_obrien"), "zhou_2008": ("direct", "zhou_2008_collisional"),
                  "beaulieu": ("direct", "beaulieu_2020"), "voronoi_a": ("indirect", "cheng_1999_voronoi_a"),
                  "surrounding_layer": ("indirect", "musser_2011_surrounding_layer"),
                  "gunn_1978": ("convection", "gunn"), "krause_2017_radiation": ("radiation", "krause_2017"),
                  "varadi_1996_partition": ("partition", "varadi_1996")}


def test_records_reproduce_the_legacy_ids_and_aliases():
    for mech, table in LEGACY.items():
        got = {n: r.id for n, r in registry.records(mech).items()}
        extra = {n: i for n, i in got.items() if n not in table}
        assert {n: got[n] for n in table} == table
        assert extra == ({"bahrami_2006_rough_sphere": 6} if mech == "direct" else {})
    for alias, (mech, name) in LEGACY_ALIASES.items():
        assert registry.canonical_name(mech, alias) == name
    with pytest.raises(ValueError, match="valid: bahrami_2006_rough_sphere, batchelor_obrien"):
        registry.model_id("direct", "nope")


def test_table_layout_keeps_the_kernel_column_constants():
    mk, gk = registry.MATERIAL_KEYS, registry.GAS_KEYS
    assert [mk[k] for k in ("thermal_conductivity", "heat_capacity", "density", "emissivity", "microhardness",
                            "roughness", "asperity_slope", "youngs_modulus", "poisson_ratio",
                            "real_youngs_modulus", "accommodation_coefficient")] == list(range(11))
    assert (gk["conductivity"][0], gk["prandtl"][0], gk["cutoff"][0], gk["radiation_range"][0],
            gk["quadrature_tolerance"][0]) == (registry.KF, registry.PR, registry.CUTOFF, registry.RAD_RANGE,
                                               registry.QUAD_TOL)
    assert registry.N_TPROP == 11 and registry.N_GAS == 21
    # defaults as before: porosity 0.4, real modulus 0 = not given, accommodation from the gas
    tmat, garr, _ = registry.build_tables([{"thermal_conductivity": 1.0}], {})
    assert garr[registry.POROSITY_GLOBAL] == 0.4 and tmat[0, registry.REAL_YOUNG] == 0.0
    assert tmat[0, registry.ACCOM] == 0.9 and math.isnan(garr[registry.KF])


def test_history_width_and_reach_from_the_records():
    assert registry.history_width({"direct": "zhou_2008_collisional", "indirect": "none"}) == 2
    assert registry.history_width({"direct": "byc", "indirect": "voronoi_a"}) == 0
    g = registry.build_gas_table({"cutoff": 0.5, "radiation_range": 4.0})
    # same arithmetic as ThermalModel.__init__: cutoff * rmax, (radiation_range - 2) * rmax
    assert registry.neighbour_reach({"indirect": "voronoi_b"}, g, 2e-3) == 0.5 * 2e-3
    assert registry.neighbour_reach({"indirect": "voronoi_b", "radiation": "krause_2017"}, g, 2e-3) == 2.0 * 2e-3
    assert registry.neighbour_reach({"direct": "batchelor_obrien"}, g, 2e-3) == 0.0


SYNTHETIC = '''
import numba
from dem.thermal.records import GAS, MATERIAL, Input, ModelRecord


@numba.njit(cache=False)
def _pp(Ri, Rj, d, rc, mi, mj, tmat, gas, t_contact, vn_impact, col_mat, col_gas):
    return tmat[mi, col_mat] * gas[col_gas] * rc


@numba.njit(cache=False)
def _pw(R, d, rc, mp, mw, tmat, gas, t_contact, vn_impact, col_mat, col_gas):
    return -tmat[mp, col_mat] * gas[col_gas]


RECORDS = (ModelRecord("synthetic_test_model", "direct", 99, material=("thermal_conductivity",),
                       new_inputs=(Input("test_coating_thickness", MATERIAL, "m", None, (0.0, 1.0), "coating"),
                                   Input("test_gas_factor", GAS, "-", 2.5, (0.0, 10.0), "factor")),
                       laws=dict(pp=_pp, pw=_pw)),)
'''


def test_a_new_input_is_appended_and_reaches_the_law(tmp_path, monkeypatch):
    """A model declaring new material and gas inputs in its record only: the columns are appended
    (existing indices unchanged) and the generated dispatcher passes their indices to the law."""
    (tmp_path / "synthetic_model_records.py").write_text(SYNTHETIC)
    monkeypatch.syspath_prepend(str(tmp_path))
    d = registry._collect(registry.MODEL_MODULES + ("synthetic_model_records",))
    assert d["material_keys"]["test_coating_thickness"] == 11 and d["gas_keys"]["test_gas_factor"] == 21
    assert all(d["material_keys"][k] == i for k, i in registry.MATERIAL_KEYS.items())
    src = dispatch.source(d)
    assert "return _direct_pp_99(Ri, Rj, d, rc, mi, mj, tmat, gas, t_contact, vn_impact, 11, 21)" in src
    mod = dispatch.load(dispatch.write(src, folder=str(tmp_path)))
    tmat = np.full((2, 12), 1.0)
    tmat[0, 11] = 3.0
    gas = registry.build_gas_table({})
    gas = np.append(gas, 2.5)
    assert mod.direct_pp(99, 1e-3, 1e-3, 2e-3, 0.5, 0, 1, tmat, gas, 0.0, 0.0) == 3.0 * 2.5 * 0.5
    assert mod.direct_pw(99, 1e-3, 0.9e-3, 0.5, 0, 1, tmat, gas, 0.0, 0.0) == -7.5
    assert mod.direct_pp(0, 1e-3, 1e-3, 2e-3, 0.5, 0, 1, tmat, gas, 0.0, 0.0) == 4.0 * 0.5 * 0.5  # B&O kept


def test_generated_dispatchers_load_from_the_cache_in_a_second_process():
    pair_conductance("batchelor_obrien", Ri=1e-3, Rj=1e-3, d=1.99e-3, ki=1.0, kj=2.0)  # compiled here
    code = textwrap.dedent("""
        from dem.thermal import pair_conductance
        from dem.thermal.direct import direct_pp
        pair_conductance("batchelor_obrien", Ri=1e-3, Rj=1e-3, d=1.99e-3, ki=1.0, kj=2.0)
        print(sum(direct_pp.stats.cache_hits.values()), sum(direct_pp.stats.cache_misses.values()))
    """)
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True,
                         env=dict(os.environ, PYTHONPATH=ROOT), cwd=ROOT).stdout.split()
    assert out == ["1", "0"]


def test_docs_tables_are_the_generated_ones():
    with open(docs.DOC, encoding="utf-8") as fh:
        text = fh.read()
    assert docs.render(text) == text, "run python -m dem.thermal.docs"
    assert "| 6 | `bahrami_2006_rough_sphere` |" in text


# ---------------------------------------------------------------- Bahrami-Yovanovich-Culham
def _byc_reference(rc, Rs, Es, k, sigma, m, Hmic):
    # independent plain-Python evaluation of the published relations (bahrami_2006.py docstring)
    ks = k  # equal conductivities: harmonic mean = k
    alpha = sigma * Rs / rc ** 2
    tau = Rs / rc
    p = 1.0 / (1.0 + 1.37 * alpha * tau ** -0.075)
    aL = rc * (1.605 / math.sqrt(p) if p <= 0.47 else 3.51 - 2.51 * p)
    F = 4.0 * Es * rc ** 3 / (3.0 * Rs)
    return 1.0 / (1.0 / (2 * ks * aL) + 0.565 * Hmic * (sigma / m) / (ks * F))


def test_byc_hand_computed_value():
    """rc = 0.1 mm, R* = 2.5 mm, E* = 100 GPa, k = 16 W/(m K), sigma = 2 um, m = 0.1, H_mic = 4 GPa:
    alpha = 0.5, tau = 25, P0' = 1/(1 + 1.37 * 0.5 * 25^-0.075) = 0.65016, a_L = rc (3.51 - 2.51 P0')
    = 0.18781 mm, R_L = 1/(2 * 16 * a_L) = 166.39 K/W, F = 53.333 N,
    R_s = 0.565 * 4e9 * 2e-5/(16 * 53.333) = 52.969 K/W, H = 1/219.36 = 4.5587e-3 W/K
    (hand arithmetic to 5 digits: rel 1e-4)."""
    H = byc.bahrami_2006_rough_sphere(1e-4, 2.5e-3, 1e11, 16.0, 16.0, 2e-6, 0.1, 4e9)
    assert H == pytest.approx(4.5587e-3, rel=1e-4)
    assert byc.bahrami_2005_relative_pressure(1e-4, 2.5e-3, 2e-6) == pytest.approx(0.65016, rel=1e-4)
    assert H == pytest.approx(_byc_reference(1e-4, 2.5e-3, 1e11, 16.0, 2e-6, 0.1, 4e9), rel=1e-14)
    # first branch (very rough): P0' <= 0.47
    assert byc.bahrami_2006_rough_sphere(1e-4, 2.5e-3, 1e11, 16.0, 16.0, 2e-5, 0.1, 4e9) == \
        pytest.approx(_byc_reference(1e-4, 2.5e-3, 1e11, 16.0, 2e-5, 0.1, 4e9), rel=1e-14)
    assert byc.bahrami_2005_relative_pressure(1e-4, 2.5e-3, 2e-5) < 0.47


def test_byc_smooth_limit_is_batchelor_obrien():
    """sigma = 0: a_L = a_H, R_s = 0, H = 2 k_s r_c = 4 k_bar r_c (to round-off)."""
    common = dict(Ri=1e-3, Rj=2e-3, d=2.99e-3, rc=5e-5, ki=1.5, kj=40.0)
    rough = dict(hardness_i=3e9, hardness_j=5e9, roughness_i=0.0, roughness_j=0.0, slope_i=0.1, slope_j=0.1,
                 E_i=7e10, E_j=2e11, nu_i=0.25, nu_j=0.3)
    assert pair_conductance("byc", **common, **rough) == pytest.approx(
        pair_conductance("batchelor_obrien", **common), rel=1e-15)
    assert wall_conductance("byc", R=1e-3, d=0.99e-3, rc=5e-5, kp=1.5, hardness_p=3e9, hardness_w=3e9,
                            roughness_p=0.0, roughness_w=0.0, slope_p=0.1, slope_w=0.1, E_p=7e10, E_w=2e11,
                            nu_p=0.25, nu_w=0.3) == pytest.approx(4 * 1.5 * 5e-5, rel=1e-15)
    # a small roughness tends continuously to the smooth value
    Hs = byc.bahrami_2006_rough_sphere(5e-5, 1e-3, 1e11, 10.0, 10.0, 0.0, 0.1, 3e9)
    Hr = byc.bahrami_2006_rough_sphere(5e-5, 1e-3, 1e11, 10.0, 10.0, 1e-12, 0.1, 3e9)
    assert Hr == pytest.approx(Hs, rel=1e-5)


def test_byc_monotonic_in_load_and_its_roughness_optimum():
    """More load (larger Hertz radius) always conducts more. Roughness acts twice: it widens the
    macrocontact (a_L/a_H - 1 ~ 3.4 alpha at small alpha, R_L down) and adds the microcontact
    resistance R_s ~ sigma. Near smooth the first wins, for rough surfaces the second: H rises
    from the smooth (Batchelor & O'Brien) value, peaks, then falls - the joint resistance has a
    minimum at an intermediate roughness."""
    Rs, Es, k, m, Hm = 2.5e-3, 1e11, 16.0, 0.1, 4e9
    for sigma in (0.0, 1e-7, 1e-6, 5e-6):
        rcs = np.geomspace(2e-5, 3e-4, 60)
        H = [byc.bahrami_2006_rough_sphere(rc, Rs, Es, k, k, sigma, m, Hm) for rc in rcs]
        assert np.all(np.diff(H) > 0)
    sig = np.geomspace(1e-9, 2e-5, 200)
    H = np.array([byc.bahrami_2006_rough_sphere(1e-4, Rs, Es, k, k, s, m, Hm) for s in sig])
    top = int(np.argmax(H))
    assert 0 < top < len(sig) - 1
    assert np.all(np.diff(H[:top + 1]) > 0) and np.all(np.diff(H[top:]) < 0)
    assert H[0] == pytest.approx(2 * k * 1e-4, rel=1e-3) and H[-1] < 2 * k * 1e-4
    # the macrocontact grows with roughness, from a_H (P0' = 1)
    aL = [byc.bahrami_2005_macrocontact_radius(1e-4, Rs, s) for s in sig]
    assert aL[0] == pytest.approx(1e-4, rel=1e-3) and np.all(np.diff(aL) > 0)


def test_byc_in_a_heat_scene_and_dem_check():
    mat = dict(name="p", density=7800.0, youngs_modulus=2e9, poisson_ratio=0.3, restitution=0.5, friction=0.3,
               thermal_conductivity=16.0, heat_capacity=500.0, microhardness=4e9, roughness=1e-6,
               asperity_slope=0.1)
    R = 1e-3
    sc = {"simulation": {"time_step": 1e-5, "end_time": 2.0, "mechanics": False, "output_interval": 2.0,
                         "gravity": [0.0, 0.0, 0.0]},
          "domain": {"min": [-0.01] * 3, "max": [0.01] * 3}, "materials": [mat],
          "particles": [{"material": "p", "positions": [[0, 0, 0]], "radius": R, "temperature": 400.0},
                        {"material": "p", "positions": [[2 * R - 2e-6, 0, 0]], "radius": R,
                         "temperature": 300.0}],
          "thermal": {"direct": "byc", "time_step": 0.1}, "walls": []}
    sim = Simulation.from_dict(sc)
    runs = "\n".join(sim.check()["runs"])
    assert "direct conduction: bahrami_2006_rough_sphere (contact radius hertz_overlap" in runs
    H = sim.state.Hd[sim.state.Hd > 0]
    assert H.size == 1
    rc = math.sqrt(0.5 * R * 2e-6)
    Es = 1.0 / (2 * (1 - 0.3 ** 2) / 2e9)
    assert H[0] == pytest.approx(_byc_reference(rc, 0.5 * R, Es, 16.0, math.sqrt(2) * 1e-6,
                                                math.sqrt(2) * 0.1, 4e9), rel=1e-13)
    C = 1.0 / sim.state.inv_heat_capacity
    sim.run(progress=False)
    T = sim.state.temperature
    assert (T[0] - T[1]) / 100.0 == pytest.approx(math.exp(-H[0] * (2 / C[0]) * sim.time), rel=1e-4)
    assert np.sum(C * T) == pytest.approx(C[0] * 400 + C[1] * 300, rel=1e-13)


def test_byc_missing_material_key_is_named():
    mat = dict(name="p", density=7800.0, youngs_modulus=2e9, poisson_ratio=0.3, restitution=0.5, friction=0.3,
               thermal_conductivity=16.0, heat_capacity=500.0, microhardness=4e9, asperity_slope=0.1)
    sc = {"simulation": {"time_step": 1e-5, "end_time": 1.0, "mechanics": False, "output_interval": 1.0},
          "domain": {"min": [-0.01] * 3, "max": [0.01] * 3}, "materials": [mat],
          "particles": [{"material": "p", "positions": [[0, 0, 0]], "radius": 1e-3}],
          "thermal": {"direct": "bahrami_2006"}, "walls": []}
    from dem.scene import SceneError
    with pytest.raises(SceneError, match=r"materials\[0\]\.roughness.*bahrami_2006_rough_sphere"):
        Simulation.from_dict(sc)


def test_inputs_declared_once():
    """Each input key is declared once per table, with a unit, bounds and a description."""
    d = registry.derived()
    for inputs, table in ((d["material_inputs"], MATERIAL), (d["gas_inputs"], GAS)):
        keys = [i.key for i in inputs]
        assert len(keys) == len(set(keys))
        assert all(isinstance(i, Input) and i.table == table and i.unit and i.description for i in inputs)
