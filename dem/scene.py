"""Scene files (TOML) -> a validated, typed scene.

Everything is checked before any computation; each problem raises :class:`SceneError`
naming the file, the key path (``particles[1].radius``) and what is allowed.
"""
import math
import os
import tomllib

import numpy as np

from .contact.registry import CONTACT_MODELS, ROLLING_MODELS, DAMPING_MODELS, TANGENTIAL_MODELS
from .errors import SceneError
from .parcels import parcel_factors
from .regions import check_region_in_domain, radius_spec, region, region_box, region_volume, spec_bounds


_NUM = (int, float)
# largest magnitude of any number in a scene: cubes and products of two stay finite in float64
MAX_MAGNITUDE = 1e100


class _V:
    """Small validation helper bound to a file name."""

    def __init__(self, file):
        self.file = file

    def err(self, path, msg):
        raise SceneError(self.file, path, msg)

    def table(self, d, path, allowed, required=()):
        if not isinstance(d, dict):
            self.err(path, f"must be a table, got {type(d).__name__}")
        for k in d:
            if k not in allowed:
                self.err(f"{path}.{k}" if path else k,
                         f"unknown key; allowed keys: {', '.join(sorted(allowed))}")
        for k in required:
            if k not in d:
                self.err(f"{path}.{k}" if path else k, "missing required key")
        return d

    def num(self, d, key, path, default=None, lo=None, hi=None, lo_open=False, hi_open=False,
            required=False):
        p = f"{path}.{key}" if path else key
        if key not in d:
            if required:
                self.err(p, "missing required key")
            return default
        x = d[key]
        if isinstance(x, bool) or not isinstance(x, _NUM):
            self.err(p, f"must be a number, got {x!r}")
        x = float(x)
        if not math.isfinite(x):
            self.err(p, f"must be finite, got {x}")
        if abs(x) > MAX_MAGNITUDE:
            self.err(p, f"{x:g} is too large to compute with (|value| <= {MAX_MAGNITUDE:g}); check the units")
        rng = f"{'(' if lo_open or lo is None else '['}{'-inf' if lo is None else lo}, " \
              f"{'inf' if hi is None else hi}{')' if hi_open or hi is None else ']'}"
        if lo is not None and (x < lo or (lo_open and x == lo)):
            self.err(p, f"must be in {rng}, got {x}")
        if hi is not None and (x > hi or (hi_open and x == hi)):
            self.err(p, f"must be in {rng}, got {x}")
        return x

    def integer(self, d, key, path, default=None, lo=None, required=False):
        p = f"{path}.{key}" if path else key
        if key not in d:
            if required:
                self.err(p, "missing required key")
            return default
        x = d[key]
        if isinstance(x, bool) or not isinstance(x, int):
            self.err(p, f"must be an integer, got {x!r}")
        if lo is not None and x < lo:
            self.err(p, f"must be >= {lo}, got {x}")
        return x

    def boolean(self, d, key, path, default=False):
        if key not in d:
            return default
        x = d[key]
        if not isinstance(x, bool):
            self.err(f"{path}.{key}" if path else key, f"must be true or false, got {x!r}")
        return x

    def string(self, d, key, path, default=None, choices=None, required=False):
        p = f"{path}.{key}" if path else key
        if key not in d:
            if required:
                self.err(p, "missing required key" + (f"; one of: {', '.join(choices)}" if choices else ""))
            return default
        x = d[key]
        if not isinstance(x, str):
            self.err(p, f"must be a string, got {x!r}")
        if choices is not None and x not in choices:
            self.err(p, f"unknown value {x!r}; valid: {', '.join(choices)}")
        return x

    def vec(self, d, key, path, n=3, default=None, required=False, kind="number"):
        p = f"{path}.{key}" if path else key
        if key not in d:
            if required:
                self.err(p, "missing required key")
            return default
        x = d[key]
        ok = isinstance(x, list) and len(x) == n and all(
            (isinstance(e, bool) if kind == "bool" else (isinstance(e, _NUM) and not isinstance(e, bool)))
            for e in x)
        if not ok:
            self.err(p, f"must be a list of {n} {'booleans' if kind == 'bool' else 'numbers'}, got {x!r}")
        if kind == "bool":
            return [bool(e) for e in x]
        arr = np.array(x, float)
        if not np.all(np.isfinite(arr)):
            self.err(p, f"must be finite numbers (no nan or inf), got {arr.tolist()}")
        if np.any(np.abs(arr) > MAX_MAGNITUDE):
            self.err(p, f"{arr.tolist()} is too large to compute with (|value| <= {MAX_MAGNITUDE:g}); check the units")
        return arr

    def unit(self, d, key, path, required=True, default=None):
        a = self.vec(d, key, path, required=required, default=default)
        if a is None:
            return None
        nrm = np.linalg.norm(a)
        if nrm == 0:
            self.err(f"{path}.{key}", "must be a non-zero vector")
        return a / nrm


SIM_KEYS = {"time_step", "end_time", "gravity", "output_interval", "checkpoint_interval", "seed",
            "force", "max_overlap_ratio", "mechanics", "neighbor_skin", "initial_overlap_ratio",
            "sort_interval"}
MAT_KEYS_MECH = {"name", "density", "youngs_modulus", "poisson_ratio", "restitution", "friction",
                 "rolling_friction"}
PART_KEYS = {"material", "positions", "radii", "radius", "velocities", "velocity", "file", "count",
             "region", "temperature", "angular_velocities", "coarse_graining"}
WALL_KEYS = {"type", "material", "point", "normal", "extent", "u_axis", "axis", "radius", "inside",
             "length", "velocity", "angular_velocity", "rotation_center", "name", "thermal",
             "file", "scale", "rotate", "translate", "oscillation"}
MESH_ONLY = {"file", "scale", "rotate", "translate", "oscillation"}
CONTACT_KEYS = {"model", "rolling", "damping", "tangential", "normal_stiffness", "tangential_stiffness_ratio",
                "characteristic_velocity", "rolling_damping"}
OUTPUT_KEYS = {"vtk", "heat_by_mechanism", "contacts"}
PARALLEL_KEYS = {"decomposition", "slab_axis", "balance_threshold", "pair_weight", "insertion_block"}
TOP_KEYS = {"simulation", "domain", "materials", "particles", "walls", "contact", "output",
            "thermal", "gas", "parallel", "inlets", "outlets"}

# Time-step limits (documented in docs/models.md): dt <= 0.3 t_Rayleigh and
# dt <= t_Hertz / 10 at the characteristic impact velocity, unless [simulation] force = true.
RAYLEIGH_FRACTION = 0.3
HERTZ_FRACTION = 0.1


