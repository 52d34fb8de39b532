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
