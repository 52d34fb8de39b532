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
def layout(tmp_path_factory, solver):
    """The heated bed's run to END on (m DEM ranks, gas processes, transport), each run once for
    the module (on first use) and shared by the tests that read it (none writes into its output
    folder): ``layout(m, gas, transport="socket")`` is (output folder, CompletedProcess)."""
    base = tmp_path_factory.mktemp("m2m")
    done = {}

    def get(m: int, gas: int, transport: str = "socket"):
        key = (m, gas, transport)
        if key not in done:
            o = base / f"run_{m}x{gas}_{transport}"
            done[key] = (o, coupled(m, case_with(base, "fluidized_bed_heating", gas, transport), o))
        return done[key]
    return get


@pytest.fixture(scope="module")
def reference(tmp_path_factory, layout):
    """The (1 DEM rank, 1 gas process) run, in serial, and the (1, 2) run."""
    return tmp_path_factory.mktemp("m2m_runs"), {gas: layout(1, gas)[0] for gas in (1, 2)}


def test_dem_ranks_on_one_gas_process_match_serial(reference, layout):
    """(2, 1) and (3, 1) equal (1, 1) to round-off; every rank owned cells and exchanged only
    its own: gas bytes per rank per step = its cells x columns (+ headers), their sum the mesh."""
    base, ref = reference
    a = final(ref[1])
    for m in (2, 3):
        o, p = layout(m, 1)
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


def test_sigusr1_to_mpirun_stops_at_once_and_continues(tmp_path, solver):
    """The prompt way to stop an mpirun job: Open MPI forwards SIGUSR1 to every rank at once
    (Ctrl-C reaches them as SIGTERM only odls_base_sigkill_timeout seconds later) and kills
    nothing itself: exit 138 on every rank, not 143. Every DEM rank stops at the same coupling
    step, the solver writes its fields there, a restart point is written, and the printed
    command continues the run."""
    import re
    import signal
    import time
    case = case_with(tmp_path, "fluidized_bed_heating", 1, tag="_usr1")
    out = tmp_path / "out"
    env = _env()
    rank = "trap '' INT TERM USR1; \"$@\"; echo $? > " + str(tmp_path) + "/rc.$OMPI_COMM_WORLD_RANK"
    cmd = ["mpirun", "-np", "2", "sh", "-c", rank, "sh", sys.executable, "-m", "coupling.run", "run", str(case),
           "--out", str(out), "--end-time", "0.5"]
    p = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env, cwd=str(ROOT))
    t0 = time.monotonic()
    while not (out / "coupling.csv").exists() or len((out / "coupling.csv").read_text().splitlines()) < 3:
        assert p.poll() is None, p.communicate()
        assert time.monotonic() - t0 < 600
        time.sleep(0.1)
    p.send_signal(signal.SIGUSR1)   # to mpirun, as `kill -USR1 <mpirun>` or a scheduler's warning
    so, se = p.communicate(timeout=300)
    codes = [int((tmp_path / f"rc.{k}").read_text()) for k in (0, 1)]
    assert codes == [138, 138], so[-2000:] + se[-3000:]
    m = re.search(r"stopped by SIGUSR1 at t = (\S+) s \(coupling step (\d+)\); restart point (\S+) .*"
                  r"continue with: (.*)$", se, re.M)
    assert m, se[-3000:]
    step = int(m.group(2))
    assert Path(m.group(3)).is_file() and step < 1000
    assert not subprocess.run(["pgrep", "-f", f"thermoDemFoam.*{out}"], capture_output=True).stdout
    argv = m.group(4).split()
    assert argv[:5] == ["mpirun", "-np", "2", "coupling", "run"] and "--restart" in argv, argv
    end = repr((step + 2) * 5e-4)   # two coupling steps more
    argv[argv.index("--end-time") + 1] = end
    q = subprocess.run(argv[:3] + [sys.executable, "-m", "coupling.run"] + argv[4:], capture_output=True, text=True, env=_env(), timeout=900, cwd=str(ROOT))
    assert q.returncode == 0, q.stdout[-2000:] + q.stderr[-3000:]
    assert float(final(out)["time"]) == pytest.approx(float(end), rel=1e-9)
    balance_closed(out)


