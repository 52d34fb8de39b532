"""Coarse-grained thermal DEM against the fine bed (issue 15; docs/models.md "Coarse graining").

    python benchmarks/coarse_graining.py [--quick] [--out DIR]

**Effective conductivity of a packed bed between a hot and a cold wall.** For each factor
cg = 1, 2, 3, 4 a bed of glass beads of radius 1 mm (as parcels of radius cg mm standing for cg^3
beads each) is settled under gravity between two walls L = 80 mm apart (x = 0 and x = L;
--quick: 40 mm), on a floor, periodic along y over 12 parcel diameters (24 cg mm), with 8,000 real
beads per 24 mm of depth (--quick: 2,000), so that every bed holds the same real solid per wall
area (Hertz, E = 5 MPa, time step 1e-5 cg s); then frozen. The periodic depth grows with cg: over
a fixed 24 mm (three parcel diameters at cg = 4) the periodic images ordered the parcel packings,
and their coordination number rose from 5.5 (fine bed) to 5.8, 6.1 and 6.4. At 12 parcel diameters
it is 5.55, 5.63, 5.66, 5.60. The wall x = 0 is held at 400 K and the wall x = L at 300 K, the floor
is adiabatic. The implicit heat step, whose fixed point is the steady state of the conductance
network for any step, gives the steady heat flow Q from the walls' records. The figures of merit,
as ratios to cg = 1: the effective conductivity of the bed, Q / (L_y |dT/dx|) with dT/dx the slope
of a least-squares line of the parcels' temperatures against x over the middle 60 % (per metre
of depth), and the bed's conductance with the walls, G = Q / (L_y (T_hot - T_cold)) (per metre of
depth), which adds the walls' contact resistance and the layered packing next to each wall (a
layer of a few parcel diameters: cg times thicker for parcels); for scale, k_eff = G L / H with H
the highest particle top. Cases: direct conduction only (Batchelor & O'Brien), indirect only
(Cheng et al. 1999, Voronoi A), and both, each at k_p / k_f = 38 (glass, 1 W/(m K), in air) and 385
(10 W/(m K)). The issue's bound is 5 %. --quick is a smoke run of the script (a few minutes), not
a verification: its cg = 4 bed is 5 parcels wide and its middle 3, and its ratios scatter by
10 %.

Prints particle counts, the settle and thermal run times, and the table; writes the packings
into --out (default out/coarse_graining) so that a second run reuses them.
"""
import argparse
import math
import os
import sys
import time

HERE = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, os.path.dirname(HERE))

import numpy as np  # noqa: E402

R = 1e-3
RHO = 2500.0
MAT = dict(name="glass", density=RHO, youngs_modulus=5e6, poisson_ratio=0.3, restitution=0.3, friction=0.3,
           thermal_conductivity=1.0, heat_capacity=840.0)
AIR = dict(conductivity=0.026, density=1.2, viscosity=1.8e-5, heat_capacity=1005.0, temperature=300.0)


LY1 = 0.024   # periodic depth of the fine bed: 12 bead diameters
NSEED = 4     # packings per bed


def depth(cg):
    """The periodic depth: 12 parcel diameters at every cg (a depth of a few parcel diameters orders
    the packing through its periodic images: at 24 mm the coordination number rose from 5.5 to 5.8
    (cg = 2) and 6.4 (cg = 4); dem check warns below 10)."""
    return LY1 * cg


def _walls(L, H, thermal=None):
    t = thermal or {}
    return [
        {"type": "plane", "name": "floor", "point": [0, 0, 0], "normal": [0, 0, 1], "material": "glass"},
        {"type": "plane", "name": "hot", "point": [0, 0, 0], "normal": [1, 0, 0], "material": "glass",
         **({"thermal": t["hot"]} if "hot" in t else {})},
        {"type": "plane", "name": "cold", "point": [L, 0, 0], "normal": [-1, 0, 0], "material": "glass",
         **({"thermal": t["cold"]} if "cold" in t else {})},
    ]


