"""Heat transfer to a horizontal tube in a bubbling bed (openfoam_cases/immersed_tube, issue 14).

    python benchmarks/immersed_tube.py --out out/immersed_tube [--end-time T]   # run the case, analyse
    python benchmarks/immersed_tube.py --analyse-only out/immersed_tube [--discard 0.3] [--plot f.png]

The run is `coupling run openfoam_cases/immersed_tube --out OUT` (prefix `taskset -c 1` to pin
it). The analysis reads the run folder:

* ``wall_heat.csv``: the heat the DEM wall ``tube`` gives the particles, by path (``contact``,
  ``gas_gap``; ``gas_convection``, the gas's own heat from the tube patch, when the file has
  it); without ``gas_convection`` rows the gas path is read from the solver's log
  ("Wall heat into the gas, patch tube: ... W", every CFD step);
* ``coupling.csv``: the mean particle temperature T_bed (T_particles), the pressure drop and the
  mean particle height;
* ``wall_heat_angle.csv`` (time, wall, angle_deg, contact_W_m2, gas_gap_W_m2, radiation_W_m2)
  when present: the local coefficient around the tube.
A tube that radiates (an emissivity and a radiation model) adds the path ``radiation`` to the
particles' coefficient.

The tube coefficient of each output interval is h = Q / (A (T_tube - T_bed)) with Q the mean
heat rate of the interval (from the energies) and T_bed at the interval's middle; the reported
h is its time average after the start-up transient (``--discard``), split by path, next to
Zabrodsky's maximum and Molerus' correlation (functions below, importable). Also reported: the
running average of h against the window length (and the window after which it stays within
5 % of the final value), the pressure drop against the bed weight, the bubble frequency, and
the cost of the run. Figure: ``immersed_tube.png`` in the run folder (or ``--plot``).
"""
from __future__ import annotations

import argparse
import csv
import glob
import json
import math
import os
import re
import subprocess
import sys
import tomllib
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
ROOT = HERE.parent
sys.path.insert(0, str(ROOT))

CASE = ROOT / "openfoam_cases" / "immersed_tube"
G = 9.81
# Voidage at minimum fluidization of the correlations: Wen & Yu (1966) approximate Ergun with
# 1/(phi eps_mf^3) = 14, which for spheres (phi = 1) is eps_mf = 14^(-1/3) = 0.415.
EPS_MF = 0.415
SETTLED = (0.05, 0.02)    # running average "settled": stays within 5 % (2 %) of the final value


# ----------------------------------------------------------------------------- correlations

def zabrodsky_hmax(rho_p, k_g, d_p):
    """Maximum bed-to-surface heat transfer coefficient of a gas-fluidized bed [W/(m2 K)]:

        h_max = 35.8 rho_p^0.2 k_g^0.6 d_p^-0.36      (SI units: kg/m3, W/(m K), m)

    Zabrodsky, S.S. (1966), Hydrodynamics and Heat Transfer in Fluidized Beds, MIT Press
    (translation of the 1963 Russian edition); Zabrodsky, S.S., Antonishin, N.V. & Parnas, A.L.
    (1976), On fluidized bed-to-surface heat transfer, Can. J. Chem. Eng. 54(1-2): 52-58,
    doi:10.1002/cjce.5450540107. The maximum over the gas velocity, dominated by particle
    convection (Geldart B/A particles, no radiation). 1 mm glass (2500 kg/m3) in air
    (0.0262 W/(m K)): 231 W/(m2 K).

    Published scatter: NOT confirmed here. The original papers were not accessible; the
    coefficient and exponents are the commonly quoted ones and agree with an independent
    implementation (Thanheiser et al., Energies 15 (2022) 1316, zabrodsky.m of
    github.com/sthanhe/HeatTransfer), but the scatter of the data around the correlation could
    not be read, so no band is claimed."""
    return 35.8 * rho_p ** 0.2 * k_g ** 0.6 * d_p ** -0.36


