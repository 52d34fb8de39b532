"""Checks and reports of a simulation before it runs: `dem check`'s derived quantities, the
time-step verdict, which models run and which are skipped, the time scales and the memory
estimate. Functions of the world and the stepper; nothing here changes the run.
"""
import math


from . import scene as scene_mod
from . import schema as S
from . import step as K
from .contact.damping import rayleigh_time, hertz_collision_time
from .errors import SceneError
from .neighbors import grid_bytes, raw_rows_bytes
from .parcels import parcel_factors

# a periodic length below this many parcel diameters orders a coarse-grained packing through its
# periodic images (docs/notebook.md, "Coarse graining": over 3 to 6 parcel diameters the
# coordination number of poured parcel beds was 6 to 15 % above the fine bed's, at 12 within 2 %)
PARCEL_PERIOD_DIAMETERS = 10.0


def check(world, stepper):
    """Derived quantities and the time-step verdict; raises SceneError when the step is
    above the documented fraction and the scene does not say force = true."""
    sc = world.scene
    st = world.state
    dt = world.dt
    par = stepper.par
    n = st.n_owned
    rep = {"particles": world.n_total, "walls": len(sc.walls), "materials": len(sc.materials)}
    m, r = st.mass[:n], st.radius[:n]
    rep["mass_total"] = _over_ranks(par, "sum", float(m.sum()))
    rep["mass_min"] = _over_ranks(par, "min", float(m.min(initial=math.inf)))
    rep["mass_max"] = _over_ranks(par, "max", float(m.max(initial=-math.inf)))
    rep["radius_min"] = _over_ranks(par, "min", float(r.min(initial=math.inf)))
    rep["radius_max"] = _over_ranks(par, "max", float(r.max(initial=-math.inf)))
    tr, th, ovmax = time_scales(world, par)
    vchar = st.fp[K.FP.vchar]
    rep["impact_overlap_ratio"] = ovmax
    rep["rayleigh_time"] = tr
    rep["hertz_time"] = th
    rep["characteristic_velocity"] = vchar
    rep["dt"] = dt
    rep["dt_over_rayleigh"] = dt / tr
    rep["dt_over_hertz"] = dt / th
    rep["mechanics"] = bool(sc.simulation["mechanics"])
    rep["steps"] = int(round(world.end_time / dt))
    mem, rep["memory_neighbor_build_bytes"] = memory_estimate(world, stepper.par)
    rep["memory_bytes"] = int(mem)
    rep["memory_per_particle"] = mem / max(st.n, 1)
    rep["runs"], rep["skipped"] = models_report(world, stepper.par)
    warnings = []
    if sc.simulation["mechanics"] and ovmax > st.fp[K.FP.maxov]:
        warnings.append(f"a Hertz impact at the characteristic velocity {vchar:.3g} m/s overlaps "
                        f"{ovmax:.3g} of the radius, above simulation.max_overlap_ratio = "
                        f"{st.fp[K.FP.maxov]:g}: the overlap guard may stop the run (raise "
                        f"youngs_modulus, or the bound if such overlaps are acceptable)")
    warnings += parcel_period_warnings(sc)
    if world.thermal is not None:
        rep.update(world.thermal.check(dt, stepper.compute_forces))
    rep["warnings"] = warnings + rep.get("warnings", [])
    problems = []
    if sc.simulation["mechanics"]:
        if dt > scene_mod.RAYLEIGH_FRACTION * tr:
            problems.append(f"time_step {dt:g} s is {dt / tr:.3g} of the Rayleigh time {tr:.3g} s "
                            f"(allowed: {scene_mod.RAYLEIGH_FRACTION})")
        if dt > scene_mod.HERTZ_FRACTION * th:
            problems.append(f"time_step {dt:g} s is {dt / th:.3g} of the Hertz collision time {th:.3g} s "
                            f"at {vchar:.3g} m/s (allowed: {scene_mod.HERTZ_FRACTION})")
    rep["problems"] = problems
    if problems and not sc.simulation["force"]:
        raise SceneError(sc.file, "simulation.time_step",
                         "; ".join(problems) + ". Lower time_step, or set simulation.force = true to run anyway")
    return rep


def models_report(world, par):
    """(what runs, what is skipped and why): one line each."""
    from .energy_guard import inputs_of
    sc = world.scene
    runs = [f"contact: {sc.contact['model']} (damping {sc.contact['damping']}, tangential {sc.contact['tangential']})"]
    skipped = []
    if sc.contact["rolling"] != "none":
        runs.append(f"rolling resistance: {sc.contact['rolling']}")
    else:
        skipped.append("rolling resistance: [contact] rolling = 'none'")
    if world.nwalls:
        nm = sum(w["type"] == "mesh" for w in world.scene.walls)
        runs.append(f"walls: {len(world.scene.walls)}" + (f" ({nm} triangle mesh{'es' if nm > 1 else ''}, "
                    f"{sum(w['surface'].n_triangles for w in world.scene.walls if w['type'] == 'mesh')} "
                    f"triangles)" if nm else ""))
    else:
        skipped.append("walls: none in the scene")
    for d in sc.inlets:
        unit = "particles/s" if d["kind"] == "rate" else "kg/s"
        runs.append(f"inlet {d['name']}: {d['rate']:g} {unit}, a batch every {d['interval']:.4g} s "
                    f"({d['steps']} steps) in a {d['region']['type']} region, from t = {d['start']:g} s")
    for d in sc.outlets:
        where = {"face": lambda: f"beyond the domain face {d.get('face')}",
                 "plane": lambda: f"beyond the plane through {list(map(float, d['point']))} "
                                  f"(normal {list(map(float, d['normal']))})"}.get(
            d["type"], lambda: f"inside a {d['type']} region")()
        runs.append(f"outlet {d['name']}: particles {where} removed every {d['steps']} steps")
    if not sc.simulation["mechanics"]:
        runs[0] = "mechanics frozen (simulation.mechanics = false): contacts computed once"
    if par is not None:
        runs.append(f"parallel: {par.describe()}, ghosts within {world.halo():.4g} m, "
                    f"re-balanced above {sc.parallel['balance_threshold']:g}")
    else:
        skipped.append("parallel decomposition: one process (mpirun -np N dem run ... splits the domain)")
    why = inputs_of(world)
    if why:
        skipped.append(f"energy guard: {', '.join(why)} (energy enters the system)")
    else:
        runs.append("energy guard: the mechanical energy of this closed system may not grow")
    if world.thermal is None:
        skipped.append("heat transfer: no [thermal] section (no thermal arrays, no thermal cost)")
    else:
        r, s = world.thermal.models_report()
        runs += r
        skipped += s
    return runs, skipped


