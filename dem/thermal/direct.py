"""Direct (contact) conduction: particle-particle and particle-wall conductances.

All functions return a conductance H [W/K] such that the heat rate into
particle i is Q_i = H (T_j - T_i) (T_j = wall temperature for walls).
Sources: Rangel (2021) survey, reference 002 ("Direct conduction"), the
Beaulieu (2020) network as documented in reference 000, and reference 001
(particle-wall conduction: the wall is a perfect conductor, k = k_i).

Conventions: a wall is a body with infinite radius and mass; its material
row in ``tmat`` gives its conductivity (``inf`` = perfect conductor, which is
the fixed-temperature wall of reference 001), Young's modulus, etc.
Harmonic-type means treat an infinite conductivity as a perfect conductor.

Each model has a record (``RECORDS`` at the end) with its two dispatcher laws: ``pp`` with the
signature of ``direct_pp`` after the model id, ``pw`` with that of ``direct_pw``. The
dispatchers ``direct_pp`` / ``direct_pw`` themselves are generated from all direct-conduction
records by dem.thermal.dispatch (``rc <= 0`` gives 0 before any law is called; unknown id -1).
"""
import math

import numba

from ._quad import erfcinv
from .contact_radius import effective_modulus
from .records import ModelRecord
from .registry import (ACCOM, ASPERITY_SLOPE, CP, DENSITY, DIRECT_BATCHELOR_OBRIEN, DIRECT_BEAULIEU,
                       DIRECT_QUINTANA_RUIZ_CAMPELLO, DIRECT_ROJEK, DIRECT_THERMAL_PIPE,
                       DIRECT_ZHOU_COLLISIONAL, GAMMA_RATIO, K_COND, KF, MEAN_FREE_PATH,
                       MICROHARDNESS, POISSON, PR, REAL_YOUNG, ROUGHNESS, YOUNG)

SQRT2 = math.sqrt(2.0)


# ----------------------------------------------------------------- helpers
@numba.njit(cache=True, error_model="numpy")
def series_conductivity(ki, kj):
    """k_bar = (1/ki + 1/kj)^-1 = ki kj/(ki+kj) [W/(m K)] (ref 002 App. A); inf = perfect conductor."""
    if math.isinf(ki):
        return kj
    if math.isinf(kj):
        return ki
    if ki + kj <= 0.0:
        return 0.0
    return ki * kj / (ki + kj)


@numba.njit(cache=True, error_model="numpy")
def harmonic_mean(a, b):
    """2 a b/(a + b); an infinite argument gives 2 x the other (perfect conductor)."""
    return 2.0 * series_conductivity(a, b)


@numba.njit(cache=True, error_model="numpy")
def real_modulus(tmat, m):
    """Real Young's modulus of material m (REAL_YOUNG if > 0 else YOUNG) [Pa]."""
    e = tmat[m, REAL_YOUNG]
    if e > 0.0:
        return e
    return tmat[m, YOUNG]


# ----------------------------------------------------------------- models
@numba.njit(cache=True, error_model="numpy")
def batchelor_obrien_keff(rc, keff):
    """Batchelor & O'Brien conductance from the series conductivity: H = 4 k_bar rc [W/K]
    (the solver passes k_bar from a per-material-pair table; see batchelor_obrien_1977)."""
    if rc <= 0.0:
        return 0.0
    return 4.0 * keff * rc


@numba.njit(cache=True, error_model="numpy")
def batchelor_obrien_1977(rc, ki, kj):
    """Batchelor & O'Brien (1977) static contact conductance [W/K].

    H = 4 k_bar rc, k_bar = ki kj/(ki + kj) (ref 002, "Model by Batchelor &
    O'Brien", modification for different conductivities, Cheng et al. 1999;
    identical to reference 001 eq. 3299 and to R_L = 1/(2 k_h rc) of ref 000
    with k_h = 2 ki kj/(ki+kj)). For ki = kj = k this is B&O's original
    2 k rc. Wall (kj = inf, perfect conductor, ref 001 eq. 3300): H = 4 ki rc.
    rc [m]: contact radius (Hertz or geometric, possibly corrected).
    """
    return batchelor_obrien_keff(rc, series_conductivity(ki, kj))


