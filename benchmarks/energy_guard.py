"""Energy guard tolerance: the largest relative energy gain between two checks of stable runs
at the default step, and of runs forced above the step limits.

    python benchmarks/energy_guard.py [--quick]

Each run goes through Simulation.run with the guard measuring only (tolerance = inf): the
figure is max over checks of (E_k - E_k-1) / (kinetic + rotational + elastic energy + |work of
gravity|), see dem.energy_guard. A check is made at every output (output_interval below).
Stable runs must stay well below dem.energy_guard.GAIN_TOLERANCE, forced runs well above.
"""
import argparse
import math
import os
import sys
import time

HERE = os.path.dirname(os.path.abspath(__file__))
ROOT = os.path.dirname(HERE)
sys.path.insert(0, ROOT)

R = 1e-3
GLASS = dict(name="glass", density=2500.0, youngs_modulus=1e7, poisson_ratio=0.25, restitution=0.5,
             friction=0.3)


def rayleigh():
    from dem.contact.damping import rayleigh_time
    G = GLASS["youngs_modulus"] / (2 * (1 + GLASS["poisson_ratio"]))
    return rayleigh_time(R, GLASS["density"], G, GLASS["poisson_ratio"])


def three_beads(f, v=0.5, restitution=0.5, end=0.004, out=None):
    """Two beads thrown at a third at rest, on a line, no gravity; dt = f t_R; a check every step."""
    dt = f * rayleigh()
    return {"simulation": {"time_step": dt, "end_time": end, "output_interval": out or dt, "force": True,
                           "gravity": [0.0, 0.0, 0.0]},
            "domain": {"min": [-0.02] * 3, "max": [0.02] * 3},
            "materials": [dict(GLASS, restitution=restitution)],
            "particles": [{"material": "glass", "positions": [[-2.2 * R, 0, 0], [0, 0, 0], [2.2 * R, 0, 0]],
                           "radius": R, "velocities": [[v, 0, 0], [0, 0, 0], [-v, 0, 0]]}]}


def wall_rebound(f, v=1.0, restitution=0.5, end=0.004, out=None, z0=1.05):
    """One bead thrown on a plane at v, gravity on; dt = f t_R; a check every step."""
    dt = f * rayleigh()
    return {"simulation": {"time_step": dt, "end_time": end, "output_interval": out or dt, "force": True,
                           "gravity": [0.0, 0.0, -9.81]},
            "domain": {"min": [-0.01, -0.01, -0.001], "max": [0.01, 0.01, 0.02]},
            "materials": [dict(GLASS, restitution=restitution)],
            "particles": [{"material": "glass", "positions": [[0, 0, z0 * R]], "radius": R,
                           "velocities": [[0, 0, -v]]}],
            "walls": [{"type": "plane", "point": [0, 0, 0], "normal": [0, 0, 1], "material": "glass"}]}


def oblique_rebound(f, v=1.0, restitution=0.9, end=0.004):
    """One bead thrown at 45 degrees on a frictional plane (tangential spring loaded, sliding)."""
    sc = wall_rebound(f, v=v, restitution=restitution, end=end)
    sc["particles"][0]["velocities"] = [[v / 2 ** 0.5, 0, -v / 2 ** 0.5]]
    return sc


def sliding_columns():
    """tests/scenes/par_periodic.toml: 18 columns of 2 beads sliding at 3.5 m/s on a frictional
    floor (periodic x, y), a check every 25 steps."""
    import tomllib
    with open(os.path.join(ROOT, "tests", "scenes", "par_periodic.toml"), "rb") as fh:
        sc = tomllib.load(fh)
    sc["simulation"]["output_interval"] = 25 * sc["simulation"]["time_step"]
    sc.pop("parallel", None)
    return sc


def settle_box(end, out):
    import tomllib
    with open(os.path.join(ROOT, "examples", "settle_box.toml"), "rb") as fh:
        sc = tomllib.load(fh)
    sc["simulation"].update(end_time=end, output_interval=out, checkpoint_interval=0.0)
    return sc


def measure(sc):
    """(max gain ratio over the checks, checks made, outcome, wall rebound e or None)."""
    import dem.energy_guard as EG
    from dem import Simulation
    from dem.simulation import SimulationError
    sim = Simulation.from_dict(sc, base_dir=os.path.join(ROOT, "examples"))
    v0 = sim.state.velocity.copy()
    saved = EG.GAIN_TOLERANCE
    EG.GAIN_TOLERANCE = math.inf
    ke0 = sim.state.kinetic_energy()[0]
    try:
        sim.run(progress=False)
        outcome = "completed"
    except SimulationError as exc:
        outcome = "stopped: " + str(exc)[:80]
    finally:
        EG.GAIN_TOLERANCE = saved
    g = sim.energy_guard
    ke1 = sim.state.kinetic_energy()[0]
    return g.max_ratio, g.prev[0], outcome, ke1 / ke0 if ke0 > 0 else float("nan"), v0


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="settle_box for 0.05 s instead of 0.25 s")
    a = ap.parse_args(argv)
    from dem.energy_guard import GAIN_TOLERANCE
    t0 = time.perf_counter()
    rows = []
    cases = []
    for f in (0.1, 0.2, 0.3):
        for e in (0.5, 0.9, 1.0):
            cases.append((f"3 beads, 0.5 m/s each, e = {e}, dt = {f} t_R", three_beads(f, restitution=e)))
            cases.append((f"wall rebound 1 m/s, e = {e}, dt = {f} t_R", wall_rebound(f, restitution=e)))
    for f in (0.1, 0.3):
        cases.append((f"oblique wall impact 1 m/s at 45 deg, e = 0.9, dt = {f} t_R", oblique_rebound(f)))
    cases.append(("sliding columns (tests/scenes/par_periodic.toml, dt = 0.117 t_R), check every 25 steps",
                   sliding_columns()))
    end = 0.05 if a.quick else 0.25
    cases.append((f"examples/settle_box.toml, {end} s, check every 1 ms", settle_box(end, 0.001)))
    for f in (1.0, 2.0, 2.7):
        cases.append((f"oblique wall impact 1 m/s at 45 deg, e = 0.9, dt = {f} t_R (forced)", oblique_rebound(f)))
        for e in (0.5, 0.9):
            cases.append((f"3 beads, 0.5 m/s each, e = {e}, dt = {f} t_R (forced)", three_beads(f, restitution=e)))
            cases.append((f"wall rebound 0.3 m/s, e = {e}, dt = {f} t_R (forced)",
                          wall_rebound(f, v=0.3, restitution=e, z0=1.0)))
    print(f"| run | checks | max gain / (kinetic + elastic + gravity work) | KE end / KE start | outcome |")
    print("|---|---|---|---|---|")
    for name, sc in cases:
        ratio, steps, outcome, ke, _ = measure(sc)
        rows.append((name, ratio))
        print(f"| {name} | {steps} steps | {ratio:+.3g} | {ke:.3g} | {outcome} |", flush=True)
    print(f"\nGAIN_TOLERANCE = {GAIN_TOLERANCE}; {time.perf_counter() - t0:.0f} s")
    return 0


if __name__ == "__main__":
    sys.exit(main())