def _report_values(text: str) -> dict:
    """The coupling checks' values as printed before a run (name, value)."""
    vals = {}
    for line in text.splitlines():
        parts = line.split()
        if line.startswith("  ") and len(parts) == 2 and parts[0].islower():
            try:
                vals[parts[0]] = float(parts[1])
            except ValueError:
                pass
    return vals


def test_checks_on_three_ranks_see_every_particle(tmp_path, layout):
    """The coupling checks run on every DEM rank, each holding its own particles: the report
    is over all particles (reductions, the worst particle's record from the rank that has it),
    the same as the serial one, printed to 4 digits. The one estimate that differs is the
    coordination number: pairs across a cut are not counted (within 5 % here; it only tells a
    loose packing from one at rest). The single particle on 2 ranks (one rank owns nothing)
    runs and reports as in serial. The bed's reports are those of the module's shared (1, 1) and
    (3, 1) runs (the same case and command): the report is printed before the first step and
    holds nothing of the end time (time steps, counts, sizes, speeds and Courant numbers of the
    initial state), so the runs' length does not enter it."""
    for name, m, end in (("fluidized_bed_heating", 3, END), ("single_particle_heating", 2, "0.002")):
        reps = {}
        for k in (1, m):
            if name == "fluidized_bed_heating":
                p = layout(k, 1)[1]
            else:
                case = case_with(tmp_path, name, 1, tag="_checks")
                cmd = [sys.executable, "-m", "coupling.run", "run", str(case), "--out",
                       str(tmp_path / f"{name}_{k}"), "--end-time", end]
                p = subprocess.run((["mpirun", "-np", str(k)] if k > 1 else []) + cmd, capture_output=True,
                                   text=True, env=_env(), timeout=900, cwd=str(ROOT))
            assert p.returncode == 0, p.stdout[-3000:] + p.stderr[-3000:]
            reps[k] = _report_values(p.stdout)
        a, b = reps[1], reps[m]
        assert a.keys() == b.keys() and len(a) > 15, (a, b)
        for key in a:
            if key == "coordination_number":
                assert b[key] == pytest.approx(a[key], rel=0.05), (key, a[key], b[key])
            else:
                assert b[key] == a[key], (name, key, a[key], b[key])


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


def _view_count(centres, lo, hi, reach):
    """Cells whose centre lies within ``reach`` of the box [lo, hi] (computed here, not by
    coupling.cells)."""
    lo, hi = np.asarray(lo, float), np.asarray(hi, float)
    d = np.maximum(np.maximum(lo - centres, centres - hi), 0.0)
    return np.flatnonzero(np.sqrt((d * d).sum(axis=1)) <= reach)


