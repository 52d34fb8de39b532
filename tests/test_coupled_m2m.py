"""Coupled runs on several DEM ranks and several gas processes (the many-to-many exchange:
coupling.cells, coupling.m2m, thermoDemFoam's m2m transport), run as a user runs them:
``mpirun -np M python -m coupling.run run CASE`` with ``gas_processes = N`` in coupling.toml.

Bounds, and why:

* M DEM ranks on the same gas layout (M = 1, 2, 3): the same particles, forces and gas; only
  the order in which the per-cell sums of several ranks are added differs (each rank sums its
  own particles, the owner adds the ranks' partials), so results agree to round-off. After 4
  coupling steps (200 DEM steps) of the heated bed that is below 1e-13 m in position and
  1e-10 m/s, 1e-10 K (as the 2-rank DEM test of tests/test_coupled.py).
* N = 2 gas processes against N = 1: the gas itself is not round-off identical in parallel
  (OpenFOAM's preconditioned linear solvers differ at the processor boundary:
  tests/test_openfoam_solver.py::test_parallel_matches_serial bounds U by 1e-5 of its
  largest value), and the particles feel it through the drag: the bound is that of the gas.
* The m2m transport against the master-gather file transport on the same gas decomposition,
  one DEM rank: the same bytes reach every gas cell, so the results are bit-identical.
"""
from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from coupling.run import run_case  # noqa: E402
from dem.final import read as read_final

CASES = ROOT / "openfoam_cases"
END = "0.002"   # 4 coupling steps of 50 DEM steps


def _env():
    return dict(os.environ, OMPI_ALLOW_RUN_AS_ROOT="1", OMPI_ALLOW_RUN_AS_ROOT_CONFIRM="1",
                OMPI_MCA_rmaps_base_oversubscribe="1", OMPI_MCA_mpi_yield_when_idle="1")


def case_with(tmp_path: Path, name: str, gas: int, transport: str = "socket", tag: str = "") -> Path:
    dst = tmp_path / f"case_{name}_{gas}_{transport}{tag}"
    if not dst.exists():
        shutil.copytree(CASES / name, dst, ignore=shutil.ignore_patterns("README.md"))
        t = dst / "coupling.toml"
        text = t.read_text()
        text = text.replace('transport = "socket"', f'transport = "{transport}"')
        text = text.replace("[coupling]\n", f"[coupling]\ngas_processes = {gas}\n", 1)
        t.write_text(text)
    return dst


def coupled(m: int, case: Path, out: Path, *extra, check=True):
    """``mpirun -np m coupling run case --out out --end-time END`` (m = 1: no mpirun)."""
    cmd = [sys.executable, "-m", "coupling.run", "run", str(case), "--out", str(out), "--end-time", END, *extra]
    if m > 1:
        cmd = ["mpirun", "-np", str(m)] + cmd
    p = subprocess.run(cmd, capture_output=True, text=True, env=_env(), timeout=900, cwd=str(ROOT))
    if check:
        assert p.returncode == 0, p.stdout[-3000:] + p.stderr[-3000:]
    return p


def final(out: Path):
    return read_final(out / "final.npz")


def gas_last(out: Path, field: str):
    """The gas field of the last time, serial or decomposed (fc reads either)."""
    from coupling import foam_case as fc
    times = sorted((float(p.name), p) for p in out.iterdir() if p.is_dir() and _is_time(p.name))
    procs = sorted(out.glob("processor*"))
    if procs:
        addr = fc.cell_proc_addressing(out)
        n = sum(a.size for a in addr)
        tname = max((p.name for p in procs[0].iterdir() if p.is_dir() and _is_time(p.name)), key=float)
        parts = [fc.read_internal_field(pr / tname / field) for pr in procs]
        full = np.zeros((n,) + parts[0].shape[1:])
        for a, v in zip(addr, parts):
            full[a] = v
        return full
    return fc.read_internal_field(times[-1][1] / field)


def _is_time(name):
    try:
        return float(name) > 0
    except ValueError:
        return False


