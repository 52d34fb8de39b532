"""Coupled stress sweeps of the stability map (benchmarks/stability/run.py):

* particle diameter / CFD cell size from 0.1 to 3 with each void-fraction model
  (a settled bed of 2 mm beads, hot air at 0.5 m/s superficial, below minimum fluidization);
* sudden void-fraction changes seen by the gas solver (a packed bed appearing in one
  coupling step, a dense cluster thrown through fine cells).

Every run goes through ``coupling.run.run_case`` (the checks, the guards and the messages
a user sees); the cases are written from openfoam_cases/fluidized_bed_heating with a new
mesh, DEM scene and coupling.toml.
"""
from __future__ import annotations

import math
import os
import re
import shutil
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[2]
TEMPLATE = ROOT / "openfoam_cases" / "fluidized_bed_heating"
WORK = ROOT / "out" / "stability"

D = 2e-3                 # particle diameter
RHO_G, NU_G, CP_G, K_G = 1.2, 1.5e-5, 1005.0, 0.0262
T_IN, T_P0 = 373.15, 300.0


def bed_packing(log=print, n=700, L=0.02):
    """A settled random bed of n beads (d = 2 mm) in a periodic L x L column (cached)."""
    import sys
    sys.path.insert(0, str(ROOT))
    from benchmarks.accuracy.common import settled_packing
    x, L = settled_packing(n=n, L=L, log=log)
    return np.asarray(x, float), L


def _sub(path: Path, pattern: str, repl: str, count: int = 0, flags=re.S) -> None:
    text = path.read_text()
    new, k = re.subn(pattern, repl, text, count=count, flags=flags)
    if k == 0:
        raise RuntimeError(f"{path}: pattern {pattern!r} not found")
    path.write_text(new)


