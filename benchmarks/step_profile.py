"""Where a step goes: one process's step of the shared beds split into its phases, and the pair
loop split into candidates that do not touch and contacts, against the arithmetic of the law.

    python benchmarks/step_profile.py                      # shared 10k bed, heat off and on
    python benchmarks/step_profile.py --beds 10k 50k --steps 400 --repeats 3 --threads 1

Each figure is in ns per particle-step (the phase's time over the steps, divided by the owned
particles). Method:

* whole step: ``Simulation.step`` over ``--steps`` steps (the production path: one compiled
  call), the best of ``--repeats`` runs from the same state (every array of dem.schema is
  copied before and put back between repeats, so each repeat does the same work);
* phases: the same steps with each phase its own compiled call (dem.step.advance with one
  phase bit: drift, drift + neighbour rebuild (the steps whose drift rebuilt the lists),
  interact (pair loop + walls: dem.step.compute_forces), kick + guards, heat step), less the
  cost of an empty call (measured); "per-step Python" is the production path's time over
  its steps minus the sum of the phases' (negative values mean the phases' calls cost more
  than they save, i.e. zero within noise);
* pair loop: the interact phase timed on the same positions with neighbour lists built with
  1x, 2x and 3x the scene's skin: more candidates, the same contacts, so the slope of time
  against candidates is the cost of a candidate that does not touch (a distance test), and
  what remains at the scene's skin, over the contacts, is the cost of a contact (the law,
  history, heat; walls and per-row work included, so an upper bound);
* the floor: the floating-point operations of one Hertz-Mindlin contact with tangential
  history and (heat) fused conduction, counted from dem.step.interact_rows (FLOPS_* below),
  at the 2 scalar double-precision operations per cycle of an AVX2/FMA core without
  vectorisation, and the clock read from /proc/cpuinfo.
"""
import argparse
import os
import sys
import time

import numpy as np

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
sys.path.insert(0, ROOT)

from dem import Simulation  # noqa: E402
from dem import schema as S  # noqa: E402
from dem import step as K  # noqa: E402

# Floating-point operations of one contact in dem.step.interact_rows, counted by hand
# (+, -, *, fused multiply-add as 2; sqrt and division as 1 each, although they cost 4-20 cycles):
# branch distance and normal 23 (dx 3, r^2 5, sqrt, 1/r, normal 3, overlap 2, ...), relative
# velocity at the contact 27, Hertz normal force + Tsuji damping 24 (sqrt(R* delta), kn, gamma),
# tangential spring: rotation of the history 20, increment 9, Coulomb cap 14, damping 9,
# force and torque sums on both particles 36, overlap ratio 4.
FLOPS_MECH = 166
# fused conduction (Batchelor-O'Brien: contact radius from the Hertz overlap, H = 2 k a, rate
# H (Tj - Ti) into both particles): 12
FLOPS_HEAT = 12


def cpu_ghz():
    try:
        with open("/proc/cpuinfo") as fh:
            mhz = [float(line.split(":")[1]) for line in fh if line.startswith("cpu MHz")]
        return sum(mhz) / len(mhz) / 1000.0 if mhz else float("nan")
    except OSError:
        return float("nan")


def snapshot(st):
    """Every declared array (dem.schema.FIELDS), copied."""
    return {f.name: getattr(st, f.name).copy() for f in S.FIELDS}


def restore(sim, snap):
    st = sim.state
    for name, a in snap.items():
        cur = getattr(st, name)
        if cur.shape == a.shape:
            cur[...] = a
        else:
            setattr(st, name, a.copy())


def timed(fn):
    t0 = time.perf_counter()
    r = fn()
    return time.perf_counter() - t0, r


def whole_steps(sim, snap, steps, repeats):
    best = float("inf")
    for _ in range(repeats):
        restore(sim, snap)
        s0 = sim.step_count
        dt, _ = timed(lambda: sim.step(steps))
        best = min(best, dt)
        sim.world.set_step(s0)
    return best