def load(path, end_time=None, comm="auto"):
    """Read and validate a scene file; returns a :class:`Scene`. ``end_time``: the end time
    a caller supplies when the file has no ``simulation.end_time`` (a coupled case takes
    its end time from system/controlDict); without it the key is required. The scene
    records whether the file gave one (``Scene.end_time_in_file``)."""
    path = os.fspath(path)
    if os.path.isdir(path):
        raise SceneError(path, "", "is a folder; give the scene file (.toml)")
    try:
        with open(path, "rb") as fh:
            raw = fh.read()
    except FileNotFoundError:
        raise SceneError(path, "", "file not found") from None
    except OSError as exc:
        raise SceneError(path, "", f"cannot read: {exc.strerror or exc}") from None
    try:
        text = raw.decode("utf-8").removeprefix("\ufeff")
    except UnicodeDecodeError as exc:
        line = raw[:exc.start].count(b"\n") + 1
        raise SceneError(path, "", f"line {line}: not UTF-8 text (byte 0x{raw[exc.start]:02x}); a scene is a "
                                   "TOML text file saved as UTF-8") from None
    try:
        data = tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        raise SceneError(path, "", f"not valid TOML: {exc}") from None
    return parse(data, path, base_dir=os.path.dirname(os.path.abspath(path)), end_time=end_time, comm=comm)


class Scene:
    """Validated scene: plain dicts plus particle arrays."""

    def __init__(self, **kw):
        self.__dict__.update(kw)


def _read_particle_file(v, fname, path, base_dir, part=None):
    """A packing file (dem.particle_file): every cell checked, problems named by line/row
    and column under the key ``particles[k].file``. ``part`` (MPI): only this rank's slice
    of the rows (dem.particle_file.read_part), the problems agreed over the ranks."""
    from .particle_file import ParticleFileError, read, read_part
    full = fname if os.path.isabs(fname) else os.path.join(base_dir, fname)
    try:
        if part is None:
            cols, where = read(full)
        else:
            got = read_part(full, part)
            cols, where = got.cols, got.where
            part.rows_read += got.rows_read
    except ParticleFileError as exc:
        v.err(path + ".file", str(exc))
    n = cols["x"].size
    zero = np.zeros(n)
    pos = np.stack([cols["x"], cols["y"], cols["z"]], 1)
    vel = np.stack([cols.get("vx", zero), cols.get("vy", zero), cols.get("vz", zero)], 1)
    om = np.stack([cols.get("wx", zero), cols.get("wy", zero), cols.get("wz", zero)], 1)
    return pos, cols["radius"].copy(), vel, om, cols.get("id"), cols.get("temperature"), where


# densest packing of equal spheres (Kepler): no region holds more sphere volume than this
DENSEST_PACKING = math.pi / (3 * math.sqrt(2))




