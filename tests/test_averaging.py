"""Time-averaged particle fields on the gas mesh (``[averaging]`` of coupling.toml,
coupling.averaging; docs/models.md "Time-averaged fields on the gas mesh").

A small heated bed (openfoam_cases/fluidized_bed_heating with 600 beads, the ``centre`` void
fraction, no time smoothing, every coupling step written by both sides) runs 6 coupling steps
through the command line, serial and on 2 DEM ranks x 2 gas processes. The means OpenFOAM's
fieldAverage wrote into the time folders (per processor when decomposed) are compared with
means computed here, independently, from the particle frames the DEM wrote (particles.pvd:
positions, radii, velocities, temperatures at every coupling time): each particle's volume
binned into the cell holding its centre by its coordinates (the 6 mm cells of the block mesh),
the samples those of the coupling steps ending at t >= start (the gas step ending at t_k solves
with the frame of the particles at t_(k-1)), averaged by fieldAverage's recursion
(mean <- (1 - b) mean + b x, b = dt / (time averaged), or dt / window once the window is full).
Bound: 1e-12 of each field's largest value (the sums run in another order; the means are
written at 17 digits). The heat source, which the frames do not hold (it needs the gas
temperature after the step), is compared with the mean of the instantaneous Qp = Sexp - Simp T
the solver wrote at every step.

Also: a run stopped at half time and continued (``--restart``) writes the same means as the
uninterrupted one (fieldAverage continues from its state in the restart time folder); a bad
``[averaging]`` key is refused with exit 2, naming the file and the key, before anything is
written.
"""
from __future__ import annotations

import os
import re
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

ROOT = Path(__file__).resolve().parents[1]
SRC = ROOT / "openfoam_cases" / "fluidized_bed_heating"
DT = 5e-4                  # the case's coupling step (system/controlDict deltaT)
END = 6 * DT
START = 2 * DT
EPS_MIN = 0.3              # coupling.toml eps_min of the case
CELL = 0.006               # the block mesh's cells: 10 x 2 x 30 of 6 mm
TOL = 1e-12


def _env():
    return dict(os.environ, PYTHONPATH=str(ROOT) + os.pathsep + os.environ.get("PYTHONPATH", ""),
                OMPI_ALLOW_RUN_AS_ROOT="1", OMPI_ALLOW_RUN_AS_ROOT_CONFIRM="1",
                OMPI_MCA_rmaps_base_oversubscribe="1", OMPI_MCA_mpi_yield_when_idle="1")


def make_case(dst: Path, averaging: str, gas: int = 1) -> Path:
    shutil.copytree(SRC, dst, ignore=shutil.ignore_patterns("README.md"))
    t = dst / "coupling.toml"
    text = t.read_text().replace('void_fraction = "smoothed"', 'void_fraction = "centre"')
    text = re.sub(r"smoothing_time = [0-9.e-]+", "smoothing_time = 0.0", text)
    text = text.replace("output_interval = 0.01", f"output_interval = {DT!r}")
    text = text.replace("[coupling]\n", f"[coupling]\ngas_processes = {gas}\n", 1)
    t.write_text(text + "\n" + averaging)
    d = dst / "dem.toml"
    d.write_text(d.read_text().replace("count = 3000", "count = 600")
                 .replace("output_interval = 0.01", f"output_interval = {DT!r}"))
    c = dst / "system" / "controlDict"
    c.write_text(c.read_text().replace("writeInterval   100;", "writeInterval   1;"))
    return dst


def run(case: Path, out: Path, end: float, *extra, ranks: int = 1, check: bool = True):
    cmd = [sys.executable, "-m", "coupling.run", "run", str(case), "--out", str(out), "--end-time", repr(end),
           "--quiet", *extra]
    if ranks > 1:
        cmd = ["mpirun", "-np", str(ranks)] + cmd
    p = subprocess.run(cmd, capture_output=True, text=True, env=_env(), timeout=600, cwd=str(ROOT))
    if check:
        assert p.returncode == 0, p.stdout[-3000:] + p.stderr[-3000:]
    return p


# --------------------------------------------------------------------------- reading

def frames(out: Path) -> dict[int, dict]:
    """The DEM's frames by coupling step k (t = k DT): position, radius, velocity, temperature
    (a .vtu, or the .vtu pieces a .pvtu names)."""
    import meshio
    res = {}
    for t, f in re.findall(r'timestep="([^"]+)"[^>]*file="([^"]+)"', (out / "particles.pvd").read_text()):
        path = out / f
        files = [path] if path.suffix == ".vtu" else \
            [path.parent / s for s in re.findall(r'<Piece Source="([^"]+)"', path.read_text())]
        parts = [meshio.read(p) for p in files]
        res[round(float(t) / DT)] = dict(
            position=np.concatenate([m.points for m in parts]),
            **{k: np.concatenate([m.point_data[k] for m in parts]) for k in ("radius", "velocity", "temperature")})
    return res


