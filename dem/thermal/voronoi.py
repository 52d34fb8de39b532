"""Local porosity from a true Voronoi tessellation (scipy.spatial), to verify the
porosity-based estimates of Zhou et al. (2009) used by the Voronoi conduction models.

The porosity of particle i is 1 - V_i / V_cell,i with V_cell the volume of its Voronoi cell
(the standard, not the radical, tessellation: exact for monosized spheres). Cells are
bounded by mirroring the particles across the six faces of the domain box (walls that
coincide with the box faces are therefore treated as cell faces); cells that would still be
unbounded (periodic axes) are left with NaN and replaced by the measuring-sphere value.
"""
import numpy as np


def voronoi_porosity(position, radius, lo, hi):
    from scipy.spatial import ConvexHull, Voronoi
    x = np.asarray(position, float)
    n = x.shape[0]
    pts = [x]
    for k in range(3):
        for b, sgn in ((lo[k], -1), (hi[k], 1)):
            m = x.copy()
            m[:, k] = 2 * b - m[:, k]
            pts.append(m)
    vor = Voronoi(np.concatenate(pts))
    vol = np.full(n, np.nan)
    for i in range(n):
        reg = vor.regions[vor.point_region[i]]
        if not reg or -1 in reg:
            continue
        vol[i] = ConvexHull(vor.vertices[reg]).volume
    vp = 4.0 / 3.0 * np.pi * np.asarray(radius, float) ** 3
    return 1.0 - vp / vol
