"""Pictures of both phases of a coupled output folder: a mid-plane slice of a gas field (void
fraction by default) with the particles whose centres lie within one radius of the plane, with
a time label, a length scale and colour bars beside the data. Off-screen, without a display
(EGL: dem.render.headless).

* ``coupling render OUT``: one picture at one written gas time (default the last); the PNG
  never replaces a user's file (dem.outdir.claim_file).
* ``coupling render OUT --animate``: one frame per written gas time (``--times START:END``: those
  in that range; t = 0 included) into a folder of its own, ``frame_0000.png`` ... and
  ``animation.gif`` (Pillow, one palette for every frame), every frame with the same colour
  ranges: those of all the frames (the animation does not flicker). The folder (default
  ``OUT/gas_animation_<field>``) is new, empty or an earlier animation of this tool: it has its
  own manifest (dem.outdir), a new animation replaces exactly what the earlier one wrote, and a
  folder holding anything else is refused before anything is drawn.

    coupling render out/fluidized_bed                       # OUT/gas_render.png, eps, last time
    coupling render out/fluidized_bed --field T --time 0.1 --png t.png
    coupling render out/fluidized_bed --animate --times 0.1:0.3
"""
from __future__ import annotations

import argparse
import glob
import math
import os

import numpy as np

FIELDS = {"alpha": "eps", "eps": "eps", "U": "U", "T": "T", "p": "p"}
LABELS = {"eps": "gas void fraction", "U": "gas speed (m/s)", "T": "gas temperature (K)", "p": "pressure (Pa)"}
ANIMATION = "coupling render --animate"   # the command recorded in an animation folder's manifest
GIF = "animation.gif"
FRAME_MS = 250                            # each frame of the GIF: 4 frames per second


def times_argument(text):
    """argparse type of ``--times``: START:END in seconds (either end may be left out) ->
    (start, end), None for an open end."""
    what = f"must be START:END in seconds (e.g. 0.05:0.2; either end may be left out), got {text!r}"
    if text.count(":") != 1:
        raise argparse.ArgumentTypeError(what)
    ends = []
    for part in text.split(":"):
        part = part.strip()
        if not part:
            ends.append(None)
            continue
        try:
            x = float(part)
        except ValueError:
            raise argparse.ArgumentTypeError(what) from None
        if not math.isfinite(x) or x < 0:
            raise argparse.ArgumentTypeError(f"must be START:END with finite times >= 0 s, got {text!r}")
        ends.append(x)
    if ends[0] is not None and ends[1] is not None and ends[0] > ends[1]:
        raise argparse.ArgumentTypeError(f"START must not be after END, got {text!r}")
    return tuple(ends)


def time_argument(text):
    """argparse type of ``--time``: a finite time >= 0 in seconds."""
    try:
        x = float(text)
    except ValueError:
        x = float("nan")
    if not math.isfinite(x) or x < 0:
        raise argparse.ArgumentTypeError(f"must be a time in seconds, finite and >= 0 (e.g. 0.1), got {text!r}")
    return x


def _opener(out):
    found = sorted(glob.glob(os.path.join(out, "*.foam")))
    if not found:
        from dem.outdir import OutputFolderError
        raise OutputFolderError(f"{out}: no <case>.foam opener: not the --out folder of a `coupling run` "
                                f"(or one written before the opener existed: touch {out}/case.foam)")
    return found[0]


def _reader(out, opener):
    """(pyvista's OpenFOAM reader of the gas, its written times: those with a time folder, in
    OUT or, decomposed, in processor0; the reader lists t = 0 even when no folder holds it)."""
    import pyvista as pv
    decomposed = bool(glob.glob(os.path.join(out, "processor*"))) and not _reconstructed_times(out)
    r = pv.POpenFOAMReader(opener)
    if decomposed:
        r.case_type = "decomposed"
    where = os.path.join(out, "processor0") if decomposed else out
    folders = [float(d) for d in _time_names(where)]
    written = [t for t in r.time_values if any(abs(t - f) <= 1e-9 * max(abs(f), 1e-6) for f in folders)]
    return r, written


def _time_names(folder):
    """The names of ``folder``'s time folders (numbers >= 0)."""
    def is_time(name):
        try:
            return float(name) >= 0.0 and os.path.isdir(os.path.join(folder, name))
        except ValueError:
            return False
    return [d for d in os.listdir(folder) if is_time(d)] if os.path.isdir(folder) else []


