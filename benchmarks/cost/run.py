"""What each heat-transfer mechanism costs, and that what a scene does not enable costs nothing.

    python benchmarks/cost/run.py [--quick] [--no-docs]
    python -m benchmarks.cost [--quick] [--no-docs]

Three measurements, one core, Numba kernels compiled (or loaded from the cache) and a
few steps run before any clock starts. The DEM figures are CPU seconds of the process
(time.process_time; the wall time is printed beside): on a machine shared with other
jobs the wall time also counts the time another job holds the core.

1. Mechanisms: the shared settled bed of 10,000 spheres (benchmarks/shared_bed_10k.toml,
   mechanics only; benchmarks/shared_bed_heat_10k.toml, + direct contact conduction) and
   variants derived from it, each adding one mechanism to the direct-conduction scene:
   every indirect model, every convection correlation, both radiation models, heat
   generation (a source in every particle) and friction heat. All variants advance the
   same number of steps from the same settled state (the integral indirect models, 10-40 x
   slower per step, about ``cap`` seconds of steps), in turns (round-robin, the order
   reversed each round), the best of the rounds kept; the table gives particle-steps/s
   and the ratio of the time per step to mechanics only and to direct conduction only.
2. Not enabled costs nothing: the mechanics-only scene run by our kernel (which holds the
   heat code behind a run-time switch) against a copy of the package whose step kernel has
   the heat code compiled out (``heat = False``, made in out/bench_cache/dem_noheat; the
   repository's dem/ is never touched), in separate whole processes, alternately, pair by
   pair (each process: its best of a few equal parts); the median and range of the per-pair
   ratios, the standard error of the median and the run-to-run spread of each build.
3. Coupling: the coupled fluidized bed of benchmarks/coupling_split.py (socket transport,
   thermoDemFoam), the wall time of the coupling phases (locate, void fraction,
   interpolation, exchange terms, send) against the DEM time and the coupled loop.

Writes the section "## Cost of each mechanism" of docs/benchmarks.md unless --no-docs.
"""
import argparse
import copy
import datetime
import json
import os
import platform
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
import tomllib

HERE = os.path.dirname(os.path.abspath(__file__))
ROOT = os.path.dirname(os.path.dirname(HERE))
if ROOT not in sys.path:
    sys.path.insert(0, ROOT)

from benchmarks.accuracy.common import CACHE, DOCS, md_table, replace_section  # noqa: E402

SECTION = "## Cost of each mechanism"
BENCH = os.path.join(ROOT, "benchmarks")
MECH_TOML = os.path.join(BENCH, "shared_bed_10k.toml")
HEAT_TOML = os.path.join(BENCH, "shared_bed_heat_10k.toml")
NOHEAT_DIR = os.path.join(CACHE, "dem_noheat")  # parent of the package copy "dem"
HEAT_SWITCH = "heat = hon is not None and thi[TI.heat] != 0"
HEAT_OFF = "heat = False  # benchmarks/cost: the heat code compiled out"

# air around the bed: what the indirect, convection and radiation models read
GAS = {"conductivity": 0.026, "density": 1.2, "viscosity": 1.8e-5, "heat_capacity": 1005.0,
       "temperature": 350.0, "velocity": [0.0, 0.0, 0.5]}
EMISSIVITY = 0.8
SOURCE_POWER = 1e-4  # W in every particle (generation)
TIGHT_TOL = 1e-11  # the former fixed quadrature tolerance, against the default (1e-4)

INDIRECT = ("cheng_1999_voronoi_a", "gan_2016_voronoi_a", "cheng_1999_voronoi_b", "chen_2019_voronoi_b",
            "rong_horio_1999_surrounding_layer", "musser_2011_surrounding_layer", "vargas_mccarthy_2002")
CONVECTION = ("ranz_marshall", "whitaker", "gunn", "li_mason")
RADIATION = ("zhou_2009", "krause_2017")
FRICTION = ("nguyen_2009",)
MECHANISM_KEYS = ("direct", "indirect", "convection", "radiation", "friction_heat")

