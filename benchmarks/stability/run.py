"""Stability map: stress sweeps that find where the DEM and thermal runs stop being stable,
and which guard stops them.

    python benchmarks/stability/run.py [--quick] [--no-docs]

Sweeps: mechanical step up to and past the Rayleigh / Hertz limits (simulation.force =
true), thermal step past the network limit (euler vs exponential), k_p/k_f from 1e-2 to
1e4 with every indirect model, temperature spans up to 1800 K with radiation (zhou_2009),
impacts up to 10 m/s on soft particles (E = 1e6, 1e7), dense beds with large initial
overlaps. Each run records whether `check()` refuses the step (SceneError), how the run
ended (completed / the guard that stopped it and its message) and whether the state
arrays are finite; a completed run with a non-finite or out-of-bounds state is a failure
(exit status 1). Writes the section "## Stability map" of docs/benchmarks.md.
"""
import argparse
import math
import os
import platform
import sys
import time

import numpy as np

HERE = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, os.path.dirname(os.path.dirname(HERE)))

from benchmarks.accuracy.common import (AIR, DOCS, MAT, R, fmt, md_table, packed_bed_scene,  # noqa: E402
                                        replace_section, scene, settled_packing, finite_state)

SECTION = "## Stability map"
RECORDS = []


def log(*a):
    print(*a, flush=True)


def guard_of(msg):
    if "overlap by" in msg and "initially" not in msg:
        return "overlap guard"
    if "non-finite velocity" in msg:
        return "non-finite velocity guard"
    if "reached temperature" in msg:
        return "temperature guard"
    if "left the domain" in msg:
        return "domain guard"
    if "initially" in msg:
        return "initial-overlap check (SceneError)"
    if "time_step" in msg:
        return "step-limit check (SceneError)"
    return "other"


def attempt(group, setting, sc, end_time, bounds=None, extra=""):
    """check() without force, then the run (force = true); one record."""
    from dem import Simulation
    from dem.scene import SceneError
    from dem.simulation import SimulationError
    rec = dict(group=group, setting=setting, check="ok", outcome="", guard="", message="", finite=None,
               bounded=None, extra=extra, seconds=0.0)
    forced = sc["simulation"].get("force", False)
    sc["simulation"]["force"] = False
    try:
        sim = Simulation.from_dict(sc)
        rep = sim.check()
        if rep.get("warnings"):
            rec["check"] = "warning: " + "; ".join(rep["warnings"])
    except SceneError as exc:
        rec["check"] = "refused"
        rec["check_message"] = str(exc)
        if "time_step" not in str(exc) or not forced:
            rec["guard"] = guard_of(str(exc))
            rec["message"] = str(exc)
            rec["outcome"] = "not run"
            RECORDS.append(rec)
            log(f"  {group} | {setting}: refused: {str(exc)[:200]}")
            return rec
    sc["simulation"]["force"] = forced
    t0 = time.perf_counter()
    try:
        sim = Simulation.from_dict(sc)
        sim.run(end_time=end_time, progress=False)
        rec["outcome"] = "completed"
    except SimulationError as exc:
        rec["outcome"] = "stopped"
        rec["guard"] = guard_of(str(exc))
        rec["message"] = str(exc)
    except SceneError as exc:
        rec["outcome"] = "not run"
        rec["guard"] = guard_of(str(exc))
        rec["message"] = str(exc)
        RECORDS.append(rec)
        return rec
    rec["seconds"] = time.perf_counter() - t0
    rec["finite"] = finite_state(sim)
    if bounds is not None and sim.thermal is not None and rec["finite"]:
        T = sim.state.temperature
        lo, hi = bounds
        rec["bounded"] = bool(T.min() >= lo - 1e-6 * abs(lo) and T.max() <= hi + 1e-6 * abs(hi))
        rec["extra"] = (extra + " " if extra else "") + f"T in [{T.min():.5g}, {T.max():.5g}] K"
    rec["sim"] = sim
    RECORDS.append(rec)
    log(f"  {group} | {setting}: {rec['seconds']:.2f} s {rec['outcome']} {rec['guard']} finite={rec['finite']} bounded={rec['bounded']} "
        f"{rec['extra']} {rec['message'][:160]}")
    return rec


