"""One picture of both phases of a coupled output folder: a mid-plane slice of a gas field
(void fraction by default) with the particles whose centres lie within one radius of the
plane, at one time (default the last written), with a time label, a length scale and colour
bars beside the data (`coupling render OUT`). Off-screen, without a display (EGL:
dem.render.headless); the PNG never replaces a user's file (dem.outdir.claim_file).

    coupling render out/fluidized_bed                       # OUT/gas_render.png, eps, last time
    coupling render out/fluidized_bed --field T --time 0.1 --png t.png
"""
from __future__ import annotations

import glob
import os

import numpy as np

FIELDS = {"alpha": "eps", "eps": "eps", "U": "U", "T": "T", "p": "p"}
LABELS = {"eps": "gas void fraction", "U": "gas speed (m/s)", "T": "gas temperature (K)", "p": "pressure (Pa)"}


def _opener(out):
    found = sorted(glob.glob(os.path.join(out, "*.foam")))
    if not found:
        from dem.outdir import OutputFolderError
        raise OutputFolderError(f"{out}: no <case>.foam opener: not the --out folder of a `coupling run` "
                                f"(or one written before the opener existed: touch {out}/case.foam)")
    return found[0]


def _gas(out, opener, time):
    """(time, cell mesh) of the gas at the written time nearest ``time`` (None: the last)."""
    import pyvista as pv
    decomposed = bool(glob.glob(os.path.join(out, "processor*"))) and not _reconstructed_times(out)
    r = pv.POpenFOAMReader(opener)
    if decomposed:
        r.case_type = "decomposed"
    times = [t for t in r.time_values if t > 0.0] or list(r.time_values)
    if not times:
        from dem.outdir import OutputFolderError
        raise OutputFolderError(f"{opener}: the gas wrote no time folder yet")
    t = times[-1] if time is None else min(times, key=lambda v: abs(v - time))
    r.set_active_time_value(t)
    return t, r.read()["internalMesh"]


def _reconstructed_times(out):
    def is_time(name):
        try:
            return float(name) > 0.0
        except ValueError:
            return False
    return [d for d in os.listdir(out) if is_time(d) and os.path.isdir(os.path.join(out, d))]


def _particles(out, t):
    """(points, radius, temperature or None) of the particle frame nearest time t."""
    from dem.output import read_frames
    frames = read_frames(out)
    if not frames:
        return np.zeros((0, 3)), np.zeros(0), None
    tf, _, pts, data = min(frames, key=lambda f: abs(f[0] - t))
    return pts, np.asarray(data["radius"], float), (np.asarray(data["temperature"], float)
                                                   if "temperature" in data else None)


def render(out, png=None, field="eps", time=None, window=(900, 1000)):
    """Write the picture; returns its path. ``field``: eps (alias alpha), U, T or p."""
    from dem.outdir import OutputFolderError, claim_file
    from dem.render import headless, write_png
    if not os.path.isdir(out):
        raise OutputFolderError(f"{out}: no such output folder (give the --out folder of a `coupling run`)")
    if field not in FIELDS:
        raise OutputFolderError(f"--field {field}: allowed are {', '.join(FIELDS)}")
    name = FIELDS[field]
    png = png or os.path.join(out, "gas_render.png")
    opener = _opener(out)
    claim_file(png, "--png")   # refused before anything is drawn
    headless()
    import pyvista as pv
    pv.OFF_SCREEN = True
    t, cells = _gas(out, opener, time)
    if name not in cells.cell_data:
        raise OutputFolderError(f"--field {field}: no gas field {name!r} at t = {t:g} s; fields: "
                                f"{', '.join(sorted(cells.cell_data.keys()))}")
    lo, hi = np.array(cells.bounds[0::2]), np.array(cells.bounds[1::2])
    ext = hi - lo
    up = 2                                   # gravity along z: the bed's height is up
    across = 1 if ext[1] <= ext[0] else 0    # the slice's normal: the thinner horizontal axis
    side = 1 - across
    centre = 0.5 * (lo + hi)
    normal = np.zeros(3)
    normal[across] = 1.0
    sl = cells.slice(normal=normal, origin=centre)
    if name == "U":
        sl.cell_data["speed"] = np.linalg.norm(np.asarray(sl.cell_data["U"]), axis=1)
        scal = "speed"
    else:
        scal = name
    pts, rad, temp = _particles(out, t)
    near = np.abs(pts[:, across] - centre[across]) < rad if pts.shape[0] else np.zeros(0, bool)
    pl = pv.Plotter(off_screen=True, window_size=window)
    pl.set_background("white")
    pl.add_mesh(sl, scalars=scal, preference="cell", cmap="viridis" if name == "eps" else "coolwarm",
                scalar_bar_args=dict(title=LABELS[name], vertical=True, position_x=0.86, position_y=0.25,
                                     height=0.5, width=0.05, fmt="%.3g", color="black"))
    if near.any():
        cloud = pv.PolyData(pts[near].copy())
        cloud["radius"] = rad[near]
        # the particles in front of the slice (towards the camera), so the gas shows between them
        cloud.points[:, across] = centre[across] - 0.5 * rad[near]
        glyphs = cloud.glyph(scale="radius", geom=pv.Sphere(radius=1.0, theta_resolution=10, phi_resolution=10),
                             orient=False)
        if temp is not None:
            glyphs["particle T (K)"] = np.repeat(temp[near], glyphs.n_points // max(near.sum(), 1))
            pl.add_mesh(glyphs, scalars="particle T (K)", cmap="inferno",
                        scalar_bar_args=dict(title="particle T (K)", vertical=True, position_x=0.06,
                                             position_y=0.25, height=0.5, width=0.05, fmt="%.2f",
                                             color="black"))
        else:
            pl.add_mesh(glyphs, color="lightgray")
    # a length scale: a bar of a round length under the domain
    L = ext[side]
    bar = 10.0 ** np.floor(np.log10(0.3 * L))
    y0 = lo[up] - 0.04 * ext[up]
    a = lo.copy()
    a[up] = y0
    b = a.copy()
    b[side] += bar
    pl.add_mesh(pv.Line(a, b), color="black", line_width=4)
    pl.add_point_labels([b], [f"{bar * 1e3:g} mm"], font_size=14, text_color="black", shape=None,
                        show_points=False, always_visible=True)
    pl.add_text(f"t = {t:.4g} s   slice {'xyz'[across]} = {centre[across] * 1e3:.3g} mm   "
                f"{int(near.sum())} particles within one radius", position=(20, window[1] - 40), font_size=11,
                color="black")
    pl.camera_position = [tuple(centre - 3.0 * ext.max() * normal), tuple(centre),
                          tuple(np.eye(3)[up])]
    pl.enable_parallel_projection()
    pl.reset_camera()
    pl.camera.parallel_scale = 0.62 * max(ext[up], ext[side] * window[1] / window[0])
    img = pl.screenshot(return_img=True)
    pl.close()
    write_png(png, img, command="coupling render")
    return png
