"""Settled Ergun bed against the CFD step: is the coupled scheme stable and steady?

    python benchmarks/coupled_drag.py [--steps 0.25e-3,1e-3,2e-3] [--end 0.1] [--n 600]

A bed of n glass beads of 1 mm (2500 kg/m3) settled on the distributor of a periodic 6 x 6 mm
column, 30 mm high, 3 mm cells (void_fraction "divided", Di Felice drag), a viscous dense gas
(rho 10 kg/m3, nu 1.5e-4 m2/s: the particle drag relaxation time m/beta is a few ms) blown
upward at half the minimum fluidization velocity (Wen & Yu 1966). The same case runs with the
CFD step (= coupling step) of each --steps value through `coupling run` (the checks and
messages a user sees), and the script prints, per step: the check's verdict, the coupling
step over the particle relaxation time, and the pressure drop over the second half of the run
(mean, largest relative departure from the mean, the Ergun value at the bed's mean void
fraction), and the largest particle speed.

A bed at rest under a steady flow must keep a steady pressure drop whatever the step; with the
drag held fixed over a coupling step (explicit), it oscillated at 1 ms and blew apart at 2 ms.
"""
from __future__ import annotations

import argparse
import math
import os
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
ROOT = HERE.parent
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(HERE))

D_P = 1e-3            # bead diameter (m)
RHO_P = 2500.0
RHO_G, NU_G = 10.0, 1.5e-4
L = 6e-3              # column width (periodic)
H = 0.03              # column height
NXY, NZ = 2, 10       # 3 mm cells
FLOOR = 0.25e-3       # the distributor plate of the DEM 0.25 mm above the gas inlet: no bead's volume
# (satellite points of the "divided" void fraction) touches the inlet face, where a bead resting on
# the plate would move volume in and out of the mesh as it jitters by nanometres


def minimum_fluidization(eps=0.4):
    """Wen & Yu (1966) minimum fluidization velocity (superficial, m/s)."""
    mu = RHO_G * NU_G
    ar = RHO_G * (RHO_P - RHO_G) * 9.81 * D_P ** 3 / mu ** 2
    re = math.sqrt(33.7 ** 2 + 0.0408 * ar) - 33.7
    return re * mu / (RHO_G * D_P)


def ergun_gradient(u, eps):
    """Ergun (1952) pressure gradient (Pa/m) at superficial velocity u and void fraction eps."""
    mu = RHO_G * NU_G
    return 150 * mu * (1 - eps) ** 2 * u / (eps ** 3 * D_P ** 2) + 1.75 * RHO_G * (1 - eps) * u * u / (eps ** 3 * D_P)


V_REST = 1e-4   # m/s: "at rest" (a bead at 0.1 mm/s would take 10 s to cross its diameter)
T_SETTLE_MAX = 1.0   # s: the longest settling of settled_bed
# A bed whose last moving beads no longer speed up or slow down (no bead's speed changed by
# more than V_STEADY over 0.05 s, none faster than 10 V_REST) is done settling too: what moves
# is a bead rolling on the floor or spinning about the vertical in its cage, which Hertz-Mindlin
# without rolling or twisting resistance keeps doing (seed 4 of 600 beads, steady by 0.65 s:
# one bead rolling on the floor at 0.16 mm/s, 1.8 um from its neighbours, until it met one at
# about 1.05 s; another spinning at 5.6 rad/s about the vertical, moving at 0.105 mm/s,
# unchanged from 0.8 to 2.4 s). Such a bed stopped with an error before.
V_STEADY = 1e-6


def settled(speed, before):
    """Whether a settling bed is done: no bead faster than V_REST, or (``before``: each bead's
    speed 0.05 s earlier, None at the first check) none faster than 10 V_REST and none whose
    speed changed by V_STEADY or more (a steady roll or spin, not settling)."""
    vmax = float(speed.max())
    if vmax < V_REST:
        return True
    return before is not None and vmax < 10 * V_REST and float(np.abs(speed - before).max()) < V_STEADY