def _check_count(v, p, reg, spec, n, force, block=None, ranks=1):
    """An insertion ``count`` that cannot fit: more sphere volume (at the smallest radius of
    the distribution) than the densest packing of the region, or more memory than the
    machine has for the candidate arrays (dem.memory)."""
    from .memory import check_insertion
    vol = region_volume(reg)
    rmin, rmax = spec_bounds(spec)
    need = n * 4.0 / 3.0 * math.pi * rmin ** 3
    if need > DENSEST_PACKING * vol:
        v.err(p + ".count", f"{n} spheres of radius >= {rmin:g} m hold {need:.3g} m3, more than the "
                            f"densest packing ({DENSEST_PACKING:.3f}) of the region's {vol:.3g} m3 can hold "
                            f"(at most {int(DENSEST_PACKING * vol / (4.0 / 3.0 * math.pi * rmin ** 3))}); "
                            "enlarge the region or lower the count")
    if block is None:
        check_insertion(v, p + ".count", reg, n, rmax, force)
    else:   # by blocks: one block at a time, and one rank's share of the particles
        from .memory import check_block_insertion
        blo, bhi = _block_boxes(np.asarray(reg["min"], float), np.asarray(reg["max"], float), -(-n // block))
        check_block_insertion(v, p + ".count", n, dict(type="box", min=blo[0], max=bhi[0]), block, rmax,
                              ranks, force)


def _finite_rows(v, arr, key):
    """``key[k]: must be finite`` for the first row of ``arr`` holding nan or inf."""
    bad = np.nonzero(~np.isfinite(arr.reshape(len(arr), -1)).all(1))[0]
    if bad.size:
        k = bad[0]
        v.err(f"{key}[{k}]", f"must be finite numbers (no nan or inf), got {arr[k].tolist()}")
    big = np.nonzero((np.abs(arr.reshape(len(arr), -1)) > MAX_MAGNITUDE).any(1))[0]
    if big.size:
        k = big[0]
        v.err(f"{key}[{k}]", f"{arr[k].tolist()} is too large to compute with (|value| <= {MAX_MAGNITUDE:g}); "
                             "check the units")


def parse(data, file="<dict>", base_dir=".", end_time=None, comm="auto"):
    """Validate a scene given as a dict (see :func:`load` for ``end_time``).

    ``comm``: under ``mpirun -np N`` (N > 1; "auto": dem.parallel.world()) the scene is set up
    per rank (docs/architecture.md, "Set-up under MPI"): this rank's slice of every packing
    file and explicit list, the ``count`` groups inserted on one rank each; the scene's
    arrays are then this rank's rows (in group order) and ``n_total``, ``rmax`` are the
    run's. None: the whole scene on this process (the serial set-up)."""
    if comm == "auto":
        from .parallel import world
        comm = world()
    part = None
    if comm is not None:
        from .parallel.setup import SetupComm
        part = SetupComm(comm)
    v = _V(file)
    v.table(data, "", TOP_KEYS, required=("simulation", "domain", "materials", "particles"))
    # --- simulation
    need_end = end_time is None
    s = v.table(data["simulation"], "simulation", SIM_KEYS,
                required=("time_step", "end_time") if need_end else ("time_step",))
    sim = dict(
        time_step=v.num(s, "time_step", "simulation", lo=0, lo_open=True, required=True),
        end_time=v.num(s, "end_time", "simulation", lo=0, required=need_end,
                       default=None if need_end else float(end_time)),
        gravity=v.vec(s, "gravity", "simulation", default=np.array([0.0, 0.0, -9.81])),
        seed=v.integer(s, "seed", "simulation", default=0, lo=0),
        force=v.boolean(s, "force", "simulation"),
        mechanics=v.boolean(s, "mechanics", "simulation", default=True),
        max_overlap_ratio=v.num(s, "max_overlap_ratio", "simulation", default=0.1, lo=0, lo_open=True, hi=1),
        initial_overlap_ratio=v.num(s, "initial_overlap_ratio", "simulation", default=0.05, lo=0, hi=1),
        neighbor_skin=_skin(v, s),
        sort_interval=v.integer(s, "sort_interval", "simulation", default=1000, lo=0),
    )
    sim["output_interval"] = v.num(s, "output_interval", "simulation", default=sim["end_time"] / 10 or 1.0,
                                   lo=0, lo_open=True)
    sim["checkpoint_interval"] = v.num(s, "checkpoint_interval", "simulation", default=0.0, lo=0)
    if sim["output_interval"] < sim["time_step"]:
        v.err("simulation.output_interval", f"must be >= time_step ({sim['time_step']}), got {sim['output_interval']}")
    # --- domain
    d = v.table(data["domain"], "domain", {"min", "max", "periodic"}, required=("min", "max"))
    lo = v.vec(d, "min", "domain", required=True)
    hi = v.vec(d, "max", "domain", required=True)
    if np.any(hi <= lo):
        v.err("domain.max", f"must be larger than domain.min on every axis, got min {lo.tolist()} max {hi.tolist()}")
    periodic = v.vec(d, "periodic", "domain", kind="bool", default=[False, False, False])
    # --- materials
    mats = data["materials"]
    if not isinstance(mats, list) or not mats:
        v.err("materials", "must be a non-empty array of tables [[materials]]")
    thermal_keys = set()
    try:
        from .thermal.registry import MATERIAL_KEYS as _TK  # thermal issue: optional keys
        thermal_keys = set(_TK)
    except Exception:  # noqa: BLE001
        thermal_keys = set()
    materials, names = [], {}
    for k, m in enumerate(mats):
        p = f"materials[{k}]"
        v.table(m, p, MAT_KEYS_MECH | thermal_keys, required=("name", "density"))
        name = v.string(m, "name", p, required=True)
        if name in names:
            v.err(p + ".name", f"duplicate material name {name!r} (already materials[{names[name]}]); "
                               "material names must be unique")
        names[name] = k
        mm = dict(name=name,
                  density=v.num(m, "density", p, lo=0, lo_open=True, required=True),
                  youngs_modulus=v.num(m, "youngs_modulus", p, lo=0, lo_open=True, required=True),
                  poisson_ratio=v.num(m, "poisson_ratio", p, lo=-1, hi=0.5, lo_open=True, hi_open=True, required=True),
                  restitution=v.num(m, "restitution", p, lo=0, hi=1, lo_open=True, required=True),
                  friction=v.num(m, "friction", p, lo=0, default=0.0),
                  rolling_friction=v.num(m, "rolling_friction", p, lo=0, default=0.0))
        for tk in thermal_keys:
            if tk in m:
                mm[tk] = m[tk]
        materials.append(mm)

    def mat_ref(tbl, p):
        nm = v.string(tbl, "material", p, required=True)
        if nm not in names:
            v.err(p + ".material", f"unknown material {nm!r}; defined: {', '.join(names)}")
        return names[nm]

    # --- contact
    c = v.table(data.get("contact", {}), "contact", CONTACT_KEYS)
    contact = dict(
        model=v.string(c, "model", "contact", default="hertz_mindlin", choices=list(CONTACT_MODELS)),
        rolling=v.string(c, "rolling", "contact", default="none", choices=list(ROLLING_MODELS)),
        damping=v.string(c, "damping", "contact", default="exact", choices=list(DAMPING_MODELS)),
        tangential=v.string(c, "tangential", "contact", default="rescaled", choices=list(TANGENTIAL_MODELS)),
        normal_stiffness=v.num(c, "normal_stiffness", "contact", default=0.0, lo=0),
        tangential_stiffness_ratio=v.num(c, "tangential_stiffness_ratio", "contact", default=2.0 / 7.0, lo=0, lo_open=True),
        characteristic_velocity=v.num(c, "characteristic_velocity", "contact", default=None, lo=0, lo_open=True),
        rolling_damping=v.num(c, "rolling_damping", "contact", default=0.3, lo=0),
    )
    if contact["rolling"] != "none" and all(m["rolling_friction"] == 0 for m in materials):
        v.err("contact.rolling", f"rolling model {contact['rolling']!r} needs rolling_friction > 0 in at least one material")
    # --- particles
    parts = data["particles"]
    if not isinstance(parts, list) or not parts:
        v.err("particles", "must be a non-empty array of tables [[particles]]")
    rng = np.random.default_rng(sim["seed"])
    P = dict(x=[], r=[], v=[], w=[], mat=[], id=[], T=[], group=[], mode=[], where=[], cg=[], cgv=[], gidx=[])
    n_count_groups = 0
    pa0 = data.get("parallel", {})
    block = INSERTION_BLOCK
    if isinstance(pa0, dict) and "insertion_block" in pa0:
        block = v.integer(pa0, "insertion_block", "parallel", lo=100)
    from .insertion import insert, sample_radii
    for k, g in enumerate(parts):
        p = f"particles[{k}]"
        v.table(g, p, PART_KEYS, required=("material",))
        mi = mat_ref(g, p)
        # coarse graining (issue 15): each parcel stands for cg^3 real particles; the radii given
        # are the real particles', the parcel's is cg times larger (docs/models.md)
        cg = v.num(g, "coarse_graining", p, default=1.0, lo=1.0)
        if cg > 1000.0:
            v.err(p + ".coarse_graining", f"must be in [1.0, 1000.0] (a parcel of at most 1e9 particles), got {cg}")
        modes = [m for m in ("positions", "file", "count") if m in g]
        if len(modes) != 1:
            v.err(p, "give exactly one of 'positions' (explicit list), 'file' (CSV/NPZ) or 'count' (insertion)"
                  + (f"; got {', '.join(modes)}" if modes else ""))
        mode = modes[0]
        ids = None
        temp_col = None
        om = None
        where = None
        if mode == "positions":
            pos = g["positions"]
            if not isinstance(pos, list) or not pos or not all(
                    isinstance(q, list) and len(q) == 3 and all(isinstance(e, _NUM) and not isinstance(e, bool) for e in q)
                    for q in pos):
                v.err(p + ".positions", "must be a non-empty list of [x, y, z] number triples")
            pos = np.array(pos, float)
            _finite_rows(v, pos, p + ".positions")
            n = len(pos)
            if "radii" in g:
                if "radius" in g:
                    v.err(p + ".radius", "give either 'radius' (one for all) or 'radii' (one per position), not both")
                rr = g["radii"]
                if not isinstance(rr, list) or len(rr) != n or not all(isinstance(e, _NUM) and not isinstance(e, bool) for e in rr):
                    v.err(p + ".radii", f"must be a list of {n} numbers (one per position)")
                rad = np.array(rr, float)
                _finite_rows(v, rad, p + ".radii")
                bad = np.nonzero(~(rad > 0))[0]
                if bad.size:
                    v.err(f"{p}.radii[{bad[0]}]", f"radius must be > 0, got {rad[bad[0]]}")
            else:
                if "radius" not in g:
                    v.err(p + ".radius", "missing required key (or 'radii', one per position)")
                rad = np.full(n, v.num(g, "radius", p, lo=0, lo_open=True, required=True))
            vel = np.zeros((n, 3))
            if "velocities" in g:
                vv = g["velocities"]
                if not isinstance(vv, list) or len(vv) != n or not all(
                        isinstance(q, list) and len(q) == 3 and all(isinstance(e, _NUM) and not isinstance(e, bool) for e in q) for q in vv):
                    v.err(p + ".velocities", f"must be a list of {n} [vx, vy, vz] triples")
                vel = np.array(vv, float)
                _finite_rows(v, vel, p + ".velocities")
            if "angular_velocities" in g:
                vv = g["angular_velocities"]
                if not isinstance(vv, list) or len(vv) != n or not all(
                        isinstance(q, list) and len(q) == 3 and all(isinstance(e, _NUM) and not isinstance(e, bool) for e in q) for q in vv):
                    v.err(p + ".angular_velocities", f"must be a list of {n} [wx, wy, wz] triples")
                om = np.array(vv, float)
                _finite_rows(v, om, p + ".angular_velocities")
            if part is not None:   # the TOML list is parsed whole by every rank; each keeps its slice
                a, b = n * part.rank // part.size, n * (part.rank + 1) // part.size
                pos, rad, vel = pos[a:b], rad[a:b], vel[a:b]
                om = om[a:b] if om is not None else None
                n = b - a
        elif mode == "file":
            fname = v.string(g, "file", p, required=True)
            pos, rad, vel, om, ids, temp_col, where = _read_particle_file(v, fname, p, base_dir, part)
            n = len(pos)
        else:
            n = v.integer(g, "count", p, lo=1, required=True)
            spec = radius_spec(v, g, p)
            reg = region(v, g, p)
            # the checks see the parcels' radii
            spec_p = {key: (val * cg if key in ("value", "min", "max", "mean", "std") else val)
                      for key, val in spec.items()}
            check_region_in_domain(v, p, reg, spec_p, lo, hi, periodic)
            gidx = None
            if n > block:   # by blocks: the same particles on any number of ranks, serial included
                if reg["type"] != "box":
                    v.err(p + ".count", f"{n} particles, more than parallel.insertion_block = {block}, in a "
                                        f"{reg['type']} region: insertion by blocks takes a box region; use a box, split "
                                        "the group, or give a packing file")
                _check_count(v, p, reg, spec_p, n, sim["force"], block=block,
                             ranks=1 if part is None else part.size)
                pos, rad, gidx, placed = _insert_blocks(part, reg, spec, cg, n, block, sim["seed"], k, P)
            else:
                _check_count(v, p, reg, spec_p, n, sim["force"])
                rad = sample_radii(spec, n, rng) * cg
            if gidx is None and part is None:
                ex_x = np.concatenate(P["x"]) if P["x"] else np.zeros((0, 3))
                ex_r = np.concatenate(P["r"]) if P["r"] else np.zeros(0)
                pos, keep, placed = insert(reg, rad, rng, ex_x, ex_r)
            elif gidx is None:
                pos, rad, placed = _insert_part(v, p, part, reg, rad, rng, P, n_count_groups)
            n_count_groups += 1
            if placed < n:
                v.err(p + ".count", f"could place only {placed} of {n} particles without overlap in the region; "
                                    "enlarge the region or lower the count")
            n = len(pos)
            vel = np.zeros((n, 3))
        if mode != "count":
            rad = rad * cg   # the parcels' radii (count: before the insertion)
        if "velocity" in g:
            vel = np.tile(v.vec(g, "velocity", p, required=True), (n, 1))
        if om is None:
            om = np.zeros((n, 3))
        T = None
        if "temperature" in g:
            T = np.full(n, v.num(g, "temperature", p, lo=0, lo_open=True))
        elif temp_col is not None:
            T = temp_col
        P["x"].append(pos)
        P["r"].append(rad)
        P["v"].append(vel)
        P["w"].append(om)
        P["mat"].append(np.full(n, mi, np.int32))
        P["id"].append(ids)
        P["T"].append(T)
        P["group"].append(np.full(n, k, np.int32))
        P["cg"].append(np.full(n, cg))
        P["cgv"].append(cg)
        P["mode"].append(mode)
        P["where"].append(where)
        P["gidx"].append(gidx if mode == "count" else None)
    x = np.ascontiguousarray(np.concatenate(P["x"]))
    r = np.ascontiguousarray(np.concatenate(P["r"]))
    n = r.size
    if part is not None:
        ids, group, totals = _ids_and_domain_part(v, part, P, x, lo, hi, periodic)
    elif any(i is not None for i in P["id"]):
        ids, nxt = [], 1
        for i, xx in zip(P["id"], P["x"]):
            ids.append(i.astype(np.int64) if i is not None else np.arange(nxt, nxt + len(xx)))
            nxt = max(nxt, int(ids[-1].max()) + 1)
        ids = np.concatenate(ids)
        if np.unique(ids).size != n:
            v.err("particles", "particle ids are not unique across groups")
    else:
        ids = np.arange(1, n + 1, dtype=np.int64)
    if part is None:
        group = np.concatenate(P["group"])
    _check_inside_domain(v, P, x, ids, group, lo, hi, periodic, part, totals if part is not None else None)
    # --- walls
    walls = []
    if not isinstance(data.get("walls", []), list):
        v.err("walls", "must be an array of tables [[walls]]")
    for k, wl in enumerate(data.get("walls", [])):
        p = f"walls[{k}]"
        v.table(wl, p, WALL_KEYS, required=("type", "material"))
        wt = v.string(wl, "type", p, choices=["plane", "cylinder", "mesh"], required=True)
        W = dict(type=wt, material=mat_ref(wl, p), name=v.string(wl, "name", p, default=f"wall{k}"),
                 velocity=v.vec(wl, "velocity", p, default=np.zeros(3)),
                 angular_velocity=v.vec(wl, "angular_velocity", p, default=np.zeros(3)),
                 thermal=wl.get("thermal"))
        if wt == "mesh":
            v.table(wl, p, WALL_KEYS - {"point", "normal", "extent", "u_axis", "axis", "radius", "inside", "length"})
            W.update(_mesh_wall(v, wl, p, base_dir, lo, hi))
            W["rotation_center"] = v.vec(wl, "rotation_center", p, default=W["point"])
            if "oscillation" in wl:   # a prescribed periodic translation (a vibrating wall)
                o = v.table(wl["oscillation"], p + ".oscillation", {"amplitude", "frequency", "phase"},
                            required=("amplitude", "frequency"))
                W["oscillation"] = dict(amplitude=v.vec(o, "amplitude", p + ".oscillation"),
                                        frequency=v.num(o, "frequency", p + ".oscillation", lo=0, lo_open=True),
                                        phase=v.num(o, "phase", p + ".oscillation", default=0.0))
        elif wt == "plane":
            v.table(wl, p, WALL_KEYS - {"axis", "radius", "inside", "length"} - MESH_ONLY)
            W["point"] = v.vec(wl, "point", p, required=True)
            W["normal"] = v.unit(wl, "normal", p)
            ext = v.vec(wl, "extent", p, n=2, default=None)
            if ext is not None and np.any(ext <= 0):
                v.err(p + ".extent", "half sizes must be > 0")
            W["extent"] = ext
            ua = v.unit(wl, "u_axis", p, required=False)
            if ua is None:
                nn = W["normal"]
                ua = np.cross(nn, [1.0, 0, 0] if abs(nn[0]) < 0.9 else [0, 1.0, 0])
            ua = ua - ua.dot(W["normal"]) * W["normal"]
            if np.linalg.norm(ua) < 1e-9:
                v.err(p + ".u_axis", "must not be parallel to the normal")
            W["u_axis"] = ua / np.linalg.norm(ua)
            W["rotation_center"] = v.vec(wl, "rotation_center", p, default=W["point"])
            om = W["angular_velocity"]
            if np.linalg.norm(np.cross(om, W["normal"])) > 1e-12 * max(1.0, np.linalg.norm(om)):
                v.err(p + ".angular_velocity", "a plane may only turn about its normal (its surface must stay in place)")
        else:
            v.table(wl, p, WALL_KEYS - {"normal", "extent", "u_axis"} - MESH_ONLY)
            W["point"] = v.vec(wl, "point", p, required=True)
            W["axis"] = v.unit(wl, "axis", p)
            W["radius"] = v.num(wl, "radius", p, lo=0, lo_open=True, required=True)
            W["inside"] = v.boolean(wl, "inside", p, default=True)
            W["length"] = v.num(wl, "length", p, default=math.inf, lo=0, lo_open=True)
            W["rotation_center"] = v.vec(wl, "rotation_center", p, default=W["point"])
            om = W["angular_velocity"]
            if np.linalg.norm(np.cross(om, W["axis"])) > 1e-12 * max(1.0, np.linalg.norm(om)):
                v.err(p + ".angular_velocity", "a cylinder may only turn about its own axis")
            if np.linalg.norm(np.cross(W["rotation_center"] - W["point"], W["axis"])) > 1e-12:
                v.err(p + ".rotation_center", "must lie on the cylinder axis")
        walls.append(W)
    if part is None:
        _check_periodic_length(v, lo, hi, periodic, r)
        _check_walls(v, walls, x, ids, periodic)
        _check_meshes(v, walls, x, r, ids, sim["initial_overlap_ratio"])
        rmax = float(r.max())
    else:
        rmax = float(part.max(r.max(initial=0.0)))
        _check_periodic_length(v, lo, hi, periodic, np.array([rmax]))
        _check_walls(v, walls, x, ids, periodic, part, totals)
        _check_meshes(v, walls, x, r, ids, sim["initial_overlap_ratio"], part, totals)
    from . import flow as flow_mod
    inlets, outlets = flow_mod.parse(v, data, sim, lo, hi, periodic, mat_ref, materials, len(parts))
    if (inlets or outlets) and not sim["mechanics"]:
        v.err("inlets" if inlets else "outlets", "particles enter and leave a moving bed: not with "
                                                 "simulation.mechanics = false (a frozen packing)")
    if inlets and any(c != 1.0 for c in P["cgv"]):
        v.err("inlets", "an inlet's particles are real particles: not with coarse-grained [[particles]] "
                        "(particles[].coarse_graining) in the same scene")
    flow_rmax = max([i["rmax"] for i in inlets], default=0.0)
    next_id = int(ids.max(initial=0)) + 1 if part is None else int(part.max(int(ids.max(initial=0)))) + 1
    o = v.table(data.get("output", {}), "output", OUTPUT_KEYS)
    output = dict(vtk=v.boolean(o, "vtk", "output", default=True),
                  heat_by_mechanism=v.boolean(o, "heat_by_mechanism", "output", default=False),
                  contacts=v.boolean(o, "contacts", "output", default=False))
    if output["heat_by_mechanism"] and data.get("thermal") is None:
        v.err("output.heat_by_mechanism", "needs a [thermal] section (the heat of each particle by mechanism)")
    pa = v.table(data.get("parallel", {}), "parallel", PARALLEL_KEYS)
    parallel = dict(
        decomposition=v.string(pa, "decomposition", "parallel", default="rcb", choices=("rcb", "slabs")),
        slab_axis=v.string(pa, "slab_axis", "parallel", default="auto", choices=("auto", "x", "y", "z")),
        balance_threshold=v.num(pa, "balance_threshold", "parallel", default=1.1, lo=1.0),
        pair_weight=v.num(pa, "pair_weight", "parallel", default=1.0, lo=0.0))
    # "auto" (the default): chosen at each build up to 0.2 r_max (dem.neighbors.adaptive_skin)
    sim["neighbor_skin_auto"] = sim["neighbor_skin"] is None
    if sim["neighbor_skin"] is None:
        sim["neighbor_skin"] = 0.2 * max(rmax, flow_rmax)
    sc = Scene(file=file, base_dir=base_dir, simulation=sim, domain=dict(min=lo, max=hi, periodic=periodic),
               materials=materials, material_index=names, contact=contact, walls=walls, output=output,
               parallel=parallel, id=ids, position=x, radius=r, velocity=np.ascontiguousarray(np.concatenate(P["v"])),
               angular_velocity=np.ascontiguousarray(np.concatenate(P["w"])),
               material=np.concatenate(P["mat"]), group=group, coarse_graining=np.concatenate(P["cg"]),
               temperature=P["T"], raw=data, thermal=None, end_time_in_file="end_time" in s,
               n_total=n, rmax=rmax, group_cg=list(P["cgv"]),
               materials_used=sorted(set(np.unique(np.concatenate(P["mat"])).tolist())), distributed=False,
               inlets=inlets, outlets=outlets, flow_rmax=flow_rmax, next_id=next_id)
    if part is None:
        _check_overlaps(v, sc)
    else:   # the overlaps are checked once the particles sit on their owners (dem.parallel.setup)
        _scene_part(sc, part, totals, P)
    _thermal_hook(v, sc, data)
    if part is not None:
        from .parallel.setup import particle_digests
        particle_digests(sc, part)
    return sc


def _skin(v, s):
    """simulation.neighbor_skin: a length (m), fixed; or "auto" (also when absent): None, the
    skin then chosen at each neighbour build (dem.neighbors.adaptive_skin)."""
    if s.get("neighbor_skin") == "auto":
        return None
    if isinstance(s.get("neighbor_skin"), str):
        v.err("simulation.neighbor_skin", f"must be a length in m (> 0) or \"auto\", got {s['neighbor_skin']!r}")
    return v.num(s, "neighbor_skin", "simulation", default=None, lo=0, lo_open=True)


def _check_periodic_length(v, lo, hi, periodic, r):
    """A periodic axis must be at least two of the largest diameters long: the neighbour
    search takes the nearest image of each neighbour, so a sphere must never touch two
    images of the same neighbour (or its own image)."""
    d = 2.0 * float(r.max())
    for ax in range(3):
        L = float(hi[ax] - lo[ax])
        if periodic[ax] and L < 2.0 * d:
            v.err("domain.periodic", f"axis {'xyz'[ax]} is periodic with length {L:g} m, less than two of "
                                     f"the largest particle diameters (2 x {d:g} m): a particle would touch "
                                     f"its own image or two images of a neighbour; enlarge the domain along "
                                     f"{'xyz'[ax]} or make it non-periodic")


def _check_walls(v, walls, x, ids, periodic, part=None, totals=None):
    """Walls that cannot be meant: an unbounded wall across a periodic axis, an unbounded
    plane with a particle centre behind it (its normal must point towards the particles),
    a cylinder with every particle on the wrong side of ``inside``. Under MPI (``part``:
    dem.parallel.setup.SetupComm, ``totals``: the scene's global rows) on this rank's rows:
    counts reduced, the first particle in scene order agreed."""
    if part is None:   # one process: every row is here
        grow, n_all = np.arange(len(x)), len(x)

        def count(c):
            return c

        def first(key, text):
            return None if key is None else text()
    else:
        count, first = part.sum, part.agree
        grow, n_all = totals["grow"], totals["n"]
    for k, w in enumerate(walls):
        p = f"walls[{k}]"
        if w["type"] == "mesh":   # _check_meshes
            continue
        if w["type"] == "plane":
            n = w["normal"]
            if w["extent"] is not None:
                continue
            cross = [a for a in range(3) if periodic[a] and abs(n[a]) > 1e-12]
            if cross:
                v.err(p + ".normal", f"an unbounded plane across the periodic axis {'xyz'[cross[0]]} "
                                     f"(normal {n.tolist()}): particles leaving through the periodic "
                                     f"boundary would meet the wall from behind; remove the wall, give it an "
                                     f"extent, or make axis {'xyz'[cross[0]]} non-periodic")
            s = (x - w["point"]) @ n
            front = int(count(int(np.count_nonzero(s >= 0))))
            if front == 0:
                v.err(p + ".normal", f"points away from every particle (normal {n.tolist()}, all {n_all} "
                                     f"particle centres lie behind the plane through {w['point'].tolist()}); "
                                     f"the normal of a plane points into the region of the particles: use "
                                     f"{(0.0 - n).tolist()}")
            behind = np.nonzero(s < 0)[0]
            q = int(behind[0]) if behind.size else None
            msg = first(None if q is None else int(grow[q]), lambda: (
                f"particle id {ids[q]} at {x[q].tolist()} lies behind the plane "
                f"(through {w['point'].tolist()}, normal {n.tolist()}); an unbounded "
                f"plane is one-sided: every particle centre must lie on the side its "
                f"normal points to"))
            if msg is not None:
                v.err(p + ".normal", msg)
        else:
            a = w["axis"]
            if math.isinf(w["length"]):
                cross = [b for b in range(3) if periodic[b] and np.linalg.norm(np.cross(a, np.eye(3)[b])) > 1e-9]
                if cross:
                    v.err(p + ".axis", f"an unbounded cylinder across the periodic axis {'xyz'[cross[0]]} "
                                       f"(axis {a.tolist()}); a cylinder may only run along periodic axes: "
                                       f"turn it, give it a length, or make axis {'xyz'[cross[0]]} non-periodic")
            rel = x - w["point"]
            s = rel @ a
            along = np.abs(s) <= w["length"] / 2
            rho = np.linalg.norm(rel[along] - s[along, None] * a, axis=1)
            c = count(np.array([along.sum(), np.count_nonzero(rho <= w["radius"]),
                                np.count_nonzero(rho >= w["radius"])], np.int64))
            if c[0] == 0:
                continue
            if w["inside"] and c[1] == 0:
                v.err(p + ".inside", f"every particle lies outside the cylinder (radius {w['radius']:g} m "
                                     f"about {w['point'].tolist()}, axis {a.tolist()}) but inside = true "
                                     "keeps particles inside it; set inside = false or check radius and point")
            if not w["inside"] and c[2] == 0:
                v.err(p + ".inside", f"every particle lies inside the cylinder (radius {w['radius']:g} m "
                                     f"about {w['point'].tolist()}, axis {a.tolist()}) but inside = false "
                                     "keeps particles outside it; set inside = true or check radius and point")


def _mesh_wall(v, wl, p, base_dir, lo, hi):
    """A [[walls]] type = "mesh": its surface file (STL, ASCII or binary, or a format meshio
    reads), placed by scale (a number or one per axis), rotate (degrees about x, y, z, in that
    order) and translate (m), checked triangle by triangle (dem.contact.mesh)."""
    from .contact.mesh import Surface, SLOTS
    fname = v.string(wl, "file", p, required=True)
    path = fname if os.path.isabs(fname) else os.path.join(base_dir, fname)
    sc = wl.get("scale", 1.0)
    if isinstance(sc, list):
        scale = v.vec(wl, "scale", p)
    else:
        scale = v.num(wl, "scale", p, default=1.0, lo=0, lo_open=True)
    if np.any(np.asarray(scale) <= 0):
        v.err(p + ".scale", f"must be > 0 (one number, or one per axis), got {np.asarray(scale).tolist()}")
    rotate = v.vec(wl, "rotate", p, default=np.zeros(3))
    translate = v.vec(wl, "translate", p, default=np.zeros(3))
    try:
        surf = Surface(path, p + ".file", scale, rotate, translate)
    except SceneError as e:
        v.err(p + ".file", f"{fname}: {e.message}")
    if np.any(surf.hi < lo) or np.any(surf.lo > hi):
        v.err(p + ".file", f"{fname}: the mesh (from {surf.lo.tolist()} to {surf.hi.tolist()} after scale, "
                           f"rotate and translate) does not reach the domain (from {np.asarray(lo).tolist()} to "
                           f"{np.asarray(hi).tolist()}); check scale (the file's units: mm from CAD is "
                           f"scale = 0.001) and translate")
    return dict(file=fname, path=path, scale=np.asarray(scale, float).tolist() if np.ndim(scale) else float(scale),
                rotate=rotate, translate=translate, surface=surf, slots=SLOTS, digest=surf.digest,
                point=0.5 * (surf.lo + surf.hi))


def _check_meshes(v, walls, x, r, ids, ratio, part=None, totals=None):
    """No particle may start overlapping a mesh wall by more than initial_overlap_ratio of its
    radius (the first in scene order named, with the triangle as numbered in the file). Under
    MPI on this rank's rows, the first over the ranks agreed (dem.parallel.setup.SetupComm)."""
    from .contact.mesh import nearest
    for k, w in enumerate(walls):
        if w["type"] != "mesh":
            continue
        s = w["surface"]
        d, tri = nearest(x, r, s.verts, s.faces, s.bins(float(2.0 * r.max(initial=1e-3))))
        bad = np.flatnonzero((r - d) > ratio * r)
        q = int(bad[0]) if bad.size else None
        key = None if q is None else (int(totals["grow"][q]) if part is not None else q)

        def text(q=q, w=w, d=d, tri=tri):
            return (f"{w['file']}: particle id {ids[q]} at {x[q].tolist()} (radius {r[q]:g} m) overlaps "
                    f"triangle {int(tri[q]) + 1} by {(r[q] - d[q]) / r[q]:.3g} of its radius initially "
                    f"(allowed: simulation.initial_overlap_ratio = {ratio}); move the particles or the mesh")
        msg = part.agree(key, text) if part is not None else (None if q is None else text())
        if msg is not None:
            v.err(f"walls[{k}].file", msg)


def _check_overlaps(v, sc):
    """Initial overlaps beyond [simulation] initial_overlap_ratio (of the smaller radius)."""
    from .insertion import max_overlap
    x, r = sc.position, sc.radius
    if x.shape[0] < 2:
        return
    per = np.asarray(sc.domain["periodic"], bool)
    box = np.where(per, np.asarray(sc.domain["max"], float) - np.asarray(sc.domain["min"], float), 0.0)
    ov, i, j = max_overlap(np.ascontiguousarray(x, float), np.ascontiguousarray(r, float), box)
    if ov > sc.simulation["initial_overlap_ratio"]:
        v.err(f"particles[{sc.group[i]}]",
              f"particles id {sc.id[i]} and id {sc.id[j]} overlap by {ov:.3g} of the smaller radius "
              f"initially (allowed: simulation.initial_overlap_ratio = {sc.simulation['initial_overlap_ratio']})")


def _thermal_hook(v, sc, data):
    """Parse [thermal] / [gas] when present (dem.thermal.scene)."""
    if "thermal" not in data and "gas" not in data:
        if any(t is not None for t in sc.temperature):
            pass
        return
    from .thermal.scene import parse_thermal
    sc.thermal = parse_thermal(v, sc, data)


# ---------------------------------------------------------------------------- set-up per rank (MPI)
# [parallel] insertion_block's default: groups of at most this many inserted particles keep the
# serial insertion and its random stream exactly (under MPI inserted on one rank each); larger
# ones are inserted by blocks (_insert_blocks), on any number of ranks the same particles
INSERTION_BLOCK = 131072


def _insert_part(v, p, part, reg, rad, rng, P, k_ins):
    """A ``count`` group under MPI: inserted on one rank (the k-th count group on rank k % N)
    with the serial algorithm and random stream (every rank advances the stream by the same
    draws), avoiding the earlier groups' particles near the region, which the other ranks send
    it (typed Gatherv). Returns (positions, radii, placed) of this rank's rows."""
    from .insertion import ATTEMPTS, insert
    n = rad.size
    root = k_ins % part.size
    ex_x = np.concatenate(P["x"]) if P["x"] else np.zeros((0, 3))
    ex_r = np.concatenate(P["r"]) if P["r"] else np.zeros(0)
    reach = float(rad.max()) + float(part.max(ex_r.max(initial=0.0)))
    blo, bhi = region_box(reg)
    near = part.gather_near(ex_x, ex_r, blo - reach, bhi + reach, root)
    if part.rank == root:
        part.largest_read = max(part.largest_read, near[1].size + n)
        pos, _, placed = insert(reg, rad, rng, near[0], near[1])
    else:   # the draws the inserting rank takes: one 64-bit output per uniform double
        rng.bit_generator.advance(n * ATTEMPTS * 3)
        pos, rad, placed = np.zeros((0, 3)), rad[:0], n
    placed = int(part.min(placed, np.int64))
    return pos, rad, placed


def _ids_and_domain_part(v, part, P, x, lo, hi, periodic):
    """Ids (as the serial set-up numbers them: per-group totals and offsets from typed
    reductions) and the inside-the-domain check (the first particle in scene order, agreed)."""
    G = len(P["x"])
    nloc = np.array([len(a) for a in P["x"]], np.int64)
    goff = part.exscan(nloc)                  # rows of each group on the lower ranks
    gtot = part.sum(nloc)
    gstart = np.concatenate([[0], np.cumsum(gtot)[:-1]]).astype(np.int64)
    # each row's index within its group: rank slices in rank order, or the blocks' own numbering
    gi = [P["gidx"][g] if P["gidx"][g] is not None else goff[g] + np.arange(nloc[g], dtype=np.int64)
          for g in range(G)]
    grow = np.concatenate([gstart[g] + gi[g] for g in range(G)])
    if any(i is not None for i in P["id"]):
        ids, nxt = [], 1
        for g in range(G):
            if P["id"][g] is not None:
                ids.append(P["id"][g].astype(np.int64))
                nxt = max(nxt, int(part.max(ids[-1].max(initial=-1), np.int64)) + 1)
            else:
                ids.append(nxt + gi[g])
                nxt = nxt + int(gtot[g])
        ids = np.concatenate(ids)
        if part.duplicates(ids, grow) is not None:
            v.err("particles", "particle ids are not unique across groups")
    else:
        ids = grow + 1
    group = np.concatenate(P["group"])
    return ids, group, dict(nloc=nloc, goff=goff, gtot=gtot, grow=grow, gi=gi, n=int(gtot.sum()))


def _check_inside_domain(v, P, x, ids, group, lo, hi, periodic, part=None, totals=None):
    """Every particle centre inside the domain (non-periodic axes; periodic ones are wrapped
    later): the first particle outside, in scene order (by axis, then row), named with its key
    and, from a file, its line or row. Under MPI (``part``, ``totals``: _ids_and_domain_part)
    on this rank's rows, the first over the ranks agreed."""
    nloc = np.array([len(a) for a in P["x"]], np.int64)
    if part is None:   # one process: every row is here, in scene order
        gi = [np.arange(m, dtype=np.int64) for m in nloc]
        grow = np.arange(len(x), dtype=np.int64)
    else:
        gi, grow = totals["gi"], totals["grow"]
    local_start = np.concatenate([[0], np.cumsum(nloc)[:-1]])
    best, text = None, None
    for ax in range(3):
        if periodic[ax]:
            continue
        out = np.nonzero((x[:, ax] < lo[ax]) | (x[:, ax] > hi[ax]))[0]
        if out.size:
            q = int(out[0])
            g = int(group[q])
            il = q - int(local_start[g])
            i = int(gi[g][il])   # index within its [[particles]] group
            key = {"positions": f"particles[{g}].positions[{i}]", "file": f"particles[{g}].file",
                   "count": f"particles[{g}].region"}[P["mode"][g]]
            in_file = f" ({P['where'][g](il)})" if P["mode"][g] == "file" else ""
            best = ax * (1 << 40) + int(grow[q])
            text = key + "\n" + (f"particle id {ids[q]}{in_file} at "
                                 f"{x[q].tolist()} lies outside the domain [{lo.tolist()}, {hi.tolist()}] on axis "
                                 f"{'xyz'[ax]}; particle centres must lie within domain.min .. domain.max")
            break
    msg = text if part is None else part.agree(best, text)
    if msg is not None:
        v.err(*msg.split("\n", 1))


def _scene_part(sc, part, totals, P):
    """The run's totals of a scene set up per rank: particles, the materials used (a typed
    reduction), the largest speed (the characteristic velocity), what this rank read and held."""
    sc.distributed = True
    sc.n_total = totals["n"]
    used = np.zeros(len(sc.materials), np.int64)
    used[np.unique(sc.material)] = 1
    sc.materials_used = np.nonzero(part.sum(used))[0].tolist()
    sc.max_speed = float(part.max(float(np.max(np.linalg.norm(sc.velocity, axis=1), initial=0.0))))
    sc.n_rank = -(-sc.n_total // part.size)
    sc.setup_rows = dict(read=int(part.rows_read),
                         held=max(int(sc.radius.size), int(part.largest_read)))
    sc.group_totals = totals["gtot"].tolist()
    G = len(P["r"])
    gmax = np.array([float(a.max(initial=0.0)) for a in P["r"]] + [-float(sc.radius.min(initial=np.inf))])
    gmax = part.max(gmax) if G else gmax
    sc.group_rmax, sc.rmin = gmax[:G].tolist(), -float(gmax[G])


def _block_boxes(lo, hi, nb):
    """At least ``nb`` equal blocks of the box [lo, hi]: the longest block edge halved until
    there are enough (ties: the lower axis); fixed by the region and the count alone."""
    g = np.ones(3, np.int64)
    while int(g.prod()) < nb:
        g[int(np.argmax((hi - lo) / g))] *= 2
    edges = []
    for a in range(3):
        e = lo[a] + (hi[a] - lo[a]) * np.arange(g[a] + 1) / g[a]
        e[-1] = hi[a]
        edges.append(e)
    idx = np.stack(np.meshgrid(*[np.arange(m) for m in g], indexing="ij"), -1).reshape(-1, 3)
    blo = np.stack([edges[a][idx[:, a]] for a in range(3)], 1)
    bhi = np.stack([edges[a][idx[:, a] + 1] for a in range(3)], 1)
    return blo, bhi


def _insert_blocks(part, reg, spec, cg, n, block, seed, k, P):
    """A ``count`` group larger than ``block`` (parallel.insertion_block): the region box cut
    into fixed blocks of at most about ``block`` particles (:func:`_block_boxes`), the count
    shared by volume (largest remainder), each block filled by the serial algorithm with its
    own random stream default_rng([seed, group, block]) and every sphere kept inside its block
    (thin empty seams between blocks: no two blocks' spheres can touch), the earlier groups'
    particles near the block avoided. Block b is filled on rank b mod N (serial: all), so the
    particles (ids, positions, radii) are the same on any number of ranks.
    Returns (positions, radii, index within the group, placed over all ranks)."""
    from .insertion import insert, sample_radii
    lo, hi = np.asarray(reg["min"], float), np.asarray(reg["max"], float)
    blo, bhi = _block_boxes(lo, hi, -(-n // block))
    vol = np.prod(bhi - blo, axis=1)
    q = n * vol / vol.sum()
    cnt = np.floor(q).astype(np.int64)
    cnt[np.argsort(-(q - cnt), kind="stable")[:n - int(cnt.sum())]] += 1
    start = np.concatenate([[0], np.cumsum(cnt)[:-1]])
    ex_x = np.concatenate(P["x"]) if P["x"] else np.zeros((0, 3))
    ex_r = np.concatenate(P["r"]) if P["r"] else np.zeros(0)
    rex = float(ex_r.max(initial=0.0))
    if part is not None:
        rex = float(part.max(rex))
    rmax = float(spec["value"] if spec["distribution"] == "constant" else spec["max"]) * cg
    size, rank = (1, 0) if part is None else (part.size, part.rank)
    pos, rad, idx, placed = [np.zeros((0, 3))], [np.zeros(0)], [np.zeros(0, np.int64)], 0
    for b in range(blo.shape[0]):
        owner = b % size
        a, z = blo[b] - (rmax + rex), bhi[b] + (rmax + rex)
        if part is None:
            inside = np.all((ex_x >= a) & (ex_x <= z), axis=1)
            near = (ex_x[inside], ex_r[inside])
        else:
            near = part.gather_near(ex_x, ex_r, a, z, owner)
        if rank != owner or cnt[b] == 0:
            continue
        rng = np.random.default_rng([seed, k, b])
        rb = sample_radii(spec, int(cnt[b]), rng) * cg
        xb, _, pl = insert(dict(type="box", min=blo[b], max=bhi[b]), rb, rng, near[0], near[1])
        if part is not None:
            part.largest_read = max(part.largest_read, near[1].size + int(cnt[b]))
        placed += pl
        pos.append(xb[:pl] if pl < cnt[b] else xb)
        rad.append(rb[:pl] if pl < cnt[b] else rb)
        idx.append(start[b] + np.arange(min(pl, cnt[b]), dtype=np.int64))
    if part is not None:
        placed = int(part.sum(placed))
    return np.concatenate(pos), np.concatenate(rad), np.concatenate(idx), placed
