"""The two tangential spring models (dem.contact.tangential, scene key [contact] tangential).

* ``projected`` is LIGGGHTS's ``tangential_model history`` (and LAMMPS ``gran/hertz/history``):
  checked against an independent transcription of that algorithm's order of operations
  (spring += v_t dt, drop its normal part, cap the spring force alone, dashpot only while sticking).
* ``rescaled`` (the default) keeps the spring's length when the plane turns and caps the whole
  force (Luding 2008).
* How a turn changes a spring, exactly: kept length against the cosine of the turn.
The impacts of tests/test_impacts.py (Coulomb impulse, sticking, the continuous Hertz-Mindlin
solution) run with both models.
"""
import math

import numpy as np
import pytest

from dem.contact.hertz_mindlin import hertz_mindlin
from dem.contact.linear import linear_spring_dashpot
from dem.contact.tangential import luding_2008_turn, silbert_2001_turn, TANGENTIAL_PROJECTED
from dem.contact.registry import TANGENTIAL_MODELS


def _unit(a):
    return a / np.linalg.norm(a)


def _liggghts_history(h, n, vt, kt, gammat, mu, fn, dt):
    """LIGGGHTS-PUBLIC 3.8 tangential_model_history.h surfacesIntersect, transcribed in its order:
    the spring (from the previous step, any direction) and the unit normal n of this step."""
    h = h + vt * dt
    h = h - np.dot(h, n) * n
    shrmag = math.sqrt(np.dot(h, h))
    ft = -kt * h
    if kt * shrmag > mu * abs(fn):
        if shrmag != 0.0:
            ft = ft * (mu * abs(fn) / (kt * shrmag))
            h = -ft / kt
        else:
            ft = 0.0 * ft
    else:
        ft = ft - gammat * vt
    return ft, h


def _luding(h, n, vt, st, ct, mu, fn, dt):
    """The rescaled model written out: turn keeping |h|, add v_t dt, cap the whole force."""
    old = math.sqrt(np.dot(h, h))
    h = h - np.dot(h, n) * n
    if old > 0:
        h = h * old / math.sqrt(np.dot(h, h))
    h = h + vt * dt
    f = -st * h - ct * vt
    if np.dot(f, f) > (mu * fn) ** 2:
        f = f * mu * fn / math.sqrt(np.dot(f, f))
        h = -(f + ct * vt) / st
    return f, h


def _contacts(seed, count):
    """Random Hertz contacts: overlap, approach speed, a turned normal, a tangential velocity in
    its plane and a stored spring of the previous plane, sized so that about half slide."""
    rng = np.random.default_rng(seed)
    out = []
    for _ in range(count):
        n = _unit(rng.normal(size=3))
        vt = rng.normal(size=3) * 10 ** rng.uniform(-4, -1)
        vt -= np.dot(vt, n) * n
        h = rng.normal(size=3) * 10 ** rng.uniform(-8, -5)
        out.append(dict(delta=10 ** rng.uniform(-7, -5), vn=rng.normal() * 0.05, n=n, vt=vt, h=h,
                        rstar=5e-4, mstar=rng.uniform(1e-6, 1e-5)))
    return out


MAT = dict(estar=5e6 / (2 * (1 - 0.09)), gstar=5e6 / (2 * (1 + 0.3)) / (2 * (2 - 0.3)), damp=0.6, mu=0.3)
DT = 1e-5


