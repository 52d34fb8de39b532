"""openfoam_cases/packed_bed_heating against Schumann's (1929) solution.

    python benchmarks/schumann_packed_bed.py [--out DIR] [--end-time 1.0] [--reuse]
                                             [--figure docs/schumann_packed_bed.png]

Runs the coupled case (thermoDemFoam + DEM, socket) unless --reuse finds DIR already
complete, then compares the gas and solid temperatures of every bed layer at every
written time (0.1 s apart) with Schumann's two-equation model

    gas  : eps rho c (dTg/dt + u_i dTg/dx) = h a (Ts - Tg)     plug flow, no axial conduction
    solid: (1 - eps) rho_s c_s dTs/dt      = h a (Tg - Ts)     lumped particles

With Y = h a x / (rho c u_s) and Z = h a (t - x / u_i) / ((1 - eps) rho_s c_s) (the shift by
the gas transit time x / u_i makes the gas hold-up exact) and theta = (T - T0)/(Tin - T0):

    theta_s(Y, Z) = exp(-Y) int_0^Z exp(-s) I0(2 sqrt(Y s)) ds
    theta_g(Y, Z) = theta_s + exp(-Y - Z) I0(2 sqrt(Y Z))              (Z > 0; 0 for Z < 0)

h a is read from the run (the Simp field = sum_i (hA)_i / V_c of the bed cells), the solid
temperature of a layer from Sexp / Simp (the particle temperatures of the start of the
coupling step, i.e. at t - dt), the gas temperature from T at the cell centres.
Prints the errors (max over layers and times, in units of Tin - T0) and writes a figure.
"""
from __future__ import annotations

import argparse
import math
import sys
from pathlib import Path

import numpy as np
from scipy import integrate, special

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

CASE = ROOT / "openfoam_cases" / "packed_bed_heating"
T0, TIN = 300.0, 373.15
RHO, CP, U_S = 1.2, 1005.0, 0.5
BED_HEIGHT = 0.06


def _kernel(s, y):
    # exp(-y - s) I0(2 sqrt(y s)) without overflow: i0e(x) = exp(-x) I0(x)
    return special.i0e(2.0 * np.sqrt(y * s)) * np.exp(-(np.sqrt(y) - np.sqrt(s)) ** 2)


def schumann(Y, Z):
    """(theta_gas, theta_solid) of Schumann's model at dimensionless (Y, Z), arrays."""
    Y, Z = np.broadcast_arrays(np.asarray(Y, float), np.asarray(Z, float))
    tg, ts = np.zeros(Y.shape), np.zeros(Y.shape)
    for i in np.ndindex(Y.shape):
        y, z = Y[i], Z[i]
        if z <= 0.0:
            continue
        s, _ = integrate.quad(_kernel, 0.0, z, args=(y,), epsabs=1e-12, epsrel=1e-10, limit=200)
        ts[i] = s
        tg[i] = s + _kernel(z, y)
    return tg, ts


def load(out: Path):
    """Per written time t > 0: gas T and solid T (Sexp/Simp) of the bed cells, and h a."""
    from coupling import foam_case as fc
    C = fc.read_cell_centres(out)
    n = len(C)
    order = np.argsort(C[:, 2])
    z = C[order, 2]
    bed = z < BED_HEIGHT
    from dem.final import read as read_final   # an MPI run's final.npz: a manifest and its pieces
    dem = read_final(out / "final.npz")
    eps = float(fc.read_internal_field(out / "0" / "eps", n)[order][bed].mean())
    times, tg, ts, ha = [], [], [], []
    for d in out.iterdir():
        try:
            t = float(d.name)
        except ValueError:
            continue
        if t <= 0 or not (d / "T").is_file() or not (d / "Simp").is_file():
            continue
        T = fc.read_internal_field(d / "T", n)[order][bed]
        simp = fc.read_internal_field(d / "Simp", n)[order][bed]
        sexp = fc.read_internal_field(d / "Sexp", n)[order][bed]
        times.append(t)
        tg.append(T)
        ts.append(sexp / simp)
        ha.append(simp)
    k = np.argsort(times)
    return dict(t=np.array(times)[k], x=z[bed], eps=eps, Tg=np.array(tg)[k], Ts=np.array(ts)[k],
                ha=np.array(ha)[k], final=dem)


