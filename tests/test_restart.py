"""A run split in two by a checkpoint restart follows the same trajectory (1e-12)."""
import numpy as np

from dem import Simulation
from dem.final import read as read_final


def scene():
    return {
        "simulation": {"time_step": 1e-5, "end_time": 0.04, "gravity": [0, 0, -9.81], "seed": 5,
                       "output_interval": 0.01, "checkpoint_interval": 0.02, "sort_interval": 700},
        "domain": {"min": [0, 0, 0], "max": [0.01, 0.01, 0.04]},
        "materials": [dict(name="g", density=2500.0, youngs_modulus=5e6, poisson_ratio=0.3,
                           restitution=0.5, friction=0.4, rolling_friction=0.05)],
        "contact": {"rolling": "epsd"},
        "particles": [{"material": "g", "count": 300, "radius": {"distribution": "uniform", "min": 4e-4, "max": 6e-4},
                       "region": {"type": "box", "min": [0, 0, 0], "max": [0.01, 0.01, 0.02]}}],
        "walls": [{"type": "plane", "point": [0, 0, 0], "normal": [0, 0, 1], "material": "g"},
                  {"type": "plane", "point": [0, 0, 0], "normal": [1, 0, 0], "material": "g"},
                  {"type": "plane", "point": [0.01, 0, 0], "normal": [-1, 0, 0], "material": "g"},
                  {"type": "plane", "point": [0, 0, 0], "normal": [0, 1, 0], "material": "g"},
                  {"type": "plane", "point": [0, 0.01, 0], "normal": [0, -1, 0], "material": "g"}],
    }


def test_restart_matches_single_run(tmp_path):
    one = Simulation.from_dict(scene())
    one.run(out_dir=str(tmp_path / "one"), progress=False)
    a = read_final(tmp_path / "one" / "final.npz")

    first = Simulation.from_dict(scene())
    first.run(end_time=0.02, out_dir=str(tmp_path / "two"), progress=False)
    ck = tmp_path / "two" / "checkpoint.npz"
    second = Simulation.from_dict(scene())
    second.run(out_dir=str(tmp_path / "two"), restart=str(ck), progress=False)
    b = read_final(tmp_path / "two" / "final.npz")
    # the steps each run did (the speed that `dem run` prints counts these, not the restart's step)
    assert (one.steps_run, first.steps_run, second.steps_run) == (4000, 2000, 2000)

    assert np.array_equal(a["id"], b["id"])
    scale = np.abs(a["position"]).max()
    assert np.abs(a["position"] - b["position"]).max() <= 1e-12 * scale
    assert np.abs(a["velocity"] - b["velocity"]).max() <= 1e-12 * max(np.abs(a["velocity"]).max(), 1e-30) + 1e-15
    # history.csv continues without duplicates
    h = np.genfromtxt(tmp_path / "two" / "history.csv", delimiter=",", names=True)
    assert np.all(np.diff(h["time"]) > 0)
    assert h["time"][-1] == 0.04
