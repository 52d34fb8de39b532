"""Particles that enter and leave (issue 50, dem.flow): [[inlets]] and [[outlets]] through the
command line as a user runs them.

What is asserted and why the tolerances:
* the number is exact: particles(t) = N0 + n_in - n_out at every history row, the ids unique and
  never reused (every new id above the scene's, none seen twice in the run);
* a rate is held on the mean: after k insertions n_in = floor(k rate interval) minus what is still
  owed, at most one batch (a batch that cannot be placed is owed to the next);
* the mass rate: mass_in stays within one particle mass of mass_rate x time (the debt carries the rest);
* the energy ledger closes: thermal_energy(t) - thermal_energy(0) = heat through the wall + H_in -
  H_out to 1e-9 of the enthalpy moved (the history's 12 significant digits);
* a run stopped and continued is bit-identical across insertions and removals; 1 rank and 2 ranks
  give the same particles (ids) and positions within 1e-10 m (the ranks sum the forces in another
  order: the tolerance of tests/test_parallel.py);
* every bad input is refused by `dem check`/`dem run` with exit 2, the file and the key named.
"""
import math
import os
import shutil
import signal
import subprocess
import sys
import time

import numpy as np
import pytest

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))

SCENE = """
[simulation]
time_step = 1e-5
end_time = {end}
output_interval = 0.01
checkpoint_interval = 0.05
seed = 1

[domain]
min = [0.0, 0.0, 0.0]
max = [0.04, 0.02, 0.06]
periodic = [false, true, false]

[[materials]]
name = "glass"
density = 2500.0
youngs_modulus = 1e7
poisson_ratio = 0.3
restitution = 0.5
friction = 0.3
heat_capacity = 840.0
thermal_conductivity = 1.0

[[particles]]
material = "glass"
count = 40
radius = 0.001
region = {{ type = "box", min = [0.0, 0.0, 0.0], max = [0.04, 0.02, 0.015] }}

[[walls]]
type = "plane"
name = "floor"
point = [0.0, 0.0, 0.0]
normal = [0.0, 0.0, 1.0]
material = "glass"
thermal = {{ condition = "fixed_temperature", temperature = 350.0 }}

[[walls]]
type = "plane"
name = "back"
point = [0.0, 0.0, 0.0]
normal = [1.0, 0.0, 0.0]
material = "glass"

[[inlets]]
name = "feed"
material = "glass"
radius = {{ distribution = "uniform", min = 0.0008, max = 0.0012 }}
{rate}
region = {{ type = "box", min = [0.0, 0.0, 0.04], max = [0.02, 0.02, 0.06] }}
velocity = [0.3, 0.0, 0.0]
temperature = 400.0
interval = 0.01

[[outlets]]
name = "side"
type = "face"
face = "xmax"

[thermal]
initial_temperature = 300.0
direct = "batchelor_obrien"
"""
RATE = "rate = 1000.0"


def env(**extra):
    e = dict(os.environ, PYTHONPATH=ROOT + os.pathsep + os.environ.get("PYTHONPATH", ""))
    e.update(extra)
    return e


def dem(*args, timeout=600):
    return subprocess.run([sys.executable, "-m", "dem", *map(str, args)], capture_output=True, text=True,
                          env=env(), timeout=timeout)


def write(tmp_path, name="flow.toml", end=0.2, rate=RATE):
    p = tmp_path / name
    p.write_text(SCENE.format(end=end, rate=rate))
    return p


def history(out):
    return np.genfromtxt(os.path.join(out, "history.csv"), delimiter=",", names=True)


def final(out):
    from dem.final import read
    return dict(read(os.path.join(out, "final.npz")))


@pytest.fixture(scope="module")
def run(tmp_path_factory):
    """One run of the scene (0.2 s: 20 insertions, particles leaving by the open face x = 0.04)."""
    tmp = tmp_path_factory.mktemp("flow")
    f = write(tmp)
    out = tmp / "out"
    p = dem("run", f, "--out", out, "--quiet", "--threads", "1")
    assert p.returncode == 0, p.stderr
    return f, out, p


