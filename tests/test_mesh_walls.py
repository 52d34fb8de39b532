"""Triangle-mesh walls, the geometry (dem.contact.mesh; issue 50): reading STL (ASCII and binary)
and what meshio reads, refusing broken meshes by triangle, the contacts of a sphere with a mesh
(one contact on a smooth surface of many triangles, wherever the sphere sits; one per face in a
concave crease; one on a convex edge or corner), and the binned search.

Tolerances: on a flat mesh the closest point is computed from corners that lie exactly in the
plane, so the distance equals the analytic plane's to a few ulps of the coordinates (1e-15 m on
coordinates of 0.1 m); rotated into the scene, the corners carry the rotation's round-off (a few
1e-17 m per coordinate), so 1e-15 m again. The normal's error is the position's round-off over
the distance (1e-17 m / 1e-4 m): 1e-12 allowed."""
import math
import os

import numba
import numpy as np
import pytest

from dem.contact import mesh as M
from dem.errors import SceneError

R = 1e-3   # sphere radius (m)


def plane_mesh(n=20, size=0.1, jitter=0.3, seed=1):
    """z = 0 over [0, size]^2 as n x n squares of two triangles, the inner corners moved in the
    plane by up to ``jitter`` of a square (triangles of every shape and orientation)."""
    rng = np.random.default_rng(seed)
    xs = np.linspace(0.0, size, n + 1)
    X, Y = np.meshgrid(xs, xs, indexing="ij")
    J = rng.uniform(-jitter, jitter, X.shape + (2,)) * (size / n)
    J[0], J[-1], J[:, 0], J[:, -1] = 0.0, 0.0, 0.0, 0.0
    P = np.stack([X + J[..., 0], Y + J[..., 1], np.zeros_like(X)], -1)
    tris = []
    for i in range(n):
        for j in range(n):
            a, b, c, d = P[i, j], P[i + 1, j], P[i + 1, j + 1], P[i, j + 1]
            tris += [[a, b, c], [a, c, d]] if (i + j) % 2 else [[a, b, d], [b, c, d]]
    return np.array(tris)


class Mesh:
    def __init__(self, tris, cell=2.5 * R):
        self.verts, self.faces = M.check_triangles(np.ascontiguousarray(tris, float), "mesh.stl", "walls[0].file")
        self.ev, self.vv = M.valences(self.faces, len(self.verts))
        self.bins = M.bin_triangles(self.verts, self.faces, cell)
        self.cell = cell
        self.stamp = np.zeros(len(self.faces), np.int64)
        self.tag = 0
        self.cand = np.empty(len(self.faces), np.int64)
        self.raw = np.empty((len(self.faces), 8))
        self.out = np.empty((8, 8))

    def contacts(self, p, radius=R):
        self.tag += 1
        n = M.near_triangles(np.asarray(p, float), radius, self.bins, self.stamp, self.tag, self.cand)
        assert n >= 0
        k = M.sphere_contacts(p[0], p[1], p[2], radius, self.verts, self.faces, self.ev, self.vv, self.cand, n,
                              self.raw, self.out)
        return self.out[:k].copy()


# --------------------------------------------------------------------------- files

def test_stl_ascii_and_binary_read_back(tmp_path):
    tris = plane_mesh(6) + np.array([0.0, 0.0, 0.01])
    M.write_stl(tmp_path / "a.stl", tris, binary=False)
    M.write_stl(tmp_path / "b.stl", tris, binary=True)
    a = M.read_triangles(str(tmp_path / "a.stl"))
    b = M.read_triangles(str(tmp_path / "b.stl"))
    assert np.array_equal(a, tris)                                  # 17 digits: float64 exactly
    assert np.array_equal(b, tris.astype(np.float32).astype(np.float64))   # binary STL is float32
    # an OBJ through meshio: the same triangles
    import meshio
    verts, faces = M.weld(tris)
    meshio.write(str(tmp_path / "c.obj"), meshio.Mesh(verts, [("triangle", faces)]))
    c = M.read_triangles(str(tmp_path / "c.obj"))
    assert c.shape == tris.shape and np.abs(c - tris).max() < 1e-12
    # placed: mm from CAD to m, turned 90 degrees about z, moved
    p = M.place(tris * 1000.0, scale=0.001, rotate=(0, 0, 90), translate=(1.0, 0, 0))
    assert np.abs(p[..., 0] - (1.0 - tris[..., 1])).max() < 1e-15
    assert np.abs(p[..., 1] - tris[..., 0]).max() < 1e-15


