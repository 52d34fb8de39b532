"""Insertion regions and radius distributions of a scene: the checks shared by [[particles]]
count groups and [[inlets]] (dem.scene, dem.flow), each raising SceneError through the scene's
validator ``v`` (dem.scene._V) with the key path."""
import math

import numpy as np

def radius_spec(v, g, p):
    """``radius`` of a [[particles]] count group or an [[inlets]] entry: a number, or a table with
    distribution = constant|uniform|normal|lognormal (its min, max, mean, std); the spec of
    dem.insertion.sample_radii."""
    rs = g.get("radius")
    if rs is None:
        v.err(p + ".radius", "missing required key (a number, or a table with distribution = "
                             "constant|uniform|normal|lognormal)")
    if not isinstance(rs, dict):
        return dict(distribution="constant", value=v.num(g, "radius", p, lo=0, lo_open=True, required=True))
    v.table(rs, p + ".radius", {"distribution", "value", "min", "max", "mean", "std"}, required=("distribution",))
    dist = v.string(rs, "distribution", p + ".radius", choices=["constant", "uniform", "normal", "lognormal"],
                    required=True)
    if dist == "constant":
        v.num(rs, "value", p + ".radius", lo=0, lo_open=True, required=True)
    else:
        a = v.num(rs, "min", p + ".radius", lo=0, lo_open=True, required=True)
        b = v.num(rs, "max", p + ".radius", lo=0, lo_open=True, required=True)
        if b < a:
            v.err(p + ".radius.max", f"must be >= min ({a}), got {b}")
        if dist in ("normal", "lognormal"):
            mean = v.num(rs, "mean", p + ".radius", lo=0, lo_open=True, required=True)
            v.num(rs, "std", p + ".radius", lo=0, lo_open=True, required=True)
            if not a <= mean <= b:
                v.err(p + ".radius.mean", f"must lie in [min, max] = [{a}, {b}], got {mean}")
    return rs


def spec_bounds(spec):
    """(smallest, largest) radius of a radius spec (:func:`radius_spec`)."""
    if spec["distribution"] == "constant":
        return float(spec["value"]), float(spec["value"])
    return float(spec["min"]), float(spec["max"])


def region(v, g, p, key="region"):
    """``region`` of a count group or an inlet: a box (min, max) or a cylinder (center, axis, radius,
    length), checked; returned as given (dem.insertion.insert reads it)."""
    reg = g.get(key)
    if reg is None:
        v.err(f"{p}.{key}", "missing required key (a table with type = box|cylinder)")
    q = f"{p}.{key}"
    v.table(reg, q, {"type", "min", "max", "center", "axis", "radius", "length"}, required=("type",))
    rt = v.string(reg, "type", q, choices=["box", "cylinder"], required=True)
    if rt == "box":
        a = v.vec(reg, "min", q, required=True)
        b = v.vec(reg, "max", q, required=True)
        if np.any(b <= a):
            v.err(q + ".max", "must be larger than region.min on every axis")
    else:
        v.vec(reg, "center", q, required=True)
        v.unit(reg, "axis", q)
        v.num(reg, "radius", q, lo=0, lo_open=True, required=True)
        v.num(reg, "length", q, lo=0, lo_open=True, required=True)
    return reg


def region_volume(reg):
    """Volume (m^3) of a checked region (:func:`region`)."""
    if reg["type"] == "box":
        return float(np.prod(np.asarray(reg["max"], float) - np.asarray(reg["min"], float)))
    return math.pi * float(reg["radius"]) ** 2 * float(reg["length"])

def region_box(reg):
    """(lo, hi) of the box around a checked region (a cylinder's: its axis' extent plus the
    radius across it)."""
    if reg["type"] == "box":
        return np.asarray(reg["min"], float), np.asarray(reg["max"], float)
    ax = np.asarray(reg["axis"], float) / np.linalg.norm(reg["axis"])
    ext = np.abs(ax) * float(reg["length"]) / 2 + np.sqrt(np.maximum(0.0, 1 - ax ** 2)) * float(reg["radius"])
    c = np.asarray(reg["center"], float)
    return c - ext, c + ext


def check_region_in_domain(v, p, reg, spec, lo, hi, periodic):
    """The centres an insertion region can receive must lie inside the domain (non-periodic
    axes): its box (or the box around its cylinder) shrunk by the smallest radius."""
    rmin = float(spec["value"] if spec["distribution"] == "constant" else spec["min"])
    a, b = region_box(reg)
    tol = 1e-9 * float(np.max(hi - lo))
    for k in range(3):
        if periodic[k]:
            continue
        if a[k] + rmin < lo[k] - tol or b[k] - rmin > hi[k] + tol:
            v.err(p + ".region", f"reaches outside the domain on axis {'xyz'[k]} (region {a[k]:g} .. {b[k]:g} m, "
                                 f"domain {lo[k]:g} .. {hi[k]:g} m): particles could be placed outside; keep "
                                 "the region inside [domain]")
