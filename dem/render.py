"""Off-screen rendering of a run's last VTK output with pyvista (no display needed).

The PNG never replaces a user's file (dem.outdir.claim_file): it is written only
where nothing exists yet, or over a PNG the tool wrote (listed in the output folder's
manifest, or carrying the tEXt "Software: thermodem" chunk every rendered PNG gets)."""
import glob
import os

from .outdir import PNG_SOFTWARE, OutputFolderError, claim_file
from .output import atomic_write


def headless():
    """Without a display (no DISPLAY: a server, CI, ssh), draw through EGL (Mesa's libEGL,
    installed by scripts/setup.sh) instead of VTK's default X window, which prints "bad X
    server connection" before it falls back; a user's VTK_DEFAULT_OPENGL_WINDOW is kept. Must
    run before VTK is imported."""
    import ctypes.util
    if os.environ.get("DISPLAY") or os.environ.get("WAYLAND_DISPLAY") or "VTK_DEFAULT_OPENGL_WINDOW" in os.environ:
        return
    if ctypes.util.find_library("EGL"):
        os.environ["VTK_DEFAULT_OPENGL_WINDOW"] = "vtkEGLRenderWindow"


def render(out_dir, png=None, color=None):
    what = "--png" if png else "the PNG"
    png = png or os.path.join(out_dir, "render.png")
    if not os.path.isdir(out_dir):
        raise OutputFolderError(f"{out_dir}: no such output folder (give the --out folder of a `dem run`)")
    files = _frames(out_dir)
    if not files:
        raise OutputFolderError(f"{out_dir}: no vtk/*.vtu output to render (a `dem run` with [output] vtk = true "
                                f"writes them)")
    claim_file(png, what)   # refused before anything is drawn; recorded in an output folder's manifest
    headless()
    import pyvista as pv
    pv.OFF_SCREEN = True
    mesh = pv.read(files[-1])
    if color is None:
        color = "temperature" if "temperature" in mesh.point_data else "velocity"
    if color not in mesh.point_data:
        raise OutputFolderError(f"--color: no field {color!r} in {files[-1]}; fields: "
                                        f"{', '.join(sorted(mesh.point_data.keys()))}")
    scal = mesh.point_data[color]
    if scal.ndim == 2:
        import numpy as np
        mesh.point_data[color + "_magnitude"] = np.linalg.norm(scal, axis=1)
        color = color + "_magnitude"
    geom = pv.Sphere(radius=1.0, theta_resolution=12, phi_resolution=12)
    glyphs = mesh.glyph(scale="radius", geom=geom, orient=False)
    pl = pv.Plotter(off_screen=True, window_size=(900, 700))
    pl.set_background("white")
    # the colour bar upright in the right-hand fifth of the picture, its numbers to its right,
    # and the particles in the rest (the camera's window centre moved right, the view zoomed
    # out to the left four fifths): nothing drawn over anything else, no number cut at an edge
    pl.add_mesh(glyphs, scalars=color, cmap="coolwarm" if "temp" in color else "viridis",
                scalar_bar_args=dict(title=_title(color), vertical=True, position_x=0.80, position_y=0.2,
                                     height=0.6, width=0.06, fmt="%.4g", color="black", title_font_size=16,
                                     label_font_size=14))
    pl.view_isometric()
    pl.reset_camera()
    pl.camera.zoom(0.8)
    pl.camera.SetWindowCenter(0.26, 0.0)
    img = pl.screenshot(return_img=True)
    pl.close()
    write_png(png, img)
    return png


UNITS = {"temperature": "K", "velocity_magnitude": "m/s", "angular_velocity_magnitude": "rad/s",
         "radius": "m", "heat_rate": "W"}


def _title(field):
    """The colour bar's title: the field and its unit."""
    return f"{field.replace('_', ' ')} ({UNITS[field]})" if field in UNITS else field.replace("_", " ")


def _frames(out_dir):
    """The VTK frames of a run in time order: the .pvd's entries (a serial .vtu or an MPI .pvtu
    with one piece per rank), else the vtk/*.vtu files."""
    from .output import pvd_entries
    pvd = os.path.join(out_dir, "particles.pvd")
    if os.path.isfile(pvd):
        files = [os.path.join(out_dir, f) for _, f in pvd_entries(pvd)]
        files = [f for f in files if os.path.isfile(f)]
        if files:
            return files
    return sorted(glob.glob(os.path.join(out_dir, "vtk", "*.vtu")))


def write_png(path, img, command="dem render"):
    """The image as a PNG tagged as ours (tEXt Software), written atomically (and recorded
    in the manifest when ``path`` is inside an output folder)."""
    from PIL import Image
    from PIL.PngImagePlugin import PngInfo
    info = PngInfo()
    info.add_text("Software", f"{PNG_SOFTWARE} {command}")
    atomic_write(path, lambda tmp: Image.fromarray(img).save(tmp, format="PNG", pnginfo=info))
