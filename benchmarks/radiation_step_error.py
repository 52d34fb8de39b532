"""Error of the exponential heat integrator with radiation against the step / radiation limit.

    python benchmarks/radiation_step_error.py

A single 1 mm glass bead (emissivity 0.8) radiating (zhou_2009, no neighbour: to the gas at
T_env) from T0 to T_env, cooling 1200 -> 300 K and heating 300 -> 1200 K, with
thermal.integrator = "exponential" and dt = f x radiation_step_limit (the limit of `dem
check`, C / (4 eps sigma A T_max^3)). Error: the largest |T - T_exact| over the steps, in % of
|T0 - T_env|, T_exact from the ODE C dT/dt = eps sigma A (T_env^4 - T^4) (SciPy, rtol 1e-11).
Pure radiation is the worst case: conduction, handled exactly by the exponential update,
only dilutes the error. dem.thermal.kernel.RADIATION_EXPONENTIAL_ERROR holds this curve
(the larger of the two directions) for `dem check`.
"""
import math
import os
import sys

HERE = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, os.path.dirname(HERE))

import numpy as np  # noqa: E402

R = 1e-3
SIGMA = 5.670374419e-8
MAT = dict(name="p", density=2500.0, youngs_modulus=1e7, poisson_ratio=0.3, restitution=0.5, friction=0.3,
           thermal_conductivity=1.0, heat_capacity=840.0, emissivity=0.8)
RATIOS = [0.25, 0.5, 1.0, 2.0, 4.0, 8.0, 16.0, 32.0]


def scene(T0, Tenv, dt, end):
    return {"simulation": {"time_step": 1e-5, "end_time": end, "mechanics": False, "gravity": [0, 0, 0]},
            "domain": {"min": [-0.01] * 3, "max": [0.01] * 3}, "materials": [dict(MAT)],
            "particles": [{"material": "p", "positions": [[0, 0, 0]], "radius": R, "temperature": T0}],
            "thermal": {"direct": "none", "radiation": "zhou_2009", "time_step": dt, "integrator": "exponential",
                        "porosity": "global"},
            "gas": {"conductivity": 0.026, "density": 1.2, "viscosity": 1.8e-5, "heat_capacity": 1005.0,
                    "temperature": Tenv, "porosity": 1.0}}


def error(T0, Tenv, f):
    """(dt / limit, max error in % of |T0 - Tenv|)."""
    from scipy.integrate import solve_ivp
    from dem import Simulation
    probe = Simulation.from_dict(scene(T0, Tenv, 1.0, 1.0))
    lim = probe.check()["radiation_step_limit"]
    dt = f * lim
    nsteps = max(int(math.ceil(20 * lim / dt)), 4)
    sim = Simulation.from_dict(scene(T0, Tenv, dt, nsteps * dt))
    C = 1.0 / sim.state.inv_heat_capacity[0]
    A = 4 * math.pi * R ** 2
    T = [T0]
    for _ in range(nsteps):
        sim.step(1)
        T.append(float(sim.state.temperature[0]))
    t = dt * np.arange(nsteps + 1)
    sol = solve_ivp(lambda _t, y: [0.8 * SIGMA * A * (Tenv ** 4 - y[0] ** 4) / C], (0, t[-1]), [T0],
                    t_eval=t, rtol=1e-11, atol=1e-9, method="LSODA")
    return dt / lim, 100 * float(np.max(np.abs(np.array(T) - sol.y[0]))) / abs(T0 - Tenv)


def main():
    print("| dt / radiation limit | error, cooling 1200 -> 300 K [% of 900 K] | error, heating 300 -> 1200 K "
          "[% of 900 K] |")
    print("|---|---|---|")
    curve = []
    for f in RATIOS:
        _, ec = error(1200.0, 300.0, f)
        _, eh = error(300.0, 1200.0, f)
        curve.append((f, max(ec, eh)))
        print(f"| {f:g} | {ec:.3g} | {eh:.3g} |", flush=True)
    print("\nRADIATION_EXPONENTIAL_ERROR = (" + ", ".join(f"({f:g}, {e:.3g})" for f, e in curve) + ")")
    return 0


if __name__ == "__main__":
    sys.exit(main())