def settled_bed(n=600, seed=3, log=print):
    """n beads poured into the periodic column and settled on a floor until at rest: at least
    0.25 s, then in steps of 0.05 s until no bead moves faster than V_REST, or the last moving
    beads move steadily (V_STEADY: rolling or spinning, not settling) (at most T_SETTLE_MAX;
    DEM only, cached in out/bench_cache, keyed on the sources: accuracy.common.cache_path). Returns the positions.

    A fixed 0.25 s was not enough for every packing: the last beads still rolled into place at
    25-58 mm/s there, and whether they were done depended on the realization (the seed, or the
    rounding of the contact law), which a bed meant to be at rest must not."""
    from benchmarks.accuracy.common import cache_path, claim
    path = cache_path(f"settled_bed_{n}_{seed}")
    if os.path.exists(path):
        return np.load(path)["x"]
    from dem import Simulation
    t0 = time.perf_counter()
    r = D_P / 2
    sc = {"simulation": {"time_step": 5e-6, "end_time": T_SETTLE_MAX, "gravity": [0, 0, -9.81], "seed": seed},
          "domain": {"min": [0, 0, 0], "max": [L, L, 0.1], "periodic": [True, True, False]},
          "materials": [dict(name="glass", density=RHO_P, youngs_modulus=1e7, poisson_ratio=0.25,
                             restitution=0.3, friction=0.5)],
          "particles": [{"material": "glass", "count": n, "radius": r,
                         "region": {"type": "box", "min": [0, 0, r], "max": [L, L, 0.1 - r]}}],
          "walls": [{"type": "plane", "point": [0, 0, 0], "normal": [0, 0, 1], "material": "glass"}]}
    sim = Simulation.from_dict(sc)
    t_end = 0.25
    before = None
    while True:
        sim.run(end_time=t_end, progress=False)
        st = sim.state
        by_id = np.argsort(st.id[:st.n_owned])      # the same bead in the same row at each check
        speed = np.sqrt((st.velocity[:st.n_owned][by_id] ** 2).sum(axis=1))
        vmax = float(speed.max())
        done = settled(speed, before)
        if done or t_end >= T_SETTLE_MAX - 1e-9:
            break
        before = speed
        t_end += 0.05
    if not done:
        raise RuntimeError(f"the bed of {n} beads (seed {seed}) is not at rest after {T_SETTLE_MAX:g} s: "
                           f"a bead at {vmax:.3g} m/s")
    x = sim.state.position[:sim.state.n_owned].copy()
    claim(path)
    np.savez(path, x=x)
    how = "at rest" if vmax < V_REST else f"steady (its fastest bead rolls or spins at {vmax:.2g} m/s)"
    log(f"  settled bed of {n} beads: {how} after {t_end:.2f} s, {time.perf_counter() - t0:.1f} s "
        f"(cached in {path})")
    return x


def write(dest: Path, x, dt_cfd: float, end: float, u_in: float, dt_dem: float = 1e-5,
          drag_integration: str | None = None, mechanics: bool = True) -> Path:
    """The coupled case at CFD step dt_cfd (benchmarks.stability.coupled.write_case)."""
    from stability.coupled import write_case
    k = int(round(dt_cfd / dt_dem))
    return write_case(dest, L=L, H=H, nxy=NXY, nz=NZ, positions=x + [0.0, 0.0, FLOOR], floor=FLOOR, diameter=D_P, density=RHO_P,
                      dt_dem=dt_dem, interval=k, n_steps=int(round(end / (k * dt_dem))), u_in=u_in,
                      void_fraction="divided", eps_min=0.3, heat=False, rho_g=RHO_G, nu_g=NU_G,
                      friction=0.5, restitution=0.3, walls_top=False, drag="gidaspow_1994",
                      drag_integration=drag_integration, mechanics=mechanics)


