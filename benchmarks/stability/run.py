"""Stability map: stress sweeps that find where the DEM, thermal and coupled runs stop being
stable or accurate, and which guard stops them.

    python benchmarks/stability/run.py [--quick] [--no-docs] [--no-coupled] [--only SWEEP ...]

DEM sweeps: mechanical step up to and past the Rayleigh / Hertz limits (simulation.force =
true), thermal step past the network limit (euler vs exponential), k_p/k_f from 1e-2 to
1e4 with every indirect model, temperature spans up to 1800 K with radiation (zhou_2009),
impacts up to 10 m/s on soft particles (E = 1e6, 1e7), dense beds with large initial
overlaps. Coupled sweeps (thermoDemFoam, benchmarks/stability/coupled.py): particle
diameter / cell size 0.1 .. 3 with each void-fraction model, eps_min, a bed moved in one
coupling step, a dense cluster thrown through fine cells, coupling step vs drag relaxation
time. Each run records the verdict of the checks without force, how the run ended
(completed / the guard that stopped it and its message), whether its output is finite and
bounded, and for coupled runs the eps clipping and the gas-particle exchange consistency.
A run that leaves NaN/inf in its output is a failure (exit status 1). Writes the section
"## Stability map" of docs/benchmarks/stability.md (re-read right before writing; summarised in
docs/benchmarks.md, "Stability: summary of the map").
"""
import argparse
import math
import os
import platform
import re
import sys
import time

import numpy as np

HERE = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, os.path.dirname(os.path.dirname(HERE)))

from benchmarks.accuracy.common import (AIR, DOCS, MAT, R, fmt, md_table, packed_bed_scene,  # noqa: E402
                                        replace_section, scene, settled_packing, finite_state)

SECTION = "## Stability map"
PAGE = os.path.join(DOCS, "benchmarks", "stability.md")
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


def attempt(group, setting, sc, end_time, bounds=None, extra="", x=None):
    """check() without force, then the run (force = true); one record."""
    from dem import Simulation
    from dem.scene import SceneError
    from dem.simulation import SimulationError
    rec = dict(group=group, setting=setting, check="ok", outcome="", guard="", message="", finite=None,
               bounded=None, extra=extra, seconds=0.0, x=x)
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
                end_time=max(200, round(0.01 / dt)) * dt, x=f)
    m = 4 / 3 * math.pi * R ** 3 * MAT["density"]
    estar = MAT["youngs_modulus"] / (2 * (1 - MAT["poisson_ratio"] ** 2))
    tH = hertz_collision_time(m / 2, R / 2, estar, 1.0)
    for f in ([0.1, 0.3, 0.5, 1.0, 2.0] if quick else [0.05, 0.1, 0.2, 0.3, 0.5, 0.75, 1.0, 2.0]):
        dt = f * tH
        sc = scene([{"material": "p", "positions": [[-R - 1e-5, 0, 0], [R + 1e-5, 0, 0]], "radius": R,
                     "velocities": [[0.5, 0, 0], [-0.5, 0, 0]]}], mech=True, dt=dt, end=1.0, force=True)
        attempt("mechanical step, pair impact 1 m/s (E = 1e7)", f"dt = {f:g} t_H", sc,
                end_time=math.ceil(5 * tH / dt) * dt, x=f)


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
                    end_time=300 * dt, bounds=(300.0, 400.0), x=(integ, f))


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
                    end_time=100 * 20.0, bounds=(300.0, 400.0), x=(mdl, ratio))


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
                              sc, end_time=200.0, bounds=(300.0, Th), x=(Th, integ, dt))
                if rec["outcome"] != "completed":
                    continue
                tmax = float(rec["sim"].state.temperature.max())
                if ref is None:
                    ref = tmax
                rec["err"] = (tmax - ref) / (ref - 300.0)
                rec["extra"] += f"; hottest particle off by {100 * rec['err']:+.2g} % of its rise"


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
                               "thermal": {"condition": "fixed_temperature", "temperature": 400.0}}],
                       contact={"characteristic_velocity": v})   # dem check predicts the impact overlap
            rec = attempt(f"wall impact, E = {E:g} Pa (dt = 0.05 t_H(v))", f"v = {v:g} m/s", sc,
                          end_time=math.ceil((0.01 * R / v + 3 * tH) / dt) * dt, bounds=(300.0, 400.0),
                          extra=f"Hertz max overlap {dmax / R:.3g} R", x=(E, v))
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
                    bounds=(300.0, 400.0), x=(guards, s))


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true")
    ap.add_argument("--no-docs", action="store_true")
    ap.add_argument("--only", nargs="*", help="sweeps to run (mech_step thermal_step conductivity_ratio radiation "
                                              "impacts dense coupled_size coupled_eps_min coupled_teleport "
                                              "coupled_cluster coupled_relaxation)")
    ap.add_argument("--no-coupled", action="store_true", help="skip the coupled (thermoDemFoam) sweeps")
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
    if not a.no_coupled:
        from benchmarks.stability.coupled import coupled_sweeps, SWEEPS as COUPLED
        if not a.only or any(n in COUPLED for n in a.only):
            RECORDS.extend(coupled_sweeps(a.quick, log, guard_of, only=a.only))
    total = time.perf_counter() - t_all
    bad = [r for r in RECORDS if r["outcome"] == "completed" and (r["finite"] is False or r["bounded"] is False)]
    nonfinite_stop = [r for r in RECORDS if r["outcome"] == "stopped" and r["finite"] is False]
    log(f"total {total:.0f} s, {len(RECORDS)} runs, completed with a bad state: {len(bad)}, "
        f"stopped by a guard with non-finite state: {len(nonfinite_stop)}, inaccurate: "
        f"{sum(1 for r in RECORDS if r.get('inaccurate') and r['outcome'] == 'completed')}")
    for f in findings():
        log("* " + f)
    if not a.no_docs:
        write_docs(a.quick, total)
    for r in bad:
        log(f"FAIL {r['group']} | {r['setting']}: finite={r['finite']} bounded={r['bounded']} {r['extra']}")
    nan = [r for r in RECORDS if r["finite"] is False]
    for r in nan:
        log(f"NaN/inf in the output of {r['group']} | {r['setting']} ({r['outcome']})")
    if nan:
        sys.exit(f"{len(nan)} run(s) left NaN/inf in their output")
    return RECORDS


