"""Rolling resistance models (Ai, Chen, Rotter & Ooi, Powder Technol. 206 (2011) 269).

* ``constant_torque`` (model A, constant directional torque):
      M_r = -mu_r R* F_n  w_rel / |w_rel|
* ``epsd`` (model C, elastic-plastic spring-dashpot):
      k_r = 2.25 k_n mu_r^2 R*^2,  M_r^k += -k_r dtheta_r,  |M_r^k| <= mu_r R* F_n,
      viscous part  M_r^d = -eta_r 2 sqrt(I_r k_r) w_rel, active only while the
      spring is not fully mobilised (Ai et al. eq. 17-21), I_r the reduced rolling inertia.
w_rel is the relative angular velocity projected on the tangent plane.
"""
import math
from numba import njit


@njit(cache=True, error_model="numpy")
def constant_torque(wx, wy, wz, rstar, fn, mur):
    """Model A: torque on particle i (the opposite on j)."""
    w = math.sqrt(wx * wx + wy * wy + wz * wz)
    if w < 1e-300:
        return 0.0, 0.0, 0.0
    s = -mur * rstar * fn / w
    return s * wx, s * wy, s * wz


@njit(cache=True, error_model="numpy")
def epsd(wx, wy, wz, hx, hy, hz, rstar, fn, kn, mur, eta_r, inertia_r, dt):
    """Model C: returns (torque x, y, z, new spring torque x, y, z)."""
    kr = 2.25 * kn * mur * mur * rstar * rstar
    hx -= kr * wx * dt
    hy -= kr * wy * dt
    hz -= kr * wz * dt
    mmax = mur * rstar * fn
    m2 = hx * hx + hy * hy + hz * hz
    if m2 > mmax * mmax:
        s = mmax / math.sqrt(m2)
        hx *= s
        hy *= s
        hz *= s
        return hx, hy, hz, hx, hy, hz
    cr = eta_r * 2.0 * math.sqrt(inertia_r * kr)
    return hx - cr * wx, hy - cr * wy, hz - cr * wz, hx, hy, hz
