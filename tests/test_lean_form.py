"""The lean form of the interact phase (issue 28): ``xon``, a type like the heat switch ``hon``,
compiles the contact loops without rolling resistance, periodic images and the heat models
beyond direct conduction (indirect conduction, radiation, frictional heating, contact age) when
a scene uses none of them (dem.step.full_form, dem.stepper.Stepper.xon). Its direct conduction is
Batchelor & O'Brien's with a contact radius sqrt(R* delta) or the geometric one, times a constant
of the material pair for a correction (dem.thermal.contact_radius.hertz_radius_factor): under the
Hertz law the force-based radii and corrections are that product, without a cube root per contact.

What is asserted: which scenes take which form; that the lean form gives the full form's results
bit for bit on scenes it serves with the same arithmetic (the left-out switches being constants),
and to round-off where it computes a radius by the identity (a root and a pair constant instead of
a cube root); the identity itself on random contacts; and that the lean form refuses a scene that
needs the full one rather than leaving its physics out.
"""
import numpy as np
import pytest

from dem import Simulation
from dem import schema as S
from dem.stepper import Stepper

BASE = {"simulation": {"time_step": 1e-5, "end_time": 1e-3, "gravity": [0, 0, -100.0]},
        "domain": {"min": [0.0, 0.0, 0.0], "max": [0.004, 0.004, 0.004]},
        "materials": [dict(name="g", density=2500.0, youngs_modulus=5e6, poisson_ratio=0.3, restitution=0.5,
                           friction=0.4, rolling_friction=0.05, thermal_conductivity=1.0, heat_capacity=840.0,
                           emissivity=0.8, real_youngs_modulus=6e10)],
        "particles": [{"material": "g", "radius": 2e-4, "positions": (
            # a 4 x 4 x 4 lattice a little closer than touching, jittered, in a corner of the
            # floor and two side walls: its contacts open and close while it settles (20 to 90)
            np.array([[0.0004 + 0.0003995 * a, 0.0004 + 0.0003995 * b, 0.000199 + 0.0003995 * c]
                      for a in range(4) for b in range(4) for c in range(4)])
            + np.random.default_rng(1).uniform(-5e-7, 5e-7, (64, 3))).tolist()}],
        "walls": [{"name": "floor", "type": "plane", "point": [0, 0, 0], "normal": [0, 0, 1], "material": "g"},
                  {"name": "x0", "type": "plane", "point": [0.0002, 0, 0], "normal": [1, 0, 0], "material": "g"},
                  {"name": "y0", "type": "plane", "point": [0, 0.0002, 0], "normal": [0, 1, 0], "material": "g"}]}
GAS = {"conductivity": 0.026, "density": 1.2, "viscosity": 1.8e-5, "heat_capacity": 1000.0, "temperature": 300.0}
HEAT = {"initial_temperature": 300.0, "direct": "batchelor_obrien"}

# (name, what the scene adds to BASE, the form it needs: True full, None lean)
SCENES = [
    ("mechanics only", {}, None),
    ("rolling, constant torque", {"contact": {"rolling": "constant_torque"}}, True),
    ("rolling, epsd", {"contact": {"rolling": "epsd"}}, True),
    ("periodic x", {"walls": [], "domain": {"min": [0.0] * 3, "max": [0.004] * 3,
                                            "periodic": [True, False, False]}}, True),
    ("heat, fused Euler", {"thermal": dict(HEAT)}, None),
    ("heat, fused Euler, no correction", {"thermal": dict(HEAT, correction="none")}, None),
    ("heat, geometric contact radius and a correction",
     {"thermal": dict(HEAT, contact_radius="geometric", correction="zhou_2010")}, None),
    ("heat, Hertz force radius", {"thermal": dict(HEAT, contact_radius="hertz_force", correction="none")}, None),
    ("heat, lu_2017 correction", {"thermal": dict(HEAT, correction="lu_2017")}, None),
    ("heat, force radius, morris_2016_area_time",
     {"thermal": dict(HEAT, contact_radius="hertz_force", correction="morris_2016_area_time")}, None),
    ("heat, geometric radius with lu_2017",
     {"thermal": dict(HEAT, contact_radius="geometric", correction="lu_2017")}, True),
    ("heat, linear law, Hertz force radius", {"contact": {"model": "linear_spring_dashpot"},
                                              "thermal": dict(HEAT, contact_radius="hertz_force", correction="none")},
     True),
    ("heat, linear law, overlap radius, zhou_2010", {"contact": {"model": "linear_spring_dashpot"},
                                                     "thermal": dict(HEAT, correction="zhou_2010")}, None),
    ("heat, another direct law", {"thermal": dict(HEAT, direct="thermal_pipe")}, True),
    ("heat, implicit (conductances kept)", {"thermal": dict(HEAT, integrator="implicit")}, None),
    ("heat, convection", {"thermal": dict(HEAT, convection="ranz_marshall"), "gas": GAS}, None),
    ("heat, indirect", {"thermal": dict(HEAT, indirect="vargas_mccarthy_2002"), "gas": GAS}, True),
    ("heat, radiation", {"thermal": dict(HEAT, radiation="zhou_2009"), "gas": GAS}, True),
    ("heat, friction heat", {"thermal": dict(HEAT, friction_heat="nguyen_2009")}, True),
    ("heat, contact age", {"thermal": dict(HEAT, direct="zhou_2008_collisional")}, True),
]


