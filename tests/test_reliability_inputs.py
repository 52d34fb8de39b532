"""Every bad input gets one named error before anything is written, never a traceback.

Through the command line, as a user runs it (``python -m dem.cli check|run``,
``python -m coupling.run check|run``): each broken input asserts exit status 2, a message
naming the file and the key (or line and column of a packing file) and saying what is
allowed, no ``Traceback``, and that no output folder was created. docs/reliability/inputs.md
lists the same cases with their messages.
"""
import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

ROOT = Path(__file__).resolve().parents[1]
ENV = dict(os.environ, PYTHONPATH=str(ROOT) + os.pathsep + os.environ.get("PYTHONPATH", ""))

SCENE = """\
[simulation]
time_step = 1e-6
end_time = 1e-4
output_interval = 1e-5

[domain]
min = [0.0, 0.0, 0.0]
max = [0.01, 0.01, 0.01]

[[materials]]
name = "glass"
density = 2500.0
youngs_modulus = 1e7
poisson_ratio = 0.25
restitution = 0.5
friction = 0.3
thermal_conductivity = 1.0
heat_capacity = 840.0

[[particles]]
material = "glass"
file = "bed.csv"

[[walls]]
type = "plane"
point = [0.0, 0.0, 0.0]
normal = [0.0, 0.0, 1.0]
material = "glass"
"""
THERMAL = '\n[thermal]\ninitial_temperature = 300.0\ndirect = "batchelor_obrien"\n'
HEADER = "x,y,z,radius,vx,vy,vz\n"
ROW1 = "0.002,0.002,0.002,0.001,0,0,0\n"
ROW2 = "0.005,0.002,0.002,0.001,0,0,-0.1\n"
GOOD_CSV = HEADER + ROW1 + ROW2


def scene(*edits, extra=""):
    """The base scene with (old, new) text replacements applied and ``extra`` appended."""
    s = SCENE
    for old, new in edits:
        assert old in s, old
        s = s.replace(old, new)
    return s + extra


def csv(*rows, header=HEADER):
    return header + "".join(rows)


def npz(**arrays):
    def write(path):
        np.savez(path, **arrays)
    return write


def explicit(positions, extra=""):
    """Particles given in the scene instead of bed.csv."""
    return ('file = "bed.csv"', f"positions = {positions}\nradius = 0.001{extra}")


def materialize(tmp, files):
    for name, content in files.items():
        p = tmp / name
        if content is None:
            p.mkdir()
        elif callable(content):
            content(p)
        elif isinstance(content, bytes):
            p.write_bytes(content)
        else:
            p.write_text(content)


def cli(module, *args, cwd):
    return subprocess.run([sys.executable, "-m", module, *map(str, args)], cwd=cwd, env=ENV,
                          capture_output=True, text=True, timeout=300)


def assert_refused(r, *phrases):
    assert r.returncode == 2, (r.returncode, r.stdout, r.stderr)
    assert "Traceback" not in r.stderr, r.stderr
    for ph in phrases:
        assert ph in r.stderr, f"{ph!r} not in {r.stderr!r}"