def terminal_velocity(d, rho_p, eps=1.0, drag="di_felice_1994"):
    """Settling velocity of one sphere in still gas (RHO_G, NU_G) by the drag law of the case:
    beta(v) v = (rho_p - rho_g) V_p g (drag coefficients of coupling.drag, model A with the
    hydrostatic pressure gradient: buoyancy), by bisection to round-off."""
    from coupling.drag import drag_coefficient, drag_model_id
    mid = drag_model_id(drag)
    mu = RHO_G * NU_G
    w = (rho_p - RHO_G) * math.pi / 6 * d ** 3 * 9.81
    lo, hi = 0.0, 100.0
    for _ in range(200):
        v = 0.5 * (lo + hi)
        if drag_coefficient(mid, d, eps, RHO_G, mu, v) * v < w:
            lo = v
        else:
            hi = v
    return 0.5 * (lo + hi)


def single_particle(dest: Path, d: float, steps_per_tau: float, n_steps: int, dt_dem: float = 5e-7,
                    cell: float = 0.01) -> tuple[Path, float, float]:
    """One bead of diameter d (2500 kg/m3) falling from rest in the still gas of a column of one
    cell per layer (cell x cell x 3 cells, slip sides: the gas of a layer cannot move
    vertically, the inlet being closed), at a CFD step of steps_per_tau particle relaxation
    times m/beta (beta of the drag law at the terminal velocity). Returns (case, CFD step,
    relaxation time)."""
    from stability.coupled import write_case
    from coupling.drag import drag_coefficient, drag_model_id
    vt = terminal_velocity(d, RHO_P)
    tau = RHO_P * math.pi / 6 * d ** 3 / drag_coefficient(drag_model_id("di_felice_1994"), d, 1.0, RHO_G,
                                                           RHO_G * NU_G, vt)
    k = max(1, int(round(steps_per_tau * tau / dt_dem)))
    x = np.array([[cell / 2, cell / 2, 2.2 * cell]])
    case = write_case(dest, L=cell, H=3 * cell, nxy=1, nz=3, positions=x, diameter=d, density=RHO_P,
                      dt_dem=dt_dem, interval=k, n_steps=n_steps, u_in=0.0, void_fraction="divided",
                      eps_min=0.3, heat=False, rho_g=RHO_G, nu_g=NU_G, walls_top=False)
    return case, k * dt_dem, tau


def run(case: Path, out: Path):
    """`coupling run` as a user runs it; returns (exit status, output text, coupling.csv or None)."""
    env = dict(os.environ, PYTHONPATH=str(ROOT) + os.pathsep + os.environ.get("PYTHONPATH", ""))
    p = subprocess.run([sys.executable, "-m", "coupling.run", "run", str(case), "--out", str(out), "--overwrite"], capture_output=True, text=True, env=env, cwd=str(ROOT))
    csv = out / "coupling.csv"
    d = np.atleast_1d(np.genfromtxt(csv, delimiter=",", names=True)) if csv.exists() else None
    return p.returncode, p.stdout + p.stderr, d


