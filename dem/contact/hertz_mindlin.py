"""Hertz-Mindlin no-slip contact with tangential history.

References
----------
* Hertz (1882), Mindlin (1949) no-slip tangential stiffness; the form used by
  Di Renzo & Di Maio, Chem. Eng. Sci. 59 (2004) 525 and by LIGGGHTS
  ``gran model hertz tangential history``:
    k_n = 4/3 E* sqrt(R* delta)         (F_n,el = k_n delta)
    S_t = 8 G* sqrt(R* delta)           (tangential stiffness, F_t,el = -S_t xi)
    F_n damping = c_n delta^(1/4) v_n   c_n = A(e) sqrt(m* E* sqrt(R*))
    F_t damping = c_t v_t,              c_t = c_n delta^(1/4) sqrt(S_t / S_n), S_n = 2 E* sqrt(R* delta)
* ``A(e)`` is either the exact value that reproduces the restitution coefficient e
  for the damped Hertz oscillator with no attraction (solved once per material pair,
  see :mod:`dem.contact.damping`), or LIGGGHTS' approximation
  A = -2 sqrt(5/6) beta sqrt(2), beta = ln e / sqrt(ln^2 e + pi^2) (Tsuji et al. 1992 form).
* The tangential spring's turn and Coulomb cap: dem.contact.tangential (``rescaled``, Luding
  2008, the default; ``projected``, Silbert et al. 2001 as LAMMPS and LIGGGHTS).
"""
import math
from numba import njit

from .tangential import luding_2008_cap, silbert_2001_cap


@njit(cache=True, error_model="numpy", fastmath={"nsz", "arcp", "contract", "afn", "reassoc"})
def hertz_mindlin(delta, vn, vtx, vty, vtz, hx, hy, hz,
                  rstar, mstar, estar, gstar, damp_a, mu, ctr, dt, ton):
    """Hertz-Mindlin pair force.

    delta: overlap (m, > 0); vn: normal approach speed (m/s, > 0 approaching);
    vt*: tangential relative velocity of the contact point; h*: tangential
    spring history (m) already in the tangent plane; ctr: sqrt(4 G* / E*), the ratio
    c_t / c_n of the material pair (dem.step TAB.ctr, tabulated once by dem.world.pair_tables).
    ton: the tangential model as a type (None rescaled, True projected; dem.contact.tangential).
    Returns (F_n >= 0, Ft_x, Ft_y, Ft_z, new history x, y, z, k_n).
    """
    sq = math.sqrt(rstar * delta)
    kn = 4.0 / 3.0 * estar * sq
    # c_n = A sqrt(m* E* sqrt(R*)) delta^(1/4) = A sqrt(m* E* sqrt(R* delta)): one root
    cn = damp_a * math.sqrt(mstar * estar * sq)
    fn = kn * delta + cn * vn
    if fn < 0.0:
        fn = 0.0
    st = 8.0 * gstar * sq
    # c_t = c_n sqrt(S_t / S_n) = c_n sqrt(4 G* / E*)  (S_n = 2 E* sqrt(R* delta)): the root of
    # a material constant, from the table (the same rounding as computed here: sqrt and / are exact)
    ct = cn * ctr
    # the model's branch on this function's own argument: Numba removes the other before typing
    if ton is not None:
        fx, fy, fz, hx, hy, hz = silbert_2001_cap(hx, hy, hz, vtx, vty, vtz, st, ct, fn, mu, dt)
    else:
        fx, fy, fz, hx, hy, hz = luding_2008_cap(hx, hy, hz, vtx, vty, vtz, st, ct, fn, mu, dt)
    return fn, fx, fy, fz, hx, hy, hz, 2.0 * estar * sq
