"""A few thousand monodisperse spheres settled by gravity on a floor, periodic in x and y
(so the bulk is free of side walls): bulk packing fraction in the random-packing range,
lower with more friction, no particle lost, bed at rest."""
import math

import numpy as np
import pytest

from dem import Simulation

R = 1e-3
L = 0.02


def slab_fraction(z, r, z1, z2, area):
    """Exact solid fraction of the slab z1 < z < z2 (sum of sphere segments)."""
    a = np.clip(z1 - z, -r, r)
    b = np.clip(z2 - z, -r, r)
    seg = math.pi * (r ** 2 * (b - a) - (b ** 3 - a ** 3) / 3)
    return seg.sum() / (area * (z2 - z1))


def settle(friction, n=2000):
    scene = {
        "simulation": {"time_step": 1e-5, "end_time": 0.45, "gravity": [0, 0, -9.81], "seed": 3},
        "domain": {"min": [0, 0, 0], "max": [L, L, 0.1], "periodic": [True, True, False]},
        "materials": [dict(name="g", density=2500.0, youngs_modulus=1e7, poisson_ratio=0.25,
                           restitution=0.3, friction=friction)],
        "particles": [{"material": "g", "count": n, "radius": R,
                       "region": {"type": "box", "min": [0, 0, 0.001], "max": [L, L, 0.099]}}],
        "walls": [{"type": "plane", "point": [0, 0, 0], "normal": [0, 0, 1], "material": "g"}],
    }
    sim = Simulation.from_dict(scene)
    sim.run(progress=False)
    return sim


@pytest.fixture(scope="module")
def beds():
    return {mu: settle(mu) for mu in (0.05, 0.5)}


def test_settled_bed(beds):
    fractions = {}
    for mu, sim in beds.items():
        st = sim.state
        assert st.n == 2000
        assert np.all(np.isfinite(st.position))
        assert st.position[:, 2].min() > 0.5 * R  # nobody through the floor
        top = np.percentile(st.position[:, 2], 95)
        phi = slab_fraction(st.position[:, 2], st.radius, 4 * R, top - 4 * R, L * L)
        fractions[mu] = phi
        assert 0.55 <= phi <= 0.64, (mu, phi)
        # at rest: largest speed below 1 % of the free-fall speed over one diameter
        vmax = np.linalg.norm(st.velocity, axis=1).max()
        assert vmax < 0.01 * math.sqrt(2 * 9.81 * 2 * R), vmax
    assert fractions[0.5] < fractions[0.05] - 0.01
