"""The implicit heat integrators (backward Euler, TR-BDF2) of a frozen packing under MPI
(dem.thermal.implicit_mpi): the conjugate gradients over the ranks, with the ghosts' entries of
the search direction sent before each product and the dot products summed over the ranks, so
that a frozen bed's result does not depend on the rank count, and ``auto`` is the same
integrator on 1 and N ranks. Every run goes through `mpirun ... python -m dem run`.
"""
import csv
import shutil
import subprocess
import sys

import numpy as np
import pytest

from dem.final import read as read_final
from test_parallel import mpirun
from test_scene_errors import to_toml
from test_thermal_implicit import ENV, bed_scene, line_scene

pytestmark = pytest.mark.skipif(shutil.which("mpirun") is None, reason="needs Open MPI (mpirun)")

NET_LIMIT = 18.2   # s: the line of ten's network limit min C_i / sum H_ij (test_thermal_implicit)


def _write(path, sc, slabs=True):
    if slabs:   # cut along the line / across the bed, so that pairs cross every cut
        sc["parallel"] = {"decomposition": "slabs", "slab_axis": "x"}
    path.write_text(to_toml(sc))
    return path


def _serial(scene, out, *extra):
    p = subprocess.run([sys.executable, "-m", "dem", "run", str(scene), "--out", str(out), "--quiet", *extra],
                       capture_output=True, text=True, env=ENV, timeout=600)
    assert p.returncode == 0, p.stderr
    return p


def _by_id(out):
    f = read_final(out / "final.npz")
    o = np.argsort(f["id"])
    return {k: np.asarray(v)[o] for k, v in f.items() if np.ndim(v) >= 1 and len(v) == len(o)}


def _last(out):
    with open(out / "history.csv") as fh:
        rows = list(csv.DictReader(fh))
    return {k: float(v) for k, v in rows[-1].items()}, {k: float(v) for k, v in rows[0].items()}


@pytest.mark.parametrize("ranks", [2, 3])
@pytest.mark.parametrize("integrator", ["auto", "implicit", "trbdf2"])
def test_line_of_ten_at_100_network_limits_exact_on_any_rank_count(tmp_path, ranks, integrator):
    """The line of ten between walls at 400 and 300 K, cut into 2 and 3 slabs (pairs across every
    cut), at dt = 100 network limits (auto: backward Euler there, as on one process): the steady
    state is the network's own, linear inside and symmetric about 350 K to 1e-8 K, the same as one
    process's to 1e-8 K, and the heat balance closes. (The exponential update, which auto ran
    under MPI before, is 9.9 K off there.)"""
    dt = 100 * NET_LIMIT
    sc = line_scene(dt, integrator, 60 * dt)
    sc["simulation"]["output_interval"] = 30 * dt
    scene = _write(tmp_path / "line.toml", sc)
    if integrator == "auto":   # `dem check` states what auto chose, as on one process
        c = mpirun(ranks, "check", str(scene), cwd=tmp_path)
        assert "thermal integrator: implicit (auto: dt = 99.9 x the network limit" in c.stdout, c.stdout
        assert "steady state exact" in c.stdout and "NOT exact" not in c.stdout + c.stderr
    p = mpirun(ranks, "run", str(scene), "--out", str(tmp_path / "p"), cwd=tmp_path)
    assert f"on {ranks} ranks" in p.stdout + p.stderr
    f = _by_id(tmp_path / "p")
    T = f["temperature"][np.argsort(f["position"][:, 0])]
    steps = np.diff(T)
    assert np.abs(steps - steps.mean()).max() < 1e-8
    assert abs(T[0] + T[-1] - 700.0) < 1e-8
    assert 300.0 < T[-1] < T[0] < 400.0 and T[0] - T[-1] > 80.0
    _serial(scene, tmp_path / "s")
    assert np.abs(_by_id(tmp_path / "s")["temperature"] - f["temperature"]).max() < 1e-8
    last, first = _last(tmp_path / "p")
    gain = last["thermal_energy"] - first["thermal_energy"]
    walls = last["E_wall_left"] + last["E_wall_right"]
    assert gain == pytest.approx(walls, rel=1e-9, abs=1e-9 * last["E_wall_left"])


