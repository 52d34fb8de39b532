"""`coupling check` / `coupling run` tell the truth (issue 13, item 5), through the command line
on copies of the shipped cases:

* the Biot number comes from the case's convection correlation at the gas speed of 0/U
  (Bi = h (V/A) / k_p = Nu k_f / (6 k_p)), with a warning above 0.1;
* the particle Courant rule is silent for a bed at rest and, for a bed the gas lifts,
  warns with the deltaT / coupling_interval that passes;
* one end time per case: a dem.toml or coupling.toml end_time that disagrees with
  system/controlDict is refused before anything is written; an omitted one is controlDict's;
* the main case (fluidized_bed_heating) checks without a warning.

Expected values are computed here from the published correlations, independently of the code.
"""
from __future__ import annotations

import math
import os
import re
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

ROOT = Path(__file__).resolve().parents[1]
CASES = ROOT / "openfoam_cases"
ENV = dict(os.environ, PYTHONPATH=str(ROOT) + os.pathsep + os.environ.get("PYTHONPATH", ""))
RHO, MU, CP, KF = 1.2, 1.8e-5, 1005.0, 0.0262
PR = MU * CP / KF
G = 9.81


def cli(*args, cwd):
    return subprocess.run([sys.executable, "-m", *map(str, args)], cwd=cwd, env=ENV, capture_output=True,
                          text=True, timeout=600)


def copy_case(name: str, dest: Path) -> Path:
    shutil.copytree(CASES / name, dest, ignore=shutil.ignore_patterns("README.md"))
    return dest


def edit(path: Path, old: str, new: str) -> None:
    text = path.read_text()
    assert old in text, (path, old)
    path.write_text(text.replace(old, new))


def values(report: str) -> dict:
    """The '  name   number' lines of a `coupling check` report."""
    out = {}
    for m in re.finditer(r"^  ([a-z_]+)\s+(-?[0-9.]+(?:e[-+]?[0-9]+)?)$", report, re.M):
        out[m.group(1)] = float(m.group(2))
    return out


def warnings(report: str) -> list[str]:
    return [ln for ln in report.splitlines() if "WARNING" in ln]


def ranz_marshall(re_):
    return 2 + 0.6 * math.sqrt(re_) * PR ** (1 / 3)


def gunn(re_, e):
    p3 = PR ** (1 / 3)
    return (7 - 10 * e + 5 * e * e) * (1 + 0.7 * re_ ** 0.2 * p3) + (1.33 - 2.4 * e + 1.2 * e * e) * re_ ** 0.7 * p3


def wen_yu_umf(d, rho_p):
    ar = RHO * (rho_p - RHO) * G * d ** 3 / MU ** 2
    return (math.sqrt(33.7 ** 2 + 0.0408 * ar) - 33.7) * MU / (RHO * d)


# --------------------------------------------------------------------------- main case

def test_main_case_checks_without_warning(tmp_path):
    """fluidized_bed_heating: no WARNING line. Its 6 mm cells are 2.86 of the largest
    diameter, but the 'smoothed' kernel averages the void fraction over more than 3; the Biot
    number is Ranz-Marshall's at the 2 m/s inlet speed; the gas lifts the bed (2 m/s > U_mf)."""
    r = cli("coupling.run", "check", CASES / "fluidized_bed_heating", cwd=tmp_path)
    assert r.returncode == 0, r.stdout + r.stderr
    assert warnings(r.stdout) == [], r.stdout
    assert "verdict: OK" in r.stdout
    v = values(r.stdout)
    assert v["cell_over_diameter"] < 3 <= v["averaging_over_diameter"]
    # Biot at the largest-Biot particle: Re = rho u_s d / mu, Nu = Ranz-Marshall, Bi = Nu k_f / (6 k_p)
    assert v["biot_gas_speed"] == pytest.approx(2.0)
    d = v["biot_reynolds"] * MU / (RHO * 2.0)
    assert 1.9e-3 * (1 - 1e-3) <= d <= 2.1e-3 * (1 + 1e-3)
    assert v["biot_nusselt"] == pytest.approx(ranz_marshall(v["biot_reynolds"]), rel=1e-3)
    assert v["biot_h"] == pytest.approx(v["biot_nusselt"] * KF / d, rel=1e-3)
    assert v["biot"] == pytest.approx(v["biot_nusselt"] * KF / (6 * 1.0), rel=1e-3)
    assert v["biot"] < 0.1
    # U_mf of the smallest bead (lifted first; U_mf grows with d), 1.9..2.1 mm glass
    assert wen_yu_umf(1.9e-3, 2500.0) * (1 - 1e-3) <= v["u_mf"] <= wen_yu_umf(2.1e-3, 2500.0)
    assert v["gas_excess_speed"] == pytest.approx(2.0 - v["u_mf"], abs=1e-3)
    assert v["particle_courant"] <= 0.1


