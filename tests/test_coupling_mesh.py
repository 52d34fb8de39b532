"""Tests of the particle-to-mesh coupling: polyMesh reader, geometry,
point location, void fraction, exchange-term accumulation, drag closures
and interpolation.  All meshes are small (2 shared cores)."""
import math
import os
import time
import warnings

import numpy as np
import pytest

from coupling import drag as D
from coupling import voidfraction as VF
from coupling.interpolate import cell_gradient, interpolate
from coupling.mesh import (PolyMesh, read_foam_list, read_polymesh, structured_hex_mesh,
                           write_polymesh)


# --------------------------------------------------------------------------
# mesh generators
# --------------------------------------------------------------------------
def uniform_X(n=(6, 5, 4), L=(1.2, 1.0, 0.8), origin=(0.1, -0.2, 0.3)):
    axes = [np.linspace(o, o + l, k + 1) for o, l, k in zip(origin, L, n)]
    return np.stack(np.meshgrid(*axes, indexing="ij"), -1)


def distorted_X(n=(7, 6, 5), seed=0, perturb=0.0):
    """Non-uniform spacing + shear (non-orthogonal, planar faces); with
    ``perturb`` > 0 interior points are moved randomly (warped faces)."""
    rng = np.random.default_rng(seed)
    axes = []
    for k in n:
        h = rng.uniform(0.5, 1.5, k)
        axes.append(np.concatenate([[0.0], np.cumsum(h)]) / h.sum())
    x, y, z = np.meshgrid(*axes, indexing="ij")
    X = np.stack([x + 0.35 * y + 0.15 * z, y + 0.25 * z + 0.1 * x, z], -1)
    if perturb > 0:
        hmin = min(np.diff(a).min() for a in axes)
        inner = (slice(1, -1),) * 3
        X[inner] += perturb * hmin * rng.uniform(-1, 1, X[inner].shape)
    return X


def mesh_from_X(X, tmp_path=None, style="multiline"):
    arrays = structured_hex_mesh(X)
    if tmp_path is None:
        return PolyMesh(*arrays)
    d = os.path.join(str(tmp_path), "constant", "polyMesh")
    write_polymesh(d, *arrays, style=style)
    return read_polymesh(str(tmp_path))


def random_points_in_hull(mesh, n, seed):
    rng = np.random.default_rng(seed)
    return mesh.bbox_lo + (mesh.bbox_hi - mesh.bbox_lo) * rng.random((n, 3))


# --------------------------------------------------------------------------
# reader and geometry
# --------------------------------------------------------------------------
@pytest.mark.parametrize("style", ["multiline", "compact"])
def test_reader_roundtrip_and_geometry(tmp_path, style):
    X = distorted_X(perturb=0.2)
    arrays = structured_hex_mesh(X)
    m_mem = PolyMesh(*arrays)
    m = mesh_from_X(X, tmp_path, style)
    for a, b in zip(arrays[:5], (m.points, m.face_offsets, m.face_points, m.owner, m.neighbour)):
        np.testing.assert_array_equal(a, b)
    assert [p["nFaces"] for p in m.boundary] == [p["nFaces"] for p in arrays[5]]
    assert m.boundary[0]["name"] == "xmin" and m.boundary[0]["type"] == "wall"
    np.testing.assert_allclose(m.cell_volumes, m_mem.cell_volumes, rtol=0, atol=0)
    # closed cells: sum of outward area vectors vanishes
    S = np.zeros((m.n_cells, 3))
    np.add.at(S, np.repeat(np.arange(m.n_cells), np.diff(m.cf_off)),
              m.cf_normal * m.face_mag[m.cf_face][:, None])
    assert np.abs(S).max() < 1e-14
    # total volume = volume enclosed by the boundary (divergence theorem)
    nb = m.n_internal_faces
    vol_b = np.sum(np.einsum("ij,ij->i", m.face_centres[nb:], m.face_areas[nb:])) / 3.0
    assert abs(m.cell_volumes.sum() - vol_b) < 1e-13


