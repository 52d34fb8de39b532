"""Pressure drop of a settled bed at its porosity jumps: in-bed gradient, bed-top loss, averaging.

    python benchmarks/bed_surface.py [--layers 1e-3,3e-3] [--end 0.05] [--n 600]

The settled bed of benchmarks/coupled_drag.py (600 glass beads of 1 mm, periodic 6 x 6 mm
column, Gidaspow drag, dense viscous gas rho 10 kg/m3, nu 1.5e-4 m2/s, half the minimum
fluidization velocity) held still (`mechanics = false`) and meshed with one cell per layer
(--columns 1) of each --layers height, run with `coupling run` as a user runs it until the gas is steady. The script
reads the last gas time and separates what the pressure drop is made of:

* **solver**: p(bottom cell) - p(top cell) minus the gas hydrostatics;
* **sent**: the exact 1-D answer to the solver's input, the integral of Ksl u_s/eps^2 over the
  layers with the Ksl and eps the DEM sent: solver / sent - 1 is the gas solver's own error, and
  the layer-by-layer difference shows where it sits (bed top, floor);
* **cells**: the drag law (the case's Gidaspow) evaluated at each layer's void fraction, as the
  gas sees it, with the exact superficial velocity, integrated over the same span (it differs
  from "sent" where a cell's drag, summed over the beads whose centres it holds, and its void
  fraction, shared out by the `divided` model, disagree);
* **bulk**: Ergun at the bed's mean void fraction (from its height) times its height: what the
  cell averaging of the loose floor layer and the rough top loses against a uniform bed;
* **in-bed gradient**: the pressure difference between two cells 3 d_p apart in the bed,
  against the drag law at their mean void fraction.

--verbose adds each layer's void fraction, its gas velocity against u_s/eps, the drag's
resistance against the gas's own (|U|/d + nu/d^2: the velocity is the drag law's where the drag
dominates), and the viscous
stress of the inlet cell (the gas enters at u_s and moves at u_s/eps inside it), which slows
that cell's gas by the fraction printed.
"""
from __future__ import annotations

import argparse
import math
import sys
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
ROOT = HERE.parent
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(HERE))

import coupled_drag as cd  # noqa: E402


def layer_gradient(eps, u_s):
    """Pressure gradient (Pa/m) the case's drag law (Gidaspow 1994, model A) needs at void
    fraction eps for superficial velocity u_s through beads held still: Ksl u_s / eps^2 with
    Ksl = (1 - eps)/V_p beta(d_p, eps, |u_s/eps|)."""
    from coupling.drag import drag_coefficient, drag_model_id
    mid = drag_model_id("gidaspow_1994")
    vp = math.pi / 6 * cd.D_P ** 3
    out = np.zeros(len(eps))
    for i, e in enumerate(eps):
        if e < 1.0:
            beta = drag_coefficient(mid, cd.D_P, float(e), cd.RHO_G, cd.RHO_G * cd.NU_G, u_s / e)
            out[i] = (1 - e) / vp * beta * u_s / e ** 2
    return out


def last_time(out: Path) -> str:
    times = [d.name for d in out.iterdir() if d.is_dir() and _is_number(d.name) and float(d.name) > 0]
    return max(times, key=float)


def _is_number(s):
    try:
        float(s)
        return True
    except ValueError:
        return False