@numba.njit(cache=True, error_model="numpy")
def thermal_pipe(rc, d, ki, kj):
    """Generic thermal pipe (ref 002, "Thermal pipe models") [W/K].

    H = k A_p / d_ij, A_p = pi rc^2, with the pipe made of two halves of length
    d/2 in series, k = 2 ki kj/(ki + kj) (reduces to k_p for one material).
    """
    if rc <= 0.0 or d <= 0.0:
        return 0.0
    return harmonic_mean(ki, kj) * math.pi * rc * rc / d


@numba.njit(cache=True, error_model="numpy")
def quintana_ruiz_campello_2020(rc, d, Ri, Rj, ki, kj):
    """Quintana-Ruiz & Campello (2020) thermal pipe [W/K].

    H = k~ A_p / d_ij, A_p = pi (Rc_geo)^2, k~ = (Ri + Rj)/(Ri/ki + Rj/kj)
    (ref 002; the extracted text has k_i twice in the denominator: corrected to
    Rj/kj). For a wall pass Rj = 0 (pipe entirely in the particle): k~ = ki.
    """
    if rc <= 0.0 or d <= 0.0:
        return 0.0
    den = Ri / ki
    if Rj > 0.0 and not math.isinf(kj):
        den += Rj / kj
    ktil = (Ri + Rj) / den
    return ktil * math.pi * rc * rc / d


@numba.njit(cache=True, error_model="numpy")
def rojek_2014(Ri, Rj, ki, kj):
    """Rojek (2014) 3D bar model [W/K]: H = k_p b with b = r_bar = (Ri+Rj)/2.

    From Q = k_p A_p/d_ij with A_p = 2 r_bar b and d_ij = 2 r_bar (ref 002).
    For two materials k_p is the harmonic mean 2 ki kj/(ki+kj).
    """
    return harmonic_mean(ki, kj) * 0.5 * (Ri + Rj)


@numba.njit(cache=True, error_model="numpy")
def rojek_2014_wall(R, kp):
    """Rojek (2014) bar model against a wall [W/K]: H = k_p A_p / L with
    A_p = 2 R b, b = R and bar length L = R (centre to wall): H = 2 k_p R."""
    return 2.0 * kp * R


@numba.njit(cache=True, error_model="numpy")
def hertz_collision(mstar, Rstar, Estar, vn):
    """Hertz impact (ref 002 App. A): returns (Rc_max [m], t_c [s]).

    Rc_max = (15 m* R*^2 vn^2 / (16 E*))^(1/5),
    t_c = 2.87 (m*^2 / (R* E*^2 vn))^(1/5); vn: normal impact velocity [m/s].
    """
    if vn <= 0.0:
        return 0.0, 0.0
    rcm = (15.0 * mstar * Rstar * Rstar * vn * vn / (16.0 * Estar)) ** 0.2
    tc = 2.87 * (mstar * mstar / (Rstar * Estar * Estar * vn)) ** 0.2
    return rcm, tc


@numba.njit(cache=True, error_model="numpy")
def zhou_2008_coefficient(Fo, c):
    """Zhou et al. (2008) correction coefficient C(Fo, c), c = rho_i c_i/(rho_j c_j).

    C = 0.435 (sqrt(C2^2 - 4 C1 (C3 - Fo)) - C2)/C1 with
    C1 = -2.300 c^2 + 8.909 c - 4.235, C2 = 8.169 c^2 - 33.770 c + 24.885,
    C3 = -5.758 c^2 + 24.464 c - 20.511 (ref 002). The fit is only defined
    where C1 != 0 and the discriminant is >= 0 (c roughly in (0.55, 3.3));
    outside, C = 1 (the semi-infinite solution of Sun & Chen) is returned.
    """
    C1 = -2.300 * c * c + 8.909 * c - 4.235
    C2 = 8.169 * c * c - 33.770 * c + 24.885
    C3 = -5.758 * c * c + 24.464 * c - 20.511
    disc = C2 * C2 - 4.0 * C1 * (C3 - Fo)
    if C1 == 0.0 or disc < 0.0:
        return 1.0
    C = 0.435 * (math.sqrt(disc) - C2) / C1
    if not (C > 0.0) or math.isinf(C):
        return 1.0
    return C