def test_uniform_geometry_exact():
    m = mesh_from_X(uniform_X())
    np.testing.assert_allclose(m.cell_volumes, 0.2 * 0.2 * 0.2, rtol=1e-13)
    ug = m.uniform_grid
    assert ug is not None and tuple(ug.dims) == (6, 5, 4)
    # cell (1,2,3) centre
    c = 1 + 6 * (2 + 5 * 3)
    np.testing.assert_allclose(m.cell_centres[c], [0.1 + 0.3, -0.2 + 0.5, 0.3 + 0.7], atol=1e-14)
    assert mesh_from_X(distorted_X()).uniform_grid is None


def test_reader_formats(tmp_path):
    hdr = "FoamFile\n{\n version 2.0;\n format ascii;\n class %s;\n object %s;\n}\n// comment\n"
    (tmp_path / "owner").write_text(hdr % ("labelList", "owner") + "4{7}\n")
    np.testing.assert_array_equal(read_foam_list(str(tmp_path / "owner")), [7, 7, 7, 7])
    (tmp_path / "nb").write_text(hdr % ("labelList", "neighbour") + "/* c */ 3(1 2 3)\n")
    np.testing.assert_array_equal(read_foam_list(str(tmp_path / "nb")), [1, 2, 3])
    (tmp_path / "faces").write_text(hdr % ("faceList", "faces") + "2(3(0 1 2) 4(1 2 3 4))")
    off, idx = read_foam_list(str(tmp_path / "faces"))
    np.testing.assert_array_equal(off, [0, 3, 7])
    np.testing.assert_array_equal(idx, [0, 1, 2, 1, 2, 3, 4])
    (tmp_path / "fc").write_text(hdr % ("faceCompactList", "faces")
                                 + "3(0 3 7)\n7(0 1 2 1 2 3 4)\n")
    off2, idx2 = read_foam_list(str(tmp_path / "fc"))
    np.testing.assert_array_equal(off2, off)
    np.testing.assert_array_equal(idx2, idx)
    (tmp_path / "points").write_text(hdr % ("vectorField", "points")
                                     + "2\n(\n(0 0 0)\n(1e-3 2 -3.5)\n)\n")
    np.testing.assert_array_equal(read_foam_list(str(tmp_path / "points")),
                                  [[0, 0, 0], [1e-3, 2, -3.5]])
    (tmp_path / "bin").write_text((hdr % ("labelList", "owner")).replace("ascii", "binary") + "3(")
    with pytest.raises(NotImplementedError, match="foamFormatConvert"):
        read_foam_list(str(tmp_path / "bin"))
    (tmp_path / "bad").write_text(hdr % ("labelList", "owner") + "5(1 2 3)")
    with pytest.raises(ValueError, match="5 labels"):
        read_foam_list(str(tmp_path / "bad"))


# --------------------------------------------------------------------------
# locate
# --------------------------------------------------------------------------
def test_locate_uniform_grid(tmp_path):
    m = mesh_from_X(uniform_X(), tmp_path)
    pts = random_points_in_hull(m, 3000, 1)
    pts = np.vstack([pts, m.bbox_lo - 0.01, m.bbox_hi + 0.01])  # two outside points
    ref, cnt = m.locate_brute_force(pts)
    assert cnt[:-2].min() == 1 and (ref[-2:] == -1).all()
    gen = m.locate(pts, method="general")
    fast = m.locate(pts, method="uniform")
    np.testing.assert_array_equal(gen, ref)
    np.testing.assert_array_equal(fast, ref)
    # points exactly on the domain boundary are inside
    corner = np.array([m.bbox_lo, m.bbox_hi])
    assert (m.locate(corner, method="uniform") >= 0).all()
    assert (m.locate(corner, method="general") >= 0).all()
    # hinted: from the right cell, from a wrong cell, after a small move
    np.testing.assert_array_equal(m.locate(pts, hint=ref, method="general"), ref)
    wrong = np.roll(ref, 7)
    np.testing.assert_array_equal(m.locate(pts, hint=wrong, method="general"), ref)


