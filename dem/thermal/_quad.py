"""Numerical helpers for the thermal models (njit, allocation-light).

* ``gk_adaptive``: globally adaptive Gauss-Kronrod (G7/K15) quadrature, in the
  spirit of QUADPACK's QAG, for the integral indirect-conduction models
  (Voronoi model A, surrounding layer). The integrand is selected by an
  integer ``kind`` and a tuple of 10 float parameters so that the function can
  be cached by numba (no first-class function arguments).
* ``erfcinv``: inverse complementary error function (needed by the
  Beaulieu 2020 gas-microgap resistance).
"""
import math

import numba
import numpy as np

# Kronrod 15-point nodes / weights and embedded Gauss 7-point weights
# (standard values, as tabulated e.g. in QUADPACK qk15).
_XGK = np.array([
    0.991455371120812639206854697526329,
    0.949107912342758524526189684047851,
    0.864864423359769072789712788640926,
    0.741531185599394439863864773280788,
    0.586087235467691130294144845693013,
    0.405845151377397166906606412076961,
    0.207784955007898467600689403773245,
    0.000000000000000000000000000000000,
])
_WGK = np.array([
    0.022935322010529224963732008058970,
    0.063092092629978553290700663189204,
    0.104790010322250183839876322541518,
    0.140653259715525918745189590510238,
    0.169004726639267902826583426598550,
    0.190350578064785409913256402421014,
    0.204432940075298892414161999234649,
    0.209482141084727828012999174891714,
])
_WG = np.array([
    0.129484966168869693270611432679082,
    0.279705391489276667901467771423780,
    0.381830050505118944950369775488975,
    0.417959183673469387755102040816327,
])

# integrand kinds
KIND_VORONOI_A_PP = 0
KIND_VORONOI_A_PW = 1
KIND_SURR_LAYER_PP = 2
KIND_SURR_LAYER_PW = 3

TWO_PI = 2.0 * math.pi


@numba.njit(cache=True, error_model="numpy")
def _sqrt_pos(x):
    return math.sqrt(x) if x > 0.0 else 0.0


@numba.njit(cache=True, error_model="numpy")
def integrand(kind, r, p):
    """Integrand dH/dr [W/(K m)] of the integral indirect conduction models.

    kind 0 (Voronoi A, particle-particle, Gan 2016 general form, which is
    Cheng 1999 for equal radii), p = (ki, kj, kf, d, Ri, Rj, Di, Dj, rci, rcj):
        2 pi r / [ (b_i - D_i r/rc_i)/k_i + (b_j - D_j r/rc_j)/k_j + (d - b_i - b_j)/k_f ]
    kind 1 (Voronoi A, particle-wall), p = (kp, kf, d, R, rij, ...):
        2 pi r / [ (b - d r/rij)/k_p + (d - b)/k_f ]
    kind 2 (surrounding layer, particle-particle), p = (kf, d, Ri, Rj, S, ...):
        k_f 2 pi r / max(S, d - b_i - b_j)
    kind 3 (surrounding layer, particle-wall), p = (kf, d, R, S, ...):
        k_f 2 pi r / max(S, d - b)
    with b = sqrt(R^2 - r^2). Path lengths are clipped at 0 (an overlapped
    fluid path contributes no resistance).
    """
    if kind == KIND_VORONOI_A_PP:
        ki, kj, kf, d, Ri, Rj, Di, Dj, rci, rcj = p
        bi = _sqrt_pos(Ri * Ri - r * r)
        bj = _sqrt_pos(Rj * Rj - r * r)
        li = bi - Di * r / rci
        lj = bj - Dj * r / rcj
        lf = d - bi - bj
        res = max(li, 0.0) / ki + max(lj, 0.0) / kj + max(lf, 0.0) / kf
        if res <= 0.0:
            return 0.0
        return TWO_PI * r / res
    elif kind == KIND_VORONOI_A_PW:
        kp = p[0]
        kf = p[1]
        d = p[2]
        R = p[3]
        rij = p[4]
        b = _sqrt_pos(R * R - r * r)
        lp = b - d * r / rij
        lf = d - b
        res = max(lp, 0.0) / kp + max(lf, 0.0) / kf
        if res <= 0.0:
            return 0.0
        return TWO_PI * r / res
    elif kind == KIND_SURR_LAYER_PP:
        kf = p[0]
        d = p[1]
        Ri = p[2]
        Rj = p[3]
        S = p[4]
        gap = d - _sqrt_pos(Ri * Ri - r * r) - _sqrt_pos(Rj * Rj - r * r)
        return kf * TWO_PI * r / max(S, gap)
    else:
        kf = p[0]
        d = p[1]
        R = p[2]
        S = p[3]
        gap = d - _sqrt_pos(R * R - r * r)
        return kf * TWO_PI * r / max(S, gap)