def laminar_length(mu_g, rho_p, rho_g, g=G):
    """Molerus' laminar flow length scale l_l = (mu / (sqrt(g) (rho_p - rho_g)))^(2/3) [m]."""
    return (mu_g / (math.sqrt(g) * (rho_p - rho_g))) ** (2.0 / 3.0)


def molerus_1995(rho_p, rho_g, cp_p, cp_g, k_g, mu_g, d_p, U, U_mf, eps_mf, g=G):
    """Bed-to-immersed-surface heat transfer coefficient of a bubbling bed [W/(m2 K)], split into
    the particle-convective and the gas-convective parts:

        Nu = h l_l / k_g = Nu_pc + Nu_gc,   l_l = (mu / (sqrt(g) (rho_p - rho_g)))^(2/3)
        Nu_pc = 0.125 (1 - eps_mf) [1 + 33.3 / (r^(1/3) X)]^-1
                / (1 + k_g/(2 cp_p mu) [1 + 0.28 (1 - eps_mf)^2 (rho_g/(rho_p - rho_g))^0.5 X^2 r])
        Nu_gc = 0.165 Pr^(1/3) (rho_g/(rho_p - rho_g))^(1/3) [1 + 0.05 r]^-1
        X = (rho_p cp_p / (k_g g))^(1/3) (U - U_mf),   r = U_mf / (U - U_mf),   Pr = cp_g mu / k_g

    Molerus, O., Burschka, A. & Dietz, S. (1995), Particle migration at solid surfaces and heat
    transfer in bubbling fluidized beds - II. Prediction of heat transfer in bubbling fluidized
    beds, Chem. Eng. Sci. 50(5): 879-885, doi:10.1016/0009-2509(94)00446-X; the length scale and
    the limits (laminar: particle convection, turbulent: gas convection) from Molerus, O. (1992),
    Heat transfer in gas fluidized beds, part 1 and part 2, Powder Technol. 70: 1-14 and 15-20.
    cp_p is the heat capacity of the particles, cp_g of the gas; d_p enters only through U_mf
    (the correlation's length is l_l); it is used here for the Archimedes number returned.

    NOT confirmed against the original paper (not accessible here): the form above is written
    from its citations in the secondary literature as remembered, and checked only against two
    independent MATLAB implementations (Thanheiser: FluBed.m of github.com/sthanhe/engMan and
    molerus.m of github.com/sthanhe/TubeBankHeatTransfer). They agree on every constant (0.125,
    33.3, 0.28, 0.165, 0.05) but use ((U - U_mf)/U_mf)^(1/3), the inverse of r^(1/3), in the 33.3
    term (at U = 2 U_mf, r = 1, the two readings are identical; the immersed_tube case runs at
    r = 0.99); the second of them also writes the 0.28 term differently (k_g/(2 cp_p mu) squared,
    no leading 1), which looks like a slip.
    Published scatter: not confirmed either (no band is claimed). Needs U > U_mf.

    Returns a dict: h (total), h_pc, h_gc [W/(m2 K)], Nu_pc, Nu_gc, l_l [m], Ar (with d_p)."""
    if U <= U_mf:
        raise ValueError(f"Molerus' bubbling-bed correlation needs U > U_mf (U = {U}, U_mf = {U_mf})")
    drho = rho_p - rho_g
    l_l = laminar_length(mu_g, rho_p, rho_g, g)
    ue = U - U_mf
    r = U_mf / ue
    X = (rho_p * cp_p / (k_g * g)) ** (1.0 / 3.0) * ue
    pi2 = k_g / (2.0 * cp_p * mu_g)
    damp = 1.0 + 0.28 * (1.0 - eps_mf) ** 2 * math.sqrt(rho_g / drho) * X ** 2 * r
    nu_pc = 0.125 * (1.0 - eps_mf) / (1.0 + 33.3 / (r ** (1.0 / 3.0) * X)) / (1.0 + pi2 * damp)
    pr = cp_g * mu_g / k_g
    nu_gc = 0.165 * pr ** (1.0 / 3.0) * (rho_g / drho) ** (1.0 / 3.0) / (1.0 + 0.05 * r)
    ar = rho_g * drho * g * d_p ** 3 / mu_g ** 2
    return dict(h=(nu_pc + nu_gc) * k_g / l_l, h_pc=nu_pc * k_g / l_l, h_gc=nu_gc * k_g / l_l,
                Nu_pc=nu_pc, Nu_gc=nu_gc, l_l=l_l, Ar=ar)


