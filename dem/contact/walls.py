"""Wall geometry: planes (infinite one-sided, or bounded two-sided rectangles) and
cylinders (particles inside or outside, optionally finite), moving with a constant
translational velocity and/or a surface rotation about an axis that leaves the surface
invariant (a drum turning about its axis, an end plate turning about its normal).

Walls are rows of a float array ``wf`` (columns below) and an int array ``wi``. A triangle-mesh
wall is several rows of type MESH (one per contact at once, dem.contact.mesh): their geometry is
per particle (dem.schema ``mcon``), so :func:`wall_distance` has none for them (inf); their
motion columns (vx, ox, cx) are the mesh's, so :func:`wall_velocity` serves them.
"""
import math

import numpy as np
from numba import njit

from ..schema import slots

# float columns (Walls.wf)
WF = slots("WF", (
    ("px", 3, "a point of the plane, or of the cylinder's axis (m, at t = 0)"),
    ("nx", 3, "unit normal of the plane (towards the particles), or the cylinder's axis"),
    ("ux", 3, "in-plane axis u of a bounded plane (v = n x u)"),
    ("eu", "half extent along u (inf: unbounded); a cylinder's half length"),
    ("ev", "half extent along v (inf: unbounded)"),
    ("rad", "cylinder radius (m)"),
    ("vx", 3, "translational velocity (m/s)"),
    ("ox", 3, "surface angular velocity (rad/s)"),
    ("cx", 3, "centre of the rotation (m, at t = 0)"),
    ("side", "cylinder: 1 particles inside, -1 outside"),
))
# int columns (Walls.wi)
WI = slots("WI", (
    ("type", "PLANE, CYLINDER or MESH"),
    ("mat", "material index"),
    ("mesh", "the mesh of a MESH row (dem.contact.mesh; -1 for a plane or a cylinder)"),
))
PLANE, CYLINDER, MESH = 0, 1, 2


@njit(cache=True, error_model="numpy")
def wall_distance(wf, wi, w, x0, x1, x2, t):
    """Distance from a particle centre to wall ``w`` and the unit vector from the centre
    towards the wall. Returns (dist, nx, ny, nz); dist = inf when no contact is possible."""
    px = wf[w, WF.px] + wf[w, WF.vx] * t
    py = wf[w, WF.px + 1] + wf[w, WF.vx + 1] * t
    pz = wf[w, WF.px + 2] + wf[w, WF.vx + 2] * t
    rx = x0 - px
    ry = x1 - py
    rz = x2 - pz
    ax = wf[w, WF.nx]
    ay = wf[w, WF.nx + 1]
    az = wf[w, WF.nx + 2]
    s = rx * ax + ry * ay + rz * az
    if wi[w, WI.type] == PLANE:
        eu = wf[w, WF.eu]
        ev = wf[w, WF.ev]
        if eu == math.inf and ev == math.inf:
            return s, -ax, -ay, -az
        ux = wf[w, WF.ux]
        uy = wf[w, WF.ux + 1]
        uz = wf[w, WF.ux + 2]
        vx = ay * uz - az * uy
        vy = az * ux - ax * uz
        vz = ax * uy - ay * ux
        a = rx * ux + ry * uy + rz * uz
        b = rx * vx + ry * vy + rz * vz
        a = min(max(a, -eu), eu)
        b = min(max(b, -ev), ev)
        dx = rx - a * ux - b * vx
        dy = ry - a * uy - b * vy
        dz = rz - a * uz - b * vz
        d = math.sqrt(dx * dx + dy * dy + dz * dz)
        if d < 1e-300:
            sg = 1.0 if s >= 0 else -1.0
            return 0.0, -sg * ax, -sg * ay, -sg * az
        return d, -dx / d, -dy / d, -dz / d
    if wi[w, WI.type] == MESH:   # per particle: dem.schema mcon
        return math.inf, 0.0, 0.0, 1.0
    # cylinder
    half = wf[w, WF.eu]
    if abs(s) > half:
        return math.inf, 0.0, 0.0, 1.0
    qx = rx - s * ax
    qy = ry - s * ay
    qz = rz - s * az
    rho = math.sqrt(qx * qx + qy * qy + qz * qz)
    if rho < 1e-300:
        return math.inf, 0.0, 0.0, 1.0
    side = wf[w, WF.side]
    return side * (wf[w, WF.rad] - rho), side * qx / rho, side * qy / rho, side * qz / rho


@njit(cache=True, error_model="numpy", inline="always")
def particle_wall(wf, wi, mcon, w, i, x0, x1, x2, t):
    """:func:`wall_distance` of particle i (centre x) and wall row w, a mesh row's from the
    particle's own contact record ``mcon`` (dem.schema; dem.contact.mesh.mesh_contacts)."""
    if wi[w, WI.type] == MESH:
        return mcon[i, w, 0], mcon[i, w, 1], mcon[i, w, 2], mcon[i, w, 3]
    return wall_distance(wf, wi, w, x0, x1, x2, t)


@njit(cache=True, error_model="numpy")
def wall_velocity(wf, w, cx, cy, cz, t):
    """Velocity of the wall surface at point c: V + Omega x (c - C(t))."""
    ox = wf[w, WF.ox]
    oy = wf[w, WF.ox + 1]
    oz = wf[w, WF.ox + 2]
    rx = cx - (wf[w, WF.cx] + wf[w, WF.vx] * t)
    ry = cy - (wf[w, WF.cx + 1] + wf[w, WF.vx + 1] * t)
    rz = cz - (wf[w, WF.cx + 2] + wf[w, WF.vx + 2] * t)
    return (wf[w, WF.vx] + oy * rz - oz * ry,
            wf[w, WF.vx + 1] + oz * rx - ox * rz,
            wf[w, WF.vx + 2] + ox * ry - oy * rx)


def wall_rows(walls):
    """The rows of the scene's walls ``walls`` (dem.scene) in wf / wi and every per-wall array:
    (first row of each wall, the wall of each row). A plane or a cylinder is one row, a mesh
    its ``slots`` (dem.contact.mesh.SLOTS); without meshes row k is wall k."""
    counts = np.array([int(w.get("slots", 1)) for w in walls], np.int64)
    first = np.r_[0, np.cumsum(counts)[:-1]].astype(np.int64) if len(walls) else np.zeros(0, np.int64)
    owner = np.repeat(np.arange(len(walls), dtype=np.int64), counts)
    return first, owner


def per_wall(values, walls):
    """Per-row values (the wall totals of dem.schema, rows of wall_rows) summed per wall."""
    first, owner = wall_rows(walls)
    v = np.asarray(values, float)[:owner.size]
    if owner.size == len(walls):
        return v.copy()
    return np.bincount(owner, weights=v, minlength=len(walls))