def write_case(dest: Path, *, L: float, H: float, nxy: int, nz: int, positions, velocities=None,
               dt_dem: float = 1e-5, interval: int = 10, n_steps: int = 30, u_in: float = 0.5,
               void_fraction: str = "divided", eps_min: float = 0.3, smoothing_time: float = 0.0,
               mechanics: bool = True, force: bool = False, youngs: float = 1e7,
               periodic: bool = True, walls_top: bool = True, max_overlap_ratio: float | None = None,
               heat: bool = True, diameter: float = D, density: float = 2500.0, rho_g: float = RHO_G,
               nu_g: float = NU_G, drag: str = "di_felice_1994", friction: float = 0.3,
               restitution: float = 0.9, floor: float = 0.0, drag_integration: str | None = None,
               drag_void_fraction: str | None = None, drag_averaging_length: float | None = None) -> Path:
    """A coupled case: L x L x H box meshed nxy x nxy x nz, hot gas entering at the bottom
    at u_in (superficial), beads of 2 mm at the given positions (300 K)."""
    from dem import outdir   # dest: new, empty or this benchmark's earlier case (replaced), never a user's
    outdir.claim_folder(dest, overwrite=True, command="benchmarks/stability case", what="case folder")
    skip = ("README.md", "dem.toml", "coupling.toml")
    for name in [n for n in os.listdir(TEMPLATE) if n not in skip] + ["particles.csv", "dem.toml", "coupling.toml"]:
        outdir.claim(dest / name)
    shutil.copytree(TEMPLATE, dest, ignore=shutil.ignore_patterns(*skip), dirs_exist_ok=True)
    bm = dest / "system" / "blockMeshDict"
    _sub(bm, r"vertices\s*\(.*?\n\);",
         "vertices\n(\n    (0 0 0) ({L} 0 0) ({L} {L} 0) (0 {L} 0)\n"
         "    (0 0 {H}) ({L} 0 {H}) ({L} {L} {H}) (0 {L} {H})\n);"
         .format(L=repr(L), H=repr(H)))
    _sub(bm, r"hex \(0 1 2 3 4 5 6 7\) \([^)]*\)", f"hex (0 1 2 3 4 5 6 7) ({nxy} {nxy} {nz})")
    dt_cfd = interval * dt_dem
    end = n_steps * dt_cfd
    ctl = dest / "system" / "controlDict"
    _sub(ctl, r"\ndeltaT\s+[^;]+;", f"\ndeltaT          {dt_cfd!r};")
    _sub(ctl, r"\nendTime\s+[^;]+;", f"\nendTime         {end!r};")
    _sub(ctl, r"\nwriteInterval\s+[^;]+;", "\nwriteInterval   100000;")
    tp = dest / "constant" / "transportProperties"
    _sub(tp, r"\nnu\s+[^;]+;", f"\nnu              {nu_g!r};")
    _sub(tp, r"\nrho\s+[^;]+;", f"\nrho             {rho_g!r};")
    u = dest / "0" / "U"
    _sub(u, r"uniform \(0 0 2\.0\)", f"uniform (0 0 {u_in!r})")
    # the DEM column is periodic: the side walls of the gas are slip planes (symmetry)
    _sub(u, r"xWalls\s*\{[^}]*\}", "xWalls\n    {\n        type slip;\n    }")
    x = np.asarray(positions, float)
    n = len(x)
    with open(dest / "particles.csv", "w") as f:
        f.write("x,y,z,radius\n")
        for p in x:
            f.write(f"{float(p[0])!r},{float(p[1])!r},{float(p[2])!r},{diameter / 2!r}\n")
    part = ('[[particles]]\nmaterial = "glass"\nfile = "particles.csv"\ntemperature = 300.0\n'
            if velocities is None else
            '[[particles]]\nmaterial = "glass"\nradius = {r!r}\ntemperature = 300.0\npositions = {p}\n'
            'velocities = {v}\n'.format(r=diameter / 2, p=_toml_list(x),
                          v=_toml_list(np.asarray(velocities, float))))
    walls = ['[[walls]]\ntype = "plane"\nname = "distributor"\npoint = [0.0, 0.0, {f!r}]\nnormal = [0.0, 0.0, 1.0]\n'
             'material = "glass"\n'.format(f=float(floor))]
    if walls_top:
        walls.append(f'[[walls]]\ntype = "plane"\nname = "top"\npoint = [0.0, 0.0, {H!r}]\n'
                     'normal = [0.0, 0.0, -1.0]\nmaterial = "glass"\n')
    if not periodic:
        for name, pt, nrm in (("left", (0, 0, 0), (1, 0, 0)), ("right", (L, 0, 0), (-1, 0, 0)),
                              ("back", (0, 0, 0), (0, 1, 0)), ("front", (0, L, 0), (0, -1, 0))):
            walls.append(f'[[walls]]\ntype = "plane"\nname = "{name}"\npoint = {list(map(float, pt))}\n'
                         f'normal = {list(map(float, nrm))}\nmaterial = "glass"\n')
    sim_extra = f"force = true\n" if force else ""
    if max_overlap_ratio is not None:
        sim_extra += f"max_overlap_ratio = {max_overlap_ratio!r}\n"
    per = "true" if periodic else "false"
    dem = f"""[simulation]
time_step = {dt_dem!r}
end_time = {end!r}
gravity = [0.0, 0.0, -9.81]
mechanics = {"true" if mechanics else "false"}
output_interval = {end!r}
{sim_extra}
[domain]
min = [0.0, 0.0, 0.0]
max = [{L!r}, {L!r}, {H!r}]
periodic = [{per}, {per}, false]

[[materials]]
name = "glass"
density = {density!r}
youngs_modulus = {youngs!r}
poisson_ratio = 0.25
restitution = {restitution!r}
friction = {friction!r}
heat_capacity = 840.0
thermal_conductivity = 1.0

{part}
{"".join(walls)}
[thermal]
direct = "batchelor_obrien"
convection = "ranz_marshall"
porosity = "global"

[gas]
conductivity = {K_G!r}
density = {rho_g!r}
viscosity = {rho_g * nu_g!r}
heat_capacity = {CP_G!r}
temperature = {T_IN!r}

[output]
vtk = false
"""
    (dest / "dem.toml").write_text(dem)
    (dest / "coupling.toml").write_text(
        "[coupling]\ntransport = \"socket\"\n"
        f"coupling_interval = {interval}\ndrag = \"{drag}\"\nvoid_fraction = \"{void_fraction}\"\n"
        f"interpolation = \"cell\"\neps_min = {eps_min!r}\nsmoothing_time = {smoothing_time!r}\n"
        f"heat = {'true' if heat else 'false'}\ntimeout = 60\nend_time = {end!r}\noutput_interval = {dt_cfd!r}\n"
        f"force = {'true' if force else 'false'}\n"
        + (f"drag_integration = \"{drag_integration}\"\n" if drag_integration else "")
        + (f"drag_void_fraction = \"{drag_void_fraction}\"\n" if drag_void_fraction else "")
        + (f"drag_averaging_length = {drag_averaging_length!r}\n" if drag_averaging_length else ""))
    return dest


