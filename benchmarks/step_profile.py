"""Where a step goes: one process's step of the shared beds split into its phases, and the pair
loop split into candidates that do not touch and contacts, against the arithmetic of the law.

    python benchmarks/step_profile.py                      # shared 10k bed, heat off and on
    python benchmarks/step_profile.py --beds 10k 50k --steps 400 --repeats 3 --threads 1

Each figure is in ns per particle-step (the phase's time over the steps, divided by the owned
particles). Method:

* whole step: ``Simulation.step`` over ``--steps`` steps (the production path: one compiled
  call), the best of ``--repeats`` runs from the same state (every array of dem.schema is
  copied before and put back between repeats, so each repeat does the same work);
* phases: the compiled step alone (dem.step.advance, every phase, one call: the difference to
  the whole step is per-step Python), then each phase alone in one compiled call of the same
  steps (dem.step.advance with one phase bit: drift (until a rebuild falls due), interact
  (pair loop + walls: dem.step.compute_forces), kick + guards, heat step), and the neighbour
  rebuild timed alone (dem.step's build_half_list + after_build, as an MPI rebuild calls
  them) times the rebuilds the compiled step made;
* pair loop: the interact phase timed on the same positions with neighbour lists built with
  1x, 2x and 3x the scene's skin: more candidates, the same contacts, so the slope of time
  against candidates is the cost of a candidate that does not touch (a distance test), and
  what remains at the scene's skin, over the contacts, is the cost of a contact (the law,
  history, heat; walls and per-row work included, so an upper bound);
* the floor: the arithmetic of one Hertz-Mindlin contact with tangential history and (heat)
  fused conduction, counted from dem.step.interact_rows (OPS_* below), at 4 scalar operations
  per cycle or 5 cycles per division or root, whichever is longer (floor_cycles), with the
  clock read from /proc/cpuinfo.
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

# The arithmetic of one sticking Hertz-Mindlin contact with tangential history in
# dem.step.interact_rows, counted by hand from the code (dem.step, dem.contact.hertz_mindlin):
# distance test 10, 1/d^2, root and normal 7, overlap ratio 2, contact-point velocity 24, normal
# and tangential parts 11, spring rotation on the centre line (_rotate_history) 27, R* and m*
# (from 1/m) 4, Hertz-Mindlin with Tsuji damping (its ratio sqrt(4 G*/E*) from the pair table)
# and Coulomb test 38, force sums on both rows 12, torque sums 21: 156 operations, of which 5
# divisions and 4 square roots. Fused conduction (Batchelor-O'Brien on the Hertz contact radius,
# H = 2 k a, rate into both rows, energy tally): 14 more, one root.
OPS_MECH, DIVSQRT_MECH = 156, 9
OPS_HEAT, DIVSQRT_HEAT = 14, 1
# The same with the projected tangential model ([contact] tangential = "projected", LIGGGHTS's law,
# which the shared beds run: dem.contact.tangential): the spring's turn is 12 operations, no
# division or root (15 and 2 fewer), and the cap tests |S_t xi|^2 (2 more): 143 operations, 7.
OPS_MECH_PROJECTED, DIVSQRT_MECH_PROJECTED = 143, 7
# The floor in cycles: 4 scalar floating-point operations per cycle (2 FMA/multiply + 2 add
# pipes of an AMD Zen core, counting each operation as one), or the divider: about 5 cycles
# per double-precision division or square root (reciprocal throughput, Agner Fog's tables for
# AMD Zen 3/4), whichever is longer. Memory traffic is not in the floor.
OPS_PER_CYCLE, DIVSQRT_CYCLES = 4.0, 5.0


def floor_cycles(heat, projected=False):
    ops = (OPS_MECH_PROJECTED if projected else OPS_MECH) + (OPS_HEAT if heat else 0)
    ds = (DIVSQRT_MECH_PROJECTED if projected else DIVSQRT_MECH) + (DIVSQRT_HEAT if heat else 0)
    return ops, ds, max(ops / OPS_PER_CYCLE, ds * DIVSQRT_CYCLES)


# The distance test of a candidate that does not touch: 10 operations, no division: 2.5 cycles.
OPS_TEST = 10


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


def best_of(sim, snap, repeats, fn):
    """The least seconds of ``fn()`` over ``repeats`` runs, each from the snapshot; fn's last result."""
    best, res = float("inf"), None
    for _ in range(repeats):
        restore(sim, snap)
        s0 = sim.step_count
        dt, res = timed(fn)
        best = min(best, dt)
        sim.world.set_step(s0)
    restore(sim, snap)
    return best, res