# --------------------------------------------------------------------------- Biot

def test_biot_from_the_case_nusselt_warns_above_0_1(tmp_path):
    """single_particle_heating: d = 3.6 mm, k_p = 0.84 W/(m K) in 6 m/s air. Ranz-Marshall at
    Re = 1440 gives Nu = 22.1 and Bi = h (V/A) / k_p = 0.115 > 0.1 (the stagnant Nu = 2 gave
    0.010): warned, with the length used. With k_p = 2 W/(m K), Bi = 0.048: no warning."""
    case = copy_case("single_particle_heating", tmp_path / "case")
    r = cli("coupling.run", "check", case, cwd=tmp_path)
    assert r.returncode == 0, r.stdout + r.stderr
    v = values(r.stdout)
    re_ = RHO * 6.0 * 3.6e-3 / MU
    nu = ranz_marshall(re_)
    assert v["biot_reynolds"] == pytest.approx(re_, rel=1e-3)
    assert v["biot_nusselt"] == pytest.approx(nu, rel=1e-3)
    assert v["biot_h"] == pytest.approx(nu * KF / 3.6e-3, rel=1e-3)
    bi = nu * KF / 3.6e-3 * 1.8e-3 / (3 * 0.84)
    assert v["biot"] == pytest.approx(bi, rel=1e-3) and bi > 0.1
    w = [x for x in warnings(r.stdout) if "Biot number" in x]
    assert len(w) == 1, r.stdout
    assert "h (V/A) / k_p = h R / (3 k_p)" in w[0] and f"{bi:.3g} > 0.1" in w[0]
    assert "temperature gradients inside" in w[0]
    # a more conductive sphere: below the limit, no warning
    edit(case / "dem.toml", "thermal_conductivity = 0.84", "thermal_conductivity = 2.0")
    r = cli("coupling.run", "check", case, cwd=tmp_path)
    assert r.returncode == 0, r.stdout + r.stderr
    assert values(r.stdout)["biot"] == pytest.approx(bi * 0.84 / 2.0, rel=1e-3)
    assert not [x for x in warnings(r.stdout) if "Biot" in x], r.stdout


def test_biot_uses_the_void_fraction_of_the_bed(tmp_path):
    """packed_bed_heating with Gunn's correlation (porosity-dependent): Nu at the bed's initial
    void fraction 1 - pi/6 and Re = rho u_s d / mu at the 0.5 m/s inlet speed."""
    case = copy_case("packed_bed_heating", tmp_path / "case")
    edit(case / "dem.toml", 'convection = "ranz_marshall"', 'convection = "gunn"')
    r = cli("coupling.run", "check", case, cwd=tmp_path)
    assert r.returncode == 0, r.stdout + r.stderr
    v = values(r.stdout)
    re_ = RHO * 0.5 * 4e-3 / MU
    nu = gunn(re_, 1 - math.pi / 6)
    assert v["biot_reynolds"] == pytest.approx(re_, rel=1e-3)
    assert v["biot_nusselt"] == pytest.approx(nu, rel=1e-3)
    assert v["biot"] == pytest.approx(nu * KF / (6 * 1.0), rel=1e-3)


# --------------------------------------------------------------------------- particle Courant

def _moving_lattice(dest: Path, u: float, interval: int) -> Path:
    """The ergun lattice bed (simple cubic, touching spheres, 6 mm cells) with mechanics on
    (DEM step 1e-5 s), inlet speed u and deltaT = interval x 1e-5 s."""
    case = copy_case("ergun", dest)
    edit(case / "dem.toml", "time_step = 1e-4", "time_step = 1e-5")
    edit(case / "dem.toml", "mechanics = false", "mechanics = true")
    edit(case / "coupling.toml", "coupling_interval = 1", f"coupling_interval = {interval}")
    edit(case / "system" / "controlDict", "deltaT          0.0001;", f"deltaT          {interval * 1e-5:.6g};")
    f = case / "0" / "U"
    f.write_text(f.read_text().replace("uniform (0 0 0.5)", f"uniform (0 0 {u})"))
    return case