def molerus_1995_max(rho_p, rho_g, cp_p, cp_g, k_g, mu_g, d_p, U_mf, eps_mf, g=G, upto=20.0):
    """The largest total coefficient of :func:`molerus_1995` over U in (U_mf, upto U_mf]
    (a dense scan refined by golden-section search). Returns (h_max, U at the maximum)."""
    def h(u):
        return molerus_1995(rho_p, rho_g, cp_p, cp_g, k_g, mu_g, d_p, u, U_mf, eps_mf, g)["h"]
    us = U_mf * (1.0 + np.geomspace(1e-3, upto - 1.0, 400))
    hs = np.array([h(u) for u in us])
    k = int(np.argmax(hs))
    a, b = us[max(k - 1, 0)], us[min(k + 1, len(us) - 1)]
    q = (math.sqrt(5.0) - 1.0) / 2.0
    for _ in range(80):
        c, d = b - q * (b - a), a + q * (b - a)
        if h(c) >= h(d):
            b = d
        else:
            a = c
    u = 0.5 * (a + b)
    return h(u), u


# ----------------------------------------------------------------------------- reading a run

def case_properties(out):
    """Material, gas and tube data of a run folder (its dem.toml and 0/U copies)."""
    from coupling import foam_case as fc
    from coupling.drag import wen_yu_1966_umf
    out = Path(out)
    with open(out / "dem.toml", "rb") as fh:
        dem = tomllib.load(fh)
    mat = dem["materials"][0]
    gas = dem["gas"]
    tube = next(w for w in dem["walls"] if w.get("name") == "tube")
    rad = dem["particles"][0]["radius"]
    d_p = float(rad["min"] + rad["max"]) if isinstance(rad, dict) else 2.0 * float(rad)
    inlet = fc.parse_foam_dict(out / "0" / "U")["boundaryField"]["inlet"]["value"]
    U = float(re.findall(r"[-+0-9.eE]+", inlet)[-1])
    lo, hi = np.array(dem["domain"]["min"], float), np.array(dem["domain"]["max"], float)
    p = dict(rho_p=float(mat["density"]), cp_p=float(mat["heat_capacity"]), rho_g=float(gas["density"]),
             cp_g=float(gas["heat_capacity"]), k_g=float(gas["conductivity"]), mu_g=float(gas["viscosity"]),
             d_p=d_p, U=U, T_tube=float(tube["thermal"]["temperature"]), tube_r=float(tube["radius"]),
             tube_xz=(float(tube["point"][0]), float(tube["point"][2])),
             dem_dt=float(dem["simulation"]["time_step"]),
             section=float((hi[0] - lo[0]) * (hi[1] - lo[1])))
    p["U_mf"] = wen_yu_1966_umf(d_p, p["rho_p"], p["rho_g"], p["mu_g"], G)
    return p


def read_csv(path):
    """Columns of a CSV with a header row as float arrays (text columns as str arrays)."""
    with open(path, newline="") as fh:
        rows = list(csv.reader(fh))
    head, body = rows[0], rows[1:]
    cols = {}
    for k, name in enumerate(head):
        vals = [r[k] for r in body]
        try:
            cols[name] = np.array(vals, float)
        except ValueError:
            cols[name] = np.array(vals)
    return cols


