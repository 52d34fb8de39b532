"""benchmarks/cost: the scenes of the cost table enable exactly the mechanism they are named
after, and the no-heat build can still be made (no timing here)."""
import os
import sys

import pytest

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
if ROOT not in sys.path:
    sys.path.insert(0, ROOT)

from benchmarks.cost import run as cost  # noqa: E402
from dem import reports  # noqa: E402
from dem import scene as scene_mod  # noqa: E402
from dem.thermal import registry as R  # noqa: E402
from dem.world import World  # noqa: E402


def small(d):
    """The scene with a 3 x 3 x 3 lattice of touching spheres instead of the 10k packing."""
    pos = [[0.01 + 0.00199 * a, 0.01 + 0.00199 * b, 0.001 + 0.00199 * c]
           for a in range(3) for b in range(3) for c in range(3)]
    d["particles"] = [{"material": d["materials"][0]["name"], "positions": pos, "radius": 0.001}]
    return d


VARIANTS = cost.variants(small(cost.load(cost.MECH_TOML)), small(cost.load(cost.HEAT_TOML)))


class Reported:
    """What cost.enabled reads of a Simulation (its models_report and thermal), built from the
    scene's World without the Simulation's stepper. Simulation.from_dict(scene) is
    Simulation(scene_mod.parse(...)); its models_report is reports.models_report(world, par)
    (par: None in one process) and its thermal is world.thermal, so what this test asserts is
    read from the same objects. The stepper added by the Simulation only makes the first call
    of the step kernel, which compiled a heat kernel per variant (up to 40 s each with a cold
    cache) that nothing asserted here reads. (Checked once on all 18 variants: both report
    lists equal, line for line.)"""

    def __init__(self, scene, base_dir, name):
        self.world = World(scene_mod.parse(scene, name, base_dir=base_dir))
        self.thermal = self.world.thermal

    def models_report(self):
        return reports.models_report(self.world, None)


def test_every_model_has_a_row():
    keys = {v.key for v in VARIANTS}
    for mech, names in (("indirect", cost.INDIRECT), ("convection", cost.CONVECTION),
                        ("radiation", cost.RADIATION)):
        assert set(names) == set(R.valid_names(mech))
        assert set(names) <= keys
    assert {"mechanics", "direct", "sources"} <= keys
    assert len(keys) == len(VARIANTS)


@pytest.mark.parametrize("v", VARIANTS, ids=[v.key for v in VARIANTS])
def test_variant_enables_exactly_its_mechanism(v):
    sim = Reported(v.scene, base_dir=cost.BENCH, name=v.key)
    got = cost.enabled(sim)
    if v.expect is None:  # mechanics only: no thermal section, nothing thermal runs
        assert not got.pop("thermal")
        assert set(got.values()) <= {"none", 0}
        return
    assert got == dict(v.expect, thermal=True)
    others = [k for k in cost.MECHANISM_KEYS if k != "direct" and got[k] != "none"]
    if v.key == "direct":
        assert others == [] and got["sources"] == 0 and got["direct"] != "none"
    elif v.mechanism == "generation":
        assert others == [] and got["sources"] == 1
    else:
        assert len(others) == 1 and got["sources"] == 0


def test_heat_switch_is_there_to_compile_out():
    with open(os.path.join(ROOT, "dem", "step.py")) as f:
        assert f.read().count(cost.HEAT_SWITCH) == 2  # compute_forces and advance
