"""[output] heat_by_mechanism: each particle's heat rate of the last step split by mechanism
(dem.thermal.heat.QM; VTK and final.npz fields heat_direct, heat_indirect, heat_wall, heat_conv,
heat_rad, heat_gen, heat_src). Every integrator: the columns sum to the particle's heat_rate, and
their sums over the particles are the run totals' increments over that step (the walls', the
radiation's, ...), the pairs' net being zero in a closed bed."""
import math
import os
import subprocess
import sys

import numpy as np
import pytest

from dem import Simulation

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
R = 1e-3
MAT = dict(name="p", density=2500.0, youngs_modulus=1e7, poisson_ratio=0.3, restitution=0.5,
           friction=0.3, thermal_conductivity=1.0, heat_capacity=840.0, emissivity=0.8)
GAS = dict(conductivity=0.026, density=1.2, viscosity=1.8e-5, heat_capacity=1005.0, temperature=350.0,
           porosity=0.4, velocity=[0.0, 0.0, 0.5])
FIELDS = ("direct", "indirect", "wall", "conv", "rad", "gen", "src")
LEDGER = {"direct": 0, "indirect": 1, "conv": 2, "rad": 3, "gen": 4, "src": 5}   # dem.thermal.heat.TOT


def bed(mech):
    """27 beads in a 3 x 3 x 3 lattice 1.98 R apart (pressed 0.02 R together), the bottom layer on a floor at
    400 K; the layers (one group each) at 300, 320 and 340 K; moving (mechanics, sliding on the
    floor) or frozen."""
    g = np.arange(3) * 1.98 * R
    groups = []
    for k, z in enumerate(g):
        pos = [[x - 1.98 * R, y - 1.98 * R, z + R - 2e-5] for y in g for x in g]
        groups.append({"material": "p", "positions": pos, "radius": R, "temperature": 300.0 + 20.0 * k,
                       **({"velocities": [[0.05, 0.0, 0.0]] * len(pos)} if mech else {})})
    return groups


def scene(integrator, mech, end, dt):
    th = {"direct": "batchelor_obrien", "indirect": "musser_2011_surrounding_layer", "convection": "ranz_marshall",
          "radiation": "zhou_2009", "porosity": "global", "sources": [{"group": 0, "power": 0.002}]}
    if integrator != "auto":
        th["integrator"] = integrator
    if mech:
        th["friction_heat"] = "nguyen_2009"
        th["partition"] = "equal"
    else:
        th["time_step"] = dt
    floor = {"type": "plane", "name": "floor", "point": [0, 0, 0], "normal": [0, 0, 1], "material": "p",
             "thermal": {"condition": "fixed_temperature", "temperature": 400.0}}
    return {"simulation": {"time_step": dt if mech else 1e-5, "end_time": end, "mechanics": mech,
                           "gravity": [0.0, 0.0, -9.81] if mech else [0.0, 0.0, 0.0]},
            "domain": {"min": [-0.01, -0.01, -0.001], "max": [0.01, 0.01, 0.01]}, "materials": [dict(MAT)],
            "particles": bed(mech), "thermal": th, "walls": [floor], "gas": dict(GAS),
            "output": {"heat_by_mechanism": True}}


@pytest.mark.parametrize("integrator, mech, dt", [("auto", True, 2e-6), ("exponential", True, 2e-6),
                                                  ("exponential", False, 0.05), ("implicit", False, 0.05),
                                                  ("trbdf2", False, 0.05)])