def wall_energy(path, wall="tube"):
    """{mechanism: (time, energy_J)} of one wall in wall_heat.csv, and its area [m2]."""
    c = read_csv(path)
    sel = c["wall"] == wall
    if not np.any(sel):
        raise SystemExit(f"{path}: no rows for wall {wall!r}")
    out = {}
    for mech in np.unique(c["mechanism"][sel]):
        s = sel & (c["mechanism"] == mech)
        out[str(mech)] = (c["time"][s], c["energy_J"][s])
    return out, float(c["area_m2"][sel][0])


def gas_heat_from_log(out, patch="tube"):
    """(time, W) of the gas's heat from a wall patch, from the solver's log lines
    'Time = t ...' and 'Wall heat into the gas, patch <patch>: Q W' (every CFD step). Later
    logs (a restart) replace earlier values at the same time. None when no line is found."""
    rec = {}
    pat = re.compile(r"Wall heat into the gas, patch " + re.escape(patch) + r": ([-+0-9.eE]+) W")
    for f in sorted(glob.glob(str(Path(out) / "log.thermoDemFoam*")), key=os.path.getmtime):
        t = None
        with open(f, errors="replace") as fh:
            for line in fh:
                if line.startswith("Time = "):
                    t = float(line.split()[2])
                else:
                    m = pat.search(line)
                    if m and t is not None:
                        rec[t] = float(m.group(1))
    if not rec:
        return None
    t = np.array(sorted(rec))
    return t, np.array([rec[x] for x in t])


def interval_rates(t, E):
    """Mean rate of each output interval (t[k-1], t[k]] from a cumulative energy."""
    return np.diff(E) / np.diff(t)


def running_average(t0, t1, h):
    """Running time average of the interval values h over (t0[0], t1[k]] for each k."""
    dt = t1 - t0
    return np.cumsum(h * dt) / np.cumsum(dt)


def settled_window(tau, run, tol):
    """Shortest averaging window tau[k] after which the running average stays within tol of
    its final value (tau: the window length at each point of ``run``)."""
    bad = np.flatnonzero(np.abs(run - run[-1]) > tol * abs(run[-1]))
    return float(tau[0] if bad.size == 0 else tau[min(bad[-1] + 1, len(tau) - 1)])


def batch_error(dt, h, nb=5):
    """Standard error of the time average from nb equal batches (batch means)."""
    n = len(h) // nb
    if n < 1:
        return float("nan")
    means = [np.sum(h[i * n:(i + 1) * n] * dt[i * n:(i + 1) * n]) / np.sum(dt[i * n:(i + 1) * n])
             for i in range(nb)]
    return float(np.std(means, ddof=1) / math.sqrt(nb))


def read_angles(path, wall="tube"):
    """wall_heat_angle.csv: (angles [deg], times, contact and gas-gap flux [W/m2] as
    (time, angle) arrays) of one wall; None when the file is absent."""
    if not Path(path).exists():
        return None
    c = read_csv(path)
    sel = c["wall"] == wall
    ang, tim = np.unique(c["angle_deg"][sel]), np.unique(c["time"][sel])
    flux = {}
    for key in ("contact_W_m2", "gas_gap_W_m2", "radiation_W_m2"):
        if key not in c:     # a file from before the radiation column
            flux[key] = np.zeros((len(tim), len(ang)))
            continue
        a = np.full((len(tim), len(ang)), np.nan)
        a[np.searchsorted(tim, c["time"][sel]), np.searchsorted(ang, c["angle_deg"][sel])] = c[key][sel]
        flux[key] = a
    return ang, tim, flux


# ----------------------------------------------------------------------------- the analysis

def _gas_rates(out, wall, t0, t1):
    """The gas's heat from the tube patch, mean of the CFD-step values of the solver's log
    within each output interval (NaN where the log has none); None without log lines."""
    log = gas_heat_from_log(out, wall)
    if log is None:
        return None
    lt, lq = log
    q = np.full(len(t1), np.nan)
    for k in range(len(t1)):
        s = (lt > t0[k] + 1e-12) & (lt <= t1[k] + 1e-12)
        if np.any(s):
            q[k] = lq[s].mean()
    return q