def cell_of(out: Path):
    """A function giving the cell of each position: the cell whose centre is in the same
    6 mm box of the block mesh (the centres from the mesh files)."""
    from coupling.mesh import read_polymesh
    centres = read_polymesh(str(out)).cell_centres
    key = lambda x: tuple(np.floor(np.asarray(x) / CELL).astype(int).T)   # noqa: E731
    index = {k: c for c, k in enumerate(zip(*key(centres)))}
    return (lambda x: np.array([index[k] for k in zip(*key(x))])), centres.shape[0], read_polymesh(str(out))


def gas_field(out: Path, time: str, name: str) -> np.ndarray:
    """A field of one time folder in global cell order (reconstructed from processor*/)."""
    from coupling import foam_case as fc
    procs = sorted((p for p in out.glob("processor*") if p.name[9:].isdigit()), key=lambda p: int(p.name[9:]))
    if not procs:
        return fc.read_internal_field(out / time / name)
    addr = fc.cell_proc_addressing(out)
    parts = [fc.read_internal_field(p / time / name, a.size) for p, a in zip(procs, addr)]
    full = np.zeros((sum(a.size for a in addr),) + parts[0].shape[1:])
    for a, v in zip(addr, parts):
        full[a] = v
    return full


def time_name(k: int) -> str:
    return f"{k * DT:.8g}"


# --------------------------------------------------------------------------- expected

def fa_mean(samples, window=None):
    """fieldAverage's mean of ``samples`` (one per coupling step DT), base time, windowType
    approximate: mean <- (1 - b) mean + b x, b = DT / (time averaged so far), or DT / window
    once the time averaged before this sample reaches the window."""
    mean, total = None, 0.0
    for x in samples:
        total += DT
        b = DT / total
        if window is not None and total - DT >= window:
            b = DT / window
        mean = x.copy() if mean is None else (1 - b) * mean + b * x
    return mean


def expected(out: Path, n: int, window=None) -> dict:
    """The means at the time folder of step n from the frames (fields of [averaging]:
    docs/models.md)."""
    locate, n_cells, mesh = cell_of(out)
    V = mesh.cell_volumes
    fr = frames(out)
    k0 = round(START / DT)
    alpha, aU, aT, eps = [], [], [], []
    for k in range(k0, n + 1):
        f = fr[k - 1]   # the gas step ending at t_k took the frame of the particles at t_(k-1)
        c = locate(f["position"])
        vp = 4.0 / 3.0 * np.pi * f["radius"] ** 3
        s = np.bincount(c, vp, n_cells) / V
        alpha.append(s)
        aU.append(np.stack([np.bincount(c, vp * f["velocity"][:, i], n_cells) for i in range(3)], 1) / V[:, None])
        aT.append(np.bincount(c, vp * f["temperature"], n_cells) / V)
        eps.append(np.minimum(np.maximum(1.0 - s, EPS_MIN), 1.0))
    a = fa_mean(alpha, window)
    some = a > 0
    up = np.zeros((n_cells, 3))
    up[some] = fa_mean(aU, window)[some] / a[some, None]
    tp = np.zeros(n_cells)
    tp[some] = fa_mean(aT, window)[some] / a[some]
    qp = fa_mean([gas_field(out, time_name(k), "Qp") for k in range(k0, n + 1)], window)
    return dict(epsMean=fa_mean(eps, window), alphapMean=a, UpMean=up, TpMean=tp, QpMean=qp)


def assert_means(out: Path, n: int, window=None):
    want = expected(out, n, window)
    t = time_name(n)
    for name, w in want.items():
        got = gas_field(out, t, name)
        scale = np.abs(w).max()
        assert scale > 0, name
        err = np.abs(got - w).max()
        assert err <= TOL * scale, (name, err, scale)
    a = want["alphapMean"]
    assert (a > 0).any() and (a == 0).any()   # the bed and the freeboard above it
    return want


# --------------------------------------------------------------------------- tests

@pytest.fixture(scope="module")
def serial(tmp_path_factory, solver):
    base = tmp_path_factory.mktemp("averaging")
    case = make_case(base / "case", f"[averaging]\nstart = {START!r}\n")
    out = base / "out"
    run(case, out, END)
    return case, out


def test_serial_means_match_the_particle_frames(serial):
    _, out = serial
    assert_means(out, round(END / DT))
    assert_means(out, round(START / DT) + 1)         # an earlier write time: its own samples
    assert not (out / time_name(1) / "epsMean").exists()   # before start: no means
    # the heat source sampled: the instantaneous Qp is the particles' heat the gas took
    for k in range(1, 7):
        t = time_name(k)
        q, se, si, T = (gas_field(out, t, f) for f in ("Qp", "Sexp", "Simp", "T"))
        assert np.abs(q - (se - si * T)).max() <= 1e-9 * np.abs(se).max()
    assert np.abs(gas_field(out, time_name(6), "QpMean")).max() > 0


def test_restart_continues_the_averages(serial, tmp_path):
    """3 coupling steps, then --restart to 6: the same means as the uninterrupted run (the
    restart time, 0.0015 s, is inside the averaging: fieldAverage continues from its state)."""
    case, ref = serial
    out = tmp_path / "out"
    run(case, out, 3 * DT)
    run(case, out, END, "--restart")
    t = time_name(6)
    for name in ("epsMean", "alphapMean", "UpMean", "TpMean", "QpMean", "alphapUpMean"):
        a, b = gas_field(out, t, name), gas_field(ref, t, name)
        assert np.abs(a - b).max() <= TOL * np.abs(b).max(), name