def settle(cg, n_real, L, folder, seed=7):
    """Positions (n, 3) of n_real cg / cg^3 parcels of radius cg R (n_real real beads per 24 mm of
    depth) settled in the box of depth(cg); cached."""
    LY = depth(cg)
    path = os.path.join(folder, f"packing_cg{cg:g}_n{n_real}_L{L:g}_depth{1e3 * LY:g}mm_s{seed}"
                        + ".npy")
    if os.path.exists(path):
        return np.load(path), 0.0
    from dem import Simulation
    n = int(round(n_real * cg / cg ** 3))
    vol = n * 4.0 / 3.0 * math.pi * (cg * R) ** 3
    h_ins = vol / (L * LY * 0.15)
    dt = 1e-5 * cg
    end = math.sqrt(2 * h_ins / 9.81) + 0.35
    sc = {"simulation": {"time_step": dt, "end_time": end, "gravity": [0, 0, -9.81], "seed": seed},
          "domain": {"min": [0, 0, 0], "max": [L, LY, h_ins + 2 * cg * R], "periodic": [False, True, False]},
          "materials": [dict(MAT)],
          "particles": [{"material": "glass", "count": n, "radius": R, "coarse_graining": cg,
                         "region": {"type": "box", "min": [0, 0, 0], "max": [L, LY, h_ins]}}],
          "walls": _walls(L, h_ins), "output": {"vtk": False}}
    sim = Simulation.from_dict(sc)
    t0 = time.perf_counter()
    sim.step(int(round(end / dt)))
    el = time.perf_counter() - t0
    ke = sum(sim.state.kinetic_energy())
    x = sim.state.position[:sim.state.n_owned].copy()
    order = np.argsort(sim.state.id[:sim.state.n_owned])
    x = x[order]
    os.makedirs(folder, exist_ok=True)
    np.save(path, x)
    print(f"  settled cg {cg:g} (seed {seed}): {n} parcels, {end:.2f} s in {el:.0f} s, kinetic energy at the end {ke:.2e} J",
          flush=True)
    return x, el


def packing(x, cg, L):
    """(bed top H, solid fraction, coordination number, mean real contact radius
    sqrt(R* delta / cg)) of a packing; the last three of the parcels in the middle of the bed
    (0.2-0.8 L across, 0.2-0.7 H high; the Hertz contact radius of the real particles: their
    overlap is the parcel's / cg)."""
    from scipy.spatial import cKDTree
    Rp = cg * R
    LY = depth(cg)
    n = len(x)
    xs = np.concatenate([x, x + [0, LY, 0], x - [0, LY, 0]])   # periodic along y
    pairs = np.array(sorted(cKDTree(xs).query_pairs(2 * Rp)))
    pairs = pairs[pairs[:, 0] < n]
    d = np.linalg.norm(xs[pairs[:, 0]] - xs[pairs[:, 1]], axis=1)
    H = float((x[:, 2] + Rp).max())
    mid = (x[:, 0] > 0.2 * L) & (x[:, 0] < 0.8 * L) & (x[:, 2] > 0.2 * H) & (x[:, 2] < 0.7 * H)
    phi = mid.sum() * 4 / 3 * math.pi * Rp ** 3 / (0.6 * L * LY * 0.5 * H)
    ends = np.c_[pairs[:, 0], pairs[:, 1] % n]
    z = (mid[ends[:, 0]].sum() + mid[ends[:, 1]].sum()) / mid.sum()
    inm = mid[ends[:, 0]]
    return H, float(phi), float(z), float(np.sqrt(0.5 * R * (2 * Rp - d[inm]) / cg).mean())