def _bed(cp, p, discard):
    """Pressure drop against the bed weight, its dominant frequency, mean particle height."""
    mass = cp["E_particles"] / (p["cp_p"] * cp["T_particles"])      # E = sum m c T, one c
    sb = cp["time"] >= discard - 1e-9
    dp = cp["dp"][sb]
    f = np.fft.rfftfreq(dp.size, np.diff(cp["time"][sb]).mean()) if dp.size > 4 else None
    spec = np.abs(np.fft.rfft(dp - dp.mean())) if dp.size > 4 else None
    return dict(weight=float(mass[-1] * G / p["section"]), dp_mean=float(dp.mean()), dp_std=float(dp.std()),
                bubble_hz=float(f[1:][np.argmax(spec[1:])]) if f is not None else float("nan"),
                height_mean=float(cp["bed_height"][sb].mean()), height_std=float(cp["bed_height"][sb].std()))


def _correlations(p):
    args = (p["rho_p"], p["rho_g"], p["cp_p"], p["cp_g"], p["k_g"], p["mu_g"], p["d_p"])
    return dict(zabrodsky=zabrodsky_hmax(p["rho_p"], p["k_g"], p["d_p"]),
                molerus=molerus_1995(*args, p["U"], p["U_mf"], EPS_MF),
                molerus_max=molerus_1995_max(*args, p["U_mf"], EPS_MF))


def _cost(out):
    if not (out / "timings.json").exists():
        return {}
    tj = json.loads((out / "timings.json").read_text())
    return dict(particles=tj["particles"], particle_steps_per_s=tj["particle_steps_per_s"], loop_s=tj["loop"],
                wall_s=tj["wall_total"], dem_share=tj["phases"]["dem"] / tj["loop"])


def _angles(out, wall, cp, p, discard, angles_from=None):
    ang = read_angles(out / "wall_heat_angle.csv", wall)
    if ang is None:
        return None
    a, at, fl = ang
    s = at >= max(discard, angles_from or 0.0) - 1e-9
    dT = p["T_tube"] - np.interp(at[s], cp["time"], cp["T_particles"])[:, None]
    return dict(angle=a, **{k: np.nanmean(v[s] / dT, axis=0) for k, v in fl.items()})


def analyse(out, discard=0.3, wall="tube", angles_from=None):
    """Every number of the report (a dict); see the module docstring."""
    out = Path(out)
    p = case_properties(out)
    energy, area = wall_energy(out / "wall_heat.csv", wall)
    cp = read_csv(out / "coupling.csv")
    paths = {m: energy[m] for m in ("contact", "gas_gap", "radiation", "gas_convection") if m in energy}
    t = energy["total"][0] if "total" in energy else next(iter(paths.values()))[0]
    t0, t1 = t[:-1], t[1:]
    rates = {m: interval_rates(*paths[m]) for m in paths}
    gas_src = "wall_heat.csv" if "gas_convection" in rates else None
    if gas_src is None and (q := _gas_rates(out, wall, t0, t1)) is not None:
        rates["gas_convection"], gas_src = q, "solver log"
    T_bed = np.interp(0.5 * (t0 + t1), cp["time"], cp["T_particles"])     # at each interval's middle
    h = {m: rates[m] / (area * (p["T_tube"] - T_bed)) for m in rates}
    h["particles"] = sum(h[m] for m in ("contact", "gas_gap", "radiation") if m in h)
    if "gas_convection" in h:
        h["all"] = h["particles"] + h["gas_convection"]
    keep = t0 >= discard - 1e-9
    if np.count_nonzero(keep) < 2:
        raise SystemExit(f"{out}: output reaches t = {t[-1]:g} s; nothing to average after --discard {discard} s")
    dt = t1 - t0
    mean, covered = {}, {}
    for m, v in h.items():      # a path missing in some intervals (a log lost to a restart) is
        k = keep & np.isfinite(v)    # averaged over the intervals it has; covered says how long
        mean[m] = float(np.sum(v[k] * dt[k]) / np.sum(dt[k])) if np.any(k) else float("nan")
        covered[m] = float(np.sum(dt[k]))
    run = running_average(t0[keep], t1[keep], h["particles"][keep])
    tau = t1[keep] - t0[keep][0]
    return dict(props=p, area=area, discard=discard, t_end=float(t[-1]), t0=t0, t1=t1, h=h, mean=mean,
                covered=covered, gas_source=gas_src, running=run, tau=tau,
                settled={x: settled_window(tau, run, x) for x in SETTLED},
                stderr=batch_error(dt[keep], h["particles"][keep]), T_bed=T_bed,
                T_bed_mean=float(np.mean(T_bed[keep])), coupling=cp, corr=_correlations(p), cost=_cost(out),
                angles=_angles(out, wall, cp, p, discard, angles_from), folder=out, **_bed(cp, p, discard))