def test_the_columns_sum_to_the_heat_rate_and_to_the_ledger(integrator, mech, dt):
    """After some steps, one more: per particle the columns sum to heat_rate (1e-9 of the largest
    rate: the exponential update's shares of a link, the conjugate gradients' residual; and the
    rounding of heat_rate itself where it is C (T^n+1 - T^n) / dt); over the
    particles each mechanism times the step is what that step added to its run total (1e-9 of
    the largest of them), the pairs' nets cancel (1e-12 of their size), and the floor's column is
    its wall record's increment. With mechanics ("auto" is Euler there) the force loop's fused
    sum is replaced by the heat step's: the bed heats as without the split (1e-9 K)."""
    sc = scene(integrator, mech, end=1.0, dt=dt)
    sim = Simulation.from_dict(sc)
    sim.step(40)
    st, th = sim.state, sim.thermal
    tot0, wall0 = th.tot.copy(), th.wtot.copy()
    sim.step(1)
    n = st.n_owned
    q = st.qmech[:n]
    step = sim.world.dt
    rate = st.heat_rate[:n]
    assert np.abs(rate).max() > 0.0
    # (the exponential and implicit updates report heat_rate as C (T^n+1 - T^n) / dt: its
    # rounding, a few ulp of T over the step, bounds the agreement besides the 1e-9)
    ulp = 8.0 * np.finfo(float).eps * st.temperature[:n] / (st.inv_heat_capacity[:n] * step)
    assert np.all(np.abs(q.sum(axis=1) - rate) <= 1e-9 * np.abs(rate).max() + ulp)
    dtot = th.tot - tot0
    ref = max(np.abs(dtot[2:6]).max(), abs(th.wtot[0] - wall0[0]))
    for name, k in LEDGER.items():
        if name in ("direct", "indirect"):
            col = q[:, FIELDS.index(name)]
            assert np.abs(col).sum() > 0.0, name
            assert abs(col.sum()) <= 1e-12 * np.abs(col).sum(), name
            continue
        got = q[:, FIELDS.index(name)].sum() * step
        if name == "gen" and not mech:
            assert got == 0.0
            continue
        assert got == pytest.approx(dtot[k], abs=1e-9 * ref), name
    assert q[:, FIELDS.index("wall")].sum() * step == pytest.approx(th.wtot[0] - wall0[0], abs=1e-9 * ref)
    assert q[:, FIELDS.index("wall")].sum() > 0.0   # the hot floor heats the bed
    if mech and integrator == "auto":
        sc2 = scene(integrator, mech, end=1.0, dt=dt)
        del sc2["output"]
        plain = Simulation.from_dict(sc2)
        plain.step(41)
        assert plain.state.qmech.shape[0] == 0   # nothing extra kept without the option
        assert np.abs(plain.state.temperature[:n] - st.temperature[:n]).max() <= 1e-9


def test_the_fields_of_a_run_through_the_command_line(tmp_path):
    """`dem run` of a scene file with [output] heat_by_mechanism: the VTK frames and final.npz
    carry heat_<mechanism> of the mechanisms the scene runs (a scene with direct conduction and
    a hot floor: heat_direct and heat_wall, no radiation column), which sum to heat_rate; the
    floor's column is positive at the bottom layer only (the others do not touch it)."""
    from dem.final import read as read_final
    from dem.output import read_frames
    g = np.arange(3) * 1.98 * R
    pos = [[float(x), 0.0, float(z + R - 2e-5)] for z in g for x in g]
    f = tmp_path / "bed.toml"
    f.write_text(f"""
[simulation]
time_step = 1e-5
end_time = 0.5
mechanics = false
output_interval = 0.25

[domain]
min = [-0.01, -0.01, -0.001]
max = [0.01, 0.01, 0.01]

[[materials]]
name = "p"
density = 2500.0
youngs_modulus = 1e7
poisson_ratio = 0.3
restitution = 0.5
friction = 0.3
thermal_conductivity = 1.0
heat_capacity = 840.0

[[particles]]
material = "p"
radius = {R}
positions = {pos}
temperature = 300.0

[[walls]]
type = "plane"
name = "floor"
point = [0.0, 0.0, 0.0]
normal = [0.0, 0.0, 1.0]
material = "p"
thermal = {{ condition = "fixed_temperature", temperature = 400.0 }}

[thermal]
direct = "batchelor_obrien"
time_step = 0.01

[output]
heat_by_mechanism = true
""")
    out = tmp_path / "out"
    p = subprocess.run([sys.executable, "-m", "dem", "run", str(f), "--out", str(out), "--quiet"],
                       capture_output=True, text=True, cwd=ROOT, env=dict(os.environ, PYTHONPATH=ROOT))
    assert p.returncode == 0, p.stderr
    fin = read_final(out / "final.npz")
    heat = [k for k in fin if k.startswith("heat_") and k != "heat_rate"]
    assert sorted(heat) == ["heat_direct", "heat_wall"]
    assert np.abs(fin["heat_direct"] + fin["heat_wall"] - fin["heat_rate"]).max() <= \
        1e-9 * np.abs(fin["heat_rate"]).max()
    bottom = fin["position"][:, 2] < 1.5 * R
    assert np.all(fin["heat_wall"][bottom] > 0.0) and np.all(fin["heat_wall"][~bottom] == 0.0)
    frames = read_frames(str(out))
    t, _, _, data = frames[-1]
    assert t == pytest.approx(0.5)
    assert "heat_direct" in data and "heat_wall" in data and "heat_rad" not in data
    assert np.sort(data["heat_wall"]) == pytest.approx(np.sort(fin["heat_wall"]), rel=1e-12)