def conductivity(x, cg, L, direct, indirect, kp):
    """(G = Q / dT per metre of depth, walls included; Q / |dT/dx| of the middle per metre of depth;
    k_eff; run time; steadiness)."""
    from dem import Simulation
    LY = depth(cg)
    H = float((x[:, 2] + cg * R).max())
    mat = dict(MAT, thermal_conductivity=kp)
    th = {"direct": direct, "indirect": indirect, "integrator": "implicit", "porosity": "local", "time_step": 1e6}
    walls = _walls(L, H, {"hot": {"condition": "fixed_temperature", "temperature": 400.0},
                          "cold": {"condition": "fixed_temperature", "temperature": 300.0}})
    sc = {"simulation": {"time_step": 1e-5, "end_time": 3e6, "mechanics": False, "gravity": [0, 0, -9.81]},
          "domain": {"min": [0, 0, 0], "max": [L, LY, H + 2 * cg * R], "periodic": [False, True, False]},
          "materials": [mat],
          "particles": [{"material": "glass", "positions": x.tolist(), "radius": R, "coarse_graining": cg,
                         "temperature": 350.0}],
          "walls": walls, "thermal": th, "gas": dict(AIR, porosity=0.4), "output": {"vtk": False}}
    sim = Simulation.from_dict(sc)
    t0 = time.perf_counter()
    sim.step(2)   # converged by the second step (implicit Euler at dt = 1e6 s >> the bed's time)
    e1 = sim.state.wtot.copy()
    sim.step(1)
    el = time.perf_counter() - t0
    q = (sim.state.wtot - e1) / sim.dt           # W into the particles per wall, last step
    Q = 0.5 * (q[1] - q[2])                      # the hot wall gives, the cold wall takes
    A = LY * H
    G = Q / 100.0 / LY
    T = sim.state.temperature[:sim.state.n_owned]
    xx = sim.state.position[:sim.state.n_owned, 0]
    mid = (xx > 0.2 * L) & (xx < 0.8 * L)
    slope = np.polyfit(xx[mid], T[mid], 1)[0]
    return G, Q / abs(slope) / LY, G * LY * L / A, el, abs(q[1] + q[2]) / abs(q[1])


# ----------------------------------------------------------------------------- bubbling bed
CASE = os.path.join(os.path.dirname(HERE), "openfoam_cases", "fluidized_bed_heating")
N_FINE = 24000     # the main case's 3,000 beads of 2 mm as beads of 1 mm: the same bed mass
CFD_STEP = 5e-4    # the main case's


def bubbling_case(dest, cg, end, own=False):
    """The main case (openfoam_cases/fluidized_bed_heating) with beads of half the size (d = 0.95-
    1.05 mm, 24,000 of them, the same bed mass) as parcels of factor cg, fluidized at 2 U_mf of
    1 mm beads (Wen & Yu), to ``end``; DEM step 5e-6 cg s (100 / cg DEM steps per CFD step)."""
    import re
    import shutil
    from coupling.drag import wen_yu_1966_umf
    if os.path.exists(dest):
        shutil.rmtree(dest)      # this benchmark's own case folder
    shutil.copytree(CASE, dest, ignore=shutil.ignore_patterns("README.md"))
    u = 2.0 * wen_yu_1966_umf(1e-3, 2500.0, 1.2, 1.8e-5, 9.81)
    t = open(os.path.join(dest, "dem.toml")).read()
    a = 'count = 3000\nradius = { distribution = "uniform", min = 0.00095, max = 0.00105 }\n'
    assert a in t
    n = int(round(N_FINE / cg ** 3))
    t = t.replace(a, f'count = {n}\nradius = {{ distribution = "uniform", min = 0.000475, max = 0.000525 }}\n'
                     f'coarse_graining = {float(cg)!r}\n')
    t = t.replace("vtk = true", "vtk = false")
    if own:   # the parcels' own heat laws: what a code without the thermal scaling computes
        assert 'convection = "ranz_marshall"\n' in t
        t = t.replace('convection = "ranz_marshall"\n', 'convection = "ranz_marshall"\nparcel_heat = "own"\n')
    # the DEM step: a tenth of the Hertz collision time of a 1 mm bead at 1 m/s (9.8e-5 s), which
    # grows with the parcel's radius; the CFD step stays 5e-4 s
    k = {1: 100, 2: 50, 3: 34, 4: 25}[int(cg)]
    assert "time_step = 1e-5\n" in t
    t = t.replace("time_step = 1e-5\n", f"time_step = {CFD_STEP / k!r}\n")
    open(os.path.join(dest, "dem.toml"), "w").write(t)
    f = os.path.join(dest, "coupling.toml")
    s = open(f).read()
    assert "coupling_interval = 50 " in s
    open(f, "w").write(s.replace("coupling_interval = 50 ", f"coupling_interval = {k} "))
    for name in ("0/U",):
        f = os.path.join(dest, name)
        s = open(f).read()
        s = s.replace("uniform (0 0 2.0)", f"uniform (0 0 {u!r})")
        open(f, "w").write(s)
    f = os.path.join(dest, "system", "controlDict")
    s = open(f).read()
    s = re.sub(r"\nendTime\s+[^;]+;", f"\nendTime         {end!r};", s)
    s = re.sub(r"\nwriteInterval\s+[^;]+;", "\nwriteInterval   100000;", s)
    open(f, "w").write(s)
    return n, u


