"""The fluidization curve: the pressure drop of a settled bed as the gas is raised in steps through
minimum fluidization and lowered back (the classic experiment).

    python benchmarks/fluidization_curve.py [--up 0.25,0.5,...] [--down 1.6,...] [--step 0.4]
                                            [--average 0.4] [--n 680] [--cells 3e-3]
                                            [--method voronoi] [--figure docs/fluidization_curve.png]

The bed and the gas of benchmarks/ergun_column.py (its functions, imported): n glass beads of
1 mm (2500 kg/m3; 680: about 16 mm deep) settled on a distributor plate in a periodic 6 x 6 mm
column 36 mm high, meshed in one cell per layer of --cells height (a 1-D column), a viscous
dense gas (rho 10 kg/m3, nu 1.5e-4 m2/s), Gidaspow drag at the void fraction around each bead
(--method, coupling.toml drag_void_fraction), the beads free. The bed is one `coupling run`
as a user runs it, its inlet OpenFOAM's own time-varying condition (0/U: `uniformFixedValue`,
a table of the speeds), so the bed carries its whole history (positions, velocities, contact
springs) from step to step; the gas writes at the end of each step, and with it the run's
restart point (checkpoints/checkpoint_<step>.npz): the bed as it is at the end of the step.

The speeds (--up, then --down) are fractions of the bed's own Ergun estimate of U_mf: Ergun
over the settled bed's measured void fraction profile (ergun_column.measure: slabs of one
diameter, exact sphere-slab volumes; ergun_column.ergun_series: the slabs in series) equated
to its buoyant weight per area N V_p (rho_p - rho_g) g / A. Each step lasts --step seconds;
its pressure drop is coupling.csv's dp, less the gas hydrostatics, averaged over the last
--average of the step. Printed per step: U, the drop, its drift (the mean of the window's
second half less its first half, of the weight), Ergun over the profile measured from the
beads at the end of that step, the weight.

U_mf from the curve, for each branch: the intersection of its fixed-bed line (the measured
drops of its lowest speeds, fitted as c times Ergun over the branch's settled bed: the bed
before the flow on the way up, the bed left at the end on the way down) with its plateau (the
mean of the others); the split between the two is the one of least squares. Compared with the
bed's own Ergun estimate and with Wen & Yu (1966), Re_mf = sqrt(33.7^2 + 0.0408 Ar) - 33.7,
whose published scatter is about +-34 % (one standard deviation over their data). Hysteresis:
both branches' fixed-bed drops at the same speeds, and the settled bed before and after.
"""
from __future__ import annotations

import argparse
import json
import math
import sys
import time
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
ROOT = HERE.parent
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(HERE))

import coupled_drag as cd  # noqa: E402
import ergun_column as EC  # noqa: E402

DT_CFD = 1e-3          # the CFD (= coupling) step of ergun_column.write
WEN_YU_SCATTER = 0.34  # Wen & Yu (1966): standard deviation of their correlation over their data
PLATEAU = 0.02         # the plateau against the buoyant weight per area (issue 51)
SETTLED = 0.005        # a step whose drop still drifts by this much of the weight has not settled
UP = "0.25,0.5,0.75,0.9,1.1,1.3,1.6,2.0"
DOWN = "1.6,1.3,1.1,0.9,0.75,0.5,0.25"


def solve(f, lo=1e-6, hi=1.0):
    """The root of the increasing f between lo and hi (bisection to round-off)."""
    for _ in range(200):
        mid = 0.5 * (lo + hi)
        if f(mid) < 0:
            lo = mid
        else:
            hi = mid
    return 0.5 * (lo + hi)


def ergun_umf(eps_slabs, weight):
    """The bed's own Ergun estimate of U_mf: Ergun over its measured profile (the slabs in
    series) equated to its buoyant weight per area."""
    return solve(lambda u: EC.ergun_series(u, eps_slabs) - weight)


def stepped_inlet(case: Path, speeds, step):
    """0/U of the case: the inlet's superficial velocity speeds[k] from k step to (k+1) step
    (OpenFOAM's `uniformFixedValue` with a table; each change within one CFD step), the gas
    starting at the first speed; the gas writes (a restart point) at the end of every step."""
    from coupling import foam_case as fc
    from stability.coupled import _sub
    rows = []
    for k, u in enumerate(speeds):
        rows += [f"            ({k * step + (DT_CFD if k else 0.0)!r} (0 0 {u!r}))",
                 f"            ({(k + 1) * step!r} (0 0 {u!r}))"]
    u0 = f"uniform (0 0 {speeds[0]!r})"
    _sub(case / "0" / "U", r"inlet\s*\{[^}]*\}",
         "inlet\n    {\n        type uniformFixedValue;\n        uniformValue table\n        (\n"
         + "\n".join(rows) + f"\n        );\n        value {u0};\n    }}", count=1)
    _sub(case / "0" / "U", r"\ninternalField\s+[^;]+;", f"\ninternalField   {u0};", count=1)
    fc.set_entries(case / "system" / "controlDict", {"writeInterval": int(round(step / DT_CFD))})


