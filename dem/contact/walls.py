"""Wall geometry: planes (infinite one-sided, or bounded two-sided rectangles) and
cylinders (particles inside or outside, optionally finite), moving with a constant
translational velocity and/or a surface rotation about an axis that leaves the surface
invariant (a drum turning about its axis, an end plate turning about its normal).

Walls are rows of a float array ``wf`` (columns below) and an int array ``wi``.
"""
import math
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
    ("type", "PLANE or CYLINDER"),
    ("mat", "material index"),
))
PLANE, CYLINDER = 0, 1


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
