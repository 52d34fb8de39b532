"""Expected error of the exponential heat update with radiation beyond its step limit.

Measured by benchmarks/radiation_step_error.py: one bead (emissivity 0.8) radiating alone,
cooling 1200 -> 300 K and heating 300 -> 1200 K, exponential update at dt = f x the
radiation limit C / (4 eps sigma A T_max^3) of `dem check`; the largest |T - T_exact| over
the steps in % of the temperature change, the larger of the two directions, made
non-decreasing in f (at very large steps the update jumps to the end state, so fewer
intermediate values are seen; the error of the transient does not shrink). Radiation alone is
the worst case: conduction, integrated exactly by the exponential update, dilutes it (the
stability map's frozen bed, docs/benchmarks.md: 1.4 % at 10 s, 3.8 % at 20 s).
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

