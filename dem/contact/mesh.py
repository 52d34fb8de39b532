"""Triangle-mesh walls: reading a CAD surface (STL, ASCII or binary; other formats meshio reads),
checking it, welding it into vertices and faces with their edge neighbours, and the contacts of
a sphere with it (issue 50).

The contacts of one sphere with one mesh are its closest points on the candidate triangles
(Ericson, *Real-Time Collision Detection*, 2005, sec. 5.1.5: the closest point of a triangle to
a point, by the Voronoi regions of its vertices, edges and face), each tagged with the feature
it lies on: the face's interior, an edge or a vertex. A sphere over a smooth surface sees the
same point from every triangle that shares the edge or the vertex under it, and sees the edges
of the neighbours of the face it touches; counting those would push it twice. Of the raw
closest points within the radius we keep (the rule of Hu, Hu, Jin and Dong, *Powder Technol.*
246 (2013) 498; Kremmer and Favier, *Int. J. Numer. Meth. Eng.* 51 (2001) 1407: a feature
contact counts only when no contact of a larger feature that contains it does):

* every face contact;
* an edge contact unless a triangle with a face contact holds that edge, or the same edge was
  already kept;
* a vertex contact unless a triangle with a face contact, or a kept edge, holds that vertex, or
  the same vertex was already kept.

So a sphere on a flat surface of many triangles has exactly the analytic plane's one contact,
wherever it sits, and a sphere in a concave crease (a valley, the corner of a hopper) keeps one
contact per face it touches. Triangles are stored in the mesh's own (reference) frame; a
moving mesh moves the sphere's centre into that frame instead (rigid motion), so the triangles,
their bins and their neighbours never change during a run.
"""
from __future__ import annotations

import math
import os
import re

import numpy as np
from numba import njit

from ..errors import SceneError
from ..schema import slots
from .walls import WI

FACE, EDGE, VERTEX = 0, 1, 2


# --------------------------------------------------------------------------- reading

def read_triangles(path, key="file"):
    """The triangles of a surface file as an (n, 3, 3) float64 array (triangle, corner, xyz):
    STL, ASCII or binary, read here; OBJ, PLY, OFF and the other formats meshio reads through
    meshio (its triangle cells; quads are split in two). Raises SceneError naming the file."""
    if not os.path.isfile(path):
        raise SceneError(path, key, "no such file (give the path of an STL file, relative to the scene file)")
    ext = os.path.splitext(path)[1].lower()
    if ext == ".stl":
        with open(path, "rb") as fh:
            data = fh.read()
        return _stl(path, key, data)
    try:
        import meshio
        m = meshio.read(path)
    except Exception as e:  # noqa: BLE001 (meshio raises many kinds for a file it cannot read)
        raise SceneError(path, key, f"not a surface meshio can read ({type(e).__name__}: {e}); "
                                    "give an STL file (ASCII or binary) or an OBJ/PLY/OFF file") from None
    pts = np.asarray(m.points, float)
    if pts.shape[1] == 2:
        pts = np.c_[pts, np.zeros(len(pts))]
    tris = []
    for block in m.cells:
        if block.type == "triangle":
            tris.append(pts[block.data])
        elif block.type == "quad":
            q = block.data
            tris.append(pts[q[:, [0, 1, 2]]])
            tris.append(pts[q[:, [0, 2, 3]]])
    if not tris:
        raise SceneError(path, key, "holds no triangles (a surface mesh of triangles or quads is needed)")
    return np.ascontiguousarray(np.concatenate(tris), dtype=np.float64)


def _stl(path, key, data):
    n_bin = int.from_bytes(data[80:84], "little") if len(data) >= 84 else -1
    if len(data) >= 84 and len(data) == 84 + 50 * n_bin:
        rec = np.dtype([("normal", "<f4", 3), ("v", "<f4", (3, 3)), ("attr", "<u2")])
        arr = np.frombuffer(data, rec, count=n_bin, offset=84)
        tris = arr["v"].astype(np.float64)
    elif data.lstrip()[:5].lower() == b"solid":
        text = data.decode("ascii", errors="replace")
        nums = re.findall(r"^\s*vertex\s+(\S+)\s+(\S+)\s+(\S+)", text, re.M | re.I)
        n_facets = len(re.findall(r"^\s*endfacet\b", text, re.M | re.I))
        try:
            v = np.array(nums, dtype=np.float64)
        except ValueError as e:
            raise SceneError(path, key, f"an ASCII STL vertex is not three numbers ({e})") from None
        if v.shape[0] != 3 * n_facets or n_facets == 0:
            raise SceneError(path, key, f"not a complete ASCII STL: {n_facets} facets, {v.shape[0]} vertices "
                                        "(three 'vertex x y z' lines per facet)")
        tris = v.reshape(-1, 3, 3)
    else:
        raise SceneError(path, key, f"not an STL file: {len(data)} bytes, neither ASCII ('solid' ... 'endsolid') "
                                    f"nor binary (84 + 50 x {n_bin} bytes)")
    if tris.shape[0] == 0:
        raise SceneError(path, key, "holds no triangles")
    return np.ascontiguousarray(tris)


# --------------------------------------------------------------------------- placing and checking

def rotation_matrix(degrees):
    """Rotation by ``degrees`` = (about x, about y, about z), applied in that order (x first)."""
    ax, ay, az = (math.radians(float(a)) for a in degrees)
    cx, sx, cy, sy, cz, sz = math.cos(ax), math.sin(ax), math.cos(ay), math.sin(ay), math.cos(az), math.sin(az)
    rx = np.array([[1, 0, 0], [0, cx, -sx], [0, sx, cx]])
    ry = np.array([[cy, 0, sy], [0, 1, 0], [-sy, 0, cy]])
    rz = np.array([[cz, -sz, 0], [sz, cz, 0], [0, 0, 1]])
    return rz @ ry @ rx


def place(tris, scale=1.0, rotate=(0.0, 0.0, 0.0), translate=(0.0, 0.0, 0.0)):
    """x -> R (scale x) + translate: the file's units (mm from CAD: scale = 0.001) to metres,
    then turned and moved into the scene."""
    s = np.broadcast_to(np.asarray(scale, float), (3,))
    out = (tris * s) @ rotation_matrix(rotate).T + np.asarray(translate, float)
    return np.ascontiguousarray(out)