QUICK = dict(steps=200, rounds=1, cap=1.0, ab_pairs=3, ab_steps=600, ab_segments=2, coupling_end=0.02)
FULL = dict(steps=1000, rounds=3, cap=3.0, ab_pairs=8, ab_steps=2000, ab_segments=4, coupling_end=0.1)
MIN_STEPS = 20  # fewest steps of a slow variant
SLOW = 5.0  # a variant slower per step than SLOW x mechanics only runs cap seconds, not all steps
COUPLING_WARMUP = 0.002  # s of coupled run (2 coupling steps) that compiles the coupling kernels


def log(*a):
    print(*a, flush=True)


# ----------------------------------------------------------------------------- scenes
def load(path):
    with open(path, "rb") as f:
        return tomllib.load(f)


class Variant:
    """One scene of the cost table: ``expect`` is what its report must enable
    (mechanism -> model name or "none"; "sources": number of heat sources)."""

    def __init__(self, key, mechanism, model, scene, expect):
        self.key, self.mechanism, self.model, self.scene, self.expect = key, mechanism, model, scene, expect

    def __repr__(self):
        return f"Variant({self.key})"


def variants(mech=None, heat=None):
    """The scenes of the table, derived from the two shared scenes (dicts as loaded from
    their TOML; by default the files themselves). Every variant but the first two adds one
    mechanism to ``heat`` (direct contact conduction)."""
    mech = load(MECH_TOML) if mech is None else mech
    heat = load(HEAT_TOML) if heat is None else heat
    base = {k: "none" for k in MECHANISM_KEYS}
    base_direct = heat.get("thermal", {}).get("direct", "batchelor_obrien")
    out = [Variant("mechanics", "mechanics only", "hertz_mindlin", copy.deepcopy(mech), None),
           Variant("direct", "direct", base_direct, copy.deepcopy(heat), dict(base, direct=base_direct, sources=0))]

    def derive(key, mechanism, model, thermal, gas=False, material=None, sources=None):
        d = copy.deepcopy(heat)
        d["thermal"].update(thermal)
        if gas:
            d["gas"] = copy.deepcopy(GAS)
        for m in d["materials"]:
            m.update(material or {})
        if sources:
            d["thermal"]["sources"] = sources
        exp = dict(base, direct=d["thermal"].get("direct", "batchelor_obrien"), sources=len(sources or []))
        for k in MECHANISM_KEYS[1:]:
            if k in thermal:
                exp[k] = thermal[k]
        out.append(Variant(key, mechanism, model, d, exp))

    for name in INDIRECT:
        th = {"indirect": name}
        if name == "rong_horio_1999_surrounding_layer":  # integrates over the contact itself
            th["direct"] = "none"
        derive(name, "indirect", name, th, gas=True)
    if _has_quadrature_tolerance():  # the knob of the integral models' cost
        derive(INDIRECT[0] + "_tol", "indirect", f"{INDIRECT[0]}, quadrature_tolerance = {TIGHT_TOL:g}",
               {"indirect": INDIRECT[0], "quadrature_tolerance": TIGHT_TOL}, gas=True)
    for name in CONVECTION:
        derive(name, "convection", name, {"convection": name}, gas=True)
    for name in RADIATION:  # zhou_2009 exchanges with the gas temperature: needs [gas]
        derive(name, "radiation", name, {"radiation": name}, gas=name == "zhou_2009",
               material={"emissivity": EMISSIVITY})
    derive("sources", "generation", f"{SOURCE_POWER:g} W per particle", {},
           sources=[{"group": 0, "power": SOURCE_POWER}])
    for name in FRICTION:
        derive("friction_" + name, "friction heat", name, {"friction_heat": name})
    return out


def _has_quadrature_tolerance():
    from dem.thermal.scene import THERMAL_KEYS
    return "quadrature_tolerance" in THERMAL_KEYS


def build(v):
    from dem import Simulation
    return Simulation.from_dict(v.scene, base_dir=BENCH, name=v.key)


def enabled(sim):
    """What a Simulation's report runs: mechanism -> model name ("none" when skipped),
    "sources" -> number of heat sources, "thermal" -> whether there is heat at all."""
    runs, _ = sim.models_report()
    got = {k: "none" for k in MECHANISM_KEYS}
    got["sources"] = 0
    got["thermal"] = sim.thermal is not None
    labels = {"direct conduction": "direct", "indirect conduction": "indirect", "convection": "convection",
              "radiation": "radiation", "friction heat": "friction_heat"}
    for line in runs:
        head, _, rest = line.partition(": ")
        if head in labels:
            got[labels[head]] = rest.split(" ")[0]
        elif head == "heat sources":
            got["sources"] = int(rest)
    return got


