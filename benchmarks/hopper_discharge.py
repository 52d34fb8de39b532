"""Conical hopper discharge (examples/hopper_discharge.toml) in our code and in LIGGGHTS (Debian's
`liggghts`, LIGGGHTS-PUBLIC 3.8.0) side by side on one core, with the same STL and the same initial
particles: discharge rates against Beverloo with the Rose & Tanaka cone factor, and speeds.

    python3 benchmarks/hopper_discharge.py [--widths 6 8 10] [--end-time 0.5] [--dt 5e-6]
                                           [--tangential scene|projected] [--repeat N] [--keep DIR]

For each orifice diameter D (mm; examples/data/discharge_D<D>.stl, made by
examples/data/make_hopper.py):

* ours: a copy of the scene in a temporary folder (the STL by its absolute path, end_time, the
  time step, `[output] vtk = true` for the bulk density below; with --tangential projected also
  `[contact] tangential = "projected"`, LIGGGHTS's own tangential law), run as its own process
  `python3 -m dem run <copy> --out <dir> --threads 1 --quiet`; its time is the `wall` of the
  `done:` line (the run only: reading the scene and compiling or loading the kernels are
  outside it, and the line says how long the kernels took);
* LIGGGHTS: one process (no mpirun), the particles of the same scene at t = 0 (dem.scene.load:
  the positions and radii our run starts from) written as a data file, the same STL
  (`fix mesh/surface file ... type 1 scale 0.001`, `fix wall/gran model hertz tangential
  history mesh n_meshes 1 meshes hopper`), the same material constants (youngsModulus,
  poissonsRatio, coefficientRestitution, coefficientFriction, density), gravity, time step and
  domain (`boundary f f f`, neighbour skin 0.2 mm as in ../shared/bench); a particle below the
  domain's bottom face z = 0.005 m is lost at the next re-neighbouring and dropped
  (`thermo_modify lost ignore`), the LIGGGHTS form of our `[[outlets]] type = "face" face =
  "zmin"` (removed beyond the face, checked every 50 steps); mass and count that left from the
  thermo output (`mass(all)`, `atoms`) at our output interval; its time is the `Loop time`.
  (LIGGGHTS 3.8.0 has no `fix evaporate`; `-screen none` crashes it in the STL reader, so the
  screen goes to a file.)

Speed: particle-steps per second, the particle-steps counted alike for both codes as the sum
over steps of the particles present, integrated by the trapezoid rule over the output rows (our
history.csv `particles`, LIGGGHTS's thermo `atoms`; both every output interval), divided by the
run's time above. One simulation at a time, each on one core (the machine's other core may be
someone else's): the ratio is of runs made one after the other, minutes apart. With --repeat N
the two codes run N times each, alternately (ours, LIGGGHTS, ours, ...), and each is timed by its
fastest run (the least disturbed by the machine's other load; the runs themselves are identical).

Rates: W = the least-squares slope of the mass that left against time over the steady window,
from when 10 % of the initial mass has left (no later than half the run, so that a slow orifice
still has a window) to the end, or to when 30 % remains if that comes first; each code on its
own curve. Beverloo: W_B = C rho_b sqrt(g) (D - k d)^(5/2) (tan theta tan phi_d)^(-0.35) with
C = 0.58, k = 1.5, d the mean particle diameter of the scene, the Rose & Tanaka (1956) cone
factor for theta = 30 degrees (the cone's half angle) and phi_d = 45 degrees (valid for theta <
90 - phi_d); rho_b = the particles' density times the solid fraction measured in our run: the
volume of the spheres whose centres lie in the cylinder r < 8 mm, 22 < z < 30 mm (inside the
cone, 2.4 mm or more from its wall) over its volume, averaged over the VTK frames of the window
in which the bed's top (99th percentile of the heights) is above 32 mm.
"""
import argparse
import math
import os
import re
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

HERE = os.path.dirname(os.path.abspath(__file__))
ROOT = os.path.dirname(HERE)
sys.path.insert(0, HERE)
sys.path.insert(0, ROOT)
from liggghts_side_by_side import ensure_liggghts  # noqa: E402
from shared_scene import parse_loop  # noqa: E402
from benchmarks.accuracy.common import md_table  # noqa: E402
from benchmarks.accuracy.coupled import set_toml  # noqa: E402
from benchmarks.cost.run import machine  # noqa: E402

