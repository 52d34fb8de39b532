"""Particles that enter and leave a run: ``[[inlets]]`` and ``[[outlets]]``.

    [[inlets]]                       # particles created during the run
    name = "feed"
    material = "bead"
    radius = { distribution = "uniform", min = 0.0009, max = 0.0011 }   # or a number
    mass_rate = 0.02                 # kg/s (or rate = particles per second)
    region = { type = "cylinder", center = [0, 0, 0.07], axis = [0, 0, 1], radius = 0.015, length = 0.01 }
    velocity = [0.0, 0.0, -0.5]      # m/s (default 0)
    temperature = 300.0              # K (default thermal.initial_temperature)
    interval = 0.01                  # s between insertions (default: the time to leave the region)
    start = 0.0                      # s; stop = end of the insertions (default: never)

    [[outlets]]                      # particles removed during the run
    name = "orifice"
    type = "plane"                   # plane (point, normal: removed on the side the normal points to),
                                     # box (min, max) or cylinder (center, axis, radius, length): removed
                                     # inside; face = "zmin" ...: removed beyond that face of [domain]
    point = [0, 0, 0.0]
    normal = [0, 0, -1]
    interval = 0.0005                # s between checks (default 50 time steps)

An insertion or a removal is an *event* at a multiple of its interval (in steps), between two
compiled chunks of the run (dem.operations, ``FlowEvents``): outlets first, then inlets. Each
inlet's batch is a pure function of (simulation.seed, inlet, step): the radii from the size
distribution and the places by random sequential insertion in the region (dem.insertion, the
batch's spheres never overlapping each other), generated alike on every rank; each place is
kept by the rank that owns it (dem.parallel.decomposition) if it overlaps no particle there (owned
or ghost) and no wall. A candidate's id is the run's next id plus its number in the batch: ids are
never reused, and are the same on any number of ranks. What a batch could not place is owed to
the next one (the mean rate holds while the region empties fast enough); when the debt exceeds a
batch the run says so once, with what fits. After a change the neighbour lists are built again
and the contact history kept by id (dem.parallel.records), as after a migration.

The run totals (dem.schema ``flow``: number, mass and enthalpy m c T in and out per inlet and
outlet, summed over the ranks) go to history.csv and checkpoints; with heat the energy ledger is

    thermal_energy(t) - thermal_energy(0) = sum of E_<mechanism> + H_in - H_out.
"""
import math

import numpy as np
from numba import njit

from . import schema as S
from .contact.walls import WI, MESH, wall_distance
from .state import sphere_masses
from .regions import check_region_in_domain, radius_spec, region, region_box, region_volume, spec_bounds

FACES = {"xmin": (0, 0), "xmax": (0, 1), "ymin": (1, 0), "ymax": (1, 1), "zmin": (2, 0), "zmax": (2, 1)}
INLET_KEYS = {"name", "material", "radius", "rate", "mass_rate", "region", "velocity", "temperature", "interval",
              "start", "stop"}
OUTLET_KEYS = {"name", "type", "point", "normal", "min", "max", "center", "axis", "radius", "length", "face",
               "interval"}
# the largest solid fraction of one batch in its region: random sequential insertion of equal
# spheres jams at about 0.38 (Widom 1966; Talbot et al. 2000); at a quarter 200 random attempts
# per sphere place every one (dem.insertion.ATTEMPTS)
FILL_LIMIT = 0.25
OUTLET_STEPS = 50          # default steps between two outlet checks
FLOW_TAG = 7919            # the random streams of the inlets: default_rng([seed, FLOW_TAG, inlet, step])
COLUMNS = ("number", "mass", "enthalpy")