def _toml_list(a):
    return "[" + ", ".join("[" + ", ".join(repr(float(v)) for v in row) + "]" for row in a) + "]"


# ----------------------------------------------------------------------------- instrumentation
class Probe:
    """Wraps CouplingInterface.prepare for the runs of this module: records, per coupling
    step, the exchange consistency at one time level (gas-side sums with the gas state the
    particles saw vs the particle-side sums) and the eps clipping of the interface."""

    def __init__(self):
        self.rows = []
        self.teleport = None        # (coupling step, dz): shift every particle by dz before that step
        self._orig = None

    def install(self):
        from coupling.interface import CouplingInterface
        import coupling.run as crun
        self._orig = (CouplingInterface.prepare, CouplingInterface.advance_dem, crun.plot)
        probe = self

        def prepare(self_, fluid, dt_cfd):
            frame = probe._orig[0](self_, fluid, dt_cfd)
            probe._record(self_, fluid, frame)
            return frame

        def advance_dem(self_, k):
            if probe.teleport is not None and self_.sim.step_count == probe.teleport[0] * k:
                st = self_.sim.state
                st.position[:st.n_owned, 2] += probe.teleport[1]
            return probe._orig[1](self_, k)

        CouplingInterface.prepare = prepare
        CouplingInterface.advance_dem = advance_dem
        crun.plot = lambda out, title: None       # no coupling.png (saves a second a run)

    def uninstall(self):
        from coupling.interface import CouplingInterface
        import coupling.run as crun
        if self._orig is not None:
            CouplingInterface.prepare, CouplingInterface.advance_dem, crun.plot = self._orig
            self._orig = None

    def reset(self, teleport=None):
        self.rows = []
        self.teleport = teleport

    def _record(self, iface, fluid, frame):
        st = iface.sim.state
        n = st.n_owned
        V = iface.V
        last = iface.last
        beta, vel = last["beta"], st.velocity[:n]
        f_p = float((beta * (last["uf"][:, 2] - vel[:, 2])).sum())           # drag on the particles
        f_g = -float((frame["Ksl"] * (fluid["U"][:, 2] - frame["Us"][:, 2]) * V).sum())  # on the gas
        q_p = q_g = 0.0
        if iface.heat:
            tg = np.where(np.isfinite(last["Tg"]), last["Tg"], st.temperature[:n])
            q_p = float((last["hA"] * (tg - st.temperature[:n])).sum())      # heat to the particles
            q_g = float(((frame["Sexp"] - frame["Simp"] * fluid["T"]) * V).sum())  # heat to the gas
        u = fluid["U"]
        self.rows.append(dict(step=iface.sim.step_count, f_p=f_p, f_g=f_g, q_p=q_p, q_g=q_g,
                              clip_cells=iface.clip["cells"], clip_fraction=iface.clip["fraction"],
                              eps_raw_min=iface.clip["eps_raw_min"], eps_min=float(frame["eps"].min()),
                              u_gas_max=float(np.sqrt((u * u).sum(1)).max()), eps_change=iface.eps_change[0],
                              v_max=float(np.sqrt((vel * vel).sum(1)).max()) if n else 0.0))

    def summary(self):
        r = self.rows
        if not r:
            return {}
        def rel(a, b):
            return abs(a + b) / max(abs(a), 1e-300)
        ef = [rel(x["f_p"], x["f_g"]) for x in r if abs(x["f_p"]) > 0]
        eq = [rel(x["q_p"], x["q_g"]) for x in r if abs(x["q_p"]) > 0]
        return dict(momentum_mismatch=max(ef) if ef else None, heat_mismatch=max(eq) if eq else None,
                    clip_cells=max(x["clip_cells"] for x in r), clip_fraction=max(x["clip_fraction"] for x in r),
                    eps_raw_min=min(x["eps_raw_min"] for x in r), eps_min=min(x["eps_min"] for x in r),
                    u_gas_max=max(x["u_gas_max"] for x in r), v_max=max(x["v_max"] for x in r),
                    eps_change=max(x["eps_change"] for x in r),
                    f_p=r[-1]["f_p"])


