"""Triangle-mesh walls in runs (issue 50): a bed on an STL plane of many triangles is the bed on
the analytic plane, a V of two faces is the two planes, a faceted drum turns its particle like
the cylinder, heat through a mesh wall is the plane's heat, a restart is bit-identical, and bad
meshes are refused through the command line naming the file and the triangle.

Why the tolerances: the mesh and the plane compute the same contact by different arithmetic
(the closest point of a triangle, Ericson's barycentric form, against the plane's dot product),
so one force evaluation agrees to round-off (1e-12 of the force), and a bed of colliding
spheres, which amplifies round-off by its chaotic collisions, stays within 1e-8 m (1e-5 of a
radius) over the runs below. A lost tangential spring where a sphere slides from one triangle
to the next, or a second contact at a shared edge, changes a force by its whole tangential or
normal part (1e-4 N here) and the positions by microns within a few hundred steps."""
import os
import subprocess
import sys

import numpy as np
import pytest

from dem import Simulation
from dem import step as K
from dem.contact.mesh import write_stl

from test_mesh_walls import plane_mesh

R = 1e-3
MAT = dict(name="m", density=2500.0, youngs_modulus=1e7, poisson_ratio=0.3, restitution=0.5, friction=0.5,
           rolling_friction=0.05)
ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


def bed_positions(nx=4, layers=(0.0015, 0.004), half=0.006, seed=3):
    rng = np.random.default_rng(seed)
    pos = np.array([[x, y, z] for x in np.linspace(-half, half, nx) for y in np.linspace(-half, half, nx)
                    for z in layers])
    return pos + rng.uniform(-2e-4, 2e-4, pos.shape)


def scene(walls, pos, end, velocity=(0.03, 0.01, -0.2), thermal=None, dt=2e-6):
    sc = {"simulation": {"time_step": dt, "end_time": end, "gravity": [0, 0, -9.81], "output_interval": end},
          "domain": {"min": [-0.01, -0.01, -0.002], "max": [0.01, 0.01, 0.02]},
          "materials": [dict(MAT)],
          "particles": [{"material": "m", "positions": np.asarray(pos).tolist(), "radius": R,
                         "velocities": [list(velocity)] * len(pos)}],
          "contact": {"rolling": "constant_torque"},
          "walls": walls}
    if thermal is not None:
        sc["thermal"] = thermal
    return sc


@pytest.fixture(scope="module")
def floor_stl(tmp_path_factory):
    """z = 0 over [-0.01, 0.01]^2 as 288 jittered triangles (ASCII STL, 17 digits)."""
    path = tmp_path_factory.mktemp("mesh") / "floor.stl"
    write_stl(str(path), plane_mesh(n=12, size=0.02, jitter=0.3) - [0.01, 0.01, 0.0], binary=False)
    return str(path)


PLANE = {"type": "plane", "name": "floor", "point": [0, 0, 0], "normal": [0, 0, 1], "material": "m"}


def test_one_force_evaluation_on_an_stl_plane_is_the_planes(floor_stl):
    """Spheres pressed into the floor at every kind of place on the triangles: the first force
    evaluation equals the plane's to 1e-12 of the force (one contact each, none doubled)."""
    rng = np.random.default_rng(7)
    g = np.array([[x, y] for x in np.linspace(-0.0085, 0.0085, 8) for y in np.linspace(-0.008, 0.008, 5)])
    pos = np.c_[g + rng.uniform(-2e-4, 2e-4, g.shape), np.full(len(g), R - 2e-5)]   # 2.4 mm apart
    sims = []
    for wall in (PLANE, {"type": "mesh", "name": "floor", "file": floor_stl, "material": "m"}):
        sim = Simulation.from_dict(scene([wall], pos, 2e-6, velocity=(0.05, 0.02, 0.0)))
        sim.run(progress=False)
        sims.append(sim)
    a, b = (s.state for s in sims)
    fmax = np.abs(a.force).max()
    assert fmax > 1e-3   # pressed: the floor's force is there
    assert np.abs(a.force - b.force).max() <= 1e-12 * fmax
    assert np.abs(a.torque - b.torque).max() <= 1e-12 * np.abs(a.torque).max()
    assert sims[0].stepper.last_contacts == sims[1].stepper.last_contacts


