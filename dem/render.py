"""Off-screen rendering of a run's last VTK output with pyvista (no display needed)."""
import glob
import os


def render(out_dir, png=None, color=None):
    import pyvista as pv
    pv.OFF_SCREEN = True
    from .scene import SceneError
    if not os.path.isdir(out_dir):
        raise SceneError(out_dir, "", "no such output folder (give the --out folder of a `dem run`)")
    files = sorted(glob.glob(os.path.join(out_dir, "vtk", "*.vtu")))
    if not files:
        raise SceneError(out_dir, "", "no vtk/*.vtu output to render (a `dem run` with [output] vtk = true "
                                      "writes them)")
    mesh = pv.read(files[-1])
    if color is None:
        color = "temperature" if "temperature" in mesh.point_data else "velocity"
    if color not in mesh.point_data:
        raise SceneError("--color", "", f"no field {color!r} in {files[-1]}; fields: "
                                        f"{', '.join(sorted(mesh.point_data.keys()))}")
    scal = mesh.point_data[color]
    if scal.ndim == 2:
        import numpy as np
        mesh.point_data[color + "_magnitude"] = np.linalg.norm(scal, axis=1)
        color = color + "_magnitude"
    geom = pv.Sphere(radius=1.0, theta_resolution=12, phi_resolution=12)
    glyphs = mesh.glyph(scale="radius", geom=geom, orient=False)
    pl = pv.Plotter(off_screen=True, window_size=(900, 700))
    pl.add_mesh(glyphs, scalars=color, cmap="coolwarm" if "temp" in color else "viridis",
                scalar_bar_args={"fmt": "%.2f", "title": color})
    pl.view_isometric()
    png = png or os.path.join(out_dir, "render.png")
    pl.screenshot(png)
    pl.close()
    return png