def _short(msg, n=170):
    msg = msg.replace("|", "/").replace("\n", " ")
    return msg if len(msg) <= n else msg[:n - 1] + "…"


def verdict(r):
    if r["outcome"] == "not run":
        return "refused"
    if r["outcome"] == "stopped":
        return "unstable"
    if r["finite"] is False:
        return "**NaN/inf, not caught**"
    if r["bounded"] is False:
        return "**unstable, not caught**"
    if r.get("inaccurate"):
        return "**inaccurate**"
    return "stable"


def _good(r):
    return verdict(r) == "stable"


def write_docs(quick, total):
    cmd = "python benchmarks/stability/run.py" + (" --quick" if quick else "")
    rows = []
    for r in RECORDS:
        state = "–" if r["finite"] is None else ("finite" if r["finite"] else "**NaN/inf**")
        if r["bounded"] is False:
            state += ", **T out of bounds**"
        guard, msg = r["guard"] or "–", r["message"]
        if r.get("coupled") and r["check"] == "refused" and r["outcome"] == "completed":
            guard, msg = "coupled check (run with force)", "check: " + r.get("check_message", "")
        notes = r["extra"] or "–"
        if r.get("inaccurate"):
            notes = f"**{r['inaccurate']}**; " + notes
        rows.append([r["group"], r["setting"], "refused" if r["check"] == "refused" else
                     ("warns" if r["check"].startswith("warning") else "ok"), verdict(r), guard,
                     _short(msg) if msg else "–", state, notes])
    n_bad = sum(1 for r in RECORDS if r["outcome"] == "completed" and (r["finite"] is False or r["bounded"] is False))
    n_nan = sum(1 for r in RECORDS if r["finite"] is False)
    body = (f"```\n{cmd}\n```\n\n"
            f"Measured {time.strftime('%Y-%m-%d')} on {platform.machine()} ({os.cpu_count()} shared cores), "
            f"{len(RECORDS)} runs in {total:.0f} s{' (--quick)' if quick else ''}. `check` is the verdict of "
            f"`Simulation.check()` (DEM) or of the coupled case checks (`coupling check`) without `force` "
            f"(refused = SceneError from the step-limit or initial-overlap check, or a coupled-check PROBLEM; "
            f"warns = a warning, e.g. Euler above the network limit or cells below 3 particle diameters); the "
            f"run itself uses `force = true`. \"stable\" = ran to the end with a finite state (and, for heat, "
            f"temperatures inside the span of the boundary, inlet and initial temperatures); \"unstable\" = "
            f"stopped by the named guard (SimulationError, or for coupled runs the gas-field guard); \"unstable, "
            f"not caught\" = ran to the end but the temperature left the physical span; \"inaccurate\" = ran to "
            f"the end, finite and bounded, but the result is wrong (reason in the notes). Coupled runs "
            f"(thermoDemFoam, `coupling.run.run_case`) are checked for finite values in the DEM state, "
            f"coupling.csv and the last gas fields. Completed runs with a bad state: **{n_bad}**; runs with "
            f"NaN/inf in their output: **{n_nan}**. The script exits non-zero if any run leaves NaN/inf in "
            f"its output.\n\n"
            + md_table(["sweep", "setting", "check", "result", "guard", "message", "state", "notes"], rows) + "\n")
    edges = []
    for g in dict.fromkeys(r["group"] for r in RECORDS):
        rr = [r for r in RECORDS if r["group"] == g]
        ok = [r for r in rr if _good(r)]
        badr = [r for r in rr if not _good(r)]
        first = (f"first failure: {badr[0]['setting']} ({verdict(badr[0]).strip('*')}"
                 f"{', ' + badr[0]['guard'] if badr[0]['guard'] else ''})") if badr else "no failure"
        edges.append(f"* {g}: {len(ok)}/{len(rr)} stable; {first}.")
    body += "\nEdges found:\n\n" + "\n".join(edges) + "\n"
    body += "\nFindings (generated from the rows above):\n\n" + "\n".join(f"* {f}" for f in findings()) + "\n"
    replace_section(PAGE, SECTION, body)


