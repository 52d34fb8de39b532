"""The surrounding-layer integral in the variable w = ln(gap) (see
indirect._surrounding_layer_pp): int 2 pi r dr / gap = pi int (du/dgap) dw with u = r^2 and
du/dgap = 2 b_i b_j / (d - gap), b_i,j = ((d - gap) +- (Ri^2 - Rj^2)/(d - gap))/2 (the
intersection circle of the two spheres brought to centre distance d - gap, so u(gap) is
closed-form). In r the integrand 1/gap spans five orders of magnitude near contact; in
ln(gap) it is a smooth rational function of gap, and one G7/K15 panel is exact to round-off.
Kept apart from _quad.gk_adaptive (the Voronoi A quadrature), whose compiled speed is
sensitive to what shares its module.
"""
import math

import numba

from ._quad import _WG, _WGK, _XGK


@numba.njit(cache=True, error_model="numpy")
def _surr_log_panel(a, b, d, Ri, Rj):
    """G7/K15 panel of f(w) = 2 b_i b_j / D on [a, b], D = d - exp(w),
    b_i,j = (D +- (Ri^2 - Rj^2)/D)/2; returns (K15 value, |K15 - G7|)."""
    c = 0.5 * (a + b)
    h = 0.5 * (b - a)
    dr2 = Ri * Ri - Rj * Rj
    resk = 0.0
    resg = 0.0
    for j in range(15):
        x = c + h * (_XGK[j] if j < 8 else -_XGK[14 - j])
        D = d - math.exp(x)
        q = dr2 / D
        f = 2.0 * max(0.5 * (D + q), 0.0) * max(0.5 * (D - q), 0.0) / D
        k = j if j < 8 else 14 - j
        resk += _WGK[k] * f
        if k % 2 == 1:  # the G7 nodes: odd Kronrod indices, the centre (7) included
            resg += _WG[k // 2] * f
    return resk * h, abs((resk - resg) * h)


@numba.njit(cache=True, error_model="numpy")
def surrounding_layer_log(wa, wb, d, Ri, Rj, epsrel):
    """int_{wa}^{wb} 2 b_i b_j / (d - e^w) dw, w = ln(gap) (the surrounding-layer integral
    int 2 pi r dr / gap divided by pi; see indirect._surrounding_layer_pp): composite G7/K15
    on n = 1, 2, 4, ... 256 equal panels until the summed |K15 - G7| <= epsrel |I|."""
    n = 1
    while True:
        h = (wb - wa) / n
        v = 0.0
        e = 0.0
        for i in range(n):
            vi, ei = _surr_log_panel(wa + i * h, wa + (i + 1) * h, d, Ri, Rj)
            v += vi
            e += ei
        if e <= epsrel * abs(v) or n >= 256:
            return v
        n *= 2
