"""Writes the round vessel of openfoam_cases/round_bed from one description, for both phases:
system/blockMeshDict (the gas: an O-grid of five blocks, a square core and four blocks out to
the wall, whose arcs blockMesh divides at equal angles) and vessel.stl (the DEM's wall: the gas
mesh's wall faces, the flat quads between the O-grid's boundary points, two triangles each), so
that the particles meet the wall exactly where the gas does. Deterministic:
`python3 openfoam_cases/round_bed/make_case.py` writes the same bytes.

Vessel: radius R = 20 mm (at the boundary points), height 0.15 m; core half-side 9 mm in 3 x 3
cells, 3 cells along each quarter arc (a 12-sided section, 3 R^2 = 95.5 % of pi R^2), 2 cells
from the core to the wall, 24 layers of 6.25 mm."""
import math
import os
import sys

import numpy as np

HERE = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, os.path.join(HERE, "..", ".."))
from dem.contact.mesh import write_stl  # noqa: E402

R, A, H = 0.020, 0.009, 0.15         # wall radius, core half-side, height (m)
NCORE, NRAD, NZ = 3, 2, 24            # cells: core side, core to wall, layers


def corners():
    """The core's corners and the wall points at 45, 135, 225, 315 degrees (counter-clockwise)."""
    ang = np.radians([45.0, 135.0, 225.0, 315.0])
    core = np.c_[np.sign(np.cos(ang)) * A, np.sign(np.sin(ang)) * A]
    wall = np.c_[R * np.cos(ang), R * np.sin(ang)]
    return core, wall


def wall_points():
    """The gas mesh's boundary points around the wall: blockMesh divides each quarter arc in NCORE
    cells at equal angles."""
    th = np.radians(45.0 + 90.0 * np.arange(4 * NCORE) / NCORE)
    return np.c_[R * np.cos(th), R * np.sin(th)]


def block_mesh_dict():
    core, wall = corners()
    pts = [(x, y, z) for z in (0.0, H) for x, y in np.r_[core, wall]]   # 0-3 core, 4-7 wall; +8 at the top
    v = "\n".join(f"    ({x:.9g} {y:.9g} {z:.9g})  // {k}" for k, (x, y, z) in enumerate(pts))
    b = [f"    hex (0 1 2 3 8 9 10 11) ({NCORE} {NCORE} {NZ}) simpleGrading (1 1 1)"]
    edges = []
    for q in range(4):   # the block between core edge q -> q+1 and the wall arc
        c0, c1, w0, w1 = q, (q + 1) % 4, 4 + q, 4 + (q + 1) % 4
        b.append(f"    hex ({c0} {w0} {w1} {c1} {c0 + 8} {w0 + 8} {w1 + 8} {c1 + 8}) ({NRAD} {NCORE} {NZ}) "
                 "simpleGrading (1 1 1)")
        mid = math.radians(90.0 + 90.0 * q)
        for z, o in ((0.0, 0), (H, 8)):
            edges.append(f"    arc {w0 + o} {w1 + o} ({R * math.cos(mid):.9g} {R * math.sin(mid):.9g} {z:.9g})")
    faces = {"inlet": [], "outlet": [], "wall": []}
    faces["inlet"].append("(0 1 2 3)")
    faces["outlet"].append("(8 11 10 9)")
    for q in range(4):
        c0, c1, w0, w1 = q, (q + 1) % 4, 4 + q, 4 + (q + 1) % 4
        faces["inlet"].append(f"({c0} {c1} {w1} {w0})")
        faces["outlet"].append(f"({c0 + 8} {w0 + 8} {w1 + 8} {c1 + 8})")
        faces["wall"].append(f"({w0} {w1} {w1 + 8} {w0 + 8})")
    bnd = "\n".join(f"    {name}\n    {{\n        type {'wall' if name == 'wall' else 'patch'};\n"
                    f"        faces ( {' '.join(f)} );\n    }}" for name, f in faces.items())
    return f"""/*--------------------------------*- C++ -*----------------------------------*\\
  thermodem template for thermoDemFoam (OpenFOAM v1912): written by make_case.py
\\*---------------------------------------------------------------------------*/
FoamFile
{{
    version     2.0;
    format      ascii;
    class       dictionary;
    object      blockMeshDict;
}}
// * * * * * * * * * * * * * * * * * * * * * * * * * * * * * * * * * * * * * //

// Round fluidized bed: radius {R} m, height {H} m, an O-grid of five blocks; gas enters at z = 0.
convertToMeters 1;

vertices
(
{v}
);

blocks
(
{chr(10).join(b)}
);

edges
(
{chr(10).join(edges)}
);

boundary
(
{bnd}
);

mergePatchPairs ();

// ************************************************************************* //
"""


def vessel_triangles():
    """The wall faces of the gas mesh (one quad per boundary arc segment, full height), as
    triangles with their normals pointing out of the vessel (STL convention; the DEM takes the
    side the particles are on)."""
    p = wall_points()
    tris = []
    for k in range(len(p)):
        a, b = p[k], p[(k + 1) % len(p)]
        a0, b0, a1, b1 = [*a, 0.0], [*b, 0.0], [*a, H], [*b, H]
        tris += [[a0, b0, b1], [a0, b1, a1]]
    return np.array(tris)


if __name__ == "__main__":
    with open(os.path.join(HERE, "system", "blockMeshDict"), "w") as fh:
        fh.write(block_mesh_dict())
    write_stl(os.path.join(HERE, "vessel.stl"), vessel_triangles(), binary=False, name="vessel")
    print(os.path.join(HERE, "system", "blockMeshDict"), os.path.join(HERE, "vessel.stl"))