def bubbling(cg, folder, end, own=False):
    """Run the bubbling bed at factor cg to ``end`` (an earlier, shorter run in the same folder is
    continued from its last checkpoint: ``coupling run --restart --end-time``); returns
    (coupling.csv columns, parcels, wall time per simulated second of the last leg)."""
    import json
    import subprocess
    tag = f"cg{cg:g}" + ("_own" if own else "")
    case = os.path.join(folder, f"bubbling_case_{tag}")
    out = os.path.join(folder, f"bubbling_{tag}")
    n, u = bubbling_case(case, cg, end, own)
    csv = os.path.join(out, "coupling.csv")
    done = 0.0
    if os.path.exists(os.path.join(out, "final.npz")):
        done = float(np.genfromtxt(csv, delimiter=",", names=True)["time"][-1])
    if done < end - 1e-9:
        cmd = [sys.executable, "-m", "coupling.run", "run", case, "--out", out]
        cmd += ["--restart", "--end-time", repr(end)] if done > 0 else ["--overwrite"]
        t0 = time.perf_counter()
        r = subprocess.run(cmd, capture_output=True, text=True, cwd=os.path.dirname(HERE))
        if r.returncode != 0:
            raise SystemExit(f"cg {cg}: coupling run failed\n{r.stdout[-3000:]}\n{r.stderr[-3000:]}")
        print(f"  bubbling bed {tag}: {n} parcels at {u:.3f} m/s, {done:g} to {end:g} s in "
              f"{time.perf_counter() - t0:.0f} s", flush=True)
    c = np.genfromtxt(csv, delimiter=",", names=True)
    with open(os.path.join(out, "timings.json")) as fh:   # the last leg's
        tj = json.load(fh)
    return c, n, float(tj["wall_total"]) / (tj["coupling_steps"] * CFD_STEP)


def window_mean(t, y, t0, batch=0.25):
    """Mean of y over t >= t0 and its standard error from batch means (batches of ``batch`` s,
    longer than the bubbles' period, so that the batch means are nearly independent)."""
    m = t >= t0 - 1e-12
    t, y = t[m], y[m]
    k = np.floor((t - t0) / batch + 1e-9).astype(int)
    nb = int(k.max()) + (1 if np.sum(k == k.max()) * (t[1] - t[0]) >= 0.5 * batch else 0)
    means = np.array([y[k == i].mean() for i in range(nb)])
    return float(y.mean()), float(means.std(ddof=1) / math.sqrt(nb)) if nb > 1 else float("nan")