def compare(d, rho_s_cs: float, dt: float):
    """Errors of the run against Schumann; returns a dict with arrays and maxima."""
    ha = float(d["ha"].mean())
    spread = float(np.ptp(d["ha"]) / ha)
    eps = d["eps"]
    u_i = U_S / eps
    x, t = d["x"], d["t"][:, None]
    Y = ha * x / (RHO * CP * U_S)
    tau_s = (1 - eps) * rho_s_cs / ha
    Zg = (t - x / u_i) / tau_s
    Zs = (t - dt - x / u_i) / tau_s          # Sexp/Simp: particle temperatures at t - dt
    tg_ref, _ = schumann(Y[None, :] + 0 * Zg, Zg)
    _, ts_ref = schumann(Y[None, :] + 0 * Zs, Zs)
    th_g = (d["Tg"] - T0) / (TIN - T0)
    th_s = (d["Ts"] - T0) / (TIN - T0)
    return dict(ha=ha, ha_spread=spread, ntu=float(ha * BED_HEIGHT / (RHO * CP * U_S)), tau_s=tau_s,
                Y=Y, Zg=Zg, th_g=th_g, th_s=th_s, ref_g=tg_ref, ref_s=ts_ref,
                err_g=float(np.abs(th_g - tg_ref).max()), err_s=float(np.abs(th_s - ts_ref).max()),
                rms_g=float(np.sqrt(((th_g - tg_ref) ** 2).mean())),
                rms_s=float(np.sqrt(((th_s - ts_ref) ** 2).mean())))


def ranz_marshall_ha(eps, d=4e-3, mu=1.8e-5, k=0.0262):
    re_ = RHO * U_S * d / mu                        # eps_i |u_i| = u_s
    nu = 2.0 + 0.6 * math.sqrt(re_) * (mu * CP / k) ** (1 / 3)
    return nu * k / d * 6 * (1 - eps) / d


def figure(r, d, path: Path):
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    fig, ax = plt.subplots(1, 2, figsize=(10, 4), sharey=True)
    yf = np.linspace(0, r["Y"].max(), 200)
    eps, ha = d["eps"], r["ha"]
    for j, t in enumerate(d["t"]):
        if j % 2 == 0 or j == len(d["t"]) - 1:
            c = plt.cm.viridis(t / d["t"].max())
            xf = yf * RHO * CP * U_S / ha
            zg = (t - xf * eps / U_S) / r["tau_s"]
            g, s = schumann(yf, zg)
            ax[0].plot(yf, g, color=c, lw=1)
            ax[0].plot(r["Y"], r["th_g"][j], "o", color=c, ms=3, label=f"t = {t:g} s")
            ax[1].plot(yf, s, color=c, lw=1)
            ax[1].plot(r["Y"], r["th_s"][j], "s", color=c, ms=3)
    ax[0].set(xlabel="Y = h a x / (rho c u_s)", ylabel="(T - T0) / (Tin - T0)",
              title=f"gas (max err {r['err_g']:.3f})")
    ax[1].set(xlabel="Y", title=f"solid (max err {r['err_s']:.3f})")
    ax[0].legend(fontsize=7)
    fig.suptitle("packed_bed_heating: CFD-DEM (symbols) vs Schumann 1929 (lines)")
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110)
    plt.close(fig)


def main(argv=None):
    ap = argparse.ArgumentParser()
    ap.add_argument("--out", type=Path, default=ROOT / "out" / "packed_bed_heating")
    ap.add_argument("--end-time", type=float, default=1.0)
    ap.add_argument("--reuse", action="store_true", help="use an existing complete run in --out")
    ap.add_argument("--figure", type=Path, default=None, help="default: OUT/schumann.png")
    a = ap.parse_args(argv)
    import tomllib
    from coupling import foam_case as fc
    from coupling.run import run_case
    if not (a.reuse and (a.out / "final.npz").is_file()):
        run_case(CASE, a.out, end_time=a.end_time, quiet=True, overwrite=True)  # only our earlier output
    mat = tomllib.loads((a.out / "dem.toml").read_text())["materials"][0]
    rho_s_cs = float(mat["density"]) * float(mat["heat_capacity"])
    dt = float(fc.parse_foam_dict(a.out / "system" / "controlDict")["deltaT"])
    d = load(a.out)
    r = compare(d, rho_s_cs, dt)
    print(f"bed: eps {d['eps']:.4f}, h a {r['ha']:.5g} W/(m3 K) (Ranz-Marshall {ranz_marshall_ha(d['eps']):.5g}, "
          f"spread over layers/times {r['ha_spread']:.1e}), NTU {r['ntu']:.3f}, tau_s {r['tau_s']:.4f} s, "
          f"{len(d['x'])} layers, times {d['t'][0]:g}..{d['t'][-1]:g} s")
    print(f"error / (Tin - T0): gas max {r['err_g']:.4f} rms {r['rms_g']:.4f}; "
          f"solid max {r['err_s']:.4f} rms {r['rms_s']:.4f}")
    fig = a.figure or (a.out / "schumann.png")
    if a.figure is None:   # into the output folder: recorded in its manifest, never over a user's file
        from dem.outdir import claim_file
        claim_file(fig, "the figure")
    figure(r, d, fig)
    print(f"figure {fig}")
    return r


if __name__ == "__main__":
    main()