@pytest.mark.parametrize("perturb", [0.0, 0.25])
def test_locate_distorted_mesh(tmp_path, perturb):
    m = mesh_from_X(distorted_X(perturb=perturb), tmp_path)
    assert m.uniform_grid is None
    pts = random_points_in_hull(m, 4000, 2)
    ref, cnt = m.locate_brute_force(pts)
    assert (ref == -1).sum() > 100          # the sheared hull has outside points
    unique = cnt <= 1                       # warped faces: skip ambiguous points
    if perturb == 0.0:
        assert unique.all()                 # planar faces: a partition
    else:
        assert unique.mean() > 0.97
    for hint in (None, np.roll(ref, 11), np.where(ref >= 0, ref, 0)):
        got = m.locate(pts, hint=hint)
        np.testing.assert_array_equal(got[unique], ref[unique])
        # an ambiguous point must be in one of its containing cells
        amb = ~unique
        for p in np.nonzero(amb)[0]:
            c = got[p]
            dmax = np.max(np.einsum("ij,ij->i", pts[p] - m.cf_centre[m.cf_off[c]:m.cf_off[c + 1]],
                                    m.cf_normal[m.cf_off[c]:m.cf_off[c + 1]]))
            assert dmax <= m.tol
    # moving particles: small displacement, hint = previous cell
    inside = ref >= 0
    rng = np.random.default_rng(3)
    moved = pts[inside] + 0.05 * rng.uniform(-1, 1, (inside.sum(), 3))
    r2, c2 = m.locate_brute_force(moved)
    ok = c2 <= 1
    np.testing.assert_array_equal(m.locate(moved, hint=ref[inside])[ok], r2[ok])


def test_locate_speed_1e5():
    m = mesh_from_X(distorted_X(n=(20, 20, 20), perturb=0.2))
    pts = random_points_in_hull(m, 100_000, 4)
    m.locate(pts[:10])
    t0 = time.perf_counter()
    c = m.locate(pts)
    t1 = time.perf_counter()
    m.locate(pts, hint=c)
    t2 = time.perf_counter()
    print(f"\nlocate 1e5 points, 8000-cell distorted mesh: no hint {t1 - t0:.4f} s, "
          f"hint {t2 - t1:.4f} s")
    assert t1 - t0 < 5.0 and t2 - t1 < 2.0


# --------------------------------------------------------------------------
# void fraction
# --------------------------------------------------------------------------
def particles(mesh, n, rmax, seed):
    rng = np.random.default_rng(seed)
    pts = random_points_in_hull(mesh, 4 * n, seed)
    cells = mesh.locate(pts)
    pts = pts[cells >= 0][:n]
    r = rng.uniform(0.3, 1.0, len(pts)) * rmax
    return pts, r


@pytest.mark.parametrize("model", VF.MODELS)
def test_void_fraction_conserves_volume(model):
    m = mesh_from_X(distorted_X(perturb=0.2))
    pos, r = particles(m, 500, 0.03, 5)
    vp = 4.0 / 3.0 * np.pi * r ** 3
    eps, pw = VF.void_fraction(m, pos, r, model, eps_min=0.0, return_weights=True)
    assert pw.n_lost == 0
    np.testing.assert_allclose(pw.weights.sum(axis=1), 1.0, rtol=0, atol=1e-14)
    vs = VF.solid_volume(pw, r)
    assert abs(vs.sum() - vp.sum()) <= 1e-12 * vp.sum()
    assert abs(np.sum((1 - eps) * m.cell_volumes) - vp.sum()) <= 1e-12 * vp.sum()
    # exchange terms use the same weights: cell integrals equal particle sums
    rng = np.random.default_rng(6)
    beta = rng.uniform(1e-5, 1e-3, len(r))
    hA = rng.uniform(1e-4, 1e-2, len(r))
    Tp = rng.uniform(300, 900, len(r))
    K = VF.drag_coefficient_sum(pw, beta, m.cell_volumes)
    Simp, Sexp = VF.heat_sources(pw, hA, Tp, m.cell_volumes)
    for cellq, pq in ((K, beta), (Simp, hA), (Sexp, hA * Tp)):
        assert abs(np.sum(cellq * m.cell_volumes) - pq.sum()) <= 1e-12 * pq.sum()
    u = rng.normal(size=(len(r), 3))
    Us = VF.mean_particle_velocity(pw, r, u)
    solid_mom = VF.accumulate(pw, u * vp[:, None])
    np.testing.assert_allclose(Us * vs[:, None], solid_mom, atol=1e-15)
    np.testing.assert_allclose(np.sum(Us * vs[:, None], axis=0), np.sum(u * vp[:, None], axis=0),
                               rtol=1e-12, atol=1e-18)


