"""Coupled (CFD-DEM) cases of the work-precision suite: each runs thermoDemFoam + the DEM
through ``coupling.run.run_case`` on a modified copy of a case of openfoam_cases/.

* single particle cooled by a gas stream: lumped analytic solution with Ranz-Marshall,
  swept over the coupling (= thermal) step and the integrator;
* packed bed heated by gas: Schumann (1929), swept over the CFD step, the cell size and
  the void fraction model;
* bubbling fluidized bed: mean particle temperature history against a fine-step,
  fine-coupling run, swept over the coupling interval.

Wall time = the coupled loop of run_case without its output phase (solver start-up, mesh
reading and the DEM kernels' compilation happen before the loop's clock; the Numba cache
is filled by scripts/setup.sh). Figures: docs/benchmarks/accuracy.md, section "Work-precision (DEM and thermal)".
"""
from __future__ import annotations

import math
import re
import tempfile
import time
import tomllib
from pathlib import Path

import numpy as np



# ----------------------------------------------------------------------------- case editing
def copy_case(name: str, dest: Path) -> Path:
    from coupling import foam_case as fc
    return fc.copy_template(name, dest, overwrite=True)


def set_toml(path: Path, section: str, **entries):
    """Replace/add scalar keys of one [section] of a TOML file (text edit, comments kept)."""
    text = path.read_text()
    head = f"[{section}]\n"
    start = text.index(head) + len(head)
    m = re.search(r"^\[", text[start:], re.M)
    end = start + m.start() if m else len(text)
    body = text[start:end]
    for k, v in entries.items():
        val = f'"{v}"' if isinstance(v, str) else ("true" if v is True else "false" if v is False else repr(v))
        pat = re.compile(rf"^{k}\s*=.*$", re.M)
        body = pat.sub(f"{k} = {val}", body) if pat.search(body) else f"{k} = {val}\n" + body
    path.write_text(text[:start] + body + text[end:])


def set_control(case: Path, **entries):
    from coupling import foam_case as fc
    fc.set_entries(case / "system" / "controlDict", entries)


def set_cells_z(case: Path, nz: int):
    f = case / "system" / "blockMeshDict"
    f.write_text(re.sub(r"hex \(0 1 2 3 4 5 6 7\) \((\d+) (\d+) (\d+)\)",
                        lambda m: f"hex (0 1 2 3 4 5 6 7) ({m.group(1)} {m.group(2)} {nz})", f.read_text()))


def run(case: Path, out: Path, end_time: float):
    """Coupled run; returns (summary, coupling.csv as a structured array, loop wall seconds)."""
    from coupling.run import run_case
    t0 = time.perf_counter()
    s = run_case(case, out, end_time=end_time, quiet=True, overwrite=True)  # replaces the previous sweep point
    whole = time.perf_counter() - t0
    d = np.atleast_1d(np.genfromtxt(Path(s["out"]) / "coupling.csv", delimiter=",", names=True))
    loop = float(s["loop"]) - float(s["phases"].get("output", 0.0))   # without output writing
    return s, d, loop, whole


# ----------------------------------------------------------------------------- single particle
RHO, MU, CP, K = 1.2, 1.8e-5, 1005.0, 0.0262


def lumped_ranz_marshall(t, T0=373.15, Tg=298.15, u=6.0, d=3.6e-3, rho_p=8850.0, cp_p=55.0):
    """Lumped cooling with the Ranz-Marshall (1952) Nusselt number, Nu = 2 + 0.6 Re^1/2 Pr^1/3."""
    re_ = RHO * u * d / MU
    pr = MU * CP / K
    nu = 2.0 + 0.6 * math.sqrt(re_) * pr ** (1.0 / 3.0)
    hA = math.pi * d * K * nu
    C = rho_p * math.pi / 6.0 * d ** 3 * cp_p
    return Tg + (T0 - Tg) * np.exp(-hA / C * np.asarray(t)), C / hA