def write(dest, x, dz, speeds, step, method, output_interval=2e-3):
    """The case (ergun_column.write, beads free) with the stepped inlet; coupling.csv every
    output_interval seconds."""
    case = EC.write(dest, x, dz, speeds[0], method, True, step * len(speeds))
    stepped_inlet(case, speeds, step)
    from stability.coupled import _sub
    _sub(case / "coupling.toml", r"\noutput_interval = [^\n]*", f"\noutput_interval = {output_interval!r}")
    return case


def step_rows(out, d, n, dz, speeds, step, average):
    """Per step: U, the drop averaged over the last ``average`` of the step, its rms and drift,
    the bed measured at the end of the step (from its restart point) and Ergun over it."""
    w = EC.buoyant_weight(n)
    k_step = int(round(step / DT_CFD))
    rows = []
    for k, u in enumerate(speeds):
        t1 = (k + 1) * step
        t0 = t1 - average * step
        dp, rms = EC.bed_drop(d, dz, t0 + 1e-9, t1)
        first, _ = EC.bed_drop(d, dz, t0 + 1e-9, 0.5 * (t0 + t1))
        second, _ = EC.bed_drop(d, dz, 0.5 * (t0 + t1) + 1e-9, t1)
        with np.load(out / "checkpoints" / f"checkpoint_{(k + 1) * k_step:08d}.npz") as z:
            order = np.argsort(z["state_id"])           # the beads in the order of their ids
            x = z["state_position"][order] - [0.0, 0.0, dz]   # the plate at z = 0, as ergun_column measures
            v = float(np.sqrt((z["state_velocity"] ** 2).sum(axis=1)).max())
        m = EC.measure(x, n)
        rows.append(dict(u=u, dp=dp, rms=rms, drift=(second - first) / w, ergun=EC.ergun_series(u, m["eps_slabs"]),
                         weight=w, bed=m, v_max=v, x=x))
    return rows


def intersection(u, dp, ergun):
    """U_mf of one branch: the fixed-bed line dp = c ergun(U) through its lowest speeds and the
    plateau (the mean of the others), split where least squares puts it (at least one point in
    each); returns dict(umf, c, plateau, n_fixed)."""
    order = np.argsort(u)
    u, dp = np.asarray(u, float)[order], np.asarray(dp, float)[order]
    e = np.array([ergun(v) for v in u])
    best = None
    for j in range(1, len(u)):
        c = float(dp[:j] @ e[:j] / (e[:j] @ e[:j]))
        p = float(dp[j:].mean())
        sse = float(((dp[:j] - c * e[:j]) ** 2).sum() + ((dp[j:] - p) ** 2).sum())
        if best is None or sse < best[0]:
            best = (sse, j, c, p)
    _, j, c, p = best
    return dict(umf=solve(lambda v: c * ergun(v) - p), c=c, plateau=p, n_fixed=j)


def curve(work, n=680, up=UP, down=DOWN, step=0.4, average=0.4, dz=3e-3, method="voronoi"):
    """Run the curve (one `coupling run`); returns dict of the steps (rows, with the branch of
    each), the two branches' U_mf, the references, the beds before and after, the run's speed."""
    from dem import outdir
    work = Path(work)
    x0 = EC.bed(n)
    m0 = EC.measure(x0, n)
    w = EC.buoyant_weight(n)
    u_ergun0 = ergun_umf(m0["eps_slabs"], w)
    f_up, f_down = [float(v) for v in up.split(",")], [float(v) for v in down.split(",")] if down else []
    speeds = [f * u_ergun0 for f in f_up + f_down]
    case, out = work / "case", work / "out"
    outdir.claim(case)
    outdir.claim(out)
    write(case, x0, dz, speeds, step, method)
    t0 = time.perf_counter()
    code, text, d = cd.run(case, out)
    wall = time.perf_counter() - t0
    if code != 0:
        raise RuntimeError(f"coupling run failed (exit {code}):\n{text[-3000:]}")
    return analyse(out, d, x0, n, f_up, f_down, u_ergun0, step, average, dz, method, wall)


