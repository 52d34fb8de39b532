"""Broken scenes: each gives its own clear SceneError -- ``file: key.path: message`` naming the
file, the exact key path and what is allowed -- raised while the scene is read, before any
computation and before anything is written.

Table-driven: a small valid scene (a few explicit particles, one plane wall) and ~30 broken
variants of it, each written to a TOML file and loaded with :func:`dem.scene.load`; the CLI
(``dem check`` / ``dem run``) is checked on a few of them in subprocesses.
"""
import copy
import json
import math
import os
import subprocess
import sys

import pytest

from dem.scene import SceneError, load, parse

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


# ----------------------------------------------------------------------------- valid base scene
def base_scene():
    return {
        "simulation": {"time_step": 1e-6, "end_time": 1e-4, "gravity": [0.0, 0.0, -9.81],
                       "output_interval": 1e-5, "seed": 3},
        "domain": {"min": [0.0, 0.0, 0.0], "max": [0.01, 0.01, 0.01]},
        "materials": [{"name": "glass", "density": 2500.0, "youngs_modulus": 1e7, "poisson_ratio": 0.25,
                       "restitution": 0.5, "friction": 0.3}],
        "contact": {"model": "hertz_mindlin"},
        "particles": [
            {"material": "glass", "positions": [[0.002, 0.002, 0.002], [0.005, 0.002, 0.002],
                                                [0.008, 0.002, 0.002]],
             "radii": [0.001, 0.0009, 0.0011]},
            {"material": "glass", "positions": [[0.002, 0.007, 0.005], [0.006, 0.007, 0.005]],
             "radius": 0.001, "velocity": [0.0, 0.0, -0.1]},
        ],
        "walls": [{"type": "plane", "point": [0.0, 0.0, 0.0], "normal": [0.0, 0.0, 1.0],
                   "material": "glass"}],
    }


# ----------------------------------------------------------------------------- minimal TOML writer
def _val(x):
    if isinstance(x, bool):
        return "true" if x else "false"
    if isinstance(x, int):
        return str(x)
    if isinstance(x, float):
        if math.isinf(x):
            return "inf" if x > 0 else "-inf"
        if math.isnan(x):
            return "nan"
        return repr(x)
    if isinstance(x, str):
        return json.dumps(x)
    if isinstance(x, list):
        return "[" + ", ".join(_val(e) for e in x) + "]"
    if isinstance(x, dict):
        return "{ " + ", ".join(f"{k} = {_val(e)}" for k, e in x.items()) + " }"
    raise TypeError(type(x))


def to_toml(data):
    lines = [f"{k} = {_val(x)}" for k, x in data.items()
             if not isinstance(x, dict) and not (isinstance(x, list) and x and all(isinstance(e, dict) for e in x))]
    for k, x in data.items():
        if isinstance(x, dict):
            lines.append(f"\n[{k}]")
            lines += [f"{kk} = {_val(e)}" for kk, e in x.items()]
        elif isinstance(x, list) and x and all(isinstance(e, dict) for e in x):
            for t in x:
                lines.append(f"\n[[{k}]]")
                lines += [f"{kk} = {_val(e)}" for kk, e in t.items()]
    return "\n".join(lines) + "\n"


def write_scene(path, data):
    path.write_text(to_toml(data))
    return path


# ----------------------------------------------------------------------------- variants
def _set(*keys_and_value):
    """Mutation setting data[k0][k1]...[kn] = value."""
    *keys, value = keys_and_value

    def f(d):
        for k in keys[:-1]:
            d = d[k]
        d[keys[-1]] = value
    return f


def _del(*keys):
    def f(d):
        for k in keys[:-1]:
            d = d[k]
        del d[keys[-1]]
    return f


def _both(*fs):
    def f(d):
        for g in fs:
            g(d)
    return f


def _add_material(d):
    d["materials"].append(dict(d["materials"][0], restitution=0.7))


def _insertion(count):
    def f(d):
        # spheres of radius 1 mm in a 4 mm cube: 8 fill 52 % of it (random insertion fails),
        # 500 hold 33 times its volume (refused before trying)
        d["particles"].append({"material": "glass", "count": count, "radius": 0.001,
                               "region": {"type": "box", "min": [0.0, 0.0, 0.006], "max": [0.004, 0.004, 0.01]}})
    return f