@pytest.mark.parametrize("model", ["projected", "rescaled"])
def test_hertz_mindlin_tangential_models_against_their_algorithms(model):
    """2,000 random contacts, about half at the Coulomb limit: the kernel's force and spring
    equal the written-out algorithm to 1e-12 of the force scale (round-off: the kernel adds
    v_t dt after the turn, compares squares and uses fused operations)."""
    tang = TANGENTIAL_MODELS[model]
    ctr = math.sqrt(4 * MAT["gstar"] / MAT["estar"])
    slid = stuck = 0
    for c in _contacts(11, 2000):
        n, vt, h = c["n"], c["vt"], c["h"]
        turn = silbert_2001_turn if tang == TANGENTIAL_PROJECTED else luding_2008_turn
        hx, hy, hz = turn(h[0], h[1], h[2], n[0], n[1], n[2], 1.0)
        fn, fx, fy, fz, gx, gy, gz, _ = hertz_mindlin(
            c["delta"], c["vn"], vt[0], vt[1], vt[2], hx, hy, hz, c["rstar"], c["mstar"],
            MAT["estar"], MAT["gstar"], MAT["damp"], MAT["mu"], ctr, DT,
            True if tang == TANGENTIAL_PROJECTED else None)
        sq = math.sqrt(c["rstar"] * c["delta"])
        st = 8 * MAT["gstar"] * sq
        ct = MAT["damp"] * math.sqrt(c["mstar"] * MAT["estar"] * sq) * ctr
        if model == "projected":
            f_ref, h_ref = _liggghts_history(h, n, vt, st, ct, MAT["mu"], fn, DT)
        else:
            f_ref, h_ref = _luding(h, n, vt, st, ct, MAT["mu"], fn, DT)
        scale = max(np.linalg.norm(f_ref), st * np.linalg.norm(h_ref), 1e-30)
        assert np.allclose([fx, fy, fz], f_ref, rtol=0, atol=1e-12 * scale), (c, f_ref)
        assert np.allclose([gx, gy, gz], h_ref, rtol=0, atol=1e-12 * np.linalg.norm(h_ref) + 1e-30), c
        if np.linalg.norm(f_ref) >= MAT["mu"] * fn * (1 - 1e-12) and fn > 0:
            slid += 1
        else:
            stuck += 1
    assert slid > 300 and stuck > 300, (slid, stuck)   # both branches of the cap exercised


def test_linear_law_projected_cap():
    """The linear law shares the models: at the limit, the projected cap scales the spring force
    alone (no dashpot), the rescaled one the whole force."""
    kn, ktr, damp, mu = 1e3, 2 / 7, 0.5, 0.3
    delta, vn, vt, h = 1e-5, 0.0, np.array([0.01, 0.0, 0.0]), np.array([1e-4, 0.0, 0.0])
    fn, fx, _, _, hx, _, _, _ = linear_spring_dashpot(delta, vn, vt[0], vt[1], vt[2], h[0], h[1], h[2],
                                                      1e-6, kn, ktr, damp, mu, DT, True)
    assert fn == pytest.approx(kn * delta, rel=1e-15)
    assert fx == pytest.approx(-mu * fn, rel=1e-14)
    assert hx == pytest.approx(mu * fn / (ktr * kn), rel=1e-14)     # -F_t / k_t: no dashpot part
    fn, fx, _, _, hx, _, _, _ = linear_spring_dashpot(delta, vn, vt[0], vt[1], vt[2], h[0], h[1], h[2],
                                                      1e-6, kn, ktr, damp, mu, DT, None)
    ct = damp * math.sqrt(1e-6 * kn) * math.sqrt(ktr)
    assert fx == pytest.approx(-mu * fn, rel=1e-14)
    assert hx == pytest.approx((mu * fn - ct * vt[0]) / (ktr * kn), rel=1e-12)  # -(F_t + c_t v_t) / k_t


@pytest.mark.parametrize("theta_deg", [1e-3, 0.5, 10.0, 60.0])
def test_turn_keeps_length_or_projects(theta_deg):
    """A spring in the old tangent plane, the plane turned by theta about an axis normal to both:
    the rescaled turn keeps |xi|, the projected one leaves |xi| cos(theta); both end in the new
    plane. The pair loop passes the unnormalised centre line and 1/|d|^2: the same result."""
    th = math.radians(theta_deg)
    n0 = np.array([0.0, 0.0, 1.0])
    h = np.array([3e-6, 0.0, 0.0])                      # in the plane normal to n0
    n1 = np.array([math.sin(th), 0.0, math.cos(th)])    # turned towards h
    d = 2.1e-3 * n1
    for u, inv in ((n1, 1.0), (d, 1.0 / np.dot(d, d))):
        r = np.array(luding_2008_turn(h[0], h[1], h[2], u[0], u[1], u[2], inv))
        p = np.array(silbert_2001_turn(h[0], h[1], h[2], u[0], u[1], u[2], inv))
        assert np.linalg.norm(r) == pytest.approx(3e-6, rel=1e-14)
        assert np.linalg.norm(p) == pytest.approx(3e-6 * math.cos(th), rel=1e-13)
        assert abs(np.dot(r, n1)) < 1e-15 * 3e-6 and abs(np.dot(p, n1)) < 1e-15 * 3e-6
    assert luding_2008_turn(0.0, 0.0, 0.0, 0.0, 0.0, 1.0, 1.0) == (0.0, 0.0, 0.0)