def _refused(path, *needles):
    with pytest.raises(SceneError) as e:
        tris = M.read_triangles(str(path), "walls[0].file")
        M.check_triangles(tris, str(path), "walls[0].file")
    msg = str(e.value)
    assert msg.startswith(f"{path}: walls[0].file: "), msg
    for s in needles:
        assert s in msg, msg
    return msg


def test_broken_meshes_are_refused_naming_the_triangle(tmp_path):
    tris = plane_mesh(3)
    p = tmp_path / "nan.stl"
    t = tris.copy()
    t[4, 1, 2] = np.nan
    M.write_stl(p, t, binary=False)
    _refused(p, "triangle 5 has a coordinate that is not a finite number")
    t = tris.copy()
    t[2, 2] = t[2, 0]                                              # two corners equal
    M.write_stl(tmp_path / "deg.stl", t, binary=True)
    _refused(tmp_path / "deg.stl", "triangle 3 is degenerate")
    t = tris.copy()
    t[7] = [t[7, 0], t[7, 1], 0.5 * (t[7, 0] + t[7, 1])]           # three corners on a line
    M.write_stl(tmp_path / "line.stl", t, binary=True)
    _refused(tmp_path / "line.stl", "triangle 8 is degenerate")
    t = np.concatenate([tris, tris[[3]][:, [1, 2, 0]]])            # the same corners, turned
    M.write_stl(tmp_path / "dup.stl", t, binary=True)
    _refused(tmp_path / "dup.stl", f"triangle {len(tris) + 1} duplicates triangle 4")
    M.write_stl(tmp_path / "cut.stl", tris, binary=True)
    data = (tmp_path / "cut.stl").read_bytes()
    (tmp_path / "cut.stl").write_bytes(data[:-20])
    _refused(tmp_path / "cut.stl", "not an STL file", "binary (84 + 50 x 18 bytes)")
    M.write_stl(tmp_path / "half.stl", tris, binary=False)
    text = (tmp_path / "half.stl").read_text().splitlines()
    (tmp_path / "half.stl").write_text("\n".join(text[:-10]) + "\n")
    _refused(tmp_path / "half.stl", "not a complete ASCII STL")
    _refused(tmp_path / "none.stl", "no such file")


# --------------------------------------------------------------------------- contacts

def test_a_flat_mesh_of_many_triangles_is_the_analytic_plane():
    """Spheres anywhere over a plane of 800 triangles of every shape, also exactly over their
    corners and edges, below or above it: exactly one contact, at the plane's distance, along
    its normal."""
    m = Mesh(plane_mesh())
    rng = np.random.default_rng(2)
    pts = [np.r_[rng.uniform(0.005, 0.095, 2), 0.0] for _ in range(3000)]
    for _ in range(3000):   # on a corner, on an edge
        t = rng.integers(len(m.faces))
        k = rng.integers(3)
        a, b = m.verts[m.faces[t, k]], m.verts[m.faces[t, (k + 1) % 3]]
        q = a + rng.choice([0.0, 1.0, rng.uniform()]) * (b - a)
        if 0.005 < q[0] < 0.095 and 0.005 < q[1] < 0.095:
            pts.append(q.copy())
    for p in pts:
        p[2] = rng.choice([-1, 1]) * rng.uniform(0.95, 0.9999) * R     # overlaps of up to 5 %
        c = m.contacts(p)
        assert len(c) == 1, (p, c)
        assert abs(c[0, 0] - abs(p[2])) <= 1e-15
        assert np.abs(c[0, 1:4] - [0.0, 0.0, -math.copysign(1.0, p[2])]).max() <= 1e-12
    # out of reach: nothing
    assert len(m.contacts(np.r_[0.05, 0.05, 1.0001 * R])) == 0