def single_particle_coupled(quick, work, log=print):
    """openfoam_cases/single_particle_heating: one fixed sphere (tau = 1.81 s) cooled by a
    6 m/s, 298.15 K air stream, 2 s; CFD step = coupling step = thermal step swept with the
    integrators (auto: TR-BDF2 for this frozen particle on one process); error =
    max |T - T_lumped| / (T0 - Tg) over the run."""
    dts = [2.5e-4, 5e-4, 1e-3, 2e-3, 5e-3, 1e-2] if not quick else [5e-4, 1e-3, 5e-3]
    end = 2.0
    rows = []
    _, tau = lumped_ranz_marshall(0.0)
    for integ in ("euler", "exponential", "auto"):
        for dt in dts:
            case = copy_case("single_particle_heating", work / "sp_case")
            set_toml(case / "dem.toml", "simulation", time_step=dt, output_interval=max(dt, 0.05))
            set_toml(case / "dem.toml", "thermal", time_step=dt, integrator=integ)
            set_toml(case / "coupling.toml", "coupling", coupling_interval=1, force=True,
                     output_interval=max(dt, 0.05))
            set_control(case, deltaT=dt, writeInterval=max(1, round(1.0 / dt)))
            try:
                s, d, loop, whole = run(case, work / "sp_out", end)
            except Exception as exc:  # noqa: BLE001
                log(f"    {integ} dt={dt:g}: {type(exc).__name__}: {str(exc)[:200]}")
                rows.append(dict(integrator=integ, dt=dt, setting=f"dt = {dt:g} s", steps=0, wall=math.nan,
                                 err=math.inf))
                continue
            ref, _ = lumped_ranz_marshall(d["time"])
            err = float(np.max(np.abs(d["T_particles"] - ref)) / 75.0)
            rows.append(dict(integrator=integ, dt=dt, setting=f"dt = {dt:g} s", steps=int(d["step"][-1]),
                             wall=loop, err=err, whole=whole))
    return dict(key="single_particle_coupled", title="One particle cooled by a gas stream (coupled, lumped "
                "Ranz-Marshall)",
                what=f"openfoam_cases/single_particle_heating (thermoDemFoam + DEM, socket): a fixed sphere of "
                     f"3.6 mm at 373.15 K in 6 m/s air at 298.15 K (Re = 1440, time constant {tau:.2f} s), 2 s; "
                     f"coupling interval 1 (CFD step = thermal step = dt; `coupling.force = true` above the gas "
                     f"CFL limit); error = max |T - T_lumped| / (T0 - Tg) over the written times; wall = the "
                     f"coupled loop (gas solve included)",
                rows=rows, series="integrator", default_label="auto (TR-BDF2 for a frozen particle)",
                default_rows=[r for r in rows if r["integrator"] == "auto"], particles=1,
                extra=dict(tau=tau))