# ------------------------------------------------------------------------------------ parsing
def parse(v, data, sim, lo, hi, periodic, mat_ref, materials, groups):
    """The [[inlets]] and [[outlets]] of a scene (``v``: dem.scene._V); (inlets, outlets) as
    checked dicts. ``groups``: the number of [[particles]] groups (an inlet's particles get
    group groups + its index)."""
    inlets, outlets, names = [], [], {}
    for key in ("inlets", "outlets"):
        if not isinstance(data.get(key, []), list):
            v.err(key, f"must be an array of tables [[{key}]]")
    dt = sim["time_step"]
    for k, d in enumerate(data.get("inlets", [])):
        p = f"inlets[{k}]"
        v.table(d, p, INLET_KEYS, required=("material", "radius", "region"))
        name = _name(v, d, p, f"inlet{k}", names)
        spec = radius_spec(v, d, p)
        reg = region(v, d, p)
        check_region_in_domain(v, p, reg, spec, lo, hi, periodic)
        rates = [r for r in ("rate", "mass_rate") if r in d]
        if len(rates) != 1:
            v.err(p, "give exactly one of 'rate' (particles per second) or 'mass_rate' (kg/s)"
                  + (f"; got {', '.join(rates)}" if rates else ""))
        mat = mat_ref(d, p)
        rate = v.num(d, rates[0], p, lo=0, lo_open=True)
        vel = v.vec(d, "velocity", p, default=np.zeros(3))
        vol = region_volume(reg)
        interval = _default_interval(reg, vel, sim["gravity"])
        if "interval" in d or interval is None:   # (None: neither the velocity nor gravity moves it)
            interval = v.num(d, "interval", p, lo=dt, required=True)
        rmin, rmax = spec_bounds(spec)
        vmean = mean_volume(spec)
        rho = materials[mat]["density"]
        unit_of_rate = 1.0 if rates[0] == "rate" else rho * vmean   # a particle in the rate's unit
        per = rate * interval / unit_of_rate   # particles per insertion
        if per * vmean > FILL_LIMIT * vol:
            most = FILL_LIMIT * vol / vmean / interval * unit_of_rate
            unit = "particles/s" if rates[0] == "rate" else "kg/s"
            v.err(f"{p}.{rates[0]}", f"{rate:g} {unit} at one insertion every {interval:g} s is {per:.4g} particles "
                                     f"a batch, {per * vmean / vol:.3g} of the region's {vol:.3g} m3; random "
                                     f"insertion places at most {FILL_LIMIT} of it: at most {most:.4g} {unit} fit. "
                                     "Enlarge the region, shorten inlets.interval or lower the rate")
        start = v.num(d, "start", p, default=0.0, lo=0.0)
        stop = v.num(d, "stop", p, default=math.inf, lo=start)
        inlets.append(dict(name=name, material=mat, radius=spec, rmin=rmin, rmax=rmax, kind=rates[0], rate=rate,
                           region=reg, velocity=vel, interval=interval, steps=max(1, int(round(interval / dt))),
                           start=start, stop=stop, group=groups + k,
                           temperature=v.num(d, "temperature", p, default=None, lo=0, lo_open=True)))
    for k, d in enumerate(data.get("outlets", [])):
        p = f"outlets[{k}]"
        v.table(d, p, OUTLET_KEYS, required=("type",))
        name = _name(v, d, p, f"outlet{k}", names)
        kind = v.string(d, "type", p, choices=["plane", "box", "cylinder", "face"], required=True)
        o = dict(name=name, type=kind)
        shape = {"plane": {"point", "normal"}, "box": {"min", "max"}, "face": {"face"},
                 "cylinder": {"center", "axis", "radius", "length"}}[kind]
        v.table(d, p, shape | {"name", "type", "interval"}, required=tuple(sorted(shape)))
        if kind == "plane":
            o.update(point=v.vec(d, "point", p, required=True), normal=v.unit(d, "normal", p))
        elif kind == "face":
            face = v.string(d, "face", p, choices=list(FACES), required=True)
            axis, side = FACES[face]
            if periodic[axis]:
                v.err(p + ".face", f"face {face} lies on the periodic axis {'xyz'[axis]}: particles cross it into "
                                   "the other side; make the axis non-periodic or use a plane outlet")
            o.update(face=face, axis=axis, side=side)
        else:
            o["region"] = _outlet_region(v, d, p, kind)
        steps = OUTLET_STEPS
        if "interval" in d:
            steps = max(1, int(round(v.num(d, "interval", p, lo=dt) / dt)))
        o.update(interval=steps * dt, steps=steps)
        outlets.append(o)
    return inlets, outlets