def phase_steps(sim, snap, steps, repeats, heat):
    """Seconds per phase over ``steps`` steps, each phase its own compiled call (best repeat)."""
    stp = sim.stepper
    best = None
    for _ in range(repeats):
        restore(sim, snap)
        s = sim.step_count
        acc = dict(drift=0.0, rebuild=0.0, forces=0.0, kick=0.0, heat=0.0, calls=0)
        nreb = 0
        for k in range(steps):
            s0 = s + k
            dt, res = timed(lambda: stp.phases(K.PH_DRIFT | K.PH_REBUILD, s0=s0))
            stp.set_pairs(res[-1])
            if res[6]:
                acc["rebuild"] += dt
                nreb += 1
            else:
                acc["drift"] += dt
            dt, res = timed(lambda: stp.phases(K.PH_FORCES, s0=s0))
            acc["forces"] += dt
            dt, _ = timed(lambda: stp.phases(K.PH_KICK, s0=s0))
            acc["kick"] += dt
            calls = 3
            if heat:
                dt, _ = timed(lambda: stp.phases(K.PH_HEAT, s0=s0))
                acc["heat"] += dt
                calls += 1
            acc["calls"] += calls
        acc["nreb"] = nreb
        if best is None or sum(acc[p] for p in ("drift", "rebuild", "forces", "kick", "heat")) < \
                sum(best[p] for p in ("drift", "rebuild", "forces", "kick", "heat")):
            best = acc
    return best


def empty_call(sim, reps=2000):
    stp = sim.stepper
    s0 = sim.step_count
    stp.phases(0, nsteps=0, s0=s0)
    t0 = time.perf_counter()
    for _ in range(reps):
        stp.phases(0, nsteps=0, s0=s0)
    return (time.perf_counter() - t0) / reps


