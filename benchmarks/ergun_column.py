"""Ergun through a settled column, ends included, by cell size and drag void fraction method.

    python benchmarks/ergun_column.py [--cells 1e-3,2e-3,3e-3,4e-3] [--methods cell,voronoi,kernel]
                                      [--speeds 0.2,0.45,0.7] [--fluidized 1.5,2.0] [--n 680]
    python benchmarks/ergun_column.py --seeds 3-10 [--cells 1e-3,3e-3] [--methods voronoi]

A settled bed of n glass beads of 1 mm (2500 kg/m3; 680: about 16 mm deep) in a periodic
6 x 6 mm column 36 mm high, meshed with one cell per layer of each --cells height (a 1-D
column), in a viscous dense gas (rho 10 kg/m3, nu 1.5e-4 m2/s, Gidaspow drag). The bed rests
on a distributor plate at the top face of the bottom cell, so the bottom cell holds gas only
and p(bottom cell) - p(top cell), less the gas hydrostatics between their centres, is the
whole bed's pressure drop. Every run goes through `coupling run` as a user runs it.

* **Held bed** (`mechanics = false`), inlet at each --speeds fraction of U_mf (Wen & Yu at
  the bed's void fraction), 50 CFD steps of 1 ms (steady): the pressure drop against Ergun
  at the bed's measured void fraction. How the bed is measured: its void fraction profile in
  slabs of one diameter from the plate up (exact sphere-slab volumes, as a tomography scan
  gives it; the floor slab 0.45, the core 0.38-0.42, the last slabs the rough top), and
  Ergun over it as layers in series, each slab's Ergun drop at its void fraction over one
  diameter: the bed's ends are in the reference with the packing they have. Also printed:
  Ergun at the core's packing (2 d from either end) times the height of a uniform bed of that
  packing holding all the beads (the mass over the bulk density), which counts the looser
  ends as core packing; and the in-bed gradient between the two cell centres farthest apart
  in the core against Ergun at the core's packing between them.
* **Fluidized** (`--fluidized`, fractions of U_mf, beads free): the pressure drop averaged
  over the second half of --fluid-end seconds against the bed's buoyant weight per area,
  N V_p (rho_p - rho_g) g / A.
* **Packings** (`--seeds a-b`): the held bed at 0.45 U_mf on the packing of each seed (the same
  pour, another realization), each against Ergun over its own profile, with the mean and the
  standard deviation over the packings: how much of a method's departure is the packing's.
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

H_COL = 0.036          # column height: 36, 18, 12, 9 cells of 1, 2, 3, 4 mm
DT_DEM = 1e-5


def slab_solid_fraction(x, r, z0, z1, area):
    """Solid fraction of the slab z0 < z < z1 (exact volumes of the spheres' slices)."""
    zc = x[:, 2]
    a = np.maximum(z0, zc - r)
    b = np.minimum(z1, zc + r)
    ok = b > a
    f = lambda t: math.pi * (r * r * (t - zc[ok]) - (t - zc[ok]) ** 3 / 3.0)  # noqa: E731
    return float((f(b[ok]) - f(a[ok])).sum() / (area * (z1 - z0)))


def profile(x, plate=0.0):
    """The bed's void fraction in slabs of one diameter from the plate up to the last slab
    holding solid (exact sphere-slab volumes, a tomography profile): (slab bottoms, eps)."""
    r = cd.D_P / 2
    area = cd.L * cd.L
    z0 = np.arange(plate, float(x[:, 2].max()) + r, cd.D_P)
    return z0, np.array([1.0 - slab_solid_fraction(x, r, z, z + cd.D_P, area) for z in z0])


def ergun_series(u, eps):
    """Ergun over a layered bed: the sum of each slab's drop, Ergun at its void fraction over
    one diameter (the layers are in series: the same superficial velocity crosses each)."""
    return float(sum(cd.ergun_gradient(u, e) * cd.D_P for e in eps if e < 1.0))


def measure(x, n, plate=0.0):
    """The bed as measured (see the module docstring): dict of top, core, eps_core, height,
    eps_top (the void fraction with the top's height), eps_slabs (the profile)."""
    r = cd.D_P / 2
    area = cd.L * cd.L
    z = np.sort(x[:, 2])
    top = float(z[-max(n // 10, 1):].mean()) + r
    z0, z1 = plate + 2 * cd.D_P, top - 2 * cd.D_P
    phi = slab_solid_fraction(x, r, z0, z1, area)
    vp = math.pi / 6 * cd.D_P ** 3
    height = n * vp / (area * phi)
    return dict(top=top - plate, core=(z0 - plate, z1 - plate), eps_core=1.0 - phi, height=height,
                eps_top=1.0 - n * vp / (area * (top - plate)), eps_slabs=profile(x, plate)[1])


def bed(n):
    """The settled bed (benchmarks/coupled_drag.settled_bed: on a plate at z = 0)."""
    return cd.settled_bed(n)


AVERAGING = None       # drag_averaging_length of the runs (None: the method's default; --averaging)


def write(dest, x, dz, u, method, mechanics, end, dt_cfd=1e-3, columns=1):
    from stability.coupled import write_case
    k = int(round(dt_cfd / DT_DEM))
    nz = int(round(H_COL / dz))
    return write_case(dest, L=cd.L, H=H_COL, nxy=columns, nz=nz, positions=x + [0.0, 0.0, dz], floor=dz,
                      diameter=cd.D_P, density=cd.RHO_P, dt_dem=DT_DEM, interval=k,
                      n_steps=int(round(end / (k * DT_DEM))), u_in=u, void_fraction="divided", eps_min=0.3,
                      heat=False, rho_g=cd.RHO_G, nu_g=cd.NU_G, friction=0.5, restitution=0.3, walls_top=False,
                      drag="gidaspow_1994", mechanics=mechanics, drag_void_fraction=method,
                      drag_averaging_length=AVERAGING if method == "kernel" else None)


def bed_drop(d, dz, t_from, t_to=math.inf):
    """Mean of coupling.csv's dp (p(bottom cells) - p(top cells)) from t_from (to t_to), less the
    gas hydrostatics between the two cell centres; and its rms departure (relative)."""
    sel = (d["time"] >= t_from - 1e-12) & (d["time"] <= t_to + 1e-12)
    dp = d["dp"][sel] - cd.RHO_G * 9.81 * (H_COL - dz)
    mean = float(dp.mean())
    return mean, float(np.sqrt(((dp - mean) ** 2).mean()) / abs(mean))


def run_column(work, tag, x, dz, u, method, mechanics, end, columns=1):
    """Write and run one column case (through `coupling run`); returns (run folder,
    coupling.csv rows). Raises RuntimeError with the run's output if it fails."""
    from dem import outdir
    case, out = work / f"case_{tag}", work / f"out_{tag}"
    outdir.claim(case)
    outdir.claim(out)
    write(case, x, dz, u, method, mechanics, end, columns=columns)
    code, text, d = cd.run(case, out)
    if code != 0:
        raise RuntimeError(f"coupling run failed (exit {code}):\n{text[-3000:]}")
    return out, d


def held(work, x, n, dz, frac, method, m, end=0.05, columns=1):
    """One held-bed run; returns (pressure drop Pa, Ergun over the profile, Ergun at the core
    packing times the bulk height, in-bed gradient, Ergun there)."""
    u = frac * cd.minimum_fluidization(m["eps_core"])
    out, d = run_column(work, f"{method}_{dz * 1e3:g}mm_{frac:g}", x, dz, u, method, False, end, columns)
    dp, _ = bed_drop(d, dz, end - 10e-3)
    grad, grad_ref = in_bed(out, x, dz, u, m)
    return (dp, ergun_series(u, m["eps_slabs"]), cd.ergun_gradient(u, m["eps_core"]) * m["height"], grad, grad_ref)


def in_bed(out, x, dz, u, m):
    """The pressure gradient between the two cell centres farthest apart inside the bed's core
    (from the last gas time), less the gas hydrostatics, and Ergun there at the core's packing
    between them (exact slab volumes)."""
    from coupling import foam_case as fc
    import bed_surface as bs
    C = fc.read_cell_centres(out)
    t = bs.last_time(out)
    p = fc.read_internal_field(out / t / "p", len(C)) * cd.RHO_G
    z = np.round(C[:, 2], 9)
    levels = np.unique(z)
    pl = np.array([p[z == lv].mean() for lv in levels])
    z0, z1 = m["core"][0] + dz, m["core"][1] + dz     # the bed sits on the plate at z = dz
    inside = np.flatnonzero((levels >= z0) & (levels <= z1))
    i0, i1 = inside[0], inside[-1]
    grad = (pl[i0] - pl[i1]) / (levels[i1] - levels[i0]) - cd.RHO_G * 9.81
    eps = 1.0 - slab_solid_fraction(x + [0.0, 0.0, dz], cd.D_P / 2, levels[i0], levels[i1], cd.L * cd.L)
    return grad, cd.ergun_gradient(u, eps)


def fluidized(work, x, n, dz, frac, method, m, end=0.3, columns=1):
    """One free-bed run above U_mf; returns (mean pressure drop of the second half, its rms
    departure, the buoyant weight per area)."""
    u = frac * cd.minimum_fluidization(m["eps_core"])
    _, d = run_column(work, f"fluid_{method}_{dz * 1e3:g}mm_{frac:g}", x, dz, u, method, True, end, columns)
    dp, rms = bed_drop(d, dz, 0.5 * end)
    return dp, rms, buoyant_weight(n)


def buoyant_weight(n):
    """The buoyant weight per area of n beads in the column, N V_p (rho_p - rho_g) g / A (Pa):
    the pressure drop of a bed the gas carries whole."""
    return n * math.pi / 6 * cd.D_P ** 3 * (cd.RHO_P - cd.RHO_G) * 9.81 / (cd.L * cd.L)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--cells", default="1e-3,2e-3,3e-3,4e-3", help="cell layer heights (m)")
    ap.add_argument("--methods", default="cell,voronoi,kernel", help="drag_void_fraction methods")
    ap.add_argument("--speeds", default="0.2,0.45,0.7", help="inlet speeds, fractions of U_mf (held bed)")
    ap.add_argument("--fluidized", default="", help="inlet speeds above U_mf, fractions (free bed)")
    ap.add_argument("--fluid-end", type=float, default=0.3, help="physical time of a free-bed run (s)")
    ap.add_argument("--n", type=int, default=680)
    ap.add_argument("--averaging", type=float, default=None,
                    help="coupling.toml drag_averaging_length (m) of the kernel runs (default: 3 diameters)")
    ap.add_argument("--seeds", default="", help="a-b: the held bed on the packing of each seed (--cells, "
                                                "--methods; 0.45 U_mf)")
    ap.add_argument("--work", default=str(ROOT / "out" / "ergun_column"))
    a = ap.parse_args(argv)
    if a.seeds:
        lo, _, hi = a.seeds.partition("-")
        if not (lo.isdigit() and (hi.isdigit() or not hi)) or int(hi or lo) < int(lo):
            ap.error(f"--seeds: a seed or a range a-b of seeds (a <= b), got {a.seeds!r}")
        return packings(a)
    from dem import outdir
    global AVERAGING
    AVERAGING = a.averaging
    work = Path(a.work)
    outdir.claim_folder(work, overwrite=True, command="benchmarks/ergun_column.py", what="work folder")
    x = bed(a.n)
    m = measure(x, a.n)
    umf = cd.minimum_fluidization(m["eps_core"])
    print("void fraction profile (slabs of one diameter from the plate): "
          + " ".join(f"{e:.3f}" for e in m["eps_slabs"]))
    print(f"bed: {a.n} beads of {cd.D_P * 1e3:g} mm, core packing ({m['core'][0] * 1e3:.2f}-{m['core'][1] * 1e3:.2f} "
          f"mm above the plate) eps {m['eps_core']:.4f}, bulk height {m['height'] * 1e3:.2f} mm; top (highest 10 % "
          f"+ r) {m['top'] * 1e3:.2f} mm, eps {m['eps_top']:.4f}; U_mf (Wen-Yu) {umf * 1e3:.3f} mm/s")
    cells = [float(v) for v in a.cells.split(",")]
    methods = a.methods.split(",")
    rows = []
    if a.speeds:
        print("| cells | method | u / U_mf | dp [Pa] | Ergun over the profile [Pa] | dp / it - 1 | "
              "Ergun, bulk [Pa] | dp / it - 1 | in-bed gradient [Pa/m] | Ergun there | error |")
        print("|---|---|---|---|---|---|---|---|---|---|---|")
        for dz in cells:
            for meth in methods:
                for frac in [float(v) for v in a.speeds.split(",")]:
                    dp, e_ser, e_bulk, g, g_ref = held(work, x, a.n, dz, frac, meth, m)
                    rows.append(dict(kind="held", dz=dz, method=meth, frac=frac, dp=dp, ref=e_ser, ref_bulk=e_bulk,
                                     grad=g, grad_ref=g_ref))
                    print(f"| {dz * 1e3:g} mm | {meth} | {frac:g} | {dp:.3f} | {e_ser:.3f} | "
                          f"{100 * (dp / e_ser - 1):+.2f} % | {e_bulk:.3f} | {100 * (dp / e_bulk - 1):+.2f} % | "
                          f"{g:.1f} | {g_ref:.1f} | {100 * (g / g_ref - 1):+.2f} % |", flush=True)
    if a.fluidized:
        print("| cells | method | u / U_mf | dp [Pa] (mean, 2nd half) | rms | weight / area [Pa] | dp / weight - 1 |")
        print("|---|---|---|---|---|---|---|")
        for dz in cells:
            for meth in methods:
                for frac in [float(v) for v in a.fluidized.split(",")]:
                    dp, rms, w = fluidized(work, x, a.n, dz, frac, meth, m, end=a.fluid_end)
                    rows.append(dict(kind="fluidized", dz=dz, method=meth, frac=frac, dp=dp, ref=w, rms=rms))
                    print(f"| {dz * 1e3:g} mm | {meth} | {frac:g} | {dp:.3f} | {rms:.2g} | {w:.3f} | "
                          f"{100 * (dp / w - 1):+.2f} % |", flush=True)
    return rows


def packings(a):
    """--seeds: the held bed at 0.45 U_mf on the packing of each seed, against Ergun over its
    own profile; the mean and the standard deviation over the packings."""
    from dem import outdir
    lo, _, hi = a.seeds.partition("-")
    seeds = range(int(lo), int(hi or lo) + 1)
    cells = [float(v) for v in a.cells.split(",")]
    methods = a.methods.split(",")
    work = Path(a.work)
    outdir.claim_folder(work, overwrite=True, command="benchmarks/ergun_column.py", what="work folder")
    print("| seed | core eps | " + " | ".join(f"{m} {dz * 1e3:g} mm: dp / Ergun over the profile - 1"
                                              for m in methods for dz in cells) + " |")
    print("|---|---|" + "---|" * (len(methods) * len(cells)))
    rows = []
    for seed in seeds:
        x = cd.settled_bed(a.n, seed=seed, log=lambda *_: None)
        m = measure(x, a.n)
        w = work / f"seed_{seed}"
        outdir.claim(w)
        w.mkdir(exist_ok=True)
        dev = []
        for meth in methods:
            for dz in cells:
                dp, e_ser, *_ = held(w, x, a.n, dz, 0.45, meth, m)
                dev.append(dp / e_ser - 1)
                rows.append(dict(kind="packing", seed=seed, dz=dz, method=meth, dp=dp, ref=e_ser))
        print(f"| {seed} | {m['eps_core']:.4f} | " + " | ".join(f"{100 * d:+.2f} %" for d in dev) + " |", flush=True)
    for meth in methods:
        for dz in cells:
            d = np.array([r["dp"] / r["ref"] - 1 for r in rows if r["method"] == meth and r["dz"] == dz])
            print(f"{meth}, {dz * 1e3:g} mm cells, {len(d)} packings: mean {100 * d.mean():+.2f} %, standard "
                  f"deviation {100 * d.std(ddof=1) if len(d) > 1 else 0.0:.2f} %, {100 * d.min():+.2f} to "
                  f"{100 * d.max():+.2f} %")
    return rows


if __name__ == "__main__":
    main()