def _sim(extra):
    data = {k: (dict(v) if isinstance(v, dict) else v) for k, v in BASE.items()}
    data.update(extra)
    if "thermal" in data and data["walls"]:   # a hot floor
        data["walls"] = [dict(data["walls"][0], thermal={"condition": "fixed_temperature", "temperature": 350.0})]
    return Simulation.from_dict(data)


@pytest.mark.parametrize("name, extra, form", SCENES, ids=[s[0] for s in SCENES])
def test_each_scene_takes_the_form_it_needs(name, extra, form):
    assert _sim(extra).stepper.xon is form, name


def _state(sim):
    """Every declared array (dem.schema): particles, pairs, walls, the heat totals; of a
    neighbour or wall slot array only the slots in use (nnb, wnn: the others are not written)."""
    st = sim.state
    out = {}
    for f in S.FIELDS:
        a = getattr(st, f.name)
        for slot, count in (("S", st.nnb), ("Q", st.wnn)):
            if f.tail[:1] == (slot,) and a.shape[0]:
                a = a[np.arange(a.shape[1])[None, :] < count[:a.shape[0], None]]
        out[f.name] = a.copy()
    return out




def _by_identity(extra):
    """Whether the lean form computes this scene's contact radius by the Hertz identity (a root
    and a pair constant where the full form takes a cube root of the force: the same to
    round-off only): a force radius, or a force-based correction (BASE's material is softened,
    so a scene without a correction key gets lu_2017, dem.thermal.scene)."""
    th = extra.get("thermal")
    if th is None:
        return False
    return th.get("contact_radius") == "hertz_force" or th.get("correction", "lu_2017") not in ("none", "zhou_2010")


LEAN = [s for s in SCENES if s[2] is None and not _by_identity(s[1])]
IDENTITY = [s for s in SCENES if s[2] is None and _by_identity(s[1])]


@pytest.mark.parametrize("name, extra, form", LEAN, ids=[s[0] for s in LEAN])
def test_lean_form_gives_the_full_forms_results_bit_for_bit(name, extra, form, monkeypatch):
    """300 steps of a settling, colliding bed (contacts open and close, the floor heats it) in
    the lean form and in the full form forced on the same scene: every declared array
    (particles, contacts, walls, heat totals) and the contact count are identical."""
    lean = _sim(extra)
    lean.step(300)
    assert lean.stepper.last_contacts > 40, lean.stepper.last_contacts   # a bed in contact
    monkeypatch.setattr(Stepper, "xon", property(lambda self: True))
    full = _sim(extra)
    full.step(300)
    a, b = _state(lean), _state(full)
    assert a.keys() == b.keys()
    for k in a:
        assert a[k].shape == b[k].shape and np.array_equal(a[k], b[k], equal_nan=True), (name, k)
    assert lean.stepper.last_contacts == full.stepper.last_contacts
    if lean.world.thermal is not None:
        assert np.ptp(lean.state.temperature[:lean.state.n_owned]) > 0   # the floor's heat moved


def test_lean_form_refuses_a_scene_that_needs_the_full_one(monkeypatch):
    """A scene with rolling resistance never runs in the form that leaves it out: the compiled
    step stops with an internal error naming the check (dem.step.full_form)."""
    monkeypatch.setattr(Stepper, "xon", property(lambda self: None))
    sim = _sim({"contact": {"rolling": "epsd"}})
    with pytest.raises(ValueError, match="full_form"):
        sim.step(5)


