"""Helpers shared by benchmarks/accuracy and benchmarks/stability: scene builders, the
settled packing (cached), Zehner-Schlunder, timing, the docs section writer."""
import math
import os
import re
import sys
import time

import numpy as np

HERE = os.path.dirname(os.path.abspath(__file__))
ROOT = os.path.dirname(os.path.dirname(HERE))
if ROOT not in sys.path:
    sys.path.insert(0, ROOT)

DOCS = os.path.join(ROOT, "docs")
CACHE = os.path.join(ROOT, "out", "bench_cache")

R = 1e-3
MAT = dict(name="p", density=2500.0, youngs_modulus=1e7, poisson_ratio=0.3, restitution=0.5,
           friction=0.3, thermal_conductivity=1.0, heat_capacity=840.0, emissivity=0.8)
AIR = dict(conductivity=0.026, density=1.2, viscosity=1.8e-5, heat_capacity=1005.0, temperature=300.0)


def scene(particles, thermal=None, walls=(), mech=False, dt=1e-5, end=1.0, domain=((-0.01,) * 3, (0.01,) * 3),
          gas=None, mats=None, gravity=(0.0, 0.0, 0.0), periodic=(False, False, False), contact=None,
          force=False, **simkw):
    sc = {"simulation": dict({"time_step": dt, "end_time": end, "mechanics": mech, "output_interval": end,
                              "gravity": list(gravity), "force": force}, **simkw),
          "domain": {"min": list(domain[0]), "max": list(domain[1]), "periodic": list(periodic)},
          "materials": mats or [dict(MAT)], "particles": particles, "walls": list(walls)}
    if thermal is not None:
        sc["thermal"] = thermal
    if gas is not None:
        sc["gas"] = gas
    if contact is not None:
        sc["contact"] = contact
    return sc


def timed_run(sim, end_time):
    """Run (kernels compiled/loaded before the clock starts); returns wall seconds."""
    sim.warmup()
    t0 = time.perf_counter()
    sim.run(end_time=end_time, progress=False)
    return time.perf_counter() - t0


def finite_state(sim):
    """True when every state array of the run is finite (position, velocities, temperature)."""
    st = sim.state
    arrs = [st.position, st.velocity, st.angular_velocity]
    if getattr(st, "temperature", None) is not None and sim.thermal is not None:
        arrs.append(st.temperature)
    return all(bool(np.all(np.isfinite(a))) for a in arrs)


def claim_cache():
    """out/bench_cache as the benchmarks' own folder (dem.outdir: new, empty or written by them;
    kept between runs). Returns its path."""
    from dem.outdir import claim_folder
    claim_folder(CACHE, restart=True, reuse=True, command="benchmarks cache", what="benchmark cache folder")
    return CACHE


def claim(path):
    from dem.outdir import claim as _claim
    _claim(path)


def cache_path(stem):
    """out/bench_cache/<stem>_<digest>.npz (the folder claimed for the benchmarks), the digest
    being that of the sources the compiled kernels are keyed on (dem.source_digest). A settling
    is chaotic (any change of the contact law's or the neighbour list's rounding gives another
    packing of the same statistics), so a bed cached by other sources is not the bed a clean
    clone makes: a cache keyed on the name alone once let tests pass here on the old packing
    that failed on a clean clone on the new one."""
    from dem import source_digest
    return os.path.join(claim_cache(), f"{stem}_{source_digest()[:12]}.npz")


def settled_packing(n=600, L=0.012, seed=11, log=print):
    """The random packing of tests/test_thermal_mechanisms.py: n spheres of 1 mm poured into a
    periodic L x L column and settled on a floor for 0.35 s (cached in out/bench_cache)."""
    from dem import Simulation
    path = cache_path(f"packing_{n}_{L:g}_{seed}")
    if os.path.exists(path):
        return np.load(path)["x"], L
    t0 = time.perf_counter()
    sc = {"simulation": {"time_step": 1e-5, "end_time": 0.35, "gravity": [0, 0, -9.81], "seed": seed},
          "domain": {"min": [0, 0, 0], "max": [L, L, 0.1], "periodic": [True, True, False]},
          "materials": [dict(MAT, friction=0.5, restitution=0.3)],
          "particles": [{"material": "p", "count": n, "radius": R,
                         "region": {"type": "box", "min": [0, 0, 0.001], "max": [L, L, 0.099]}}],
          "walls": [{"type": "plane", "point": [0, 0, 0], "normal": [0, 0, 1], "material": "p"}]}
    sim = Simulation.from_dict(sc)
    sim.run(progress=False)
    x = sim.state.position.copy()
    claim(path)
    np.savez(path, x=x)
    log(f"  settled packing of {n} spheres: {time.perf_counter() - t0:.1f} s (cached in {path})")
    return x, L


