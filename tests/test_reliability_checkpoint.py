"""Checkpoints that carry what they need, and restarts with an edited scene, through the
command line (``python -m dem.cli run SCENE --out OUT --restart CK``) on real processes.

Bad checkpoints (flipped byte, truncated, empty, final.npz, a foreign npz, text, a folder,
an old format, a forged shortened array) exit 2 with one line naming the file and no
traceback; scene edits are applied and listed, or refused naming the key (exit 2).
"""
import math
import os
import subprocess
import sys

import numpy as np
import pytest
from dem.final import read as read_final

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))

R = 1e-3            # particle radius (m)
E = 1e7             # Young's modulus (Pa)
NU = 0.3
RHO = 2500.0

GLASS = f"""
[[materials]]
name = "glass"
density = {RHO}
youngs_modulus = {E}
poisson_ratio = {NU}
restitution = 0.3
friction = 0.3
"""
STEEL = """
[[materials]]
name = "steel"
density = 7800.0
youngs_modulus = 2e7
poisson_ratio = 0.28
restitution = 0.9
friction = 0.1
"""
FLOOR = """
[[walls]]
name = "floor"
type = "plane"
point = [0.0, 0.0, 0.0]
normal = [0.0, 0.0, 1.0]
material = "glass"
"""


def scene_text(materials=GLASS, walls=FLOOR, time_step=1e-5, end_time=0.04,
               positions="[[-0.005, 0.0, 0.001], [0.0, 0.0, 0.001], [0.005, 0.0, 0.001]]"):
    return f"""
[simulation]
time_step = {time_step}
end_time = {end_time}
output_interval = 0.01

[domain]
min = [-0.01, -0.01, 0.0]
max = [0.01, 0.01, 0.02]

[output]
vtk = false
{materials}
[[particles]]
material = "glass"
positions = {positions}
radius = {R}
{walls}
"""


def write(path, text):
    path.write_text(text)
    return str(path)


def dem(*args):
    env = dict(os.environ, PYTHONPATH=ROOT)
    return subprocess.run([sys.executable, "-m", "dem.cli", "run", *args, "--quiet"], cwd=ROOT, env=env,
                          capture_output=True, text=True, timeout=600)


def ok(r):
    assert r.returncode == 0, r.stderr[-3000:]
    return r


def refused(r, *needles):
    """Exit 2, one line on stderr naming what is wrong, no traceback, nothing on stdout."""
    assert r.returncode == 2, (r.returncode, r.stdout[-2000:], r.stderr[-3000:])
    assert "Traceback" not in r.stderr
    lines = r.stderr.strip().splitlines()
    assert len(lines) == 1, r.stderr
    for n in needles:
        assert n in lines[0], lines[0]
    return lines[0]


@pytest.fixture(scope="module")
def base(tmp_path_factory):
    """Three beads resting on the floor, run to 0.02 s: its checkpoint and scene."""
    d = tmp_path_factory.mktemp("ck")
    sc = write(d / "rest.toml", scene_text())
    ok(dem(sc, "--out", str(d / "out"), "--end-time", "0.02"))
    return d, sc, d / "out" / "checkpoint.npz"


