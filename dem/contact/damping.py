"""Viscous damping coefficient from the restitution coefficient.

For the Hertz law the normal damping is c_n = A sqrt(m* E* sqrt(R*)) delta^(1/4); in
dimensionless form (delta = L x, t = L/v0 tau, L = (m* v0^2/k')^(2/5)) the collision is

    x'' = -x^(3/2) - g x^(1/4) x',   g = A sqrt(3/4),   x(0) = 0, x'(0) = 1

and its restitution does not depend on the impact speed (Tsuji, Tanaka & Ishida 1992;
Antypov & Elliott, EPL 94 (2011) 50004). The force is clipped at zero (no attraction),
so the particles separate when the force vanishes. ``exact`` finds g by bisection on
the numerically integrated collision (RK4, 2e5 steps, e reproduced to < 1e-6), instead of
the linear-oscillator formula A = -2 sqrt(5/6) beta sqrt(2) (LIGGGHTS, ``tsuji_liggghts``),
which misses the target restitution by a few per cent at e = 0.5.
The linear spring-dashpot (x'' = -x - g x', g = A) is treated the same way.
"""
import json
import math
import os

import numpy as np
from numba import njit


@njit(cache=True, error_model="numpy")
def _accel(x, u, g, hertz):
    if x <= 0.0:
        return 0.0
    if hertz:
        f = x * math.sqrt(x) + g * math.sqrt(math.sqrt(x)) * u
    else:
        f = x + g * u
    return -f if f > 0.0 else 0.0


@njit(cache=True, error_model="numpy")
def collision_restitution(g, hertz):
    """Restitution of the dimensionless damped collision with damping g."""
    h = 2e-5
    x = 0.0
    u = 1.0
    for _ in range(2000000):
        k1x = u
        k1u = _accel(x, u, g, hertz)
        k2x = u + 0.5 * h * k1u
        k2u = _accel(x + 0.5 * h * k1x, k2x, g, hertz)
        k3x = u + 0.5 * h * k2u
        k3u = _accel(x + 0.5 * h * k2x, k3x, g, hertz)
        k4x = u + h * k3u
        k4u = _accel(x + h * k3x, k4x, g, hertz)
        xn = x + h / 6.0 * (k1x + 2 * k2x + 2 * k3x + k4x)
        un = u + h / 6.0 * (k1u + 2 * k2u + 2 * k3u + k4u)
        if xn <= 0.0 and un < 0.0:
            return -un
        if un < 0.0 and _accel(xn, un, g, hertz) == 0.0:
            return -un  # force vanished: free flight from here on
        x = xn
        u = un
    return -u


@njit(cache=True, error_model="numpy")
def _solve_g(e, hertz):
    if e >= 1.0:
        return 0.0
    lo = 0.0
    hi = 1.0
    while collision_restitution(hi, hertz) > e:
        hi *= 2.0
    for _ in range(60):
        mid = 0.5 * (lo + hi)
        if collision_restitution(mid, hertz) > e:
            lo = mid
        else:
            hi = mid
        if hi - lo < 1e-10 * hi:
            break
    return 0.5 * (lo + hi)


_CACHE = {}
MEMO = "damping_factors.json"   # beside Numba's cache, in the folder keyed by the sources' digest


def _memo_path():
    import numba
    return os.path.join(numba.config.CACHE_DIR, MEMO) if numba.config.CACHE_DIR else None


def _memo_read():
    """The factors solved by earlier processes ({"e model": g}), {} when there are none or
    the file cannot be read (a cache: solved again then)."""
    path = _memo_path()
    try:
        with open(path) as fh:
            memo = json.load(fh)
        return memo if isinstance(memo, dict) else {}
    except (OSError, ValueError, TypeError):
        return {}


def _memo_add(name, g):
    """Add one solved factor (written whole, by rename: a reader never sees half a file; two
    processes adding at once may keep only one of their entries, and the other is solved again
    next time). Silent when the folder cannot be written: the factor is only not kept."""
    path = _memo_path()
    if path is None:
        return
    memo = _memo_read()
    memo[name] = g
    tmp = f"{path}.{os.getpid()}.tmp"
    try:
        os.makedirs(os.path.dirname(path), exist_ok=True)
        with open(tmp, "w") as fh:
            json.dump(memo, fh)
        os.replace(tmp, path)
    except OSError:
        try:
            os.unlink(tmp)
        except OSError:
            pass


def damping_factor(e, model, damping):
    """Factor A of c_n for restitution e.

    model: 0 Hertz, 1 linear; damping: 0 exact, 1 tsuji_liggghts (closed form).
    The exact factor's bisection (about 0.3 s) is solved once per restitution and kept, in this
    process and in a file beside Numba's cache (MEMO, in the folder keyed by the sources'
    digest, so an edit of the solver solves again): later runs read the same bits.
    """
    e = float(e)
    if damping == 1:
        if e >= 1.0:
            return 0.0
        beta = math.log(e) / math.sqrt(math.log(e) ** 2 + math.pi ** 2)
        return -2.0 * math.sqrt(5.0 / 6.0) * beta * math.sqrt(2.0) if model == 0 else -2.0 * beta
    key = (round(e, 14), model)
    if key not in _CACHE:
        name = f"{key[0]!r} {'hertz' if model == 0 else 'linear'}"
        g = _memo_read().get(name)
        if not isinstance(g, float) or not math.isfinite(g):
            g = _solve_g(e, model == 0)
            _memo_add(name, g)
        _CACHE[key] = g / math.sqrt(0.75) if model == 0 else g
    return _CACHE[key]


def hertz_collision_time(mstar, rstar, estar, v):
    """Hertz contact duration of an elastic impact: t_c = 2.868 (m*^2/(R* E*^2 v))^(1/5)."""
    return 2.8682 * (mstar ** 2 / (rstar * estar ** 2 * max(v, 1e-12))) ** 0.2


def rayleigh_time(radius, density, shear_modulus, poisson):
    """Rayleigh wave critical step pi R sqrt(rho/G) / (0.1631 nu + 0.8766)."""
    return math.pi * radius * math.sqrt(density / shear_modulus) / (0.1631 * poisson + 0.8766)


def mixed_tables(materials):
    """Pair tables (n_mat x n_mat) of E*, G*, restitution, friction, rolling friction.

    E* = 1/((1-nu_i^2)/E_i + (1-nu_j^2)/E_j), G* = 1/(2(2-nu_i)(1+nu_i)/E_i + ...),
    restitution, friction and rolling friction: arithmetic mean of the two materials.
    """
    n = len(materials)
    E = np.array([m["youngs_modulus"] for m in materials], float)
    nu = np.array([m["poisson_ratio"] for m in materials], float)
    e = np.array([m["restitution"] for m in materials], float)
    mu = np.array([m["friction"] for m in materials], float)
    mur = np.array([m.get("rolling_friction", 0.0) for m in materials], float)
    estar = 1.0 / ((1 - nu[:, None] ** 2) / E[:, None] + (1 - nu[None, :] ** 2) / E[None, :])
    gstar = 1.0 / (2 * (2 - nu[:, None]) * (1 + nu[:, None]) / E[:, None]
                   + 2 * (2 - nu[None, :]) * (1 + nu[None, :]) / E[None, :])
    avg = lambda a: 0.5 * (a[:, None] + a[None, :])  # noqa: E731
    return dict(estar=np.ascontiguousarray(estar), gstar=np.ascontiguousarray(gstar),
                restitution=avg(e), friction=avg(mu), rolling_friction=avg(mur), n=n)