def check_triangles(tris, path, key):
    """Refuse a mesh with a triangle that is not finite, degenerate (a zero or near-zero area:
    two corners equal or all three on a line) or a duplicate of another (the same three corners),
    naming the first such triangle as it is numbered in the file (from 1)."""
    bad = ~np.isfinite(tris).all(axis=(1, 2))
    if bad.any():
        k = int(np.flatnonzero(bad)[0])
        raise SceneError(path, key, f"triangle {k + 1} has a coordinate that is not a finite number "
                                    f"({tris[k].tolist()})")
    a, b, c = tris[:, 0], tris[:, 1], tris[:, 2]
    area2 = np.linalg.norm(np.cross(b - a, c - a), axis=1)
    longest = np.max(np.stack([np.linalg.norm(b - a, axis=1), np.linalg.norm(c - b, axis=1),
                               np.linalg.norm(a - c, axis=1)]), axis=0)
    # a sliver whose height is below 1e-9 of its longest side has no usable normal
    small = area2 <= 1e-9 * longest ** 2
    if small.any():
        k = int(np.flatnonzero(small)[0])
        raise SceneError(path, key, f"triangle {k + 1} is degenerate (area {0.5 * area2[k]:.3g}, corners "
                                    f"{tris[k].tolist()}): remove it or repair the mesh")
    verts, faces = weld(tris)
    key3 = np.sort(faces, axis=1)
    _, first, inv = np.unique(key3, axis=0, return_index=True, return_inverse=True)
    inv = inv.reshape(-1)
    dup = first[inv] != np.arange(len(faces))
    if dup.any():
        k = int(np.flatnonzero(dup)[0])
        raise SceneError(path, key, f"triangle {k + 1} duplicates triangle {int(first[inv[k]]) + 1} "
                                    "(the same three corners): remove one of them")
    return verts, faces


def weld(tris, tol=1e-9):
    """Vertices (nv, 3) and faces (n, 3) of a triangle soup: corners closer than ``tol`` of the
    mesh's size are one vertex (STL stores every corner of every triangle)."""
    pts = tris.reshape(-1, 3)
    size = float(np.max(np.ptp(pts, axis=0))) or 1.0
    q = np.round(pts / (tol * size)).astype(np.int64)
    _, first, inv = np.unique(q, axis=0, return_index=True, return_inverse=True)
    verts = np.ascontiguousarray(pts[first])
    faces = np.ascontiguousarray(inv.reshape(-1, 3).astype(np.int64))
    return verts, faces


# --------------------------------------------------------------------------- closest points

@njit(cache=True, error_model="numpy")
def closest_on_triangle(px, py, pz, ax, ay, az, bx, by, bz, cx, cy, cz):
    """The point of triangle abc closest to p (Ericson 2005, sec. 5.1.5) and its feature:
    returns (qx, qy, qz, kind, index) with kind FACE (index 0), EDGE (index 0: ab, 1: bc,
    2: ca) or VERTEX (index 0: a, 1: b, 2: c)."""
    abx, aby, abz = bx - ax, by - ay, bz - az
    acx, acy, acz = cx - ax, cy - ay, cz - az
    apx, apy, apz = px - ax, py - ay, pz - az
    d1 = abx * apx + aby * apy + abz * apz
    d2 = acx * apx + acy * apy + acz * apz
    if d1 <= 0.0 and d2 <= 0.0:
        return ax, ay, az, VERTEX, 0
    bpx, bpy, bpz = px - bx, py - by, pz - bz
    d3 = abx * bpx + aby * bpy + abz * bpz
    d4 = acx * bpx + acy * bpy + acz * bpz
    if d3 >= 0.0 and d4 <= d3:
        return bx, by, bz, VERTEX, 1
    vc = d1 * d4 - d3 * d2
    if vc <= 0.0 and d1 >= 0.0 and d3 <= 0.0:
        v = d1 / (d1 - d3)
        return ax + v * abx, ay + v * aby, az + v * abz, EDGE, 0
    cpx, cpy, cpz = px - cx, py - cy, pz - cz
    d5 = abx * cpx + aby * cpy + abz * cpz
    d6 = acx * cpx + acy * cpy + acz * cpz
    if d6 >= 0.0 and d5 <= d6:
        return cx, cy, cz, VERTEX, 2
    vb = d5 * d2 - d1 * d6
    if vb <= 0.0 and d2 >= 0.0 and d6 <= 0.0:
        w = d2 / (d2 - d6)
        return ax + w * acx, ay + w * acy, az + w * acz, EDGE, 2
    va = d3 * d6 - d5 * d4
    if va <= 0.0 and (d4 - d3) >= 0.0 and (d5 - d6) >= 0.0:
        w = (d4 - d3) / ((d4 - d3) + (d5 - d6))
        return bx + w * (cx - bx), by + w * (cy - by), bz + w * (cz - bz), EDGE, 1
    denom = 1.0 / (va + vb + vc)
    v = vb * denom
    w = vc * denom
    return (ax + abx * v + acx * w, ay + aby * v + acy * w, az + abz * v + acz * w, FACE, 0)


@njit(cache=True, error_model="numpy", inline="always")
def _near_segment(qx, qy, qz, ax, ay, az, bx, by, bz, h):
    """Whether the point q is within h of the segment from a to b."""
    ex = bx - ax
    ey = by - ay
    ez = bz - az
    rx = qx - ax
    ry = qy - ay
    rz = qz - az
    e2 = ex * ex + ey * ey + ez * ez
    s = min(max((rx * ex + ry * ey + rz * ez) / e2, 0.0), 1.0)
    dx = rx - s * ex
    dy = ry - s * ey
    dz = rz - s * ez
    return dx * dx + dy * dy + dz * dz <= h * h