def assert_close(a, b, pos, vel, temp):
    assert np.array_equal(a["id"], b["id"])
    dp = np.abs(a["position"] - b["position"]).max()
    dv = np.abs(a["velocity"] - b["velocity"]).max()
    dt = np.abs(a["temperature"] - b["temperature"]).max()
    assert dp <= pos and dv <= vel and dt <= temp, (dp, dv, dt)


def balance_closed(out: Path):
    """The coupled energy balance's residual stays within its documented bound (coupling.csv)."""
    import csv
    rows = list(csv.DictReader(open(out / "coupling.csv")))
    assert rows and "balance_residual" in rows[-1], rows[-1].keys()
    r = float(rows[-1]["balance_residual"])
    scale = max(abs(float(rows[-1]["E_gas"])), abs(float(rows[-1]["E_particles"])))
    assert abs(r) <= 1e-6 * scale, (r, scale)


@pytest.fixture(scope="module")
def reference(tmp_path_factory, solver):
    """The (1 DEM rank, 1 gas process) run, in serial, and the (1, 2) run."""
    base = tmp_path_factory.mktemp("m2m")
    out = {}
    for gas in (1, 2):
        o = base / f"ref_1x{gas}"
        coupled(1, case_with(base, "fluidized_bed_heating", gas), o)
        out[gas] = o
    return base, out


def test_dem_ranks_on_one_gas_process_match_serial(reference):
    """(2, 1) and (3, 1) equal (1, 1) to round-off; every rank owned cells and exchanged only
    its own: gas bytes per rank per step = its cells x columns (+ headers), their sum the mesh."""
    base, ref = reference
    a = final(ref[1])
    for m in (2, 3):
        o = base / f"run_{m}x1"
        p = coupled(m, case_with(base, "fluidized_bed_heating", 1), o)
        assert f"{m} MPI ranks" in p.stdout
        assert_close(a, final(o), 1e-13, 1e-10, 1e-10)
        t = json.loads((o / "timings.json").read_text())
        ranks = t["ranks"]
        assert len(ranks) == m
        n_cells = sum(r["owned_cells"] for r in ranks)
        steps = t["coupling_steps"]
        for r in ranks:
            assert 0 < r["owned_cells"] < n_cells
            # 7 columns (eps, Ksl, Us, Simp, Sexp) per owned cell and step, plus 64-byte headers
            assert r["gas_bytes_sent"] == steps * (8 * 7 * r["owned_cells"] + 72 * r["gas_partners"]), r
            # the DEM ranks share only the cells near their common box faces: no rank sees the mesh
            assert 0 < r["halo_cells"] and r["owned_cells"] + r["halo_cells"] < n_cells
        gas_t = gas_last(ref[1], "T")
        assert np.abs(gas_last(o, "T") - gas_t).max() <= 1e-9 * np.abs(gas_t).max()
        balance_closed(o)


def test_gas_processes_many_to_many(reference):
    """(1, 2) with the m2m transport is bit-identical to the master-gather file transport on
    the same decomposition; (2, 2) and (3, 2) equal (1, 2) to round-off; and every layout
    equals (1, 1) within the gas's own parallel-solve bound."""
    base, ref = reference
    a1, a2 = final(ref[1]), final(ref[2])
    o = base / "file_1x2"
    coupled(1, case_with(base, "fluidized_bed_heating", 2, transport="file"), o)
    b = final(o)
    for k in ("position", "velocity", "temperature"):
        assert np.array_equal(a2[k], b[k]), k
    for m in (2, 3):
        o = base / f"run_{m}x2"
        coupled(m, case_with(base, "fluidized_bed_heating", 2), o)
        assert_close(a2, final(o), 1e-13, 1e-10, 1e-10)
        balance_closed(o)
    # N = 2 against N = 1: the gas's parallel linear solvers (1e-5 of U's scale), felt by the drag
    vscale = np.abs(a1["velocity"]).max()
    assert_close(a1, a2, 1e-7, 1e-4 * vscale, 1e-6)