@numba.njit(cache=True, error_model="numpy")
def _gk15(kind, a, b, p):
    c = 0.5 * (a + b)
    h = 0.5 * (b - a)
    fc = integrand(kind, c, p)
    resk = fc * _WGK[7]
    resg = fc * _WG[3]
    for j in range(7):
        x = h * _XGK[j]
        f1 = integrand(kind, c - x, p)
        f2 = integrand(kind, c + x, p)
        resk += _WGK[j] * (f1 + f2)
        if j % 2 == 1:
            resg += _WG[j // 2] * (f1 + f2)
    return resk * h, abs((resk - resg) * h)


@numba.njit(cache=True, error_model="numpy")
def gk_adaptive(kind, a, b, p, epsrel=1e-11, epsabs=0.0, maxint=400):
    """Globally adaptive G7/K15 integral of ``integrand(kind, r, p)`` on [a, b].

    Bisects the sub-interval with the largest error estimate until the total
    error estimate is below max(epsabs, epsrel*|I|) or ``maxint`` intervals are
    used. The G7-K15 difference is a very pessimistic error estimate for
    smooth integrands, so the achieved accuracy is usually far better.
    """
    if not (b > a):
        return 0.0
    v, e = _gk15(kind, a, b, p)
    if e <= max(epsabs, epsrel * abs(v)) or maxint <= 1:
        return v  # one panel is enough: return before allocating the work arrays
    lo = np.empty(maxint)
    hi = np.empty(maxint)
    val = np.empty(maxint)
    err = np.empty(maxint)
    lo[0] = a
    hi[0] = b
    val[0] = v
    err[0] = e
    n = 1
    total = v
    etot = e
    while etot > max(epsabs, epsrel * abs(total)) and n < maxint:
        # interval with the largest error
        k = 0
        emax = err[0]
        for i in range(1, n):
            if err[i] > emax:
                emax = err[i]
                k = i
        m = 0.5 * (lo[k] + hi[k])
        if m <= lo[k] or m >= hi[k]:
            break  # cannot subdivide further
        v1, e1 = _gk15(kind, lo[k], m, p)
        v2, e2 = _gk15(kind, m, hi[k], p)
        total += v1 + v2 - val[k]
        etot += e1 + e2 - err[k]
        lo[n] = m
        hi[n] = hi[k]
        val[n] = v2
        err[n] = e2
        hi[k] = m
        val[k] = v1
        err[k] = e1
        n += 1
    # re-sum to avoid cancellation drift
    s = 0.0
    for i in range(n):
        s += val[i]
    return s


@numba.njit(cache=True, error_model="numpy")
def erfcinv(x):
    """Inverse complementary error function, 0 < x < 2 (inf/-inf at 0/2).

    Initial guess from Giles' (2010) single-precision erfinv approximation,
    refined by Halley iterations on erfc(y) - x (double precision).
    """
    if x <= 0.0:
        return np.inf
    if x >= 2.0:
        return -np.inf
    # erfinv(1 - x) initial guess (Giles)
    w = -math.log((2.0 - x) * x)
    z = 1.0 - x
    if w < 5.0:
        w = w - 2.5
        q = 2.81022636e-08
        q = 3.43273939e-07 + q * w
        q = -3.5233877e-06 + q * w
        q = -4.39150654e-06 + q * w
        q = 0.00021858087 + q * w
        q = -0.00125372503 + q * w
        q = -0.00417768164 + q * w
        q = 0.246640727 + q * w
        q = 1.50140941 + q * w
    else:
        w = math.sqrt(w) - 3.0
        q = -0.000200214257
        q = 0.000100950558 + q * w
        q = 0.00134934322 + q * w
        q = -0.00367342844 + q * w
        q = 0.00573950773 + q * w
        q = -0.0076224613 + q * w
        q = 0.00943887047 + q * w
        q = 1.00167406 + q * w
        q = 2.83297682 + q * w
    y = q * z
    c = 2.0 / math.sqrt(math.pi)
    for _ in range(4):
        f = math.erfc(y) - x
        fp = -c * math.exp(-y * y)
        if fp == 0.0:
            break
        # Halley: f'' = -2 y f'
        dy = f / fp
        y = y - dy / (1.0 + y * dy)
    return y