def analyse(out, d, x0, n, f_up, f_down, u_ergun0, step, average, dz, method, wall):
    """The curve's figures from the run in ``out`` (its coupling.csv rows ``d``): see curve."""
    m0 = EC.measure(x0, n)
    w = EC.buoyant_weight(n)
    speeds = [f * u_ergun0 for f in f_up + f_down]
    rows = step_rows(out, d, n, dz, speeds, step, average)
    for k, r in enumerate(rows):
        r["branch"] = "up" if k < len(f_up) else "down"
        r["frac"] = (f_up + f_down)[k]
    timing = json.loads((out / "timings.json").read_text())
    res = dict(rows=rows, weight=w, bed_before=m0, u_ergun_before=u_ergun0, u_wen_yu=cd.minimum_fluidization(),
               wall=wall, loop=timing["loop"], particle_steps_per_s=timing["particle_steps_per_s"],
               particle_steps=timing["particles"] * timing["dem_steps"], method=method, dz=dz, n=n, step=step,
               average=average)
    # the bed left at the end, settled at the lowest speed of the way down
    res["bed_after"] = rows[-1]["bed"] if f_down else None
    res["u_ergun_after"] = ergun_umf(res["bed_after"]["eps_slabs"], w) if f_down else None
    for branch, bed in (("up", m0), ("down", res["bed_after"])):
        sel = [r for r in rows if r["branch"] == branch]
        # the way down ends at its lowest speed: its plateau is its fluidized speeds, and the top
        # of the way up (the last step of the way up is the first of the curve's plateau)
        if branch == "down":
            sel = sel + [rows[len(f_up) - 1]]
        if len(sel) < 2:
            continue
        fit = intersection([r["u"] for r in sel], [r["dp"] for r in sel],
                           lambda v, e=bed["eps_slabs"]: EC.ergun_series(v, e))
        res[f"fit_{branch}"] = fit
    return res


def fixed_points(res, branch):
    """The steps of a branch on its fixed-bed line (the least-squares split of the intersection)."""
    fit = res.get(f"fit_{branch}")
    if fit is None:
        return []
    sel = [r for r in res["rows"] if r["branch"] == branch]
    return sorted(sel, key=lambda r: r["u"])[:fit["n_fixed"]]


def plateau_points(res):
    """The steps of the curve's plateau: every step above the way up's fixed-bed points and
    above the way down's (the least-squares splits)."""
    fixed = {id(r) for b in ("up", "down") for r in fixed_points(res, b)}
    return [r for r in res["rows"] if id(r) not in fixed]