# ----------------------------------------------------------------------------- 1. mechanisms
def measure_variants(vs, steps, rounds, cap):
    """Per variant: best time per step of ``rounds`` runs (round-robin over the variants).
    Each runs ``steps`` steps; a variant that a timed 10-step run finds more than SLOW
    times slower than mechanics only (the integral indirect models, 15-60 x) runs about
    ``cap`` seconds instead (at least MIN_STEPS): the bed is at rest, so the cost per step
    does not depend on how many are run."""
    sims, nsteps = [], []
    per0 = None
    for v in vs:
        sim = build(v)
        sim.warmup()
        sim.run(end_time=sim.time + 5 * sim.dt, progress=False)  # compiled, caches warm
        c0 = time.process_time()
        sim.run(end_time=sim.time + 10 * sim.dt, progress=False)
        per_step = (time.process_time() - c0) / 10
        per0 = per_step if per0 is None else per0
        k = steps
        if per_step > SLOW * per0:
            k = min(steps, max(MIN_STEPS, int(cap / per_step) // 10 * 10))
        sims.append(sim)
        nsteps.append(k)
    cpu = [[] for _ in vs]
    wall = [[] for _ in vs]
    for r in range(rounds):
        order = range(len(vs)) if r % 2 == 0 else reversed(range(len(vs)))
        for k in order:
            sim = sims[k]
            t0, c0 = time.perf_counter(), time.process_time()
            sim.run(end_time=sim.time + nsteps[k] * sim.dt, progress=False)
            cpu[k].append(time.process_time() - c0)
            wall[k].append(time.perf_counter() - t0)
            log(f"  round {r + 1}/{rounds} {vs[k].key:36s} {nsteps[k]:5d} steps  cpu {cpu[k][-1]:7.2f} s  "
                f"wall {wall[k][-1]:7.2f} s")
    rows = []
    for v, sim, c, w, k in zip(vs, sims, cpu, wall, nsteps):
        n = sim.state.n
        per = min(c) / k
        rows.append(dict(key=v.key, mechanism=v.mechanism, model=v.model, n=n, steps=k, cpu=c, wall=w,
                         per_step=per, pps=n / per, pps_wall=n * k / min(w),
                         pairs=float(sim.state.nnb[:n].sum()) / n))
    t_mech = next(r["per_step"] for r in rows if r["key"] == "mechanics")
    t_dir = next(r["per_step"] for r in rows if r["key"] == "direct")
    for r in rows:
        r["vs_mech"] = r["per_step"] / t_mech
        r["vs_direct"] = r["per_step"] / t_dir
    return rows


# ----------------------------------------------------------------------------- 2. not enabled
def noheat_copy():
    """A copy of dem/ whose step kernel has the heat code compiled out, in NOHEAT_DIR/dem.
    Files are rewritten only when their text changes, so Numba's cache of the copy stays
    valid between runs. Returns NOHEAT_DIR."""
    from benchmarks.accuracy.common import claim, claim_cache
    claim_cache()
    claim(NOHEAT_DIR)   # our entry of out/bench_cache: never a user's folder (dem.outdir)
    src = os.path.join(ROOT, "dem")
    dst = os.path.join(NOHEAT_DIR, "dem")
    want = {}
    for dirpath, dirs, files in os.walk(src):
        dirs[:] = [d for d in dirs if d != "__pycache__"]
        for f in files:
            if f.endswith(".py"):
                p = os.path.join(dirpath, f)
                rel = os.path.relpath(p, src)
                with open(p) as fh:
                    want[rel] = fh.read()
    step = want["step.py"]
    if step.count(HEAT_SWITCH) != 2:
        raise RuntimeError(f"dem/step.py: expected the heat switch {HEAT_SWITCH!r} in compute_forces and "
                           f"advance, found it {step.count(HEAT_SWITCH)} times; update benchmarks/cost/run.py")
    want["step.py"] = step.replace(HEAT_SWITCH, HEAT_OFF)
    for rel, text in want.items():
        p = os.path.join(dst, rel)
        old = None
        if os.path.exists(p):
            with open(p) as fh:
                old = fh.read()
        if old != text:
            os.makedirs(os.path.dirname(p), exist_ok=True)
            with open(p, "w") as fh:
                fh.write(text)
    for dirpath, dirs, files in os.walk(dst):
        dirs[:] = [d for d in dirs if d != "__pycache__"]
        for f in files:
            rel = os.path.relpath(os.path.join(dirpath, f), dst)
            if f.endswith(".py") and rel not in want:
                os.remove(os.path.join(dirpath, f))
    return NOHEAT_DIR


def worker(build_name, steps, segments=1):
    """One whole-process run of the mechanics-only scene with our package ("repo") or the
    copy without heat code ("noheat"): ``steps`` steps timed in ``segments`` equal parts;
    prints one JSON line (cpu, wall: the best part scaled to ``steps``, so that a burst of
    load from another job in one part does not count)."""
    if build_name == "noheat":
        sys.path.insert(0, NOHEAT_DIR)
    import dem
    from dem import Simulation
    want = os.path.join(NOHEAT_DIR if build_name == "noheat" else ROOT, "dem")
    if os.path.dirname(os.path.abspath(dem.__file__)) != os.path.abspath(want):
        raise RuntimeError(f"imported {dem.__file__}, expected the package in {want}")
    sim = Simulation.from_dict(load(MECH_TOML), base_dir=BENCH, name="mechanics")
    comp = sim.warmup()
    sim.run(end_time=sim.time + 5 * sim.dt, progress=False)
    seg = steps // max(segments, 1)
    cpu, wall = [], []
    for _ in range(max(segments, 1) if seg else 0):
        t0, c0 = time.perf_counter(), time.process_time()
        sim.run(end_time=sim.time + seg * sim.dt, progress=False)
        cpu.append(time.process_time() - c0)
        wall.append(time.perf_counter() - t0)
    f = steps / seg if seg else 0.0
    print(json.dumps(dict(build=build_name, cpu=min(cpu, default=0.0) * f, wall=min(wall, default=0.0) * f,
                          cpu_parts=cpu, wall_parts=wall, steps=steps, n=sim.state.n, compile=comp,
                          dem=dem.__file__)), flush=True)


def _worker_run(build_name, steps, segments=1):
    cmd = [sys.executable, os.path.abspath(__file__), "--worker", build_name, "--steps", str(steps),
           "--segments", str(segments)]
    env = dict(os.environ)
    env.pop("PYTHONPATH", None)
    p = subprocess.run(cmd, capture_output=True, text=True, env=env, cwd=ROOT)
    if p.returncode != 0:
        raise RuntimeError(f"{' '.join(cmd)} failed:\n{p.stderr[-2000:]}")
    return json.loads(p.stdout.strip().splitlines()[-1])


def measure_not_enabled(pairs, steps, segments):
    """Alternate whole-process runs repo / noheat (ABBA order); per-pair time ratios."""
    noheat_copy()
    t0 = time.perf_counter()
    for b in ("repo", "noheat"):  # compile or load each build's kernels: not counted
        w = _worker_run(b, 0)
        log(f"  warm-up {b}: kernels ready in {w['compile']:.1f} s")
    log(f"  (warm-ups {time.perf_counter() - t0:.1f} s)")
    runs = []
    for k in range(pairs):
        noheat_copy()  # the same sources on both sides even if dem/ was edited meanwhile
        order = ("repo", "noheat") if k % 2 == 0 else ("noheat", "repo")
        got = {b: _worker_run(b, steps, segments) for b in order}
        runs.append(got)
        a, b = got["repo"], got["noheat"]
        log(f"  pair {k + 1}/{pairs}: cpu repo {a['cpu']:.2f} s, noheat {b['cpu']:.2f} s, ratio "
            f"{a['cpu'] / b['cpu']:.3f}  (wall {a['wall']:.2f} / {b['wall']:.2f} s = {a['wall'] / b['wall']:.3f})")
    ratios = [r["repo"]["cpu"] / r["noheat"]["cpu"] for r in runs]
    ta = [r["repo"]["cpu"] for r in runs]
    tb = [r["noheat"]["cpu"] for r in runs]
    wall_ratios = [r["repo"]["wall"] / r["noheat"]["wall"] for r in runs]
    med = statistics.median(ratios)
    # noise of the median ratio: 1.4826 MAD estimates the scatter of one ratio without
    # letting a burst of load from another job dominate; the median's standard error is
    # about 1.25 sigma / sqrt(n)
    mad = statistics.median(abs(x - med) for x in ratios)
    se = 1.25 * 1.4826 * mad / len(ratios) ** 0.5
    res = dict(pairs=pairs, steps=steps, segments=segments, ratios=ratios, median=med, lo=min(ratios), hi=max(ratios),
               repo=ta, noheat=tb, se=se, slower=sum(x > 1 for x in ratios),
               wall_median=statistics.median(wall_ratios), wall_lo=min(wall_ratios), wall_hi=max(wall_ratios),
               pps_repo=runs[0]["repo"]["n"] * steps / statistics.median(ta),
               pps_noheat=runs[0]["noheat"]["n"] * steps / statistics.median(tb),
               spread_repo=max(ta) / min(ta) - 1, spread_noheat=max(tb) / min(tb) - 1)
    res["within_noise"] = abs(med - 1) <= 2 * se
    return res


def verdict(ab):
    d = 100 * (ab["median"] - 1)
    two = 200 * ab["se"]
    sign = f"{ab['slower']} of {ab['pairs']} pairs slower with the heat code"
    if ab["within_noise"]:
        return (f"within noise (the median difference {d:+.1f} % is inside two standard errors of the "
                f"median, {two:.1f} %; {sign})")
    return (f"a measurable difference of {d:+.1f} % (more than two standard errors of the median, "
            f"{two:.1f} %; {sign})")


# ----------------------------------------------------------------------------- 3. coupling
def measure_coupling(end_time):
    from benchmarks.coupling_split import COUPLING, run as split_run
    tmp = tempfile.mkdtemp(prefix="cost_coupling_")
    try:  # a first short run compiles (or loads) the coupling kernels outside the figures
        split_run("socket", COUPLING_WARMUP, os.path.join(tmp, "warmup"))
        s = split_run("socket", end_time, tmp)
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    ph = s["phases"]
    coup = sum(ph.get(p, 0.0) for p in COUPLING)
    return dict(end_time=end_time, phases=ph, coupling=coup, dem=ph.get("dem", 0.0), loop=s["loop"],
                particles=s["particles"], coupling_steps=s["coupling_steps"], dem_steps=s["dem_steps"],
                share=coup / s["loop"], vs_dem=coup / max(ph.get("dem", 0.0), 1e-12),
                share_no_output=coup / max(s["loop"] - ph.get("output", 0.0), 1e-12))


# ----------------------------------------------------------------------------- output
def machine():
    cpu = platform.machine()
    try:
        with open("/proc/cpuinfo") as f:
            for line in f:
                if line.startswith("model name"):
                    cpu = line.split(":", 1)[1].strip()
                    break
    except OSError:
        pass
    import numba
    return (f"{cpu}, {os.cpu_count()} cores (one used), Python {platform.python_version()}, "
            f"numba {numba.__version__}")


def variant_table(rows):
    cols = ["mechanism", "model", "steps", "particle-steps/s", "time / mechanics only", "time / direct only",
            "list pairs per particle"]
    return md_table(cols, [[r["mechanism"], r["model"], r["steps"], f"{r['pps']:.3g}", f"{r['vs_mech']:.2f}",
                            f"{r['vs_direct']:.2f}", f"{r['pairs']:.1f}"] for r in rows])


def ab_table(ab):
    rows = [[k + 1, f"{a:.2f}", f"{b:.2f}", f"{a / b:.3f}"] for k, (a, b) in enumerate(zip(ab["repo"], ab["noheat"]))]
    return md_table(["pair", "our kernel, CPU [s]", "heat code compiled out, CPU [s]", "ratio"], rows)


def coupling_table(c):
    rows = [[p, f"{v:.2f}", f"{100 * v / c['loop']:.1f}"] for p, v in c["phases"].items()]
    rows.append(["**coupling** (locate + void_fraction + interpolation + exchange_terms + exchange)",
                 f"{c['coupling']:.2f}", f"{100 * c['share']:.1f}"])
    rows.append(["coupled loop", f"{c['loop']:.2f}", "100"])
    return md_table(["phase", "wall [s]", "share [%]"], rows)


def interpretation(rows, ab, cp):
    by = {r["key"]: r for r in rows}

    def span(keys):
        v = [by[k]["vs_direct"] for k in keys if k in by]
        return f"{min(v):.2f}-{max(v):.2f}x" if len(v) > 1 else f"{v[0]:.2f}x"

    integral = ("cheng_1999_voronoi_a", "gan_2016_voronoi_a", "rong_horio_1999_surrounding_layer",
                "musser_2011_surrounding_layer")
    closed = ("cheng_1999_voronoi_b", "chen_2019_voronoi_b", "vargas_mccarthy_2002")
    s = (f"Direct conduction costs {by['direct']['vs_mech']:.2f}x mechanics only (contact radius and "
         f"conductance of each contact in the force loop, one temperature update per particle). The "
         f"integral indirect models (Voronoi A, surrounding layer) are by far the most expensive, "
         f"{span(integral)} direct only: they evaluate an adaptive Gauss-Kronrod quadrature (default "
         f"tolerance 1e-4) for every pair within the gas cut-off at every step")
    tol = INDIRECT[0] + "_tol"
    if tol in by:
        s += (f"; the former fixed tolerance {TIGHT_TOL:g} costs {by[tol]['vs_direct']:.2f}x instead of "
              f"{by[INDIRECT[0]]['vs_direct']:.2f}x: at the default most pairs converge on the first 15-point "
              f"panel, so the cost is that panel, evaluated for each pair at each step")
    s += (f". The closed-form indirect models (Voronoi B, Vargas & McCarthy) cost {span(closed)}: "
          f"mostly the neighbour list lengthened to the cut-off (pairs per particle "
          f"{by['direct']['pairs']:.1f} -> {by[INDIRECT[0]]['pairs']:.1f}) and the local porosity measured "
          f"at each rebuild; convection ({span(CONVECTION)}) and radiation ({span(RADIATION)}) pay for the "
          f"same longer list (porosity, radiation range) and a per-particle term; a heat source "
          f"({span(['sources'])}) and friction heat ({span(['friction_' + FRICTION[0]])}) add almost "
          f"nothing. ")
    s += (f"A scene without heat runs our kernel at {ab['median']:.3f}x the CPU time of the same kernel "
          f"with the heat code compiled out: {verdict(ab)}.")
    if cp is not None:
        s += (f" In the coupled fluidized bed the coupling work (locating, void fraction, interpolation, "
              f"exchange terms, sending) takes {100 * cp['share']:.1f} % of the coupled loop, "
              f"{100 * cp['vs_dem']:.0f} % of the DEM time of the same interval.")
    return s


def section(args, p, rows, ab, cp, cp_err, when, total):
    cmd = "python benchmarks/cost/run.py" + (" --quick" if args.quick else "")
    n = rows[0]["n"]
    out = [f"`{cmd}` ({total:.0f} s in all). Measured {when} on {machine()}, shared with other jobs "
           "(quote ratios, not absolute times). DEM times are CPU seconds of the process "
           "(`time.process_time`): on the shared machine the wall time also counts the time another job "
           "holds the core.", "",
           f"**Mechanisms** on the shared settled bed (N = {n:,}, Hertz-Mindlin, 5 walls, dt = 1e-5 s): "
           f"each scene advances {p['steps']:,} steps from the settled state (a scene more than {SLOW:g} x "
           f"slower per step than mechanics only: about {p['cap']:g} s of steps, see the steps column; the "
           f"bed is at rest, so the cost per step does not depend on the count), {p['rounds']} round(s) "
           "round-robin over all scenes (order reversed each round), best round kept; kernels compiled "
           "and a few steps run before the clock. `direct` is `benchmarks/shared_bed_heat_10k.toml` "
           "(batchelor_obrien, geometric contact radius); every other row adds one mechanism to it "
           "(rong_horio_1999_surrounding_layer replaces the direct model, as it must), with air "
           f"(k = {GAS['conductivity']} W/(m K), {GAS['temperature']:g} K, 0.5 m/s slip) where a model "
           f"reads the gas, emissivity {EMISSIVITY} for radiation, {SOURCE_POWER:g} W per particle for "
           "generation. \"list pairs per particle\": neighbour-list entries (half list) per particle, "
           "which the gas cut-off and the radiation range lengthen.", "",
           variant_table(rows), "",
           f"**What is not enabled costs nothing**: `benchmarks/shared_bed_10k.toml` (no [thermal] section), "
           f"{ab['steps']:,} steps per process timed in {ab['segments']} parts (best part kept), our kernel against a copy of the package whose step kernel has the heat "
           f"code compiled out (`heat = False` in place of the run-time switch, made in "
           f"out/bench_cache/dem_noheat), {ab['pairs']} pairs of whole-process runs in alternating order, "
           f"start-up and compilation excluded. Median CPU-time ratio **{ab['median']:.3f}** (range "
           f"{ab['lo']:.3f}-{ab['hi']:.3f}, standard error of the median {ab['se']:.3f}); run-to-run spread of one build: ours "
           f"{100 * ab['spread_repo']:.0f} %, compiled out {100 * ab['spread_noheat']:.0f} %; wall-time ratio "
           f"{ab['wall_median']:.3f} ({ab['wall_lo']:.3f}-{ab['wall_hi']:.3f}). Verdict: "
           f"{verdict(ab)}.", "", ab_table(ab), ""]
    if cp is not None:
        out += [f"**Coupling** (the measurement of `benchmarks/coupling_split.py`): "
                f"openfoam_cases/fluidized_bed_heating, socket transport, {cp['particles']:,} particles, "
                f"{cp['coupling_steps']} coupling steps x {cp['dem_steps'] // max(cp['coupling_steps'], 1)} "
                f"DEM steps (t = {cp['end_time']:g} s from the start: the bed is still settling into "
                f"fluidization), serial thermoDemFoam running alongside, after a {COUPLING_WARMUP:g} s run "
                f"that compiles the coupling kernels. Coupling work: {100 * cp['share']:.1f} % of the coupled "
                f"loop ({100 * cp['share_no_output']:.1f} % without output), {100 * cp['vs_dem']:.0f} % of "
                "the DEM time.", "", coupling_table(cp), ""]
    else:
        out += [f"**Coupling**: not measured ({cp_err}).", ""]
    out += [interpretation(rows, ab, cp)]
    return "\n".join(out)


# ----------------------------------------------------------------------------- main
def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--quick", action="store_true", help="fewer steps, rounds and pairs (under 2 minutes)")
    ap.add_argument("--no-docs", action="store_true", help="do not write docs/benchmarks.md")
    ap.add_argument("--worker", choices=["repo", "noheat"], help=argparse.SUPPRESS)
    ap.add_argument("--steps", type=int, default=0, help=argparse.SUPPRESS)
    ap.add_argument("--segments", type=int, default=1, help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    if args.worker:
        worker(args.worker, args.steps, args.segments)
        return
    p = QUICK if args.quick else FULL
    when = datetime.datetime.now().astimezone().strftime("%Y-%m-%d %H:%M %Z")
    t_all = time.perf_counter()
    vs = variants()
    log(f"1. mechanisms: {len(vs)} scenes x {p['steps']} steps x {p['rounds']} round(s)")
    rows = measure_variants(vs, p["steps"], p["rounds"], p["cap"])
    log(variant_table(rows))
    log(f"2. not enabled: {p['ab_pairs']} pairs x {p['ab_steps']} steps, whole processes")
    ab = measure_not_enabled(p["ab_pairs"], p["ab_steps"], p["ab_segments"])
    log(ab_table(ab))
    log(f"median ratio {ab['median']:.3f} (range {ab['lo']:.3f}-{ab['hi']:.3f}): {verdict(ab)}")
    log(f"3. coupling: fluidized bed to t = {p['coupling_end']:g} s, socket transport")
    cp, cp_err = None, None
    try:
        cp = measure_coupling(p["coupling_end"])
        log(coupling_table(cp))
    except Exception as exc:  # noqa: BLE001  (no OpenFOAM here: the rest still stands)
        cp_err = f"{type(exc).__name__}: {str(exc).splitlines()[0] if str(exc) else ''}"
        log(f"  coupling not measured: {cp_err}")
    total = time.perf_counter() - t_all
    body = section(args, p, rows, ab, cp, cp_err, when, total)
    log("\n" + interpretation(rows, ab, cp))
    log(f"total {total:.0f} s")
    if not args.no_docs:
        path = os.path.join(DOCS, "benchmarks.md")
        replace_section(path, SECTION, body)  # re-reads the file: other sections stay as they are
        log(f"written: {path} ({SECTION})")


if __name__ == "__main__":
    main()