# ----------------------------------------------------------------------------- sweeps
def mech_step(quick, x, L):
    """Settled bed restarted from rest (gravity, Hertz-Mindlin) with dt = f t_R, and a pair
    impact at 1 m/s with dt = f t_H."""
    from dem.contact.damping import rayleigh_time, hertz_collision_time
    G = MAT["youngs_modulus"] / (2 * (1 + MAT["poisson_ratio"]))
    tR = rayleigh_time(R, MAT["density"], G, MAT["poisson_ratio"])
    fr = [0.1, 0.3, 0.5, 1.0, 2.0, 5.0] if quick else [0.1, 0.3, 0.5, 0.75, 1.0, 1.5, 2.0, 5.0, 10.0]
    for f in fr:
        dt = f * tR
        sc = scene([{"material": "p", "positions": x.tolist(), "radius": R}], mech=True, dt=dt, end=1.0,
                   domain=((0, 0, 0), (L, L, 0.1)), periodic=(True, True, False), gravity=(0, 0, -9.81),
                   walls=[{"type": "plane", "point": [0, 0, 0], "normal": [0, 0, 1], "material": "p"}],
                   force=True, mats=[dict(MAT, friction=0.5, restitution=0.3)])
        attempt("mechanical step, settled bed (600, E = 1e7)", f"dt = {f:g} t_R", sc,
                end_time=max(200, round(0.01 / dt)) * dt)
    m = 4 / 3 * math.pi * R ** 3 * MAT["density"]
    estar = MAT["youngs_modulus"] / (2 * (1 - MAT["poisson_ratio"] ** 2))
    tH = hertz_collision_time(m / 2, R / 2, estar, 1.0)
    for f in ([0.1, 0.3, 0.5, 1.0, 2.0] if quick else [0.05, 0.1, 0.2, 0.3, 0.5, 0.75, 1.0, 2.0]):
        dt = f * tH
        sc = scene([{"material": "p", "positions": [[-R - 1e-5, 0, 0], [R + 1e-5, 0, 0]], "radius": R,
                     "velocities": [[0.5, 0, 0], [-0.5, 0, 0]]}], mech=True, dt=dt, end=1.0, force=True)
        attempt("mechanical step, pair impact 1 m/s (E = 1e7)", f"dt = {f:g} t_H", sc,
                end_time=math.ceil(5 * tH / dt) * dt)


def thermal_step(quick, x, L):
    """Frozen packing (hot floor 400 K, cold top 300 K), dt = f x the network limit."""
    from dem import Simulation
    sc, top = packed_bed_scene(x, L, 1.0, {"integrator": "euler"})
    lim = Simulation.from_dict(sc).check()["network_step_limit"]
    fr = [0.5, 1.0, 2.0, 4.0, 10.0, 100.0] if quick else [0.5, 0.9, 1.0, 1.5, 2.0, 3.0, 4.0, 10.0, 100.0]
    for integ in ("euler", "exponential"):
        for f in fr:
            dt = f * lim
            sc, top = packed_bed_scene(x, L, dt, {"integrator": integ})
            attempt(f"thermal step, frozen bed (network limit {lim:.3g} s)", f"{integ}, dt = {f:g} x limit", sc,
                    end_time=300 * dt, bounds=(300.0, 400.0))