def bubbling_table(folder, end, cgs=(1, 2, 3), t_avg=0.3):
    runs = [(cg, False) for cg in cgs] + [(cg, True) for cg in cgs if cg > 1]
    res = {k: bubbling(k[0], folder, end, k[1]) for k in runs}
    print(f"Bubbling bed heated by the gas: the main case with beads of 1 mm ({N_FINE} of them at cg = 1), "
          f"to {end:g} s; time means over t >= {t_avg:g} s +- standard error (batch means of 0.25 s); own: the "
          f"parcels' own heat laws, no thermal scaling")
    print("| cg | parcel heat | parcels | wall per simulated s [s] | T rise at the end [K] | / cg=1 | largest over t >= 0.1 s | "
          "heat to the particles [J] | / cg=1 | mean particle height [mm] | / cg=1 | std [mm] | dp [Pa] | / cg=1 |")
    print("|---|---|---|---|---|---|---|---|---|---|---|---|---|---|")
    wp = {}
    ref = None
    c1 = res[runs[0]][0]
    for key in runs:
        cg = key[0]
        c, n, wall = res[key]
        late = c["time"] >= t_avg - 1e-12
        h, she = window_mean(c["time"], 1e3 * c["bed_height"], t_avg)
        dp, sdp = window_mean(c["time"], c["dp"], t_avg)
        row = (c["T_particles"][-1] - c["T_particles"][0], c["E_conv_particles"][-1], h, dp)
        ref = ref or (row, she, sdp)
        # the mean temperature rise against the fine bed's at the same output times
        t1 = c1["time"] >= 0.1 - 1e-12
        rise1 = c1["T_particles"][t1] - c1["T_particles"][0]
        rise = np.interp(c1["time"][t1], c["time"], c["T_particles"]) - c["T_particles"][0]
        dev = float(np.max(np.abs(rise / rise1 - 1.0)))
        wp[key] = (wall, dev)
        eh = math.hypot(she / h, ref[1] / ref[0][2]) * h / ref[0][2]
        ed = math.hypot(sdp / dp, ref[2] / ref[0][3]) * dp / ref[0][3]
        print(f"| {cg} | {'own' if key[1] else 'scaled'} | {n} | {wall:.0f} | {row[0]:.4f} | {row[0] / ref[0][0]:.3f} | "
              f"{100 * dev:.1f} % | {row[1]:.4g} | {row[1] / ref[0][1]:.3f} | "
              f"{h:.2f} +- {she:.2f} | {h / ref[0][2]:.3f} +- {eh:.3f} | {np.std(1e3 * c['bed_height'][late]):.2f} | "
              f"{dp:.1f} +- {sdp:.1f} | {dp / ref[0][3]:.3f} +- {ed:.3f} |", flush=True)
    plot_work_precision(wp, os.path.join(os.path.dirname(HERE), "docs", "coarse_graining.png"))
    return res


