"""The immersed-tube benchmark (benchmarks/immersed_tube.py, openfoam_cases/immersed_tube):
the correlations against hand-computed values, the analysis on a synthetic run folder with
known answers, and the case's mesh (location and void fraction on the O-grid)."""
import math
import re
import shutil
import sys
import tomllib
from pathlib import Path

import numpy as np
import pytest

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "benchmarks"))
import immersed_tube as IT  # noqa: E402

CASE = ROOT / "openfoam_cases" / "immersed_tube"
# the case's beads and gas: glass 2500 kg/m3, 840 J/(kg K); air 1.2 kg/m3, 1.8e-5 Pa s,
# 1005 J/(kg K), 0.0262 W/(m K); d_p 1 mm; U = 1.08 m/s; U_mf (Wen & Yu) 0.538042 m/s
AIR = dict(rho_p=2500.0, rho_g=1.2, cp_p=840.0, cp_g=1005.0, k_g=0.0262, mu_g=1.8e-5, d_p=1e-3)


# ----------------------------------------------------------------------------- correlations

def test_zabrodsky_hand_value():
    # 35.8 x 2500^0.2 x 0.0262^0.6 x (1e-3)^-0.36 = 35.8 x 4.78176 x 0.112456 x 12.0226
    # = 231.45 W/(m2 K)
    assert IT.zabrodsky_hmax(2500.0, 0.0262, 1e-3) == pytest.approx(231.45, rel=1e-4)
    # exponents: twice the diameter -> 2^-0.36 = 0.77916; twice k_g -> 2^0.6 = 1.51572
    h = IT.zabrodsky_hmax(2500.0, 0.0262, 1e-3)
    assert IT.zabrodsky_hmax(2500.0, 0.0262, 2e-3) / h == pytest.approx(0.779165, rel=1e-5)
    assert IT.zabrodsky_hmax(2500.0, 0.0524, 1e-3) / h == pytest.approx(1.515717, rel=1e-5)


def test_laminar_length_hand_value():
    # (1.8e-5 / (sqrt(9.81) x 2498.8))^(2/3) = (1.8e-5 / 7826.5)^(2/3) = (2.29988e-9)^(2/3)
    # = 1.74236e-6 m
    assert IT.laminar_length(1.8e-5, 2500.0, 1.2) == pytest.approx(1.74236e-6, rel=1e-5)


def test_molerus_hand_value_at_the_case():
    # l_l = 1.74236e-6 m, k_g / l_l = 15037.1 W/(m2 K); U - U_mf = 0.541958, r = 0.992774
    # X = (2500 x 840 / (0.0262 x 9.81))^(1/3) x 0.541958 = 201.411 x 0.541958 = 109.156
    # k_g / (2 cp_p mu) = 0.0262 / 0.03024 = 0.866402
    # damping 1 + 0.28 x 0.585^2 x (1.2/2498.8)^0.5 x X^2 x r
    #        = 1 + 0.28 x 0.342225 x 0.0219142 x 11915.1 x 0.992774 = 25.8395
    # Nu_pc = 0.125 x 0.585 / (1 + 33.3/(0.997586 x 109.156)) / (1 + 0.866402 x 25.8395)
    #       = 0.073125 x 0.765811 / 23.3873 = 0.00239445 -> h_pc = 36.01 W/(m2 K)
    # Nu_gc = 0.165 x 0.690458^(1/3) x (1.2/2498.8)^(1/3) / (1 + 0.05 r)
    #       = 0.165 x 0.883851 x 0.0783099 / 1.049639 = 0.0108803 -> h_gc = 163.61 W/(m2 K)
    m = IT.molerus_1995(**AIR, U=1.08, U_mf=0.538042, eps_mf=0.415)
    assert m["h_pc"] == pytest.approx(36.01, rel=1e-3)
    assert m["h_gc"] == pytest.approx(163.61, rel=1e-3)
    assert m["h"] == pytest.approx(36.01 + 163.61, rel=1e-3)
    # Ar = 1.2 x 2498.8 x 9.81 x 1e-9 / (1.8e-5)^2 = 9.0790e4
    assert m["Ar"] == pytest.approx(9.0790e4, rel=1e-4)


