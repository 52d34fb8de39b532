"""A user's files are sacred (issue 11, part 1): output folders through the command line.

Every run writes only into a folder that is new, empty, or an earlier output of the tool (the
manifest .thermodem-manifest.json lists what it wrote, and nothing else is there). Refusals
exit with status 2, one line, before anything is written; --overwrite removes exactly the
listed entries. Each test hashes the folders it hands to the tool before and after.
"""
import hashlib
import json
import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

ROOT = Path(__file__).resolve().parent.parent
CASES = ROOT / "openfoam_cases"
SCENE = ROOT / "tests" / "scenes" / "par_periodic.toml"   # 36 beads, 1e-5 s steps
MANIFEST = ".thermodem-manifest.json"


def _env():
    return dict(os.environ, PYTHONPATH=str(ROOT) + os.pathsep + os.environ.get("PYTHONPATH", ""))


def dem(*args, cwd=None, timeout=300):
    return subprocess.run([sys.executable, "-m", "dem.cli", *map(str, args)], cwd=cwd, env=_env(),
                          capture_output=True, text=True, timeout=timeout)


def coupling(*args, cwd=None, timeout=600):
    return subprocess.run([sys.executable, "-m", "coupling.run", *map(str, args)], cwd=cwd, env=_env(),
                          capture_output=True, text=True, timeout=timeout)


def tree(path: Path) -> dict:
    """Every file (sha256 of its bytes) and folder below ``path``."""
    out = {}
    for dirpath, dirs, files in os.walk(path):
        for d in dirs:
            out[os.path.relpath(os.path.join(dirpath, d), path) + "/"] = "dir"
        for f in files:
            p = os.path.join(dirpath, f)
            with open(p, "rb") as fh:
                out[os.path.relpath(p, path)] = hashlib.sha256(fh.read()).hexdigest()
    return out


def listed(out: Path) -> set:
    return set(json.loads((out / MANIFEST).read_text())["entries"])


def refused(r, *phrases):
    assert r.returncode == 2, (r.returncode, r.stdout, r.stderr)
    assert "Traceback" not in r.stderr, r.stderr
    lines = [ln for ln in r.stderr.splitlines() if "error:" in ln]
    assert len(lines) == 1, r.stderr                      # one line
    for p in phrases:
        assert p in lines[0], (p, lines[0])
    return lines[0]


@pytest.fixture
def case(tmp_path):
    """A copy of openfoam_cases/single_particle_heating (a mistake can only hurt the copy)."""
    c = tmp_path / "case"
    shutil.copytree(CASES / "single_particle_heating", c)
    return c


@pytest.fixture
def scene(tmp_path):
    s = tmp_path / "scene" / "periodic.toml"
    s.parent.mkdir()
    shutil.copy(SCENE, s)
    return s


def user_folder(path: Path) -> Path:
    """A user's folder whose names look like OpenFOAM's or ours."""
    (path / "2024").mkdir(parents=True)
    (path / "2024" / "data.csv").write_text("1,2,3\n")
    (path / "1e3").mkdir()
    (path / "system").mkdir()
    (path / "system" / "controlDict").write_text("my own\n")
    (path / "notes.txt").write_text("a week of work\n")
    (path / "history.csv").write_text("mine\n")
    return path


# --------------------------------------------------------------------------- coupling run

def test_coupling_out_is_case_refused(case, tmp_path):
    before = tree(case)
    r = coupling("run", case, "--out", case)
    refused(r, f"--out {case} is the case folder", "Choose a folder outside the case")
    r = coupling("run", case, "--out", case / "run1")
    refused(r, f"--out {case / 'run1'} is inside the case folder {case}")
    r = coupling("run", case, "--out", tmp_path)          # the case inside --out
    refused(r, f"the case folder {case} is inside --out {tmp_path}")
    assert tree(case) == before                           # byte-identical, nothing added
    assert sorted(os.listdir(tmp_path)) == ["case"]