@numba.njit(cache=True, error_model="numpy")
def zhou_2008_collisional(rc_max, t_c, rho_i, cp_i, k_i, rho_j, cp_j, k_j):
    """Zhou, Yu & Horio (2008) collisional contact conductance [W/K].

    H = C pi Rc_max^2 t_c^(-1/2) / [(rho_i c_i k_i)^(-1/2) + (rho_j c_j k_j)^(-1/2)]
    (ref 002; the extracted text repeats particle i in the second effusivity
    term: corrected to particle j), C = zhou_2008_coefficient(Fo, c) with
    Fo = k_i t_c/(rho_i c_i Rc_max^2), c = rho_i c_i/(rho_j c_j).
    Note: C depends on which particle is i (the fit is not symmetric); the
    caller must evaluate it once per pair. An infinite effusivity (wall with
    k = inf) contributes 0 to the denominator.
    """
    if rc_max <= 0.0 or t_c <= 0.0:
        return 0.0
    ei = math.sqrt(rho_i * cp_i * k_i)
    ej = math.sqrt(rho_j * cp_j * k_j)
    den = 0.0
    if not math.isinf(ei):
        den += 1.0 / ei
    if not math.isinf(ej):
        den += 1.0 / ej
    if den <= 0.0:
        return 0.0
    Fo = k_i * t_c / (rho_i * cp_i * rc_max * rc_max)
    c = (rho_i * cp_i) / (rho_j * cp_j)
    C = zhou_2008_coefficient(Fo, c)
    return C * math.pi * rc_max * rc_max / math.sqrt(t_c) / den


@numba.njit(cache=True, error_model="numpy")
def gas_parameter_m(alpha_i, alpha_j, gamma, mfp, Pr):
    """Gas parameter M [m] (temperature-jump distance, ref 000; Bahrami 2006):

    M = ((2 - a_i)/a_i + (2 - a_j)/a_j) (2 gamma/(1 + gamma)) Lambda / Pr.
    """
    return ((2.0 - alpha_i) / alpha_i + (2.0 - alpha_j) / alpha_j) * \
        (2.0 * gamma / (1.0 + gamma)) * mfp / Pr


@numba.njit(cache=True, error_model="numpy")
def _macrogap(rho, rc, kg, M):
    # 1/R_G = (pi kg / 2) [S ln(S/(S - A)) - A], A = 2 sqrt(rho^2 - rc^2),
    # S = 2 (rho - rc^2/(2 rho)) + M  (ref 000, B = 0)
    if kg <= 0.0 or rc >= rho:
        return math.inf
    A = 2.0 * math.sqrt(rho * rho - rc * rc)
    S = 2.0 * rho - rc * rc / rho + M
    if S - A <= 0.0:
        return 0.0
    g = S * math.log(S / (S - A)) - A
    if g <= 0.0:
        return math.inf
    return 2.0 / (math.pi * kg * g)