def test_asking_for_the_split_without_heat_is_refused(tmp_path):
    """[output] heat_by_mechanism in a scene without [thermal]: exit 2, the key named, nothing written."""
    src = open(os.path.join(ROOT, "examples", "settle_box.toml")).read()
    f = tmp_path / "s.toml"
    f.write_text(src.replace("[output]", "[output]\nheat_by_mechanism = true") if "[output]" in src
                 else src + "\n[output]\nheat_by_mechanism = true\n")
    out = tmp_path / "out"
    p = subprocess.run([sys.executable, "-m", "dem", "run", str(f), "--out", str(out)],
                       capture_output=True, text=True, cwd=ROOT, env=dict(os.environ, PYTHONPATH=ROOT))
    assert p.returncode == 2 and "output.heat_by_mechanism" in p.stderr and "[thermal]" in p.stderr, p.stderr
    assert not out.exists()


def _toml(sc):
    """The scene dict as TOML text (the few value types the scenes above use)."""
    import json

    def tv(v):
        if isinstance(v, bool):
            return "true" if v else "false"
        if isinstance(v, str):
            return json.dumps(v)
        if isinstance(v, (list, tuple)):
            return "[" + ", ".join(tv(x) for x in v) + "]"
        if isinstance(v, dict):
            return "{ " + ", ".join(f"{k} = {tv(x)}" for k, x in v.items()) + " }"
        if isinstance(v, int):
            return str(v)
        return repr(float(v))
    out, tail = [], []
    for key, val in sc.items():
        if isinstance(val, list):
            for item in val:
                out += [f"[[{key}]]"] + [f"{k} = {tv(x)}" for k, x in item.items()]
            continue
        out.append(f"[{key}]")
        for k, x in val.items():
            if k == "sources":
                for src in x:
                    tail += ["[[thermal.sources]]"] + [f"{a} = {tv(b)}" for a, b in src.items()]
            else:
                out.append(f"{k} = {tv(x)}")
    return "\n".join(out + tail) + "\n"


def test_a_continued_run_writes_the_same_fields(tmp_path):
    """The moving bed with every mechanism, heat_by_mechanism and contacts on, 1000 steps through
    `dem run`, and the same stopped at 500 and continued with --restart: final.npz is
    the same array for array, bit for bit: the split and the contact fields of the steps after
    the restart point are those of the run not stopped (the fused force loop stays off in both,
    the stored conductances come back with the checkpoint)."""
    from dem.final import read as read_final
    sc = scene("auto", True, end=0.002, dt=2e-6)
    sc["simulation"].update(output_interval=0.0005, checkpoint_interval=0.001)
    sc["output"]["contacts"] = True
    f = tmp_path / "bed.toml"
    f.write_text(_toml(sc))
    env = dict(os.environ, PYTHONPATH=ROOT)
    run = lambda *a: subprocess.run([sys.executable, "-m", "dem", "run", str(f), "--quiet", *a],   # noqa: E731
                                    capture_output=True, text=True, cwd=ROOT, env=env)
    for p in (run("--out", str(tmp_path / "a")), run("--out", str(tmp_path / "b"), "--end-time", "0.001"),
              run("--out", str(tmp_path / "b"), "--restart", str(tmp_path / "b" / "checkpoint.npz"))):
        assert p.returncode == 0, p.stderr
    a, b = read_final(tmp_path / "a" / "final.npz"), read_final(tmp_path / "b" / "final.npz")
    assert {k for k in a if k.startswith("heat_")} == {f"heat_{m}" for m in FIELDS} | {"heat_rate"}
    assert "contact_force" in a and "coordination" in a
    for k in a:
        assert np.array_equal(a[k], b[k]), k
    assert (tmp_path / "a" / "contacts.pvd").exists()