@njit(cache=True, error_model="numpy")
def _snap(qx, qy, qz, ax, ay, az, bx, by, bz, cx, cy, cz, kind, idx):
    """The feature of a closest point q of the triangle (a, b, c), decided by distance (within
    1e-10 of the triangle's perimeter): a point on a shared edge or vertex gets the same feature
    from every triangle that holds it, whatever the round-off of each one's region tests.
    (Scalars only: called for every contact, where arrays would cost their reference counts.)"""
    h = (math.sqrt((bx - ax) ** 2 + (by - ay) ** 2 + (bz - az) ** 2)
         + math.sqrt((cx - bx) ** 2 + (cy - by) ** 2 + (cz - bz) ** 2)
         + math.sqrt((ax - cx) ** 2 + (ay - cy) ** 2 + (az - cz) ** 2))
    h *= 1e-10
    if (qx - ax) ** 2 + (qy - ay) ** 2 + (qz - az) ** 2 <= h * h:
        return VERTEX, 0
    if (qx - bx) ** 2 + (qy - by) ** 2 + (qz - bz) ** 2 <= h * h:
        return VERTEX, 1
    if (qx - cx) ** 2 + (qy - cy) ** 2 + (qz - cz) ** 2 <= h * h:
        return VERTEX, 2
    if kind == VERTEX:
        return kind, idx
    if _near_segment(qx, qy, qz, ax, ay, az, bx, by, bz, h):
        return EDGE, 0
    if _near_segment(qx, qy, qz, bx, by, bz, cx, cy, cz, h):
        return EDGE, 1
    if _near_segment(qx, qy, qz, cx, cy, cz, ax, ay, az, h):
        return EDGE, 2
    return FACE, 0


def valences(faces, n_verts):
    """How many triangles hold each triangle's edges (n, 3: edge k from corner k to k + 1) and
    each vertex (n_verts): 2 inside a closed or smooth surface, 1 on an open border."""
    e = np.sort(np.stack([faces, np.roll(faces, -1, axis=1)], axis=-1), axis=-1).reshape(-1, 2)
    _, inv, cnt = np.unique(e, axis=0, return_inverse=True, return_counts=True)
    edge = np.ascontiguousarray(cnt[inv.reshape(-1)].reshape(-1, 3).astype(np.int64))
    vert = np.ascontiguousarray(np.bincount(faces.reshape(-1), minlength=n_verts).astype(np.int64))
    return edge, vert


@njit(cache=True, error_model="numpy")
def sphere_contacts(px, py, pz, radius, verts, faces, edge_val, vert_val, cand, ncand, raw, out):
    """The contacts of the sphere (centre p, ``radius``) with the mesh's candidate triangles
    ``cand[:ncand]`` (every triangle within reach of the sphere), into ``out`` (rows of 8: the
    distance from the centre to the contact point, the unit normal from the centre towards the
    surface (3), the triangle, the feature kind, the feature's vertices a, b (-1: none));
    returns how many (at most out.shape[0]). ``raw``: scratch of at least ncand rows of 8.

    A face's closest point is a contact. An edge's or a vertex's is a contact only when every
    triangle that holds that edge or vertex (``edge_val``, ``vert_val``: how many) has it as its
    own closest point, and then once: it is then the closest point of the surface around it
    (a convex edge or corner); where a triangle holding it has a closer point, that triangle's
    own contact is the one (a flat or smooth surface, a concave crease)."""
    kmax = out.shape[0]
    m = 0
    for q in range(ncand):
        t = cand[q]
        a = faces[t, 0]
        b = faces[t, 1]
        c = faces[t, 2]
        qx, qy, qz, kind, idx = closest_on_triangle(
            px, py, pz, verts[a, 0], verts[a, 1], verts[a, 2], verts[b, 0], verts[b, 1], verts[b, 2],
            verts[c, 0], verts[c, 1], verts[c, 2])
        dx, dy, dz = qx - px, qy - py, qz - pz
        d = math.sqrt(dx * dx + dy * dy + dz * dz)
        if not d < radius or d < 1e-300:
            continue
        kind, idx = _snap(qx, qy, qz, verts[a, 0], verts[a, 1], verts[a, 2], verts[b, 0], verts[b, 1], verts[b, 2],
                          verts[c, 0], verts[c, 1], verts[c, 2], kind, idx)
        f0 = -1
        f1 = -1
        val = 0
        if kind == EDGE:
            f0 = faces[t, idx]
            f1 = faces[t, (idx + 1) % 3]
            if f1 < f0:
                f0, f1 = f1, f0
            val = edge_val[t, idx]
        elif kind == VERTEX:
            f0 = faces[t, idx]
            val = vert_val[f0]
        raw[m, 0] = d
        raw[m, 1] = dx / d
        raw[m, 2] = dy / d
        raw[m, 3] = dz / d
        raw[m, 4] = t
        raw[m, 5] = kind + 10.0 * val     # the kind, and how many triangles hold the feature
        raw[m, 6] = f0
        raw[m, 7] = f1
        m += 1
    k = 0
    for q in range(m):
        code = raw[q, 5]
        kind = np.int64(code) % 10
        keep = True
        if kind != FACE:
            val = np.int64(code) // 10
            seen = 0
            for s in range(m):
                if np.int64(raw[s, 5]) % 10 == kind and raw[s, 6] == raw[q, 6] and \
                        (kind == VERTEX or raw[s, 7] == raw[q, 7]):
                    if s < q:
                        keep = False     # the same feature, kept already
                        break
                    seen += 1
            if keep and seen != val:
                keep = False             # a triangle holding it has a closer point
        if keep and k < kmax:
            for j in range(8):
                out[k, j] = raw[q, j]
            out[k, 5] = kind
            k += 1
    return k


# --------------------------------------------------------------------------- the search

@njit(cache=True, error_model="numpy")
def _tri_cells(verts, faces, lo, cell, dims, keys, tris, fill):
    """(cell, triangle) pairs of the cells a triangle passes within half a cell diagonal of
    (every cell it touches, and a few beside); counts only when ``fill`` is False."""
    half_diag = 0.8660254037844386 * cell
    m = 0
    for t in range(faces.shape[0]):
        a = faces[t, 0]
        b = faces[t, 1]
        c = faces[t, 2]
        i0 = np.empty(3, np.int64)
        i1 = np.empty(3, np.int64)
        for k in range(3):
            mn = min(verts[a, k], verts[b, k], verts[c, k])
            mx = max(verts[a, k], verts[b, k], verts[c, k])
            i0[k] = max(np.int64(math.floor((mn - lo[k]) / cell)), 0)
            i1[k] = min(np.int64(math.floor((mx - lo[k]) / cell)), dims[k] - 1)
        for ix in range(i0[0], i1[0] + 1):
            cx = lo[0] + (ix + 0.5) * cell
            for iy in range(i0[1], i1[1] + 1):
                cy = lo[1] + (iy + 0.5) * cell
                for iz in range(i0[2], i1[2] + 1):
                    cz = lo[2] + (iz + 0.5) * cell
                    qx, qy, qz, _, _ = closest_on_triangle(
                        cx, cy, cz, verts[a, 0], verts[a, 1], verts[a, 2], verts[b, 0], verts[b, 1],
                        verts[b, 2], verts[c, 0], verts[c, 1], verts[c, 2])
                    if (qx - cx) ** 2 + (qy - cy) ** 2 + (qz - cz) ** 2 <= half_diag * half_diag:
                        if fill:
                            keys[m] = ix + dims[0] * (iy + dims[1] * np.int64(iz))
                            tris[m] = t
                        m += 1
    return m