def test_number_mass_and_ids_are_exact(run):
    f, out, p = run
    h = history(out)
    n0 = 40
    assert np.array_equal(h["particles"], n0 + h["n_in_feed"] - h["n_out_side"])
    assert h["n_out_side"][-1] > 50     # particles did leave by the face (0.3 m/s for 0.2 s)
    fa = final(out)
    ids = fa["id"]
    assert ids.size == int(h["particles"][-1]) and np.unique(ids).size == ids.size
    assert np.all(fa["position"][:, 0] <= 0.04 + 0.3 * 50 * 1e-5 * 10)   # none far beyond the open face
    # mass: what is there is what came in less what left
    m = fa["radius"] ** 3 * 4.0 / 3.0 * math.pi * 2500.0
    m0 = 40 * 4.0 / 3.0 * math.pi * 1e-9 * 2500.0
    assert abs(m.sum() - (m0 + h["mass_in_feed"][-1] - h["mass_out_side"][-1])) <= 1e-12 * m0 * 100


def test_rate_is_held_on_the_mean(run):
    f, out, p = run
    h = history(out)
    k = np.round(h["time"] / 0.01)        # insertions done by each row (one every 10 ms from t = 10 ms)
    asked = np.floor(k * 10.0 + 1e-9)     # 1000 /s x 10 ms per batch
    assert np.all(h["n_in_feed"] <= asked)
    assert np.all(asked - h["n_in_feed"] <= 10)   # at most one batch owed
    assert h["n_in_feed"][-1] >= 0.95 * asked[-1]


def test_energy_ledger_closes_with_inflow_and_outflow(run):
    f, out, p = run
    h = history(out)
    lhs = h["thermal_energy"] - h["thermal_energy"][0]
    rhs = h["E_wall_floor"] + h["H_in"] - h["H_out"]
    assert h["H_in"][-1] > 0 and h["H_out"][-1] > 0 and h["E_wall_floor"][-1] != 0
    # the enthalpy in is m c T of what came in: 400 K, c = 840
    assert abs(h["H_in"][-1] - h["mass_in_feed"][-1] * 840.0 * 400.0) <= 1e-9 * h["H_in"][-1]
    assert np.max(np.abs(lhs - rhs)) <= 1e-9 * h["H_in"][-1]


def test_mass_rate_within_one_particle(tmp_path):
    """A region that clears between insertions (1 m/s down, 20 ms apart): each batch takes the
    draws of the size distribution until the next would pass the mass asked, so the mass in stays
    within one particle of mass_rate x time."""
    f = write(tmp_path, end=0.1, rate="mass_rate = 0.05")
    f.write_text(f.read_text().replace("interval = 0.01", "interval = 0.02").replace(
        "velocity = [0.3, 0.0, 0.0]", "velocity = [0.0, 0.0, -1.0]"))
    out = tmp_path / "out"
    p = dem("run", f, "--out", out, "--quiet", "--threads", "1")
    assert p.returncode == 0, p.stderr
    assert "could not be placed" not in p.stdout + p.stderr
    h = history(out)
    mmax = 4.0 / 3.0 * math.pi * 0.0012 ** 3 * 2500.0
    k = np.floor(h["time"] / 0.02 + 1e-9)
    assert np.all(np.abs(h["mass_in_feed"] - 0.05 * 0.02 * k) <= mmax)
    assert h["mass_in_feed"][-1] > 0.05 * 0.1 - mmax


def test_a_rate_the_region_cannot_take_is_said_with_what_fits(tmp_path):
    """Batches that the region is not yet clear for (300 particles every 10 ms, 0.16 of the region
    each, moving 3 mm of its 20 mm between two): the debt passes a batch and the run says so once,
    and goes on."""
    f = write(tmp_path, end=0.05, rate="rate = 30000.0")
    out = tmp_path / "out"
    p = dem("run", f, "--out", out, "--quiet", "--threads", "1")
    assert p.returncode == 0, p.stderr
    said = [ln for ln in (p.stdout + p.stderr).splitlines() if "inlet feed" in ln]
    assert len(said) == 1 and "could not be placed" in said[0] and "owed" in said[0], said
    h = history(out)
    assert h["n_in_feed"][-1] < 0.9 * 30000.0 * 0.05


def test_ids_never_reused_across_the_run(tmp_path):
    """Every id a run ever held, from the VTK frames: new ids above the scene's, and an id that left
    never comes back."""
    f = write(tmp_path, end=0.1)
    f.write_text(f.read_text().replace("[thermal]", "[output]\nvtk = true\n\n[thermal]"))
    out = tmp_path / "out"
    p = dem("run", f, "--out", out, "--quiet", "--threads", "1")
    assert p.returncode == 0, p.stderr
    from dem.output import read_frames
    frames = read_frames(str(out))
    assert len(frames) >= 10
    seen, gone = set(), set()
    for _, _, _, data in frames:
        ids = set(np.asarray(data["id"]).astype(np.int64).tolist())
        assert not (ids & gone)
        gone |= seen - ids
        seen |= ids
    assert min(seen - set(range(1, 41))) > 40 and gone