# ----------------------------------------------------------------------------- one run
def output_finite(out: Path, n_cells: int):
    """(finite, details): final.npz or checkpoint.npz, coupling.csv and the last gas time
    directory (U, p, T; T > 0) hold only finite values."""
    from coupling import foam_case as fc
    bad = []
    f = out / "final.npz" if (out / "final.npz").exists() else out / "checkpoint.npz"
    if f.exists():
        from dem.final import read as read_final   # an MPI run's final.npz: a manifest and its pieces
        z = read_final(f) if f.name == "final.npz" else np.load(f)
        for k in z.files:
            a = z[k]
            if a.dtype.kind == "f" and not np.all(np.isfinite(a)):
                bad.append(f"{f.name}:{k}")
    csv = out / "coupling.csv"
    if csv.exists():
        d = np.atleast_1d(np.genfromtxt(csv, delimiter=",", names=True))
        for k in d.dtype.names:
            if not np.all(np.isfinite(d[k])):
                bad.append(f"coupling.csv:{k}")
    times = sorted((float(p.name), p) for p in out.iterdir() if p.is_dir() and _is_time(p.name))
    if times and times[-1][0] > 0:
        tdir = times[-1][1]
        for k in ("U", "p", "T"):
            try:
                a = fc.read_internal_field(tdir / k, n_cells)
            except Exception as e:  # noqa: BLE001  (a field with nan/inf does not parse)
                bad.append(f"{tdir.name}/{k}: {type(e).__name__}")
                continue
            if not np.all(np.isfinite(a)) or (k == "T" and a.min() <= 0):
                bad.append(f"{tdir.name}/{k}")
    return (not bad), bad


def _is_time(name):
    try:
        float(name)
        return True
    except ValueError:
        return False


def run_one(case: Path, out: Path, probe: Probe, teleport=None):
    """run_case with the report captured. Returns a dict: check (ok / warns / refused),
    warnings, problems, outcome, exception class and message, seconds, probe summary,
    finite output."""
    from coupling.run import run_case, CouplingRunError
    from coupling.exchange import CouplingError
    from coupling.case import CaseConfigError
    from dem.simulation import SimulationError
    lines = []
    probe.reset(teleport)
    res = dict(outcome="completed", error="", message="")
    t0 = time.perf_counter()
    try:
        res["summary"] = run_case(case, out, quiet=False, log=lambda *a: lines.append(" ".join(map(str, a))),
                                  overwrite=True)
    except (SimulationError, CouplingError, CouplingRunError, CaseConfigError) as e:
        res["outcome"] = "stopped"
        res["error"] = type(e).__name__
        res["message"] = str(e).split("\n  DEM checkpoint")[0]
    res["seconds"] = time.perf_counter() - t0
    text = "\n".join(lines)
    res["warnings"] = re.findall(r"^  WARNING: (.*)", text, re.M)
    res["problems"] = re.findall(r"^  PROBLEM: (.*)", text, re.M)
    res["log"] = text
    res["probe"] = probe.summary()
    m = re.search(r"^  cells\s+(\d+)", text, re.M)
    n_cells = int(m.group(1)) if m else None
    res["finite"], res["nonfinite"] = output_finite(out, n_cells) if n_cells else (None, [])
    d = None
    if (out / "coupling.csv").exists():
        d = np.atleast_1d(np.genfromtxt(out / "coupling.csv", delimiter=",", names=True))
    res["csv"] = d
    res["out"] = out
    res["n_cells"] = n_cells
    res["runtime_warnings"] = re.findall(r"coupling: WARNING: (.*)", text)
    return res