def test_courant_rule_silent_at_rest_warns_with_the_fix_when_lifted(tmp_path):
    """A bed at rest (touching lattice, particles still, gas 0.5 m/s below U_mf = 1.06 m/s)
    has nothing that moves it: Courant 0 even with a 2 ms coupling step (the former rule took
    the inlet speed and warned at 0.17). At 2.5 m/s the gas lifts it: the characteristic speed
    is U - U_mf, and the warning gives the deltaT and coupling_interval that pass."""
    umf = wen_yu_umf(2e-3, 2500.0)
    rest = _moving_lattice(tmp_path / "rest", 0.5, 200)
    r = cli("coupling.run", "check", rest, cwd=tmp_path)
    assert r.returncode == 0, r.stdout + r.stderr
    v = values(r.stdout)
    assert v["coordination_number"] >= 3
    assert v["particle_settling_speed"] == 0.0 and v["gas_excess_speed"] == 0.0
    assert v["u_mf"] == pytest.approx(umf, rel=1e-3)
    assert v["particle_courant"] == 0.0
    assert not [x for x in warnings(r.stdout) if "Courant" in x], r.stdout

    lifted = _moving_lattice(tmp_path / "lifted", 2.5, 60)
    r = cli("coupling.run", "check", lifted, cwd=tmp_path)
    assert r.returncode == 0, r.stdout + r.stderr
    v = values(r.stdout)
    co = (2.5 - umf) * 60e-5 / 6e-3
    assert v["gas_excess_speed"] == pytest.approx(2.5 - umf, rel=1e-3)
    assert v["particle_courant"] == pytest.approx(co, rel=1e-3) and 0.1 < co < 0.5
    w = [x for x in warnings(r.stdout) if "particle Courant number" in x]
    assert len(w) == 1, r.stdout
    k = math.floor(0.1 * 6e-3 / ((2.5 - umf) * 1e-5))
    assert f"coupling_interval = {k} in coupling.toml" in w[0] and f"deltaT = {k * 1e-5:.6g} s" in w[0], w[0]
    assert "U - U_mf" in w[0]
    # the advised setting passes
    edit(lifted / "coupling.toml", "coupling_interval = 60", f"coupling_interval = {k}")
    edit(lifted / "system" / "controlDict", f"deltaT          {60e-5:.6g};", f"deltaT          {k * 1e-5:.6g};")
    r = cli("coupling.run", "check", lifted, cwd=tmp_path)
    assert r.returncode == 0, r.stdout + r.stderr
    assert values(r.stdout)["particle_courant"] <= 0.1
    assert not [x for x in warnings(r.stdout) if "Courant" in x], r.stdout


# --------------------------------------------------------------------------- one end time

@pytest.mark.parametrize("where", ["coupling.toml", "dem.toml"])
def test_end_time_conflict_refused_before_writing(tmp_path, where):
    """A second end time that disagrees with system/controlDict (2 s) is refused by check and
    run, naming both files and both values; the output folder is never created."""
    case = copy_case("single_particle_heating", tmp_path / "case")
    if where == "coupling.toml":
        edit(case / "coupling.toml", "[coupling]\n", "[coupling]\nend_time = 0.5\n")
    else:
        edit(case / "dem.toml", "[simulation]\n", "[simulation]\nend_time = 1.0\n")
    wrong = "0.5" if where == "coupling.toml" else "1"
    for cmd in (["check", case], ["run", case, "--out", tmp_path / "out"]):
        r = cli("coupling.run", *cmd, cwd=tmp_path)
        assert r.returncode == 2, (r.stdout, r.stderr)
        assert "Traceback" not in r.stderr
        err = r.stderr
        assert f"{case / where}: " in err and str(case / "system" / "controlDict") in err, err
        assert f"end_time = {wrong} s disagrees with endTime = 2 s" in err, err
        assert "--end-time" in err and f"Remove end_time from {where}" in err, err
        assert not (tmp_path / "out").exists()
    # the same value is accepted
    edit(case / where, f"end_time = {'0.5' if where == 'coupling.toml' else '1.0'}\n", "end_time = 2.0\n")
    r = cli("coupling.run", "check", case, cwd=tmp_path)
    assert r.returncode == 0, r.stdout + r.stderr


def test_omitted_end_time_is_controldict_s(tmp_path):
    """The shipped dem.toml has no end_time: a coupled run goes to controlDict's endTime; the
    same scene alone (`dem run`) keeps its error for the missing key."""
    case = copy_case("single_particle_heating", tmp_path / "case")
    assert "end_time =" not in (case / "dem.toml").read_text()
    assert "end_time" not in (case / "coupling.toml").read_text()
    edit(case / "system" / "controlDict", "endTime         2;", "endTime         0.01;")
    r = cli("coupling.run", "run", case, "--out", tmp_path / "out", "--quiet", cwd=tmp_path)
    assert r.returncode == 0, r.stdout[-2000:] + r.stderr[-2000:]
    d = np.atleast_1d(np.genfromtxt(tmp_path / "out" / "coupling.csv", delimiter=",", names=True))
    assert d["time"][-1] == pytest.approx(0.01, rel=1e-9)
    r = cli("dem.cli", "run", case / "dem.toml", "--out", tmp_path / "alone", "--quiet", cwd=tmp_path)
    assert r.returncode == 2, (r.stdout, r.stderr)
    assert "simulation.end_time: missing required key" in r.stderr, r.stderr
    assert not (tmp_path / "alone").exists()