@pytest.mark.parametrize("name, extra, form", IDENTITY, ids=[s[0] for s in IDENTITY])
def test_lean_radius_by_the_hertz_identity_gives_the_full_forms_heat(name, extra, form, monkeypatch):
    """The force-based radii in the lean form (sqrt(R* delta) times the pair constant) against the
    full form's cube roots of the force, 300 steps of the settling bed heated from its floor: the
    mechanics bit for bit (heat does not act on it), the contacts' heat rates within 1e-12 of
    their largest, the temperatures within 1e-11 K (they move by 2e-4 to 1e-2 K; one unit in the
    last place of 300 K is 5.7e-14 K), the heat totals within 1e-12 of themselves."""
    lean = _sim(extra)
    lean.step(300)
    assert lean.stepper.last_contacts > 40, lean.stepper.last_contacts
    monkeypatch.setattr(Stepper, "xon", property(lambda self: True))
    full = _sim(extra)
    full.step(300)
    a, b = _state(lean), _state(full)
    for k in ("position", "velocity", "angular_velocity", "force", "hist"):
        assert np.array_equal(a[k], b[k]), (name, k)
    n = lean.state.n_owned
    ta, tb = a["temperature"][:n], b["temperature"][:n]
    assert np.ptp(tb) > 1e-4   # the floor's heat moved
    assert np.max(np.abs(ta - tb)) < 1e-11
    qa, qb = a["heat_rate"][:n], b["heat_rate"][:n]
    assert np.max(np.abs(qa - qb)) <= 1e-12 * np.max(np.abs(qb))
    assert np.allclose(a["tot"], b["tot"], rtol=1e-12, atol=0.0)


def test_hertz_radius_factor_is_the_force_based_radius():
    """rc = c sqrt(R* delta) (dem.thermal.contact_radius.hertz_radius_factor) against the
    dispatcher's force-based radius and correction of the Hertz force Fn = 4/3 E* sqrt(R*)
    delta^(3/2), on 2,000 random contacts and moduli, for every method and correction that the
    lean form computes so: within 4e-16 relative (a root against a cube root, a few ulp)."""
    from dem.thermal import contact_radius as CR
    rng = np.random.default_rng(7)
    worst = 0.0
    for method in (CR.HERTZ_FORCE, CR.HERTZ_OVERLAP, CR.GEOMETRIC):
        for corr in CR.CORRECTIONS.values():
            if not CR.lean_radius(method, corr, 0):
                continue
            for _ in range(400):
                ri, rj = rng.uniform(1e-4, 3e-3, 2)
                delta = rng.uniform(1e-6, 5e-2) * min(ri, rj)
                estar, ereal = 10 ** rng.uniform(5, 8), 10 ** rng.uniform(9, 11)
                rstar = ri * rj / (ri + rj)
                fel = 4.0 / 3.0 * estar * np.sqrt(rstar) * delta ** 1.5
                base = CR.geometric_pp(ri, rj, ri + rj - delta) if method == CR.GEOMETRIC \
                    else np.sqrt(rstar * delta)
                lean = CR.hertz_radius_factor(corr, estar, ereal) * base
                # the full form's radius (dem.step.interact_rows): the method's, then the correction
                rc = {CR.HERTZ_FORCE: CR.hertz_force(fel, rstar, estar), CR.HERTZ_OVERLAP: np.sqrt(rstar * delta),
                      CR.GEOMETRIC: base}[method]
                full = CR.apply_correction(method, corr, rc, rstar, fel, estar, ereal)
                worst = max(worst, abs(lean - full) / full)
    assert worst < 4e-16 * 4, worst
    # an unknown real modulus leaves the radius as it is
    assert CR.hertz_radius_factor(CR.LU_2017, 1e7, 0.0) == 1.0
    # the linear law's force-based radii are not of that form: the full form computes them
    assert not CR.lean_radius(CR.HERTZ_FORCE, CR.NONE, 1) and not CR.lean_radius(CR.HERTZ_OVERLAP, CR.LU_2017, 1)
    assert CR.lean_radius(CR.HERTZ_OVERLAP, CR.ZHOU_2010, 1) and not CR.lean_radius(CR.GEOMETRIC, CR.LU_2017, 0)