TERMS = r'''
import sys
import numpy as np
from coupling.run import _case_on_temporary_mesh

case_dir, out = sys.argv[1], sys.argv[2]
with _case_on_temporary_mesh(case_dir) as (case, mesh, iface, eps0, rep):
    C = mesh.cell_centres
    fluid = {"U": np.c_[0.1 * np.sin(40 * C[:, 0]), 0.05 * C[:, 1], 0.3 + C[:, 2]],
             "gradp": np.c_[0 * C[:, 0], 0 * C[:, 0], -1.2 * 9.81 + 0 * C[:, 0]],
             "T": 300.0 + 100.0 * C[:, 2], "p": 0 * C[:, 0]}
    case.sim.warmup()
    f1 = iface.prepare(fluid, case.dt_cfd)
    iface.advance_dem(case.config.coupling_interval)
    iface.map_particles()
    f2 = iface.prepare(fluid, case.dt_cfd)
    cs = iface.cells
    res = {}
    for tag, f in (("a", f1), ("b", f2)):
        for k, v in f.items():
            res[f"{tag}_{k}"] = cs.gather_owned(np.asarray(v))
    owned = cs.gather_owned(np.full(mesh.n_cells, cs.rank, np.int64))
    par = case.sim.par
    stats = (int(cs.owned.size), cs.halo_cells, cs.served_cells, cs.bytes_sent)
    allst = [stats] if par is None else par.comm.gather(stats, root=0)
    if cs.rank == 0:
        np.savez(out, n_cells=mesh.n_cells, stats=np.array(allst), owner=owned, **res)
'''


def test_exchange_terms_on_three_dem_ranks_match_serial(tmp_path):
    """The DEM side of the many-to-many exchange without a gas solver: the exchange terms of
    the fluidized bed (two coupling steps with a given gas frame) on 3 DEM ranks equal the serial
    ones to round-off (2e-15 of each field's largest value: only the order of the ranks' partial
    sums differs), every cell has exactly one owner, and each rank's messages to the other DEM
    ranks are exactly its shared cells times the columns exchanged: 14 summed columns (1 + 6 +
    1 + 6: void fraction, drag/velocity/heat sums, twice) travel to the owner and back, 2 (the
    relaxed void fraction) from the owner only; no term of the mesh size."""
    script = tmp_path / "terms.py"
    script.write_text(TERMS)
    env = dict(_env(), PYTHONPATH=str(ROOT))
    case = str(CASES / "fluidized_bed_heating")
    subprocess.run([sys.executable, str(script), case, str(tmp_path / "one.npz")], check=True, env=env,
                   timeout=600, cwd=str(ROOT))
    p = subprocess.run(["mpirun", "-np", "3", sys.executable, str(script), case, str(tmp_path / "three.npz")],
                       env=env, timeout=600, cwd=str(ROOT), capture_output=True, text=True)
    assert p.returncode == 0, p.stdout[-2000:] + p.stderr[-3000:]
    a, b = np.load(tmp_path / "one.npz"), np.load(tmp_path / "three.npz")
    fields = [k for k in a.files if k[:2] in ("a_", "b_")]
    assert len(fields) == 10
    for k in fields:
        scale = np.abs(a[k]).max()
        assert np.abs(a[k] - b[k]).max() <= 2e-15 * max(scale, 1e-300), k
    assert np.abs(a["b_Ksl"] - a["a_Ksl"]).max() > 0   # the particles moved between the two steps
    n = int(b["n_cells"])
    owner = b["owner"]
    assert sorted(np.unique(owner)) == [0, 1, 2]
    stats = b["stats"]
    assert stats[:, 0].sum() == n
    for owned, halo, served, sent in stats:
        assert 0 < halo and 0 < served
        assert sent == 8 * (14 * (halo + served) + 2 * served)


