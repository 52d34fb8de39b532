"""Wall geometry: planes (infinite one-sided, or bounded two-sided rectangles) and
cylinders (particles inside or outside, optionally finite), moving with a constant
translational velocity and/or a surface rotation about an axis that leaves the surface
invariant (a drum turning about its axis, an end plate turning about its normal).

Walls are rows of a float array ``wf`` (columns below) and an int array ``wi``.
"""
import math
from numba import njit

# float columns
PX, NX, UX, EU, EV, RAD, VX, OX, CX, SIDE = 0, 3, 6, 9, 10, 11, 12, 15, 18, 21
NWF = 22
# int columns
WTYPE, WMAT = 0, 1
NWI = 2
PLANE, CYLINDER = 0, 1


@njit(cache=True, error_model="numpy")
def wall_distance(wf, wi, w, x0, x1, x2, t):
    """Distance from a particle centre to wall ``w`` and the unit vector from the centre
    towards the wall. Returns (dist, nx, ny, nz); dist = inf when no contact is possible."""
    px = wf[w, PX] + wf[w, VX] * t
    py = wf[w, PX + 1] + wf[w, VX + 1] * t
    pz = wf[w, PX + 2] + wf[w, VX + 2] * t
    rx = x0 - px
    ry = x1 - py
    rz = x2 - pz
    ax = wf[w, NX]
    ay = wf[w, NX + 1]
    az = wf[w, NX + 2]
    s = rx * ax + ry * ay + rz * az
    if wi[w, WTYPE] == PLANE:
        eu = wf[w, EU]
        ev = wf[w, EV]
        if eu == math.inf and ev == math.inf:
            return s, -ax, -ay, -az
        ux = wf[w, UX]
        uy = wf[w, UX + 1]
        uz = wf[w, UX + 2]
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
    half = wf[w, EU]
    if abs(s) > half:
        return math.inf, 0.0, 0.0, 1.0
    qx = rx - s * ax
    qy = ry - s * ay
    qz = rz - s * az
    rho = math.sqrt(qx * qx + qy * qy + qz * qz)
    if rho < 1e-300:
        return math.inf, 0.0, 0.0, 1.0
    side = wf[w, SIDE]
    return side * (wf[w, RAD] - rho), side * qx / rho, side * qy / rho, side * qz / rho


@njit(cache=True, error_model="numpy")
def wall_velocity(wf, w, cx, cy, cz, t):
    """Velocity of the wall surface at point c: V + Omega x (c - C(t))."""
    ox = wf[w, OX]
    oy = wf[w, OX + 1]
    oz = wf[w, OX + 2]
    rx = cx - (wf[w, CX] + wf[w, VX] * t)
    ry = cy - (wf[w, CX + 1] + wf[w, VX + 1] * t)
    rz = cz - (wf[w, CX + 2] + wf[w, VX + 2] * t)
    return (wf[w, VX] + oy * rz - oz * ry,
            wf[w, VX + 1] + oz * rx - ox * rz,
            wf[w, VX + 2] + ox * ry - oy * rx)