def conductivity_ratio(quick, x, L):
    """k_p/k_f from 1e-2 to 1e4 (k_p = 1) with each indirect model, default integrator."""
    models = ["voronoi_a", "voronoi_b", "gan_2016_voronoi_a", "chen_2019_voronoi_b",
              "musser_2011_surrounding_layer", "rong_horio_1999_surrounding_layer", "vargas_mccarthy_2002"]
    if quick:
        models = models[:2] + models[4:6]
    ratios = [1e-2, 1.0, 1e2, 1e4] if quick else [1e-2, 1e-1, 1.0, 10.0, 1e2, 1e3, 1e4]
    for mdl in models:
        for ratio in ratios:
            th = {"indirect": mdl}
            if mdl.startswith("rong_horio"):
                th["direct"] = "none"
            sc, top = packed_bed_scene(x, L, 20.0, th, gas=dict(AIR, conductivity=1.0 / ratio))
            attempt("k_p/k_f, frozen bed (exponential, dt = 20 s)", f"{mdl}, k_p/k_f = {ratio:g}", sc,
                    end_time=100 * 20.0, bounds=(300.0, 400.0))


def radiation(quick, x, L):
    """Hot floor at 600..1800 K, cold top 300 K, radiation zhou_2009 + conduction, frozen, 200 s;
    the notes give the error of the hottest particle against Euler at dt = 0.1 s."""
    spans = [600.0, 1000.0, 1500.0, 1800.0] if not quick else [1000.0, 1800.0]
    dts = [0.1, 1.0, 2.0, 5.0, 10.0] if quick else [0.1, 0.5, 1.0, 2.0, 5.0, 10.0, 20.0]
    for Th in spans:
        ref = None
        for integ in ("euler", "exponential"):
            for dt in dts:
                sc, top = packed_bed_scene(x, L, dt, {"integrator": integ, "radiation": "zhou_2009"})
                sc["walls"][0]["thermal"]["temperature"] = Th
                sc["thermal"]["initial_temperature"] = 300.0
                rec = attempt("radiation zhou_2009, frozen bed, 200 s", f"floor {Th:g} K, {integ}, dt = {dt:g} s",
                              sc, end_time=200.0, bounds=(300.0, Th))
                if rec["outcome"] != "completed":
                    continue
                tmax = float(rec["sim"].state.temperature.max())
                if ref is None:
                    ref = tmax
                rec["extra"] += f"; hottest particle off by {100 * (tmax - ref) / (ref - 300.0):+.2g} % of its rise"


def impacts(quick):
    """Sphere onto a wall at up to 10 m/s, E = 1e6 and 1e7, dt = 0.05 t_H at the impact speed."""
    from dem.contact.damping import hertz_collision_time
    for E in (1e6, 1e7):
        for v in ([0.1, 1.0, 3.0, 10.0] if quick else [0.1, 0.3, 1.0, 2.0, 3.0, 5.0, 10.0]):
            m = 4 / 3 * math.pi * R ** 3 * MAT["density"]
            estar = E / (2 * (1 - MAT["poisson_ratio"] ** 2))
            tH = hertz_collision_time(m, R, estar, v)
            dmax = (15 * m * v * v / (16 * estar * math.sqrt(R))) ** 0.4
            dt = 0.05 * tH
            mat = dict(MAT, youngs_modulus=E)
            sc = scene([{"material": "p", "positions": [[0, 0, R * 1.01]], "radius": R, "velocities": [[0, 0, -v]]}],
                       {"direct": "batchelor_obrien", "initial_temperature": 300.0}, mech=True, dt=dt,
                       end=1.0, mats=[mat], domain=((-0.01, -0.01, -0.01), (0.01, 0.01, 0.05)),
                       walls=[{"type": "plane", "point": [0, 0, 0], "normal": [0, 0, 1], "material": "p",
                               "thermal": {"condition": "fixed_temperature", "temperature": 400.0}}])
            rec = attempt(f"wall impact, E = {E:g} Pa (dt = 0.05 t_H(v))", f"v = {v:g} m/s", sc,
                          end_time=math.ceil((0.01 * R / v + 3 * tH) / dt) * dt, bounds=(300.0, 400.0),
                          extra=f"Hertz max overlap {dmax / R:.3g} R")
            if rec.get("sim") is not None and rec["outcome"] == "completed":
                rec["extra"] += f", rebound {rec['sim'].state.velocity[0, 2] / v:.3g} v"