def test_sigterm_on_two_by_two_continues_on_three_by_one(reference, tmp_path):
    """A scheduler's SIGTERM to the DEM ranks of a run with 2 gas processes: every DEM rank
    stops at the same coupling step, the solver writes its fields there, the run exits 143 with
    the command that continues it. Continued on 3 DEM ranks and 1 gas process (the gas fields
    reconstructed by OpenFOAM's reconstructPar), it ends where the uninterrupted (1, 1) run
    ends, within the bound of the gas's parallel solve (module docstring)."""
    import signal
    import time
    base, ref = reference
    from coupling import foam_case as fc
    case = case_with(tmp_path, "fluidized_bed_heating", 2, tag="_sig")
    fc.set_entries(case / "system" / "controlDict", {"writeControl": "timeStep", "writeInterval": 4})
    out = tmp_path / "out"
    env = dict(_env(), OMPI_MCA_odls_base_sigkill_timeout="3")   # Open MPI: SIGTERM after 3 s, SIGKILL 3 s later
    # each rank's exit status, recorded by a shell that ignores the signals itself
    rank = "trap '' INT TERM; \"$@\"; echo $? > " + str(tmp_path) + "/rc.$OMPI_COMM_WORLD_RANK"
    cmd = ["mpirun", "-np", "2", "sh", "-c", rank, "sh", sys.executable, "-m", "coupling.run", "run", str(case),
           "--out", str(out), "--end-time", "0.5"]
    p = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env, cwd=str(ROOT))
    t0 = time.monotonic()
    while not (out / "checkpoints" / "checkpoint_00000004.npz").exists():   # the first restart point
        assert p.poll() is None, p.communicate()
        assert time.monotonic() - t0 < 600
        time.sleep(0.1)
    # a batch scheduler's SIGTERM reaches every process of the job (as pkill -TERM does here)
    ranks = subprocess.run(["pgrep", "-f", f"coupling.run run {case}"], capture_output=True, text=True).stdout.split()
    ranks = [int(x) for x in ranks if open(f"/proc/{x}/cmdline").read().startswith(sys.executable)]
    assert len(ranks) == 2, ranks
    for pid in ranks:
        os.kill(pid, signal.SIGTERM)
    so, se = p.communicate(timeout=300)
    codes = [int((tmp_path / f"rc.{k}").read_text()) for k in (0, 1)]
    assert codes == [143, 143], so[-2000:] + se[-3000:]
    assert "stopped by SIGTERM" in se and "--restart" in se, se[-2000:]
    steps = sorted(int(f.name[11:19]) for f in (out / "checkpoints").glob("checkpoint_*.npz"))
    assert steps and 5 <= steps[-1] < 100, steps
    end = repr((steps[-1] + 4) * 5e-4)   # four coupling steps more
    # continue on (3, 1): the user edits gas_processes and restarts with more DEM ranks
    t = case / "coupling.toml"
    t.write_text(t.read_text().replace("gas_processes = 2", "gas_processes = 1"))
    q = coupled(3, case, out, "--restart", "--end-time", end)
    assert "moved from 2 to 1" in q.stdout, q.stdout[-2000:]
    r = tmp_path / "ref"
    coupled(1, case_with(tmp_path, "fluidized_bed_heating", 1, tag="_ref"), r, "--end-time", end)
    a, b = final(r), final(out)
    vscale = np.abs(a["velocity"]).max()
    assert_close(a, b, 1e-7, 1e-4 * vscale, 1e-6)
    balance_closed(out)


def test_coarse_grained_bed_on_two_by_two(tmp_path, solver):
    """The coarse-grained bed (37,100 parcels) on (2, 2) against (1, 1): two coupling steps equal
    within the gas's parallel-solve bound; each DEM rank owns part of the mesh."""
    outs = {}
    for m, gas in ((1, 1), (2, 2)):
        case = case_with(tmp_path, "fluidized_bed_cg", gas)
        outs[m] = tmp_path / f"cg_{m}x{gas}"
        cmd = [sys.executable, "-m", "coupling.run", "run", str(case), "--out", str(outs[m]), "--end-time", "0.0005"]
        if m > 1:
            cmd = ["mpirun", "-np", str(m)] + cmd
        p = subprocess.run(cmd, capture_output=True, text=True, env=_env(), timeout=1200, cwd=str(ROOT))
        assert p.returncode == 0, p.stdout[-2000:] + p.stderr[-3000:]
    a, b = final(outs[1]), final(outs[2])
    vscale = np.abs(a["velocity"]).max()
    assert_close(a, b, 1e-7, 1e-4 * vscale, 1e-6)
    ranks = json.loads((outs[2] / "timings.json").read_text())["ranks"]
    assert len(ranks) == 2 and all(r["owned_cells"] > r["halo_cells"] > 0 for r in ranks)