def bin_triangles(verts, faces, cell):
    """The triangles binned into cubes of side ``cell`` (the particles' cell size: a query
    then visits a few cells), with ``keys`` the occupied cells
    (sorted), and cell keys[k]'s triangles items[start[k]:start[k + 1]]. Only cells near the
    surface are stored, so a hollow vessel costs its area over cell^2, not its volume.
    Returned as the tuple (lo, cell, dims, keys, start, items) that near_triangles reads."""
    cell = float(cell)
    lo = np.ascontiguousarray(verts.min(axis=0) - cell)
    dims = np.ascontiguousarray(np.ceil((verts.max(axis=0) + cell - lo) / cell).astype(np.int64) + 1)
    none = np.empty(0, np.int64)
    m = _tri_cells(verts, faces, lo, cell, dims, none, none, False)
    keys = np.empty(m, np.int64)
    tris = np.empty(m, np.int64)
    _tri_cells(verts, faces, lo, cell, dims, keys, tris, True)
    order = np.argsort(keys, kind="stable")
    keys, tris = keys[order], tris[order]
    ukeys, start = np.unique(keys, return_index=True)
    start = np.ascontiguousarray(np.r_[start, m].astype(np.int64))
    return lo, cell, dims, np.ascontiguousarray(ukeys), start, np.ascontiguousarray(tris)


@njit(cache=True, error_model="numpy")
def near_triangles(p, reach, bins, stamp, tag, out):
    """The triangles that may pass within ``reach`` of point p (3,) (``bins``: of
    :func:`bin_triangles`; those binned in the cells the box
    p +- reach overlaps), each once, into ``out``; returns how many (at most out.size; -1 when
    more would not fit). ``stamp`` (one int per triangle) marks those taken with ``tag``: a
    caller passes a new tag for each query, so nothing is cleared between them."""
    return near_xyz(p[0], p[1], p[2], reach, bins, stamp, tag, out)


@njit(cache=True, error_model="numpy")
def near_xyz(px, py, pz, reach, bins, stamp, tag, out):
    """:func:`near_triangles` of the point (px, py, pz)."""
    lo, cell, dims, keys, start, items = bins
    n = 0
    j0 = np.int64(math.floor((px - reach - lo[0]) / cell))
    j1 = np.int64(math.floor((px + reach - lo[0]) / cell))
    k0 = np.int64(math.floor((py - reach - lo[1]) / cell))
    k1 = np.int64(math.floor((py + reach - lo[1]) / cell))
    l0 = np.int64(math.floor((pz - reach - lo[2]) / cell))
    l1 = np.int64(math.floor((pz + reach - lo[2]) / cell))
    for iz in range(max(l0, 0), min(l1, dims[2] - 1) + 1):
        for iy in range(max(k0, 0), min(k1, dims[1] - 1) + 1):
            for ix in range(max(j0, 0), min(j1, dims[0] - 1) + 1):
                key = ix + dims[0] * (iy + dims[1] * np.int64(iz))
                at = np.searchsorted(keys, key)
                if at >= keys.size or keys[at] != key:
                    continue
                for q in range(start[at], start[at + 1]):
                    t = items[q]
                    if stamp[t] == tag:
                        continue
                    stamp[t] = tag
                    if n >= out.size:
                        return -1
                    out[n] = t
                    n += 1
    return n


# --------------------------------------------------------------------------- writing

def write_stl(path, tris, binary=True, name="thermodem"):
    """Triangles (n, 3, 3) as an STL file (binary float32, or ASCII with 17 significant
    digits); the facet normals from the corners' order (right hand)."""
    tris = np.asarray(tris, float)
    nrm = np.cross(tris[:, 1] - tris[:, 0], tris[:, 2] - tris[:, 0])
    nrm /= np.maximum(np.linalg.norm(nrm, axis=1), 1e-300)[:, None]
    if binary:
        rec = np.zeros(len(tris), np.dtype([("normal", "<f4", 3), ("v", "<f4", (3, 3)), ("attr", "<u2")]))
        rec["normal"] = nrm
        rec["v"] = tris
        with open(path, "wb") as fh:
            fh.write(name.encode()[:80].ljust(80, b" "))
            fh.write(np.uint32(len(tris)).tobytes())
            fh.write(rec.tobytes())
        return
    lines = [f"solid {name}"]
    for n, t in zip(nrm, tris):
        lines.append(f"  facet normal {n[0]:.17g} {n[1]:.17g} {n[2]:.17g}")
        lines.append("    outer loop")
        for v in t:
            lines.append(f"      vertex {v[0]:.17g} {v[1]:.17g} {v[2]:.17g}")
        lines.append("    endloop")
        lines.append("  endfacet")
    lines.append(f"endsolid {name}")
    with open(path, "w") as fh:
        fh.write("\n".join(lines) + "\n")


# --------------------------------------------------------------------------- in the step
#
# A mesh wall is ``nslot`` consecutive wall rows (dem.world.wall_tables): one row per contact
# the sphere may have with the mesh at once (a concave corner of three faces has three), so that
# every per-wall array of a plane (the tangential and rolling springs, the contact age, the
# conductance and the heat totals: dem.schema) serves a mesh contact unchanged. The geometry of
# each row's contact is per particle: dem.schema ``mcon`` (distance, unit normal towards the
# surface; distance inf: no contact in that row), written before each force evaluation by
# :func:`mesh_contacts`. Triangles are in the mesh's reference frame (its place at t = 0); the
# frame moves rigidly: x = C + D(t) + R(Omega t) (X - C), D(t) = V t + A (sin(w t + phi) - sin phi)
# (a constant velocity, a prescribed oscillation, or both), turning about its moving centre.