def _read(r, t):
    r.set_active_time_value(t)
    return r.read()["internalMesh"]


def _gas(out, opener, time):
    """(time, cell mesh) of the gas at the written time nearest ``time`` (None: the last)."""
    r, written = _reader(out, opener)
    times = [t for t in written if t > 0.0] or written
    if not times:
        from dem.outdir import OutputFolderError
        raise OutputFolderError(f"{opener}: the gas wrote no time folder yet")
    t = times[-1] if time is None else min(times, key=lambda v: abs(v - time))
    return t, _read(r, t)


def _reconstructed_times(out):
    return [d for d in _time_names(out) if float(d) > 0.0]


def _particles(out, t, entries=None):
    """(points, radius, temperature or None, frame time) of the particle frame nearest time t
    (``entries``: the .pvd's, read once by an animation)."""
    from dem.output import pvd_entries, read_frame
    pvd = os.path.join(out, "particles.pvd")
    if entries is None:
        entries = pvd_entries(pvd) if os.path.isfile(pvd) else []
    entries = [e for e in entries if os.path.isfile(os.path.join(out, e[1]))]
    if not entries:
        return np.zeros((0, 3)), np.zeros(0), None, None
    tf, f = min(entries, key=lambda e: abs(e[0] - t))
    pts, data = read_frame(os.path.join(out, f))
    return (pts, np.asarray(data["radius"], float),
            np.asarray(data["temperature"], float) if "temperature" in data else None, tf)


class _View:
    """Where the slice lies and how the camera sees it (from the gas mesh's bounds: the same
    for every frame). Gravity along -z: the bed's height is up; the slice's normal is the
    thinner horizontal axis."""

    def __init__(self, cells, window):
        self.lo, self.hi = np.array(cells.bounds[0::2]), np.array(cells.bounds[1::2])
        self.ext = self.hi - self.lo
        self.up = 2
        self.across = 1 if self.ext[1] <= self.ext[0] else 0
        self.side = 1 - self.across
        self.centre = 0.5 * (self.lo + self.hi)
        self.normal = np.zeros(3)
        self.normal[self.across] = 1.0
        self.window = window

    def slice(self, cells, name):
        """(the slice of the cells, the name of its scalar: the field, or the speed of U)."""
        sl = cells.slice(normal=self.normal, origin=self.centre)
        if name == "U":
            sl.cell_data["speed"] = np.linalg.norm(np.asarray(sl.cell_data["U"]), axis=1)
            return sl, "speed"
        return sl, name

    def near(self, pts, rad):
        """The particles whose centres lie within one radius of the plane."""
        if not pts.shape[0]:
            return np.zeros(0, bool)
        return np.abs(pts[:, self.across] - self.centre[self.across]) < rad


def _field_error(field, t, cells):
    from dem.outdir import OutputFolderError
    return OutputFolderError(f"--field {field}: no gas field {FIELDS[field]!r} at t = {t:g} s; fields: "
                             f"{', '.join(sorted(cells.cell_data.keys()))}")


