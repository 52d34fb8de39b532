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