@numba.njit(cache=True, error_model="numpy")
def beaulieu_2020_network(Ri, Rj, rc, ki, kj, kg, Hi, Hj, sig_i, sig_j, tau_i, tau_j,
                          Estar_real, M, wall):
    """Beaulieu (2020) thermal resistance network, conductance [W/K] (ref 000).

    1/R = 1/(R_L + (1/R_s + 1/R_g)^-1) + 1/(R_c + R_G) with
      R_L = 1/(2 k_h rc)                                    macrocontact
      R_s = (H'/P0)^0.96 1.184 sigma/(pi rc^2 k_h tau)      microcontacts
      R_g = 2 sqrt2 sigma a2 / (pi k_g rc^2 ln(1 + a2/(a1 + M/(2 sqrt2 sigma))))  gas microgap
      R_c = sum_i (pi R_i/4) / (k_i pi (R_i^2 - rc^2))        solid layers
      R_G = 2 / (pi k_g [S ln(S/(S - A)) - A])               gas macrogap
    k_h = 2 ki kj/(ki+kj); H' = 2 Hi Hj/(Hi+Hj) (microhardness, Pa);
    sigma = sqrt(sig_i^2 + sig_j^2) (RMS roughness, m); tau = sqrt(tau_i^2 +
    tau_j^2) (asperity slope); a1 = erfcinv(2 P0/H'), a2 = erfcinv(0.03 P0/H') - a1;
    A = 2 sqrt(r_h^2 - rc^2), S = 2 r_h - rc^2/r_h + M, r_h = 2 Ri Rj/(Ri+Rj).
    Real-modulus correction: the Hertz maximum pressure is evaluated with the
    real effective modulus and the (corrected, real) contact radius,
    P0 = 2 E*_real rc/(pi R*) (= 2 E* delta/(pi rc) of ref 000 with
    delta = rc^2/R*); rc itself should come from contact_radius with the
    zhou_2010 correction as in ref 000.
    R_g is dropped (infinite) when 2 P0/H' is outside (0, 2) (as Lethe does),
    R_s = 0 and R_g = inf for perfectly smooth surfaces (sigma = 0).
    wall=True: Rj, kj are the wall's (Rj ignored, kj = inf = perfect
    conductor); only the particle's solid layer is counted; the sphere-plane
    gas macrogap is the exact sphere-plane form of the same integral,
    R_G,wall = R_G(r_h = R, M -> 2M)/2 (our derivation; Lethe instead uses
    r_h = 2R and halves R_G).
    """
    if rc <= 0.0:
        return 0.0
    kh = harmonic_mean(ki, kj)
    if wall:
        Rstar = Ri
    else:
        Rstar = Ri * Rj / (Ri + Rj)
    P0 = 2.0 * Estar_real * rc / (math.pi * Rstar)
    Hp = harmonic_mean(Hi, Hj)
    sigma = math.sqrt(sig_i * sig_i + sig_j * sig_j)
    tau = math.sqrt(tau_i * tau_i + tau_j * tau_j)
    rc2 = rc * rc
    R_L = 1.0 / (2.0 * kh * rc)
    # microcontacts and gas microgap, in parallel
    if sigma > 0.0 and tau > 0.0 and P0 > 0.0:
        R_s = (Hp / P0) ** 0.96 * 1.184 * sigma / (math.pi * rc2 * kh * tau)
        x1 = 2.0 * P0 / Hp
        R_g = math.inf
        if 0.0 < x1 < 2.0 and kg > 0.0:
            a1 = erfcinv(x1)
            a2 = erfcinv(0.03 * P0 / Hp) - a1
            den = a1 + M / (2.0 * SQRT2 * sigma)
            if den > 0.0 and a2 > 0.0:
                R_g = 2.0 * SQRT2 * sigma * a2 / (math.pi * kg * rc2 * math.log(1.0 + a2 / den))
        par = 1.0 / R_s + (0.0 if math.isinf(R_g) else 1.0 / R_g)
        R_micro = R_L + 1.0 / par
    else:
        R_micro = R_L
    # solid layers + gas macrogap, in series
    R_c = 0.25 * math.pi * Ri / (ki * math.pi * (Ri * Ri - rc2))
    if wall:
        R_G = 0.5 * _macrogap(Ri, rc, kg, 2.0 * M)
    else:
        R_c += 0.25 * math.pi * Rj / (kj * math.pi * (Rj * Rj - rc2))
        R_G = _macrogap(2.0 * Rstar, rc, kg, M)
    H = 1.0 / R_micro
    R2 = R_c + R_G
    if not math.isinf(R2) and R2 > 0.0:
        H += 1.0 / R2
    return H