def test_a_dead_gas_processor_stops_every_dem_rank(reference, tmp_path):
    """kill -9 of one of the two thermoDemFoam processes of a (2, 2) run: every DEM rank stops
    (no hang), the run exits 3 with one line naming the DEM rank that saw it, the gas processor
    and the coupling step, and a checkpoint is written."""
    import signal
    import time
    case = case_with(tmp_path, "fluidized_bed_heating", 2, tag="_kill")
    out = tmp_path / "out"
    cmd = ["mpirun", "-np", "2", sys.executable, "-m", "coupling.run", "run", str(case), "--out", str(out),
           "--end-time", "0.02"]
    p = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=_env(), cwd=str(ROOT))
    log = out / "log.thermoDemFoam"
    t0 = time.monotonic()
    while not (log.exists() and "Time = 0.001" in log.read_text()):
        assert p.poll() is None, p.communicate()
        assert time.monotonic() - t0 < 600
        time.sleep(0.2)
    pids = subprocess.run(["pgrep", "-f", f"thermoDemFoam -case {out.resolve()}"], capture_output=True, text=True).stdout.split()
    solvers = [int(x) for x in pids if "mpirun" not in open(f"/proc/{x}/cmdline").read().replace("\0", " ")]
    assert len(solvers) == 2, pids
    os.kill(max(solvers), signal.SIGKILL)
    so, se = p.communicate(timeout=300)
    assert p.returncode == 3, so[-2000:] + se[-3000:]
    lines = [ln for ln in se.splitlines() if ln.startswith("coupling: error")]
    assert len(lines) == 1, se[-3000:]
    assert "DEM rank" in lines[0] and "CFD solver" in lines[0] and "coupling step" in lines[0], lines[0]
    assert (out / "checkpoint.npz").exists()


def test_file_transport_with_two_dem_ranks_is_refused(tmp_path):
    """The file transport runs with one DEM rank: under ``mpirun -np 2`` the run is refused
    before anything is written, exit 2, naming coupling.toml and what to use."""
    case = case_with(tmp_path, "fluidized_bed_heating", 1, transport="file")
    out = tmp_path / "out"
    p = coupled(2, case, out, check=False)
    assert p.returncode == 2, p.stdout[-2000:] + p.stderr[-2000:]
    assert "coupling.toml" in p.stderr and 'transport = "socket"' in p.stderr, p.stderr[-2000:]
    assert not out.exists()


def test_exchange_host(reference, tmp_path):
    """coupling.exchange_host: an IPv4 address or "auto" (each DEM rank its node's address, for gas
    processes on other nodes). "auto" on (2, 1) gives the (1, 1) result to round-off, the plan
    names the node's address; a value that is neither is refused naming the key; an address of
    another machine is refused before the solver starts, exit 2, naming the key and the rank."""
    import socket
    from coupling.case import CaseConfigError, load_config
    base, ref = reference
    bad = tmp_path / "bad.toml"
    bad.write_text('[coupling]\nexchange_host = "my-laptop"\n')
    with pytest.raises(CaseConfigError, match=r"coupling.exchange_host: 'my-laptop' is not an IPv4 address"):
        load_config(bad)
    case = case_with(tmp_path, "fluidized_bed_heating", 1, tag="_auto")
    t = case / "coupling.toml"
    t.write_text(t.read_text().replace("[coupling]\n", '[coupling]\nexchange_host = "auto"\n', 1))
    out = tmp_path / "auto"
    coupled(2, case, out)
    assert_close(final(ref[1]), final(out), 1e-13, 1e-10, 1e-10)
    node = socket.gethostbyname(socket.gethostname())
    lines = [f.read_text().split()[0] for f in (out / "coupling" / "m2m" / "gas0").glob("dem*")]
    assert lines and set(lines) == {node}, lines
    t.write_text(t.read_text().replace('exchange_host = "auto"', 'exchange_host = "192.0.2.1"'))
    p = coupled(2, case, tmp_path / "far", check=False)
    assert p.returncode == 2, p.stderr[-2000:]
    assert "coupling.exchange_host = '192.0.2.1': DEM rank" in p.stderr and "cannot listen there" in p.stderr