# (id, mutation, exact key path, phrases saying what is allowed / what is wrong)
CASES = [
    # unknown keys
    ("unknown-top-level", _set("solver", {"x": 1}), "solver", ["unknown key", "allowed keys", "simulation"]),
    ("unknown-simulation", _set("simulation", "timestep", 1e-6), "simulation.timestep",
     ["unknown key", "allowed keys", "time_step"]),
    ("unknown-material", _set("materials", 0, "youngs", 1e7), "materials[0].youngs",
     ["unknown key", "allowed keys", "youngs_modulus"]),
    ("unknown-particles", _set("particles", 1, "radiu", 0.001), "particles[1].radiu",
     ["unknown key", "allowed keys", "radius"]),
    ("unknown-walls", _set("walls", 0, "norm", [0.0, 0.0, 1.0]), "walls[0].norm",
     ["unknown key", "allowed keys", "normal"]),
    ("unknown-contact", _set("contact", "modle", "hertz_mindlin"), "contact.modle",
     ["unknown key", "allowed keys", "model"]),
    # wrong types
    ("string-for-number", _set("simulation", "time_step", "1e-6"), "simulation.time_step",
     ["must be a number", "'1e-6'"]),
    ("string-for-radius", _set("particles", 1, "radius", "1 mm"), "particles[1].radius",
     ["must be a number"]),
    ("vec-of-2", _set("simulation", "gravity", [0.0, -9.81]), "simulation.gravity",
     ["must be a list of 3 numbers"]),
    ("normal-of-2", _set("walls", 0, "normal", [0.0, 1.0]), "walls[0].normal",
     ["must be a list of 3 numbers"]),
    ("bool-for-number", _set("materials", 0, "density", True), "materials[0].density",
     ["must be a number", "True"]),
    ("walls-not-array", lambda d: d.__setitem__("walls", d["walls"][0]), "walls",
     ["must be an array of tables [[walls]]"]),
    ("angular-velocities-pairs", _set("particles", 1, "angular_velocities", [[0.0, 1.0], [0.0, 1.0]]),
     "particles[1].angular_velocities", ["must be a list of 2 [wx, wy, wz] triples"]),
    ("radius-and-radii", _set("particles", 0, "radius", -1.0), "particles[0].radius",
     ["either 'radius'", "or 'radii'", "not both"]),
    # missing required keys
    ("missing-time-step", _del("simulation", "time_step"), "simulation.time_step", ["missing required key"]),
    ("missing-materials", _del("materials"), "materials", ["missing required key"]),
    ("missing-particle-material", _del("particles", 1, "material"), "particles[1].material",
     ["missing required key"]),
    ("missing-radius", _del("particles", 1, "radius"), "particles[1].radius",
     ["missing required key", "or 'radii'"]),
    ("missing-wall-normal", _del("walls", 0, "normal"), "walls[0].normal", ["missing required key"]),
    # non-physical values
    ("radius-zero", _set("particles", 1, "radius", 0.0), "particles[1].radius", ["must be in (0, inf)"]),
    ("radius-negative", _set("particles", 1, "radius", -0.001), "particles[1].radius", ["must be in (0, inf)"]),
    ("radii-2-negative", _set("particles", 0, "radii", [0.001, 0.001, -0.001]), "particles[0].radii[2]",
     ["must be > 0"]),
    ("restitution-0", _set("materials", 0, "restitution", 0.0), "materials[0].restitution",
     ["must be in (0, 1]"]),
    ("restitution-1.5", _set("materials", 0, "restitution", 1.5), "materials[0].restitution",
     ["must be in (0, 1]"]),
    ("poisson-minus-1", _set("materials", 0, "poisson_ratio", -1.0), "materials[0].poisson_ratio",
     ["must be in (-1, 0.5)"]),
    ("poisson-0.5", _set("materials", 0, "poisson_ratio", 0.5), "materials[0].poisson_ratio",
     ["must be in (-1, 0.5)"]),
    ("density-zero", _set("materials", 0, "density", 0.0), "materials[0].density", ["must be in (0, inf)"]),
    ("density-negative", _set("materials", 0, "density", -2500.0), "materials[0].density",
     ["must be in (0, inf)"]),
    ("friction-negative", _set("materials", 0, "friction", -0.1), "materials[0].friction",
     ["must be in [0, inf)"]),
    ("youngs-zero", _set("materials", 0, "youngs_modulus", 0), "materials[0].youngs_modulus",
     ["must be in (0, inf)"]),
    # references and names
    ("unknown-material-ref", _set("particles", 1, "material", "steel"), "particles[1].material",
     ["unknown material 'steel'", "defined: glass"]),
    ("unknown-wall-material", _set("walls", 0, "material", "steel"), "walls[0].material",
     ["unknown material 'steel'", "defined: glass"]),
    ("unknown-contact-model", _set("contact", "model", "hooke"), "contact.model",
     ["unknown value 'hooke'", "hertz_mindlin", "linear_spring_dashpot"]),
    ("unknown-tangential-model", _set("contact", "tangential", "liggghts"), "contact.tangential",
     ["unknown value 'liggghts'", "rescaled", "projected"]),
    ("duplicate-material", _add_material, "materials[1].name", ["duplicate material name 'glass'", "unique"]),
    # geometry
    ("particle-outside-domain", _set("particles", 1, "positions", [[0.002, 0.007, 0.005], [0.006, 0.007, 0.02]]),
     "particles[1].positions[1]", ["outside the domain", "axis z"]),
    ("initial-overlap", _set("particles", 1, "positions", [[0.002, 0.007, 0.005], [0.0025, 0.007, 0.005]]),
     "particles[1]", ["overlap", "allowed: simulation.initial_overlap_ratio = 0.05"]),
    ("domain-max-le-min", _set("domain", "max", [0.01, 0.0, 0.01]), "domain.max",
     ["must be larger than domain.min on every axis"]),
    ("insertion-cannot-fit", _insertion(8), "particles[2].count",
     ["could place only", "of 8", "enlarge the region or lower the count"]),
    ("insertion-beyond-densest-packing", _insertion(500), "particles[2].count",
     ["500 spheres", "more than the densest packing", "(at most 11)", "enlarge the region or lower the count"]),
    ("plane-spin-not-about-normal", _set("walls", 0, "angular_velocity", [1.0, 0.0, 0.0]),
     "walls[0].angular_velocity", ["may only turn about its normal"]),
]