# ----------------------------------------------------------------- dispatcher laws
# pp: (Ri, Rj, d, rc, mi, mj, tmat, gas, t_contact, vn_impact); pw: (R, d, rc, mp, mw, tmat, gas,
# t_contact, vn_impact); called by the generated direct_pp / direct_pw only when rc > 0.
@numba.njit(cache=True, error_model="numpy")
def _zhou_or_static(rc, Rstar, mstar, Estar_real, vn_impact, t_contact,
                    rho_i, cp_i, k_i, rho_j, cp_j, k_j):
    rcm, tc = hertz_collision(mstar, Rstar, Estar_real, vn_impact)
    if vn_impact > 0.0 and t_contact < tc:
        return zhou_2008_collisional(rcm, tc, rho_i, cp_i, k_i, rho_j, cp_j, k_j)
    return batchelor_obrien_1977(rc, k_i, k_j)


@numba.njit(cache=True, error_model="numpy", inline="always")
def _bo_pp(Ri, Rj, d, rc, mi, mj, tmat, gas, t_contact, vn_impact):
    return batchelor_obrien_1977(rc, tmat[mi, K_COND], tmat[mj, K_COND])


@numba.njit(cache=True, error_model="numpy", inline="always")
def _bo_pw(R, d, rc, mp, mw, tmat, gas, t_contact, vn_impact):
    return batchelor_obrien_1977(rc, tmat[mp, K_COND], tmat[mw, K_COND])


@numba.njit(cache=True, error_model="numpy", inline="always")
def _pipe_pp(Ri, Rj, d, rc, mi, mj, tmat, gas, t_contact, vn_impact):
    return thermal_pipe(rc, d, tmat[mi, K_COND], tmat[mj, K_COND])


@numba.njit(cache=True, error_model="numpy", inline="always")
def _pipe_pw(R, d, rc, mp, mw, tmat, gas, t_contact, vn_impact):
    kp = tmat[mp, K_COND]
    if d <= 0.0:
        return 0.0
    return kp * math.pi * rc * rc / d


@numba.njit(cache=True, error_model="numpy", inline="always")
def _qrc_pp(Ri, Rj, d, rc, mi, mj, tmat, gas, t_contact, vn_impact):
    return quintana_ruiz_campello_2020(rc, d, Ri, Rj, tmat[mi, K_COND], tmat[mj, K_COND])


@numba.njit(cache=True, error_model="numpy", inline="always")
def _qrc_pw(R, d, rc, mp, mw, tmat, gas, t_contact, vn_impact):
    return quintana_ruiz_campello_2020(rc, d, R, 0.0, tmat[mp, K_COND], tmat[mw, K_COND])


@numba.njit(cache=True, error_model="numpy", inline="always")
def _rojek_pp(Ri, Rj, d, rc, mi, mj, tmat, gas, t_contact, vn_impact):
    return rojek_2014(Ri, Rj, tmat[mi, K_COND], tmat[mj, K_COND])


@numba.njit(cache=True, error_model="numpy", inline="always")
def _rojek_pw(R, d, rc, mp, mw, tmat, gas, t_contact, vn_impact):
    return rojek_2014_wall(R, tmat[mp, K_COND])


