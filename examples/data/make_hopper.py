"""Writes examples/data/hopper.stl, the vessel of examples/hopper_fill.toml: a cylinder of
radius 20 mm from z = 40 to 80 mm on a cone (its wall 25 degrees from the axis) down to a flat
bottom of radius 6 mm at z = 10 mm, in millimetres (the scene
scales by 0.001), 72 segments around, as a CAD program would export it. Deterministic:
`python3 examples/data/make_hopper.py` writes the same bytes."""
import os
import sys

import numpy as np

sys.path.insert(0, os.path.join(os.path.dirname(os.path.abspath(__file__)), "..", ".."))
from dem.contact.mesh import write_stl  # noqa: E402

SEG = 72
RINGS = [(0.0, 10.0), (6.0, 10.0), (20.0, 40.0), (20.0, 80.0)]   # (radius, z) from the bottom's centre up


def hopper():
    th = np.linspace(0.0, 2 * np.pi, SEG + 1)
    tris = []
    for (r0, z0), (r1, z1) in zip(RINGS[:-1], RINGS[1:]):
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


if __name__ == "__main__":
    out = os.path.join(os.path.dirname(os.path.abspath(__file__)), "hopper.stl")
    write_stl(out, hopper(), binary=True, name="hopper")
    print(out)