def test_smoothed_fast_path_bitwise_equal_to_reference():
    """compute_weights' smoothed stencil (precomputed h^2 per cell, preallocated buffers,
    located= skipping the second locate) and the one-quantity scatter of solid_volume are
    bitwise equal to the reference kernel + accumulate (no change of results)."""
    m = mesh_from_X(distorted_X(perturb=0.2))
    pos, r = particles(m, 800, 0.03, 11)
    cells = m.locate(pos)
    off, nbrs = m.point_neighbours()
    kmax = int(np.diff(off).max())
    c_ref, w_ref = VF._smoothed_kernel(pos, cells, m.cell_centres, m.cell_volumes, off, nbrs, 1.5, kmax)
    ref = VF.ParticleWeights("smoothed", c_ref, w_ref, cells, m.n_cells)
    vs_ref = VF.accumulate(ref, np.broadcast_to(VF.particle_volumes(r), (len(r),)))
    pw = VF.compute_weights(m, pos, r, "smoothed", located=cells)
    assert np.array_equal(pw.cells, c_ref)
    assert np.array_equal(pw.weights.view(np.uint64), w_ref.view(np.uint64))
    assert np.array_equal(VF.solid_volume(pw, r).view(np.uint64), vs_ref.view(np.uint64))
    # buffer reuse: overwritten in place, still the same result for other positions
    pos2, r2 = particles(m, 800, 0.03, 12)
    c2 = m.locate(pos2)
    pw2 = VF.compute_weights(m, pos2, r2, "smoothed", located=c2, out=pw)
    assert pw2.cells is pw.cells
    c_ref2, w_ref2 = VF._smoothed_kernel(pos2, c2, m.cell_centres, m.cell_volumes, off, nbrs, 1.5, kmax)
    assert np.array_equal(pw2.cells, c_ref2) and np.array_equal(pw2.weights, w_ref2)
    with pytest.raises(ValueError, match="located"):
        VF.compute_weights(m, pos, r, "smoothed", located=cells[:-1])


@pytest.mark.parametrize("model", ["centre", "divided"])
def test_sphere_inside_cell_exact(model):
    m = mesh_from_X(distorted_X(perturb=0.1))
    c = 100
    r = 0.2 * np.cbrt(m.cell_volumes[c])
    eps = VF.void_fraction(m, m.cell_centres[c:c + 1], [r], model)
    exact = 1.0 - 4.0 / 3.0 * np.pi * r ** 3 / m.cell_volumes[c]
    assert abs(eps[c] - exact) < 1e-14
    others = np.delete(eps, c)
    assert (others == 1.0).all()


def test_smoothed_spreads_and_is_continuous():
    m = mesh_from_X(uniform_X(n=(8, 8, 8), L=(1, 1, 1), origin=(0, 0, 0)))
    r = 0.02
    vp = 4.0 / 3.0 * np.pi * r ** 3
    c = 3 + 8 * (3 + 8 * 3)
    pw = VF.compute_weights(m, m.cell_centres[c:c + 1], [r], "smoothed")
    # h = 1.5 dx: centre, 6 face and 12 edge neighbours; corners (sqrt(3) dx) get 0
    assert (pw.cells[0] >= 0).sum() == 19
    vs = VF.solid_volume(pw, [r])
    assert vs[c] == vs.max() and abs(vs.sum() - vp) < 1e-12 * vp
    # moving across the face x = 0.5: continuous deposit on a uniform grid
    x0 = np.array([0.5, 0.43, 0.47])
    dx = np.array([1e-7, 0, 0])
    a = VF.solid_volume(VF.compute_weights(m, [x0 - dx], [r], "smoothed"), [r])
    b = VF.solid_volume(VF.compute_weights(m, [x0 + dx], [r], "smoothed"), [r])
    assert np.abs(a - b).max() < 1e-5 * vp
    # whereas centre jumps by the whole volume
    a = VF.solid_volume(VF.compute_weights(m, [x0 - dx], [r], "centre"), [r])
    b = VF.solid_volume(VF.compute_weights(m, [x0 + dx], [r], "centre"), [r])
    assert np.abs(a - b).max() == pytest.approx(vp)