def test_base_scene_is_valid(tmp_path):
    sc = load(write_scene(tmp_path / "ok.toml", base_scene()))
    assert sc.radius.size == 5
    assert len(sc.walls) == 1
    assert sorted(os.listdir(tmp_path)) == ["ok.toml"]


@pytest.mark.parametrize("name, mutate, path, phrases", CASES, ids=[c[0] for c in CASES])
def test_broken_scene(tmp_path, name, mutate, path, phrases):
    data = copy.deepcopy(base_scene())
    mutate(data)
    f = write_scene(tmp_path / f"{name}.toml", data)
    with pytest.raises(SceneError) as ei:
        load(f)
    exc = ei.value
    msg = str(exc)
    assert msg.startswith(f"{f}: "), msg
    assert exc.file == str(f)
    assert exc.path == path, msg
    assert f": {path}: " in msg, msg
    for ph in phrases:
        assert ph in msg, f"{ph!r} not in {msg!r}"
    # nothing written next to the scene
    assert sorted(os.listdir(tmp_path)) == [f.name], os.listdir(tmp_path)


def test_every_case_has_its_own_message(tmp_path):
    msgs = set()
    for name, mutate, _, _ in CASES:
        data = copy.deepcopy(base_scene())
        mutate(data)
        with pytest.raises(SceneError) as ei:
            parse(data, "scene.toml", base_dir=str(tmp_path))
        msgs.add(str(ei.value).split(", got")[0])
    # a few cases legitimately share a message (e.g. two out-of-range densities)
    assert len(msgs) >= len(CASES) - 6


# ----------------------------------------------------------------------------- particle files
def _file_scene(fname):
    d = base_scene()
    d["particles"] = [{"material": "glass", "file": fname}]
    return d


def test_missing_particle_file(tmp_path):
    f = write_scene(tmp_path / "s.toml", _file_scene("nope.csv"))
    with pytest.raises(SceneError) as ei:
        load(f)
    msg = str(ei.value)
    assert msg.startswith(f"{f}: particles[0].file: ")
    assert "file not found" in msg and "nope.csv" in msg


def test_csv_without_radius_column(tmp_path):
    (tmp_path / "p.csv").write_text("x,y,z,diameter\n0.002,0.002,0.002,0.002\n0.006,0.006,0.006,0.002\n")
    f = write_scene(tmp_path / "s.toml", _file_scene("p.csv"))
    with pytest.raises(SceneError) as ei:
        load(f)
    msg = str(ei.value)
    assert msg.startswith(f"{f}: particles[0].file: ")
    assert "missing column 'radius'" in msg and "need x, y, z, radius" in msg


def test_csv_particle_file_is_accepted(tmp_path):
    (tmp_path / "p.csv").write_text("x,y,z,radius\n0.002,0.002,0.002,0.001\n0.006,0.006,0.006,0.001\n")
    sc = load(write_scene(tmp_path / "s.toml", _file_scene("p.csv")))
    assert sc.radius.tolist() == [0.001, 0.001]


# ----------------------------------------------------------------------------- time step (Simulation.check)
def _big_step(force):
    d = base_scene()
    d["simulation"].update(time_step=1e-4, end_time=1e-3, output_interval=1e-4)
    if force:
        d["simulation"]["force"] = True
    return d


def test_time_step_above_limit_raises_in_check():
    from dem import Simulation
    sim = Simulation.from_dict(_big_step(False), name="big.toml")
    with pytest.raises(SceneError) as ei:
        sim.check()
    msg = str(ei.value)
    assert msg.startswith("big.toml: simulation.time_step: ")
    assert "Rayleigh time" in msg and "(allowed: 0.3)" in msg
    assert "simulation.force = true" in msg
    assert sim.step_count == 0 and sim.time == 0.0