# ----------------------------------------------------------------------------- records
def _temperature_span(out: Path, n_cells: int | None):
    """(min, max) of the particle temperatures (final.npz, else checkpoint.npz) and of the gas
    temperature of the last time directory."""
    from coupling import foam_case as fc
    lo, hi = math.inf, -math.inf
    f = out / "final.npz" if (out / "final.npz").exists() else out / "checkpoint.npz"
    if f.exists():
        from dem.final import read as read_final   # an MPI run's final.npz: a manifest and its pieces
        z = read_final(f) if f.name == "final.npz" else np.load(f)
        T = z["temperature"] if "temperature" in z.files else z.get("state_temperature")
        if T is not None and T.size:
            lo, hi = min(lo, float(np.min(T))), max(hi, float(np.max(T)))
    times = sorted((float(p.name), p) for p in out.iterdir() if p.is_dir() and _is_time(p.name))
    if n_cells and times and times[-1][0] > 0:
        try:
            T = fc.read_internal_field(times[-1][1] / "T", n_cells)
            lo, hi = min(lo, float(T.min())), max(hi, float(T.max()))
        except Exception:  # noqa: BLE001
            pass
    return lo, hi


def make_record(group, setting, res, guard_of, *, extra="", inaccurate=""):
    """One row of the stability map from a run_one result (same keys as the DEM records)."""
    rec = dict(group=group, setting=setting, seconds=res["seconds"], extra=extra, inaccurate=inaccurate,
               check="refused" if res["problems"] else ("warning: " + "; ".join(res["warnings"])
                                                        if res["warnings"] else "ok"),
               outcome=res["outcome"], guard="", message=res["message"], finite=res["finite"], bounded=None,
               coupled=True)
    if res["problems"]:
        rec["check_message"] = "; ".join(res["problems"])
    if res["outcome"] == "stopped":
        err, msg = res["error"], res["message"]
        if err == "GasFieldError":
            rec["guard"] = "gas-field guard (GasFieldError)"
        elif err == "CouplingError":
            rec["guard"] = "coupling exchange (CouplingError)"
        elif err in ("CouplingRunError", "CaseConfigError"):
            rec["guard"] = "coupled check (refused)"
            rec["outcome"] = "not run"
        else:
            rec["guard"] = guard_of(msg)
    n_cells = res.get("n_cells")
    lo, hi = _temperature_span(res["out"], n_cells)
    if math.isfinite(lo):
        tol = 1e-6 * T_IN
        rec["bounded"] = bool(lo >= T_P0 - tol and hi <= T_IN + tol)
        dig = 5 if rec["bounded"] else 8
        rec["extra"] = (rec["extra"] + "; " if rec["extra"] else "") + f"T in [{lo:.{dig}g}, {hi:.{dig}g}] K"
    if res["nonfinite"]:
        rec["extra"] += "; non-finite: " + ", ".join(res["nonfinite"])
    return rec


def _pct(x):
    return "–" if x is None else f"{100 * x:.2g} %"


# ----------------------------------------------------------------------------- sweeps
def expected_bed_drag(x, L, u_in, drag="di_felice_1994", d=D):
    """Drag of the gas on the settled bed at its mean void fraction (particles at rest):
    N beta(eps, U/eps) U/eps, with U the superficial velocity; and that eps."""
    from coupling.drag import drag_coefficients, drag_model_id
    n = len(x)
    vp = math.pi / 6 * d ** 3
    hb = float(x[:, 2].max()) + d / 2
    eps = 1 - n * vp / (L * L * hb)
    beta = drag_coefficients(drag_model_id(drag), np.array([d]), np.array([eps]), RHO_G, RHO_G * NU_G,
                             np.array([u_in / eps]))[0]
    return n * beta * u_in / eps, eps