def zehner_schlunder(eps, kappa):
    """Zehner & Schlunder (1970) k_eff / k_f of a packed bed, no radiation, no flattening."""
    B = 1.25 * ((1 - eps) / eps) ** (10 / 9)
    s = math.sqrt(1 - eps)
    f = (1 - 1 / kappa) * B / (1 - B / kappa) ** 2 * math.log(kappa / B) - (B + 1) / 2 - (B - 1) / (1 - B / kappa)
    return 1 - s + 2 * s / (1 - B / kappa) * f


def packed_bed_scene(x, L, dt, thermal=None, mats=None, gas=None, end=8000.0):
    """Frozen packing between a hot floor (400 K) and a cold plate on the top layer (300 K)."""
    top = float(np.max(x[:, 2])) + R - 2e-5
    walls = [{"type": "plane", "name": "hot", "point": [0, 0, 0], "normal": [0, 0, 1], "material": "p",
              "thermal": {"condition": "fixed_temperature", "temperature": 400.0}},
             {"type": "plane", "name": "cold", "point": [0, 0, top], "normal": [0, 0, -1], "material": "p",
              "thermal": {"condition": "fixed_temperature", "temperature": 300.0}}]
    th = {"direct": "batchelor_obrien", "indirect": "voronoi_a", "time_step": dt, "initial_temperature": 350.0}
    th.update(thermal or {})
    return {"simulation": {"time_step": 1e-5, "end_time": end, "mechanics": False, "gravity": [0, 0, -9.81],
                           "output_interval": end},
            "domain": {"min": [0, 0, 0], "max": [L, L, 0.05], "periodic": [True, True, False]},
            "materials": mats or [dict(MAT)],
            "particles": [{"material": "p", "positions": x.tolist(), "radius": R}],
            "walls": walls, "gas": gas or dict(AIR), "thermal": th}, top


def k_eff(sim, L, top, t_settle, t_measure):
    """Steady effective conductivity: wall heat over [t_settle, t_settle + t_measure] and the
    mid-bed temperature gradient. Returns (k_eff, q_hot, q_cold, porosity of the mid bed)."""
    sim.run(end_time=t_settle, progress=False)
    e0 = sim.thermal.wtot.copy()
    sim.run(end_time=t_settle + t_measure, progress=False)
    e1 = sim.thermal.wtot.copy()
    q_hot = (e1[0] - e0[0]) / t_measure
    q_cold = (e1[1] - e0[1]) / t_measure
    z, T = sim.state.position[:, 2], sim.state.temperature
    mid = (z > 0.25 * top) & (z < 0.75 * top)
    grad = np.polyfit(z[mid], T[mid], 1)[0]
    eps = 1 - mid.sum() * 4 / 3 * math.pi * R ** 3 / (L * L * (z[mid].max() - z[mid].min()))
    return q_hot / (L * L) / -grad, q_hot, q_cold, eps


def replace_section(path, title, body):
    """Replace the markdown section starting with ``title`` (up to the next '## ' heading)
    in ``path``, or append it; the rest of the file is kept as it is."""
    text = open(path).read() if os.path.exists(path) else ""
    block = title.rstrip() + "\n\n" + body.strip() + "\n"
    pat = re.compile(r"^" + re.escape(title.rstrip()) + r"[ \t]*\n.*?(?=^## |\Z)", re.S | re.M)
    if pat.search(text):
        text = pat.sub(lambda m: block + "\n", text, count=1)
        text = text.rstrip() + "\n"
    else:
        text = text.rstrip() + "\n\n" + block
    with open(path, "w") as f:
        f.write(text)


def fmt(v, digits=3):
    if v is None:
        return "–"
    if isinstance(v, str):
        return v
    if isinstance(v, (int, np.integer)):
        return str(int(v))
    if not math.isfinite(v):
        return "unstable" if v != v or v > 0 else str(v)
    return f"{v:.{digits}g}"


def md_table(cols, rows):
    out = ["| " + " | ".join(cols) + " |", "|" + "---|" * len(cols)]
    for r in rows:
        out.append("| " + " | ".join(fmt(c) for c in r) + " |")
    return "\n".join(out)