def cap_fraction(h, r):
    """Fraction of a sphere of radius r beyond a plane at distance h from its
    centre (0 <= h <= r)."""
    return np.pi * (r - h) ** 2 * (2 * r + h) / 3.0 / (4.0 / 3.0 * np.pi * r ** 3)


# Worst-case |fraction error| of the satellite sets for axis-aligned cuts
# over all cut heights (measured over 801 heights, 6 axis directions):
#   N = 29 -> 0.076,  N = 257 -> 0.025   (mean over random planes 0.022 / 0.005)
# i.e. about 2/N^(2/3); test tolerances 0.08 and 0.03.
@pytest.mark.parametrize("n_sat,tol", [(29, 0.08), (257, 0.03)])
def test_divided_cut_sphere(n_sat, tol):
    m = mesh_from_X(uniform_X(n=(2, 1, 1), L=(2, 1, 1), origin=(0, 0, 0)))
    r = 0.3
    errs = []
    for h in np.linspace(0.0, 0.29, 30):
        for sgn in (1, -1):
            x = np.array([1.0 - sgn * h, 0.5, 0.5])   # plane x = 1 between the cells
            pw = VF.compute_weights(m, [x], [r], "divided", n_satellites=n_sat)
            vs = VF.solid_volume(pw, [r]) / (4.0 / 3.0 * np.pi * r ** 3)
            far = 1 if sgn == 1 else 0            # cell not containing the centre
            errs.append(abs(vs[far] - cap_fraction(h, r)))
    print(f"\ndivided N={n_sat}: max cap-fraction error {max(errs):.4f}, mean {np.mean(errs):.4f}")
    assert max(errs) < tol


def test_void_fraction_clipping_and_cell_size_warning():
    m = mesh_from_X(uniform_X(n=(2, 2, 2), L=(1, 1, 1), origin=(0, 0, 0)))
    r = 0.3  # 4/3 pi r^3 = 0.113 > 0.7 * 0.125 -> eps = 0.095 < eps_min
    with pytest.warns(RuntimeWarning, match="clipped"):
        eps = VF.void_fraction(m, [[0.25, 0.25, 0.25]], [r], "centre", eps_min=0.3)
    assert eps.min() == 0.3
    with pytest.warns(RuntimeWarning, match="particle diameters"):
        assert not VF.check_cell_size(m.cell_volumes, [0.1])
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert VF.check_cell_size(m.cell_volumes, [0.05])
    with pytest.raises(ValueError, match="centre, divided, smoothed"):
        VF.compute_weights(m, [[0.1, 0.1, 0.1]], [0.01], "nearest")


def test_void_fraction_speed_1e5():
    m = mesh_from_X(uniform_X(n=(30, 30, 30), L=(1, 1, 1), origin=(0, 0, 0)))
    rng = np.random.default_rng(7)
    pos = rng.random((100_000, 3))
    r = np.full(len(pos), 0.004)   # cells 0.033 = 4 d
    times = {}
    for model in VF.MODELS:
        VF.void_fraction(m, pos[:10], r[:10], model)
        t0 = time.perf_counter()
        VF.void_fraction(m, pos, r, model, warn=False)
        times[model] = time.perf_counter() - t0
    print("\nvoid fraction 1e5 particles, 27000 cells: "
          + ", ".join(f"{k} {v:.3f} s" for k, v in times.items()))
    assert max(times.values()) < 10.0


# --------------------------------------------------------------------------
# drag
# --------------------------------------------------------------------------
RHO, MU = 1.2, 1.8e-5


def test_gidaspow_packed_bed_equals_ergun():
    d, eps = 1e-3, 0.4
    for Us in (1e-3, 0.05, 0.5):                      # superficial velocity
        ur = Us / eps                                 # interstitial slip
        dpdx = (150 * MU * (1 - eps) ** 2 * Us / (eps ** 3 * d ** 2)
                + 1.75 * RHO * (1 - eps) * Us ** 2 / (eps ** 3 * d))  # Ergun -dp/dx
        vp = math.pi * d ** 3 / 6
        per_particle = dpdx * vp / (1 - eps)          # bed pressure drop per particle
        f_drag = D.gidaspow_1994(d, eps, RHO, MU, ur) * ur
        f_gradp = D.pressure_gradient_force(d, np.array([-dpdx, 0, 0]))[0]
        assert abs(f_drag + f_gradp - per_particle) <= 1e-10 * per_particle
        assert abs(f_drag - eps * per_particle) <= 1e-10 * per_particle