def test_molerus_limits():
    kw = dict(AIR, U_mf=0.538042, eps_mf=0.415)
    # far above U_mf the gas-convective part reaches 0.165 Pr^(1/3) (rho_g/(rho_p-rho_g))^(1/3)
    # k_g / l_l = 0.165 x 0.883851 x 0.0783099 x 15037.1 = 171.73 W/(m2 K) (1/(1 + 0.05 r), r = 1e-3)
    far = IT.molerus_1995(**kw, U=0.538042 * 1001)
    assert far["h_gc"] == pytest.approx(171.73, rel=1e-4)
    # towards U_mf the particle convection vanishes as (U - U_mf)^(2/3): the 33.3 term,
    # 33.3 / (r^(1/3) X) with r^(1/3) X = (rho_p cp_p / (k_g g))^(1/3) U_mf^(1/3) (U - U_mf)^(2/3),
    # dominates and the 0.28 term, proportional to X^2 r ~ (U - U_mf), goes to 0
    a = IT.molerus_1995(**kw, U=0.538042 * (1 + 1e-6))["h_pc"]
    b = IT.molerus_1995(**kw, U=0.538042 * (1 + 1e-9))["h_pc"]
    assert a / b == pytest.approx(1000 ** (2 / 3), rel=1e-2)
    with pytest.raises(ValueError, match="U > U_mf"):
        IT.molerus_1995(**kw, U=0.5)


def test_molerus_max_is_the_maximum():
    kw = dict(AIR, U_mf=0.538042, eps_mf=0.415)
    hmax, umax = IT.molerus_1995_max(**kw)
    grid = 0.538042 * (1.0 + np.linspace(1e-3, 19.0, 200001))
    brute = max(IT.molerus_1995(**kw, U=u)["h"] for u in grid[::50])
    assert hmax >= brute * (1 - 1e-9)
    k = np.searchsorted(grid, umax)
    local = [IT.molerus_1995(**kw, U=u)["h"] for u in grid[max(k - 20, 0):k + 20]]
    assert hmax == pytest.approx(max(local), rel=1e-8)
    assert 1.0 < umax / 0.538042 < 20.0


# ----------------------------------------------------------------------------- analysis

def _synthetic_run(tmp, gas="log", angles=False, log_from=0.0):
    """A run folder with known answers: the case's dem.toml and 0/U; tube heat rates constant
    (contact 0.2 W, gas gap 0.6 W; gas 0.1 W, from wall_heat.csv or the solver log), bed
    temperature 300 + 2 t K, dp = 440 + 100 sin(2 pi 5 t) Pa, 7.2 g of beads."""
    out = tmp / "run"
    (out / "0").mkdir(parents=True)
    shutil.copy(CASE / "dem.toml", out / "dem.toml")
    shutil.copy(CASE / "0" / "U", out / "0" / "U")
    t = [float(x) for x in np.round(np.arange(0, 1.3 + 1e-9, 0.008), 10)]
    area = 0.000125663706144
    rows = ["time,wall,mechanism,energy_J,heat_rate_W,heat_flux_W_m2,area_m2"]
    rates = dict(contact=0.2, gas_gap=0.6) | (dict(gas_convection=0.1) if gas == "csv" else {})
    for tk in t:
        for m, q in rates.items():
            rows.append(f"{tk!r},tube,{m},{q * tk!r},{q},{q / area},{area}")
        rows.append(f"{tk!r},tube,total,{0.8 * tk!r},0.8,{0.8 / area},{area}")
        rows.append(f"{tk!r},distributor,contact,0.0,0,0,0.00016")
    (out / "wall_heat.csv").write_text("\n".join(rows) + "\n")
    M, c = 7.2e-3, 840.0
    cols = ["time", "step", "T_particles", "T_gas", "E_particles", "dp", "bed_height"]
    lines = [",".join(cols)]
    for k, tk in enumerate(t):
        T = 300.0 + 2.0 * tk
        lines.append(",".join(map(repr, [tk, k, T, 300.0, M * c * T, 440.0 + 100.0 * math.sin(2 * math.pi * 5 * tk),
                                         0.02])))
    (out / "coupling.csv").write_text("\n".join(lines) + "\n")
    if gas == "log":
        steps = [float(x) for x in np.round(np.arange(0.00016, 1.3 + 1e-9, 0.00016), 10) if x > log_from]
        (out / "log.thermoDemFoam").write_text("".join(
            f"Time = {tk!r}  coupling step {k + 1}\nWall heat into the gas, patch xWalls: 0 W\n"
            f"Wall heat into the gas, patch tube: 0.1 W\n" for k, tk in enumerate(steps)))
    if angles:
        rows = ["time,wall,angle_deg,contact_W_m2,gas_gap_W_m2"]
        for tk in t:
            for a in (0.0, 90.0, 180.0, 270.0):
                rows.append(f"{tk!r},tube,{a},{100.0 + a},{1000.0 + a}")
        (out / "wall_heat_angle.csv").write_text("\n".join(rows) + "\n")
    return out, area


