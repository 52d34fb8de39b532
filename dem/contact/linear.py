"""Linear spring-dashpot contact (Cundall & Strack 1979) with tangential history.

    F_n = k_n delta + c_n v_n,   c_n = A(e) sqrt(m* k_n)
    (A = -2 ln e / sqrt(ln^2 e + pi^2) is exact without the no-attraction clip;
    the 'exact' damping mode solves for A with the clip, see dem.contact.damping)
    F_t = -k_t xi - c_t v_t,     k_t = kt_ratio k_n, c_t = c_n sqrt(kt_ratio)
    |F_t| <= mu F_n, history rescaled when sliding.
The normal stiffness k_n is given in the scene ([contact] normal_stiffness) or derived
from the Hertz stiffness at a characteristic impact velocity (see dem.contact.mixing).
"""
import math
from numba import njit


@njit(cache=True, error_model="numpy")
def linear_spring_dashpot(delta, vn, vtx, vty, vtz, hx, hy, hz,
                          mstar, kn, kt_ratio, damp_a, mu, dt):
    """Returns (F_n >= 0, Ft_x, Ft_y, Ft_z, new history x, y, z, k_n)."""
    cn = damp_a * math.sqrt(mstar * kn)
    fn = kn * delta + cn * vn
    if fn < 0.0:
        fn = 0.0
    kt = kt_ratio * kn
    ct = cn * math.sqrt(kt_ratio)
    hx += vtx * dt
    hy += vty * dt
    hz += vtz * dt
    fx = -kt * hx - ct * vtx
    fy = -kt * hy - ct * vty
    fz = -kt * hz - ct * vtz
    ft2 = fx * fx + fy * fy + fz * fz
    fmax = mu * fn
    if ft2 > fmax * fmax:
        s = fmax / math.sqrt(ft2)
        fx *= s
        fy *= s
        fz *= s
        if kt > 0.0:
            hx = -(fx + ct * vtx) / kt
            hy = -(fy + ct * vty) / kt
            hz = -(fz + ct * vtz) / kt
    return fn, fx, fy, fz, hx, hy, hz, kn