# per-mesh floats (Walls.mm) and ints (Walls.mmi)
MM = slots("MM", (
    ("vx", 3, "translational velocity V (m/s)"),
    ("ox", 3, "angular velocity Omega (rad/s)"),
    ("cx", 3, "centre of the rotation C (m, at t = 0)"),
    ("lo", 3, "lower corner of the triangle bins (reference frame)"),
    ("cell", "bin size (m)"),
    ("ax", 3, "amplitude A of a prescribed oscillation (m)"),
    ("osc", "its angular frequency 2 pi f (rad/s; 0: none)"),
    ("phase", "its phase (rad)"),
))
MMI = slots("MMI", (
    ("row0", "first wall row of the mesh"),
    ("nslot", "wall rows (contacts at once) of the mesh"),
    ("dims", 3, "bins along x, y, z"),
    ("k0", "first of the mesh's occupied bins in mkeys"),
    ("nk", "occupied bins"),
    ("d0", "first of the mesh's cells in the dense map mdense (-1: none, the keys are searched)"),
    ("t0", "first triangle of the mesh (in mfc)"),
    ("nt", "triangles of the mesh"),
))
DENSE_MAX = 1 << 22   # cells of a mesh's bin grid up to which the grid has a dense map (4 bytes a cell)
MATCH_COS = 0.5   # a contact keeps its row (and its spring) when its normal turned less than 60 degrees
KMAX = 16         # contacts of one sphere with one mesh examined at once (the nslot nearest are kept)


@njit(cache=True, error_model="numpy", inline="always")
def _turn(ox, oy, oz, t, vx, vy, vz, sign):
    """R(sign Omega t) v (Rodrigues)."""
    ax, ay, az = ox * t * sign, oy * t * sign, oz * t * sign
    th = math.sqrt(ax * ax + ay * ay + az * az)
    if th == 0.0:
        return vx, vy, vz
    kx, ky, kz = ax / th, ay / th, az / th
    c = math.cos(th)
    s = math.sin(th)
    d = (kx * vx + ky * vy + kz * vz) * (1.0 - c)
    return (vx * c + (ky * vz - kz * vy) * s + kx * d,
            vy * c + (kz * vx - kx * vz) * s + ky * d,
            vz * c + (kx * vy - ky * vx) * s + kz * d)


@njit(cache=True, error_model="numpy", inline="always")
def mesh_centre(mm, m, t):
    """C + D(t): where the centre of mesh m's rotation is at time t."""
    cx = mm[m, MM.cx] + mm[m, MM.vx] * t
    cy = mm[m, MM.cx + 1] + mm[m, MM.vx + 1] * t
    cz = mm[m, MM.cx + 2] + mm[m, MM.vx + 2] * t
    w = mm[m, MM.osc]
    if w != 0.0:
        s = math.sin(w * t + mm[m, MM.phase]) - math.sin(mm[m, MM.phase])
        cx += mm[m, MM.ax] * s
        cy += mm[m, MM.ax + 1] * s
        cz += mm[m, MM.ax + 2] * s
    return cx, cy, cz


# the columns of mesh_motion: where each mesh is at one time
MO = slots("MO", (
    ("ex", 3, "C + D(t): the centre of its rotation now (m)"),
    ("ox", 3, "Omega (rad/s)"),
    ("cx", 3, "C: the centre of its rotation at t = 0 (reference frame, m)"),
    ("ux", 3, "V + A w cos(w t + phi): the velocity of its translation now (m/s)"),
))
MO_SIZE = MO.SIZE   # (a global int: Numba reads no attribute of the tuple's class)


@njit(cache=True, error_model="numpy")
def mesh_motion(mm, t):
    """Each mesh's motion at time t (columns :data:`MO`), for the loops over particles to read
    as numbers: :func:`mesh_point_velocity` and :func:`frame_point` take no array, as a function
    taking the mesh table in those loops counted its references at each particle."""
    out = np.empty((mm.shape[0], MO_SIZE))
    for m in range(mm.shape[0]):
        cx, cy, cz = mesh_centre(mm, m, t)
        vx, vy, vz = mm[m, MM.vx], mm[m, MM.vx + 1], mm[m, MM.vx + 2]
        w = mm[m, MM.osc]
        if w != 0.0:
            c = w * math.cos(w * t + mm[m, MM.phase])
            vx += mm[m, MM.ax] * c
            vy += mm[m, MM.ax + 1] * c
            vz += mm[m, MM.ax + 2] * c
        out[m, MO.ex], out[m, MO.ex + 1], out[m, MO.ex + 2] = cx, cy, cz
        for k in range(3):
            out[m, MO.ox + k] = mm[m, MM.ox + k]
            out[m, MO.cx + k] = mm[m, MM.cx + k]
        out[m, MO.ux], out[m, MO.ux + 1], out[m, MO.ux + 2] = vx, vy, vz
    return out


@njit(cache=True, error_model="numpy", inline="always")
def mesh_point_velocity(ex, ey, ez, ox, oy, oz, ux, uy, uz, px, py, pz):
    """Velocity of a mesh's surface at the point p: U + Omega x (p - E), with E = C + D(t) and
    U = V + A w cos(w t + phi) its row of :func:`mesh_motion`."""
    rx, ry, rz = px - ex, py - ey, pz - ez
    return ux + oy * rz - oz * ry, uy + oz * rx - ox * rz, uz + ox * ry - oy * rx


@njit(cache=True, error_model="numpy", inline="always")
def frame_point(ex, ey, ez, ox, oy, oz, cx, cy, cz, t, x0, x1, x2):
    """The point x at time t in the reference frame of a mesh: C + R(-Omega t) (x - E), with
    E = C + D(t), Omega and C its row of :func:`mesh_motion` (:func:`to_mesh_frame` as numbers)."""
    rx, ry, rz = _turn(ox, oy, oz, t, x0 - ex, x1 - ey, x2 - ez, -1.0)
    return cx + rx, cy + ry, cz + rz


@njit(cache=True, error_model="numpy", inline="always")
def to_mesh_frame(mm, m, x0, x1, x2, t):
    """A point at time t in the reference frame of mesh m: X = C + R(-Omega t) (x - C - D(t))."""
    cx, cy, cz = mesh_centre(mm, m, t)
    rx, ry, rz = _turn(mm[m, MM.ox], mm[m, MM.ox + 1], mm[m, MM.ox + 2], t, x0 - cx, x1 - cy, x2 - cz, -1.0)
    return mm[m, MM.cx] + rx, mm[m, MM.cx + 1] + ry, mm[m, MM.cx + 2] + rz