def plot_work_precision(wp, path):
    """Run time against the error of the bed's heating (the largest deviation of the mean
    temperature rise from the fine bed's after 0.1 s), scaled and own heat laws."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    fig, ax = plt.subplots(figsize=(6, 4))
    for own, style, label in ((False, "o-", "scaled heat laws"), (True, "s--", "own heat laws (no thermal scaling)")):
        keys = sorted(k for k in wp if k[1] == own and k[0] > 1)
        ax.plot([wp[k][0] for k in keys], [wp[k][1] for k in keys], style, label=label)
        for k in keys:
            ax.annotate(f"cg {k[0]}", (wp[k][0], wp[k][1]), textcoords="offset points", xytext=(4, 4))
    fine = [v[0] for k, v in wp.items() if k[0] == 1]
    if fine:
        ax.axvline(fine[0], color="k", lw=0.8, label=f"the fine bed (cg = 1, the reference): {fine[0]:.0f} s")
    ax.axhline(0.03, color="grey", lw=0.8, ls=":", label="3 % (issue 15's bound)")
    ax.set_xscale("log")
    ax.set_yscale("log")
    ax.set_xlabel("wall time per simulated second of the bubbling bed [s]")
    ax.set_ylabel("largest |dT/dT_fine - 1| of the mean rise, t >= 0.1 s")
    ax.legend(fontsize=8)
    ax.set_title("Coarse graining: run time against the error of the bed's heating", fontsize=9)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    print(f"wrote {path}")


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--quick", action="store_true")
    ap.add_argument("--out", default=os.path.join("out", "coarse_graining"))
    ap.add_argument("--bubbling", type=float, default=None, metavar="END",
                    help="only the bubbling bed, to END s")
    a = ap.parse_args()
    if a.bubbling:
        bubbling_table(a.out, a.bubbling)
        return
    n_real, L = (2000, 0.040) if a.quick else (8000, 0.080)
    cgs = (1, 2, 3, 4)
    print(f"Packed bed between a hot and a cold wall: {n_real} real beads of 1 mm radius per {1e3 * LY1:g} mm of "
          f"depth, walls {1e3 * L:g} mm apart, periodic over 12 parcel diameters "
          f"({', '.join(f'{1e3 * depth(cg):g}' for cg in cgs)} mm)")
    # several packings of each bed (a bed of a few hundred parcels is one sample of a random packing:
    # its conductance scatters by a few per cent from seed to seed)
    seeds = {cg: tuple(range(7, 7 + NSEED)) for cg in cgs}
    packs = {(cg, sd): settle(cg, n_real, L, a.out, sd)[0] for cg in cgs for sd in seeds[cg]}
    cases = [("direct", "batchelor_obrien", "none"), ("indirect", "none", "cheng_1999_voronoi_a"),
             ("both", "batchelor_obrien", "cheng_1999_voronoi_a")]
    for cg in cgs:
        phis, tops, zs, rcs = [], [], [], []
        for sd in seeds[cg]:
            H, phi, z, rc = packing(packs[cg, sd], cg, L)
            tops.append(H)
            phis.append(phi)
            zs.append(z)
            rcs.append(rc)
        print(f"  cg {cg}: {len(packs[cg, seeds[cg][0]])} parcels x {len(seeds[cg])} packings, bed top "
              f"{1e3 * np.mean(tops):.1f} mm, middle: solid fraction {np.mean(phis):.3f} "
              f"(range {min(phis):.3f}-{max(phis):.3f}), coordination number {np.mean(zs):.2f}, mean real contact "
              f"radius {1e6 * np.mean(rcs):.2f} um")
    print("| case | k_p/k_f | cg | G = Q/dT per depth [W/(m K)] | / cg=1 (+- std. error) | "
          "Q/|dT/dx| middle per depth [W/K] | / cg=1 | "
          "k_eff [W/(m K)] | steady (|Q_hot + Q_cold| / Q_hot) |")
    print("|---|---|---|---|---|---|---|---|---|")
    worst, worst_g = 0.0, 0.0
    for name, d, i in cases:
        for kp in (1.0, 10.0):
            ref = None
            for cg in cgs:
                r = np.array([conductivity(packs[cg, sd], cg, L, d, i, kp) for sd in seeds[cg]])
                G, B, ke, bal = r[:, 0].mean(), r[:, 1].mean(), r[:, 2].mean(), r[:, 4].max()
                if ref is None:
                    ref = (G, B)
                se = r[:, 0].std(ddof=1) / math.sqrt(len(r)) / ref[0] if len(r) > 1 else 0.0
                seb = r[:, 1].std(ddof=1) / math.sqrt(len(r)) / ref[1] if len(r) > 1 else 0.0
                worst = max(worst, abs(B / ref[1] - 1))
                worst_g = max(worst_g, abs(G / ref[0] - 1))
                print(f"| {name} | {kp / AIR['conductivity']:.0f} | {cg} | {G:.4g} | {G / ref[0]:.3f} +- {se:.3f} | "
                      f"{B:.4g} | {B / ref[1]:.3f} +- {seb:.3f} | {ke:.4g} | {bal:.1e} |", flush=True)
    print(f"largest deviation from cg = 1 (means over the packings): effective conductivity of the middle "
          f"{100 * worst:.1f} %, conductance with the walls {100 * worst_g:.1f} %")


if __name__ == "__main__":
    main()
