"""Writes the vessels of the examples, in millimetres (the scenes scale by 0.001), 72 segments
around, as a CAD program would export them. Deterministic: `python3 examples/data/make_hopper.py`
writes the same bytes.

hopper.stl (examples/hopper_fill.toml): a cylinder of radius 20 mm from z = 40 to 80 mm on a
cone (its wall 25 degrees from the axis) down to a flat bottom of radius 6 mm at z = 10 mm.

discharge_D6.stl, discharge_D8.stl, discharge_D10.stl (examples/hopper_discharge.toml,
benchmarks/hopper_discharge.py): a cylinder of radius 15 mm from z = 30 to 70 mm on a cone of
half-angle 30 degrees open at the bottom, a round orifice of diameter D mm (the cone ends where
its radius is D / 2: at z = 30 - (15 - D / 2) / tan 30 degrees).

kiln.stl (examples/kiln_feed.toml): the shell of a rotary kiln, a tube of radius 25 mm from x = 0
to 100 mm along the x axis, open at both ends."""
import os
import sys

import numpy as np

sys.path.insert(0, os.path.join(os.path.dirname(os.path.abspath(__file__)), "..", ".."))
from dem.contact.mesh import write_stl  # noqa: E402

SEG = 72
RINGS = [(0.0, 10.0), (6.0, 10.0), (20.0, 40.0), (20.0, 80.0)]   # (radius, z) from the bottom's centre up


DISCHARGE_WIDTHS = (6, 8, 10)   # orifice diameters (mm)
HALF_ANGLE = 30.0                # degrees from the axis


def discharge_rings(d):
    """(radius, z) of the discharge hopper with an orifice of diameter d mm, bottom up."""
    z0 = 30.0 - (15.0 - d / 2.0) / np.tan(np.radians(HALF_ANGLE))
    return [(d / 2.0, z0), (15.0, 30.0), (15.0, 70.0)]


def hopper(rings=RINGS):
    th = np.linspace(0.0, 2 * np.pi, SEG + 1)
    tris = []
    for (r0, z0), (r1, z1) in zip(rings[:-1], rings[1:]):
        for a, b in zip(th[:-1], th[1:]):
            p00 = [r0 * np.cos(a), r0 * np.sin(a), z0]
            p01 = [r0 * np.cos(b), r0 * np.sin(b), z0]
            p10 = [r1 * np.cos(a), r1 * np.sin(a), z1]
            p11 = [r1 * np.cos(b), r1 * np.sin(b), z1]
            if r0 == 0.0:
                tris.append([p00, p11, p10])
            else:
                tris += [[p00, p01, p11], [p00, p11, p10]]
    return np.array(tris)


def kiln(radius=25.0, length=100.0):
    """The kiln's shell: 72 segments around the x axis, one quad (two triangles) each."""
    th = np.linspace(0.0, 2 * np.pi, SEG + 1)
    tris = []
    for a, b in zip(th[:-1], th[1:]):
        p0 = [0.0, radius * np.cos(a), radius * np.sin(a)]
        p1 = [0.0, radius * np.cos(b), radius * np.sin(b)]
        q0, q1 = [length, p0[1], p0[2]], [length, p1[1], p1[2]]
        tris += [[p0, q1, p1], [p0, q0, q1]]
    return np.array(tris)


if __name__ == "__main__":
    here = os.path.dirname(os.path.abspath(__file__))
    write_stl(os.path.join(here, "hopper.stl"), hopper(), binary=True, name="hopper")
    print(os.path.join(here, "hopper.stl"))
    write_stl(os.path.join(here, "kiln.stl"), kiln(), binary=True, name="kiln")
    print(os.path.join(here, "kiln.stl"))
    for d in DISCHARGE_WIDTHS:
        out = os.path.join(here, f"discharge_D{d}.stl")
        write_stl(out, hopper(discharge_rings(d)), binary=True, name=f"discharge_D{d}")
        print(out)