def dense(quick, x, L):
    """The settled bed with radii inflated by s: initial overlaps ~2s R, gravity, heat on."""
    ss = [0.01, 0.03, 0.1, 0.2, 0.5] if quick else [0.01, 0.02, 0.03, 0.05, 0.1, 0.2, 0.3, 0.5, 0.7]
    for guards in ("default", "raised"):
        for s in ss:
            sc = scene([{"material": "p", "positions": x.tolist(), "radius": R * (1 + s)}],
                       {"direct": "batchelor_obrien", "initial_temperature": 300.0,
                        "initial_regions": [{"min": [0, 0, 0], "max": [L, L, 0.006], "temperature": 400.0}]},
                       mech=True, dt=2e-6, end=1.0, domain=((0, 0, 0), (L, L, 0.1)), periodic=(True, True, False),
                       gravity=(0, 0, -9.81), mats=[dict(MAT, friction=0.5, restitution=0.3)],
                       walls=[{"type": "plane", "point": [0, 0, 0], "normal": [0, 0, 1], "material": "p"}])
            if guards == "raised":
                sc["simulation"].update(initial_overlap_ratio=1.0, max_overlap_ratio=1.0)
            attempt(f"dense bed, radii x (1 + s), guards {guards}", f"s = {s:g}", sc, end_time=0.005,
                    bounds=(300.0, 400.0))


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true")
    ap.add_argument("--no-docs", action="store_true")
    ap.add_argument("--only", nargs="*")
    a = ap.parse_args(argv)
    t_all = time.perf_counter()
    x, L = settled_packing(log=log)
    sweeps = [("mech_step", lambda: mech_step(a.quick, x, L)), ("thermal_step", lambda: thermal_step(a.quick, x, L)),
              ("conductivity_ratio", lambda: conductivity_ratio(a.quick, x, L)),
              ("radiation", lambda: radiation(a.quick, x, L)), ("impacts", lambda: impacts(a.quick)),
              ("dense", lambda: dense(a.quick, x, L))]
    for name, fn in sweeps:
        if a.only and name not in a.only:
            continue
        t0 = time.perf_counter()
        log(f"[{name}]")
        fn()
        log(f"[{name}] {time.perf_counter() - t0:.1f} s")
    total = time.perf_counter() - t_all
    bad = [r for r in RECORDS if r["outcome"] == "completed" and (r["finite"] is False or r["bounded"] is False)]
    nonfinite_stop = [r for r in RECORDS if r["outcome"] == "stopped" and r["finite"] is False]
    log(f"total {total:.0f} s, {len(RECORDS)} runs, completed with a bad state: {len(bad)}, "
        f"stopped by a guard with non-finite state: {len(nonfinite_stop)}")
    if not a.no_docs:
        write_docs(a.quick, total)
    for r in bad:
        log(f"FAIL {r['group']} | {r['setting']}: finite={r['finite']} bounded={r['bounded']} {r['extra']}")
    assert not [r for r in bad if r["finite"] is False], "a completed run ended with NaN/inf in its state"
    return RECORDS


def _short(msg, n=170):
    msg = msg.replace("|", "/").replace("\n", " ")
    return msg if len(msg) <= n else msg[:n - 1] + "…"