# (id, files besides s.toml's default, scene text, phrases of the message: file, key, what is allowed)
CASES = [
    # packing file (CSV): every cell
    ("csv-nan", {"bed.csv": csv(ROW1, "0.005,0.002,0.002,0.001,0,0,nan\n")}, SCENE,
     ["s.toml: particles[0].file: bed.csv: line 3, column vz: not a finite number ('nan')"]),
    ("csv-inf", {"bed.csv": csv(ROW1, "0.005,0.002,0.002,0.001,inf,0,0\n")}, SCENE,
     ["particles[0].file: bed.csv: line 3, column vx: not a finite number ('inf')"]),
    ("csv-empty-cell", {"bed.csv": csv(ROW1, "0.005,,0.002,0.001,0,0,0\n")}, SCENE,
     ["particles[0].file: bed.csv: line 3, column y: empty cell; every cell must be a finite number"]),
    ("csv-text-cell", {"bed.csv": csv(ROW1, "0.005,0.002,abc,0.001,0,0,0\n")}, SCENE,
     ["particles[0].file: bed.csv: line 3, column z: not a number ('abc')"]),
    ("csv-header-only", {"bed.csv": HEADER}, SCENE,
     ["particles[0].file: bed.csv: no particles: only the header line"]),
    ("csv-empty-file", {"bed.csv": ""}, SCENE, ["particles[0].file: bed.csv: empty file", "need x, y, z, radius"]),
    ("csv-short-row", {"bed.csv": csv(ROW1, "0.005,0.002\n")}, SCENE,
     ["particles[0].file: bed.csv: line 3: 2 cells, the header has 7"]),
    ("csv-unknown-column", {"bed.csv": csv("0.002,0.002,0.002,0.001,0,0,0\n", header="x,y,z,radius,vx,vy,vzz\n")},
     SCENE, ["particles[0].file: bed.csv: column 'vzz': unknown column; allowed: x, y, z, radius, vx"]),
    ("csv-not-utf8", {"bed.csv": b"x,y,z,radius\n\xff\xfe,1,1,1\n"}, SCENE,
     ["particles[0].file: bed.csv: line 2: not UTF-8 text"]),
    ("csv-negative-radius", {"bed.csv": csv(ROW1, "0.005,0.002,0.002,-0.001,0,0,0\n")}, SCENE,
     ["particles[0].file: bed.csv: line 3, column radius: must be > 0, got -0.001"]),
    ("csv-temperature-below-0K", {"bed.csv": "x,y,z,radius,temperature\n0.002,0.002,0.002,0.001,-50\n"},
     scene(extra=THERMAL), ["particles[0].file: bed.csv: line 2, column temperature: must be > 0 K, got -50.0"]),
    ("csv-duplicate-id", {"bed.csv": "id,x,y,z,radius\n4,0.002,0.002,0.002,0.001\n4,0.005,0.002,0.002,0.001\n"},
     SCENE, ["particles[0].file: bed.csv: line 3, column id: id 4 repeats (also on line 2); ids must be unique"]),
    ("csv-is-a-folder", {"bed.csv": None}, SCENE, ["particles[0].file: bed.csv: is a folder"]),
    # packing file (NPZ)
    ("npz-lengths", {"bed.npz": npz(x=[0.002, 0.005], y=[0.002, 0.002], z=[0.002, 0.002], radius=[0.001],
                                    vx=[0.0, 0.0])},
     scene(('"bed.csv"', '"bed.npz"')), ["particles[0].file: bed.npz: array 'radius': has 1 values but 'x' has 2"]),
    ("npz-nan", {"bed.npz": npz(position=[[0.002, 0.002, 0.002], [0.005, 0.002, 0.002]], radius=[0.001, 0.001],
                                velocity=[[0.0, 0.0, 0.0], [0.0, np.nan, 0.0]])},
     scene(('"bed.csv"', '"bed.npz"')), ["particles[0].file: bed.npz: row 1, column vy: not a finite number (nan)"]),
    ("npz-corrupt", {"bed.npz": b"PK\x03\x04 not really a zip"}, scene(('"bed.csv"', '"bed.npz"')),
     ["particles[0].file: bed.npz: not a readable NPZ file"]),
    # the scene file itself
    ("scene-not-utf8", {}, SCENE.encode() + b"# caf\xe9\n",
     [f"s.toml: line {SCENE.count(chr(10)) + 1}: not UTF-8 text (byte 0xe9)"]),
    ("scene-is-a-folder", {"s.toml": None}, None, ["s.toml: is a folder; give the scene file"]),
    ("scene-nan-position", {}, scene(explicit("[[0.002, 0.002, 0.002], [0.005, 0.002, nan]]")),
     ["s.toml: particles[0].positions[1]: must be finite numbers (no nan or inf), got [0.005, 0.002, nan]"]),
    ("scene-inf-velocity", {}, scene(explicit("[[0.002, 0.002, 0.002]]", "\nvelocities = [[0.0, 0.0, -inf]]")),
     ["s.toml: particles[0].velocities[0]: must be finite numbers (no nan or inf)"]),
    # walls and the periodic domain
    ("wall-normal-away", {"bed.csv": GOOD_CSV}, scene(("normal = [0.0, 0.0, 1.0]", "normal = [0.0, 0.0, -1.0]")),
     ["s.toml: walls[0].normal: points away from every particle", "use [0.0, 0.0, 1.0]"]),
    ("wall-on-periodic-axis", {"bed.csv": GOOD_CSV},
     scene(("max = [0.01, 0.01, 0.01]", "max = [0.01, 0.01, 0.01]\nperiodic = [false, false, true]")),
     ["s.toml: walls[0].normal: an unbounded plane across the periodic axis z"]),
    ("periodic-shorter-than-diameters", {"bed.csv": csv(ROW1)},
     scene(("max = [0.01, 0.01, 0.01]", "max = [0.003, 0.01, 0.01]\nperiodic = [true, false, false]")),
     ["s.toml: domain.periodic: axis x is periodic with length 0.003 m, less than two of the largest particle "
      "diameters"]),
    ("cylinder-inside-all-outside", {"bed.csv": GOOD_CSV},
     scene(extra='\n[[walls]]\ntype = "cylinder"\npoint = [0.05, 0.05, 0.0]\naxis = [0.0, 0.0, 1.0]\n'
                 'radius = 0.01\nmaterial = "glass"\n'),
     ["s.toml: walls[1].inside: every particle lies outside the cylinder"]),
    # temperatures
    ("wall-table-nan", {"bed.csv": GOOD_CSV},
     scene(('normal = [0.0, 0.0, 1.0]\n', 'normal = [0.0, 0.0, 1.0]\nthermal = {condition = "fixed_temperature", '
                                          'table = [[0.0, 300.0], [1.0, nan]]}\n'), extra=THERMAL),
     ["s.toml: walls[0].thermal.table[1]: [time, temperature] must be finite with temperature > 0 K"]),
    ("temperature-below-0K", {"bed.csv": GOOD_CSV}, scene(('file = "bed.csv"', 'file = "bed.csv"\ntemperature = -50.0'),
                                                          extra=THERMAL),
     ["s.toml: particles[0].temperature: must be in (0, inf), got -50.0"]),
    # insertion
    ("count-1e9", {}, scene(("max = [0.01, 0.01, 0.01]", "max = [2.0, 2.0, 2.0]"),
                            ('file = "bed.csv"', 'count = 1000000000\nradius = 0.0005\n'
                                                 'region = {type = "box", min = [0, 0, 0], max = [2, 2, 2]}')),
     ["s.toml: particles[0].count: inserting 1000000000 particles needs about", "MemAvailable"]),
    ("count-float", {}, scene(('file = "bed.csv"', 'count = 1e9\nradius = 0.001\n'
                                                   'region = {type = "box", min = [0, 0, 0], max = [0.01, 0.01, 0.01]}')),
     ["s.toml: particles[0].count: must be an integer, got 1000000000.0"]),
    ("count-beyond-densest-packing", {}, scene(('file = "bed.csv"', 'count = 500\nradius = 0.001\n'
                                               'region = {type = "box", min = [0, 0, 0], max = [0.01, 0.01, 0.01]}')),
     ["s.toml: particles[0].count: 500 spheres", "more than the densest packing"]),
    ("region-outside-domain", {}, scene(('file = "bed.csv"', 'count = 3\nradius = 0.001\n'
                                        'region = {type = "box", min = [0, 0, 0.02], max = [0.01, 0.01, 0.03]}')),
     ["s.toml: particles[0].region: reaches outside the domain on axis z"]),
    # plausible slips
    ("negative-radius", {}, scene(('file = "bed.csv"', "positions = [[0.002, 0.002, 0.002]]\nradius = -0.001")),
     ["s.toml: particles[0].radius: must be in (0, inf), got -0.001"]),
    ("zero-density", {"bed.csv": GOOD_CSV}, scene(("density = 2500.0", "density = 0.0")),
     ["s.toml: materials[0].density: must be in (0, inf), got 0.0"]),
    ("missing-material-name", {"bed.csv": GOOD_CSV}, scene(('name = "glass"\n', "")),
     ["s.toml: materials[0].name: missing required key"]),
    ("duplicate-material", {"bed.csv": GOOD_CSV},
     scene(extra='\n[[materials]]\nname = "glass"\ndensity = 1.0\nyoungs_modulus = 1e7\npoisson_ratio = 0.3\n'
                 'restitution = 0.5\n'), ["s.toml: materials[1].name: duplicate material name 'glass'"]),
    ("typo-key", {"bed.csv": GOOD_CSV}, scene(("end_time", "endtime")),
     ["s.toml: simulation.endtime: unknown key; allowed keys:", "end_time"]),
    ("string-for-number", {"bed.csv": GOOD_CSV}, scene(("time_step = 1e-6", 'time_step = "1e-6"')),
     ["s.toml: simulation.time_step: must be a number, got '1e-6'"]),
    ("empty-particles-table", {}, scene(('material = "glass"\nfile = "bed.csv"\n', "")),
     ["s.toml: particles[0].material: missing required key"]),
]