def test_a_bed_on_an_stl_plane_is_the_bed_on_the_plane(floor_stl):
    """32 spheres thrown onto the floor slide and roll across hundreds of triangle edges for
    15 000 steps: the same trajectories as on the analytic plane within 1e-8 m, so the
    tangential spring survived every edge crossing."""
    pos = bed_positions()
    runs = []
    for wall in (PLANE, {"type": "mesh", "name": "floor", "file": floor_stl, "material": "m"}):
        sim = Simulation.from_dict(scene([wall], pos, 0.03))
        sim.run(progress=False)
        runs.append(sim.state)
    a, b = runs
    assert a.position[:, 2].min() < R   # the bed rests on the floor
    assert np.abs(a.velocity[:, :2]).max() > 1e-3 or np.abs(a.angular_velocity).max() > 1.0
    assert np.abs(a.position - b.position).max() < 1e-8


def v_walls(stl):
    """A V-groove along y (faces z = |x|) as two planes or one mesh of both faces, with planes
    closing y."""
    side = [{"type": "plane", "point": [0, -0.01, 0], "normal": [0, 1, 0], "material": "m"},
            {"type": "plane", "point": [0, 0.01, 0], "normal": [0, -1, 0], "material": "m"}]
    if stl is None:
        s = 2 ** -0.5
        return [{"type": "plane", "name": "v", "point": [0, 0, 0], "normal": [s, 0, s], "material": "m"},
                {"type": "plane", "name": "v2", "point": [0, 0, 0], "normal": [-s, 0, s], "material": "m"}] + side
    return [{"type": "mesh", "name": "v", "file": stl, "material": "m"}] + side


def test_spheres_in_a_v_groove_of_one_mesh_are_those_between_two_planes(tmp_path):
    """A concave crease: a sphere in the bottom of the V touches both faces of the mesh (two
    wall rows), as it touches both planes; the trajectories of a small heap agree within 1e-8 m."""
    tris = []
    ys = np.linspace(-0.011, 0.011, 7)
    for x0, x1 in ((-0.012, 0.0), (0.0, 0.012)):
        for y0, y1 in zip(ys[:-1], ys[1:]):
            a, b = [x0, y0, abs(x0)], [x1, y0, abs(x1)]
            c, d = [x1, y1, abs(x1)], [x0, y1, abs(x0)]
            tris += [[a, b, c], [a, c, d]]
    stl = str(tmp_path / "v.stl")
    write_stl(stl, np.array(tris))
    rng = np.random.default_rng(11)
    pos = np.c_[rng.uniform(-0.002, 0.002, 12), np.tile(np.linspace(-0.007, 0.007, 6), 2), np.zeros(12)]
    pos[:, 2] = np.abs(pos[:, 0]) + 1.5 * R * 2 ** 0.5 + np.repeat([0.0, 0.003], 6)
    runs = [Simulation.from_dict(scene(v_walls(w), pos, 0.02, velocity=(0.0, 0.0, -0.1))) for w in (None, stl)]
    for sim in runs:
        sim.run(progress=False)
    a, b = (s.state for s in runs)
    assert np.any(np.abs(a.position[:, 0]) < 0.2 * R)  # some sit in the crease, on both faces
    assert np.abs(a.position - b.position).max() < 1e-8
    assert runs[0].stepper.last_contacts == runs[1].stepper.last_contacts


def drum_stl(path, radius=0.01, length=0.022, facets=180):
    """The lateral surface of a cylinder about y as ``facets`` rectangles of two triangles."""
    th = np.linspace(0.0, 2 * np.pi, facets + 1)
    tris = []
    for t0, t1 in zip(th[:-1], th[1:]):
        p = [[radius * np.cos(t), y, radius * np.sin(t)] for t in (t0, t1) for y in (-length / 2, length / 2)]
        tris += [[p[0], p[2], p[3]], [p[0], p[3], p[1]]]
    write_stl(path, np.array(tris))