def test_di_felice_single_particle_limit():
    d = 2e-3
    for ur in (1e-4, 0.01, 0.3, 5.0, 80.0):
        Re = RHO * d * ur / MU
        cd = (0.63 + 4.8 / math.sqrt(Re)) ** 2
        ref = 0.5 * cd * RHO * math.pi * d ** 2 / 4 * ur
        got = D.di_felice_1994(d, 1.0, RHO, MU, ur)
        assert abs(got - ref) <= 1e-10 * ref
        # and the eps -> 1 limit is continuous
        assert abs(D.di_felice_1994(d, 1 - 1e-9, RHO, MU, ur) - ref) <= 1e-7 * ref
        # Gidaspow / Wen-Yu at eps = 1: Schiller-Naumann single-particle drag
        cd_sn = 24 / Re * (1 + 0.15 * Re ** 0.687) if Re < 1000 else 0.44
        assert abs(D.wen_yu_beta(d, 1 - 1e-12, RHO, MU, ur) * (math.pi * d ** 3 / 6) / 1e-12
                   - 0.5 * cd_sn * RHO * math.pi * d ** 2 / 4 * ur) < 1e-3 * ref
    # finite at zero slip
    for name in D.DRAG_MODELS:
        b = D.drag_coefficient(D.drag_model_id(name), d, 0.6, RHO, MU, 0.0)
        assert np.isfinite(b) and b > 0


def test_gidaspow_switch_discontinuity_documented():
    """Gidaspow switches at eps = 0.8 and is NOT continuous there: in the
    Stokes limit Wen-Yu/Ergun = 3.6*0.8^-2.65/7.5 = 0.8671 (13.3 % jump);
    the Huilin-Gidaspow blend is continuous."""
    d = 1e-3
    below = D.gidaspow_1994(d, 0.8 - 1e-12, RHO, MU, 1e-9)
    above = D.gidaspow_1994(d, 0.8, RHO, MU, 1e-9)
    assert above / below == pytest.approx(3.6 * 0.8 ** -2.65 / 7.5, rel=1e-5)
    assert abs(above / below - 0.8671) < 1e-4
    # the jump depends on Re (inertial Ergun term vs Wen-Yu Re^0.687):
    # Re_p = rho d eps ur / mu = 0.53, 5.3, 53, 533, 5333 ->
    # Wen-Yu/Ergun = 0.923, 0.975, 0.697, 0.330, 0.272 (documented in docs/models.md)
    for ur, ratio in ((0.01, 0.9228), (0.1, 0.9746), (1.0, 0.6969), (10.0, 0.3296), (100.0, 0.2716)):
        r = D.gidaspow_1994(d, 0.8, RHO, MU, ur) / D.gidaspow_1994(d, 0.8 - 1e-12, RHO, MU, ur)
        assert r == pytest.approx(ratio, abs=1e-4)
    for ur in (1e-3, 0.1, 1.0, 10.0):
        b1 = D.huilin_gidaspow_2003(d, 0.8 - 1e-9, RHO, MU, ur)
        b2 = D.huilin_gidaspow_2003(d, 0.8 + 1e-9, RHO, MU, ur)
        assert abs(b1 - b2) < 1e-6 * b1


def test_beetstra_limits():
    d = 1e-3
    # Stokes single sphere: beta_p -> 3 pi mu d
    assert D.beetstra_2007(d, 1.0, RHO, MU, 0.0) == pytest.approx(3 * math.pi * MU * d, rel=1e-12)
    # Stokes dense: eps * (10 phi/eps^2 + eps^2 (1 + 1.5 sqrt(phi))) * 3 pi mu d
    eps = 0.5
    F0 = 10 * 0.5 / 0.25 + 0.25 * (1 + 1.5 * math.sqrt(0.5))
    assert D.beetstra_2007(d, eps, RHO, MU, 0.0) == pytest.approx(3 * math.pi * MU * d * eps * F0,
                                                                  rel=1e-12)
    # monotone in slip velocity
    b = [D.beetstra_2007(d, 0.6, RHO, MU, u) for u in (0.01, 0.1, 1, 10)]
    assert all(x < y for x, y in zip(b, b[1:]))