def test_local_meshes_and_restart_pieces_on_three_by_two(solver, tmp_path):
    """(3, 2): each DEM rank holds only the gas cells it sees, a local mesh well below the
    mesh: its cells are exactly those within the particle halo plus two cell diagonals of its
    box (counted here from the box in timings.json), its bytes a fraction of the whole mesh's.
    The restart point's coupling state is a manifest and one piece per rank (the owned cells of
    each: together every cell once). Continued from the restart point of step 4, each rank reads
    exactly the pieces holding cells it sees (the bottom rank not the top one's), and the run
    ends where the uninterrupted run ends (the continuation on another layout:
    test_sigterm_on_two_by_two_continues_on_three_by_one). With the DEM boxes re-cut at every
    neighbour rebuild, the ranks rebuild their local meshes from the gas pieces and the run
    ends where the one without re-cuts ends, to round-off."""
    from coupling.mesh import read_polymesh
    from coupling import foam_case as fc
    case = case_with(tmp_path, "fluidized_bed_heating", 2, tag="_local")
    fc.set_entries(case / "system" / "controlDict", {"writeControl": "timeStep", "writeInterval": 4})
    out = tmp_path / "out"
    coupled(3, case, out, "--end-time", "0.003")   # 6 coupling steps: restart points at 4 and 6
    whole = read_polymesh(str(out))
    n = whole.n_cells
    ranks = json.loads((out / "timings.json").read_text())["ranks"]
    assert len(ranks) == 3 and sum(r["owned_cells"] for r in ranks) == n
    for r in ranks:
        assert r["mesh_rebuilds"] == 0, r
        view = _view_count(whole.cell_centres, *r["view_box"], r["view_reach"])
        assert r["local_cells"] == view.size < n, (r["local_cells"], view.size, n)
        assert r["local_cells"] == r["owned_cells"] + r["halo_cells"]
        assert r["mesh_bytes"] < whole.nbytes(), (r["mesh_bytes"], whole.nbytes())
    # the coupling state of step 4: a manifest naming 3 pieces, the owned cells of each rank
    man = np.load(out / "checkpoints" / "coupling_00000004.npz")
    assert list(man["pieces"]) == [f"rank{k:05d}.npz" for k in range(3)] and int(man["n_cells"]) == n
    folder = out / "checkpoints" / "coupling_00000004.pieces"
    held = [np.load(folder / f"rank{k:05d}.npz")["cells"] for k in range(3)]
    assert np.array_equal(np.sort(np.concatenate(held)), np.arange(n))
    assert [h.size for h in held] == [r["owned_cells"] for r in ranks]
    # continue from step 4: the user removes the later gas times (docs: restart points)
    a = dict(final(out))
    for p in [out, *out.glob("processor*")]:
        for t in p.iterdir():
            if t.is_dir() and _is_time(t.name) and float(t.name) > 0.0021:
                shutil.rmtree(t)
    coupled(3, case, out, "--restart", "--end-time", "0.003")
    ranks2 = json.loads((out / "timings.json").read_text())["ranks"]
    assert len(ranks2) == 3
    for r in ranks2:
        view = _view_count(whole.cell_centres, *r["view_box"], r["view_reach"])
        need = [f"rank{k:05d}.npz" for k in range(3) if np.intersect1d(held[k], view).size]
        assert sorted(r["restart_pieces"]) == need, (r["restart_pieces"], need)
    assert any(len(r["restart_pieces"]) < 3 for r in ranks2), ranks2
    assert_close(a, final(out), 1e-13, 1e-10, 1e-10)
    balance_closed(out)
    # the DEM boxes re-cut at every neighbour rebuild ([parallel] balance_threshold = 1): a rank
    # whose box moved beyond its local mesh rebuilds it from the gas pieces overlapping its
    # new view and its owned cells (not the whole mesh), the state moves through the owners,
    # and the run ends where the one without re-cuts ends, to round-off
    recut = case_with(tmp_path, "fluidized_bed_heating", 2, tag="_recut")
    d = recut / "dem.toml"
    # (a skin of 2 um: the neighbour lists, and with them the boxes, are rebuilt every few steps)
    d.write_text(d.read_text().replace("[simulation]\n", "[simulation]\nneighbor_skin = 2e-6\n", 1)
                 + "\n[parallel]\nbalance_threshold = 1.0\n")
    out3 = tmp_path / "out_recut"
    coupled(3, recut, out3, "--end-time", "0.003")
    ranks3 = json.loads((out3 / "timings.json").read_text())["ranks"]
    assert all(r["dem_recuts"] > 0 for r in ranks3) and sum(r["mesh_rebuilds"] for r in ranks3) > 0, ranks3
    for r in ranks3:
        if r["mesh_rebuilds"]:
            assert 0 < len(r["mesh_pieces_read"]) <= 2, r["mesh_pieces_read"]
        view = _view_count(whole.cell_centres, *r["view_box"], r["view_reach"])
        assert r["local_cells"] >= view.size and r["local_cells"] < n
    assert_close(a, final(out3), 1e-13, 1e-10, 1e-10)
    balance_closed(out3)