def test_stop_and_continue_is_bit_identical_across_insertions(run, tmp_path):
    f, out, p = run
    part = tmp_path / "part"
    p = subprocess.Popen([sys.executable, "-m", "dem", "run", str(f), "--out", str(part), "--quiet", "--threads", "1"],
                         env=env(THERMODEM_CHUNK_SECONDS="0.05"), stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                         text=True)
    t0 = time.monotonic()
    while not (part / "checkpoint.npz").exists() or _rows(part) < 8:
        assert p.poll() is None, p.communicate()
        assert time.monotonic() - t0 < 300
        time.sleep(0.02)
    p.send_signal(signal.SIGINT)
    _, err = p.communicate(timeout=120)
    assert p.returncode == 130, err
    q = dem("run", f, "--out", part, "--quiet", "--threads", "1", "--restart", part / "checkpoint.npz")
    assert q.returncode == 0, q.stderr
    a, b = final(out), final(part)
    for k in ("id", "position", "velocity", "angular_velocity", "radius", "temperature"):
        assert np.array_equal(a[k], b[k]), k
    ha, hb = history(out), history(part)
    common = np.isin(hb["time"], ha["time"])
    for col in ("particles", "n_in_feed", "n_out_side", "H_in", "H_out", "thermal_energy"):
        assert np.array_equal(hb[col][common], ha[col]), col


def _rows(out):
    try:
        with open(out / "history.csv") as fh:
            return len(fh.readlines()) - 1
    except OSError:
        return 0


def test_one_rank_and_two_ranks_insert_the_same_particles(run, tmp_path):
    if shutil.which("mpirun") is None:
        pytest.skip("needs Open MPI (mpirun)")
    f, out, _ = run
    e = env(OMPI_ALLOW_RUN_AS_ROOT="1", OMPI_ALLOW_RUN_AS_ROOT_CONFIRM="1", OMPI_MCA_rmaps_base_oversubscribe="1",
            OMPI_MCA_mpi_yield_when_idle="1")
    two = tmp_path / "np2"
    p = subprocess.run(["mpirun", "-np", "2", sys.executable, "-m", "dem", "run", str(f), "--out", str(two),
                        "--quiet", "--threads", "1"], capture_output=True, text=True, env=e, timeout=900)
    assert p.returncode == 0, p.stderr
    a, b = final(out), final(two)
    assert np.array_equal(a["id"], b["id"])
    # one process keeps its lists when particles only leave (dem.stepper.Stepper.remove_rows), the
    # ranks build theirs again: the same forces summed in another order, whose round-off the
    # collisions then grow (1.8e-10 m measured over this run, 1e-7 of a radius)
    assert np.abs(a["position"] - b["position"]).max() <= 1e-8
    assert np.abs(a["temperature"] - b["temperature"]).max() <= 1e-8
    ha, hb = history(out), history(two)
    for col in ("particles", "n_in_feed", "n_out_side"):
        assert np.array_equal(ha[col], hb[col]), col
    assert np.allclose(hb["H_in"], ha["H_in"], rtol=1e-12, atol=0)


def test_inlet_never_places_a_particle_in_a_wall_or_a_particle(tmp_path):
    """An inlet region holding the resting bed and cut by an inclined wall (x + z = 0.085): each
    history row right after an insertion (the same steps) shows no overlap beyond that of the
    contacts of a settling bed (a sphere placed across the wall or into another would overlap
    by a good part of its radius)."""
    f = write(tmp_path, end=0.05, rate="rate = 1500.0")
    text = f.read_text().replace('min = [0.0, 0.0, 0.04], max = [0.02, 0.02, 0.06]',
                                 'min = [0.0, 0.0, 0.0], max = [0.04, 0.02, 0.06]')
    text = text.replace("interval = 0.01", "interval = 0.005").replace("output_interval = 0.01",
                                                                       "output_interval = 0.005")
    text = text.replace("[[inlets]]", """[[walls]]
type = "plane"
name = "ramp"
point = [0.04, 0.0, 0.045]
normal = [-0.7071067811865476, 0.0, -0.7071067811865476]
material = "glass"

[[inlets]]""")
    f.write_text(text)
    out = tmp_path / "out"
    p = dem("run", f, "--out", out, "--quiet", "--threads", "1")
    assert p.returncode == 0, p.stderr
    h = history(out)
    assert h["n_in_feed"][-1] > 50
    assert np.max(h["max_overlap_ratio"]) < 0.05
    fa = final(out)
    x = fa["position"]
    assert np.all((x[:, 0] + x[:, 2] - 0.085) / math.sqrt(2.0) < -0.5 * fa["radius"])   # in front of the ramp