SCENE = os.path.join(ROOT, "examples", "hopper_discharge.toml")
DATA = os.path.join(ROOT, "examples", "data")
WIDTHS = (6, 8, 10)
C_BEVERLOO, K_BEVERLOO = 0.58, 1.5
HALF_ANGLE, PHI_D = 30.0, 45.0             # degrees: the cone's half angle; Rose & Tanaka's phi_d
FIT_FROM, FIT_LEFT = 0.10, 0.30            # window: from 10 % out to 30 % remaining
RHO_REGION = (0.008, 0.022, 0.030)         # bulk density: r < 8 mm, 22 < z < 30 mm
RHO_TOP = 0.032                            # ... in frames whose bed top (z99) is above 32 mm
LIGGGHTS_SKIN = 0.0002                     # m, the shared LIGGGHTS inputs' `neighbor 0.0002 bin`


# ----------------------------------------------------------------------------- ours
def scene_variant(path, d, end_time, dt, tangential):
    """The scene for orifice ``d`` (mm) in file ``path``: the STL by its absolute path, end time,
    time step, VTK frames on; ``tangential`` "scene" keeps the scene's law."""
    text = open(SCENE).read()
    stl = os.path.join(DATA, f"discharge_D{d}.stl")
    text, n = re.subn(r'(?m)^file\s*=\s*"[^"]*"', f'file = "{stl}"', text)
    if n != 1:
        raise SystemExit(f"{SCENE}: expected one `file = ...` line (the mesh wall), found {n}")
    if tangential != "scene" and not re.search(r"(?m)^\[contact\]", text):
        text += "\n[contact]\n"
    path = Path(path)
    path.write_text(text)
    set_toml(path, "simulation", end_time=float(end_time), time_step=float(dt))
    set_toml(path, "output", vtk=True)
    if tangential != "scene":
        set_toml(path, "contact", tangential=tangential)
    return str(path), stl


def run_ours(scene, out):
    cmd = [sys.executable, "-m", "dem", "run", scene, "--out", out, "--threads", "1", "--quiet"]
    env = dict(os.environ, PYTHONPATH=ROOT + os.pathsep + os.environ.get("PYTHONPATH", ""))
    t0 = time.perf_counter()
    res = subprocess.run(cmd, cwd=ROOT, capture_output=True, text=True, env=env)
    process = time.perf_counter() - t0
    text = res.stdout + res.stderr
    m = re.search(r"done: t = (\S+) s, (\d+) steps, (\d+) particles.*wall ([0-9.]+) s "
                  r"\(kernels compile/load ([0-9.]+) s\)", text)
    if res.returncode != 0 or not m:
        raise SystemExit(f"our run failed ({' '.join(cmd)}), exit {res.returncode}:\n{text[-3000:]}")
    h = np.genfromtxt(os.path.join(out, "history.csv"), delimiter=",", names=True)
    return dict(time=h["time"], n=h["particles"], out=h["mass_out_orifice"], m0=float(h["mass"][0]),
                steps=int(m.group(2)), wall=float(m.group(4)), compile=float(m.group(5)), process=process,
                notes=[ln for ln in text.splitlines() if ln.startswith(("note", "warning"))])


def bulk_density(out, rho_p, t0, t1):
    """(rho_b, solid fraction, frames used) from our VTK frames in [t0, t1] (see the docstring)."""
    from dem.output import read_frames
    R, z0, z1 = RHO_REGION
    vol = math.pi * R * R * (z1 - z0)
    frames = [(t, x, f) for t, _, x, f in read_frames(out) if t0 - 1e-9 <= t <= t1 + 1e-9]
    use = [fr for fr in frames if np.percentile(fr[1][:, 2], 99) >= RHO_TOP] or frames[:1]
    phis = []
    for t, x, f in use:
        r = f["radius"]
        inside = (np.hypot(x[:, 0], x[:, 1]) < R) & (x[:, 2] > z0) & (x[:, 2] < z1)
        phis.append(float(np.sum(4.0 / 3.0 * math.pi * r[inside] ** 3)) / vol)
    phi = float(np.mean(phis)) if phis else float("nan")
    return rho_p * phi, phi, len(phis)


