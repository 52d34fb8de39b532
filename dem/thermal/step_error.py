"""Expected error of the exponential heat update with radiation beyond its step limit.

Measured by benchmarks/radiation_step_error.py: one bead (emissivity 0.8) radiating alone,
cooling 1200 -> 300 K and heating 300 -> 1200 K, exponential update at dt = f x the
radiation limit C / (4 eps sigma A T_max^3) of `dem check`; the largest |T - T_exact| over
the steps in % of the temperature change, the larger of the two directions, made
non-decreasing in f (at very large steps the update jumps to the end state, so fewer
intermediate values are seen; the error of the transient does not shrink). Radiation alone is
the worst case: conduction, integrated exactly by the exponential update, dilutes it (the
stability map's frozen bed, docs/benchmarks/stability.md: 1.4 % at 10 s, 3.8 % at 20 s).
"""
import math

import numpy as np

# (dt / radiation limit, error in % of the temperature change)
RADIATION_EXPONENTIAL_ERROR = ((0.25, 2.0), (0.5, 3.84), (1.0, 7.17), (2.0, 13.6), (4.0, 24.4), (8.0, 29.9))


def expected_radiation_error(ratio):
    """Expected error (% of the temperature change) at dt = ratio x the radiation limit,
    interpolated in log(ratio) on the measured curve (flat beyond its ends)."""
    pts = RADIATION_EXPONENTIAL_ERROR
    if ratio <= pts[0][0]:
        return pts[0][1] * ratio / pts[0][0]
    for (f0, e0), (f1, e1) in zip(pts, pts[1:]):
        if ratio <= f1:
            w = math.log(ratio / f0) / math.log(f1 / f0)
            return e0 + w * (e1 - e0)
    return pts[-1][1]


# ---------------------------------------------------------------- frozen packings: auto's choice
def amplification(name, z):
    """Per-step amplification R(z) of a mode of rate lam of C dT/dt = -A T at z = lam dt
    (numpy array z >= 0): backward Euler ("implicit") 1 / (1 + z); TR-BDF2 ("trbdf2", gamma =
    2 - sqrt 2) the trapezoidal factor (1 - gamma z / 2) / (1 + gamma z / 2) followed by the BDF2
    stage, (R_tr / (gamma (2 - gamma)) - (1 - gamma)^2 / (gamma (2 - gamma))) / (1 + w z),
    w = (1 - gamma) / (2 - gamma) (dem.thermal.heat._trbdf2_step)."""
    z = np.asarray(z, float)
    if name == "implicit":
        return 1.0 / (1.0 + z)
    g = 2.0 - math.sqrt(2.0)
    rt = (1.0 - 0.5 * g * z) / (1.0 + 0.5 * g * z)
    k = g * (2.0 - g)
    return (rt / k - (1.0 - g) ** 2 / k) / (1.0 + (1.0 - g) / (2.0 - g) * z)


def mode_error(name, zmax):
    """Largest error of a mode's amplitude, max over its rate (z = lam dt in (0, zmax]) and the
    step count n >= 1 of |R(z)^n - exp(-n z)|, as a fraction of the mode's initial amplitude:
    the transient error of the scheme ``name`` ("implicit" or "trbdf2") on a linear network
    whose fastest rate times dt is at most zmax, in the worst case over the modes (grids of
    z and n geometric, 2 % apart: the maximum is found to about 1 %)."""
    if zmax <= 0.0:
        return 0.0
    z = np.geomspace(min(1e-4, zmax), zmax, 600)[:, None]
    n = np.unique(np.geomspace(1, 1e8, 1000).astype(np.int64)).astype(float)[None, :]
    R = amplification(name, z)
    with np.errstate(under="ignore"):
        err = np.abs(np.sign(R) ** n * np.abs(R) ** n - np.exp(-n * z))
    return float(err.max())


# auto runs TR-BDF2 up to this many network limits, backward Euler beyond (choose)
TRBDF2_MAX_RATIO = 80.0


def choose(dt, network_limit, radiation_limit):
    """``integrator = "auto"`` on a frozen packing: the integrator and why, with its expected
    errors at this step, as a dict (integrator, integrator_reason, expected_transient_error,
    expected_steady_error: text for `dem check`; auto_ratio, auto_zmax, auto_transient,
    auto_steady: numbers).

    The candidates are TR-BDF2 and backward Euler, both exact at steady state at
    any step (fixed point Q(T) = 0); the exponential update is not (benchmarks/frozen_line_errors.py:
    0.45 % of the wall-to-wall difference at the network limit, 9.9 % from 30 limits on). TR-BDF2 runs
    up to TRBDF2_MAX_RATIO = 80 network limits, backward Euler beyond, by the measured errors
    (docs/benchmarks/accuracy.md, "Line of ten", "Frozen packed bed heated from its floor"): on the
    Beaulieu-size bed TR-BDF2 is 230 to 24,000 x more accurate than backward Euler and 1,700 to
    2,400 x more than the exponential update from 0.03 to 3.4 limits, and its largest transient
    error on the line of ten is 1.9 to 2.3 x below the exponential update's at and below the limit;
    the largest transient error of the line of ten (a 50 K jump at the hot wall;
    benchmarks/frozen_line_errors.py) is TR-BDF2's
    2.8 / 5.6 / 5.97 K against backward Euler's 5.7 / 6.2 / 6.5 K at 3 / 40 / 70 limits, and
    6.2 / 3.2 K against 5.9 / 0.82 K at 100 / 1000 limits, where the step is beyond every time
    scale of the network and the L-stable damping of backward Euler, 1 / (1 + z) against
    TR-BDF2's about 4.8 / z for stiff modes, wins (besides costing one solve a step, not two).

    The expected transient error stated is the worst mode's, mode_error(name, zmax) with zmax =
    dt (2 / network limit + 1 / radiation limit) >= lam_max dt (Gershgorin: every rate of the
    network is at most max_i (2 sum_j H_ij + K_i) / C_i): a bound, as a fraction of a mode's
    initial amplitude, that stiff modes of little amplitude reach.

    The choice is the same on any number of MPI ranks: there the solvers run with global sums
    (dem.thermal.implicit_mpi), to the same tolerance."""
    zmax = dt * (2.0 / network_limit + (1.0 / radiation_limit if radiation_limit > 0 else 0.0))
    ratio = dt / network_limit
    out = dict(auto_zmax=zmax, auto_ratio=ratio)
    rad = (f" and {dt / radiation_limit:.3g} x the radiation limit" if math.isfinite(radiation_limit) else "")
    if math.isfinite(network_limit):
        at = f"dt = {ratio:.3g} x the network limit{rad}"
    else:   # no pair or fixed-temperature wall conductance (e.g. convection only)
        at = f"no conduction network{rad}"
    if ratio <= TRBDF2_MAX_RATIO:
        name, why = "trbdf2", f"second order, L-stable, up to {TRBDF2_MAX_RATIO:g} network limits"
    else:
        name, why = "implicit", (f"beyond {TRBDF2_MAX_RATIO:g} network limits the step outruns the network's time "
                                 f"scales and backward Euler damps them best")
    err = mode_error(name, zmax)
    out.update(integrator=name, auto_steady=0.0, auto_transient=err,
               integrator_reason=f"{at}: {why}",
               expected_transient_error=(f"at most {100 * err:.2g} % of a mode's initial amplitude (worst mode, "
                                         f"lam dt <= {zmax:.3g})"),
               expected_steady_error="exact (fixed point Q(T) = 0, to the solver tolerance 1e-10 of the heat "
                                     "rates)")
    return out