@njit(cache=True, error_model="numpy")
def mesh_bins(W, m):
    """The bins of mesh m as :func:`near_triangles` reads them."""
    k0 = W.mmi[m, MMI.k0]
    nk = W.mmi[m, MMI.nk]
    return (W.mm[m, MM.lo:MM.lo + 3], W.mm[m, MM.cell], W.mmi[m, MMI.dims:MMI.dims + 3],
            W.mkeys[k0:k0 + nk], W.mstart[k0 + m:k0 + m + nk + 1], W.mitems)


@njit(cache=True, error_model="numpy")
def _query(W, m, px, py, pz, reach):
    """The candidate triangles of mesh m within reach of the reference-frame point p, into
    W.mout; returns how many."""
    stamp = W.mstamp
    tag = stamp[stamp.shape[0] - 1] + 1
    stamp[stamp.shape[0] - 1] = tag
    return near_xyz(px, py, pz, reach, mesh_bins(W, m), stamp, tag, W.mout)


@njit(cache=True, error_model="numpy", inline="always")
def distance2(px, py, pz, verts, faces, t):
    """The squared distance from the point p to triangle t (its closest point, Ericson)."""
    a = faces[t, 0]
    b = faces[t, 1]
    c = faces[t, 2]
    qx, qy, qz, _, _ = closest_on_triangle(px, py, pz, verts[a, 0], verts[a, 1], verts[a, 2],
                                           verts[b, 0], verts[b, 1], verts[b, 2],
                                           verts[c, 0], verts[c, 1], verts[c, 2])
    return (qx - px) ** 2 + (qy - py) ** 2 + (qz - pz) ** 2


@njit(cache=True, error_model="numpy")
def mesh_candidates(P, W, n, xs, t, reach, skin, srange, near):
    """At a neighbour build: for each particle i < n (centre xs[i] at time t) and each mesh m,
    the triangles within its radius + ``reach`` (the heat models' range) + ``skin``, or
    ``srange`` radii + ``skin`` when a wall radiates, as its candidates P.mtri[i, :P.mtn[i]]
    (every mesh's, sorted by index: the order the contacts of each step see them in, whatever
    the bins' order; P.mtn[i] = -1 when they do not fit, and the step then searches the bins),
    and near[i, m]: whether any triangle of mesh m is that near. Until the next build a particle
    moves less than half the skin from the walls (dem.step.drift), so no other triangle comes
    within its radius + reach (dem.contact.mesh.mesh_contacts). The bins are read through
    their dense map where the mesh has one (MMI.d0), else by a search of the sorted keys; the
    arrays are taken once, outside the particle loop."""
    mtri, mtn, r = P.mtri, P.mtn, P.radius
    mv, mfc, mm, mmi = W.mv, W.mfc, W.mm, W.mmi
    mkeys, mstart, mitems, mdense, stamp, pl = W.mkeys, W.mstart, W.mitems, W.mdense, W.mstamp, W.mpl
    cap = mtri.shape[1]
    mo = mesh_motion(mm, t)
    last = stamp.shape[0] - 1
    tag = stamp[last]
    for i in range(n):
        mtn[i] = 0
    for m in range(mmi.shape[0]):
        lo0, lo1, lo2 = mm[m, MM.lo], mm[m, MM.lo + 1], mm[m, MM.lo + 2]
        cell = mm[m, MM.cell]
        n0, n1, n2 = mmi[m, MMI.dims], mmi[m, MMI.dims + 1], mmi[m, MMI.dims + 2]
        k0 = mmi[m, MMI.k0]
        keys = mkeys[k0:k0 + mmi[m, MMI.nk]]
        d0 = mmi[m, MMI.d0]
        for i in range(n):
            h = max(r[i] + reach + skin, srange * r[i] + skin)
            px, py, pz = frame_point(mo[m, MO.ex], mo[m, MO.ex + 1], mo[m, MO.ex + 2], mo[m, MO.ox], mo[m, MO.ox + 1],
                                     mo[m, MO.ox + 2], mo[m, MO.cx], mo[m, MO.cx + 1], mo[m, MO.cx + 2], t,
                                     xs[i, 0], xs[i, 1], xs[i, 2])
            tag += 1
            found = False
            j0 = max(np.int64(math.floor((px - h - lo0) / cell)), 0)
            j1 = min(np.int64(math.floor((px + h - lo0) / cell)), n0 - 1)
            l0 = max(np.int64(math.floor((py - h - lo1) / cell)), 0)
            l1 = min(np.int64(math.floor((py + h - lo1) / cell)), n1 - 1)
            z0 = max(np.int64(math.floor((pz - h - lo2) / cell)), 0)
            z1 = min(np.int64(math.floor((pz + h - lo2) / cell)), n2 - 1)
            for iz in range(z0, z1 + 1):
                for iy in range(l0, l1 + 1):
                    for ix in range(j0, j1 + 1):
                        key = ix + n0 * (iy + n1 * np.int64(iz))
                        if d0 >= 0:
                            at = np.int64(mdense[d0 + key])
                            if at < 0:
                                continue
                        else:
                            at = np.searchsorted(keys, key)
                            if at >= keys.size or keys[at] != key:
                                continue
                        for q in range(mstart[k0 + m + at], mstart[k0 + m + at + 1]):
                            tri = mitems[q]
                            if stamp[tri] == tag:
                                continue
                            stamp[tri] = tag
                            if abs(pl[tri, 0] * px + pl[tri, 1] * py + pl[tri, 2] * pz - pl[tri, 3]) > h * (1.0 + 1e-9):
                                continue   # its plane is beyond reach: so is every point of it
                            a = mfc[tri, 0]
                            b = mfc[tri, 1]
                            c = mfc[tri, 2]
                            qx, qy, qz, _, _ = closest_on_triangle(
                                px, py, pz, mv[a, 0], mv[a, 1], mv[a, 2], mv[b, 0], mv[b, 1], mv[b, 2],
                                mv[c, 0], mv[c, 1], mv[c, 2])
                            if not (qx - px) ** 2 + (qy - py) ** 2 + (qz - pz) ** 2 < h * h:
                                continue
                            found = True
                            k = mtn[i]
                            if k < 0:
                                continue
                            if k >= cap:
                                mtn[i] = -1
                                continue
                            s = k
                            while s > 0 and mtri[i, s - 1] > tri:
                                mtri[i, s] = mtri[i, s - 1]
                                s -= 1
                            mtri[i, s] = tri
                            mtn[i] = k + 1
            near[i, m] = found
    stamp[last] = tag