def test_a_turned_flat_mesh_is_the_turned_plane():
    tris = M.place(plane_mesh(), rotate=(30.0, -20.0, 50.0), translate=(0.3, -0.1, 0.2))
    m = Mesh(tris)
    n = M.rotation_matrix((30.0, -20.0, 50.0)) @ [0.0, 0.0, 1.0]
    o = np.array([0.3, -0.1, 0.2])
    rng = np.random.default_rng(3)
    for _ in range(2000):
        u = M.rotation_matrix((30.0, -20.0, 50.0)) @ np.r_[rng.uniform(0.005, 0.095, 2), 0.0]
        h = rng.choice([-1, 1]) * rng.uniform(0.95, 0.9999) * R
        c = m.contacts(o + u + h * n)
        assert len(c) == 1
        assert abs(c[0, 0] - abs(h)) <= 1e-15
        assert np.abs(c[0, 1:4] + math.copysign(1.0, h) * n).max() <= 1e-12


def test_a_sphere_rolling_across_shared_edges_feels_one_smooth_contact():
    """Along a line over the plane that crosses some 60 edges and passes near corners, at 1000
    positions: one contact at every position, its distance and normal the same all along
    (no jump where it passes from one triangle to the next)."""
    m = Mesh(plane_mesh())
    for y in (0.0333, 0.05, 0.0714):
        for s in np.linspace(0.005, 0.095, 1000):
            c = m.contacts(np.r_[s, y + 0.2 * (s - 0.05), 0.98 * R])
            assert len(c) == 1
            assert abs(c[0, 0] - 0.98 * R) <= 1e-15 and abs(c[0, 3] + 1.0) <= 1e-12


def v_mesh(half_angle_deg, sign, n=8):
    """Two planes meeting along the y axis, each made of n x n squares, rising (sign = 1: a
    valley, concave from above) or falling (sign = -1: a ridge, convex) at ``half_angle_deg``
    from the horizontal."""
    t = plane_mesh(n, size=0.02, jitter=0.0) - [0.0, 0.01, 0.0]          # x in [0, 0.02]
    s = math.radians(half_angle_deg)
    right = np.stack([t[..., 0] * math.cos(s), t[..., 1], sign * t[..., 0] * math.sin(s)], -1)
    left = right * [-1.0, 1.0, 1.0]
    return np.concatenate([right, left[:, ::-1]])


def test_a_sphere_in_a_concave_crease_touches_each_face_once():
    s = math.radians(30.0)
    m = Mesh(v_mesh(30.0, 1))
    # in the valley: both faces, at the same distance, along their normals
    z = 0.95 * R / math.cos(s)
    c = m.contacts(np.r_[0.0, 0.0013, z])
    assert len(c) == 2
    assert np.allclose(c[:, 0], z * math.cos(s), rtol=0, atol=1e-15)
    normals = sorted(c[:, 1:4].tolist())
    assert np.allclose(normals, [[-math.sin(s), 0, -math.cos(s)], [math.sin(s), 0, -math.cos(s)]], atol=1e-12)
    # beside the valley, over one face only: that face
    c = m.contacts(np.r_[0.004, 0.0013, 0.004 * math.tan(s) + 0.97 * R / math.cos(s)])
    assert len(c) == 1 and abs(c[0, 0] - 0.97 * R) <= 1e-15