def test_drag_registry_and_dispatch():
    d, eps, ur = 5e-4, 0.55, 0.7
    for name, fn in (("di_felice_1994", D.di_felice_1994), ("gidaspow_1994", D.gidaspow_1994),
                     ("beetstra_2007", D.beetstra_2007),
                     ("huilin_gidaspow_2003", D.huilin_gidaspow_2003)):
        mid = D.drag_model_id(name)
        assert D.drag_coefficient(mid, d, eps, RHO, MU, ur) == fn(d, eps, RHO, MU, ur)
    assert D.drag_model_id("DiFelice") == D.drag_model_id("difelice") == 0
    with pytest.raises(ValueError, match="di_felice_1994, gidaspow_1994"):
        D.drag_model_id("stokes")
    with pytest.raises(ValueError, match="valid ids"):
        D.drag_model_id(17)
    arr = D.drag_coefficients(2, np.full(3, d), np.full(3, eps), RHO, MU, np.array([0.1, 0.2, 0.3]))
    assert arr[1] == D.beetstra_2007(d, eps, RHO, MU, 0.2)
    np.testing.assert_allclose(D.buoyancy_force(d, RHO, np.array([0, 0, -9.81])),
                               [0, 0, RHO * math.pi * d ** 3 / 6 * 9.81])


# --------------------------------------------------------------------------
# interpolation
# --------------------------------------------------------------------------
def test_interpolation_linear_exact_and_bounded():
    m = mesh_from_X(distorted_X(perturb=0.2))
    a = np.array([0.3, -1.2, 2.0])
    f = 5.0 + m.cell_centres @ a
    U = np.stack([f, 2 * f, -f], 1)
    g = cell_gradient(m, f)
    np.testing.assert_allclose(g, np.broadcast_to(a, g.shape), atol=1e-11)
    pts = random_points_in_hull(m, 2000, 8)
    cells = m.locate(pts)
    ins = cells >= 0
    lin = interpolate(m, f, pts, cells, "linear")
    np.testing.assert_allclose(lin[ins], 5.0 + pts[ins] @ a, atol=1e-11)
    assert np.isnan(lin[~ins]).all()
    linU = interpolate(m, U, pts, cells, "linear")
    np.testing.assert_allclose(linU[ins, 1], 2 * (5.0 + pts[ins] @ a), atol=1e-10)
    np.testing.assert_array_equal(interpolate(m, f, pts, cells, "cell")[ins], f[cells[ins]])
    idw = interpolate(m, f, pts, cells, "idw")
    off, nb = m.face_neighbours()
    for p in np.nonzero(ins)[0][:200]:
        c = cells[p]
        st = np.concatenate([[c], nb[off[c]:off[c + 1]]])
        assert f[st].min() - 1e-12 <= idw[p] <= f[st].max() + 1e-12
    # IDW at a cell centre returns the cell value
    c0 = 50
    assert interpolate(m, f, m.cell_centres[c0:c0 + 1], [c0], "idw")[0] == pytest.approx(f[c0], rel=1e-12)
    with pytest.raises(ValueError, match="cell, idw, linear"):
        interpolate(m, f, pts, cells, "cubic")