@njit(cache=True, error_model="numpy")
def mesh_contacts(P, W, nown, reach, srange, t, rolling, age):
    """Before a force evaluation: the contacts of each owned particle with each mesh wall in
    its wall list (surface points within its radius + ``reach``, the heat models' range), the
    ``nslot`` nearest (out to ``srange`` radii when a wall radiates: its sphere of influence,
    dem.thermal.heat.wall_radiation_weights), each into the wall row whose previous contact's normal is closest to
    its own (within 60 degrees: the same contact, sliding or rolling from one triangle to the
    next, keeps its spring); a new contact takes a free row, whose springs start at zero.
    Writes P.mcon (rows without a contact: distance inf).

    The triangles looked at are the particle's candidates of the last neighbour build
    (:func:`mesh_candidates`) whose plane passes within the reach (the closest point of a
    triangle is no nearer than its plane; the margin keeps a contact at the rounding of the
    reach), or, for a particle whose candidates did not fit, the bins' triangles near it. The
    arrays are taken once here and the loop calls :func:`sphere_contacts` only for two
    triangles or more: in a loop, each array a called function takes costs a reference count
    up and down (about 10 ns; docs/benchmarks.md, "Hopper discharge")."""
    mcon, wnb, wnn, whist, wrhist, wage, x, r = P.mcon, P.wnb, P.wnn, P.whist, P.wrhist, P.wage, P.position, P.radius
    mtri, mtn = P.mtri, P.mtn
    wi, mm, mmi = W.wi, W.mm, W.mmi
    mv, mfc, mev, mvv, mout, mraw, pl = W.mv, W.mfc, W.mev, W.mvv, W.mout, W.mraw, W.mpl
    mo = mesh_motion(mm, t)
    cbuf = np.empty((KMAX, 8))
    used = np.zeros(KMAX, np.bool_)
    slot = np.empty(KMAX, np.int64)
    for i in range(nown):
        for q in range(wnn[i]):
            wl = wnb[i, q]
            m = wi[wl, WI.mesh]      # -1 for a plane or a cylinder
            if m < 0 or wl != mmi[m, MMI.row0]:
                continue
            row0 = mmi[m, MMI.row0]
            ns = mmi[m, MMI.nslot]
            px, py, pz = frame_point(mo[m, MO.ex], mo[m, MO.ex + 1], mo[m, MO.ex + 2], mo[m, MO.ox], mo[m, MO.ox + 1],
                                     mo[m, MO.ox + 2], mo[m, MO.cx], mo[m, MO.cx + 1], mo[m, MO.cx + 2], t,
                                     x[i, 0], x[i, 1], x[i, 2])
            cut = max(r[i] + reach, srange * r[i])
            nc = mtn[i]
            if nc < 0:   # more candidates than mtri holds: the bins
                nt = _query(W, m, px, py, pz, cut)
            else:
                t0 = mmi[m, MMI.t0]
                t1 = t0 + mmi[m, MMI.nt]
                lim = cut * (1.0 + 1e-9)
                nt = 0
                for a in range(nc):
                    tri = mtri[i, a]
                    if tri < t0 or tri >= t1:
                        continue
                    if abs(pl[tri, 0] * px + pl[tri, 1] * py + pl[tri, 2] * pz - pl[tri, 3]) > lim:
                        continue
                    mout[nt] = tri
                    nt += 1
            k = 0
            if nt == 1:   # one triangle (most particles on a wall): its closest point is the contact.
                # sphere_contacts would drop it only on an edge or vertex another triangle holds,
                # and that triangle's plane would then pass within the reach too (nt > 1)
                tri = mout[0]
                a = mfc[tri, 0]
                b = mfc[tri, 1]
                e = mfc[tri, 2]
                qx, qy, qz, _, _ = closest_on_triangle(
                    px, py, pz, mv[a, 0], mv[a, 1], mv[a, 2], mv[b, 0], mv[b, 1], mv[b, 2], mv[e, 0], mv[e, 1], mv[e, 2])
                dx, dy, dz = qx - px, qy - py, qz - pz
                d = math.sqrt(dx * dx + dy * dy + dz * dz)
                if d < cut and d >= 1e-300:
                    cbuf[0, 0] = d
                    cbuf[0, 1] = dx / d
                    cbuf[0, 2] = dy / d
                    cbuf[0, 3] = dz / d
                    k = 1
            elif nt > 1:
                k = sphere_contacts(px, py, pz, cut, mv, mfc, mev, mvv, mout, nt, mraw, cbuf)
            if k == 0:   # no contact: the rows' contacts end (their springs start at zero when taken)
                for s in range(ns):
                    mcon[i, row0 + s, 0] = math.inf
                continue
            # the nearest first (insertion sort: k is a few)
            for a in range(1, k):
                b = a
                while b > 0 and cbuf[b, 0] < cbuf[b - 1, 0]:
                    for j in range(8):
                        tmp = cbuf[b, j]
                        cbuf[b, j] = cbuf[b - 1, j]
                        cbuf[b - 1, j] = tmp
                    b -= 1
            k = min(k, ns)
            ox, oy, oz = mm[m, MM.ox], mm[m, MM.ox + 1], mm[m, MM.ox + 2]
            for c in range(k):   # normals back to the world frame
                nx, ny, nz = _turn(ox, oy, oz, t, cbuf[c, 1], cbuf[c, 2], cbuf[c, 3], 1.0)
                cbuf[c, 1] = nx
                cbuf[c, 2] = ny
                cbuf[c, 3] = nz
                slot[c] = -1
            for s in range(ns):
                used[s] = False
            for _ in range(k):   # greedy: the best-aligned (contact, row) pair first
                best = MATCH_COS
                bc = -1
                bs = -1
                for c in range(k):
                    if slot[c] >= 0:
                        continue
                    for s in range(ns):
                        if used[s] or not mcon[i, row0 + s, 0] < math.inf:
                            continue
                        d = (cbuf[c, 1] * mcon[i, row0 + s, 1] + cbuf[c, 2] * mcon[i, row0 + s, 2]
                             + cbuf[c, 3] * mcon[i, row0 + s, 3])
                        if d > best:
                            best = d
                            bc = c
                            bs = s
                if bc < 0:
                    break
                slot[bc] = bs
                used[bs] = True
            for c in range(k):   # new contacts: a row that had none, else one whose contact ended
                if slot[c] >= 0:
                    continue
                pick = -1
                for s in range(ns):
                    if not used[s] and not mcon[i, row0 + s, 0] < math.inf:
                        pick = s
                        break
                if pick < 0:
                    for s in range(ns):
                        if not used[s]:
                            pick = s
                            break
                rw = row0 + pick
                for j in range(3):
                    whist[i, rw, j] = 0.0
                    if rolling:
                        wrhist[i, rw, j] = 0.0
                if age:
                    wage[i, rw, 0] = 0.0
                    wage[i, rw, 1] = 0.0
                slot[c] = pick
                used[pick] = True
            for s in range(ns):
                if not used[s]:
                    mcon[i, row0 + s, 0] = math.inf
            for c in range(k):
                rw = row0 + slot[c]
                for j in range(4):
                    mcon[i, rw, j] = cbuf[c, j]