def test_a_turning_faceted_drum_carries_its_sphere_like_the_cylinder(tmp_path):
    """A sphere at the bottom of a drum from an STL file turning at Omega about its axis: the
    friction sets it rolling until its contact point moves with the wall, v + w x (R n) =
    Omega x r_c, within 2 % (the drum is 180 facets: its radius varies by 1.5e-4 of itself),
    as on the analytic cylinder (tests/test_walls.py)."""
    om = 2.0
    stl = str(tmp_path / "drum.stl")
    drum_stl(stl)
    rc = 0.01 * np.cos(np.pi / 180)   # the facet's distance from the axis
    sc = {"simulation": {"time_step": 5e-6, "end_time": 0.1, "gravity": [0, 0, -9.81]},
          "domain": {"min": [-0.011, -0.011, -0.011], "max": [0.011, 0.011, 0.011]},
          "materials": [dict(MAT)],
          "particles": [{"material": "m", "positions": [[0, 0, -rc + R * 0.999]], "radius": R}],
          "walls": [{"type": "mesh", "file": stl, "material": "m", "angular_velocity": [0, om, 0],
                     "rotation_center": [0, 0, 0]}]}
    sim = Simulation.from_dict(sc)
    sim.run(out_dir=str(tmp_path / "out"), progress=False)
    st = sim.state
    # walls.pvd shows the drum where it is: turned by Omega t about y (x' = x cos + z sin)
    import meshio
    from dem.output import pvd_entries
    t_last, frame = pvd_entries(str(tmp_path / "out" / "walls.pvd"))[-1]
    assert t_last == pytest.approx(0.1)
    pts = meshio.read(tmp_path / "out" / frame).points
    v0 = sim.scene.walls[0]["surface"].verts
    th = om * t_last
    turned = np.c_[v0[:, 0] * np.cos(th) + v0[:, 2] * np.sin(th), v0[:, 1], -v0[:, 0] * np.sin(th) + v0[:, 2] * np.cos(th)]
    assert np.abs(pts - turned).max() < 1e-12
    x = st.position[0]
    n = np.array([x[0], 0.0, x[2]])
    n /= np.linalg.norm(n)
    contact = st.velocity[0] + np.cross(st.angular_velocity[0], R * n)
    wall = np.cross([0, om, 0], rc * n)
    assert np.linalg.norm(contact - wall) < 0.02 * np.linalg.norm(wall)
    assert abs(st.angular_velocity[0, 1]) > 0.5 * om * 0.01 / R
    assert abs(x[1]) < 1e-9   # nothing pushes it along the axis