@pytest.mark.parametrize("gas", ["log", "csv", "none"])
def test_analysis_on_known_rates(tmp_path, gas):
    out, A = _synthetic_run(tmp_path, gas)
    r = IT.analyse(out, discard=0.3)
    # after 0.3 s: output intervals of 0.008 s, T_bed at each middle; h = Q / (A (340 - T_bed))
    t = np.round(np.arange(0, 1.3 + 1e-9, 0.008), 10)
    mids = t[:-1][t[:-1] >= 0.3] + 0.004
    dT = 340.0 - (300.0 + 2.0 * mids)
    assert r["mean"]["particles"] == pytest.approx(np.mean(0.8 / (A * dT)), rel=1e-9)
    assert r["mean"]["contact"] == pytest.approx(np.mean(0.2 / (A * dT)), rel=1e-9)
    assert r["mean"]["gas_gap"] == pytest.approx(np.mean(0.6 / (A * dT)), rel=1e-9)
    if gas == "none":
        assert "gas_convection" not in r["mean"] and r["gas_source"] is None
    else:
        assert r["gas_source"] == {"log": "solver log", "csv": "wall_heat.csv"}[gas]
        assert r["mean"]["gas_convection"] == pytest.approx(np.mean(0.1 / (A * dT)), rel=1e-9)
        assert r["mean"]["all"] == pytest.approx(np.mean(0.9 / (A * dT)), rel=1e-9)
    # bed weight from E_particles = M c T: 7.2e-3 x 9.81 / (0.04 x 0.004) = 441.45 Pa
    assert r["weight"] == pytest.approx(441.45, rel=1e-9)
    assert r["dp_mean"] == pytest.approx(440.0, abs=2.0)
    assert abs(r["bubble_hz"] - 5.0) <= 1.0 / 1.0     # one bin of the 1 s window
    # h rises slowly (T_bed rises): the running average settles within 5 % at once
    assert r["settled"][0.05] == pytest.approx(0.008)
    run = np.cumsum(1.0 / dT) / np.arange(1, len(dT) + 1)       # equal intervals
    last_out = np.flatnonzero(np.abs(run / run[-1] - 1.0) > 0.02)[-1]
    assert r["settled"][0.02] == pytest.approx(0.008 * (last_out + 2))
    assert r["T_bed_mean"] == pytest.approx(300.0 + 2.0 * mids.mean(), rel=1e-12)
    text = IT.report(r)
    assert "Zabrodsky" in text and "Molerus" in text


def test_gas_path_missing_in_part_of_the_window(tmp_path):
    """A solver log that starts late (e.g. replaced at a restart) shortens only the gas path's
    average; the particle paths keep the whole window."""
    out, A = _synthetic_run(tmp_path, log_from=0.8)
    r = IT.analyse(out, discard=0.3)
    t = np.round(np.arange(0, 1.3 + 1e-9, 0.008), 10)
    t0 = t[:-1]
    dT = 340.0 - (300.0 + 2.0 * (t0 + 0.004))
    assert r["mean"]["particles"] == pytest.approx(np.mean(0.8 / (A * dT[t0 >= 0.3])), rel=1e-9)
    late = t0 >= 0.8 - 1e-9                      # intervals (0.8, ...] hold log lines
    assert r["mean"]["gas_convection"] == pytest.approx(np.mean(0.1 / (A * dT[late])), rel=1e-9)
    assert r["covered"]["gas_convection"] == pytest.approx(0.008 * np.count_nonzero(late), rel=1e-9)
    assert "only" in IT.report(r)