def test_coupling_user_folder_refused(case, tmp_path):
    out = user_folder(tmp_path / "results")
    before = tree(out), tree(case)
    line = refused(coupling("run", case, "--out", out), f"--out {out} holds files this tool did not write",
                   "2024/", "notes.txt", "nothing was touched")
    assert "1e3/" in line and "history.csv" in line and "and 1 more" in line   # the first 4, sorted
    # --overwrite does not change that: only a manifest's entries may ever be removed
    refused(coupling("run", case, "--out", out, "--overwrite"), "2024/", "notes.txt")
    refused(coupling("run", case, "--out", out, "--restart"), "did not write")
    assert (tree(out), tree(case)) == before


# --------------------------------------------------------------------------- dem run

def test_dem_run_twice_overwrite_restart(scene, tmp_path):
    out = tmp_path / "o"
    r = dem("run", scene, "--out", out, "--end-time", "0.005", "--quiet")
    assert r.returncode == 0, r.stderr
    written = set(os.listdir(out)) - {MANIFEST}
    assert written == {"history.csv", "wall_heat.csv", "vtk", "particles.pvd", "final.npz", "checkpoint.npz"}
    assert listed(out) == written
    before = tree(out)
    # a second run into it: refused, nothing changed
    refused(dem("run", scene, "--out", out, "--end-time", "0.005", "--quiet"),
            f"--out {out} holds an earlier thermodem output", "--overwrite", "--restart")
    refused(dem("run", scene, "--out", out, "--quiet", "--overwrite", "--restart", out / "checkpoint.npz"),
            "--overwrite and --restart exclude each other")
    assert tree(out) == before
    # --restart continues in it: history keeps its rows to t = 0.005 s and goes on to 0.0075 s
    r = dem("run", scene, "--out", out, "--end-time", "0.0075", "--quiet", "--restart", out / "checkpoint.npz")
    assert r.returncode == 0, r.stderr
    h = np.genfromtxt(out / "history.csv", delimiter=",", names=True)
    assert np.allclose(h["time"], [0.0, 0.0025, 0.005, 0.0075], rtol=0, atol=1e-12)
    # a user's file in it: --overwrite refuses, naming it; nothing is removed
    (out / "notes.txt").write_text("mine\n")
    before = tree(out)
    refused(dem("run", scene, "--out", out, "--end-time", "0.005", "--quiet", "--overwrite"),
            "notes.txt", "did not write", "nothing was touched")
    assert tree(out) == before
    # without it, --overwrite removes exactly the listed entries (and a leftover temporary file)
    (out / "notes.txt").unlink()
    (out / ".tmp_thermodem_k2j4.csv").write_text("left by a kill\n")
    r = dem("run", scene, "--out", out, "--end-time", "0.0025", "--quiet", "--overwrite")
    assert r.returncode == 0, r.stderr
    h = np.atleast_1d(np.genfromtxt(out / "history.csv", delimiter=",", names=True))
    assert np.allclose(h["time"], [0.0, 0.0025], rtol=0, atol=1e-12)     # a new run, not the old rows
    assert len(os.listdir(out / "vtk")) == 2                               # the old run's 4 files are gone
    assert not (out / ".tmp_thermodem_k2j4.csv").exists()
    assert listed(out) == set(os.listdir(out)) - {MANIFEST}


def test_dem_run_user_folder_refused(scene, tmp_path):
    out = user_folder(tmp_path / "mine")
    before = tree(out)
    for extra in ([], ["--overwrite"]):
        refused(dem("run", scene, "--out", out, "--end-time", "0.005", "--quiet", *extra),
                f"--out {out} holds files this tool did not write", "2024/", "history.csv")
    assert tree(out) == before
    # the scene's own folder
    before = tree(scene.parent)
    refused(dem("run", scene, "--out", scene.parent, "--quiet"), "periodic.toml")
    assert tree(scene.parent) == before
    # --out that is a file
    f = tmp_path / "results.txt"
    f.write_text("keep\n")
    refused(dem("run", scene, "--out", f, "--quiet"), f"--out {f} is a file, not a folder")
    assert f.read_text() == "keep\n"
    # the default out/<scene name> under the working folder, when it is a user's folder
    user_folder(tmp_path / "cwd" / "out" / "periodic")
    before = tree(tmp_path / "cwd")
    refused(dem("run", scene, "--quiet", cwd=tmp_path / "cwd"), "out/periodic holds files")
    assert tree(tmp_path / "cwd") == before


