"""Contact radius for conduction models, and low-stiffness corrections.

Sources: Rangel (2021) survey (reference 002), "Appendix A - Contact
mechanics" and "Low stiffness correction"; Beaulieu/Lethe documentation
(reference 000) for the Zhou 2010 factor. All lengths in m, forces in N,
moduli in Pa. Effective quantities:
    R* = Ri Rj/(Ri+Rj)  (R* = R for a wall),
    1/E* = (1-nu_i^2)/E_i + (1-nu_j^2)/E_j.

Methods (integer ids, see ``METHODS``):
  0 ``hertz_force``   rc = (3 Fn R* / (4 E*))^(1/3)                (ref 002 App. A)
  1 ``hertz_overlap`` rc = sqrt(R* delta_n), delta_n = Ri + Rj - d (wall: R - d)
  2 ``geometric``     radius of the intersection circle of the two spheres,
                      rc = sqrt(4 d^2 Ri^2 - (d^2 - Rj^2 + Ri^2)^2) / (2 d)
                      (Musser 2011; Weisstein), wall: sqrt(R^2 - d^2)
Corrections (``CORRECTIONS``):
  0 ``none``
  1 ``zhou_2010``     rc_real = rc (E*/E*_real)^(1/5)  (Zhou, Yu & Zulli 2010;
                      ref 002 and ref 000; Hertz max. contact radius at equal
                      impact velocity scales as E*^(-1/5))
  2 ``lu_2017``       Lu et al. (2017), linear spring-dashpot extension: the
                      real overlap carrying the same (spring) force Fn = Kn delta
                      is delta_real = (Fn/K_HZ,real)^(2/3) with
                      K_HZ,real = 4/3 E*_real sqrt(R*), and rc = sqrt(R* delta_real)
                      = (3 Fn R*/(4 E*_real))^(1/3). Ref 002 prints
                      (Kn Rc / K_HZ,real)^(2/3), which is not a length; we read
                      the overlap delta_n in place of Rc (extraction error).
  3 ``morris_2016_area``  rc = (Fn R*/E*_real)^(1/3) (Morris et al. 2016a,
                      area correction, exactly as written in ref 002).
  4 ``morris_2016_area_time`` area correction times the collision-time
                      correction (t_c,real/t_c)^(2/3). For Hertz collisions
                      t_c ~ E*^(-2/5) at equal impact velocity and masses, so
                      (t_c,real/t_c)^(2/3) = (E*/E*_real)^(4/15). Morris et al.
                      recommend the time factor for (binary) collisions only:
                      use id 3 for static/enduring contacts.
When ``Estar_real <= 0`` (unknown real modulus) the corrections are identity.
Returned rc is 0 when the bodies do not overlap (d >= Ri + Rj, or d >= R).
"""
import math

import numba

from .records import ModelRecord

HERTZ_FORCE = 0
HERTZ_OVERLAP = 1
GEOMETRIC = 2
METHODS = {"hertz_force": HERTZ_FORCE, "hertz_overlap": HERTZ_OVERLAP, "geometric": GEOMETRIC}

NONE = 0
ZHOU_2010 = 1
LU_2017 = 2
MORRIS_2016_AREA = 3
MORRIS_2016_AREA_TIME = 4
CORRECTIONS = {"none": NONE, "zhou_2010": ZHOU_2010, "lu_2017": LU_2017,
               "morris_2016_area": MORRIS_2016_AREA,
               "morris_2016_area_time": MORRIS_2016_AREA_TIME}


@numba.njit(cache=True, error_model="numpy")
def effective_radius(Ri, Rj):
    """R* = Ri Rj / (Ri + Rj) [m]; a wall is passed as Rj = inf -> R* = Ri."""
    if math.isinf(Rj):
        return Ri
    if math.isinf(Ri):
        return Rj
    return Ri * Rj / (Ri + Rj)


@numba.njit(cache=True, error_model="numpy")
def effective_modulus(Ei, nui, Ej, nuj):
    """E* = [(1-nu_i^2)/E_i + (1-nu_j^2)/E_j]^-1 [Pa]; E = inf is rigid."""
    s = 0.0
    if not math.isinf(Ei):
        s += (1.0 - nui * nui) / Ei
    if not math.isinf(Ej):
        s += (1.0 - nuj * nuj) / Ej
    if s <= 0.0:
        return math.inf
    return 1.0 / s


@numba.njit(cache=True, error_model="numpy")
def hertz_force(Fn, Rstar, Estar):
    """Hertz static contact radius rc = (3 Fn R*/(4 E*))^(1/3) [m] (ref 002 App. A)."""
    if Fn <= 0.0 or Estar <= 0.0:
        return 0.0
    return (3.0 * Fn * Rstar / (4.0 * Estar)) ** (1.0 / 3.0)


@numba.njit(cache=True, error_model="numpy")
def hertz_overlap(Rstar, delta):
    """Hertz contact radius from the overlap, rc = sqrt(R* delta_n) [m] (ref 002 App. A)."""
    if delta <= 0.0:
        return 0.0
    return math.sqrt(Rstar * delta)