@pytest.mark.parametrize("distorted", [False, True])
def test_local_mesh_locates_like_the_whole_mesh(distorted):
    """PolyMesh.subset (a DEM rank's local mesh): the cells of one half, numbered locally, keep
    the whole mesh's volumes and centres bit for bit, each cell stays closed (its outward face
    areas sum to zero, the cut faces turned to point out of it), a point in one of its cells is
    located in that cell (the lattice fast path and the general walk alike) and a point in a
    cell it does not hold in none; the real patches keep their names, the cut faces none."""
    m = mesh_from_X(distorted_X(perturb=0.2) if distorted else uniform_X())
    keep = np.flatnonzero(m.cell_centres[:, 0] < np.median(m.cell_centres[:, 0]))
    s = m.subset(keep)
    assert s.n_cells == keep.size < m.n_cells and np.array_equal(s.global_ids, keep) and s.n_global == m.n_cells
    assert np.array_equal(s.cell_volumes, m.cell_volumes[keep]) and np.array_equal(s.cell_centres, m.cell_centres[keep])
    assert (s.uniform_grid is not None) == (not distorted)
    S = np.zeros((s.n_cells, 3))
    np.add.at(S, s.owner, s.face_areas)
    np.add.at(S, s.neighbour, -s.face_areas[:s.n_internal_faces])
    assert np.abs(S).max() <= 1e-12 * np.abs(s.face_areas).max()
    assert [p["name"] for p in s.boundary] == [p["name"] for p in m.boundary]
    assert sum(p["nFaces"] for p in s.boundary) + s.n_cut_faces + s.n_internal_faces == s.n_faces
    assert s.n_cut_faces > 0
    pts = random_points_in_hull(m, 3000, seed=3)
    g = m.locate(pts)
    inside = np.isin(g, keep)
    assert inside.any() and (~inside).any()
    for method in ("auto", "general"):
        c = s.locate(pts, method=method)
        assert np.array_equal(s.global_ids[c[inside]], g[inside]), method
        assert np.all(c[~inside] == -1), method
    assert s.nbytes() < m.nbytes()


def test_local_mesh_from_gas_pieces_equals_the_one_from_the_whole_mesh(tmp_path, solver):
    """MeshPieces (a DEM rank rebuilding its local mesh after a re-cut): the fluidized bed's mesh
    decomposed by decomposePar into 3 pieces across x (hierarchical: processor faces turned
    round in one of the two pieces). Read from all pieces, the cells are the whole mesh's, bit
    for bit (centres, volumes, face tables); read for the region of the bottom 30 % of the bed,
    only the pieces overlapping it are read and the local mesh cut from them equals the one cut
    from the whole mesh in every array, and locates every point alike."""
    import shutil
    from coupling import foam_case as fc
    from coupling.mesh import MeshPieces
    case = tmp_path / "fb"
    shutil.copytree(os.path.join(os.path.dirname(__file__), "..", "openfoam_cases", "fluidized_bed_heating"), case)
    d = case / "system" / "decomposeParDict"
    d.write_text(d.read_text().replace("method          simple;", "method          hierarchical;"))
    fc.block_mesh(case)
    fc.decompose(case, 3, split=(3, 1, 1))
    w = read_polymesh(str(case))
    flipped = sum(int(np.sum(read_foam_list(str(case / f"processor{k}/constant/polyMesh/faceProcAddressing")) < 0))
                  for k in range(3))
    assert flipped > 0
    P = MeshPieces(case, w.n_cells, w.uniform_grid, w.tol)
    full = P.read([(w.bbox_lo, w.bbox_hi)])
    assert sorted(full.pieces) == ["processor0", "processor1", "processor2"]
    s = full.subset(np.arange(w.n_cells))
    assert np.array_equal(s.global_ids, np.arange(w.n_cells))
    for a in ("cell_centres", "cell_volumes", "cell_vlo", "cell_vhi", "cf_off", "cf_centre", "cf_normal", "cf_nbr"):
        assert np.array_equal(getattr(s, a), getattr(w, a)), a
    # a region touching one piece only (x below the first cut)
    hi = w.bbox_hi.copy()
    hi[0] = w.bbox_lo[0] + 0.2 * (w.bbox_hi[0] - w.bbox_lo[0])
    part = P.read([(w.bbox_lo, hi)])
    assert part.pieces == ["processor0"]
    ids = np.flatnonzero(np.all(w.cell_centres <= hi, axis=1))
    a, b = w.subset(ids), part.subset(np.searchsorted(part.global_ids, ids))
    for k in ("global_ids", "cell_centres", "cell_volumes", "cf_off", "cf_centre", "cf_normal", "cf_nbr",
              "face_areas", "owner", "neighbour"):
        assert np.array_equal(getattr(a, k), getattr(b, k)), k
    pts = random_points_in_hull(w, 4000, seed=5)
    assert np.array_equal(a.locate(pts), b.locate(pts))
    assert (a.locate(pts) >= 0).any()