@njit(cache=True, error_model="numpy")
def _nearest(x, reach, verts, faces, bins, stamp, out):
    """For each point of x (n, 3): the distance to the nearest surface point within reach[i] and
    its triangle (inf, -1: none)."""
    n = x.shape[0]
    d = np.full(n, math.inf)
    tri = np.full(n, -1, np.int64)
    for i in range(n):
        nt = near_triangles(x[i], reach[i], bins, stamp, i + 1, out)
        for q in range(nt):
            t = out[q]
            e = math.sqrt(distance2(x[i, 0], x[i, 1], x[i, 2], verts, faces, t))
            if e < d[i]:
                d[i] = e
                tri[i] = t
    return d, tri


def nearest(x, reach, verts, faces, bins):
    """(distance, triangle) of each point of x (n, 3) to the mesh, looked for within reach (n,)
    (inf and -1 beyond)."""
    x = np.ascontiguousarray(x, float).reshape(-1, 3)
    reach = np.ascontiguousarray(np.broadcast_to(np.asarray(reach, float), (x.shape[0],)))
    stamp = np.zeros(faces.shape[0], np.int64)
    out = np.empty(faces.shape[0], np.int64)
    return _nearest(x, reach, verts, faces, bins, stamp, out)


def _frame_motion(w, t):
    """(C, D(t), Omega t) of scene mesh wall ``w``: the centre of its rotation at t = 0, its
    displacement (velocity and oscillation) and its rotation vector at time t."""
    d = np.asarray(w["velocity"], float) * t
    osc = w.get("oscillation")
    if osc:
        om, ph = 2.0 * math.pi * osc["frequency"], math.radians(osc["phase"])
        d = d + np.asarray(osc["amplitude"], float) * (math.sin(om * t + ph) - math.sin(ph))
    return np.asarray(w["rotation_center"], float), d, np.asarray(w["angular_velocity"], float) * t


def _rotate(v, a):
    """Rows of v (n, 3) turned by the rotation vector a (Rodrigues)."""
    th = float(np.linalg.norm(a))
    if th == 0.0:
        return v
    k = a / th
    return v * math.cos(th) + np.cross(k, v) * math.sin(th) + np.outer(v @ k, k) * (1.0 - math.cos(th))


def mesh_frame_points(w, x, t):
    """Points x (n, 3) at time t in the reference frame of scene mesh wall ``w`` (as
    :func:`to_mesh_frame`, for many points, in Python): C + R(-Omega t) (x - C - D(t))."""
    c, d, a = _frame_motion(w, t)
    return c + _rotate(np.asarray(x, float) - c - d, -a)


def placed_vertices(w, t):
    """The vertices of scene mesh wall ``w`` where they are at time t (the inverse of
    :func:`mesh_frame_points`): C + D(t) + R(Omega t) (X - C)."""
    c, d, a = _frame_motion(w, t)
    return c + d + _rotate(w["surface"].verts - c, a)


SLOTS = 4   # wall rows of a mesh: the contacts a sphere keeps with one mesh at once (a corner of
            # three faces has three; a fourth for a vertex where more faces meet)


class Surface:
    """One mesh wall as the scene reads it: its welded vertices and faces (reference frame: its
    place at t = 0), edge and vertex valences, area and bounding box, and a digest of the
    triangles (what a restart compares)."""

    def __init__(self, path, key, scale=1.0, rotate=(0.0, 0.0, 0.0), translate=(0.0, 0.0, 0.0)):
        import hashlib
        tris = place(read_triangles(path, key), scale, rotate, translate)
        self.verts, self.faces = check_triangles(tris, path, key)
        self.edge_val, self.vert_val = valences(self.faces, len(self.verts))
        a, b, c = (self.verts[self.faces[:, k]] for k in range(3))
        self.area = float(0.5 * np.linalg.norm(np.cross(b - a, c - a), axis=1).sum())
        self.lo = self.verts.min(axis=0)
        self.hi = self.verts.max(axis=0)
        self.n_triangles = len(self.faces)
        self.digest = hashlib.sha256(np.ascontiguousarray(tris).tobytes()).hexdigest()[:16]
        self._bins = {}

    def bins(self, cell):
        if cell not in self._bins:
            self._bins[cell] = bin_triangles(self.verts, self.faces, cell)
        return self._bins[cell]


@njit(cache=True, error_model="numpy")
def mesh_caps(W, m, x0, x1, x2, rm, t):
    """The volume the surface of mesh m cuts off the sphere of radius rm about x at time t: a
    cap per contact (the tangent plane at each of the ``nslot`` nearest contacts of
    :func:`mesh_contacts`), as a plane wall's (dem.thermal.heat.local_porosity)."""
    px, py, pz = to_mesh_frame(W.mm, m, x0, x1, x2, t)
    nt = _query(W, m, px, py, pz, rm)
    cbuf = np.empty((KMAX, 8))
    k = sphere_contacts(px, py, pz, rm, W.mv, W.mfc, W.mev, W.mvv, W.mout, nt, W.mraw, cbuf)
    d = np.sort(cbuf[:k, 0])
    v = 0.0
    for c in range(min(k, W.mmi[m, MMI.nslot])):
        h = rm - d[c]
        v += math.pi * h * h * (3.0 * rm - h) / 3.0
    return v