@numba.njit(cache=True, error_model="numpy")
def geometric_pp_inv(Ri, Rj, d, inv_d):
    """geometric_pp with 1/d given (the force loop has it): no division."""
    if d >= Ri + Rj:
        return 0.0
    if d <= abs(Ri - Rj):
        return min(Ri, Rj)
    t = d * d - Rj * Rj + Ri * Ri
    v = 4.0 * d * d * Ri * Ri - t * t
    if v <= 0.0:
        return 0.0
    return 0.5 * math.sqrt(v) * inv_d


@numba.njit(cache=True, error_model="numpy")
def geometric_pp(Ri, Rj, d):
    """Radius [m] of the intersection circle of two spheres at centre distance d.

    rc = sqrt(4 d^2 Ri^2 - (d^2 - Rj^2 + Ri^2)^2) / (2 d) (ref 002 App. A,
    Musser 2011). 0 if apart; min(Ri, Rj) if one sphere contains the other.
    """
    if d <= 0.0:
        return min(Ri, Rj)
    return geometric_pp_inv(Ri, Rj, d, 1.0 / d)


@numba.njit(cache=True, error_model="numpy")
def geometric_pw(R, d):
    """Radius [m] of the circle cut by a plane at distance d from a sphere centre, sqrt(R^2 - d^2)."""
    if d >= R:
        return 0.0
    if d <= 0.0:
        return R
    return math.sqrt(R * R - d * d)


@numba.njit(cache=True, error_model="numpy")
def zhou_2010(rc, Estar, Estar_real):
    """Zhou et al. (2010) correction rc_real = rc (E*/E*_real)^(1/5) [m] (ref 002, ref 000)."""
    if Estar_real <= 0.0 or Estar <= 0.0:
        return rc
    return rc * (Estar / Estar_real) ** 0.2


@numba.njit(cache=True, error_model="numpy")
def lu_2017(Fn, Rstar, Estar_real):
    """Lu et al. (2017): rc = sqrt(R* (Fn/K_HZ,real)^(2/3)) = (3 Fn R*/(4 E*_real))^(1/3) [m]."""
    if Fn <= 0.0:
        return 0.0
    return (3.0 * Fn * Rstar / (4.0 * Estar_real)) ** (1.0 / 3.0)


@numba.njit(cache=True, error_model="numpy")
def morris_2016_area(Fn, Rstar, Estar_real):
    """Morris et al. (2016a) area correction rc = (Fn R*/E*_real)^(1/3) [m] (ref 002)."""
    if Fn <= 0.0:
        return 0.0
    return (Fn * Rstar / Estar_real) ** (1.0 / 3.0)


@numba.njit(cache=True, error_model="numpy")
def morris_2016_time_factor(Estar, Estar_real):
    """Morris et al. (2016a) time correction (t_c,real/t_c)^(2/3) = (E*/E*_real)^(4/15) [-]."""
    if Estar_real <= 0.0 or Estar <= 0.0:
        return 1.0
    return (Estar / Estar_real) ** (4.0 / 15.0)


def hertz_radius_factor(correction, Estar, Estar_real):
    """The factor c of a contact radius rc = c sqrt(R* delta) of a Hertz contact, for every
    method and correction whose radius follows from the elastic force (issue 28).

    Under the Hertz law the elastic normal force is Fn = 4/3 E* sqrt(R*) delta^(3/2)
    (dem.contact.hertz_mindlin), so the force-based forms reduce to the overlap form times a
    constant of the material pair (no cube root per contact):

    * ``hertz_force``: (3 Fn R* / (4 E*))^(1/3) = sqrt(R* delta), c = 1;
    * ``zhou_2010``: rc (E*/E*_real)^(1/5) of any method: c = (E*/E*_real)^(1/5);
    * ``lu_2017``: (3 Fn R* / (4 E*_real))^(1/3) = (E*/E*_real)^(1/3) sqrt(R* delta);
    * ``morris_2016_area``: (Fn R* / E*_real)^(1/3) = (4/3 E*/E*_real)^(1/3) sqrt(R* delta);
    * ``morris_2016_area_time``: that times (E*/E*_real)^(4/15).

    Each is the radius :func:`apply_correction` gives a Hertz contact with R* = delta = 1
    (sqrt(R* delta) = 1, Fn = 4/3 E*), which is how c is computed here: the correction laws
    stay written once. With E*_real <= 0 (unknown) a correction is the identity: c = 1.
    A geometric radius takes c only for ``zhou_2010`` (the others do not follow from it:
    dem.step.full_form sends those to the full form of the contact loops)."""
    c = apply_correction(HERTZ_OVERLAP, correction, 1.0, 1.0, 4.0 / 3.0 * Estar, Estar, Estar_real)
    if not c > 0.0:
        raise ValueError(f"contact-radius correction id {correction}: no factor for E* = {Estar}, "
                         f"E*_real = {Estar_real}")
    return c