# ----------------------------------------------------------------------------- LIGGGHTS
LIG_INPUT = """# hopper discharge (benchmarks/hopper_discharge.py): the scene {scene}
atom_style      granular
atom_modify     map array
boundary        f f f
newton          off
communicate     single vel yes
units           si
processors      * * 1
read_data       {data}
neighbor        {skin!r} bin
neigh_modify    delay 0
fix m1 all property/global youngsModulus peratomtype {E!r}
fix m2 all property/global poissonsRatio peratomtype {nu!r}
fix m3 all property/global coefficientRestitution peratomtypepair 1 {e!r}
fix m4 all property/global coefficientFriction peratomtypepair 1 {mu!r}
pair_style      gran model hertz tangential history
pair_coeff      * *
timestep        {dt!r}
fix gravi all gravity {g!r} vector {gx!r} {gy!r} {gz!r}
fix hopper all mesh/surface file {stl} type 1 scale {scale!r}
fix walls all wall/gran model hertz tangential history mesh n_meshes 1 meshes hopper
fix integr all nve/sphere
variable m equal mass(all)
thermo_style    custom step atoms v_m cpu
thermo_modify   lost ignore norm no format float %.12g
thermo          {nthermo}
run             {nsteps}
"""


def liggghts_inputs(work, scene_path):
    """The data file and input script of ``scene_path`` (our variant) in ``work``; returns
    (input path, steps, thermo interval in steps, the scene)."""
    from dem import scene as scene_mod
    sc = scene_mod.load(scene_path)
    if len(sc.materials) != 1 or np.any(sc.velocity) or np.any(sc.angular_velocity):
        raise SystemExit("the LIGGGHTS side writes one material and particles at rest")
    mat = sc.materials[0]
    sim = sc.simulation
    lo, hi = sc.domain["min"], sc.domain["max"]
    rows = [f"LIGGGHTS data file of {scene_path} at t = 0 (benchmarks/hopper_discharge.py)", "",
            f"{len(sc.id)} atoms", "1 atom types", ""]
    rows += [f"{float(lo[k])!r} {float(hi[k])!r} {a}lo {a}hi" for k, a in enumerate("xyz")]
    rows += ["", "Atoms", ""]
    rho = float(mat["density"])
    rows += [f"{int(i)} 1 {2.0 * r!r} {rho!r} {x[0]!r} {x[1]!r} {x[2]!r}"
             for i, x, r in zip(sc.id.tolist(), sc.position.tolist(), sc.radius.tolist())]
    data = os.path.join(work, "particles.data")
    with open(data, "w") as fh:
        fh.write("\n".join(rows) + "\n")
    (wall,) = [w for w in sc.raw["walls"] if w.get("type") == "mesh"]
    if wall.get("rotate") or wall.get("translate") or wall.get("velocity") or wall.get("angular_velocity"):
        raise SystemExit("the LIGGGHTS side writes a fixed mesh wall, scaled only")
    g = np.asarray(sim["gravity"], float)
    gn = float(np.linalg.norm(g))
    dt = float(sim["time_step"])
    nsteps = int(round(sim["end_time"] / dt))
    nthermo = int(round(sim["output_interval"] / dt))
    if abs(nsteps * dt - sim["end_time"]) > 1e-9 or abs(nthermo * dt - sim["output_interval"]) > 1e-9:
        raise SystemExit(f"end_time and output_interval must be whole numbers of steps of {dt} s")
    text = LIG_INPUT.format(scene=scene_path, data=data, skin=LIGGGHTS_SKIN, E=float(mat["youngs_modulus"]),
                            nu=float(mat["poisson_ratio"]), e=float(mat["restitution"]), mu=float(mat["friction"]),
                            dt=dt, g=gn, gx=float(g[0] / gn), gy=float(g[1] / gn), gz=float(g[2] / gn),
                            stl=wall["file"] if os.path.isabs(wall["file"]) else os.path.join(sc.base_dir, wall["file"]),
                            scale=float(wall.get("scale", 1.0)), nthermo=nthermo, nsteps=nsteps)
    inp = os.path.join(work, "hopper.lig")
    with open(inp, "w") as fh:
        fh.write(text)
    return inp, nsteps, nthermo, sc