def mesh_for_ratio(L, ratio):
    """nxy x nxy x nz cubic cells of size D / ratio: 40 mm tall for coarse cells, 20 mm (the
    bed is 14 mm) from d/dx = 1 on."""
    nxy = max(1, round(L * ratio / D))
    dx = L / nxy
    nz = max(2, round((0.04 if ratio < 1.0 else 0.02) / dx))
    return nxy, nz, dx, nz * dx


def size_sweep(quick, log, guard_of, probe, x, L):
    """Particle diameter / cell size 0.1 .. 3 with each void-fraction model: settled bed of
    700 beads (2 mm, 14 mm deep), hot air (373 K) at 0.5 m/s superficial (below minimum
    fluidization), 30 coupling steps of 10 DEM steps (1e-5 s)."""
    ratios = [0.1, 1.0, 3.0] if quick else [0.1, 0.2, 0.5, 1.0, 2.0, 3.0]
    f_exp, eps_bed = expected_bed_drag(x, L, 0.5)
    group = f"coupled: d/dx, settled bed 700 x 2 mm (eps {eps_bed:.2f}), air 0.5 m/s, 300 DEM steps"
    out = []
    for ratio in ratios:
        nxy, nz, dx, H = mesh_for_ratio(L, ratio)
        for vf in ("centre", "divided", "smoothed"):
            case = write_case(WORK / "case", L=L, H=H, nxy=nxy, nz=nz, positions=x, void_fraction=vf, force=True)
            res = run_one(case, WORK / "out", probe)
            p = res["probe"]
            fr = p.get("f_p", float("nan")) / f_exp
            bad = []
            if p.get("clip_fraction", 0) > 0.05:
                bad.append(f"{_pct(p['clip_fraction'])} of the solid clipped")
            mm = max(p.get("momentum_mismatch") or 0, p.get("heat_mismatch") or 0)
            if mm > 0.1:
                bad.append(f"exchange mismatch {_pct(mm)}")
            extra = (f"{nxy}x{nxy}x{nz} cells; bed drag {fr:.3g} x the mean-eps value; eps 1 - Vs/V down to "
                     f"{p.get('eps_raw_min', 1):.3g}, clipped in {p.get('clip_cells', 0)} cells "
                     f"({_pct(p.get('clip_fraction'))} of the solid); exchange mismatch momentum "
                     f"{_pct(p.get('momentum_mismatch'))}, heat {_pct(p.get('heat_mismatch'))}; "
                     f"particles up to {p.get('v_max', 0):.2g} m/s")
            rec = make_record(group, f"{vf}, d/dx = {ratio:g}", res, guard_of, extra=extra,
                              inaccurate=", ".join(bad))
            rec.update(x=(vf, ratio), drag_ratio=fr, probe=p)
            out.append(rec)
            log(f"  {group} | {rec['setting']}: {res['seconds']:.1f} s {rec['outcome']} {rec['guard']} "
                f"check={rec['check'][:80]} finite={rec['finite']} {extra} {rec['message'][:160]}")
    return out


def eps_min_sweep(quick, log, guard_of, probe, x, L):
    """eps_min below the default with the 'centre' model at d/dx = 2 (each particle fills
    its cell: eps clipped everywhere in the bed)."""
    out = []
    group = "coupled: eps_min, centre, d/dx = 2 (bed clipped)"
    nxy, nz, dx, H = mesh_for_ratio(L, 2.0)
    for emin in ([0.05] if quick else [0.3, 0.1, 0.05, 0.01]):
        case = write_case(WORK / "case", L=L, H=H, nxy=nxy, nz=nz, positions=x, void_fraction="centre",
                          eps_min=emin, force=True)
        res = run_one(case, WORK / "out", probe)
        p = res["probe"]
        bad = ", ".join(b for b in (f"{_pct(p.get('clip_fraction'))} of the solid clipped"
                                    if p.get("clip_fraction", 0) > 0.05 else "",
                                    "bed set in motion" if p.get("v_max", 0) > 0.05 else "") if b)
        extra = (f"particles up to {p.get('v_max', 0):.2g} m/s (at rest: 0.005), gas up to "
                 f"{p.get('u_gas_max', 0):.3g} m/s")
        rec = make_record(group, f"eps_min = {emin:g}", res, guard_of, extra=extra, inaccurate=bad)
        rec.update(x=emin, probe=p)
        out.append(rec)
        log(f"  {group} | {rec['setting']}: {res['seconds']:.1f} s {rec['outcome']} {rec['guard']} {extra} "
            f"{rec['message'][:160]}")
    return out