def report(r):
    """The analysis as text."""
    p, m, c = r["props"], r["mean"], r["corr"]
    mo = c["molerus"]
    span = r["t_end"] - r["discard"]
    lines = [
        f"immersed tube: {p['T_tube']:g} K, area {r['area']:.4g} m2; beads d_p {1e3 * p['d_p']:.3g} mm, "
        f"U = {p['U']:g} m/s = {p['U'] / p['U_mf']:.2f} U_mf (Wen & Yu U_mf = {p['U_mf']:.3f} m/s)",
        f"averaged over t = {r['discard']:g} .. {r['t_end']:g} s ({span:.3g} s; start-up discarded), "
        f"T_bed {r['T_bed_mean']:.2f} K (mean particle temperature)",
        f"  h particles (contact + gas gap)  {m['particles']:8.1f} W/(m2 K)  +- {r['stderr']:.1f} (batch means)",
        f"    contact                         {m.get('contact', float('nan')):8.1f}",
        f"    gas gap                         {m.get('gas_gap', float('nan')):8.1f}",
    ]
    if "gas_convection" in m:
        span_gas = r["covered"]["gas_convection"]
        lines.append(f"    gas convection                  {m['gas_convection']:8.1f}   (from the {r['gas_source']}"
                     + (f", over {span_gas:.3g} s only" if span_gas < 0.999 * r["covered"]["particles"] else "")
                     + ")")
        lines.append(f"  h all paths                       {m['all']:8.1f}")
    lines += [
        "  running average within " + ", ".join(f"{100 * x:g} % of the final value after a window of "
                                                f"{r['settled'][x]:.3g} s" for x in SETTLED)
        + f" (of {r['tau'][-1]:.3g} s)",
        f"  Zabrodsky h_max                   {c['zabrodsky']:8.1f}   (ratio particles / Zabrodsky "
        f"{m['particles'] / c['zabrodsky']:.2f})",
        f"  Molerus 1995 at U: total {mo['h']:.1f} = particle-convective {mo['h_pc']:.1f} + gas-convective "
        f"{mo['h_gc']:.1f} (eps_mf {EPS_MF}, Ar {mo['Ar']:.3g}); its maximum over U {c['molerus_max'][0]:.1f} "
        f"at U = {c['molerus_max'][1] / p['U_mf']:.2f} U_mf",
        f"    ratio particles / Molerus particle-convective {m['particles'] / mo['h_pc']:.2f}" + (
            f", gas convection / Molerus gas-convective {m['gas_convection'] / mo['h_gc']:.2f}"
            if "gas_convection" in m else ""),
        f"bed: p(bottom) - p(top) {r['dp_mean']:.0f} +- {r['dp_std']:.0f} Pa (std) against the weight "
        f"{r['weight']:.0f} Pa per column section ({r['dp_mean'] / r['weight']:.2f}); dominant frequency of dp "
        f"{r['bubble_hz']:.2g} Hz; mean particle height {1e3 * r['height_mean']:.1f} +- "
        f"{1e3 * r['height_std']:.1f} mm",
    ]
    if r["cost"]:
        k = r["cost"]
        lines.append(f"cost: {k['particles']} particles, {k['particle_steps_per_s']:.3g} particle-steps/s, loop "
                     f"{k['loop_s']:.0f} s ({100 * k['dem_share']:.0f} % DEM), wall {k['wall_s']:.0f} s of this run")
    if r["angles"] is not None:
        a = r["angles"]
        lines.append("local h by angle (contact + gas gap + radiation): " + ", ".join(
            f"{x:g}: {y:.0f}" for x, y in zip(a["angle"], a["contact_W_m2"] + a["gas_gap_W_m2"]
                                              + a.get("radiation_W_m2", 0.0))))
    return "\n".join(lines)