# ----------------------------------------------------------------------------- Schumann
def _schumann_errors(out: Path, dt: float):
    """Max gas error over the bed cells and written times, and the solid error of every
    particle at the end, both in units of Tin - T0 (Schumann 1929 with the run's h a)."""
    import tomllib
    from benchmarks.schumann_packed_bed import (BED_HEIGHT, CP as CPG, RHO as RHOG, T0, TIN, U_S,
                                                ranz_marshall_ha, schumann)
    from coupling import foam_case as fc
    C = fc.read_cell_centres(out)
    n = len(C)
    z = C[:, 2]
    bed = z < BED_HEIGHT
    mat = tomllib.loads((out / "dem.toml").read_text())["materials"][0]
    rho_s_cs = float(mat["density"]) * float(mat["heat_capacity"])
    eps = 1 - math.pi / 6
    from dem.final import read as read_final   # an MPI run's final.npz: a manifest and its pieces
    fin = read_final(out / "final.npz")
    ha = ranz_marshall_ha(eps)   # h a of the bed, as the DEM computes it
    tau_s = (1 - eps) * rho_s_cs / ha
    err_g = 0.0
    times = []
    for dd in out.iterdir():
        try:
            t = float(dd.name)
        except ValueError:
            continue
        if t <= 0 or not (dd / "T").is_file():
            continue
        times.append(t)
        T = fc.read_internal_field(dd / "T", n)[bed]
        x = z[bed]
        tg, _ = schumann(ha * x / (RHOG * CPG * U_S), (t - x * eps / U_S) / tau_s)
        err_g = max(err_g, float(np.max(np.abs((T - T0) / (TIN - T0) - tg))))
    xp = fin["position"][:, 2]
    tend = max(times)
    _, ts = schumann(ha * xp / (RHOG * CPG * U_S), (tend - xp * eps / U_S) / tau_s)
    err_s = float(np.max(np.abs((fin["temperature"] - T0) / (TIN - T0) - ts)))
    return err_g, err_s


def schumann_coupled(quick, work, log=print):
    """openfoam_cases/packed_bed_heating against Schumann: CFD step x cell size x void fraction."""
    combos = []
    for vf in ("centre", "divided", "smoothed"):
        for cell_mm in (2, 4, 8):
            if quick and cell_mm == 8:
                continue
            combos.append((vf, cell_mm, 1e-3))
    for dt in ((2e-3, 5e-3, 0.01) if not quick else (5e-3,)):
        combos.append(("centre", 4, dt))
    combos.append(("centre", 4, 5e-4))
    rows = []
    end = 1.0
    for vf, cell_mm, dt in combos:
        case = copy_case("packed_bed_heating", work / "pb_case")
        set_toml(case / "dem.toml", "simulation", time_step=dt)
        set_toml(case / "dem.toml", "thermal", time_step=dt)
        set_toml(case / "coupling.toml", "coupling", void_fraction=vf, force=True, output_interval=0.1)
        set_control(case, deltaT=dt, writeInterval=max(1, round(0.1 / dt)))
        set_cells_z(case, int(round(120 / cell_mm)))
        label = f"{vf}, {cell_mm} mm cells"
        try:
            s, d, loop, whole = run(case, work / "pb_out", end)
            eg, es = _schumann_errors(Path(s["out"]), dt)
        except Exception as exc:  # noqa: BLE001
            log(f"    {label} dt={dt:g}: {type(exc).__name__}: {str(exc)[:200]}")
            rows.append(dict(series=f"{vf}: cells 2/4/8 mm (dt = 1 ms)" if dt == 1e-3 else "centre, 4 mm: CFD step",
                             void_fraction=vf, cell=cell_mm, dt=dt, setting=f"dt = {dt:g} s", steps=0,
                             wall=math.nan, err=math.inf))
            continue
        series = f"{vf}: cells 2/4/8 mm (dt = 1 ms)" if dt == 1e-3 else "centre, 4 mm: CFD step"
        rows.append(dict(series=series, void_fraction=vf, cell=cell_mm, dt=dt,
                         setting=f"{vf}, {cell_mm} mm, dt = {dt * 1e3:g} ms", steps=int(d["step"][-1]),
                         wall=loop, err=max(eg, es), err_g=eg, err_s=es, whole=whole))
    return dict(key="schumann", title="Packed bed heated by gas (coupled) against Schumann (1929)",
                what="openfoam_cases/packed_bed_heating: 540 held spheres of 4 mm (simple-cubic lattice, "
                     "eps = 0.476, 0.06 m) heated by 373.15 K gas at 0.5 m/s superficial, 1 s; gas temperature of "
                     "every bed cell at every 0.1 s and every particle temperature at the end against Schumann's "
                     "solution; error = max of both in units of Tin - T0. Swept: CFD step (= thermal step, "
                     "interval 1), cell size along the flow (2, 4, 8 mm = 0.5, 1, 2 diameters) and the void "
                     "fraction model (`coupling.force = true` where a check warns)",
                rows=rows, series="series", default_label="centre, 4 mm cells (the case)",
                default_rows=[r for r in rows if r["void_fraction"] == "centre" and r["cell"] == 4],
                particles=540)