# ----------------------------------------------------------------------------- findings
def _rows(prefix):
    return [r for r in RECORDS if r["group"].startswith(prefix)]


def _steps(rr):
    st = [int(m.group(1)) for r in rr if (m := re.search(r"\(step (\d+)\)", r["message"]))]
    return f"{min(st)}" if st and min(st) == max(st) else (f"{min(st)}-{max(st)}" if st else "?")


def _span(vals, fmt=".2g"):
    lo, hi = min(vals), max(vals)
    return f"{lo:{fmt}}" if f"{lo:{fmt}}" == f"{hi:{fmt}}" else f"{lo:{fmt}}-{hi:{fmt}}"


def _guards(rr):
    gs = sorted({r["guard"] for r in rr if r["guard"]})
    return " / ".join(gs) if gs else "no guard"


def _xs(vals, unit=""):
    return ", ".join(f"{v:g}{unit}" for v in vals)


def findings():
    from dem import scene as scene_mod
    from benchmarks.stability.coupled import _short_warning
    out = []
    nan = [r for r in RECORDS if r["finite"] is False]
    # mechanics
    for prefix, lim, unit, what in (("mechanical step, settled bed", scene_mod.RAYLEIGH_FRACTION, "t_R",
                                      "Settled bed restarted with gravity"),
                                     ("mechanical step, pair impact", scene_mod.HERTZ_FRACTION, "t_H",
                                      "Pair impact at 1 m/s")):
        rr = _rows(prefix)
        if not rr:
            continue
        ok = [r["x"] for r in rr if _good(r)]
        bad = [r for r in rr if not _good(r)]
        if bad:
            ff = min(r["x"] for r in bad)
            out.append(f"{what}: stable up to dt = {max(ok):g} {unit}; from {ff:g} {unit} on every run is stopped "
                       f"by the {_guards(bad)} at step {_steps(bad)}, with a finite state"
                       f"{'' if all(r['finite'] for r in bad) else ' (except some)'}; `dem check` refuses above "
                       f"{lim:g} {unit}, a margin of {ff / lim:.2g}x to the first failure.")
        else:
            out.append(f"{what}: stable at every step up to {max(ok):g} {unit}.")
    # impacts
    parts = []
    for E in dict.fromkeys(r["x"][0] for r in _rows("wall impact")):
        rr = [r for r in _rows("wall impact") if r["x"][0] == E]
        bad = [r for r in rr if not _good(r)]
        warned = {r["x"][1] for r in rr if r["check"].startswith("warning")}
        failed = {r["x"][1] for r in bad}
        if bad:
            s = (f"E = {E:g} Pa: the {_guards(bad)} stops the impacts from {min(failed):g} m/s "
                 f"(step {_steps(bad)})")
        else:
            s = f"E = {E:g} Pa: every impact up to {max(r['x'][1] for r in rr):g} m/s runs"
        s += ("; `dem check` (characteristic_velocity = impact speed) warned for exactly these runs"
              if warned == failed else f"; `dem check` warned at {_xs(sorted(warned), ' m/s') or 'none'}, "
              f"failures at {_xs(sorted(failed), ' m/s') or 'none'}")
        parts.append(s)
    if parts:
        out.append("Soft particles at high speed (time step 0.05 t_H at the impact speed, so the step is fine): "
                   + "; ".join(parts) + ". The overlap exceeds `max_overlap_ratio` (0.1 R) before any "
                   "instability of the integrator; the check compares the Hertz overlap at the characteristic "
                   "velocity, (15 m* V^2 / (16 E* sqrt(R*)))^(2/5), with that bound.")
    # heat step
    rr = _rows("thermal step")
    eu = [r for r in rr if r["x"][0] == "euler"]
    ex = [r for r in rr if r["x"][0] == "exponential"]
    if eu:
        bad = [r for r in eu if not _good(r)]
        ok = [r["x"][1] for r in eu if _good(r)]
        warn = [r["x"][1] for r in eu if r["check"].startswith("warning")]
        s = (f"Euler heat step: stable up to {max(ok):g} x the network limit" if ok else "Euler heat step: ")
        if bad:
            spans = [re.search(r"T in \[([^]]*)\]", r["extra"]).group(1) for r in bad if "T in [" in r["extra"]]
            s += (f", unstable from {min(r['x'][1] for r in bad):g} x; the {_guards(bad)} fires only when a "
                  f"temperature is no longer positive, at step {_steps(bad)} (the state then spans "
                  f"[{spans[0]}] K against the physical [300, 400] K)")
        if warn:
            s += f"; `dem check` warns from {min(warn):g} x the limit"
        out.append(s + ".")
    if ex:
        okx = [r for r in ex if _good(r)]
        out.append(f"Exponential heat step: {len(okx)}/{len(ex)} runs stable, up to {max(r['x'][1] for r in ex):g} x "
                   f"the network limit, temperatures inside [300, 400] K.")
    # radiation
    rad = _rows("radiation")
    if rad:
        eu = [r for r in rad if r["x"][1] == "euler"]
        ex = [r for r in rad if r["x"][1] == "exponential"]
        ths = list(dict.fromkeys(r["x"][0] for r in rad))
        fails = []
        for th in ths:
            b = [r["x"][2] for r in eu if r["x"][0] == th and not _good(r)]
            w = [r["x"][2] for r in eu if r["x"][0] == th and r["check"].startswith("warning")]
            fails.append(f"{th:g} K: fails from {min(b):g} s, warned from {min(w):g} s" if b and w else
                         f"{th:g} K: fails from {min(b):g} s" if b else f"{th:g} K: no failure")
        gb = [r for r in eu if not _good(r)]
        s = (f"Radiation (zhou_2009), Euler: {'; '.join(fails)}; each failure is stopped by the "
             f"{_guards(gb)} (advice: exponential integrator or a step below the printed limits).")
        exok = [r for r in ex if _good(r)]
        errs = [r for r in ex if r.get("err") is not None]
        if ex:
            s += (f" Exponential (walls, gas and radiation relax each particle together): {len(exok)}/{len(ex)} "
                  f"runs stable and bounded up to dt = {max(r['x'][2] for r in ex):g} s at floor temperatures up "
                  f"to {max(ths):g} K")
            if errs:
                w = max(errs, key=lambda r: abs(r["err"]))
                s += (f"; the hottest particle is at most {100 * abs(w['err']):.2g} % of its rise off the Euler "
                      f"0.1 s reference ({w['setting']})")
            s += "."
        out.append(s)
    # conductivity ratio
    rr = _rows("k_p/k_f")
    if rr:
        ok = [r for r in rr if _good(r)]
        ratios = sorted({r["x"][1] for r in rr})
        out.append(f"k_p/k_f from {ratios[0]:g} to {ratios[-1]:g} with {len({r['x'][0] for r in rr})} indirect "
                   f"models: {len(ok)}/{len(rr)} runs finite with bounded temperatures (exponential, dt = 20 s).")
    # dense beds
    d0 = _rows("dense bed, radii x (1 + s), guards default")
    d1 = _rows("dense bed, radii x (1 + s), guards raised")
    if d0:
        ref = [r for r in d0 if r["outcome"] == "not run"]
        s = "Dense beds (radii inflated by s): "
        s += (f"with the default guards s >= {min(r['x'][1] for r in ref):g} is refused by the "
              f"{_guards(ref)}" if ref else "no run refused with the default guards")
        if d1:
            ok = [r["x"][1] for r in d1 if _good(r)]
            bad = [r for r in d1 if not _good(r)]
            s += (f"; with the guards raised to 1, s up to {max(ok):g} runs with bounded heat"
                  + (f", and from s = {min(r['x'][1] for r in bad):g} on the {_guards(bad)} stops the run"
                     if bad else ""))
        out.append(s + ".")
    # coupled: size
    cs = _rows("coupled: d/dx")
    if cs:
        ratios = sorted({r["x"][1] for r in cs})
        per = []
        for vf in ("centre", "divided", "smoothed"):
            rr = sorted([r for r in cs if r["x"][0] == vf], key=lambda r: r["x"][1])
            clip = [r for r in rr if r["probe"].get("clip_cells", 0) > 0]
            bad = [r for r in rr if not _good(r)]
            t = f"'{vf}'"
            t += (f": eps clipped from d/dx = {clip[0]['x'][1]:g} ({100 * clip[0]['probe']['clip_fraction']:.2g} % of "
                  f"the solid) to {100 * rr[-1]['probe']['clip_fraction']:.2g} % at d/dx = {rr[-1]['x'][1]:g}"
                  if clip else ": never clipped")
            if bad:
                t += f", inaccurate from d/dx = {bad[0]['x'][1]:g} ({bad[0]['inaccurate']})"
            per.append(t)
        warn = sorted({r["x"][1] for r in cs if r["check"] != "ok"})
        refd = sorted({(r["x"][0], r["x"][1]) for r in cs if r["check"] == "refused"})
        coarse = [r for r in cs if r["x"][1] <= 0.2]
        fine = [r for r in cs if 0.5 <= r["x"][1] <= 1.0 and _good(r)]
        stopped = [r for r in cs if r["outcome"] != "completed"]
        clean = all(r["finite"] and r["bounded"] is not False for r in cs)
        s = (f"Coupled, particle diameter / cell size {ratios[0]:g} to {ratios[-1]:g} (settled bed at rest, "
             f"hot air through it): "
             + ("every run ends finite and bounded" if clean else "some runs end non-finite or unbounded")
             + (", and no guard stops any - the failure is accuracy: " if not stopped else
                f"; {len(stopped)} stopped ({_guards(stopped)}); accuracy: ")
             + f"{'; '.join(per)}. `coupling check` warns below 3 diameters per cell (d/dx > 1/3: "
             f"{_xs([x for x in warn if x > 1/3])}) and refuses (more than 5 % of the particle volume clipped "
             f"at t = 0) {', '.join(f'{m} at {x:g}' for m, x in refd) or 'none'}. ")
        if coarse:
            s += (f"Coarse cells smear the 14 mm bed over the freeboard: the bed drag is "
                  f"{_span([r['drag_ratio'] for r in coarse])} x the value at the bed's mean void fraction for "
                  f"d/dx <= 0.2")
        if fine:
            s += (f", {_span([r['drag_ratio'] for r in fine])} x where the cells resolve the bed with little "
                  f"clipping (d/dx {_span([r['x'][1] for r in fine], 'g')}; the local eps spread raises the "
                  f"nonlinear drag)")
        s += (". Exchange consistency (gas-side sums against particle-side sums with the same gas state): "
              "exact for 'centre' and single-cell stencils; the spread stencils of 'divided' and 'smoothed' "
              "meet cells of different gas velocity/temperature, and the mismatch grows with d/dx "
              f"(heat up to {max((r['probe'].get('heat_mismatch') or 0) for r in cs) * 100:.2g} %, momentum up to "
              f"{max((r['probe'].get('momentum_mismatch') or 0) for r in cs) * 100:.2g} %).")
        out.append(s)
    rr = _rows("coupled: eps_min")
    if rr:
        out.append("Lower eps_min with clipped cells ('centre', d/dx = 2): " + "; ".join(
            f"eps_min = {r['x']:g}: {verdict(r).strip('*')}" + (f" ({r['guard']})" if r["guard"] else "")
            + (f", particles up to {r['probe'].get('v_max', 0):.2g} m/s" if r.get("probe") else "")
            for r in rr) + ". The drag and pressure-gradient forces at eps ~ eps_min throw the resting bed apart; "
            "the DEM overlap guard stops it (its advice, a lower time_step, does not apply here) - the coupled "
            "check refuses these cases up front (clipped volume).")
    rr = _rows("coupled: bed moved up")
    if rr:
        out.append("Sudden void fraction change (the bed moved 20 mm between two coupling steps): " + "; ".join(
            f"coupling_interval {r['x'][0]}, smoothing {r['x'][1]:g} s: {verdict(r).strip('*')}"
            + (f" ({r['guard']}: gas at {r['probe'].get('u_gas_max', 0):.3g} m/s)" if r["guard"].startswith("gas-field")
               else (f" ({r['guard']})" if r["guard"] else "")
               + f", gas up to {r['probe'].get('u_gas_max', 0):.3g} m/s, bed up to "
                 f"{r['probe'].get('v_max', 0):.2g} m/s")
            + (f", warns: {' / '.join(_short_warning(w) for w in r['runtime_warnings'])}"
               if r.get("runtime_warnings") else "")
            for r in rr) + ". thermoDemFoam itself stays finite: the incompressible gas displaces the volume "
            "within one CFD step, so the gas speed scales with (eps change) x (bed depth) / deltaT; the gas-field "
            "guard stops a run when the gas is faster than the speed of sound, and the run warns (once) about an "
            "eps change above 0.2 per coupling step and a gas faster than Mach 0.3. smoothing_time spreads the "
            "change over a few CFD steps and keeps the gas and the bed sensible, at the price of a gas-particle "
            "momentum mismatch while eps and Ksl relax.")
    rr = _rows("coupled: dense cluster")
    if rr:
        out.append("Dense cluster thrown through 2 mm cells ('divided', eps 1 -> 0.45 in one coupling step): "
                   + "; ".join(
            f"v = {r['x']:g} m/s: {verdict(r).strip('*')}" + (f" ({r['guard']})" if r["guard"] else "")
            + f", gas up to {r['probe'].get('u_gas_max', 0):.3g} m/s" for r in rr)
            + (f". `coupling check` refuses v = {_xs([r['x'] for r in rr if r['check'] == 'refused'], ' m/s')} "
               "up front (particle Courant number v deltaT / dx above 0.5)"
               if any(r["check"] == "refused" for r in rr) else "")
            + "; with force thermoDemFoam stays finite (the displaced gas moves at about the cluster speed) and "
            "the fastest cluster ends on the DEM overlap guard at the floor.")
    rr = _rows("coupled: coupling step / drag relaxation")
    if rr:
        pk = [r for r in rr if r["x"][0] == "packed"]
        dl = [r for r in rr if r["x"][0] == "dilute"]
        s = "Coupling step against the drag relaxation time m/beta (0.1 mm, 250 kg/m3 beads): "
        if pk:
            s += (f"a packed bed stays at rest up to {max(r['x'][1] for r in pk if _good(r)):.3g} x (contacts hold "
                  f"the particles, the gas follows them)" if any(_good(r) for r in pk) else "the packed bed fails")
        if dl:
            s += "; dilute particles: " + "; ".join(
                f"{r['x'][1]:.3g} x: {verdict(r).strip('*')}" + (f" ({r['guard']})" if r["guard"] else "")
                + f", up to {r['probe'].get('v_max', 0):.2g} m/s" for r in dl)
            s += (" (terminal velocity 0.075 m/s; with the drag taken implicitly, docs/models.md \"Semi-implicit "
                  "drag\", no step overshoots; with the former explicit drag the dilute beads ended on the "
                  "overlap guard at 45 x)")
        s += (". `coupling check` warns above the bed's m/beta_imp (the accuracy of transients) and no longer "
              "refuses: the scheme is stable at any step.")
        out.append(s)
    fired = {}
    for r in RECORDS:
        if r["outcome"] in ("stopped", "not run") and r["guard"]:
            fired[r["guard"]] = fired.get(r["guard"], 0) + 1
    out.append(f"NaN/inf: {len(nan)} of {len(RECORDS)} runs left non-finite values in their output. Guards that "
               f"stopped or refused runs: " + ", ".join(f"{g} ({n})" for g, n in sorted(fired.items())) + ".")
    return out


if __name__ == "__main__":
    main()
