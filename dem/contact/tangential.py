"""The tangential spring of a contact with history: how it follows the turning contact plane
and how the Coulomb limit caps it. Two named models (scene key ``[contact] tangential``,
:data:`dem.contact.registry.TANGENTIAL_MODELS`), shared by the Hertz-Mindlin and the linear
laws; ``S_t`` the tangential stiffness, ``c_t`` the tangential damping coefficient, ``xi`` the
stored spring (m), ``v_t`` the tangential velocity of the contact point:

* ``rescaled`` (default): Luding, Granular Matter 10 (2008) 235, sec. 2.2.2, and Di Renzo &
  Di Maio (2004). The spring is turned onto the new tangent plane keeping its length,
      xi' = |xi| (xi - (xi.n) n) / |xi - (xi.n) n|,
  then xi += v_t dt, F_t = -S_t xi - c_t v_t, and where |F_t| > mu F_n the whole force is scaled to
  mu F_n and the spring set back to the length that gives it, xi = -(F_t + c_t v_t) / S_t.
* ``projected``: Silbert et al., Phys. Rev. E 64 (2001) 051302, eq. (3)-(4), in the form of
  LAMMPS ``pair gran/hertz/history`` and LIGGGHTS ``tangential_model history`` (the shared
  benchmark scene's law, ../shared/bench). The spring loses its normal part,
      xi' = xi - (xi.n) n             (shorter by the cosine of the turn),
  then xi += v_t dt; the cap compares the spring force alone with mu F_n:
      |S_t xi| > mu F_n:  F_t = -S_t xi mu F_n / |S_t xi|,  xi = -F_t / S_t  (sliding, no dashpot)
      otherwise:          F_t = -S_t xi - c_t v_t                          (sticking)
  Adding v_t dt before or after the projection is the same, v_t being in the tangent plane;
  LIGGGHTS compares |S_t xi| and mu |F_n| through a root, this through their squares (the same
  test up to rounding), and it scales the spring by the force's ratio (-F_t / S_t up to
  rounding). LIGGGHTS without ``limitForce`` lets the damped F_n go negative; the laws here
  clip it at 0 in both models.

The rescaled turn costs a division and a root per contact that the projection does not: on the
shared beds the projected model's step is 7-9 % shorter (docs/notebook.md). The laws
(dem.contact.hertz_mindlin, dem.contact.linear) and dem.step._rotate_history choose between the
functions below on their argument ``ton``, the model as a type (None rescaled, True projected),
so that Numba removes the other model's code before typing: as a run-time switch the model made
the pair loop 5-15 % slower whichever model ran.
"""
import math
from numba import njit

from .registry import TANGENTIAL_MODELS

# the projected model's id in ip[IP.tangential] (a module constant, as compiled code reads it)
TANGENTIAL_PROJECTED = TANGENTIAL_MODELS["projected"]


@njit(cache=True, error_model="numpy", inline="always")
def luding_2008_turn(hx, hy, hz, ux, uy, uz, inv_u2):
    """The spring (hx, hy, hz) turned onto the plane normal to (ux, uy, uz), whose squared
    length is 1 / inv_u2, keeping its length (Luding 2008)."""
    old2 = hx * hx + hy * hy + hz * hz
    if old2 == 0.0:
        return 0.0, 0.0, 0.0
    hn = (hx * ux + hy * uy + hz * uz) * inv_u2
    hx -= hn * ux
    hy -= hn * uy
    hz -= hn * uz
    new2 = hx * hx + hy * hy + hz * hz
    if new2 > 0.0:
        sc = math.sqrt(old2 / new2)
        return hx * sc, hy * sc, hz * sc
    return 0.0, 0.0, 0.0


@njit(cache=True, error_model="numpy", inline="always")
def silbert_2001_turn(hx, hy, hz, ux, uy, uz, inv_u2):
    """The spring (hx, hy, hz) less its part along (ux, uy, uz), whose squared length is
    1 / inv_u2 (Silbert et al. 2001; LAMMPS and LIGGGHTS history)."""
    hn = (hx * ux + hy * uy + hz * uz) * inv_u2
    return hx - hn * ux, hy - hn * uy, hz - hn * uz


@njit(cache=True, error_model="numpy", inline="always")
def luding_2008_cap(hx, hy, hz, vtx, vty, vtz, st, ct, fn, mu, dt):
    """xi += v_t dt, F_t = -S_t xi - c_t v_t, capped at mu F_n with the spring set back
    (Luding 2008). (hx, hy, hz): the turned spring. Returns (F_t x, y, z, spring x, y, z)."""
    hx += vtx * dt
    hy += vty * dt
    hz += vtz * dt
    fx = -st * hx - ct * vtx
    fy = -st * hy - ct * vty
    fz = -st * hz - ct * vtz
    ft2 = fx * fx + fy * fy + fz * fz
    fmax = mu * fn
    if ft2 > fmax * fmax:
        ft = math.sqrt(ft2)
        s = fmax / ft
        fx *= s
        fy *= s
        fz *= s
        if st > 0.0:
            hx = -(fx + ct * vtx) / st
            hy = -(fy + ct * vty) / st
            hz = -(fz + ct * vtz) / st
    return fx, fy, fz, hx, hy, hz


@njit(cache=True, error_model="numpy", inline="always")
def silbert_2001_cap(hx, hy, hz, vtx, vty, vtz, st, ct, fn, mu, dt):
    """xi += v_t dt; the spring force -S_t xi capped at mu F_n (sliding: the spring scaled with
    it, no dashpot), else -S_t xi - c_t v_t (Silbert et al. 2001; LIGGGHTS tangential history).
    (hx, hy, hz): the turned spring. Returns (F_t x, y, z, spring x, y, z)."""
    hx += vtx * dt
    hy += vty * dt
    hz += vtz * dt
    h2 = hx * hx + hy * hy + hz * hz
    fmax = mu * fn
    if st * st * h2 > fmax * fmax:
        s = fmax / (st * math.sqrt(h2))
        hx *= s
        hy *= s
        hz *= s
        return -st * hx, -st * hy, -st * hz, hx, hy, hz
    return -st * hx - ct * vtx, -st * hy - ct * vty, -st * hz - ct * vtz, hx, hy, hz