def run_liggghts(work, inp, dt):
    cmd = ["liggghts", "-in", inp, "-log", os.path.join(work, "log.lammps"),
           "-screen", os.path.join(work, "screen.txt")]
    env = dict(os.environ, OMPI_ALLOW_RUN_AS_ROOT="1", OMPI_ALLOW_RUN_AS_ROOT_CONFIRM="1", OMP_NUM_THREADS="1")
    t0 = time.perf_counter()
    res = subprocess.run(cmd, cwd=work, capture_output=True, text=True, env=env)
    process = time.perf_counter() - t0
    log = open(os.path.join(work, "log.lammps")).read() if os.path.exists(os.path.join(work, "log.lammps")) else ""
    loop = parse_loop(log)
    rows = np.array([[float(v) for v in ln.split()] for ln in log.splitlines()
                     if re.match(r"^\s*\d+\s+\d+\s+\S+\s+\S+\s*$", ln)])
    if res.returncode != 0 or not math.isfinite(loop) or rows.size == 0:
        raise SystemExit(f"LIGGGHTS failed ({' '.join(cmd)}), exit {res.returncode}:\n"
                         f"{(res.stdout + res.stderr)[-2000:]}\n{log[-2000:]}")
    return dict(time=rows[:, 0] * dt, n=rows[:, 1], out=rows[0, 2] - rows[:, 2], m0=float(rows[0, 2]),
                steps=int(rows[-1, 0]), wall=loop, process=process,
                notes=[ln.strip() for ln in log.splitlines() if "WARNING" in ln])


# ----------------------------------------------------------------------------- analysis
def particle_steps(t, n, dt):
    """Sum over the steps of the particles present: the trapezoid rule over the output rows."""
    return float(np.sum(0.5 * (n[1:] + n[:-1]) * np.diff(t))) / dt


def _crossing(t, y, level):
    """First time y reaches ``level`` (linear between rows), or None."""
    k = np.nonzero(y >= level)[0]
    if k.size == 0:
        return None
    k = int(k[0])
    if k == 0:
        return float(t[0])
    return float(t[k - 1] + (level - y[k - 1]) * (t[k] - t[k - 1]) / (y[k] - y[k - 1]))


def discharge_rate(r):
    """(W kg/s, window (t0, t1), rows fitted, whether the 10 % mark was reached) of a run's curve."""
    t, y, m0 = r["time"], r["out"], r["m0"]
    t10 = _crossing(t, y, FIT_FROM * m0)
    reached = t10 is not None and t10 <= 0.5 * t[-1]
    start = t10 if reached else 0.5 * t[-1]
    t70 = _crossing(t, y, (1.0 - FIT_LEFT) * m0)
    stop = min(float(t[-1]), t70) if t70 is not None else float(t[-1])
    sel = (t >= start - 1e-12) & (t <= stop + 1e-12)
    if sel.sum() < 3:
        return float("nan"), (start, stop), int(sel.sum()), reached
    w = float(np.polyfit(t[sel], y[sel], 1)[0])
    return w, (start, stop), int(sel.sum()), reached


def stalled(r, span=0.1):
    """The time from which nothing left until the end, when that is longer than ``span`` s
    (a jam, or an empty hopper), else None."""
    t, y = r["time"], r["out"]
    k = np.nonzero(y < y[-1])[0]
    last = float(t[k[-1] + 1]) if k.size else float(t[0])
    return last if t[-1] - last > span else None


def beverloo(rho_b, d_mean, D, g):
    cone = (math.tan(math.radians(HALF_ANGLE)) * math.tan(math.radians(PHI_D))) ** -0.35
    return C_BEVERLOO * rho_b * math.sqrt(g) * max(D - K_BEVERLOO * d_mean, 0.0) ** 2.5 * cone