def bed_void_fraction(x, n):
    """Mean void fraction of the bed below its top (mean height of the top 10 % of beads + r)."""
    z = np.sort(x[:, 2])
    top = float(z[-max(n // 10, 1):].mean()) + D_P / 2
    return 1.0 - n * math.pi / 6 * D_P ** 3 / (L * L * top), top


def summarize(d, t_from):
    sel = d["time"] >= t_from
    dp = d["dp"][sel]
    mean = float(dp.mean())
    dev = float(np.abs(dp - mean).max() / abs(mean))
    return mean, dev, float(d["v_max"][sel].max())


def spread(d, t_from, window=5e-3):
    """(rms departure of dp from its mean, largest departure of a window mean) after t_from,
    relative to the mean: the per-step noise of a bed whose particles jitter, and the slow
    oscillation or drift an unstable coupling shows."""
    sel = d["time"] >= t_from
    t, dp = d["time"][sel], d["dp"][sel]
    mean = float(dp.mean())
    rms = float(np.sqrt(((dp - mean) ** 2).mean()) / abs(mean))
    k = np.floor((t - t[0]) / window + 1e-9).astype(int)
    means = [dp[k == j].mean() for j in np.unique(k) if (k == j).sum() * (t[1] - t[0]) >= 0.999 * window]
    return rms, float(np.max(np.abs(np.array(means) - mean)) / abs(mean)) if means else float("nan")


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--steps", default="0.25e-3,1e-3,2e-3", help="CFD steps (s), comma separated")
    ap.add_argument("--end", type=float, default=0.1, help="physical time of each run (s)")
    ap.add_argument("--n", type=int, default=600)
    ap.add_argument("--work", default=str(ROOT / "out" / "coupled_drag"))
    ap.add_argument("--drag-integration", default=None, choices=["implicit_bed", "implicit_particle", "explicit"],
                    help="coupling.toml drag_integration (default: the coupling's default, implicit_bed)")
    a = ap.parse_args(argv)
    from dem import outdir
    work = Path(a.work)
    outdir.claim_folder(work, overwrite=True, command="benchmarks/coupled_drag.py", what="work folder")
    x = settled_bed(a.n)
    eps, top = bed_void_fraction(x, a.n)
    umf = minimum_fluidization(eps)
    u = 0.5 * umf
    mu = RHO_G * NU_G
    print(f"bed: {a.n} beads of {D_P * 1e3:g} mm, height {top * 1e3:.2f} mm, void fraction {eps:.3f}; "
          f"U_mf (Wen-Yu) {umf * 1e3:.3f} mm/s, inlet {u * 1e3:.3f} mm/s superficial")
    print(f"Ergun pressure drop of the bed {ergun_gradient(u, eps) * top:.3f} Pa (+ gas hydrostatics "
          f"{RHO_G * 9.81 * H:.3f} Pa over the column)")
    print("| CFD step (ms) | check | step / (m/beta) | step / (m/beta_imp) | dp mean (Pa) | rms | largest "
          "departure | 5 ms means | v_max (m/s) | exit |")
    print("|---|---|---|---|---|---|---|---|---|---|")
    rows = []
    for s in [float(v) for v in a.steps.split(",")]:
        outdir.claim(work / f"case_{s:g}")
        outdir.claim(work / f"out_{s:g}")
        case = write(work / f"case_{s:g}", x, s, a.end, u, drag_integration=a.drag_integration)
        t0 = time.perf_counter()
        code, text, d = run(case, work / f"out_{s:g}")
        import re
        m = re.search(r"coupling_over_relaxation\s+([0-9.eE+-]+)", text)
        ratio = float(m.group(1)) if m else float("nan")
        m = re.search(r"coupling_over_bed_relaxation\s+([0-9.eE+-]+)", text)
        ratio_bed = float(m.group(1)) if m else float("nan")
        verdict = "refused" if "refused" in text else ("warns" if "WARNING" in text else "ok")
        if d is not None and d.size > 4 and code == 0:
            mean, dev, vmax = summarize(d, a.end / 2)
            rms, win = spread(d, a.end / 2)
        else:
            mean = dev = vmax = rms = win = float("nan")
        rows.append(dict(step=s, verdict=verdict, ratio=ratio, ratio_bed=ratio_bed, dp=mean, dev=dev, rms=rms,
                         win=win, vmax=vmax, code=code,
                         seconds=time.perf_counter() - t0, text=text))
        print(f"| {s * 1e3:g} | {verdict} | {ratio:.3g} | {ratio_bed:.3g} | {mean:.4g} | {100 * rms:.2g} % | "
              f"{100 * dev:.3g} % | {100 * win:.2g} % | {vmax:.3g} | {code} |", flush=True)
        if code not in (0, 2):
            print(text[-2000:])
    return rows


if __name__ == "__main__":
    main()