def test_heat_through_an_stl_floor_is_the_planes(floor_stl, tmp_path):
    """Spheres held on and just above a hot floor (fixed temperature; mechanics frozen, so
    both runs have the same positions): direct conduction through the contacts, indirect
    conduction across the gas gap at the local porosity (the floor's cap cut off each measuring
    sphere): the heat per path in wall_heat.csv and the particle temperatures equal the plane's
    to 1e-9 (relative; the conductances differ by round-off). A floor four times the domain's
    (the mesh reaches beyond the box) gives the same heat, and its area in wall_heat.csv is the
    part inside the box, the plane's section, so the flux is the plane's too."""
    th = {"direct": "batchelor_obrien", "indirect": "cheng_1999_voronoi_a", "porosity": "local",
          "time_step": 0.05, "initial_temperature": 300.0}
    gas = dict(conductivity=0.026, density=1.2, viscosity=1.8e-5, heat_capacity=1005.0, temperature=300.0)
    hot = {"condition": "fixed_temperature", "temperature": 400.0}
    g = np.array([[x, y] for x in np.linspace(-0.0085, 0.0085, 8) for y in np.linspace(-0.008, 0.008, 5)])
    z = np.where(np.arange(len(g)) % 2, R - 1e-5, R + 1e-4)   # in contact, or 0.1 mm above
    pos = np.c_[g + np.random.default_rng(5).uniform(-2e-4, 2e-4, g.shape), z]
    big = tmp_path / "big_floor.stl"
    write_stl(str(big), plane_mesh(n=24, size=0.04, jitter=0.3) - [0.02, 0.02, 0.0], binary=False)
    out = []
    for k, wall in enumerate((PLANE, {"type": "mesh", "name": "floor", "file": floor_stl, "material": "m"},
                              {"type": "mesh", "name": "floor", "file": str(big), "material": "m"})):
        sc = scene([dict(wall, thermal=hot)], pos, 5.0, velocity=(0.0, 0.0, 0.0), thermal=th)
        sc["simulation"]["mechanics"] = False
        sc["gas"] = gas
        sc["materials"][0].update(heat_capacity=840.0, thermal_conductivity=1.0)
        sim = Simulation.from_dict(sc)
        sim.run(out_dir=str(tmp_path / f"o{k}"), progress=False)
        rows = np.genfromtxt(tmp_path / f"o{k}" / "wall_heat.csv", delimiter=",", names=True, dtype=None,
                             encoding="utf-8")
        last = [r for r in rows if float(r["time"]) == rows["time"].max()]
        out.append((sim.state.temperature.copy(), {str(r["mechanism"]): float(r["energy_J"]) for r in last},
                    {str(r["mechanism"]): (float(r["area_m2"]), float(r["heat_flux_W_m2"])) for r in last}))
    (Ta, ea, fa), (Tb, eb, fb), (Tc, ec, fc) = out
    assert ea["total"] > 0 and ea["contact"] > 0 and ea["gas_gap"] > 0
    assert Ta.max() > 301.0   # heated
    assert fa["total"][0] == pytest.approx(0.02 * 0.02, rel=1e-12)   # the box's floor
    for e, f, T in ((eb, fb, Tb), (ec, fc, Tc)):
        for m in ("contact", "gas_gap", "total"):
            assert e[m] == pytest.approx(ea[m], rel=1e-9)
            assert f[m][0] == pytest.approx(fa[m][0], rel=1e-12)
            assert f[m][1] == pytest.approx(fa[m][1], rel=1e-9)
        assert np.abs(Ta - T).max() <= 1e-9 * (Ta.max() - 300.0)


def test_a_restart_across_mesh_contacts_is_bit_identical(floor_stl, tmp_path):
    """Stopped while spheres touch the mesh (six contacts at t = 13 ms, 1.3 ms after the last
    neighbour build) and continued: the same bits as one run. The contact records (dem.schema
    mcon) are saved with the springs; the candidate triangles (mtri) are found again from the
    last build's positions and time (a restart that left them empty misses those contacts)."""
    from dem.final import read as read_final
    sc = scene([{"type": "mesh", "name": "floor", "file": floor_stl, "material": "m"}], bed_positions(), 0.02)
    sc["simulation"]["checkpoint_interval"] = 0.01
    one = Simulation.from_dict(sc)
    one.run(out_dir=str(tmp_path / "one"), progress=False)
    first = Simulation.from_dict(sc)
    first.run(end_time=0.013, out_dir=str(tmp_path / "two"), progress=False)
    st = first.state
    assert np.isfinite(st.mcon[:st.n_owned, :, 0]).sum() >= 4 and st.fp[K.FP.tbuild] < first.time - 1e-4
    second = Simulation.from_dict(sc)
    second.run(out_dir=str(tmp_path / "two"), restart=str(tmp_path / "two" / "checkpoint.npz"), progress=False)
    a, b = (read_final(tmp_path / d / "final.npz") for d in ("one", "two"))
    assert np.array_equal(a["position"], b["position"])
    assert np.array_equal(a["velocity"], b["velocity"])