def test_a_sphere_on_a_convex_ridge_or_corner_touches_it_once():
    m = Mesh(v_mesh(30.0, -1))
    # over the ridge line: one contact, on the edge, straight down
    c = m.contacts(np.r_[0.0, 0.0017, 0.97 * R])
    assert len(c) == 1 and c[0, 5] == M.EDGE
    assert abs(c[0, 0] - 0.97 * R) <= 1e-15 and np.abs(c[0, 1:4] - [0, 0, -1]).max() <= 1e-12
    # beside it, inside the edge's wedge: the edge, at the distance to the line
    p = np.r_[0.2 * R, 0.0017, 0.9 * R]
    c = m.contacts(p)
    assert len(c) == 1 and c[0, 5] == M.EDGE
    assert abs(c[0, 0] - math.hypot(p[0], p[2])) <= 1e-15
    # a cube's corner (12 triangles): one contact, at the corner, along the diagonal
    cube = []
    for ax in range(3):
        for side in (0.0, 0.01):
            u, v = [(ax + 1) % 3, (ax + 2) % 3]
            q = np.zeros((4, 3))
            q[:, ax] = side
            q[[1, 2], u] = 0.01
            q[[2, 3], v] = 0.01
            cube += [[q[0], q[1], q[2]], [q[0], q[2], q[3]]]
    m = Mesh(np.array(cube))
    d = 0.96 * R
    c = m.contacts(np.full(3, 0.01 + d / math.sqrt(3.0)))
    assert len(c) == 1 and c[0, 5] == M.VERTEX
    assert abs(c[0, 0] - d) <= 1e-15 and np.abs(c[0, 1:4] + 1 / math.sqrt(3.0)).max() <= 1e-12
    # inside the cube, in a corner: the three faces that meet there
    c = m.contacts(np.array([0.96, 0.95, 0.97]) * R)
    assert len(c) == 3 and set(c[:, 5]) == {M.FACE}
    assert np.allclose(sorted(c[:, 0]), np.array([0.95, 0.96, 0.97]) * R, rtol=0, atol=1e-15)
    # ... and on the faces' diagonals (the edge inside each face): still one contact per face
    c = m.contacts(np.full(3, 0.96 * R))
    assert len(c) == 3 and set(c[:, 5]) == {M.EDGE}
    assert np.allclose(c[:, 0], 0.96 * R, rtol=0, atol=1e-15)


# --------------------------------------------------------------------------- the search

@numba.njit
def _distances(p, tris):
    """Brute force: the distance from p to every triangle."""
    out = np.empty(tris.shape[0])
    for q in range(tris.shape[0]):
        t = tris[q]
        x, y, z, _, _ = M.closest_on_triangle(p[0], p[1], p[2], t[0, 0], t[0, 1], t[0, 2], t[1, 0], t[1, 1],
                                              t[1, 2], t[2, 0], t[2, 1], t[2, 2])
        out[q] = math.sqrt((x - p[0]) ** 2 + (y - p[1]) ** 2 + (z - p[2]) ** 2)
    return out


def test_the_binned_search_finds_every_triangle_within_reach_and_few_more():
    """A drum of 9,600 triangles: for 2,000 points, the triangles the bins give include every
    triangle within the reach (brute force over all of them), and are a few dozen, not the mesh."""
    n_th, n_z, Rd, L = 240, 20, 0.1, 0.1
    th = np.linspace(0, 2 * math.pi, n_th + 1)[:-1]
    z = np.linspace(0, L, n_z + 1)
    P = np.stack([Rd * np.cos(th)[:, None] + 0 * z, Rd * np.sin(th)[:, None] + 0 * z, 0 * th[:, None] + z], -1)
    tris = []
    for i in range(n_th):
        for j in range(n_z):
            a, b, c, d = P[i, j], P[(i + 1) % n_th, j], P[(i + 1) % n_th, j + 1], P[i, j + 1]
            tris += [[a, b, c], [a, c, d]]
    tris = np.array(tris)
    m = Mesh(tris)
    lo, cell, dims, keys, start, items = m.bins
    # only the cells near the surface are stored: those whose centre is within half a diagonal
    # of it, a layer about 1.7 cells thick, so about 1.7 x area / cell^2 (not the drum's volume)
    area = 2 * math.pi * Rd * L
    assert keys.size <= 2.0 * area / m.cell ** 2 and keys.size < 0.1 * np.prod(dims)
    rng = np.random.default_rng(4)
    most = 0
    for _ in range(2000):
        r = Rd - rng.uniform(0, 3 * R)
        t = rng.uniform(0, 2 * math.pi)
        p = np.r_[r * math.cos(t), r * math.sin(t), rng.uniform(0.0, L)]
        reach = 1.5 * R
        m.tag += 1
        k = M.near_triangles(p, reach, m.bins, m.stamp, m.tag, m.cand)
        got = set(m.cand[:k].tolist())
        assert len(got) == k
        dist = _distances(p, tris)
        assert set(np.flatnonzero(dist <= reach).tolist()) <= got
        most = max(most, k)
    assert most < 100