def test_analysis_angles_and_plot(tmp_path):
    out, A = _synthetic_run(tmp_path, angles=True)
    r = IT.analyse(out, discard=0.3)
    T = 300.0 + 2.0 * np.arange(0.304, 1.3 + 1e-9, 0.008)
    want = np.mean(1100.0 / (340.0 - T))               # angle 0: 100 + 1000 W/m2
    got = r["angles"]["contact_W_m2"] + r["angles"]["gas_gap_W_m2"]
    assert got[0] == pytest.approx(want, rel=1e-9)
    assert list(r["angles"]["angle"]) == [0.0, 90.0, 180.0, 270.0]
    png = IT.plot(r, tmp_path / "fig.png")
    assert png.stat().st_size > 10_000
    IT.plot(r, png)                                     # our own figure is replaced
    user = tmp_path / "user.png"
    user.write_bytes(b"not ours")
    from dem.outdir import OutputFolderError
    with pytest.raises(OutputFolderError):              # a user's file is not
        IT.plot(r, user)
    assert user.read_bytes() == b"not ours"


def test_settled_window():
    tau = np.arange(1, 11) * 0.1
    run = np.array([2.0, 1.5, 1.2, 1.04, 0.97, 1.02, 1.0, 1.0, 1.0, 1.0])
    assert IT.settled_window(tau, run, tol=0.05) == pytest.approx(0.4)   # 1.04, then within 5 %
    assert IT.settled_window(tau, run, tol=0.01) == pytest.approx(0.7)


# ----------------------------------------------------------------------------- the case

def test_case_is_consistent():
    with open(CASE / "dem.toml", "rb") as fh:
        dem = tomllib.load(fh)
    tube = next(w for w in dem["walls"] if w.get("name") == "tube")
    p = IT.case_properties(CASE)
    # the gas patch and the DEM wall at one temperature; 2 U_mf at the inlet
    from coupling import foam_case as fc
    assert fc.parse_foam_dict(CASE / "0" / "T")["boundaryField"]["tube"]["value"] == "uniform 340"
    assert tube["thermal"]["temperature"] == 340.0
    assert p["U"] / p["U_mf"] == pytest.approx(2.0, rel=0.01)
    # the mesh's circle points and arc midpoints lie on the DEM cylinder (axis y, radius 5 mm)
    text = (CASE / "system" / "blockMeshDict").read_text()
    verts = np.array([[float(v) for v in m.split()] for m in
                      re.findall(r"\(\s*([-0-9.e]+ [-0-9.e]+ [-0-9.e]+)\s*\)\s*//", text)])
    arcs = np.array([[float(v) for v in m.split()] for m in re.findall(r"arc \d+ \d+ \(([^)]*)\)", text)])
    c = np.array(tube["point"])
    for pts in (verts[[16, 17, 18, 19, 36, 37, 38, 39]], arcs):
        rho = np.hypot(pts[:, 0] - c[0], pts[:, 2] - c[2])
        assert np.allclose(rho, tube["radius"], rtol=0, atol=1e-10)


def test_mesh_locates_particles_and_conserves_void_fraction(tmp_path):
    """blockMesh on the case: 640 hexahedra filling the column less the 32-gon of the tube;
    every point of the bed is located in the cell that contains it (walk and brute force
    agree), and the smoothed void fraction keeps the particle volume."""
    from coupling import foam_case as fc
    from coupling import voidfraction as VF
    from coupling.mesh import read_polymesh
    case = tmp_path / "case"
    shutil.copytree(CASE, case)
    fc.block_mesh(case)
    mesh = read_polymesh(str(case))
    assert mesh.n_cells == 640 and mesh.uniform_grid is None
    poly = 16 * 0.005 ** 2 * math.sin(2 * math.pi / 32)         # 32-gon of the tube, area
    assert mesh.cell_volumes.sum() == pytest.approx((0.04 * 0.1 - poly) * 0.004, rel=1e-12)
    rng = np.random.default_rng(1)
    pts = rng.uniform([0.0005, 0.0005, 0.0005], [0.0395, 0.0035, 0.06], (20000, 3))
    out_tube = np.hypot(pts[:, 0] - 0.02, pts[:, 2] - 0.02) > 0.0055
    pts = pts[out_tube]
    cells = mesh.locate(pts)
    brute, count = mesh.locate_brute_force(pts)
    assert np.all(cells >= 0) and np.array_equal(cells, brute) and np.all(count == 1)
    r = np.full(len(pts), 0.0005)
    eps, pw = VF.void_fraction(mesh, pts[:300], r[:300], "smoothed", return_weights=True, warn=False)
    solid = ((1.0 - eps) * mesh.cell_volumes).sum()
    assert solid == pytest.approx(300 * 4 / 3 * math.pi * 0.0005 ** 3, rel=1e-12)