def phase_steps(sim, snap, steps, repeats, heat):
    """Seconds over ``steps`` steps of: the whole step through Simulation.step (production path),
    the compiled step alone (every phase, one call), and each phase alone in one compiled call
    of ``steps`` repetitions (drift: until a rebuild is due); the rebuilds of the whole step
    and the cost of one rebuild (dem.step.rebuild's functions, called as an MPI rebuild does)."""
    stp = sim.stepper
    s = sim.step_count
    r = {}
    r["api"], _ = best_of(sim, snap, repeats, lambda: sim.step(steps))
    r["step"], res = best_of(sim, snap, repeats, lambda: stp.phases(K.PH_STEP, nsteps=steps, s0=s))
    r["nreb"] = int(res[6])
    r["drift"], res = best_of(sim, snap, repeats, lambda: stp.phases(K.PH_DRIFT, nsteps=steps, s0=s))
    r["drift_steps"] = max(int(res[0]), 1)
    r["forces"], _ = best_of(sim, snap, repeats, lambda: stp.phases(K.PH_FORCES, nsteps=steps, s0=s))
    r["kick"], _ = best_of(sim, snap, repeats, lambda: stp.phases(K.PH_KICK, nsteps=steps, s0=s))
    r["heat"] = 0.0
    if heat:
        r["heat"], _ = best_of(sim, snap, repeats, lambda: stp.phases(K.PH_HEAT, nsteps=steps, s0=s))
    st = sim.state
    r["rebuild"], _ = best_of(sim, snap, repeats, lambda: stp.rebuild(s, st.lo, st.hi, st.periodic))
    restore(sim, snap)
    return r


def empty_call(sim, reps=2000):
    stp = sim.stepper
    s0 = sim.step_count
    stp.phases(0, nsteps=0, s0=s0)
    t0 = time.perf_counter()
    for _ in range(reps):
        stp.phases(0, nsteps=0, s0=s0)
    return (time.perf_counter() - t0) / reps


def one_interact(sim, snap, reps):
    """Seconds of one interact phase (pair loop + walls) from the snapshot, best of ``reps``,
    and the contacts it counted."""
    best, nc = float("inf"), 0
    for _ in range(reps):
        restore(sim, snap)
        dt, res = timed(lambda: sim.stepper.phases(K.PH_FORCES))
        best, nc = min(best, dt), int(res[5]) // 2
    restore(sim, snap)
    return best, nc