def _draw(view, sl, scal, name, t, particles, clim=None, tclim=None):
    """The picture (an RGB array) of one slice with its particles. ``clim``, ``tclim``: the
    colour ranges of the gas field and of the particle temperature (None: the data's)."""
    import pyvista as pv
    pts, rad, temp, tf = particles
    near = view.near(pts, rad)
    window = view.window
    pl = pv.Plotter(off_screen=True, window_size=window)
    pl.set_background("white")
    pl.add_mesh(sl, scalars=scal, preference="cell", cmap="viridis" if name == "eps" else "coolwarm", clim=clim,
                scalar_bar_args=dict(title=LABELS[name], vertical=True, position_x=0.86, position_y=0.25,
                                     height=0.5, width=0.05, fmt="%.3g", color="black"))
    centre, across = view.centre, view.across
    if near.any():
        cloud = pv.PolyData(pts[near].copy())
        cloud["radius"] = rad[near]
        # the particles in front of the slice (towards the camera), so the gas shows between them
        cloud.points[:, across] = centre[across] - 0.5 * rad[near]
        glyphs = cloud.glyph(scale="radius", geom=pv.Sphere(radius=1.0, theta_resolution=10, phi_resolution=10),
                             orient=False)
        if temp is not None:
            glyphs["particle T (K)"] = np.repeat(temp[near], glyphs.n_points // max(near.sum(), 1))
            pl.add_mesh(glyphs, scalars="particle T (K)", cmap="inferno", clim=tclim,
                        scalar_bar_args=dict(title="particle T (K)", vertical=True, position_x=0.06,
                                             position_y=0.25, height=0.5, width=0.05, fmt="%.2f",
                                             color="black"))
        else:
            pl.add_mesh(glyphs, color="lightgray")
    # a length scale: a bar of a round length under the domain
    lo, ext, up, side = view.lo, view.ext, view.up, view.side
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
    label = (f"t = {t:.4g} s   slice {'xyz'[across]} = {centre[across] * 1e3:.3g} mm   "
             f"{int(near.sum())} particles within one radius")
    if tf is not None and abs(tf - t) > 1e-9 * max(abs(t), 1e-3):
        label += f" (particles at t = {tf:.4g} s)"
    pl.add_text(label, position=(20, window[1] - 40), font_size=11, color="black")
    pl.camera_position = [tuple(centre - 3.0 * ext.max() * view.normal), tuple(centre),
                          tuple(np.eye(3)[up])]
    pl.enable_parallel_projection()
    pl.reset_camera()
    pl.camera.parallel_scale = 0.62 * max(ext[up], ext[side] * window[1] / window[0])
    img = pl.screenshot(return_img=True)
    pl.close()
    return img


def _check_field(out, field):
    from dem.outdir import OutputFolderError
    if not os.path.isdir(out):
        raise OutputFolderError(f"{out}: no such output folder (give the --out folder of a `coupling run`)")
    if field not in FIELDS:
        raise OutputFolderError(f"--field {field}: allowed are {', '.join(FIELDS)}")
    return FIELDS[field]


def render(out, png=None, field="eps", time=None, window=(900, 1000)):
    """Write the picture; returns its path. ``field``: eps (alias alpha), U, T or p."""
    from dem.outdir import claim_file
    from dem.render import headless, write_png
    name = _check_field(out, field)
    png = png or os.path.join(out, "gas_render.png")
    opener = _opener(out)
    claim_file(png, "--png")   # refused before anything is drawn
    headless()
    import pyvista as pv
    pv.OFF_SCREEN = True
    t, cells = _gas(out, opener, time)
    if name not in cells.cell_data:
        raise _field_error(field, t, cells)
    view = _View(cells, window)
    sl, scal = view.slice(cells, name)
    img = _draw(view, sl, scal, name, t, _particles(out, t))
    write_png(png, img, command="coupling render")
    return png


# --------------------------------------------------------------------------- animation

def select_times(written, times):
    """The written gas times within ``times`` = (start, end) (None: open; both ends included,
    to a relative 1e-9), all of them when ``times`` is None; OutputFolderError when none."""
    from dem.outdir import OutputFolderError
    if not written:
        raise OutputFolderError("--animate: the gas wrote no time folder yet: nothing to animate")
    if times is None:
        return list(written)
    a, b = times
    tol = 1e-9 * max(abs(written[-1]), 1e-3)
    chosen = [t for t in written if (a is None or t >= a - tol) and (b is None or t <= b + tol)]
    if not chosen:
        shown = ", ".join(f"{t:g}" for t in written[:8]) + (f" ... {written[-1]:g}" if len(written) > 8 else "")
        span = f"{'' if a is None else f'{a:g}'}:{'' if b is None else f'{b:g}'}"
        raise OutputFolderError(f"--times {span}: no written gas time in that range; the gas wrote {len(written)} "
                                f"time(s) from {written[0]:g} to {written[-1]:g} s ({shown}): give a range "
                                f"holding some of them, or leave --times out for all")
    return chosen


def _frames_folder(out, frames):
    """Refuse (OutputFolderError) a --frames folder that may not hold the animation: the output
    folder itself (or one holding it), a folder with files this tool did not write, or the
    output of another command; read-only."""
    from dem import outdir
    from dem.outdir import OutputFolderError
    real, rout = os.path.realpath(frames), os.path.realpath(out)
    if real == rout or rout.startswith(real.rstrip(os.sep) + os.sep):
        raise OutputFolderError(f"--frames {frames} is (or holds) the output folder {out}; the frames need a folder "
                                f"of their own (default {os.path.join(out, 'gas_animation_<field>')})")
    state = outdir.check(frames, overwrite=True, what="--frames")
    if state == "output":
        command = outdir.manifest_command(frames)
        if command != ANIMATION:
            raise OutputFolderError(f"--frames {frames} holds the output of `{command or 'another command'}`, not "
                                    f"an animation; nothing was touched. Give a new folder")


def _claim_frames_folder(frames):
    """Make ``frames`` the animation's folder: listed in the manifest of the output folder that
    holds it (so that its --overwrite removes it), what an earlier animation wrote there
    removed, its own manifest written (every frame is recorded in it before it is written)."""
    from dem import outdir
    outdir.join_output(frames)
    outdir.claim_folder(frames, overwrite=True, command=ANIMATION, what="--frames")


def _range(values):
    """(lo, hi) of the finite values (hi > lo), None when there are none."""
    v = np.concatenate([np.asarray(x, float).ravel() for x in values]) if values else np.zeros(0)
    v = v[np.isfinite(v)]
    if not v.size:
        return None
    lo, hi = float(v.min()), float(v.max())
    if hi <= lo:
        pad = max(abs(lo) * 1e-6, 1e-12)
        lo, hi = lo - pad, hi + pad
    return lo, hi


def animate(out, field="eps", times=None, frames=None, window=(900, 1000), log=None):
    """One picture per written gas time (``times`` = (start, end) seconds, None ends open; None:
    every written time, t = 0 included) into the folder ``frames`` (default
    ``OUT/gas_animation_<field>``): ``frame_0000.png`` ... and ``animation.gif``. The colour
    ranges of the gas field and of the particle temperature are those of all the frames.
    Returns (folder, [frame paths], GIF path). Everything is checked (folder, field, times)
    before anything is written."""
    from dem.output import atomic_write
    from dem.render import headless, write_png
    name = _check_field(out, field)
    frames = frames or os.path.join(out, f"gas_animation_{name}")
    opener = _opener(out)
    _frames_folder(out, frames)
    headless()
    import pyvista as pv
    pv.OFF_SCREEN = True
    r, written = _reader(out, opener)
    chosen = select_times(written, times)
    from dem.output import pvd_entries
    pvd = os.path.join(out, "particles.pvd")
    entries = pvd_entries(pvd) if os.path.isfile(pvd) else []
    # every frame's slice and particles first: the colour ranges are those of all the frames
    view, scenes = None, []
    for t in chosen:
        cells = _read(r, t)
        if name not in cells.cell_data:
            raise _field_error(field, t, cells)
        view = view or _View(cells, window)
        sl, scal = view.slice(cells, name)
        scenes.append((t, sl, scal, _particles(out, t, entries)))
    clim = _range([s[1].cell_data[s[2]] for s in scenes])
    tclim = _range([p[2][view.near(p[0], p[1])] for *_, p in scenes if p[2] is not None])
    _claim_frames_folder(frames)
    paths = []
    for k, (t, sl, scal, parts) in enumerate(scenes):
        img = _draw(view, sl, scal, name, t, parts, clim=clim, tclim=tclim)
        paths.append(os.path.join(frames, f"frame_{k:04d}.png"))
        write_png(paths[-1], img, command=ANIMATION)
        if log is not None:
            log(f"frame {k + 1}/{len(scenes)}: t = {t:g} s")
    gif = os.path.join(frames, GIF)
    atomic_write(gif, lambda tmp: _write_gif(tmp, paths))
    return frames, paths, gif


def _write_gif(path, pngs):
    """An animated GIF of the PNGs with one palette for all (that of the first and the last
    frame together): a colour is the same in every frame."""
    from PIL import Image
    first = np.asarray(Image.open(pngs[0]).convert("RGB"))
    last = np.asarray(Image.open(pngs[-1]).convert("RGB"))
    palette = Image.fromarray(np.concatenate([first, last])).quantize(colors=256, method=Image.Quantize.MEDIANCUT)
    images = [Image.open(p).convert("RGB").quantize(palette=palette, dither=Image.Dither.NONE) for p in pngs]
    images[0].save(path, format="GIF", save_all=True, append_images=images[1:], duration=FRAME_MS, loop=0,
                   optimize=False)