# ------------------------------------------------------------------ bad input, through the CLI

def _cli(args, cwd):
    env = dict(os.environ, PYTHONPATH=ROOT)
    return subprocess.run([sys.executable, "-m", "dem.cli", *args], cwd=cwd, env=env, capture_output=True,
                          text=True, timeout=300)


def _toml_scene(path, wall, pos=((0.0, 0.0, 0.005),)):
    lines = ["[simulation]", "time_step = 2e-6", "end_time = 2e-5", "",
             "[domain]", "min = [-0.01, -0.01, -0.002]", "max = [0.01, 0.01, 0.02]", "",
             "[[materials]]", 'name = "m"', "density = 2500.0", "youngs_modulus = 1e7", "poisson_ratio = 0.3",
             "restitution = 0.5", "friction = 0.5", "",
             "[[particles]]", 'material = "m"', f"positions = {[[float(c) for c in p] for p in pos]}", "radius = 0.001", "",
             "[[walls]]"] + [f"{k} = {v}" for k, v in wall.items()]
    path.write_text("\n".join(lines) + "\n")
    return path


@pytest.mark.parametrize("case", ["missing", "degenerate", "duplicate", "nan", "away", "overlap", "scale"])
def test_bad_meshes_are_refused_by_the_command_line(tmp_path, case):
    tris = plane_mesh(n=4, size=0.02, jitter=0.0) - [0.01, 0.01, 0.0]
    wall = {"type": '"mesh"', "material": '"m"', "file": '"floor.stl"'}
    pos = ((0.0, 0.0, 0.005),)
    want = None
    if case == "degenerate":
        tris[5, 2] = tris[5, 1]
        want = "triangle 6 is degenerate"
    elif case == "duplicate":
        tris[9] = tris[3][[1, 2, 0]]
        want = "triangle 10 duplicates triangle 4"
    elif case == "nan":
        tris[2, 0, 1] = np.nan
        want = "triangle 3 has a coordinate that is not a finite number"
    elif case == "away":
        wall["translate"] = "[0.0, 0.0, 1.0]"
        want = "does not reach the domain"
    elif case == "overlap":
        pos = ((0.0025, 0.0025, 0.0005),)
        want = "overlaps triangle"
    elif case == "scale":
        wall["scale"] = "-1.0"
        want = "must be"
    if case == "missing":
        wall["file"] = '"nowhere.stl"'
        want = "nowhere.stl: no such file"
    else:
        write_stl(str(tmp_path / "floor.stl"), tris, binary=case != "nan")
    f = _toml_scene(tmp_path / "scene.toml", wall, pos)
    before = sorted(os.listdir(tmp_path))
    for cmd in (["check", str(f)], ["run", str(f), "--out", str(tmp_path / "out"), "--quiet"]):
        r = _cli(cmd, tmp_path)
        assert r.returncode == 2, (r.returncode, r.stdout, r.stderr)
        key = "walls[0].scale" if case == "scale" else "walls[0].file"
        assert f"{f}: {key}: " in r.stderr, r.stderr
        assert want in r.stderr, r.stderr
        assert "Traceback" not in r.stderr
        assert sorted(os.listdir(tmp_path)) == before   # nothing written


# ------------------------------------------------------------------ MPI