@pytest.mark.parametrize("integrator", ["implicit", "trbdf2"])
def test_bed_with_every_link_on_two_ranks_is_one_process_run(tmp_path, integrator):
    """The frozen 4 x 4 x 3 lattice of test_thermal_implicit (a floor at 400 K, a side wall with a
    fixed flux, gas convection, radiation, a source), 30 steps of 100 s (> 10 network limits),
    with [output] heat_by_mechanism, on 2 ranks: the temperatures of one process to 1e-8 K (each
    solve to CG_RTOL 1e-10 of the heat rates), every heat total of history.csv to 1e-9 of the
    largest, the energy balance closed, and the per-particle rates by mechanism of the last step
    equal to one process's to 1e-9 of the largest rate (the pair shares of the particles beside a
    cut added on their own rank)."""
    sc = bed_scene(100.0, 3000.0, integrator)
    sc["simulation"]["output_interval"] = 1500.0
    sc["output"] = {"heat_by_mechanism": True}
    scene = _write(tmp_path / "bed.toml", sc)
    p = mpirun(2, "run", str(scene), "--out", str(tmp_path / "p"), cwd=tmp_path)
    assert "ghosts" in p.stdout + p.stderr   # (the parallel line: pairs cross the cut)
    _serial(scene, tmp_path / "s")
    a, b = _by_id(tmp_path / "s"), _by_id(tmp_path / "p")
    assert np.array_equal(a["id"], b["id"])
    assert np.abs(a["temperature"] - b["temperature"]).max() < 1e-8
    assert b["temperature"].min() > 300.0 and b["temperature"].max() > 330.0
    la, fa = _last(tmp_path / "s")
    lb, fb = _last(tmp_path / "p")
    heats = [k for k in la if k.startswith("E_")]
    assert len(heats) >= 4
    scale = max(abs(la[k]) for k in heats)
    for k in heats:
        assert abs(la[k] - lb[k]) <= 1e-9 * scale, (k, la[k], lb[k])
    gain = lb["thermal_energy"] - fb["thermal_energy"]
    inflow = sum(lb[k] for k in ("E_wall_floor", "E_wall_side", "E_convection", "E_radiation", "E_sources"))
    assert abs(gain - inflow) <= 1e-9 * scale
    mech = [k for k in a if k.startswith("heat_")]
    assert "heat_direct" in mech and "heat_wall" in mech and "heat_rad" in mech
    qscale = max(np.abs(a[k]).max() for k in mech)
    for k in mech:
        assert np.abs(a[k] - b[k]).max() <= 1e-9 * qscale, k
    # the pairs' shares cancel over the bed on 2 ranks as on one
    assert abs(b["heat_direct"].sum()) <= 1e-9 * np.abs(b["heat_direct"]).sum()


def test_stopped_and_continued_on_two_ranks(tmp_path):
    """TR-BDF2 keeps no history between steps: a frozen run on 2 ranks stopped at its checkpoint
    and continued ends with the temperatures and heat totals of one uninterrupted 2-rank run, to
    round-off (a multi-rank restart rebuilds each rank's rows from the pieces, so the solver's
    sums run in another order: docs/reliability.md, the restart table; a serial restart is bit
    for bit, test_thermal_implicit)."""
    sc = bed_scene(100.0, 2000.0, "trbdf2")
    sc["simulation"].update(output_interval=500.0, checkpoint_interval=1000.0)
    scene = _write(tmp_path / "bed.toml", sc)
    mpirun(2, "run", str(scene), "--out", str(tmp_path / "one"), "--quiet", cwd=tmp_path)
    mpirun(2, "run", str(scene), "--out", str(tmp_path / "two"), "--quiet", "--end-time", "1000", cwd=tmp_path)
    mpirun(2, "run", str(scene), "--out", str(tmp_path / "two"), "--quiet", "--restart",
           str(tmp_path / "two" / "checkpoint.npz"), cwd=tmp_path)
    a, b = _by_id(tmp_path / "one"), _by_id(tmp_path / "two")
    print("restart: largest temperature difference", np.abs(a["temperature"] - b["temperature"]).max())
    assert np.abs(a["temperature"] - b["temperature"]).max() < 1e-10
    la, _ = _last(tmp_path / "one")
    lb, _ = _last(tmp_path / "two")
    assert la["time"] == lb["time"] == 2000.0
    for k in la:
        if k.startswith("E_") or k == "thermal_energy":
            assert abs(la[k] - lb[k]) <= 1e-11 * abs(la["thermal_energy"]), k
    assert a["temperature"].max() > 330.0
