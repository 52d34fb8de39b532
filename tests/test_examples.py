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