def report(res, log=print):
    w = res["weight"]
    b0, b1 = res["bed_before"], res["bed_after"]
    log(f"bed: {res['n']} beads of {cd.D_P * 1e3:g} mm, {res['dz'] * 1e3:g} mm cells, drag_void_fraction "
        f"{res['method']}; buoyant weight per area {w:.3f} Pa; steps of {res['step']:g} s, the drop averaged over "
        f"the last {100 * res['average']:g} %")
    log("| branch | U / U_mf(Ergun) | U [mm/s] | dp [Pa] | rms | drift / weight | Ergun over the profile [Pa] | "
        "dp / it - 1 | dp / weight - 1 | bed core eps | fastest bead [mm/s] |")
    log("|---|---|---|---|---|---|---|---|---|---|---|")
    for r in res["rows"]:
        log(f"| {r['branch']} | {r['frac']:g} | {r['u'] * 1e3:.3f} | {r['dp']:.2f} | {100 * r['rms']:.2g} % | "
            f"{100 * r['drift']:+.2f} % | {r['ergun']:.2f} | {100 * (r['dp'] / r['ergun'] - 1):+.2f} % | "
            f"{100 * (r['dp'] / w - 1):+.2f} % | {r['bed']['eps_core']:.4f} | {r['v_max'] * 1e3:.3g} |")
    plat = plateau_points(res)
    if plat:
        p = np.array([r["dp"] for r in plat])
        log(f"plateau ({len(plat)} steps): mean {p.mean():.2f} Pa, {100 * (p.mean() / w - 1):+.2f} % of the weight; "
            f"steps {100 * (p.min() / w - 1):+.2f} to {100 * (p.max() / w - 1):+.2f} %")
    for branch in ("up", "down"):
        fx = fixed_points(res, branch)
        if fx:
            e = np.array([r["dp"] / r["ergun"] - 1 for r in fx])
            moving = [f"{r['frac']:g}" for r in fx if abs(r["drift"]) >= SETTLED]
            log(f"fixed bed, way {branch} ({len(fx)} steps): dp against Ergun over the measured profile "
                f"{100 * e.min():+.2f} to {100 * e.max():+.2f} %"
                + (f"; not settled (drift {100 * SETTLED:g} % of the weight or more): {', '.join(moving)} U_mf"
                   if moving else ""))
    uwy = res["u_wen_yu"]
    log(f"U_mf: Wen & Yu (1966) {uwy * 1e3:.3f} mm/s (scatter +-{100 * WEN_YU_SCATTER:g} %); the bed's own Ergun "
        f"estimate: before {res['u_ergun_before'] * 1e3:.3f} mm/s"
        + (f", after {res['u_ergun_after'] * 1e3:.3f} mm/s" if b1 else ""))
    for branch, own in (("up", res["u_ergun_before"]), ("down", res["u_ergun_after"])):
        fit = res.get(f"fit_{branch}")
        if fit:
            log(f"U_mf from the curve, way {branch}: {fit['umf'] * 1e3:.3f} mm/s (fixed-bed line {fit['c']:.4f} x "
                f"Ergun, {fit['n_fixed']} steps; plateau {fit['plateau']:.2f} Pa): against the bed's own Ergun "
                f"{100 * (fit['umf'] / own - 1):+.2f} %, against Wen & Yu {100 * (fit['umf'] / uwy - 1):+.2f} %")
    if b1:
        log(f"settled bed before / after: core eps {b0['eps_core']:.4f} / {b1['eps_core']:.4f}, bulk height "
            f"{b0['height'] * 1e3:.2f} / {b1['height'] * 1e3:.2f} mm, top {b0['top'] * 1e3:.2f} / "
            f"{b1['top'] * 1e3:.2f} mm (eps {b0['eps_top']:.4f} / {b1['eps_top']:.4f})")
        ups = {round(r["frac"], 9): r for r in fixed_points(res, "up")}
        for r in fixed_points(res, "down"):
            q = ups.get(round(r["frac"], 9))
            if q:
                log(f"hysteresis at {r['frac']:g} U_mf: way down {r['dp']:.2f} Pa, way up {q['dp']:.2f} Pa "
                    f"({100 * (r['dp'] / q['dp'] - 1):+.2f} %)")
    log(f"run: {res['wall']:.1f} s for the whole `coupling run` (loop {res['loop']:.1f} s, "
        f"{res['particle_steps_per_s']:.3g} particle-steps/s over {res['particle_steps']:.3g} particle-steps)")