# ------------------------------------------------------------------ damaged / foreign files
def _flip(src, dst):
    b = bytearray(src.read_bytes())
    b[len(b) // 2] ^= 0x40
    dst.write_bytes(bytes(b))


def _truncate(src, dst):
    b = src.read_bytes()
    dst.write_bytes(b[:len(b) * 2 // 3])


def _forged_short_array(src, dst):
    """A valid archive whose radius array lost a row, with its checksum recomputed (what a
    buggy tool or a hand edit would produce): the shape check must catch it."""
    from dem import checkpoint as C
    arrays, record = C.read(src)
    arrays["state_radius"] = arrays["state_radius"][:-1]
    with open(dst, "wb") as fh:
        np.savez(fh, **C.with_meta(arrays, record))


def _old_format(src, dst):
    with np.load(src) as z:
        arrays = {k: z[k] for k in z.files if k not in ("format", "format_version", "record", "checksum")}
    with open(dst, "wb") as fh:
        np.savez(fh, **arrays)


def _rewritten(src, dst):
    """A valid archive whose positions were changed after writing (the stored checksum kept)."""
    with np.load(src) as z:
        arrays = {k: z[k] for k in z.files}
    arrays["state_position"] = arrays["state_position"] + 1e-4
    with open(dst, "wb") as fh:
        np.savez(fh, **arrays)


def _foreign(src, dst):
    with open(dst, "wb") as fh:
        np.savez(fh, a=np.arange(3.0), b=np.ones(2))


BAD = {
    "flipped_byte": (_flip, "corrupted"),
    "truncated": (_truncate, "corrupted or truncated"),
    "empty": (lambda s, d: d.write_bytes(b""), "empty"),
    "text": (lambda s, d: d.write_text("time,x\n0,1\n"), "not a checkpoint"),
    "foreign_npz": (_foreign, "not a thermodem checkpoint"),
    "old_format": (_old_format, "earlier thermodem"),
    "short_array": (_forged_short_array, "'state_radius' has shape (2,)"),
    "rewritten": (_rewritten, "does not match its sha256 checksum"),
}


@pytest.mark.parametrize("kind", sorted(BAD))
def test_bad_checkpoint_is_refused(base, kind):
    d, sc, ck = base
    make, needle = BAD[kind]
    bad = d / f"{kind}.npz"
    make(ck, bad)
    before = ck.read_bytes()
    out = d / f"out_{kind}"
    refused(dem(sc, "--out", str(out), "--restart", str(bad)), str(bad), needle)
    assert not out.exists()                 # refused before anything was written
    assert ck.read_bytes() == before


def test_final_npz_and_folder_are_refused(base):
    d, sc, ck = base
    final = d / "out" / "final.npz"
    refused(dem(sc, "--out", str(d / "o1"), "--restart", str(final)), str(final), "results file",
            "checkpoint.npz")
    refused(dem(sc, "--out", str(d / "o2"), "--restart", str(d / "out")), str(d / "out"), "is a folder")


# ------------------------------------------------------------------ refused scene edits
def test_changed_time_step_is_refused(base):
    d, sc, ck = base
    edited = write(d / "dt.toml", scene_text(time_step=5e-6))
    refused(dem(edited, "--out", str(d / "o_dt"), "--restart", str(ck)), "dt.toml",
            "simulation.time_step", "1e-05", "5e-06")


def test_removed_material_in_use_is_refused(base):
    d, sc, ck = base
    renamed = GLASS.replace('"glass"', '"glass2"')
    text = scene_text(materials=renamed, walls=FLOOR.replace('"glass"', '"glass2"')).replace(
        'material = "glass"', 'material = "glass2"')
    edited = write(d / "rm.toml", text)
    refused(dem(edited, "--out", str(d / "o_rm"), "--restart", str(ck)), "materials[glass]",
            "3 particles")


# ------------------------------------------------------------------ applied scene edits
def hertz_rest_overlap(density):
    """Static overlap of a bead on a plane of the same material: (4/3) E* sqrt(R) d^1.5 = m g."""
    estar = 1.0 / (2 * (1 - NU ** 2) / E)
    m = 4.0 / 3.0 * math.pi * R ** 3 * density
    return (3 * m * 9.81 / (4 * estar * math.sqrt(R))) ** (2.0 / 3.0)


def test_doubled_density_is_applied_to_the_mass(base):
    d, sc, ck = base
    before = read_final(d / "out" / "final.npz")["position"][:, 2]
    # before the edit the beads rest at the Hertz overlap of their own mass (to 1 %)
    assert np.allclose(R - before, hertz_rest_overlap(RHO), rtol=0.01)
    edited = write(d / "dense.toml", scene_text(materials=GLASS.replace(f"density = {RHO}", "density = 5000.0")))
    r = ok(dem(edited, "--out", str(d / "o_dense"), "--restart", str(ck)))
    assert "restart: applied materials[glass].density 2500 -> 5000 (mass and inertia of 3 particles)" in r.stdout
    z = read_final(d / "o_dense" / "final.npz")["position"][:, 2]
    # they settle deeper, at the overlap of the doubled mass: 2^(2/3) = 1.59 times the former one
    assert np.allclose(R - z, hertz_rest_overlap(2 * RHO), rtol=0.01)


def test_tangential_model_edit_is_applied_with_the_springs_kept(base):
    """[contact] tangential changed at a restart: listed, the springs kept (both models store the
    same spring in the tangent plane), the run goes on with the projected model's compiled form and
    the beads stay at the Hertz overlap of their weight."""
    d, sc, ck = base
    edited = write(d / "proj.toml", scene_text() + '\n[contact]\ntangential = "projected"\n')
    r = ok(dem(edited, "--out", str(d / "o_proj"), "--restart", str(ck)))
    assert "restart: applied contact.tangential 'rescaled' -> 'projected'" in r.stdout
    z = read_final(d / "o_proj" / "final.npz")["position"][:, 2]
    assert np.allclose(R - z, hertz_rest_overlap(RHO), rtol=0.01)
    r = ok(dem(sc, "--out", str(d / "o_same"), "--restart", str(ck)))
    assert "contact.tangential" not in r.stdout      # unchanged: nothing listed


def test_material_inserted_before_keeps_each_particles_properties(tmp_path):
    """steel inserted before glass (unused): the glass beads keep glass and the run equals
    the uninterrupted one to round-off (a swap of properties would change everything)."""
    drop = "[[0.0, 0.0, 0.002], [0.0004, 0.0, 0.0055], [-0.0003, 0.0002, 0.009]]"
    sc = write(tmp_path / "drop.toml", scene_text(positions=drop))
    ok(dem(sc, "--out", str(tmp_path / "one")))
    ok(dem(sc, "--out", str(tmp_path / "first"), "--end-time", "0.02"))
    edited = write(tmp_path / "drop2.toml", scene_text(materials=STEEL + GLASS, positions=drop))
    r = ok(dem(edited, "--out", str(tmp_path / "second"), "--restart", str(tmp_path / "first" / "checkpoint.npz")))
    assert "restart: applied materials[steel] added" in r.stdout
    assert "glass 0 -> 1" in r.stdout
    a = read_final(tmp_path / "one" / "final.npz")
    b = read_final(tmp_path / "second" / "final.npz")
    assert np.array_equal(a["id"], b["id"])
    assert np.abs(a["position"] - b["position"]).max() <= 1e-12 * np.abs(a["position"]).max()
    vs = max(np.abs(a["velocity"]).max(), 1e-9)
    assert np.abs(a["velocity"] - b["velocity"]).max() <= 1e-12 * vs
    assert np.all(b["material"] == 1)       # glass is index 1 in the edited scene
    # the beads collided on the way down: the comparison covers contacts, not free fall only
    assert np.abs(a["position"][:, 0] - np.array([0.0, 0.0004, -0.0003])).max() > 1e-6


def test_added_wall_is_applied_and_particles_rest_on_it(tmp_path):
    high = "[[-0.005, 0.0, 0.008], [0.0, 0.0, 0.008], [0.005, 0.0, 0.008]]"
    sc = write(tmp_path / "fall.toml", scene_text(positions=high, end_time=0.07))
    ok(dem(sc, "--out", str(tmp_path / "first"), "--end-time", "0.01"))
    shelf_z = 0.004
    shelf = f"""
[[walls]]
name = "shelf"
type = "plane"
point = [0.0, 0.0, {shelf_z}]
normal = [0.0, 0.0, 1.0]
material = "glass"
"""
    edited = write(tmp_path / "fall2.toml", scene_text(positions=high, end_time=0.07, walls=shelf + FLOOR))
    r = ok(dem(edited, "--out", str(tmp_path / "second"), "--restart", str(tmp_path / "first" / "checkpoint.npz")))
    assert "restart: applied walls[shelf] added" in r.stdout
    z = read_final(tmp_path / "second" / "final.npz")["position"][:, 2]
    # they fell onto the shelf and rest there (without it they would lie on the floor at z = R)
    assert np.all(np.abs(z - (shelf_z + R)) < 0.01 * R), z


def test_unedited_restart_prints_no_change(base):
    d, sc, ck = base
    r = ok(dem(sc, "--out", str(d / "o_same"), "--restart", str(ck)))
    assert "restart:" not in r.stdout


def thermal_scene(wall_temperature, integrator="euler"):
    """One bead resting on a floor held at a fixed temperature; a fast conductor (tau = C / H
    about 0.2 ms) so that it takes the wall temperature within the run."""
    mat = GLASS + "thermal_conductivity = 1000.0\nheat_capacity = 1.0\n"
    floor = FLOOR + f'thermal = {{ condition = "fixed_temperature", temperature = {wall_temperature} }}\n'
    return scene_text(materials=mat, walls=floor, positions="[[0.0, 0.0, 0.001]]") + f"""
[thermal]
direct = "batchelor_obrien"
initial_temperature = 300.0
integrator = "{integrator}"
"""


def test_wall_temperature_edit_is_applied_and_model_change_refused(tmp_path):
    sc = write(tmp_path / "hot.toml", thermal_scene(400.0))
    ok(dem(sc, "--out", str(tmp_path / "out"), "--end-time", "0.02"))
    ck = tmp_path / "out" / "checkpoint.npz"
    assert read_final(tmp_path / "out" / "final.npz")["temperature"][0] == pytest.approx(400.0, abs=0.5)
    hotter = write(tmp_path / "hotter.toml", thermal_scene(500.0))
    r = ok(dem(hotter, "--out", str(tmp_path / "out"), "--restart", str(ck)))
    assert "restart: applied walls[floor].thermal.temperature 400 -> 500" in r.stdout
    # the bead follows the new wall temperature (it could not pass 400 K otherwise)
    assert read_final(tmp_path / "out" / "final.npz")["temperature"][0] == pytest.approx(500.0, abs=0.5)
    h = np.genfromtxt(tmp_path / "out" / "history.csv", delimiter=",", names=True)
    assert np.all(np.diff(h["time"]) > 0) and h["time"][0] == 0.0 and h["time"][-1] == pytest.approx(0.04)
    expo = write(tmp_path / "expo.toml", thermal_scene(400.0, integrator="exponential"))
    refused(dem(expo, "--out", str(tmp_path / "o2"), "--restart", str(ck)), "thermal.integrator",
            "'euler'", "'exponential'")


def test_added_wall_through_the_particles_is_refused(base):
    """A wall added where the beads are (at half their radius) would stop the run at its
    first step: refused before anything is written, naming the wall."""
    d, sc, ck = base
    cut = FLOOR.replace('"floor"', '"cut"').replace("point = [0.0, 0.0, 0.0]", f"point = [0.0, 0.0, {R / 2}]")
    edited = write(d / "cut.toml", scene_text(walls=FLOOR + cut))
    refused(dem(edited, "--out", str(d / "o_cut"), "--restart", str(ck)), "walls[cut]", "cuts through")
    assert not (d / "o_cut").exists()
