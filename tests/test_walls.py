"""Cylinder and bounded-plane walls, moving walls, periodic boundaries."""
import math

import numpy as np
import pytest

from dem import Simulation

R = 1e-3
MAT = dict(name="m", density=2500.0, youngs_modulus=1e7, poisson_ratio=0.3, restitution=0.8, friction=0.5)


def run(scene, steps=None):
    sim = Simulation.from_dict(scene)
    sim.run(progress=False)
    return sim


def test_cylinder_inside_restitution():
    """A sphere moving radially inside a cylinder bounces back with the restitution."""
    sc = {"simulation": {"time_step": 2e-6, "end_time": 0.02, "gravity": [0, 0, 0]},
          "domain": {"min": [-0.02] * 3, "max": [0.02] * 3},
          "materials": [dict(MAT)],
          "particles": [{"material": "m", "positions": [[0.005, 0, 0]], "radius": R, "velocities": [[1.0, 0, 0]]}],
          "walls": [{"type": "cylinder", "point": [0, 0, 0], "axis": [0, 0, 1], "radius": 0.01, "material": "m"}]}
    sim = run(sc)
    assert sim.state.velocity[0, 0] == pytest.approx(-0.8, rel=0.01)
    assert abs(sim.state.velocity[0, 1]) < 1e-12


def test_cylinder_outside():
    sc = {"simulation": {"time_step": 2e-6, "end_time": 0.02, "gravity": [0, 0, 0]},
          "domain": {"min": [-0.02] * 3, "max": [0.02] * 3},
          "materials": [dict(MAT)],
          "particles": [{"material": "m", "positions": [[0.01, 0, 0]], "radius": R, "velocities": [[-1.0, 0, 0]]}],
          "walls": [{"type": "cylinder", "point": [0, 0, 0], "axis": [0, 0, 1], "radius": 0.005, "inside": False,
                     "material": "m"}]}
    sim = run(sc)
    assert sim.state.velocity[0, 0] == pytest.approx(0.8, rel=0.01)


def test_rotating_drum_drags_particle():
    """A sphere resting at the bottom of a drum turning at omega is set spinning by the
    wall friction until its contact point moves with the wall surface (no slip):
    v + w x (-R e_z) = Omega x r_c."""
    om = 2.0
    sc = {"simulation": {"time_step": 5e-6, "end_time": 0.1, "gravity": [0, 0, -9.81]},
          "domain": {"min": [-0.011, -0.011, -0.011], "max": [0.011, 0.011, 0.011]},
          "materials": [dict(MAT)],
          "particles": [{"material": "m", "positions": [[0, 0, -0.01 + R * 0.999]], "radius": R}],
          "walls": [{"type": "cylinder", "point": [0, 0, 0], "axis": [0, 1, 0], "radius": 0.01, "material": "m",
                     "angular_velocity": [0, om, 0]}]}
    sim = run(sc)
    st = sim.state
    x = st.position[0]
    n = x / np.linalg.norm(x)  # from the drum axis (y) to the particle: towards the wall
    n[1] = 0.0
    n /= np.linalg.norm(n)
    contact = st.velocity[0] + np.cross(st.angular_velocity[0], R * n)
    wall = np.cross([0, om, 0], 0.01 * n)
    assert np.linalg.norm(contact - wall) < 0.02 * np.linalg.norm(wall)
    assert abs(st.angular_velocity[0, 1]) > 0.5 * om * 0.01 / R


def test_bounded_plane_edge():
    """A finite plate catches a sphere above it and lets one beside it fall past."""
    sc = {"simulation": {"time_step": 5e-6, "end_time": 0.05, "gravity": [0, 0, -9.81]},
          "domain": {"min": [-0.02, -0.02, -0.05], "max": [0.02, 0.02, 0.02]},
          "materials": [dict(MAT)],
          "particles": [{"material": "m", "positions": [[0, 0, 0.003], [0.01, 0, 0.003]], "radius": R}],
          "walls": [{"type": "plane", "point": [0, 0, 0], "normal": [0, 0, 1], "extent": [0.004, 0.004],
                     "material": "m"}]}
    sim = run(sc)
    z = sim.state.position[np.argsort(sim.state.id), 2]
    assert z[0] > 0.0  # held by the plate
    assert z[1] < -0.005  # fell past its edge


def test_periodic_collision_across_boundary():
    """Two spheres meeting across a periodic boundary collide like any pair."""
    sc = {"simulation": {"time_step": 2e-6, "end_time": 0.01, "gravity": [0, 0, 0]},
          "domain": {"min": [0, 0, 0], "max": [0.01, 0.01, 0.01], "periodic": [True, True, True]},
          "materials": [dict(MAT)],
          "particles": [{"material": "m", "positions": [[0.0005, 0.005, 0.005], [0.0095, 0.005, 0.005]],
                         "radius": 4e-4, "velocities": [[-0.5, 0, 0], [0.5, 0, 0]]}]}
    sim = run(sc)
    v = sim.state.velocity[np.argsort(sim.state.id), 0]
    assert v[0] == pytest.approx(0.4, rel=0.01)
    assert v[1] == pytest.approx(-0.4, rel=0.01)
    assert np.all((sim.state.position >= 0) & (sim.state.position < 0.01))