def plot(res, path):
    """dp against U, both branches, Ergun over the bed before and after, the weight (+-2 %), the
    U_mf of each branch, of the bed's own Ergun and of Wen & Yu (+-34 %); at the right, the
    transition enlarged."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    w, rows = res["weight"], res["rows"]
    fig, axes = plt.subplots(1, 2, figsize=(12, 5), gridspec_kw=dict(width_ratios=[3, 2]))
    umax = max(r["u"] for r in rows)
    uwy, uer = res["u_wen_yu"], res["u_ergun_before"]
    for i, ax in enumerate(axes):
        for branch, bed, col in (("up", res["bed_before"], "C0"), ("down", res["bed_after"], "C1")):
            sel = [r for r in rows if r["branch"] == branch]
            if not sel:
                continue
            uu = np.linspace(0, umax, 400)
            e = np.array([EC.ergun_series(v, bed["eps_slabs"]) for v in uu])
            keep = e < 1.3 * w
            ax.plot(uu[keep] * 1e3, e[keep], "--", color=col, lw=1,
                    label=f"Ergun over the bed {'before' if branch == 'up' else 'after'} (core eps {bed['eps_core']:.4f})")
            ax.plot([r["u"] * 1e3 for r in sel], [r["dp"] for r in sel], "o-" if branch == "up" else "s-",
                    color=col, mfc=col if branch == "up" else "white",
                    label="raised (way up)" if branch == "up" else "then lowered (way down)")
            fit = res.get(f"fit_{branch}")
            if fit:
                ax.axvline(fit["umf"] * 1e3, color=col, lw=0.8, ls=":")
                if i == 1:
                    ax.annotate(f"U_mf {branch}: {fit['umf'] * 1e3:.2f}", (fit["umf"] * 1e3, w * (0.86 if branch == "up" else 0.83)),
                                color=col, fontsize=8, ha="left", xytext=(3, 0), textcoords="offset points")
        ax.axhline(w, color="k", lw=1, label=f"buoyant weight per area {w:.1f} Pa")
        ax.axhspan(w * (1 - PLATEAU), w * (1 + PLATEAU), color="k", alpha=0.08, label="+-2 %")
        ax.axvspan(uwy * (1 - WEN_YU_SCATTER) * 1e3, uwy * (1 + WEN_YU_SCATTER) * 1e3, color="C2", alpha=0.07)
        ax.axvline(uwy * 1e3, color="C2", lw=1, label=f"Wen & Yu (1966) U_mf {uwy * 1e3:.2f} mm/s, +-34 % shaded")
        ax.axvline(uer * 1e3, color="C3", lw=1, label=f"the bed's own Ergun U_mf {uer * 1e3:.2f} mm/s")
        ax.set_xlabel("superficial gas velocity U (mm/s)")
        ax.set_ylabel("bed pressure drop (Pa)")
    axes[0].set_xlim(0, umax * 1e3 * 1.05)
    axes[0].set_ylim(0, 1.2 * w)
    axes[0].legend(fontsize=7, loc="lower right")
    axes[0].set_title(f"Fluidization curve: {res['n']} beads of 1 mm, {res['method']} drag void fraction, "
                      f"steps of {res['step']:g} s", fontsize=10)
    axes[1].set_xlim(0.7 * uer * 1e3, 1.4 * uer * 1e3)
    axes[1].set_ylim(0.75 * w, 1.05 * w)
    axes[1].set_title("the transition, enlarged", fontsize=10)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def _speeds(ap, name, text, falling):
    try:
        v = [float(s) for s in text.split(",")]
    except ValueError:
        ap.error(f"--{name}: comma-separated fractions of U_mf, got {text!r}")
    if not all(math.isfinite(f) and f > 0 for f in v):
        ap.error(f"--{name}: every fraction must be a finite number > 0, got {text!r}")
    if any((b >= a) if falling else (b <= a) for a, b in zip(v, v[1:])):
        ap.error(f"--{name}: the fractions must {'fall' if falling else 'rise'} from step to step, got {text!r}")
    return v


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--up", default=UP, help="speeds raised, fractions of the bed's own Ergun U_mf")
    ap.add_argument("--down", default=DOWN, help="then lowered (each below the last of --up); '' for none")
    ap.add_argument("--step", type=float, default=0.4, help="physical time of each speed (s), a multiple of 1 ms")
    ap.add_argument("--average", type=float, default=0.4, help="the part of each step the drop is averaged over")
    ap.add_argument("--n", type=int, default=680, help="beads")
    ap.add_argument("--cells", type=float, default=3e-3, help="cell layer height (m)")
    ap.add_argument("--method", default="voronoi", choices=["cell", "voronoi", "kernel"],
                    help="coupling.toml drag_void_fraction")
    ap.add_argument("--figure", default="", help="write the plot here (PNG), e.g. docs/fluidization_curve.png")
    ap.add_argument("--work", default=str(ROOT / "out" / "fluidization_curve"))
    a = ap.parse_args(argv)
    up = _speeds(ap, "up", a.up, False)
    if a.down:
        down = _speeds(ap, "down", a.down, True)
        if down[0] >= up[-1]:
            ap.error(f"--down: must start below the last speed of --up ({up[-1]:g}), got {a.down!r}")
    k = a.step / DT_CFD
    if not (math.isfinite(a.step) and a.step > 0 and abs(k - round(k)) < 1e-6 and round(k) >= 2):
        ap.error(f"--step: a multiple of the CFD step {DT_CFD:g} s, at least 2 of them, got {a.step!r}")
    if not 0 < a.average <= 1:
        ap.error(f"--average: a part of the step, in (0, 1], got {a.average!r}")
    if a.n < 10:
        ap.error(f"--n: at least 10 beads, got {a.n}")
    if not (math.isfinite(a.cells) and 0 < a.cells <= EC.H_COL / 4):
        ap.error(f"--cells: a cell height in (0, {EC.H_COL / 4:g}] m, got {a.cells!r}")
    from dem import outdir
    work = Path(a.work)
    outdir.claim_folder(work, overwrite=True, command="benchmarks/fluidization_curve.py", what="work folder")
    res = curve(work, n=a.n, up=a.up, down=a.down, step=a.step, average=a.average, dz=a.cells, method=a.method)
    report(res)
    if a.figure:
        plot(res, a.figure)
        print(f"figure: {a.figure}")
    return res


if __name__ == "__main__":
    main()