def plot(r, path):
    """immersed_tube.png: h(t) by path with the correlations, running average, bed, angles."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    fig = plt.figure(figsize=(16, 8))
    gs = fig.add_gridspec(2, 3, width_ratios=(1.0, 1.0, 0.6))
    ax = np.array([[fig.add_subplot(gs[i, j]) for j in range(2)] for i in range(2)])
    tm = 0.5 * (r["t0"] + r["t1"])
    a = ax[0, 0]
    for key, lab in (("contact", "contact"), ("gas_gap", "gas gap"), ("gas_convection", "gas convection"),
                     ("particles", "particles (contact + gas gap)")):
        if key in r["h"]:
            a.plot(tm, r["h"][key], lw=0.8 if key != "particles" else 1.4, label=lab)
    c = r["corr"]
    a.axhline(c["zabrodsky"], color="k", ls="--", label=f"Zabrodsky h_max {c['zabrodsky']:.0f}")
    a.axhline(c["molerus"]["h"], color="r", ls="--", label=f"Molerus 1995 total {c['molerus']['h']:.0f}")
    a.axhline(c["molerus"]["h_pc"], color="r", ls=":", label=f"Molerus particle-conv. {c['molerus']['h_pc']:.0f}")
    a.axvline(r["discard"], color="gray", lw=0.8)
    a.set_ylabel("h = Q / (A (T_tube - T_bed)) [W/(m2 K)]")
    a.legend(fontsize=7, loc="lower right", ncol=2)
    a = ax[0, 1]
    a.plot(r["tau"], r["running"], label="running average (particles)")
    f, tol = r["running"][-1], SETTLED[0]
    a.axhspan(f * (1 - tol), f * (1 + tol), color="0.85", label=f"final +- {100 * tol:g} %")
    a.axvline(r["settled"][tol], color="gray", ls="--", label=f"within it after {r['settled'][tol]:.2g} s")
    a.set_xlabel("averaging window [s]")
    a.set_ylabel("h [W/(m2 K)]")
    a.legend(fontsize=7)
    a = ax[1, 0]
    cp = r["coupling"]
    a.plot(cp["time"], cp["dp"], lw=0.8, label="p(bottom) - p(top)")
    a.axhline(r["weight"], color="k", ls="--", label="bed weight / section")
    a.set_ylabel("[Pa]")
    a2 = a.twinx()
    a2.plot(cp["time"], 1e3 * cp["bed_height"], color="C2", lw=0.8, label="mean particle height")
    a2.set_ylabel("mean particle height [mm]", color="C2")
    a.legend(fontsize=7, loc="upper right")
    a = ax[1, 1]
    if r["angles"] is not None:
        g = r["angles"]
        a.plot(g["angle"], g["contact_W_m2"], label="contact")
        a.plot(g["angle"], g["gas_gap_W_m2"], label="gas gap")
        if np.any(np.asarray(g.get("radiation_W_m2", 0.0)) != 0):
            a.plot(g["angle"], g["radiation_W_m2"], label="radiation")
        a.set_xlabel("angle [deg]")
        a.set_ylabel("local h [W/(m2 K)]")
    else:
        a.plot(cp["time"], cp["T_particles"], label="particles (mean)")
        a.plot(cp["time"], cp["T_gas"], label="gas (mean)")
        a.set_ylabel("T [K]")
    a.legend(fontsize=7)
    for a in (ax[0, 0], ax[1, 0]) + ((ax[1, 1],) if r["angles"] is None else ()):
        a.set_xlabel("t [s]")
    _snapshot(fig.add_subplot(gs[:, 2]), r)
    for a in ax.ravel():
        a.grid(alpha=0.3)
    fig.suptitle(f"immersed tube: averaged over {r['discard']:g}-{r['t_end']:.3g} s")
    fig.tight_layout()
    from dem.outdir import PNG_SOFTWARE, claim_file
    from dem.output import atomic_write
    claim_file(str(path), "--plot")     # never replaces a user's file; listed in a run folder's manifest
    try:                                # the Software chunk marks the PNG as ours (replaced next time)
        atomic_write(str(path), lambda tmp: fig.savefig(tmp, dpi=110, format="png",
                                                        metadata={"Software": PNG_SOFTWARE}))
    finally:
        plt.close(fig)
    return path


def _snapshot(a, r):
    """The particles of the last VTK output, (x, z), coloured by temperature, and the tube."""
    files = glob.glob(str(Path(r["folder"]) / "vtk" / "particles_*.vtu"))
    if not files:
        a.axis("off")
        return
    import meshio
    last = max(files, key=lambda f: int(re.findall(r"(\d+)\.vtu$", f)[0]))
    m = meshio.read(last)
    x, T = m.points, m.point_data["temperature"]
    sc = a.scatter(1e3 * x[:, 0], 1e3 * x[:, 2], c=T, s=2.0, cmap="coolwarm", vmin=T.min(), vmax=T.max())
    p = r["props"]
    from matplotlib.patches import Circle
    a.add_patch(Circle(tuple(1e3 * np.array(p["tube_xz"])), 1e3 * p["tube_r"], color="k", fill=False))
    a.set_aspect("equal")
    a.set_xlabel("x [mm]")
    a.set_ylabel("z [mm]")
    a.set_ylim(0, 60)
    step = int(re.findall(r"(\d+)\.vtu$", last)[0])
    a.set_title(f"particles at t = {step * p['dem_dt']:.3g} s", fontsize=9)
    a.figure.colorbar(sc, ax=a, label="T [K]", shrink=0.6)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    g = ap.add_mutually_exclusive_group(required=True)
    g.add_argument("--out", help="run the case into this folder, then analyse it")
    g.add_argument("--analyse-only", metavar="FOLDER", help="analyse an earlier run folder")
    ap.add_argument("--end-time", type=float, help="end time of the run (default: the case's endTime)")
    ap.add_argument("--discard", type=float, default=0.3, help="start-up transient left out [s] (default 0.3)")
    ap.add_argument("--plot", help="figure path (default: FOLDER/immersed_tube.png)")
    ap.add_argument("--angles-from", type=float, default=None,
                    help="average the local coefficient by angle from this time on (default: --discard); "
                         "e.g. the restart of a run whose angle records began there")
    a = ap.parse_args(argv)
    folder = a.out or a.analyse_only
    if a.out:
        cmd = [sys.executable, "-m", "coupling.run", "run", str(CASE), "--out", a.out]
        if a.end_time is not None:
            cmd += ["--end-time", repr(a.end_time)]
        env = dict(os.environ, PYTHONPATH=str(ROOT) + os.pathsep + os.environ.get("PYTHONPATH", ""))
        rc = subprocess.call(cmd, env=env)
        if rc != 0:
            return rc
    r = analyse(folder, a.discard, angles_from=a.angles_from)
    print(report(r))
    print("figure:", plot(r, a.plot or Path(folder) / "immersed_tube.png"))
    return 0


if __name__ == "__main__":
    sys.exit(main())
