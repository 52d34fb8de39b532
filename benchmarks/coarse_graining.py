"""Coarse-grained thermal DEM against the fine bed (issue 15; docs/models.md "Coarse graining").

    python benchmarks/coarse_graining.py [--quick] [--out DIR]

**Effective conductivity of a packed bed between a hot and a cold wall.** For each factor
cg = 1, 2, 3, 4 a bed of glass beads of radius 1 mm (as parcels of radius cg mm standing for cg^3
beads each, the same real solid volume: 10,000 real beads; --quick: 2,000) is settled under
gravity in a box of 40 x 40 mm (--quick: 24 x 24 mm) with walls on its four sides and floor
(Hertz, E = 5 MPa, time step 1e-5 cg s), then frozen. The wall x = 0 is held at 400 K and the
wall x = L at 300 K, the rest adiabatic. The implicit heat step, whose fixed point is the steady
state of the conductance network for any step, gives the steady heat flow Q from the walls'
records; the bed's conductivity, walls included, is

    k_eff = Q L / (A (T_hot - T_cold)),   A = L x (bed height)

and the bulk one, from the temperature gradient of the middle 60 % (a least-squares line of
the parcels' temperatures against x), k_bulk = (Q / A) / |dT/dx|. Cases: direct conduction only
(Batchelor & O'Brien), indirect only (Cheng et al. 1999, Voronoi A), and both,
each at k_p / k_f = 38 (glass, 1 W/(m K), in air) and 385 (10 W/(m K)). The figure of merit is
the ratio to cg = 1; the issue's bound is 5 %.

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


def _walls(L, H, thermal=None):
    t = thermal or {}
    return [
        {"type": "plane", "name": "floor", "point": [0, 0, 0], "normal": [0, 0, 1], "material": "glass"},
        {"type": "plane", "name": "hot", "point": [0, 0, 0], "normal": [1, 0, 0], "material": "glass",
         **({"thermal": t["hot"]} if "hot" in t else {})},
        {"type": "plane", "name": "cold", "point": [L, 0, 0], "normal": [-1, 0, 0], "material": "glass",
         **({"thermal": t["cold"]} if "cold" in t else {})},
        {"type": "plane", "name": "back", "point": [0, 0, 0], "normal": [0, 1, 0], "material": "glass"},
        {"type": "plane", "name": "front", "point": [0, L, 0], "normal": [0, -1, 0], "material": "glass"},
    ]


def settle(cg, n_real, L, folder):
    """Positions (n, 3) of n_real / cg^3 parcels of radius cg R settled in the box; cached."""
    path = os.path.join(folder, f"packing_cg{cg:g}_n{n_real}_L{L:g}.npy")
    if os.path.exists(path):
        return np.load(path), 0.0
    from dem import Simulation
    n = int(round(n_real / cg ** 3))
    vol = n * 4.0 / 3.0 * math.pi * (cg * R) ** 3
    h_ins = vol / (L * L * 0.15)
    dt = 1e-5 * cg
    end = math.sqrt(2 * h_ins / 9.81) + 0.35
    sc = {"simulation": {"time_step": dt, "end_time": end, "gravity": [0, 0, -9.81], "seed": 7},
          "domain": {"min": [0, 0, 0], "max": [L, L, h_ins + 2 * cg * R]},
          "materials": [dict(MAT)],
          "particles": [{"material": "glass", "count": n, "radius": R, "coarse_graining": cg,
                         "region": {"type": "box", "min": [0, 0, 0], "max": [L, L, h_ins]}}],
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
    print(f"  settled cg {cg:g}: {n} parcels, {end:.2f} s in {el:.0f} s, kinetic energy at the end {ke:.2e} J",
          flush=True)
    return x, el


def conductivity(x, cg, L, direct, indirect, kp):
    """(k_eff walls included, k_bulk, thermal run time) at steady state."""
    from dem import Simulation
    H = float((x[:, 2] + cg * R).max())
    mat = dict(MAT, thermal_conductivity=kp)
    th = {"direct": direct, "indirect": indirect, "integrator": "implicit", "porosity": "local", "time_step": 1e6}
    walls = _walls(L, H, {"hot": {"condition": "fixed_temperature", "temperature": 400.0},
                          "cold": {"condition": "fixed_temperature", "temperature": 300.0}})
    sc = {"simulation": {"time_step": 1e-5, "end_time": 3e6, "mechanics": False, "gravity": [0, 0, -9.81]},
          "domain": {"min": [0, 0, 0], "max": [L, L, H + 2 * cg * R]}, "materials": [mat],
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
    A = L * H
    keff = Q * L / (A * 100.0)
    T = sim.state.temperature[:sim.state.n_owned]
    xx = sim.state.position[:sim.state.n_owned, 0]
    mid = (xx > 0.2 * L) & (xx < 0.8 * L)
    slope = np.polyfit(xx[mid], T[mid], 1)[0]
    kbulk = (Q / A) / abs(slope)
    return keff, kbulk, el, abs(q[1] + q[2]) / abs(q[1])


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--quick", action="store_true")
    ap.add_argument("--out", default=os.path.join("out", "coarse_graining"))
    a = ap.parse_args()
    n_real, L = (2000, 0.024) if a.quick else (10000, 0.040)
    cgs = (1, 2, 3, 4)
    print(f"Packed bed between a hot and a cold wall: {n_real} real beads of 1 mm radius in a {1e3 * L:g} mm box")
    packs = {cg: settle(cg, n_real, L, a.out)[0] for cg in cgs}
    cases = [("direct", "batchelor_obrien", "none"), ("indirect", "none", "cheng_1999_voronoi_a"),
             ("both", "batchelor_obrien", "cheng_1999_voronoi_a")]
    print("| case | k_p/k_f | cg | parcels | k_eff [W/(m K)] | / cg=1 | k_bulk [W/(m K)] | / cg=1 | "
          "steady (|Q_hot + Q_cold| / Q_hot) | run [s] |")
    print("|---|---|---|---|---|---|---|---|---|---|")
    worst = 0.0
    for name, d, i in cases:
        for kp in (1.0, 10.0):
            ref = None
            for cg in cgs:
                ke, kb, el, bal = conductivity(packs[cg], cg, L, d, i, kp)
                if ref is None:
                    ref = (ke, kb)
                worst = max(worst, abs(ke / ref[0] - 1))
                print(f"| {name} | {kp / AIR['conductivity']:.0f} | {cg} | {len(packs[cg])} | {ke:.4g} | "
                      f"{ke / ref[0]:.3f} | {kb:.4g} | {kb / ref[1]:.3f} | {bal:.1e} | {el:.1f} |", flush=True)
    print(f"largest |k_eff / k_eff(cg=1) - 1|: {100 * worst:.1f} %")


if __name__ == "__main__":
    main()