def _cli(*args, cwd):
    import os
    import subprocess
    env = dict(os.environ, PYTHONPATH=str(ROOT) + os.pathsep + os.environ.get("PYTHONPATH", ""))
    return subprocess.run([sys.executable, "-m", *map(str, args)], cwd=cwd, env=env, capture_output=True,
                          text=True, timeout=900)


def test_case_checks_without_warning(tmp_path):
    """coupling check: no WARNING, no PROBLEM; the step and cell rules the README quotes."""
    r = _cli("coupling.run", "check", CASE, cwd=tmp_path)
    assert r.returncode == 0, r.stdout + r.stderr
    assert "WARNING" not in r.stdout and "PROBLEM" not in r.stdout, r.stdout
    assert "verdict: OK" in r.stdout
    v = {ln.split()[0]: float(ln.split()[1]) for ln in r.stdout.splitlines()
         if len(ln.split()) == 2 and re.fullmatch(r"[-+0-9.eE]+", ln.split()[1])}
    assert v["particles"] == 5500 and v["cells"] == 640
    assert v["dt_over_hertz"] < 0.1 and v["particle_courant"] < 0.1
    assert v["averaging_over_diameter"] >= 3.0


def test_short_coupled_run(tmp_path, solver):
    """20 coupling steps of the case through the command line: every particle located in the
    O-grid mesh at every output, the tube's rows in wall_heat.csv with its lateral area
    2 pi R L, and the gas heated by the 340 K tube patch at every CFD step; the tube is tied to
    its gas patch, so wall_heat.csv's gas path is the solver's (its log's per-step totals
    integrate to it), wall_heat_angle.csv has the 24 sectors at every output, and
    coupling.csv's energy balance closes to round-off."""
    out = tmp_path / "out"
    r = _cli("coupling.run", "run", CASE, "--out", out, "--end-time", "0.0032", cwd=tmp_path)
    assert r.returncode == 0, r.stdout[-3000:] + r.stderr[-3000:]
    cp = IT.read_csv(out / "coupling.csv")
    assert cp["time"][-1] == pytest.approx(0.0032) and np.all(cp["n_outside"] == 0)
    energy, area = IT.wall_energy(out / "wall_heat.csv", "tube")
    assert area == pytest.approx(2 * math.pi * 0.005 * 0.004, rel=1e-12)
    assert {"contact", "gas_gap", "gas_convection", "total"} <= set(energy)
    t, q = IT.gas_heat_from_log(out)
    assert len(t) == 20 and np.all(q > 0)
    # the log prints 6 significant digits; the CFD step is 1.6e-4 s
    assert energy["gas_convection"][1][-1] == pytest.approx(q.sum() * 1.6e-4, rel=1e-5)
    parts = sum(energy[m][1] for m in ("contact", "gas_gap", "gas_convection"))
    assert parts == pytest.approx(energy["total"][1], rel=1e-12, abs=1e-300)
    # round-off: of the energy sums (about 1e3 J here) and of the boundary integrals
    through = np.abs(cp["E_open"]) + np.abs(cp["E_walls_gas"]) + np.abs(cp["E_walls_particles"])
    scale = np.abs(cp["E_particles"]) + np.abs(cp["E_gas_solver"])
    assert np.all(np.abs(cp["balance_residual"]) <= 1e-14 * scale + 1e-9 * through)
    ang = IT.read_csv(out / "wall_heat_angle.csv")
    assert len(ang["time"]) == 24 * len(cp["time"])
    assert np.all(np.diff(np.unique(ang["angle_deg"])) == pytest.approx(15.0))