@numba.njit(cache=True, error_model="numpy", inline="always")
def _zhou_pp(Ri, Rj, d, rc, mi, mj, tmat, gas, t_contact, vn_impact):
    """Collisional formula while t_contact < t_c (Hertz collision time with the real modulus),
    then static Batchelor & O'Brien as Zhou et al. 2009."""
    ki = tmat[mi, K_COND]
    kj = tmat[mj, K_COND]
    Es = effective_modulus(real_modulus(tmat, mi), tmat[mi, POISSON],
                           real_modulus(tmat, mj), tmat[mj, POISSON])
    m1 = tmat[mi, DENSITY] * 4.0 / 3.0 * math.pi * Ri ** 3
    m2 = tmat[mj, DENSITY] * 4.0 / 3.0 * math.pi * Rj ** 3
    return _zhou_or_static(rc, Ri * Rj / (Ri + Rj), m1 * m2 / (m1 + m2), Es, vn_impact,
                           t_contact, tmat[mi, DENSITY], tmat[mi, CP], ki,
                           tmat[mj, DENSITY], tmat[mj, CP], kj)


@numba.njit(cache=True, error_model="numpy", inline="always")
def _zhou_cg_pp(cg, Ri, Rj, d, rc, mi, mj, tmat, gas, t_contact, vn_impact):
    """Coarse-graining factor of a parcel pair (real-size arguments, contact age / cg): W = cg^3
    during the collision, cg once static (docs/models.md, "Coarse graining"). At the same
    granular temperature the collision rate per volume of parcels is cg^-4 the real particles'
    (n^2 d^2), so a parcel collision, which lasts cg real collision times, must exchange cg^4 the
    heat of a real one: cg^3 times the real collisional conductance. The phase is the law's own
    (the real collision time against the age / cg, i.e. the parcel's collision time)."""
    if rc <= 0.0 or vn_impact <= 0.0:
        return cg
    Es = effective_modulus(real_modulus(tmat, mi), tmat[mi, POISSON],
                           real_modulus(tmat, mj), tmat[mj, POISSON])
    m1 = tmat[mi, DENSITY] * 4.0 / 3.0 * math.pi * Ri ** 3
    m2 = tmat[mj, DENSITY] * 4.0 / 3.0 * math.pi * Rj ** 3
    _, tc = hertz_collision(m1 * m2 / (m1 + m2), Ri * Rj / (Ri + Rj), Es, vn_impact)
    if t_contact < tc:
        return cg * cg * cg
    return cg


@numba.njit(cache=True, error_model="numpy", inline="always")
def _zhou_pw(R, d, rc, mp, mw, tmat, gas, t_contact, vn_impact):
    kp = tmat[mp, K_COND]
    kw = tmat[mw, K_COND]
    Es = effective_modulus(real_modulus(tmat, mp), tmat[mp, POISSON],
                           real_modulus(tmat, mw), tmat[mw, POISSON])
    m1 = tmat[mp, DENSITY] * 4.0 / 3.0 * math.pi * R ** 3
    return _zhou_or_static(rc, R, m1, Es, vn_impact, t_contact,
                           tmat[mp, DENSITY], tmat[mp, CP], kp,
                           tmat[mw, DENSITY], tmat[mw, CP], kw)


@numba.njit(cache=True, error_model="numpy", inline="always")
def _beaulieu_pp(Ri, Rj, d, rc, mi, mj, tmat, gas, t_contact, vn_impact):
    Es = effective_modulus(real_modulus(tmat, mi), tmat[mi, POISSON],
                           real_modulus(tmat, mj), tmat[mj, POISSON])
    M = gas_parameter_m(tmat[mi, ACCOM], tmat[mj, ACCOM], gas[GAMMA_RATIO],
                        gas[MEAN_FREE_PATH], gas[PR])
    return beaulieu_2020_network(Ri, Rj, rc, tmat[mi, K_COND], tmat[mj, K_COND], gas[KF], tmat[mi, MICROHARDNESS],
                                 tmat[mj, MICROHARDNESS], tmat[mi, ROUGHNESS], tmat[mj, ROUGHNESS],
                                 tmat[mi, ASPERITY_SLOPE], tmat[mj, ASPERITY_SLOPE], Es, M, False)