def test_a_ranks_triangles_cover_every_place_a_moving_mesh_takes(tmp_path):
    """dem.world.swept_boxes: the kiln shell (examples/data/kiln.stl) turning about a tilted axis
    through an off-centre point while it translates and oscillates: the vertices of each triangle,
    placed at 400 times over the window (dem.contact.mesh.placed_vertices, the motion the contacts
    use), stay inside that triangle's swept box (to 1e-12 m). The boxes are not the whole
    vessel's: a tube of 10 rings turning about its own axis, a triangle's box is as long along the
    axis as the triangle (1e-12 m), and the box x < 0.05 m with a margin of 1 mm holds its first 6
    rings exactly (the sixth starts at 0.05 m; the seventh 10 mm on)."""
    from dem.world import swept_boxes, mesh_selection
    here = os.path.join(os.path.dirname(__file__), "..", "examples", "data", "kiln.stl")
    s = M.Surface(here, "file", scale=0.001)
    axis = np.array([1.0, 0.3, -0.2])
    w = {"type": "mesh", "surface": s, "angular_velocity": 4.0 * axis / np.linalg.norm(axis),
         "rotation_center": np.array([0.05, 0.004, -0.003]), "velocity": np.array([0.01, -0.02, 0.005]),
         "oscillation": {"amplitude": [0.0, 0.001, 0.0005], "frequency": 7.0, "phase": 30.0}}
    t0, t1 = 0.2, 1.7
    lo, hi = swept_boxes(w, t0, t1)
    for t in np.linspace(t0, t1, 400):
        v = M.placed_vertices(w, t)[s.faces]     # (n, 3, 3)
        assert np.all(v >= lo[:, None, :] - 1e-12) and np.all(v <= hi[:, None, :] + 1e-12), t
    # a tube of radius 25 mm and length 100 mm along x in 10 rings of 24 quads
    th = np.linspace(0.0, 2 * np.pi, 25)
    xs = np.linspace(0.0, 0.1, 11)
    ring = lambda x, a: [x, 0.025 * np.cos(a), 0.025 * np.sin(a)]   # noqa: E731
    tris = []
    for i in range(10):
        for k in range(24):
            p00, p01 = ring(xs[i], th[k]), ring(xs[i], th[k + 1])
            p10, p11 = ring(xs[i + 1], th[k]), ring(xs[i + 1], th[k + 1])
            tris += [[p00, p10, p11], [p00, p11, p01]]
    path = tmp_path / "tube.stl"
    M.write_stl(str(path), np.array(tris))
    tube = M.Surface(str(path), "file")
    turn = {"type": "mesh", "surface": tube, "angular_velocity": np.array([3.0, 0.0, 0.0]),
            "rotation_center": np.array([0.05, 0.0, 0.0]), "velocity": np.zeros(3)}
    lo, hi = swept_boxes(turn, 0.0, 10.0)
    tri = tube.verts[tube.faces]
    assert np.allclose(lo[:, 0], tri[:, :, 0].min(axis=1), atol=1e-12, rtol=0)
    assert np.allclose(hi[:, 0], tri[:, :, 0].max(axis=1), atol=1e-12, rtol=0)
    inf = np.inf
    (half,) = mesh_selection([turn], [-inf, -inf, -inf], [0.05, inf, inf], 0.001, 0.0, 10.0)
    assert len(half) == 288   # the 5 rings below x = 0.05 m and the one from there; the next, 10 mm on
