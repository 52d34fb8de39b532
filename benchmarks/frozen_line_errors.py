"""Transient and steady-state errors of the frozen-bed integrators on the line of ten, the
figures behind ``integrator = "auto"`` (dem/thermal/step_error.py: choose).

    python benchmarks/frozen_line_errors.py [INTEGRATORS] [RATIOS]
    python benchmarks/frozen_line_errors.py exponential,trbdf2,implicit 0.01,0.1,1,10,100,1000

The line of tests/test_thermal_implicit.py (ten spheres of 1 mm, k_p = 1 W/(m K), walls at
400 and 300 K, from a linear 350 -> 300 K profile: a 50 K jump at the hot wall) at dt = ratio x
the network limit min C_i / sum H_ij, against the exact modal solution of the conductance
network: the largest |T - T_exact| over the steps to t = 12 / lam_min, then the distance to the
exact steady state after 40 / lam_min more (K; divide by 100 K for the fractions of the table).
"""
import math
import os
import sys

import numpy as np

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
sys.path.insert(0, ROOT)
sys.path.insert(0, os.path.join(ROOT, "tests"))

from test_thermal_implicit import line, modes  # noqa: E402


def main(argv=None):
    argv = sys.argv[1:] if argv is None else argv
    integs = (argv[0] if argv else "exponential,trbdf2,implicit,auto").split(",")
    ratios = [float(x) for x in (argv[1] if len(argv) > 1 else "0.01,0.03,0.1,0.3,1,3,10,30,100,1000").split(",")]
    lim = line(1.0).thermal.network_limit()
    print(f"network limit {lim:.6g} s")
    for integ in integs:
        for r in ratios:
            dt = r * lim
            sim = line(dt, integ)
            Tss, lam, U, c = modes(sim)
            nsteps = max(int(math.ceil(12.0 / lam[0] / dt)), 1)
            worst = 0.0
            for _ in range(nsteps):
                sim.step(1)
                exact = Tss + U @ (c * np.exp(-lam * sim.time))
                worst = max(worst, float(np.abs(sim.state.temperature - exact).max()))
            sim.step(int(math.ceil(40.0 / lam[0] / dt)) + 200)
            ss = float(np.abs(sim.state.temperature - Tss).max())
            print(f"{integ:12s} dt/limit {r:8g} ({sim.thermal.cfg['integrator']:11s}) steps {nsteps:6d}  "
                  f"largest transient error {worst:.3e} K  steady-state error {ss:.3e} K", flush=True)


if __name__ == "__main__":
    main()