def test_a_bed_on_a_mesh_floor_on_two_ranks_is_the_serial_bed(floor_stl, tmp_path):
    """72 spheres thrown onto the STL floor for 0.03 s on 2 MPI ranks (the domain cut in two by
    the default decomposition; each rank holding only the floor's triangles near its box, at most
    3/4 of them, dem.world.World.hold_mesh_near; the contact records migrating with their
    particles): the same final state as one process, within the tolerances of the plane-walled
    MPI runs (tests/test_parallel.py: the ranks sum the pair forces in another order). The
    spheres that cross the cut find their triangles on their new rank (the state would differ
    from the serial one by a sphere falling through the floor otherwise)."""
    import re
    import shutil
    from dem.final import read as read_final
    if shutil.which("mpirun") is None:
        pytest.skip("needs Open MPI (mpirun)")
    pos = bed_positions(nx=6, half=0.006, layers=(0.0015, 0.0045))
    wall = {"type": '"mesh"', "name": '"floor"', "file": f'"{floor_stl}"', "material": '"m"'}
    f = _toml_scene(tmp_path / "bed.toml", wall, [tuple(p) for p in pos])
    src = f.read_text().replace("end_time = 2e-5", "end_time = 0.03\noutput_interval = 0.03")
    src = src.replace("radius = 0.001", "radius = 0.001\nvelocities = " + str([[0.1, 0.0, -0.3]] * len(pos)))
    for x, nx in ((-0.01, 1), (0.01, -1)):   # side walls across the cut
        src += f'\n[[walls]]\ntype = "plane"\nmaterial = "m"\npoint = [{x}, 0.0, 0.0]\nnormal = [{nx}.0, 0.0, 0.0]\n'
    f.write_text(src)
    env = dict(os.environ, PYTHONPATH=ROOT, OMPI_ALLOW_RUN_AS_ROOT="1", OMPI_ALLOW_RUN_AS_ROOT_CONFIRM="1",
               OMPI_MCA_rmaps_base_oversubscribe="1", OMPI_MCA_mpi_yield_when_idle="1")
    outs = {}
    for n in (1, 2):
        out = tmp_path / f"np{n}"
        p = subprocess.run(["mpirun", "-np", str(n), sys.executable, "-m", "dem", "run", str(f), "--out", str(out),
                            "--quiet"], capture_output=True, text=True, env=env, timeout=600)
        assert p.returncode == 0, p.stderr
        outs[n] = read_final(out / "final.npz")
        if n == 2:
            m = re.search(r"mesh triangles held per rank (\d+)-(\d+) of (\d+)", p.stdout)
            assert m, p.stdout
            lo, hi, total = (int(g) for g in m.groups())
            assert 0 < lo <= hi <= 0.75 * total, m.group(0)
    a, b = outs[1], outs[2]
    assert np.array_equal(a["id"], b["id"])
    assert a["position"][:, 2].min() < R   # on the floor
    assert np.abs(a["position"] - b["position"]).max() <= 1e-10
    assert np.abs(a["velocity"] - b["velocity"]).max() <= 1e-7


def test_a_sphere_rides_a_vibrating_stl_floor(floor_stl):
    """The floor oscillates vertically, z_w = A sin(2 pi f t), at Gamma = A (2 pi f)^2 / g = 0.5:
    below 1 the floor never pulls away faster than gravity, so the sphere resting on it rides
    along: its height follows the floor's within 1 % of A (the Hertz overlap changes by 1e-7 m
    as the load swings between 0.5 and 1.5 of its weight), and its vertical velocity the
    floor's, A 2 pi f cos(2 pi f t), within 2 % of the peak (the contact's own ringing)."""
    A, f = 1e-4, 0.5 / (2 * np.pi) * (9.81 / 1e-4) ** 0.5   # Gamma = 0.5: f = 35.3 Hz
    z0 = R - 1.3e-7   # about the overlap of its weight
    sc = scene([{"type": "mesh", "name": "floor", "file": floor_stl, "material": "m",
                 "oscillation": {"amplitude": [0.0, 0.0, A], "frequency": f}}], [[0.0, 0.0, z0]], 2.0 / f, (0, 0, 0))
    sim = Simulation.from_dict(sc)
    om = 2 * np.pi * f
    for k in range(1, 9):   # eight points over a period, after one period of settling in
        t = (1.0 + k / 8.0) / f
        sim.run(end_time=t, progress=False)
        st, t = sim.state, sim.time
        assert st.position[0, 2] - z0 == pytest.approx(A * np.sin(om * t), abs=0.01 * A)
        assert st.velocity[0, 2] == pytest.approx(A * om * np.cos(om * t), abs=0.02 * A * om)
