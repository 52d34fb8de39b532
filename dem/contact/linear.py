"""Linear spring-dashpot contact (Cundall & Strack 1979) with tangential history.

    F_n = k_n delta + c_n v_n,   c_n = A(e) sqrt(m* k_n)
    (A = -2 ln e / sqrt(ln^2 e + pi^2) is exact without the no-attraction clip;
    the 'exact' damping mode solves for A with the clip, see dem.contact.damping)
    F_t = -k_t xi - c_t v_t,     k_t = kt_ratio k_n, c_t = c_n sqrt(kt_ratio)
    |F_t| <= mu F_n: the spring's turn and cap by the tangential model (dem.contact.tangential).
The normal stiffness k_n is given in the scene ([contact] normal_stiffness) or derived
from the Hertz stiffness at a characteristic impact velocity (see dem.contact.mixing).
"""
import math
from numba import njit

from .tangential import luding_2008_cap, silbert_2001_cap


@njit(cache=True, error_model="numpy")
def linear_spring_dashpot(delta, vn, vtx, vty, vtz, hx, hy, hz,
                          mstar, kn, kt_ratio, damp_a, mu, dt, ton):
    """Returns (F_n >= 0, Ft_x, Ft_y, Ft_z, new history x, y, z, k_n). ton: the tangential model
    as a type (None rescaled, True projected; dem.contact.tangential)."""
    cn = damp_a * math.sqrt(mstar * kn)
    fn = kn * delta + cn * vn
    if fn < 0.0:
        fn = 0.0
    kt = kt_ratio * kn
    ct = cn * math.sqrt(kt_ratio)
    if ton is not None:   # (removed before typing for the other model)
        fx, fy, fz, hx, hy, hz = silbert_2001_cap(hx, hy, hz, vtx, vty, vtz, kt, ct, fn, mu, dt)
    else:
        fx, fy, fz, hx, hy, hz = luding_2008_cap(hx, hy, hz, vtx, vty, vtz, kt, ct, fn, mu, dt)
    return fn, fx, fy, fz, hx, hy, hz, kn