def _name(v, d, p, default, names):
    name = v.string(d, "name", p, default=default)
    if name in names:
        v.err(p + ".name", f"duplicate name {name!r} (already {names[name]}); inlet and outlet names must be unique")
    names[name] = p
    return name


def _outlet_region(v, d, p, kind):
    keys = ("min", "max") if kind == "box" else ("center", "axis", "radius", "length")
    reg = {"type": kind, **{k: d[k] for k in keys if k in d}}
    return region(v, {"region": reg}, p)


def _default_interval(reg, vel, gravity):
    """The time a particle takes to leave the region: along the inlet velocity at its speed,
    else falling from rest through the region's height along gravity; None when neither moves it."""
    lo, hi = region_box(reg)
    speed = float(np.linalg.norm(vel))
    gn = float(np.linalg.norm(gravity))
    if speed > 0.0:
        u = vel / speed
        return float(np.abs(u) @ (hi - lo)) / speed
    if gn > 0.0:
        u = np.asarray(gravity, float) / gn
        return math.sqrt(2.0 * float(np.abs(u) @ (hi - lo)) / gn)
    return None


def mean_volume(spec):
    """Mean sphere volume of a radius distribution (exact for constant and uniform; by 4096
    draws of a fixed stream for the truncated normal and lognormal)."""
    from .insertion import sample_radii
    if spec["distribution"] == "constant":
        return 4.0 / 3.0 * math.pi * float(spec["value"]) ** 3
    if spec["distribution"] == "uniform":
        a, b = float(spec["min"]), float(spec["max"])
        return 4.0 / 3.0 * math.pi * (b ** 4 - a ** 4) / (4.0 * (b - a)) if b > a else 4.0 / 3.0 * math.pi * a ** 3
    r = sample_radii(spec, 4096, np.random.default_rng(0))
    return float(np.mean(4.0 / 3.0 * math.pi * r ** 3))


def open_faces(outlets):
    """The bitmask of dem.step IP.openfaces: bit 2 axis + side for each face outlet."""
    m = 0
    for o in outlets:
        if o["type"] == "face":
            m |= 1 << (2 * o["axis"] + o["side"])
    return m


def inside(o, x, lo, hi):
    """Which points x (n, 3) outlet ``o`` removes."""
    if o["type"] == "plane":
        return (x - o["point"]) @ o["normal"] > 0.0
    if o["type"] == "face":
        a = o["axis"]
        return x[:, a] > hi[a] if o["side"] else x[:, a] < lo[a]
    reg = o["region"]
    if reg["type"] == "box":
        return np.all((x >= np.asarray(reg["min"], float)) & (x <= np.asarray(reg["max"], float)), axis=1)
    c = np.asarray(reg["center"], float)
    ax = np.asarray(reg["axis"], float) / np.linalg.norm(reg["axis"])
    rel = x - c
    s = rel @ ax
    rho2 = np.einsum("ij,ij->i", rel, rel) - s * s
    return (np.abs(s) <= 0.5 * float(reg["length"])) & (rho2 <= float(reg["radius"]) ** 2)


# ------------------------------------------------------------------------------------ run time
@njit(cache=True, error_model="numpy")
def clashes(cx, cr, ex, er):
    """Which candidates (cx, cr) overlap any sphere (ex, er): the spheres near the candidates'
    box were selected by the caller; a plain double loop over them."""
    out = np.zeros(cx.shape[0], np.bool_)
    for a in range(cx.shape[0]):
        for b in range(ex.shape[0]):
            d0 = cx[a, 0] - ex[b, 0]
            d1 = cx[a, 1] - ex[b, 1]
            d2 = cx[a, 2] - ex[b, 2]
            rr = cr[a] + er[b]
            if d0 * d0 + d1 * d1 + d2 * d2 < rr * rr:
                out[a] = True
                break
    return out