def analyse(out: Path, u_s: float, bed_top: float, eps_bulk: float, floor: float):
    """The decomposition of the docstring from the last gas time of run folder ``out``."""
    from coupling import foam_case as fc
    C = fc.read_cell_centres(out)
    n = len(C)
    t = last_time(out)
    rd = lambda name: fc.read_internal_field(out / t / name, n)  # noqa: E731
    p, U, eps, ksl = rd("p") * cd.RHO_G, rd("U"), rd("eps"), rd("Ksl")
    z = np.round(C[:, 2], 9)
    levels = np.unique(z)
    lay = [np.flatnonzero(z == lv) for lv in levels]
    mean = lambda a: np.array([a[i].mean() for i in lay])  # noqa: E731
    pl, el, ul, kl = mean(p), mean(eps), mean(U[:, 2]), mean(ksl)
    dz = levels[1] - levels[0]
    hyd = cd.RHO_G * 9.81
    dp_solver = pl[0] - pl[-1] - hyd * (levels[-1] - levels[0])
    G = layer_gradient(el, u_s)
    w = np.full(len(levels), dz)
    w[0] = w[-1] = 0.5 * dz
    dp_cells = float((G * w).sum())
    # the same with the drag coefficient the DEM sent (Ksl u_s/eps^2): the exact answer to the
    # solver's own input, so that solver / sent - 1 is the gas solver's error alone
    Gs = kl * u_s / el ** 2
    dp_sent = float((Gs * w).sum())
    # Ergun over the bed as a uniform bed: from the bottom cell centre (or the floor above it)
    # to the bed top
    dp_bulk = cd.ergun_gradient(u_s, eps_bulk) * (bed_top - max(levels[0], floor))
    # in-bed gradient: two layers 3 d_p apart around the middle of the bed
    k = max(1, int(round(3 * cd.D_P / dz)))
    mid = int(np.searchsorted(levels, 0.5 * (floor + bed_top))) - k // 2
    i0, i1 = max(mid, 1), max(mid, 1) + k
    grad = (pl[i0] - pl[i1]) / (levels[i1] - levels[i0]) - hyd
    wt = np.ones(i1 - i0 + 1)
    wt[0] = wt[-1] = 0.5
    grad_ref = float((G[i0:i1 + 1] * wt).sum() / (i1 - i0))
    # layer-pair pressure differences against the exact ones: where the solver's error sits
    pair = (pl[:-1] - pl[1:] - hyd * dz) - 0.5 * (Gs[:-1] + Gs[1:]) * dz
    top_layer = int(np.searchsorted(levels, bed_top))
    # the viscous stress of the volume-averaged momentum equation, div(eps nu grad U), on the
    # inlet cell: the gas enters at u_s with eps = 1 (free gas below the distributor) and moves
    # at u_s/eps inside the cell, a jump over half a cell that slows the cell's gas by this
    # fraction of its drag K u_s/eps (the Brinkman term: part of the equations the solver
    # solves, left out of the 1-D answer u_s/eps; the next face weighted by eps_f as the
    # solver's laplacian(eps nu, U))
    ef = 0.5 * (el[0] + el[1])
    lap = cd.NU_G * (ef * (ul[1] - ul[0]) / dz - 1.0 * (ul[0] - u_s) / (0.5 * dz)) / dz
    inlet_viscous = float(lap / (kl[0] / cd.RHO_G * u_s / el[0]))
    # the drag's resistance per unit superficial velocity, R = K/eps^2 (model A), against the
    # gas's own, |U|/d + nu/d^2 (dragFaces.H): a cell's velocity is the drag law's u_s/eps
    # where R dominates; in the bed's fringe above the top (a few bead caps, eps 0.98-0.99,
    # R about the gas's own) it is set by the gas leaving the bed as much as by its drag
    drag_ratio = (kl / cd.RHO_G / el ** 2) / (np.abs(ul) / dz + cd.NU_G / dz ** 2)
    return dict(time=float(t), dz=dz, dp_solver=dp_solver, dp_cells=dp_cells, dp_sent=dp_sent, dp_bulk=dp_bulk,
                inlet_viscous=inlet_viscous, grad=grad, grad_ref=grad_ref, taps=(levels[i0], levels[i1]), pair=pair, eps=el,
                u_ratio=ul * el / u_s, drag_ratio=drag_ratio, top_layer=top_layer, levels=levels)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--layers", default="1e-3,3e-3", help="cell layer heights (m), comma separated")
    ap.add_argument("--end", type=float, default=0.05, help="physical time of each run (s)")
    ap.add_argument("--step", type=float, default=1e-3, help="CFD step (s)")
    ap.add_argument("--n", type=int, default=600)
    ap.add_argument("--columns", type=int, default=1,
                    help="cells across the column (1: one cell per layer, a 1-D bed whose drag-law "
                         "reference is exact)")
    ap.add_argument("--work", default=str(ROOT / "out" / "bed_surface"))
    ap.add_argument("--verbose", action="store_true", help="print the layer-by-layer table")
    ap.add_argument("--drag-void-fraction", default=None, choices=["cell", "voronoi", "kernel"])
    a = ap.parse_args(argv)
    from dem import outdir
    from stability.coupled import write_case
    work = Path(a.work)
    outdir.claim_folder(work, overwrite=True, command="benchmarks/bed_surface.py", what="work folder")
    x = cd.settled_bed(a.n)
    eps_bulk, top = cd.bed_void_fraction(x, a.n)
    top += cd.FLOOR
    u = 0.5 * cd.minimum_fluidization(eps_bulk)
    print(f"bed: {a.n} beads of {cd.D_P * 1e3:g} mm held still, top {top * 1e3:.2f} mm (floor "
          f"{cd.FLOOR * 1e3:g} mm), mean void fraction {eps_bulk:.3f}; inlet {u * 1e3:.3f} mm/s superficial "
          f"(half U_mf)")
    print("| layers (mm) | solver dp (Pa) | exact for the Ksl sent (Pa) | solver error | drag law at the cells' eps "
          "(Pa) | solver / law - 1 | Ergun at mean eps (Pa) | law at cells / Ergun at mean - 1 | in-bed gradient "
          "(Pa/m) | drag law there | error |")
    print("|---|---|---|---|---|---|---|---|---|---|---|")
    rows = []
    dt_dem = 1e-5
    for h in [float(v) for v in a.layers.split(",")]:
        nz = int(round(cd.H / h))
        nxy = a.columns
        case, out = work / f"case_{h:g}", work / f"out_{h:g}"
        outdir.claim(case)
        outdir.claim(out)
        k = int(round(a.step / dt_dem))
        write_case(case, L=cd.L, H=cd.H, nxy=nxy, nz=nz, positions=x + [0.0, 0.0, cd.FLOOR], floor=cd.FLOOR,
                   diameter=cd.D_P, density=cd.RHO_P, dt_dem=dt_dem, interval=k,
                   n_steps=int(round(a.end / (k * dt_dem))), u_in=u, void_fraction="divided", eps_min=0.3,
                   heat=False, rho_g=cd.RHO_G, nu_g=cd.NU_G, friction=0.5, restitution=0.3, walls_top=False,
                   drag="gidaspow_1994", mechanics=False, drag_void_fraction=a.drag_void_fraction)
        code, text, d = cd.run(case, out)
        if code != 0:
            print(f"| {h * 1e3:g} | run failed (exit {code}) |")
            print(text[-2000:])
            continue
        r = analyse(out, u, top, eps_bulk, cd.FLOOR)
        r["layer"] = h
        rows.append(r)
        print(f"| {h * 1e3:g} | {r['dp_solver']:.3f} | {r['dp_sent']:.3f} | "
              f"{100 * (r['dp_solver'] / r['dp_sent'] - 1):+.2f} % | {r['dp_cells']:.3f} | "
              f"{100 * (r['dp_solver'] / r['dp_cells'] - 1):+.2f} % | {r['dp_bulk']:.3f} | "
              f"{100 * (r['dp_cells'] / r['dp_bulk'] - 1):+.1f} % | {r['grad']:.1f} | {r['grad_ref']:.1f} | "
              f"{100 * (r['grad'] / r['grad_ref'] - 1):+.2f} % |", flush=True)
        if a.verbose:
            for i, lv in enumerate(r["levels"][:-1]):
                print(f"    z {lv * 1e3:6.2f} mm  eps {r['eps'][i]:.3f}  U eps/u_s {r['u_ratio'][i]:.4f}  "
                      f"drag / gas resistance {r['drag_ratio'][i]:8.3g}  dp to next layer - exact {r['pair'][i]:+.3f} Pa")
            print(f"    inlet cell: viscous stress against the inlet's free gas {100 * r['inlet_viscous']:+.2f} % "
                  f"of its drag (U eps/u_s - 1 = {100 * (r['u_ratio'][0] - 1):+.2f} %)")
    return rows


if __name__ == "__main__":
    main()