def teleport_sweep(quick, log, guard_of, probe, x, L):
    """Sudden void fraction change: the settled bed is moved up by 20 mm between two coupling
    steps (eps of the cells jumps by ~0.6), divided model, 4 mm cells."""
    out = []
    group = "coupled: bed moved up 20 mm in one coupling step (divided, 4 mm cells)"
    specs = [(1, 0.0), (10, 0.0), (10, 1e-3)] if quick else \
        [(1, 0.0), (1, 1e-4), (1, 1e-3), (10, 0.0), (10, 1e-3), (100, 0.0)]
    for k, tau in specs:
        case = write_case(WORK / "case", L=L, H=0.04, nxy=5, nz=10, positions=x, void_fraction="divided",
                          interval=k, n_steps=max(6, 60 // k), smoothing_time=tau, force=True)
        res = run_one(case, WORK / "out", probe, teleport=(2, 0.02))
        p = res["probe"]
        m = re.search(r"U = \[([^\]]*)\]", res["message"]) if res["error"] == "GasFieldError" else None
        if m:   # the refused frame never reaches the particles (nor the probe)
            p["u_gas_max"] = max(p.get("u_gas_max", 0.0), float(np.linalg.norm(np.array(m.group(1).split(), float))))
        bad = "bed set in motion" if p.get("v_max", 0) > 0.05 else ""
        extra = (f"CFD step {k * 1e-5:g} s; eps change per step up to {p.get('eps_change', 0):.2g}; "
                 f"gas up to {p.get('u_gas_max', 0):.3g} m/s, particles up to {p.get('v_max', 0):.2g} m/s; "
                 f"exchange mismatch momentum {_pct(p.get('momentum_mismatch'))}")
        warn = [w for w in res["runtime_warnings"]]
        if warn:
            extra += "; warns: " + " / ".join(_short_warning(w) for w in warn)
        rec = make_record(group, f"coupling_interval {k}, smoothing_time {tau:g} s", res, guard_of,
                          extra=extra, inaccurate=bad)
        rec.update(x=(k, tau), probe=p, runtime_warnings=res["runtime_warnings"])
        out.append(rec)
        log(f"  {group} | {rec['setting']}: {res['seconds']:.1f} s {rec['outcome']} {rec['guard']} {extra} "
            f"{rec['message'][:200]}")
    return out


def _short_warning(w):
    if "is clipped" in w:
        return "eps clipped"
    if "changes by" in w:
        return "eps jump"
    if "gas speed" in w:
        return "gas > Mach 0.3"
    return w[:40]


def cluster_sweep(quick, log, guard_of, probe, x, L):
    """A dense cluster (the settled bed, raised by 25 mm) thrown down at v through 2 mm cells,
    divided model, 100 DEM steps per CFD step: eps of a cell jumps from 1 to ~0.45 when the
    cluster front passes (particle Courant number v dt_cfd / dx)."""
    out = []
    group = "coupled: dense cluster thrown down at v (divided, 2 mm cells, CFD step 1e-3 s)"
    xx = x.copy()
    xx[:, 2] += 0.025
    for v in ([20.0] if quick else [0.5, 2.0, 5.0, 20.0]):
        case = write_case(WORK / "case", L=L, H=0.05, nxy=10, nz=25, positions=xx,
                          velocities=np.tile([0.0, 0.0, -v], (len(xx), 1)), interval=100, n_steps=2, u_in=0.0,
                          void_fraction="divided", force=True)
        res = run_one(case, WORK / "out", probe)
        p = res["probe"]
        extra = (f"particle Courant {v * 1e-3 / 2e-3:g}; eps change per step up to {p.get('eps_change', 0):.2g}; "
                 f"gas up to {p.get('u_gas_max', 0):.3g} m/s, particles up to {p.get('v_max', 0):.2g} m/s")
        rec = make_record(group, f"v = {v:g} m/s", res, guard_of, extra=extra)
        rec.update(x=v, probe=p, runtime_warnings=res["runtime_warnings"])
        out.append(rec)
        log(f"  {group} | {rec['setting']}: {res['seconds']:.1f} s {rec['outcome']} {rec['guard']} {extra} "
            f"{rec['message'][:200]}")
    return out


def relaxation_sweep(quick, log, guard_of, probe, x, L):
    """Coupling step against the drag relaxation time m/beta: light fine beads (0.1 mm,
    250 kg/m3, E = 1e5 Pa, DEM step 3e-6 s), a packed bed (the settled bed scaled by 1/20)
    and a dilute lattice falling in still air, 8 coupling steps."""
    out = []
    s = 0.05
    d = D * s
    g = np.arange(3) * (L * s / 3) + L * s / 6
    X, Y, Z = np.meshgrid(g, g, np.arange(5) * (L * s / 3) + L * s / 6, indexing="ij")
    dilute = np.c_[X.ravel(), Y.ravel(), Z.ravel()]
    specs = [("packed", 3000), ("dilute", 10000)] if quick else \
        [("packed", 100), ("packed", 1000), ("packed", 3000), ("dilute", 300), ("dilute", 3000), ("dilute", 10000)]
    for kind, k in specs:
        group = f"coupled: coupling step / drag relaxation time, 0.1 mm beads, {kind}"
        if kind == "packed":
            case = write_case(WORK / "case", L=L * s, H=2e-3, nxy=3, nz=6, positions=x * s, diameter=d,
                              density=250.0, youngs=1e5, dt_dem=3e-6, interval=k, n_steps=8, u_in=5e-4,
                              force=True)
        else:
            case = write_case(WORK / "case", L=L * s, H=4e-3, nxy=3, nz=12, positions=dilute, diameter=d,
                              density=250.0, youngs=1e5, dt_dem=3e-6, interval=k, n_steps=8, u_in=0.0,
                              force=True)
        res = run_one(case, WORK / "out", probe)
        p = res["probe"]
        ratio = re.search(r"coupling_over_relaxation\s+([0-9.eE+-]+)", res["log"])
        ratio = float(ratio.group(1)) if ratio else float("nan")
        bad = ""
        if kind == "dilute" and p.get("v_max", 0) > 0.1:
            bad = "particles faster than their terminal velocity (0.075 m/s)"
        extra = f"CFD step / (m/beta) = {ratio:.3g} (check); particles up to {p.get('v_max', 0):.2g} m/s"
        rec = make_record(group, f"CFD step {k * 3e-6:g} s", res, guard_of, extra=extra, inaccurate=bad)
        rec.update(x=(kind, ratio), probe=p)
        out.append(rec)
        log(f"  {group} | {rec['setting']}: {res['seconds']:.1f} s {rec['outcome']} {rec['guard']} {extra} "
            f"{rec['message'][:200]}")
    return out


SWEEPS = {"coupled_size": size_sweep, "coupled_eps_min": eps_min_sweep, "coupled_teleport": teleport_sweep,
          "coupled_cluster": cluster_sweep, "coupled_relaxation": relaxation_sweep}


def coupled_sweeps(quick, log, guard_of, only=None):
    """All coupled sweeps; returns the records."""
    x, L = bed_packing(log=log)
    probe = Probe()
    probe.install()
    recs = []
    try:
        for name, fn in SWEEPS.items():
            if only and name not in only:
                continue
            t0 = time.perf_counter()
            log(f"[{name}]")
            recs += fn(quick, log, guard_of, probe, x, L)
            log(f"[{name}] {time.perf_counter() - t0:.1f} s")
    finally:
        probe.uninstall()
    return recs
