"""Every example scene validates, passes its time-step checks and runs a few steps."""
import glob
import os

import numpy as np
import pytest

from dem import Simulation

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
EXAMPLES = sorted(glob.glob(os.path.join(ROOT, "examples", "*.toml")))


@pytest.mark.parametrize("path", EXAMPLES, ids=[os.path.basename(p) for p in EXAMPLES])
def test_example_runs(path):
    sim = Simulation.from_file(path)
    rep = sim.check()
    assert rep["problems"] == []
    sim.step(20)
    assert np.all(np.isfinite(sim.state.position))
    if sim.thermal is not None:
        T = sim.state.temperature
        assert np.all(np.isfinite(T)) and T.min() > 0
        assert sim.last_contacts > 0


def test_check_warns_of_large_impact_overlap():
    """A 2 m/s impact of soft spheres (E = 1e6 Pa) overlaps 0.19 R by Hertz theory
    ((15 m* v^2 / (16 E* sqrt(R*)))^(2/5)): dem check warns before the overlap guard would stop it."""
    sc = {"simulation": {"time_step": 1e-6, "end_time": 0.01, "gravity": [0, 0, 0]},
          "domain": {"min": [-0.01] * 3, "max": [0.01] * 3},
          "materials": [dict(name="m", density=2500.0, youngs_modulus=1e6, poisson_ratio=0.3, restitution=0.5)],
          "contact": {"characteristic_velocity": 2.0},
          "particles": [{"material": "m", "positions": [[0, 0, 0]], "radius": 1e-3}]}
    rep = Simulation.from_dict(sc).check()
    R, m = 1e-3, 4 / 3 * np.pi * 1e-9 * 2500
    estar = 1e6 / (2 * (1 - 0.09))
    expected = (15 * (m / 2) * 4.0 / (16 * estar * np.sqrt(R / 2))) ** 0.4 / R
    assert rep["impact_overlap_ratio"] == pytest.approx(expected, rel=1e-12)
    assert any("overlap guard" in w for w in rep["warnings"])


def test_dem_check_prints_the_impact_accuracy_limit(tmp_path, capsys):
    """dem check names the step that resolves impacts to 1 % (0.02 t_H, from the Hertz impact
    work-precision sweep) when the scene's step is above it, and stays quiet below it."""
    from dem.cli import ACCURATE_HERTZ_FRACTION, main

    def scene(dt):
        p = tmp_path / f"pair_{dt:g}.toml"
        p.write_text(f"""
[simulation]
time_step = {float(dt)!r}
end_time = {float(100 * dt)!r}
[domain]
min = [-0.01, -0.01, -0.01]
max = [0.01, 0.01, 0.01]
[[materials]]
name = "m"
density = 2500.0
youngs_modulus = 1e7
poisson_ratio = 0.3
restitution = 0.5
[[particles]]
material = "m"
positions = [[0.0, 0.0, 0.0], [0.0025, 0.0, 0.0]]
radius = 1e-3
""")
        return str(p)

    rep = Simulation.from_file(scene(1e-6)).check()
    limit = ACCURATE_HERTZ_FRACTION * rep["hertz_time"]
    main(["check", scene(0.05 * rep["hertz_time"])])   # stable (< 0.1 t_H), not 1 % accurate
    assert f"for dt <= {ACCURATE_HERTZ_FRACTION} t_H = {limit:.3g} s" in capsys.readouterr().out
    main(["check", scene(0.5 * limit)])
    assert "accuracy: impacts" not in capsys.readouterr().out