# `dem check` of every case in one process (one interpreter start instead of ~40): the CLI's
# main() per case folder, its exit status, stdout and stderr captured, any exception that
# escapes printed as a traceback into the captured stderr
BATCH = r"""
import contextlib, io, json, os, sys, traceback
from dem.cli import main
res = {}
for d in sys.argv[1:]:
    os.chdir(d)
    err, out = io.StringIO(), io.StringIO()
    with contextlib.redirect_stderr(err), contextlib.redirect_stdout(out):
        try:
            rc = main(["check", "s.toml"])
        except SystemExit as e:
            rc = e.code
        except BaseException:
            rc = None
            traceback.print_exc()
    res[d] = dict(rc=rc, stderr=err.getvalue(), stdout=out.getvalue(), files=sorted(os.listdir(d)))
print(json.dumps(res))
"""
# these also run as their own `python -m dem.cli check` process
SEPARATE = {"csv-nan", "scene-not-utf8", "wall-normal-away", "count-1e9"}


def _write_case(d, files, text):
    d.mkdir()
    if text is not None:
        (d / "s.toml").write_bytes(text if isinstance(text, bytes) else text.encode())
    materialize(d, files)
    return sorted(os.listdir(d))


@pytest.fixture(scope="module")
def batch(tmp_path_factory):
    root = tmp_path_factory.mktemp("cases")
    before = {name: _write_case(root / name, files, text) for name, files, text, _ in CASES}
    r = subprocess.run([sys.executable, "-c", BATCH, *[str(root / c[0]) for c in CASES]], env=ENV,
                       capture_output=True, text=True, timeout=600)
    assert r.returncode == 0, r.stderr
    res = json.loads(r.stdout)
    return {name: (res[str(root / name)], before[name]) for name in before}