def pair_loop(sim, snap, reps):
    """(skin multiple, candidates, contacts, seconds of one interact phase) on lists built with
    1x, 2x and 3x the scene's skin at the snapshot's positions (history starting empty)."""
    st = sim.state
    stp = sim.stepper
    skin0 = float(st.fp[K.FP.skin])
    rows = []
    for mult in (1.0, 2.0, 3.0):
        restore(sim, snap)
        st.fp[K.FP.skin] = skin0 * mult
        stp.rebuild(sim.step_count, st.lo, st.hi, st.periodic, initial=True)
        cand = int(st.nnb[:st.n_owned].sum())
        sec, nc = one_interact(sim, snapshot(st), reps)
        rows.append((mult, cand, nc, sec))
    st.fp[K.FP.skin] = skin0
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
    ph = phase_steps(sim, snap, steps, repeats, heat)
    e = empty_call(sim)
    drift = ph["drift"] / ph["drift_steps"] * steps
    rebuild = ph["rebuild"] * ph["nreb"]
    one, contacts = one_interact(sim, snap, 5 * repeats)
    one = max(one - e, 0.0)
    forces, kick, heatt = one * steps, ph["kick"], ph["heat"]
    phases_sum = drift + rebuild + forces + kick + heatt
    whole = ph["api"]
    rows = pair_loop(sim, snap, 5 * repeats)
    (m1, c1, k1, t1), (m2, c2, k2, t2), (m3, c3, k3, t3) = rows
    slope = np.polyfit([c1, c2, c3], [t1, t2, t3], 1)[0]  # s per candidate
    nontouch = c1 - contacts
    per_contact = (one - slope * nontouch) / max(contacts, 1)
    ghz = cpu_ghz()
    ops, ds, floor = floor_cycles(heat, projected=sim.stepper.ton is not None)
    label = f"{bed} bed, heat {'on' if heat else 'off'}, {sim.threads} thread(s), {n} particles, {steps} steps"
    print(f"\n== {label} (kernels compile/load {compile_s:.1f} s)")
    print(f"whole step (Simulation.step)       {whole * ps:8.1f} ns/particle-step   "
          f"{n * steps / whole:.3g} particle-steps/s")
    print(f"  compiled step (dem.step.advance)  {ph['step'] * ps:8.1f}")
    for what, sec in (("drift", drift), (f"neighbour rebuild ({ph['nreb']} in {steps} steps)", rebuild),
                      ("interact (pair loop + walls)", forces), ("kick + guards", kick),
                      ("heat step", heatt)):
        if what == "heat step" and not heat:
            continue
        print(f"    {what:32s} {sec * ps:8.1f}  {100 * sec / max(phases_sum, 1e-30):5.1f} % of the phases")
    print(f"    {'(one rebuild alone)':32s} {ph['rebuild'] / n * 1e9:8.1f}   ns per particle: "
          f"{ph['rebuild'] / max(ph['step'] / steps, 1e-30):.1f} steps' worth")
    print(f"    {'phases together, less their sum':32s} {(ph['step'] - phases_sum) * ps:8.1f}")
    print(f"  per-step Python (Simulation.step)  {(whole - ph['step']) * ps:8.1f}   "
          f"(an empty compiled call: {e * 1e6:.1f} us)")
    print(f"pair loop: {c1 / n:.2f} candidates and {contacts / n:.2f} contacts per particle (half list); "
          f"skin x1/x2/x3: {c1}/{c2}/{c3} candidates, {t1 * 1e3:.3f}/{t2 * 1e3:.3f}/{t3 * 1e3:.3f} ms")
    print(f"  a candidate that does not touch  {slope * 1e9:6.1f} ns  ({slope * 1e9 * ghz:5.1f} cycles at {ghz:.2f} GHz; "
          f"arithmetic {OPS_TEST / OPS_PER_CYCLE:.1f} cycles: the rest is fetching j's position and the slot)")
    print(f"  a contact (law, history{', heat' if heat else ''}) {per_contact * 1e9:6.1f} ns  "
          f"({per_contact * 1e9 * ghz:5.1f} cycles; floor {floor:.0f} cycles: {ops} operations, {ds} divisions "
          f"or roots: {per_contact * 1e9 * ghz / floor:.1f}x the floor)")
    print(f"  pair loop split at the scene's skin: non-touching {slope * nontouch * 1e3:.3f} ms "
          f"({100 * slope * nontouch / one:.0f} %), contacts {per_contact * contacts * 1e3:.3f} ms "
          f"({100 * per_contact * contacts / one:.0f} %)")
    return dict(bed=bed, heat=heat, whole=whole * ps, drift=drift * ps, rebuild=rebuild * ps, forces=forces * ps,
                kick=kick * ps, heatstep=heatt * ps, python=(whole - ph["step"]) * ps, cand=slope * 1e9,
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