@numba.njit(cache=True, error_model="numpy")
def lean_radius(method, correction, contact_model):
    """Whether the lean contact loops (dem.step, xon None) compute this contact radius: the
    overlap form sqrt(R* delta) or the geometric one, times the pair factor of
    :func:`hertz_radius_factor`. ``contact_model``: 0 Hertz-Mindlin, 1 linear (under the
    linear law the force-based forms are a cube root of the overlap: the full form)."""
    if method == GEOMETRIC or contact_model != 0:
        return method != HERTZ_FORCE and (correction == NONE or correction == ZHOU_2010)
    return True


@numba.njit(cache=True, error_model="numpy")
def apply_correction(method, correction, rc, Rstar, Fn, Estar, Estar_real):
    """Softened-stiffness correction of a contact radius (ids of CORRECTIONS)."""
    return _apply(method, correction, rc, Rstar, Fn, Estar, Estar_real)


@numba.njit(cache=True, error_model="numpy")
def _apply(method, correction, rc, Rstar, Fn, Estar, Estar_real):
    if rc <= 0.0:
        return 0.0
    if correction == NONE or Estar_real <= 0.0:
        return rc
    if correction == ZHOU_2010:
        return zhou_2010(rc, Estar, Estar_real)
    if correction == LU_2017:
        return lu_2017(Fn, Rstar, Estar_real)
    if correction == MORRIS_2016_AREA:
        return morris_2016_area(Fn, Rstar, Estar_real)
    if correction == MORRIS_2016_AREA_TIME:
        return morris_2016_area(Fn, Rstar, Estar_real) * morris_2016_time_factor(Estar, Estar_real)
    return -1.0  # unknown correction id


@numba.njit(cache=True, error_model="numpy")
def contact_radius_pp(method, correction, Ri, Rj, d, Fn, Estar, Estar_real):
    """Particle-particle contact radius [m] (0 if the spheres do not overlap).

    method: 0 hertz_force, 1 hertz_overlap, 2 geometric; correction: 0 none,
    1 zhou_2010, 2 lu_2017, 3 morris_2016_area, 4 morris_2016_area_time.
    Fn: normal (elastic) contact force [N]; Estar, Estar_real: effective
    simulation and real Young's moduli [Pa]. Returns -1 for unknown ids.
    """
    if d >= Ri + Rj:
        return 0.0
    Rstar = Ri * Rj / (Ri + Rj)
    if method == HERTZ_FORCE:
        rc = hertz_force(Fn, Rstar, Estar)
    elif method == HERTZ_OVERLAP:
        rc = hertz_overlap(Rstar, Ri + Rj - d)
    elif method == GEOMETRIC:
        rc = geometric_pp(Ri, Rj, d)
    else:
        return -1.0
    return _apply(method, correction, rc, Rstar, Fn, Estar, Estar_real)


@numba.njit(cache=True, error_model="numpy")
def contact_radius_pw(method, correction, R, d, Fn, Estar, Estar_real):
    """Particle-wall contact radius [m]; d = centre-to-wall distance, R* = R."""
    if d >= R:
        return 0.0
    if method == HERTZ_FORCE:
        rc = hertz_force(Fn, R, Estar)
    elif method == HERTZ_OVERLAP:
        rc = hertz_overlap(R, R - d)
    elif method == GEOMETRIC:
        rc = geometric_pw(R, d)
    else:
        return -1.0
    return _apply(method, correction, rc, R, Fn, Estar, Estar_real)


# ----------------------------------------------------------------- records
# (contact_radius_pp/pw and _apply are written by hand; records give names, ids and inputs)
_EN = ("youngs_modulus", "poisson_ratio")
_ENR = ("youngs_modulus", "poisson_ratio", "real_youngs_modulus")
RECORDS = (
    ModelRecord("hertz_force", "contact_radius", HERTZ_FORCE, material=_EN, law=hertz_force,
                reference="ref 002 App. A", summary="r_c = (3 F_n R*/(4 E*))^(1/3)"),
    ModelRecord("hertz_overlap", "contact_radius", HERTZ_OVERLAP, law=hertz_overlap,
                reference="ref 002 App. A", summary="r_c = sqrt(R* delta_n)"),
    ModelRecord("geometric", "contact_radius", GEOMETRIC, law=geometric_pp,
                reference="ref 002 App. A (Musser 2011)", summary="intersection circle of the spheres"),
    ModelRecord("none", "correction", NONE, summary="identity"),
    ModelRecord("zhou_2010", "correction", ZHOU_2010, material=_ENR, law=zhou_2010,
                reference="Zhou, Yu & Zulli (2010); refs 002, 000", summary="r_c (E*/E*_real)^(1/5)"),
    ModelRecord("lu_2017", "correction", LU_2017, material=_ENR, law=lu_2017,
                reference="Lu et al. (2017); ref 002", summary="(3 F_n R*/(4 E*_real))^(1/3)"),
    ModelRecord("morris_2016_area", "correction", MORRIS_2016_AREA, material=_ENR, law=morris_2016_area,
                reference="Morris et al. (2016a); ref 002", summary="(F_n R*/E*_real)^(1/3)"),
    ModelRecord("morris_2016_area_time", "correction", MORRIS_2016_AREA_TIME, material=_ENR,
                law=morris_2016_time_factor, reference="Morris et al. (2016a); ref 002",
                summary="area correction x (E*/E*_real)^(4/15)"),
)