@pytest.mark.parametrize("name, files, text, phrases", CASES, ids=[c[0] for c in CASES])
def test_dem_check_refuses(batch, tmp_path, name, files, text, phrases):
    res, before = batch[name]
    r = subprocess.CompletedProcess([], res["rc"], res["stdout"], res["stderr"])
    assert_refused(r, *phrases)
    assert r.stderr.count("\n") == 1, r.stderr          # one line
    assert res["files"] == before                       # nothing written
    if name in SEPARATE:
        before = _write_case(tmp_path / "c", files, text)
        r = cli("dem.cli", "check", "s.toml", cwd=tmp_path / "c")
        assert_refused(r, *phrases)
        assert r.stderr.split(" needs about")[0] == res["stderr"].split(" needs about")[0]  # figures vary
        assert sorted(os.listdir(tmp_path / "c")) == before


def test_memory_of_a_huge_domain_grows_with_the_particles_not_the_domain(tmp_path):
    """3 beads in a 20 m domain (6e9 cells of the bead size): the neighbour grid stores only
    the occupied cells, so the estimate made before anything is allocated stays below 1 MiB
    (it was 89 GiB with a grid over the whole domain) and `dem check` accepts the scene."""
    from dem.memory import scene_bytes
    from dem.scene import load
    f = tmp_path / "s.toml"
    f.write_text(scene(("max = [0.01, 0.01, 0.01]", "max = [20.0, 20.0, 20.0]"),
                       explicit("[[0.002, 0.002, 0.002], [0.005, 0.002, 0.002], [0.008, 0.002, 0.002]]")))
    est = scene_bytes(load(f))
    assert est["cells"] <= 8 * 3 + 4097
    assert est["total"] < 2**20
    r = cli("dem.cli", "check", "s.toml", cwd=tmp_path)
    assert r.returncode == 0, r.stderr
    assert "Traceback" not in r.stderr and "memory estimated before allocating:" in r.stdout