@numba.njit(cache=True, error_model="numpy", inline="always")
def _beaulieu_pw(R, d, rc, mp, mw, tmat, gas, t_contact, vn_impact):
    Es = effective_modulus(real_modulus(tmat, mp), tmat[mp, POISSON],
                           real_modulus(tmat, mw), tmat[mw, POISSON])
    M = gas_parameter_m(tmat[mp, ACCOM], tmat[mw, ACCOM], gas[GAMMA_RATIO],
                        gas[MEAN_FREE_PATH], gas[PR])
    return beaulieu_2020_network(R, math.inf, rc, tmat[mp, K_COND], tmat[mw, K_COND], gas[KF], tmat[mp, MICROHARDNESS],
                                 tmat[mw, MICROHARDNESS], tmat[mp, ROUGHNESS], tmat[mw, ROUGHNESS],
                                 tmat[mp, ASPERITY_SLOPE], tmat[mw, ASPERITY_SLOPE], Es, M, True)


# ----------------------------------------------------------------- records
_K = ("thermal_conductivity",)
RECORDS = (
    ModelRecord("batchelor_obrien", "direct", DIRECT_BATCHELOR_OBRIEN,
                aliases=("batchelor_obrien_1977", "bob"), material=_K,
                laws=dict(pp=_bo_pp, pw=_bo_pw), law=batchelor_obrien_1977,
                reference="Batchelor & O'Brien (1977); ref 002, ref 001 eqs. 3299-3300",
                summary="H = 4 k_bar r_c"),
    ModelRecord("thermal_pipe", "direct", DIRECT_THERMAL_PIPE, material=_K,
                laws=dict(pp=_pipe_pp, pw=_pipe_pw), law=thermal_pipe,
                reference="ref 002, thermal pipe models", summary="H = k_h pi r_c^2 / d"),
    ModelRecord("quintana_ruiz_campello_2020", "direct", DIRECT_QUINTANA_RUIZ_CAMPELLO,
                aliases=("quintana_ruiz_campello",), material=_K,
                laws=dict(pp=_qrc_pp, pw=_qrc_pw), law=quintana_ruiz_campello_2020,
                reference="Quintana-Ruiz & Campello (2020); ref 002", summary="H = k~ pi r_c^2 / d"),
    ModelRecord("rojek_2014", "direct", DIRECT_ROJEK, material=_K,
                laws=dict(pp=_rojek_pp, pw=_rojek_pw), law=rojek_2014,
                reference="Rojek (2014); ref 002", summary="H = k_h (Ri + Rj)/2"),
    ModelRecord("zhou_2008_collisional", "direct", DIRECT_ZHOU_COLLISIONAL,
                aliases=("zhou_2008", "collisional"),
                material=("thermal_conductivity", "heat_capacity", "density", "youngs_modulus",
                          "poisson_ratio"),
                history=2, laws=dict(pp=_zhou_pp, pw=_zhou_pw, cg_pp=_zhou_cg_pp), law=zhou_2008_collisional,
                reference="Zhou, Yu & Horio (2008); ref 002",
                summary="collisional conductance while the contact is younger than t_c, then B&O"),
    ModelRecord("beaulieu_2020", "direct", DIRECT_BEAULIEU,
                aliases=("beaulieu_2020_network", "beaulieu"),
                material=("thermal_conductivity", "microhardness", "roughness", "asperity_slope",
                          "youngs_modulus", "poisson_ratio"),
                gas=("conductivity", "mean_free_path", "heat_capacity_ratio", "prandtl",
                     "accommodation_coefficient"),
                laws=dict(pp=_beaulieu_pp, pw=_beaulieu_pw), law=beaulieu_2020_network,
                reference="Beaulieu (2020) resistance network; ref 000",
                summary="macro/microcontact, gas microgap, solid layers and gas macrogap resistances"),
)


def __getattr__(name):
    # direct_pp / direct_pw are generated from the records of all direct models
    if name in ("direct_pp", "direct_pw", "direct_cg_pp", "direct_cg_pw"):
        from . import dispatch
        return getattr(dispatch.module(), name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