def test_time_step_above_limit_accepted_with_force():
    from dem import Simulation
    rep = Simulation.from_dict(_big_step(True), name="big.toml").check()
    assert rep["problems"] and "Rayleigh time" in rep["problems"][0]
    assert rep["dt_over_rayleigh"] > 0.3


# ----------------------------------------------------------------------------- CLI
def _cli(args, cwd):
    env = dict(os.environ, PYTHONPATH=ROOT + os.pathsep + os.environ.get("PYTHONPATH", ""))
    return subprocess.run([sys.executable, "-m", "dem.cli", *args], cwd=cwd, env=env,
                          capture_output=True, text=True, timeout=300)


CLI_CASES = [
    ("restitution", _set("materials", 0, "restitution", 1.5), "materials[0].restitution", "must be in (0, 1]"),
    ("wall-normal", _del("walls", 0, "normal"), "walls[0].normal", "missing required key"),
    ("tangential", _set("contact", "tangential", "rotated"), "contact.tangential", "valid: rescaled, projected"),
    ("time-step", lambda d: d["simulation"].update(time_step=1e-4, end_time=1e-3, output_interval=1e-4),
     "simulation.time_step", "simulation.force = true"),
]


@pytest.mark.parametrize("cmd", ["check", "run"])
@pytest.mark.parametrize("name, mutate, path, phrase", CLI_CASES, ids=[c[0] for c in CLI_CASES])
def test_cli_broken_scene(tmp_path, cmd, name, mutate, path, phrase):
    data = copy.deepcopy(base_scene())
    mutate(data)
    f = write_scene(tmp_path / "broken.toml", data)
    out = tmp_path / "out_dir"
    args = [cmd, str(f)] + (["--out", str(out), "--quiet"] if cmd == "run" else [])
    r = _cli(args, cwd=tmp_path)
    assert r.returncode == 2, (r.returncode, r.stdout, r.stderr)
    assert f"{f}: {path}: " in r.stderr, r.stderr
    assert phrase in r.stderr, r.stderr
    assert "Traceback" not in r.stderr
    assert not out.exists()
    assert sorted(os.listdir(tmp_path)) == ["broken.toml"]   # nor the default out/broken


def test_cli_invalid_toml(tmp_path):
    f = tmp_path / "bad.toml"
    f.write_text("[simulation]\ntime_step = = 1e-6\n")
    out = tmp_path / "o"
    for args in (["check", str(f)], ["run", str(f), "--out", str(out)]):
        r = _cli(args, cwd=tmp_path)
        assert r.returncode == 2, r.stderr
        assert f"{f}: not valid TOML" in r.stderr, r.stderr
        assert not out.exists()
    with pytest.raises(SceneError, match="not valid TOML"):
        load(f)


def test_cli_missing_scene_file(tmp_path):
    f = tmp_path / "absent.toml"
    r = _cli(["check", str(f)], cwd=tmp_path)
    assert r.returncode == 2
    assert f"{f}: file not found" in r.stderr


def test_the_initial_overlap_check_finds_the_largest_overlap():
    """dem.insertion.max_overlap (the check of [simulation] initial_overlap_ratio) against brute
    force over every pair, by the nearest image on periodic axes: the same largest overlap
    (to 1e-12 of the radius: the same arithmetic in another order) on 200 random beds of 2 to
    300 spheres, walled and periodic axes mixed; none within reach gives -inf."""
    import numpy as np
    from dem.insertion import max_overlap
    rng = np.random.default_rng(0)
    for _ in range(200):
        n = int(rng.integers(2, 300))
        L = np.array([0.02, 0.03, 0.01])
        per = rng.random(3) < 0.5
        x = rng.uniform(0, 1, (n, 3)) * L
        r = rng.uniform(0.0005, 0.001, n)
        ov, i, j = max_overlap(x, r, np.where(per, L, 0.0))
        d = x[:, None, :] - x[None, :, :]
        d -= np.where(per, L, 0.0) * np.round(d / L) * per
        dist = np.linalg.norm(d, axis=2)
        m = (r[:, None] + r[None, :] - dist) / np.minimum(r[:, None], r[None, :])
        iu = np.triu_indices(n, 1)
        near = dist[iu] <= 2 * r.max()
        if not near.any():
            assert ov == -np.inf and (i, j) == (-1, -1)
            continue
        assert abs(ov - m[iu][near].max()) <= 1e-12
        assert abs(m[i, j] - ov) <= 1e-12 and i < j
    assert max_overlap(np.zeros((1, 3)), np.ones(1), np.zeros(3))[0] == -np.inf