def test_two_dem_ranks_two_gas_processes_per_processor(tmp_path, solver):
    """2 DEM ranks x 2 gas processes, with a window of 2 coupling steps (approximate: from the
    fourth sample on each enters with weight 1/2): the means are written by each processor
    into its own time folders."""
    window = 2 * DT
    case = make_case(tmp_path / "case", f"[averaging]\nstart = {START!r}\nwindow = {window!r}\n", gas=2)
    out = tmp_path / "out"
    run(case, out, END, ranks=2)
    assert not (out / time_name(6) / "epsMean").exists()
    for p in ("processor0", "processor1"):
        assert (out / p / time_name(6) / "UpMean").exists()
        assert (out / p / time_name(6) / "uniform" / "functionObjects" / "functionObjectProperties").exists()
    assert_means(out, 6, window)
    # the window changes the result: the plain mean differs
    plain = expected(out, 6)["epsMean"]
    assert np.abs(plain - gas_field(out, time_name(6), "epsMean")).max() > 1e-6


def test_bad_averaging_key_is_refused(tmp_path):
    case = make_case(tmp_path / "case", "[averaging]\nstart = 0.001\nwindw = 0.01\n")
    out = tmp_path / "out"
    p = run(case, out, END, check=False)
    assert p.returncode == 2, p.stdout[-2000:] + p.stderr[-2000:]
    assert "Traceback" not in p.stderr
    assert str(case / "coupling.toml") in p.stderr and "averaging.windw" in p.stderr, p.stderr
    assert not out.exists()


@pytest.mark.parametrize("table, key, words", [
    ("start = -1.0", "averaging.start", ">= 0"),
    ("start = 1.0", "averaging.start", "not before the end time"),
    ("window = 1e-5", "averaging.window", "shorter than one coupling step"),
    ("fields = [\"velocity\"]", "averaging.fields", "is not one of"),
    ("fields = []", "averaging.fields", "non-empty list"),
])
def test_averaging_values_checked(tmp_path, table, key, words):
    from coupling.case import CaseConfigError, load_case
    case = make_case(tmp_path / "case", f"[averaging]\n{table}\n")
    with pytest.raises(CaseConfigError) as e:
        load_case(case, build_sim=False)
    assert key in str(e.value) and words in str(e.value) and "coupling.toml" in str(e.value), str(e.value)


def test_heat_fields_need_heat(tmp_path):
    from coupling.case import CaseConfigError, load_case
    case = make_case(tmp_path / "case", "[averaging]\nfields = [\"particle_temperature\"]\n")
    t = case / "coupling.toml"
    t.write_text(t.read_text().replace("heat = true", "heat = false"))
    with pytest.raises(CaseConfigError, match="averaging.fields.*needs the heat exchange"):
        load_case(case, build_sim=False)
    t.write_text(t.read_text().replace('fields = ["particle_temperature"]\n', ""))
    assert load_case(case, build_sim=False).config.averaging.fields == ("void_fraction", "particle_velocity")


def test_function_objects_replaced_not_repeated(tmp_path):
    from coupling.averaging import AveragingConfig, write_function_objects
    ctl = tmp_path / "controlDict"
    shutil.copy(SRC / "system" / "controlDict", ctl)
    write_function_objects(ctl, AveragingConfig(start=0.1))
    write_function_objects(ctl, AveragingConfig(start=0.2, window=0.05))
    text = ctl.read_text()
    assert text.count("type fieldAverage;") == 1 and "timeStart 0.2;" in text and "window 0.05;" in text
    write_function_objects(ctl, None)
    assert "fieldAverage" not in ctl.read_text() and "[averaging]" not in ctl.read_text()


def test_coupling_check_says_what_is_averaged(tmp_path):
    """`coupling check` names the averaging's start, its window and the fields it writes, as
    the time folders will hold them; without [averaging] it says nothing of it."""
    case = make_case(tmp_path / "case", "[averaging]\nstart = 0.002\nwindow = 0.004\n")
    p = subprocess.run([sys.executable, "-m", "coupling.run", "check", str(case)], capture_output=True,
                       text=True, env=_env(), timeout=300, cwd=str(ROOT))
    assert p.returncode == 0, p.stdout[-2000:] + p.stderr[-2000:]
    line = [s for s in p.stdout.splitlines() if "averaging from" in s]
    assert line == ["  averaging from t = 0.002 s over a moving window of about 0.004 s: void_fraction, "
                    "particle_velocity, particle_temperature, heat_source (written as epsMean, alphapMean, "
                    "UpMean, TpMean, QpMean in the time folders)"], p.stdout
    plain = make_case(tmp_path / "plain", "")
    p = subprocess.run([sys.executable, "-m", "coupling.run", "check", str(plain)], capture_output=True,
                       text=True, env=_env(), timeout=300, cwd=str(ROOT))
    assert p.returncode == 0 and "averaging from" not in p.stdout, p.stdout[-2000:]