def write_docs(quick, total):
    cmd = "python benchmarks/stability/run.py" + (" --quick" if quick else "")
    rows = []
    for r in RECORDS:
        state = "–" if r["finite"] is None else ("finite" if r["finite"] else "**NaN/inf**")
        if r["bounded"] is False:
            state += ", **T out of bounds**"
        verdict = {"completed": "stable", "stopped": "unstable", "not run": "refused"}[r["outcome"]]
        if r["outcome"] == "completed" and (r["bounded"] is False):
            verdict = "**unstable, not caught**"
        rows.append([r["group"], r["setting"], "refused" if r["check"] == "refused" else
                     ("warns" if r["check"].startswith("warning") else "ok"), verdict, r["guard"] or "–",
                     _short(r["message"]) if r["message"] else "–", state, r["extra"] or "–"])
    n_bad = sum(1 for r in RECORDS if r["outcome"] == "completed" and (r["finite"] is False or r["bounded"] is False))
    body = (f"```\n{cmd}\n```\n\n"
            f"Measured {time.strftime('%Y-%m-%d')} on {platform.machine()} ({os.cpu_count()} shared cores), "
            f"{len(RECORDS)} runs in {total:.0f} s{' (--quick)' if quick else ''}. `check` is the verdict of "
            f"`Simulation.check()` without `force` (refused = SceneError from the step-limit or initial-overlap "
            f"check; warns = thermal warning, e.g. Euler above the network limit); the run itself uses "
            f"`simulation.force = true`. \"stable\" = ran to the end with a finite state (and, for heat, "
            f"temperatures inside the span of the boundary and initial temperatures); \"unstable\" = stopped by "
            f"the named guard (SimulationError); \"unstable, not caught\" = ran to the end but the temperature "
            f"left the physical span. Completed runs with a bad state: **{n_bad}**. The script exits non-zero "
            f"if a completed run leaves NaN/inf in the state.\n\n"
            + md_table(["sweep", "setting", "check", "result", "guard", "message", "state", "notes"], rows) + "\n")
    edges = []
    for g in dict.fromkeys(r["group"] for r in RECORDS):
        rr = [r for r in RECORDS if r["group"] == g]
        ok = [r["setting"] for r in rr if r["outcome"] == "completed" and r["bounded"] is not False
              and r["finite"]]
        badr = [r for r in rr if not (r["outcome"] == "completed" and r["bounded"] is not False and r["finite"])]
        first = f"first failure: {badr[0]['setting']} ({badr[0]['guard'] or 'not caught'})" if badr else "no failure"
        edges.append(f"* {g}: {len(ok)}/{len(rr)} stable; {first}.")
    body += "\nEdges found:\n\n" + "\n".join(edges) + "\n"
    replace_section(os.path.join(DOCS, "benchmarks.md"), SECTION, body + "\n" + SUMMARY_PLACEHOLDER)


SUMMARY_PLACEHOLDER = """Findings (see the rows above):

* Mechanics: the documented limits (0.3 t_R, 0.1 t_H) keep a margin of about 2 to 7 before the overlap
  guard fires; past the edge every run is stopped by the overlap guard (never by NaN), within a few steps.
* Soft particles at high speed: the Hertz overlap of the impact exceeds `max_overlap_ratio` (0.1 R)
  from about 1 m/s at E = 1e6 Pa and 2-3 m/s at E = 1e7 Pa, so the overlap guard stops runs whose step
  is fine; `dem check` now predicts it: it compares the Hertz overlap at the characteristic
  velocity, (15 m* V^2 / (16 E* sqrt(R*)))^(2/5), with `max_overlap_ratio` and warns.
* Euler heat step: stable at the network limit, unstable at twice it; the temperature guard fires
  only when a temperature becomes non-positive, several steps after the oscillation started (the
  state then already spans far outside the physical range).
* Exponential heat step with radiation: radiation is explicit, so the scheme is no longer
  unconditionally stable. Past a few seconds (1 mm glass, 1000-1800 K) the hottest particle is
  tens of percent too cold, and at dt = 20 s with a 1500 K floor temperatures fall below every
  boundary and initial temperature without any guard firing; at larger steps the temperature guard
  fires with a message that advises `integrator = "exponential"`, which is already in use.
  `dem check` reports no radiation step limit.
* k_p/k_f from 1e-2 to 1e4: every indirect model gives finite, non-negative conductances and
  bounded temperatures with the exponential update.
* Dense beds: initial overlaps above 5 % are refused by the initial-overlap check; with the guards
  raised, overlaps up to ~40 % of R run (heat stays bounded) until particles are expelled
  from the open top (domain guard).
"""

if __name__ == "__main__":
    main()