# ----------------------------------------------------------------------------- main
def one_width(d, a, tmp, log):
    work = os.path.join(tmp, f"D{d}")
    os.makedirs(work)
    scene, stl = scene_variant(os.path.join(work, "scene.toml"), d, a.end_time, a.dt, a.tangential)
    log(f"D = {d} mm: ours ...")
    ours = run_ours(scene, os.path.join(work, "ours"))
    ours["ps"] = particle_steps(ours["time"], ours["n"], a.dt)
    log(f"  ours: {ours['steps']} steps, wall {ours['wall']:.1f} s (kernels {ours['compile']:.1f} s, process "
        f"{ours['process']:.1f} s), {ours['ps'] / ours['wall']:.3g} particle-steps/s, {int(ours['n'][-1])} left")
    lw = os.path.join(work, "liggghts")
    os.makedirs(lw)
    inp, nsteps, _, sc = liggghts_inputs(lw, scene)
    log(f"D = {d} mm: LIGGGHTS ...")
    lig = run_liggghts(lw, inp, a.dt)
    lig["ps"] = particle_steps(lig["time"], lig["n"], a.dt)
    log(f"  LIGGGHTS: {lig['steps']} steps, loop {lig['wall']:.1f} s (process {lig['process']:.1f} s), "
        f"{lig['ps'] / lig['wall']:.3g} particle-steps/s, {int(lig['n'][-1])} left")
    for rep in range(1, a.repeat):   # the two again, alternately: each code's fastest run is its speed
        o2 = run_ours(scene, os.path.join(work, f"ours_{rep}"))
        lw2 = os.path.join(work, f"liggghts_{rep}")
        os.makedirs(lw2)
        inp2, _, _, _ = liggghts_inputs(lw2, scene)
        l2 = run_liggghts(lw2, inp2, a.dt)
        log(f"  again ({rep + 1}/{a.repeat}): ours wall {o2['wall']:.1f} s, LIGGGHTS loop {l2['wall']:.1f} s")
        ours["walls"] = ours.get("walls", [ours["wall"]]) + [o2["wall"]]
        lig["walls"] = lig.get("walls", [lig["wall"]]) + [l2["wall"]]
        ours["wall"], lig["wall"] = min(ours["wall"], o2["wall"]), min(lig["wall"], l2["wall"])
        shutil.rmtree(os.path.join(work, f"ours_{rep}"), ignore_errors=True)
        shutil.rmtree(lw2, ignore_errors=True)
    if lig["steps"] != ours["steps"] or abs(lig["m0"] - ours["m0"]) > 1e-9 * ours["m0"]:
        log(f"  warning: steps {ours['steps']}/{lig['steps']}, initial mass {ours['m0']!r}/{lig['m0']!r}")
    row = dict(D=d, ours=ours, lig=lig)
    for key, r in (("ours", ours), ("lig", lig)):
        row[key + "_W"], row[key + "_win"], row[key + "_nfit"], row[key + "_reached"] = discharge_rate(r)
        row[key + "_stall"] = stalled(r)
    rho_p = float(sc.materials[0]["density"])
    row["rho_b"], row["phi"], row["frames"] = bulk_density(os.path.join(work, "ours"), rho_p, *row["ours_win"])
    row["d_mean"] = float(np.mean(2.0 * sc.radius))
    g = float(np.linalg.norm(sc.simulation["gravity"]))
    row["W_B"] = beverloo(row["rho_b"], row["d_mean"], d * 1e-3, g)
    row["W_B06"] = beverloo(0.6 * rho_p, row["d_mean"], d * 1e-3, g)
    log(f"  W ours {row['ours_W']:.4g} kg/s, LIGGGHTS {row['lig_W']:.4g} kg/s, Beverloo {row['W_B']:.4g} kg/s "
        f"(solid fraction {row['phi']:.3f} over {row['frames']} frames)")
    if a.keep:
        dest = os.path.join(a.keep, f"D{d}")
        shutil.rmtree(dest, ignore_errors=True)
        shutil.copytree(work, dest)
    shutil.rmtree(work, ignore_errors=True)
    return row