BAD = [
    ({"rate = 1000.0": "rate = 1e6"}, "inlets[0].rate", "fit"),
    ({"rate = 1000.0": "rate = 10.0\nmass_rate = 0.1"}, "inlets[0]", "exactly one of"),
    ({"max = [0.02, 0.02, 0.06] }": "max = [0.02, 0.02, 0.07] }"}, "inlets[0].region", "outside the domain"),
    ({'face = "xmax"': 'face = "ymax"'}, "outlets[0].face", "periodic"),
    ({'name = "side"': 'name = "feed"'}, "outlets[0].name", "duplicate"),
    ({'face = "xmax"': 'face = "top"'}, "outlets[0].face", "xmin"),
    ({"temperature = 400.0": "temperature = 400.0\nspeed = 2.0"}, "inlets[0]", "speed"),
    ({"temperature = 400.0\n": ""}, None, None),    # initial_temperature serves: accepted
    ({'type = "face"\nface = "xmax"': 'type = "plane"\npoint = [0.04, 0.0, 0.0]'}, "outlets[0]", "normal"),
    ({'material = "glass"\nradius = {': 'material = "sand"\nradius = {'}, "inlets[0].material", "unknown material"),
]


@pytest.mark.parametrize("edits,key,text", BAD)
def test_bad_inlets_and_outlets_are_refused_by_the_command_line(tmp_path, edits, key, text):
    f = write(tmp_path, end=0.01)
    src = f.read_text()
    for old, new in edits.items():
        assert old in src, old
        src = src.replace(old, new, 1)
    f.write_text(src)
    p = dem("check", f)
    if key is None:
        assert p.returncode == 0, p.stderr
        return
    assert p.returncode == 2, (p.stdout, p.stderr)
    assert str(f) in p.stderr and key in p.stderr and text in p.stderr, p.stderr
    assert "Traceback" not in p.stderr
    out = tmp_path / "out"
    q = dem("run", f, "--out", out)
    assert q.returncode == 2 and not out.exists()


def test_restart_with_a_renamed_outlet_is_refused(run, tmp_path):
    f, out, _ = run
    g = tmp_path / "renamed.toml"
    g.write_text(f.read_text().replace('name = "side"', 'name = "exit"'))
    work = tmp_path / "copy"
    shutil.copytree(out, work)
    before = {p.name: p.read_bytes() for p in work.iterdir() if p.is_file()}
    p = dem("run", g, "--out", work, "--restart", work / "checkpoint.npz")
    assert p.returncode == 2 and "outlets" in p.stderr and "names cannot change" in p.stderr, p.stderr
    assert {p.name: p.read_bytes() for p in work.iterdir() if p.is_file()} == before


def test_kiln_fed_and_discharged_through_a_turning_stl_shell(tmp_path):
    """examples/kiln_feed.toml for 0.3 s: beads fed at 300 K into a turning, inclined STL shell at
    500 K leave by the open lower end. The number is exact, the ledger closes with the shell's heat
    and the enthalpy in and out (to the history's 12 digits of ~3 kJ), the shell heats the bed
    (its record grows, the beads that left are warmer than the feed), and no bead is placed into
    the turning mesh (the largest overlap stays that of rolling contacts)."""
    out = tmp_path / "kiln"
    p = dem("run", os.path.join(ROOT, "examples", "kiln_feed.toml"), "--out", out, "--end-time", "0.3",
            "--quiet", "--threads", "1")
    assert p.returncode == 0, p.stderr
    h = history(out)
    assert np.array_equal(h["particles"], 321 + h["n_in_feed"] - h["n_out_discharge"])
    assert h["n_in_feed"][-1] > 50 and h["n_out_discharge"][-1] > 10
    lhs = h["thermal_energy"] - h["thermal_energy"][0]
    rhs = h["E_wall_shell"] + h["E_wall_end"] + h["H_in"] - h["H_out"]
    assert np.max(np.abs(lhs - rhs)) <= 1e-11 * h["thermal_energy"][0]
    assert np.all(np.diff(h["E_wall_shell"]) > 0)
    assert h["H_out"][-1] / (h["mass_out_discharge"][-1] * 840.0) > 300.0
    assert np.max(h["max_overlap_ratio"]) < 0.05