def pair_loop(sim, snap, repeats, calls=20):
    """(candidates, contacts, seconds of one interact phase) at 1x, 2x and 3x the skin."""
    st = sim.state
    stp = sim.stepper
    skin0 = float(st.fp[K.FP.skin])
    rows = []
    for mult in (1.0, 2.0, 3.0):
        restore(sim, snap)
        st.fp[K.FP.skin] = skin0 * mult
        stp.rebuild(sim.step_count, st.lo, st.hi, st.periodic, initial=True)
        cand = int(st.nnb[:st.n_owned].sum())
        best = float("inf")
        for _ in range(repeats):
            t0 = time.perf_counter()
            for _ in range(calls):
                res = stp.phases(K.PH_FORCES)
            best = min(best, (time.perf_counter() - t0) / calls)
        rows.append((mult, cand, int(res[5]) // 2, best))
    st.fp[K.FP.skin] = skin0
    restore(sim, snap)
    stp.rebuild(sim.step_count, st.lo, st.hi, st.periodic, initial=True)
    restore(sim, snap)
    return rows


def profile(bed, heat, steps, repeats, threads):
    name = f"shared_bed{'_heat' if heat else ''}_{bed}.toml"
    sim = Simulation.from_file(os.path.join(ROOT, "benchmarks", name))
    if threads is not None:
        sim.set_threads(threads)
    t0 = time.perf_counter()
    sim.warmup()
    compile_s = time.perf_counter() - t0
    sim.step(50)  # past the first build and the start-up of the contacts
    snap = snapshot(sim.state)
    n = sim.state.n_owned
    ps = 1e9 / (n * steps)
    whole = whole_steps(sim, snap, steps, repeats)
    ph = phase_steps(sim, snap, steps, repeats, heat)
    e = empty_call(sim)
    corr = e  # each phase call's fixed cost
    drift = max(ph["drift"] - corr * (steps - ph["nreb"]), 0.0)
    rebuild = max(ph["rebuild"] - corr * ph["nreb"], 0.0)
    forces = max(ph["forces"] - corr * steps, 0.0)
    kick = max(ph["kick"] - corr * steps, 0.0)
    heatt = max(ph["heat"] - corr * steps, 0.0) if heat else 0.0
    phases_sum = drift + rebuild + forces + kick + heatt
    rows = pair_loop(sim, snap, repeats)
    (m1, c1, k1, t1), (m2, c2, k2, t2), (m3, c3, k3, t3) = rows
    slope = np.polyfit([c1, c2, c3], [t1, t2, t3], 1)[0]  # s per candidate
    contacts = k1
    nontouch = c1 - contacts
    per_contact = (t1 - slope * nontouch) / max(contacts, 1)
    ghz = cpu_ghz()
    flops = FLOPS_MECH + (FLOPS_HEAT if heat else 0)
    floor_cycles = flops / 2.0
    label = f"{bed} bed, heat {'on' if heat else 'off'}, {sim.threads} thread(s), {n} particles, {steps} steps"
    print(f"\n== {label} (kernels compile/load {compile_s:.1f} s)")
    print(f"whole step (production path)      {whole * ps:8.1f} ns/particle-step   "
          f"{n * steps / whole:.3g} particle-steps/s")
    for what, sec in (("drift", drift), (f"drift + rebuild ({ph['nreb']} of {steps} steps)", rebuild),
                      ("interact (pair loop + walls)", forces), ("kick + guards", kick),
                      ("heat step", heatt)):
        if what == "heat step" and not heat:
            continue
        print(f"  {what:32s} {sec * ps:8.1f} ns/particle-step  {100 * sec / max(phases_sum, 1e-30):5.1f} %")
    print(f"  {'per-step Python and calls':32s} {(whole - phases_sum) * ps:8.1f} ns/particle-step "
          f"(empty compiled call {e * 1e6:.1f} us)")
    print(f"pair loop: {c1 / n:.2f} candidates and {contacts / n:.2f} contacts per particle (half list); "
          f"skin x1/x2/x3: {c1}/{c2}/{c3} candidates, {t1 * 1e3:.3f}/{t2 * 1e3:.3f}/{t3 * 1e3:.3f} ms")
    print(f"  a candidate that does not touch  {slope * 1e9:6.1f} ns  ({slope * 1e9 * ghz:5.1f} cycles at {ghz:.2f} GHz)")
    print(f"  a contact (law, history{', heat' if heat else ''}) {per_contact * 1e9:6.1f} ns  "
          f"({per_contact * 1e9 * ghz:5.1f} cycles; floor {flops} flops = {floor_cycles:.0f} cycles: "
          f"{per_contact * 1e9 * ghz / floor_cycles:.1f}x the floor)")
    print(f"  pair loop split at the scene's skin: non-touching {slope * nontouch * 1e3:.3f} ms "
          f"({100 * slope * nontouch / t1:.0f} %), contacts {per_contact * contacts * 1e3:.3f} ms "
          f"({100 * per_contact * contacts / t1:.0f} %)")
    return dict(bed=bed, heat=heat, whole=whole * ps, drift=drift * ps, rebuild=rebuild * ps, forces=forces * ps,
                kick=kick * ps, heatstep=heatt * ps, python=(whole - phases_sum) * ps, cand=slope * 1e9,
                contact=per_contact * 1e9)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--beds", nargs="+", default=["10k"], choices=["10k", "50k"])
    ap.add_argument("--heat", choices=["off", "on", "both"], default="both")
    ap.add_argument("--steps", type=int, default=400)
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--threads", type=int, default=1)
    a = ap.parse_args(argv)
    heats = {"off": [False], "on": [True], "both": [False, True]}[a.heat]
    print(f"step profile: {os.cpu_count()} CPUs, clock {cpu_ghz():.2f} GHz (/proc/cpuinfo)")
    for bed in a.beds:
        for h in heats:
            profile(bed, h, a.steps, a.repeats, a.threads)


if __name__ == "__main__":
    main()