@njit(cache=True, error_model="numpy")
def plane_wall_clashes(cx, cr, wf, wi, nwalls, t):
    """Which candidates touch a plane or cylinder wall row (mesh rows: :func:`mesh_clashes`)."""
    out = np.zeros(cx.shape[0], np.bool_)
    for a in range(cx.shape[0]):
        for w in range(nwalls):
            if wi[w, WI.type] == MESH:
                continue
            d = wall_distance(wf, wi, w, cx[a, 0], cx[a, 1], cx[a, 2], t)[0]
            if d < cr[a]:
                out[a] = True
                break
    return out


def mesh_clashes(walls, cx, cr, t):
    """Which candidates touch a triangle-mesh wall where it is at time t."""
    from .contact.mesh import mesh_frame_points, nearest
    out = np.zeros(cx.shape[0], bool)
    for w in walls:
        if w["type"] != "mesh" or not cx.shape[0]:
            continue
        s = w["surface"]
        d, _ = nearest(mesh_frame_points(w, cx, t), cr, s.verts, s.faces, s.bins(float(2.0 * cr.max())))
        out |= d < cr
    return out


class Flow:
    """The inlets and outlets of a run (``world``: dem.world.World): the events, the new rows,
    the totals (state ``flow``) and the run's next id."""

    def __init__(self, world):
        sc = world.scene
        self.world = world
        self.inlets, self.outlets = sc.inlets, sc.outlets
        st = world.state
        st.enable(flow=True)
        st.flow = np.zeros((len(self.inlets) + len(self.outlets), len(COLUMNS)))
        self.owed = np.zeros(len(self.inlets))   # particles (rate) or kg (mass_rate) a batch could not place
        self.warned = np.zeros(len(self.inlets), bool)
        self.next_id = int(sc.next_id)
        self.seed = int(sc.simulation["seed"])
        self.changes = 0   # events that changed the particles (their rows: a coupled run's cell hints go)

    # -------------------------------------------------------------------- schedule
    def steps(self):
        """The step intervals of the events (one per inlet and outlet)."""
        return [d["steps"] for d in self.outlets + self.inlets]

    def next_due(self, step):
        """The first step after ``step`` at which an inlet or outlet acts (a coupled run advances
        its DEM interval in pieces between them: coupling.interface.advance_dem)."""
        return min((step // n + 1) * n for n in self.steps())

    def advance(self, sim, nsteps):
        """``nsteps`` steps of ``sim`` (dem.Simulation) with the events on the way: in pieces up to
        each, which then acts (what a run's FlowEvents operation does, for callers that step the
        simulation themselves: a coupled run's DEM interval, coupling.interface.advance_dem)."""
        end = sim.step_count + nsteps
        while sim.step_count < end:
            sim.step(min(self.next_due(sim.step_count), end) - sim.step_count)
            self.apply(sim.stepper, sim.step_count)

    def due(self, step):
        outs = [o for o in self.outlets if step % o["steps"] == 0]
        t = step * self.world.dt
        ins = [(k, i) for k, i in enumerate(self.inlets)
               if step % i["steps"] == 0 and i["start"] <= t + 1e-12 and t < i["stop"] and step > 0]
        return outs, ins

    # -------------------------------------------------------------------- an event
    def apply(self, stepper, step):
        """The due outlets, then the due inlets, at step number ``step`` (every rank: one sum over
        the ranks of what each removed and placed); the neighbour lists are built again when any
        rank changed. Returns (removed, inserted) over the ranks."""
        outs, ins = self.due(step)
        if not outs and not ins:
            return 0, 0
        w = self.world
        st = w.state
        par = stepper.par
        n = st.n_owned
        x = st.position[:n]
        gone = np.zeros(n, bool)
        for o in outs:
            hit = np.nonzero(inside(o, x, st.lo, st.hi) & ~gone)[0]
            self._tally(len(self.inlets) + self.outlets.index(o), st.mass[hit],
                        st.temperature[hit] if st.thermal else None, st.inv_heat_capacity[hit] if st.thermal else None)
            gone[hit] = True
        batches = [(k, inlet, self._batch(k, inlet, step, par)) for k, inlet in ins]
        new = self.rows(batches)
        local = [float(gone.sum())]
        for k, inlet, b in batches:
            local += [float(b["id"].size), float(b["masses"][0].sum())]
        tot = np.array(local) if par is None else np.asarray(par.allsum(np.array(local)), float)
        for q, (k, inlet, b) in enumerate(batches):
            got = tot[1 + 2 * q] if inlet["kind"] == "rate" else tot[2 + 2 * q]
            self._settle(k, inlet, b, got, int(tot[1 + 2 * q]), par)
        added = int(round(sum(tot[1 + 2 * q] for q in range(len(batches)))))
        if tot[0] == 0 and added == 0:
            return 0, 0
        stepper.change_particles(~gone, new)
        self.changes += 1
        w.n_total += added - int(tot[0])
        return int(tot[0]), added

    def _tally(self, row, mass, T, inv_c):
        """Add particles (this rank's: their masses, and with heat their temperatures and
        1 / (m c)) to row ``row`` of the totals: number, mass, enthalpy m c T."""
        f = self.world.state.flow[row]
        f[0] += mass.size
        f[1] += float(mass.sum())
        if T is not None:
            f[2] += float(np.sum(T / inv_c))

    def _batch(self, k, inlet, step, par):
        """This rank's new particles of inlet k at step ``step``: id, position, radius, and what the
        batch asked for (``want``: particles or kg, the debt included) and generated (``made``)."""
        from .insertion import insert, sample_radii
        w = self.world
        st = w.state
        rng = np.random.default_rng([self.seed, FLOW_TAG, k, step])
        rho = w.scene.materials[inlet["material"]]["density"]
        want = inlet["rate"] * inlet["interval"] + self.owed[k]
        if inlet["kind"] == "rate":
            radii = sample_radii(inlet["radius"], int(math.floor(want + 1e-9)), rng)
        else:   # draws until the next would pass the mass asked for
            guess = max(8, int(2 * want / (rho * mean_volume(inlet["radius"]))) + 8)
            radii = sample_radii(inlet["radius"], guess, rng)
            m = np.cumsum(sphere_masses(radii, rho)[0])
            radii = radii[:int(np.searchsorted(m, want * (1.0 + 1e-12), side="right"))]
        x, keep, _ = insert(inlet["region"], radii, rng, np.zeros((0, 3)), np.zeros(0))
        ids = self.next_id + np.arange(radii.size, dtype=np.int64)
        self.next_id += radii.size
        ok = keep.copy()
        if par is not None:
            ok &= par.dec.owner(x) == par.rank
        cand = np.nonzero(ok)[0]
        if cand.size:
            t = w.time
            cx, cr = np.ascontiguousarray(x[cand]), np.ascontiguousarray(radii[cand])
            lo, hi = cx.min(0) - 2 * w.rmax, cx.max(0) + 2 * w.rmax
            xa = st.position[:st.n]
            near = np.nonzero(np.all((xa >= lo) & (xa <= hi), axis=1))[0]
            bad = clashes(cx, cr, np.ascontiguousarray(xa[near]), np.ascontiguousarray(st.radius[near]))
            bad |= plane_wall_clashes(cx, cr, st.wf, st.wi, w.nwalls, t)
            bad |= mesh_clashes(w.scene.walls, cx, cr, t)
            ok[cand[bad]] = False
        sel = np.nonzero(ok)[0]
        r = radii[sel]
        return dict(id=ids[sel], position=np.ascontiguousarray(x[sel]), radius=r, want=want, made=int(keep.sum()),
                    masses=sphere_masses(r, rho))

    def _settle(self, k, inlet, b, got, placed, par):
        """The debt of inlet k after a batch that placed ``got`` (particles or kg) over the ranks."""
        self.owed[k] = b["want"] - got
        per = inlet["rate"] * inlet["interval"]
        if self.owed[k] > per * (1.0 + 1e-9) and not self.warned[k]:
            self.warned[k] = True
            if par is None or par.rank == 0:
                unit = "particles" if inlet["kind"] == "rate" else "kg"
                print(f"warning: inlet {inlet['name']} at t = {self.world.time:.6g} s: {self.owed[k]:.4g} {unit} "
                      f"could not be placed yet ({placed} of {b['made']} placed in this batch: the region is not "
                      f"clear of what is there); the rest is owed to the next insertions. A lower rate, a larger "
                      f"region or a faster inlet velocity fits", flush=True)

    def temperature(self, inlet):
        th = self.world.scene.thermal
        return inlet["temperature"] if inlet["temperature"] is not None else th["initial_temperature"]

    # -------------------------------------------------------------------- new rows
    def rows(self, batches):
        """The per-particle arrays (every enabled one of dem.schema) of the new particles of
        ``batches`` ((k, inlet, batch) of :meth:`apply`), concatenated; their number, mass and
        enthalpy added to the inlets' totals."""
        from .step import FP
        w = self.world
        st = w.state
        declared = [f for f in S.of("particle") if S.enabled(f, st.features)]
        parts = {f.name: [getattr(st, f.name)[:0]] for f in declared}
        for k, inlet, b in batches:
            m = b["id"].size
            arr = {f.name: np.zeros((m,) + getattr(st, f.name).shape[1:], f.dtype) for f in declared}
            mass, inv_mass, inv_inertia = b["masses"]
            arr.update(id=b["id"], position=b["position"], radius=b["radius"], mass=mass, inv_mass=inv_mass,
                       inv_inertia=inv_inertia, x_build=b["position"].copy())
            arr["velocity"][:] = inlet["velocity"]
            arr["material"][:] = inlet["material"]
            arr["group"][:] = inlet["group"]
            arr["force"][:] = mass[:, None] * st.fp[FP.gx:FP.gz + 1]   # no contact: gravity alone
            if "mcon" in arr and m:
                arr["mcon"][:, :, 0] = math.inf
            if st.thermal:
                th = w.thermal
                from .thermal import registry as R
                arr["temperature"][:] = self.temperature(inlet)
                arr["inv_heat_capacity"][:] = 1.0 / (mass * th.tmat[inlet["material"], R.CP])
                arr["por"][:], arr["tf"][:], arr["uf"][:] = th.gas_at_start()
                if st.features.get("fluid"):   # a coupled run: the gas at the particle is known from the
                    # next interval on (coupling.interface); until then no exchange (the gas's sources
                    # of this interval do not hold it either)
                    arr["tf"][:] = arr["temperature"]
                    arr["uf"][:] = arr["velocity"]
            self._tally(k, mass, arr["temperature"] if st.thermal else None,
                        arr["inv_heat_capacity"] if st.thermal else None)
            for name, a in arr.items():
                parts[name].append(a)
        return {name: np.concatenate(v) for name, v in parts.items()}

    # -------------------------------------------------------------------- output and restart
    def history_columns(self):
        cols = ["particles", "mass"]
        for d in self.inlets:
            cols += [f"n_in_{d['name']}", f"mass_in_{d['name']}"]
        for d in self.outlets:
            cols += [f"n_out_{d['name']}", f"mass_out_{d['name']}"]
        if self.world.thermal is not None:
            cols += ["H_in", "H_out"]
        return cols

    def history_values(self):
        """This rank's part of the history columns (summed over the ranks by the caller)."""
        st = self.world.state
        n = st.n_owned
        vals = [float(n), float(st.mass[:n].sum())]
        for row in st.flow:
            vals += [float(row[0]), float(row[1])]
        if self.world.thermal is not None:
            ni = len(self.inlets)
            vals += [float(st.flow[:ni, 2].sum()), float(st.flow[ni:, 2].sum())]
        return vals

    def record(self):
        """What a checkpoint's scene record says of the flow (a restart keeps the names)."""
        return dict(inlets=[d["name"] for d in self.inlets], outlets=[d["name"] for d in self.outlets])

    def saved(self):
        """The scalars a checkpoint holds (the same on every rank)."""
        return dict(flow_next_id=np.int64(self.next_id), flow_owed=np.asarray(self.owed, float),
                    flow_warned=np.asarray(self.warned, bool))

    def load(self, z):
        self.next_id = int(z["flow_next_id"])
        self.owed[:] = z["flow_owed"]
        self.warned[:] = z["flow_warned"]