# ----------------------------------------------------------------------------- bubbling bed
def bubbling_bed(quick, work, log=print):
    """openfoam_cases/fluidized_bed_heating (3,000 particles, 0.2 s): mean particle temperature
    history against a fine-step (DEM dt / 2), fine-coupling (5e-5 s CFD step) run."""
    end = 0.1 if quick else 0.2
    k_case = tomllib.loads((Path(__file__).resolve().parents[2] / "openfoam_cases" / "fluidized_bed_heating"
                            / "coupling.toml").read_text())["coupling"]["coupling_interval"]

    def one(dt, k, tag):
        case = copy_case("fluidized_bed_heating", work / "fb_case")
        set_toml(case / "dem.toml", "simulation", time_step=dt)
        set_toml(case / "coupling.toml", "coupling", coupling_interval=k, force=True, output_interval=0.01)
        # the end time: run() passes it as --end-time (a case has one end time, controlDict's)
        cfd = k * dt
        set_control(case, deltaT=cfd, writeInterval=max(1, round(0.05 / cfd)))
        s, d, loop, whole = run(case, work / f"fb_out_{tag}", end)
        return d, loop, whole

    t0 = time.perf_counter()
    dref, ref_loop, _ = one(5e-6, 10, "ref")
    log(f"    reference run {time.perf_counter() - t0:.1f} s")
    rise = float(dref["T_particles"][-1] - dref["T_particles"][0])
    rows = []
    ks = [10, 25, 50, 100, 200] if not quick else [25, 100, 200]
    for k in ks:
        try:
            d, loop, whole = one(1e-5, k, f"k{k}")
        except Exception as exc:  # noqa: BLE001
            log(f"    interval {k}: {type(exc).__name__}: {str(exc)[:200]}")
            rows.append(dict(series="DEM dt = 1e-5 s", k=k, setting=f"interval {k}", steps=0, wall=math.nan,
                             err=math.inf))
            continue
        tr = np.interp(d["time"], dref["time"], dref["T_particles"])
        err = float(np.max(np.abs(d["T_particles"] - tr)) / rise)
        rows.append(dict(series="DEM dt = 1e-5 s", k=k, setting=f"interval {k} (CFD dt = {k * 1e-5 * 1e3:g} ms)",
                         steps=int(d["step"][-1]), wall=loop, err=err, whole=whole,
                         rise=float(d["T_particles"][-1] - d["T_particles"][0])))
    return dict(key="bubbling_bed", title="Bubbling fluidized bed (coupled): mean particle temperature",
                what=f"openfoam_cases/fluidized_bed_heating: 3,000 glass beads of 2 mm fluidized and heated by "
                     f"373.15 K air at 2 m/s, {end:g} s; mean particle temperature every 10 ms against a run with "
                     f"half the DEM step (5e-6 s) and a 5e-5 s CFD step (10 DEM steps per CFD step; rise "
                     f"{rise:.3f} K, {ref_loop:.1f} s of coupled loop); error = max |T_mean - T_mean,ref| / rise. "
                     f"Swept: DEM steps per CFD step (coupling interval) at the case's DEM step 1e-5 s; the bed "
                     f"is chaotic, so part of the difference is trajectory divergence, not discretisation error",
                rows=rows, series="series", default_label=f"interval {k_case} (the case)",
                default_rows=[r for r in rows if r["k"] == k_case], particles=3000,
                extra=dict(rise=rise, ref_loop=ref_loop))


def workdir():
    return Path(tempfile.mkdtemp(prefix="thermodem_acc_"))