def _over_ranks(par, op, x):
    """x (a number) over every rank (``par``: dem.parallel.domain.ParallelDomain, None: one process)."""
    if par is None:
        return x
    return {"sum": par.allsum, "min": par.allmin, "max": par.allmax}[op](x)


def time_scales(world, par=None):
    """(Rayleigh time, Hertz collision time at the characteristic velocity, largest Hertz
    impact overlap / radius) of the smallest particle of each material (and its walls), over
    every rank's particles (``par``)."""
    sc = world.scene
    st = world.state
    vchar = st.fp[K.FP.vchar]
    tr, th = math.inf, math.inf
    ovmax = 0.0
    n = st.n_owned
    for k, m in enumerate(sc.materials):
        sel = st.material[:n] == k
        rmin = _over_ranks(par, "min", float(st.radius[:n][sel].min(initial=math.inf)))
        rmin = min([rmin] + [i["rmin"] for i in sc.inlets if i["material"] == k])   # what the inlets bring
        if rmin == math.inf:   # no particle of this material
            continue
        G = m["youngs_modulus"] / (2 * (1 + m["poisson_ratio"]))
        tr = min(tr, rayleigh_time(rmin, m["density"], G, m["poisson_ratio"]))
        mmin = 4 / 3 * math.pi * rmin ** 3 * m["density"]
        estar = st.tab[K.TAB.estar, k, k]
        th = min(th, hertz_collision_time(mmin / 2, rmin / 2, estar, vchar))
        for w in sc.walls:
            th = min(th, hertz_collision_time(mmin, rmin, st.tab[K.TAB.estar, k, w["material"]], vchar))
        # largest Hertz overlap of an impact at the characteristic velocity (smallest particle)
        d = (15 * (mmin / 2) * vchar ** 2 / (16 * estar * math.sqrt(rmin / 2))) ** 0.4
        ovmax = max(ovmax, d / rmin)
    return tr, th, ovmax


def memory_estimate(world, par):
    """(peak bytes of this process's particle arrays, bytes of one neighbour build).

    Peak = the per-particle arrays + the neighbour list and its history slots + during a
    rebuild, the new list beside the old one, the cell grid of the build (the box of
    occupied cells or sorted keys: O(n), independent of the domain size) and the rows of the
    pairs j > i before they are balanced (dem.neighbors.balance_rows)."""
    st = world.state
    lists = sum(getattr(st, f.name).nbytes for f in S.of("pair") if f.name in ("nb", "nnb") or f.record)
    if par is None:
        glo, ghi, gwrap = st.lo, st.hi, st.periodic
    else:
        glo, ghi, gwrap = par.grid_box(world)
    grid = grid_bytes(st.position, st.radius, st.n, glo, ghi, gwrap, world.reach, st.fp[K.FP.skin])
    grid += raw_rows_bytes(st.n, st.nb.shape[1])
    mem = st.memory_bytes("particle") + st.memory_bytes("pair")
    return mem + lists + grid, lists + grid


def parcel_period_warnings(sc):
    """Warnings for periodic axes only a few parcel diameters long (a scene with parcels)."""
    cg = parcel_factors(sc)
    if cg is None:
        return []
    if getattr(sc, "distributed", False):   # set up per rank (MPI): the groups' largest radii
        d = 2.0 * max(r for r, c in zip(sc.group_rmax, sc.group_cg) if c != 1.0)
    else:
        d = 2.0 * float(sc.radius[cg != 1.0].max())
    lo, hi, per = sc.domain["min"], sc.domain["max"], sc.domain["periodic"]
    out = []
    for ax in range(3):
        L = float(hi[ax] - lo[ax])
        if per[ax] and L < PARCEL_PERIOD_DIAMETERS * d:
            out.append(f"axis {'xyz'[ax]} is periodic over {L:g} m, {L / d:.3g} parcel diameters: the periodic "
                       f"images order a packing of parcels this few across (a poured bed's coordination number, "
                       f"and its contact conduction, came out 6 to 15 % high over 3 to 6 parcel diameters, within "
                       f"2 % over 12; docs/benchmarks.md, Coarse graining); make the domain along {'xyz'[ax]} at "
                       f"least {PARCEL_PERIOD_DIAMETERS:g} parcel diameters ({PARCEL_PERIOD_DIAMETERS * d:.3g} m)")
    return out