def report(rows, a, cmd, total):
    cols = ["D (mm)", "W ours (kg/s)", "W LIGGGHTS (kg/s)", "W Beverloo (kg/s)", "ours/Beverloo",
            "ours particle-steps/s", "LIGGGHTS particle-steps/s", "ratio ours/LIGGGHTS"]
    table = []
    for r in rows:
        po, pl = r["ours"]["ps"] / r["ours"]["wall"], r["lig"]["ps"] / r["lig"]["wall"]
        table.append([str(r["D"]), f"{r['ours_W']:.4g}", f"{r['lig_W']:.4g}", f"{r['W_B']:.4g}",
                      f"{r['ours_W'] / r['W_B']:.2f}", f"{po:.3g}", f"{pl:.3g}", f"**{po / pl:.2f}**"])
    law = {"scene": "the scene's (`rescaled`, our default)", "projected": "`projected` (LIGGGHTS's own)"}
    L = [f"```\n{cmd}\n```\n",
         f"Measured {time.strftime('%Y-%m-%d %H:%M')} on {machine()}, {total:.0f} s in all; one simulation at a "
         f"time, each on one core (ours `--threads 1`, LIGGGHTS one process). End time {a.end_time:g} s, time step "
         f"{a.dt:g} s (both codes), our tangential law {law[a.tangential]}; LIGGGHTS `gran model hertz tangential "
         f"history`, neighbour skin {LIGGGHTS_SKIN * 1e3:g} mm (ours: the scene's, `auto`).\n",
         md_table(cols, table), "",
         "Particle-steps: the sum over steps of the particles present (trapezoid rule over the output rows, "
         "both codes alike); time: our `done:` line's `wall` (the run; kernels loaded before it), LIGGGHTS's "
         "`Loop time`. W: least-squares slope of the mass out against time from 10 % out (at the latest half "
         "the run) to the end or 30 % remaining. W Beverloo: C = 0.58, k = 1.5, d = the mean diameter "
         f"({rows[0]['d_mean'] * 1e3:.4f} mm), Rose & Tanaka cone factor (tan 30 deg tan 45 deg)^-0.35 = "
         f"{(math.tan(math.radians(HALF_ANGLE)) * math.tan(math.radians(PHI_D))) ** -0.35:.3f}, rho_b measured in "
         "our run (below).\n",
         md_table(["D (mm)", "window ours (s)", "window LIGGGHTS (s)", "out at end ours / LIGGGHTS (%)",
                   "solid fraction (frames)", "rho_b (kg/m3)", "W Beverloo at 0.6 rho_p", "LIGGGHTS/Beverloo",
                   "ours/LIGGGHTS W", "wall ours / LIGGGHTS (s)", "particle-steps ours / LIGGGHTS"],
                  [[str(r["D"]),
                    f"{r['ours_win'][0]:.3f}-{r['ours_win'][1]:.3f} ({r['ours_nfit']} rows)"
                    + ("" if r["ours_reached"] else ", 10 % not reached: second half"),
                    f"{r['lig_win'][0]:.3f}-{r['lig_win'][1]:.3f} ({r['lig_nfit']} rows)"
                    + ("" if r["lig_reached"] else ", 10 % not reached: second half"),
                    f"{100 * r['ours']['out'][-1] / r['ours']['m0']:.1f} / {100 * r['lig']['out'][-1] / r['lig']['m0']:.1f}",
                    f"{r['phi']:.3f} ({r['frames']})", f"{r['rho_b']:.0f}", f"{r['W_B06']:.4g}",
                    f"{r['lig_W'] / r['W_B']:.2f}", f"{r['ours_W'] / r['lig_W']:.3f}",
                    f"{r['ours']['wall']:.1f} / {r['lig']['wall']:.1f}",
                    f"{r['ours']['ps']:.4g} / {r['lig']['ps']:.4g}"] for r in rows])]
    notes = []
    for r in rows:
        for key, name in (("ours", "ours"), ("lig", "LIGGGHTS")):
            if r[key + "_stall"] is not None:
                notes.append(f"D = {r['D']} mm, {name}: nothing left from t = {r[key + '_stall']:.3f} s to the end "
                             f"(jammed, or empty)")
            for n in r[key]["notes"]:
                notes.append(f"D = {r['D']} mm, {name}: {n}")
    if notes:
        L += ["", "Notes:", ""] + [f"* {n}" for n in notes]
    return "\n".join(L)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--widths", type=int, nargs="+", default=list(WIDTHS), choices=WIDTHS,
                    help="orifice diameters in mm (default 6 8 10)")
    ap.add_argument("--end-time", type=float, default=0.5, help="s (default 0.5)")
    ap.add_argument("--dt", type=float, default=5e-6,
                    help="time step of both codes, s (default 5e-6: the scene's 6e-6 does not divide its times)")
    ap.add_argument("--tangential", choices=("scene", "projected"), default="scene",
                    help="our tangential law: the scene's (default) or LIGGGHTS's own, projected")
    ap.add_argument("--repeat", type=int, default=1,
                    help="run both codes this many times, alternately, and time each by its fastest run "
                         "(the machine is shared: one run of either can be slowed by another's load; default 1)")
    ap.add_argument("--keep", metavar="DIR", help="keep each width's inputs and outputs in DIR/D<d>")
    a = ap.parse_args(argv)
    if not ensure_liggghts():
        print("LIGGGHTS is not installed and could not be installed (apt-get install liggghts needs root): "
              "skipped", file=sys.stderr)
        return 2
    cmd = " ".join(["python3", os.path.relpath(os.path.abspath(__file__), os.getcwd())] + (argv or sys.argv[1:]))
    t0 = time.perf_counter()
    rows = []
    with tempfile.TemporaryDirectory(prefix="hopper_discharge_") as tmp:
        for d in a.widths:
            rows.append(one_width(d, a, tmp, lambda s: print(s, flush=True)))
    print()
    print(report(rows, a, cmd, time.perf_counter() - t0))
    return 0


if __name__ == "__main__":
    sys.exit(main())