def test_dem_check_reports_the_memory_estimate(tmp_path):
    (tmp_path / "s.toml").write_text(SCENE)
    (tmp_path / "bed.csv").write_text(GOOD_CSV)
    r = cli("dem.cli", "check", "s.toml", cwd=tmp_path)
    assert r.returncode == 0, r.stderr
    assert "memory estimated before allocating:" in r.stdout and "available:" in r.stdout


# ----------------------------------------------------------------------------- dem run
RUN_CASES = [
    ("nan-in-packing", GOOD_CSV.replace("-0.1", "nan"), [], ["particles[0].file: bed.csv: line 3, column vz"]),
    ("end-time-nan", GOOD_CSV, ["--end-time", "nan"],
     ["argument --end-time: must be a finite number of seconds >= 0, got 'nan'"]),
    ("end-time-negative", GOOD_CSV, ["--end-time", "-1"], ["argument --end-time: must be a finite number"]),
]


@pytest.mark.parametrize("name, bed, extra, phrases", RUN_CASES, ids=[c[0] for c in RUN_CASES])
def test_dem_run_refuses_before_writing(tmp_path, name, bed, extra, phrases):
    (tmp_path / "s.toml").write_text(SCENE)
    (tmp_path / "bed.csv").write_text(bed)
    r = cli("dem.cli", "run", "s.toml", "--out", tmp_path / "o", "--quiet", *extra, cwd=tmp_path)
    assert_refused(r, *phrases)
    assert not (tmp_path / "o").exists()
    assert sorted(os.listdir(tmp_path)) == ["bed.csv", "s.toml"]   # nor the default out/s


def test_dem_run_out_is_a_file(tmp_path):
    (tmp_path / "s.toml").write_text(SCENE)
    (tmp_path / "bed.csv").write_text(GOOD_CSV)
    (tmp_path / "o").write_text("my notes\n")
    r = cli("dem.cli", "run", "s.toml", "--out", "o", "--quiet", cwd=tmp_path)
    assert_refused(r, "--out o is a file, not a folder")
    assert (tmp_path / "o").read_text() == "my notes\n"


def test_dem_run_out_read_only(tmp_path):
    """--out inside a folder the user cannot write: a chmod 555 folder, or (as root, who writes
    anywhere) a read-only tmpfs, where access() fails for root too."""
    (tmp_path / "s.toml").write_text(SCENE)
    (tmp_path / "bed.csv").write_text(GOOD_CSV)
    ro = tmp_path / "ro"
    ro.mkdir()
    if os.geteuid() == 0:
        m = subprocess.run(["mount", "-t", "tmpfs", "-o", "ro,size=64k", "tmpfs", str(ro)],
                           capture_output=True, text=True)
        if m.returncode != 0:
            pytest.skip(f"root writes anywhere and no read-only tmpfs can be mounted: {m.stderr.strip()}")
        undo = ["umount", "-l", str(ro)]
    else:
        ro.chmod(0o555)
        undo = ["chmod", "755", str(ro)]
    try:
        r = cli("dem.cli", "run", "s.toml", "--out", ro / "o", "--quiet", cwd=tmp_path)
        assert_refused(r, "cannot create --out", "is not writable (permission denied)")
        assert not (ro / "o").exists()
    finally:
        subprocess.run(undo, capture_output=True)


# ----------------------------------------------------------------------------- coupled cases
CASE = ROOT / "openfoam_cases" / "packed_bed_heating"


def _edit(rel, old, new):
    def f(d):
        p = d / rel
        t = p.read_text()
        assert old in t, (rel, old)
        p.write_text(t.replace(old, new))
    return f