def test_killed_run_is_listed_and_can_be_overwritten(scene, tmp_path):
    """Entries are recorded before they are created: after kill -9 in the middle of a run every
    entry in the folder is in the manifest, and --overwrite replaces the partial output."""
    out = tmp_path / "o"
    p = subprocess.Popen([sys.executable, "-m", "dem.cli", "run", str(scene), "--out", str(out), "--end-time",
                          "20", "--quiet"], env=_env(), stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    try:
        deadline = time.monotonic() + 240
        while time.monotonic() < deadline and p.poll() is None:
            if (out / "vtk").is_dir() and len(os.listdir(out / "vtk")) >= 3:
                break
            time.sleep(0.05)
        assert p.poll() is None, p.communicate()[1][-2000:]
        p.send_signal(signal.SIGKILL)
        p.wait(timeout=60)
    finally:
        if p.poll() is None:
            p.kill()
            p.wait()
    present = {n for n in os.listdir(out) if n != MANIFEST and not n.startswith(".tmp_thermodem_")}
    assert {"history.csv", "vtk", "particles.pvd"} <= present
    assert present <= listed(out)
    refused(dem("run", scene, "--out", out, "--end-time", "0.0025", "--quiet"), "earlier thermodem output")
    r = dem("run", scene, "--out", out, "--end-time", "0.0025", "--quiet", "--overwrite")
    assert r.returncode == 0, r.stderr
    assert sorted(os.listdir(out / "vtk")) == ["particles_000000.vtu", "particles_000250.vtu"]


# --------------------------------------------------------------------------- dem render

def test_render_never_overwrites_a_users_png(scene, tmp_path):
    out = tmp_path / "o"
    assert dem("run", scene, "--out", out, "--end-time", "0.0025", "--quiet").returncode == 0
    png = tmp_path / "figure.png"
    png.write_bytes(b"\x89PNG\r\n\x1a\n" + b"a user's figure")
    refused(dem("render", out, "--png", png), f"--png {png} exists and was not written by this tool")
    assert png.read_bytes() == b"\x89PNG\r\n\x1a\n" + b"a user's figure"
    # a render.png the user put into an output folder is not ours either
    (out / "render.png").write_bytes(b"user")
    refused(dem("render", out), "render.png exists and was not written by this tool")
    assert (out / "render.png").read_bytes() == b"user"
    (out / "render.png").unlink()
    pytest.importorskip("pyvista")
    r = dem("render", out)
    assert r.returncode == 0, r.stderr
    if not os.environ.get("DISPLAY") and not os.environ.get("VTK_DEFAULT_OPENGL_WINDOW"):
        # no display: drawn through EGL, without VTK's "bad X server connection" warning
        assert "bad X server" not in r.stderr and "WARN" not in r.stderr, r.stderr
    assert (out / "render.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert "render.png" in listed(out)        # so that --overwrite may remove it, and a re-render replace it
    from dem.outdir import png_is_ours
    assert png_is_ours(out / "render.png") and not png_is_ours(png)


# --------------------------------------------------------------------------- coupled run, overwrite

def test_coupled_output_listed_then_overwritten(case, tmp_path, solver):
    """A short coupled run: every entry it leaves (OpenFOAM time folders, logs, checkpoints) is
    listed; a second run is refused; --overwrite with a user's file in the folder is refused;
    without it, --overwrite replaces exactly the listed entries."""
    out = tmp_path / "out"
    r = coupling("run", case, "--out", out, "--end-time", "0.003", "--quiet")
    assert r.returncode == 0, r.stderr
    present = set(os.listdir(out)) - {MANIFEST}
    assert {"0", "constant", "system", "log.thermoDemFoam", "checkpoint.npz", "coupling.csv"} <= present
    assert present <= listed(out)
    before = tree(out)
    refused(coupling("run", case, "--out", out, "--end-time", "0.003"), "earlier thermodem output")
    (out / "2024").mkdir()
    refused(coupling("run", case, "--out", out, "--end-time", "0.003", "--overwrite"), "2024/")
    (out / "2024").rmdir()
    assert tree(out) == before
    (out / "0.002").mkdir()       # an OpenFOAM-like time folder the run did not write: not ours
    refused(coupling("run", case, "--out", out, "--overwrite"), "0.002/")
    (out / "0.002").rmdir()
    r = coupling("run", case, "--out", out, "--end-time", "0.002", "--quiet", "--overwrite")
    assert r.returncode == 0, r.stderr
    d = np.atleast_1d(np.genfromtxt(out / "coupling.csv", delimiter=",", names=True))
    assert d["time"][-1] == pytest.approx(0.002, abs=1e-12)
    assert set(os.listdir(out)) - {MANIFEST} <= listed(out)


# --------------------------------------------------------------------------- Python API

def test_api_run_refuses_a_users_folder(tmp_path):
    from dem import Simulation
    from dem.outdir import OutputFolderError
    out = user_folder(tmp_path / "mine")
    before = tree(out)
    sim = Simulation.from_file(str(SCENE))
    with pytest.raises(OutputFolderError, match="holds files this tool did not write"):
        sim.run(end_time=2e-5, out_dir=str(out), progress=False)
    assert tree(out) == before
    sim.run(end_time=2e-5, out_dir=str(tmp_path / "new"), progress=False)   # a new folder is fine,
    sim.run(end_time=4e-5, out_dir=str(tmp_path / "new"), progress=False)   # and continuing it
    assert listed(tmp_path / "new") == set(os.listdir(tmp_path / "new")) - {MANIFEST}


_SAVER = """
import os, sys
from dem.outdir import claim, claim_folder
out, tag = sys.argv[1], sys.argv[2]
claim_folder(out, restart=True, reuse=True, command="dem render", what="--out")
for k in range(60):
    name = os.path.join(out, f"frame_{tag}_{k:03d}.png")
    claim(name)                       # recorded in the manifest (merged with the others')
    open(name, "w").close()
"""


def test_manifest_saved_by_several_processes_at_once(scene, tmp_path):
    """Processes that write into one output folder at once (``dem render`` beside a running
    ``dem run``) each merge their entries into the manifest. With one shared temporary file for
    the manifest, two saving at the same moment made one of them fail ("cannot prepare the
    output folder: No such file or directory": 3 of 4 such processes failed) and entries
    could be lost. Four real processes, 60 entries each, at once: every process ends normally,
    the manifest lists all 240 entries (so --overwrite removes them all) and no temporary file
    is left behind."""
    out = tmp_path / "out"
    r = dem("run", scene, "--out", out, "--end-time", "1e-4", "--quiet", "--threads", "1")
    assert r.returncode == 0, r.stderr
    procs = [subprocess.Popen([sys.executable, "-c", _SAVER, str(out), str(p)], env=_env(),
                              stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True) for p in range(4)]
    for p in procs:
        _, err = p.communicate(timeout=120)
        assert p.returncode == 0, err
    listed = set(json.loads((out / MANIFEST).read_text())["entries"])
    frames = {f"frame_{p}_{k:03d}.png" for p in range(4) for k in range(60)}
    assert frames <= listed, sorted(frames - listed)[:5]
    assert not [n for n in os.listdir(out) if n.startswith(".tmp_thermodem_") or n.endswith(".tmp")]
    r = dem("run", scene, "--out", out, "--end-time", "1e-4", "--quiet", "--threads", "1", "--overwrite")
    assert r.returncode == 0, r.stderr
    assert not [n for n in os.listdir(out) if n.startswith("frame_")]