COUPLED = [
    ("coupling-typo", _edit("coupling.toml", "coupling_interval = 1", "coupling_intervall = 1"),
     ["coupling.toml: coupling.coupling_intervall: unknown key; valid keys:"]),
    ("coupling-string-for-number", _edit("coupling.toml", "output_interval = 0.1", 'output_interval = "0.1"'),
     ["coupling.toml: coupling.output_interval: must be a number, got '0.1'"]),
    ("coupling-nan", _edit("coupling.toml", "output_interval = 0.1", "output_interval = nan"),
     ["coupling.toml: coupling.output_interval: must be a finite number, got nan"]),
    ("coupling-not-utf8", lambda d: (d / "coupling.toml").write_bytes(b"[coupling]\n# \xff\n"),
     ["coupling.toml: line 2: not UTF-8 text"]),
    ("coupling-is-a-folder", lambda d: ((d / "coupling.toml").unlink(), (d / "coupling.toml").mkdir()),
     ["coupling.toml: is a folder"]),
    ("dem-packing-nan", lambda d: (d / "bed.csv").write_text((d / "bed.csv").read_text() + "0.002,0.002,nan,0.002\n"),
     ["dem.toml: particles[0].file: bed.csv: line 542, column z: not a finite number ('nan')"]),
    ("gas-temperature-below-0K", _edit("0/T", "internalField   uniform 300;", "internalField   uniform -50;"),
     ["0/T: internalField: 'uniform -50': a temperature must be > 0 K"]),
]


@pytest.mark.parametrize("name, edit, phrases", COUPLED, ids=[c[0] for c in COUPLED])
def test_coupling_check_refuses(tmp_path, name, edit, phrases):
    case = tmp_path / "case"
    shutil.copytree(CASE, case)
    edit(case)
    r = cli("coupling.run", "check", case, cwd=tmp_path)
    assert_refused(r, "coupling: error:", *phrases)
    assert sorted(os.listdir(tmp_path)) == ["case"]


STEPPED_INLET = """    inlet
    {
        type uniformFixedValue;
        uniformValue table ((0 (0 0 0.5)) (0.05 (0 0 0.5)) (0.051 (0 0 0.7)));
        value uniform (0 0 0.5);
    }"""


def test_coupling_check_takes_an_inlet_whose_type_starts_with_uniform(tmp_path):
    """OpenFOAM's own time-varying inlet (``uniformFixedValue`` with a table: the stepped inlet of
    benchmarks/fluidization_curve.py) passes the check of the ``uniform`` values: its type is not
    a value (it was read as 'uniform FixedValue', "not a number", and the case refused); a
    ``uniform`` value beside it is still checked."""
    case = tmp_path / "case"
    shutil.copytree(CASE, case)
    _edit("0/U", "    inlet\n    {\n        type fixedValue;\n        value uniform (0 0 0.5);\n    }",
          STEPPED_INLET)(case)
    r = cli("coupling.run", "check", case, cwd=tmp_path)
    assert r.returncode == 0, (r.stdout, r.stderr)
    assert "Traceback" not in r.stderr
    _edit("0/U", "value uniform (0 0 0.5);\n    }", "value uniform (0 0 nan);\n    }")(case)
    assert_refused(cli("coupling.run", "check", case, cwd=tmp_path), "0/U: boundaryField.inlet.value: "
                                                                     "'uniform (0 0 nan)' is not a finite number")


@pytest.mark.parametrize("args, phrase", [
    (["--end-time", "inf"], "argument --end-time: must be a finite number of seconds >= 0, got 'inf'"),
    (["--out", "notes.txt"], "notes.txt is a file, not a folder"),
], ids=["end-time-inf", "out-is-a-file"])
def test_coupling_run_refuses_before_writing(tmp_path, args, phrase):
    case = tmp_path / "case"
    shutil.copytree(CASE, case)
    (tmp_path / "notes.txt").write_text("mine\n")
    r = cli("coupling.run", "run", case, *args, cwd=tmp_path)
    assert_refused(r, phrase)
    assert sorted(os.listdir(tmp_path)) == ["case", "notes.txt"]
    assert (tmp_path / "notes.txt").read_text() == "mine\n"
