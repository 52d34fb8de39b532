"""A coupled CFD-DEM case directory and its validation.

Layout::

    CASE/
      0/ constant/ system/     OpenFOAM case (thermoDemFoam), ASCII
      dem.toml                 DEM scene (dem.Simulation.from_file)
      coupling.toml            [coupling] settings (below)

``coupling.toml``::

    [coupling]
    transport = "socket"          # file | socket
    coupling_interval = 10        # DEM steps per CFD step; CFD deltaT = interval * DEM dt
    drag = "di_felice_1994"       # di_felice_1994 | gidaspow_1994 | beetstra_2007 | huilin_gidaspow_2003
    drag_integration = "implicit_bed"  # implicit_bed | implicit_particle | explicit (docs/models.md)
    void_fraction = "divided"     # centre | divided | smoothed
    interpolation = "cell"        # cell | idw | linear
    eps_min = 0.3                 # lower bound of the DEM void fraction
    smoothing_time = 0.0          # s, time relaxation of eps / Ksl (0 = off)
    gas_processes = 1             # MPI ranks of thermoDemFoam (decomposePar when > 1)
    timeout = 60                  # s waiting for one frame
    send_velocity = "cell"        # cell | flux (system/couplingDict sendVelocity)
    heat = true                   # exchange heat (needs [thermal] convection in dem.toml)
    end_time = 0.5                # s (default: endTime of system/controlDict)
    output_interval = 0.01        # s, DEM output (default: dem.toml simulation.output_interval)
    force = false                 # run despite failed checks (reported as problems)
    solver_nice = 0               # nice level of the solver (serial runs; 0 = unchanged)

Checks (``check_coupled_case``), in the spirit of CFDEMcoupling's: CFD deltaT =
coupling_interval x DEM dt; gas CFL; particle Courant number (particle displacement per
coupling step / cell size); coupling step / the relaxation time of the semi-implicit drag m/beta_imp (at the initial
void fraction at the particle; a warning only: the scheme is stable at any step, see
docs/models.md "Semi-implicit drag"); cell size / particle diameter (warning under 3, a
stronger warning under 1); the initial void fraction clipped at eps_min (warning, a
problem when more than 5 % of the particle volume is clipped); gas properties of dem.toml
[gas] equal to constant/transportProperties; particles inside the mesh; plus the DEM's own
time-step checks (``Simulation.check``) and ``foam_case.check_case``.
"""
from __future__ import annotations

import math
import os
import shutil
import tempfile
import tomllib
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from . import foam_case as fc
from .drag import DRAG_MODELS, drag_coefficients, drag_model_id
from .interface import GasProperties
from .interpolate import METHODS as INTERP_METHODS
from .voidfraction import MODELS as VF_MODELS

__all__ = ["CaseConfigError", "CouplingConfig", "CoupledCase", "load_case", "check_coupled_case",
           "gas_properties", "format_report"]

# limits of the checks: (warn above, error above)
PARTICLE_COURANT = (0.1, 0.5)
GAS_CFL = (0.5, 1.0)
RELAXATION_RATIO = 1.0           # CFD deltaT / (m / beta_imp): a warning (accuracy of transients)
CELL_DIAMETERS = 3.0             # warn when the cell size is below this many diameters
CLIPPED_VOLUME = 0.05            # refuse when eps_min clipping hides more of the particle volume


class CaseConfigError(fc.CaseError):
    """Invalid coupled case; the message names the file (and the key)."""

    def __init__(self, path, message: str, key: str | None = None):
        super().__init__(path, f"{key}: {message}" if key else message)
        self.key = key


@dataclass
class CouplingConfig:
    transport: str = "socket"
    coupling_interval: int = 1
    drag: str = "di_felice_1994"
    drag_integration: str = "implicit_bed"
    void_fraction: str = "divided"
    interpolation: str = "cell"
    eps_min: float = 0.3
    smoothing_time: float = 0.0
    gas_processes: int = 1
    timeout: float = 60.0
    send_velocity: str = "cell"
    heat: bool = True
    end_time: float | None = None
    output_interval: float | None = None
    force: bool = False
    n_satellites: int = 29
    solver_nice: int = 0



_KEYS = {
    "transport": (str, ("file", "socket")),
    "coupling_interval": (int, (1, None)),
    "drag": (str, tuple(DRAG_MODELS)),
    "drag_integration": (str, ("implicit_bed", "implicit_particle", "explicit")),
    "void_fraction": (str, VF_MODELS),
    "interpolation": (str, INTERP_METHODS),
    "eps_min": (float, (0.01, 0.99)),
    "smoothing_time": (float, (0.0, None)),
    "gas_processes": (int, (1, 256)),
    "timeout": (float, (0.1, None)),
    "send_velocity": (str, ("cell", "flux")),
    "heat": (bool, None),
    "end_time": (float, (0.0, None)),
    "output_interval": (float, (0.0, None)),
    "force": (bool, None),
    "n_satellites": (int, (1, 10000)),
    "solver_nice": (int, (0, 19)),
}


def load_config(path: Path) -> CouplingConfig:
    path = Path(path)
    if not path.exists():
        raise CaseConfigError(path, "missing (a coupled case needs coupling.toml with a [coupling] table)")
    if path.is_dir():
        raise CaseConfigError(path, "is a folder; coupling.toml must be a TOML file with a [coupling] table")
    try:
        raw = path.read_bytes()
    except OSError as e:
        raise CaseConfigError(path, f"cannot read: {e.strerror or e}") from None
    try:
        text = raw.decode("utf-8").removeprefix("\ufeff")
    except UnicodeDecodeError as e:
        line = raw[:e.start].count(b"\n") + 1
        raise CaseConfigError(path, f"line {line}: not UTF-8 text (byte 0x{raw[e.start]:02x}); save it as "
                                    "UTF-8 TOML") from None
    try:
        data = tomllib.loads(text)
    except tomllib.TOMLDecodeError as e:
        raise CaseConfigError(path, f"not valid TOML: {e}") from None
    extra = sorted(set(data) - {"coupling"})
    if extra:
        raise CaseConfigError(path, f"unknown table(s) {extra}; only [coupling] is allowed")
    c = data.get("coupling")
    if not isinstance(c, dict):
        raise CaseConfigError(path, "missing [coupling] table")
    cfg = CouplingConfig()
    for key, val in c.items():
        if key not in _KEYS:
            raise CaseConfigError(path, f"unknown key; valid keys: {', '.join(sorted(_KEYS))}",
                                  f"coupling.{key}")
        typ, allowed = _KEYS[key]
        k = f"coupling.{key}"
        if typ is bool:
            if not isinstance(val, bool):
                raise CaseConfigError(path, f"must be true or false, got {val!r}", k)
        elif typ is str:
            if not isinstance(val, str) or val not in allowed:
                raise CaseConfigError(path, f"{val!r} is not one of {', '.join(allowed)}", k)
        else:
            if isinstance(val, bool) or not isinstance(val, (int, float)) or \
                    (typ is int and not isinstance(val, int)):
                raise CaseConfigError(path, f"must be {'an integer' if typ is int else 'a number'}, got {val!r}", k)
            lo, hi = allowed
            if not math.isfinite(val):
                raise CaseConfigError(path, f"must be a finite number, got {val!r}", k)
            if (lo is not None and val < lo) or (hi is not None and val > hi):
                rng = f">= {lo}" + (f" and <= {hi}" if hi is not None else "")
                raise CaseConfigError(path, f"must be {rng}, got {val!r}", k)
            val = typ(val)
        setattr(cfg, key, val)
    if cfg.output_interval == 0.0:
        raise CaseConfigError(path, "must be > 0", "coupling.output_interval")
    return cfg


def gas_properties(case: Path) -> GasProperties:
    tp_path = Path(case) / "constant" / "transportProperties"
    tp = fc.parse_foam_dict(tp_path)
    nu, rho = fc.read_float(tp_path, tp, "nu"), fc.read_float(tp_path, tp, "rho")
    cp = fc.read_float(tp_path, tp, "cp") if "cp" in tp else 1005.0
    if "k" in tp:
        k = fc.read_float(tp_path, tp, "k")
    else:
        k = rho * nu * cp / fc.read_float(tp_path, tp, "Pr")
    return GasProperties(rho=rho, nu=nu, cp=cp, k=k)


def model_type(case: Path) -> tuple[str, float]:
    p = Path(case) / "constant" / "couplingProperties"
    if not p.exists():
        return "A", 0.05
    d = fc.parse_foam_dict(p)
    return d.get("modelType", "A"), float(d.get("epsMin", "0.05").split()[-1])


def control(case: Path) -> dict:
    p = Path(case) / "system" / "controlDict"
    d = fc.parse_foam_dict(p)
    out = {}
    for key in ("deltaT", "endTime", "writeInterval"):
        out[key] = fc.read_float(p, d, key)
    out["startFrom"] = d.get("startFrom", "latestTime")
    out["writeControl"] = d.get("writeControl", "timeStep")
    return out


@dataclass
class CoupledCase:
    dir: Path
    config: CouplingConfig
    dem_file: Path
    config_file: Path
    gas: GasProperties
    model_type: str
    control: dict
    sim: object = None
    report: dict = field(default_factory=dict)

    @property
    def dt_cfd(self) -> float:
        return self.control["deltaT"]

    @property
    def end_time(self) -> float:
        return self.config.end_time if self.config.end_time is not None else self.control["endTime"]

    @property
    def end_time_source(self) -> str:
        """Where the end time comes from (for messages)."""
        if self.config.end_time is not None:
            return f"{self.config_file} (end_time)"
        return f"{self.dir / 'system' / 'controlDict'} (endTime)"


def load_case(case_dir, *, build_sim: bool = True) -> CoupledCase:
    """Read and validate the files of a coupled case (no mesh needed)."""
    import dem
    from dem.scene import SceneError
    case_dir = Path(case_dir).resolve()
    if case_dir.exists() and not case_dir.is_dir():
        raise CaseConfigError(case_dir, "is a file; give the case folder (0/, constant/, system/, dem.toml, "
                                        "coupling.toml)")
    if not case_dir.is_dir():
        raise CaseConfigError(case_dir, "case directory does not exist")
    cfg_file = case_dir / "coupling.toml"
    cfg = load_config(cfg_file)
    dem_file = case_dir / "dem.toml"
    if not dem_file.exists():
        raise CaseConfigError(dem_file, "missing (the DEM scene of the coupled case)")
    fc.check_case(case_dir, coupled=False)
    gas = gas_properties(case_dir)
    mt, _ = model_type(case_dir)
    ctl = control(case_dir)
    sim = None
    if build_sim:
        try:
            sim = dem.Simulation.from_file(str(dem_file))  # memory checked before allocating
        except SceneError as e:
            raise CaseConfigError(dem_file, str(e).split(": ", 1)[-1]) from None
    return CoupledCase(case_dir, cfg, dem_file, cfg_file, gas, mt, ctl, sim)


# --------------------------------------------------------------------------- checks

def _max_speed_of_field(path: Path, n_cells: int) -> float:
    """Largest |U| in the internal field and the 'value uniform (...)' boundary entries."""
    u = fc.read_internal_field(path, n_cells)
    vmax = float(np.sqrt((u * u).sum(axis=1)).max()) if u.size else 0.0
    import re
    for m in re.finditer(r"value\s+uniform\s+\(([^)]*)\)", fc.strip_comments(path.read_text())):
        v = np.array(m.group(1).split(), float)
        vmax = max(vmax, float(np.linalg.norm(v)))
    return vmax


def check_coupled_case(case: CoupledCase, mesh, *, eps0: np.ndarray | None = None,
                       clip: dict | None = None) -> dict:
    """Run the coupling checks on a loaded case and its mesh. Returns a report dict with
    'values', 'warnings', 'problems'. Raises :class:`CaseConfigError` on the first hard
    error (inconsistent input); failed limits go to 'problems' (the caller refuses to run
    unless coupling.force = true). ``eps0``: initial void fraction (after clipping);
    ``clip``: its clipping (CouplingInterface.clip)."""
    cfg, sim, gas = case.config, case.sim, case.gas
    vals, warnings, problems = {}, [], []
    cf = case.config_file
    ctl_path = case.dir / "system" / "controlDict"
    # --- time steps
    dt_dem = sim.dt
    dt_cfd = case.dt_cfd
    vals["dem_dt"] = dt_dem
    vals["cfd_dt"] = dt_cfd
    vals["coupling_interval"] = cfg.coupling_interval
    if not math.isclose(cfg.coupling_interval * dt_dem, dt_cfd, rel_tol=1e-9):
        raise CaseConfigError(
            cf, f"{cfg.coupling_interval} x DEM time_step {dt_dem:g} s = {cfg.coupling_interval * dt_dem:g} s "
                f"but {ctl_path} has deltaT {dt_cfd:g} s; set coupling_interval = "
                f"{dt_cfd / dt_dem:.6g} or change deltaT / the DEM time_step", "coupling.coupling_interval")
    if case.model_type not in ("A", "B"):
        raise CaseConfigError(case.dir / "constant/couplingProperties", f"modelType {case.model_type!r} unknown")
    # --- gas properties: dem.toml [gas] must match transportProperties
    thermal = sim.thermal
    if cfg.heat and thermal is None:
        warnings.append("dem.toml has no [thermal] section: no heat exchange (coupling.heat ignored)")
    if thermal is not None and cfg.heat:
        from dem.thermal import registry as R
        g = thermal.gas
        if thermal.cfg["convection"] == "none":
            raise CaseConfigError(case.dem_file, "thermal.convection is 'none': the gas-particle heat "
                                  "exchange needs a convection model (e.g. \"ranz_marshall\") or set "
                                  "coupling.heat = false in coupling.toml", "thermal.convection")
        tp = case.dir / "constant" / "transportProperties"
        pairs = (("density", R.RHO_F, gas.rho, "rho"), ("viscosity", R.MU_F, gas.mu, "rho*nu"),
                 ("conductivity", R.KF, gas.k, "k"))
        for key, idx, val, name in pairs:
            if not math.isclose(float(g[idx]), val, rel_tol=1e-6):
                raise CaseConfigError(case.dem_file, f"{g[idx]:.6g} differs from {name} = {val:.6g} in {tp}; "
                                      "use the same gas properties on both sides", f"gas.{key}")
        pr = gas.mu * gas.cp / gas.k
        if not math.isclose(float(g[R.PR]), pr, rel_tol=1e-6):
            raise CaseConfigError(case.dem_file, f"Prandtl number {g[R.PR]:.6g} differs from mu cp / k = "
                                  f"{pr:.6g} of {tp} (heat_capacity must be cp = {gas.cp:g})", "gas.heat_capacity")
    # --- mesh geometry
    V = mesh.cell_volumes
    dx_min = float(np.cbrt(V.min()))
    h = mesh.cell_vhi - mesh.cell_vlo
    dx_edge = float(h.min())          # smallest cell edge (Courant numbers)
    st = sim.state
    n = st.n_owned
    d = 2 * st.radius[:n]
    vals["particles"] = n
    vals["cells"] = mesh.n_cells
    vals["cell_size_min"] = dx_min
    vals["cell_over_diameter"] = dx_min / float(d.max())
    if dx_min < d.max() * (1 - 1e-9):
        warnings.append(f"smallest cell {dx_min:.3g} m is {dx_min / d.max():.2f} particle diameters: particles "
                        f"larger than the cells are outside the unresolved model (void fraction clipped at "
                        f"eps_min, drag and heat exchange inconsistent between gas and particles, with every "
                        f"void_fraction model); use cells of at least {CELL_DIAMETERS:g} particle diameters")
    elif dx_min < CELL_DIAMETERS * d.max() * (1 - 1e-9):
        warnings.append(f"smallest cell {dx_min:.3g} m is {dx_min / d.max():.2f} particle diameters "
                        f"(< {CELL_DIAMETERS:g}): void fraction and drag of the unresolved model are "
                        f"inaccurate; use void_fraction = 'divided' or 'smoothed'"
                        + ("" if cfg.void_fraction != "centre" else " (now 'centre')"))
    # --- initial void fraction below eps_min (clipped: solid volume the gas does not see)
    if clip is not None:
        vals["eps_initial_raw_min"] = clip["eps_raw_min"]
        vals["eps_clipped_cells"] = clip["cells"]
        vals["eps_clipped_volume_fraction"] = clip["fraction"]
        if clip["cells"]:
            msg = (f"initial void fraction below coupling.eps_min = {cfg.eps_min:g} in {clip['cells']} cell(s) "
                   f"(lowest 1 - V_solid/V_cell = {clip['eps_raw_min']:.3g}): clipping hides "
                   f"{100 * clip['fraction']:.3g} % of the particle volume from the gas; use cells of at least "
                   f"{CELL_DIAMETERS:g} particle diameters or void_fraction = 'divided' or 'smoothed' (now "
                   f"'{cfg.void_fraction}')")
            (problems if clip["fraction"] > CLIPPED_VOLUME else warnings).append(
                msg + (f" (refused above {100 * CLIPPED_VOLUME:g} %)" if clip["fraction"] > CLIPPED_VOLUME else ""))
    vals["cell_over_particle_volume"] = float(V.min() / ((math.pi / 6) * d.max() ** 3))
    # particles in the mesh
    cells = mesh.locate(st.position[:n])
    out = np.flatnonzero(cells < 0)
    if out.size:
        raise CaseConfigError(case.dem_file, f"{out.size} particle(s) outside the OpenFOAM mesh "
                              f"(first: id {int(st.id[out[0]])} at {st.position[out[0]].tolist()}); mesh "
                              f"bounding box {mesh.bbox_lo.tolist()} .. {mesh.bbox_hi.tolist()}")
    # --- gas CFL (interstitial speed ~ superficial / eps)
    umax = _max_speed_of_field(case.dir / "0" / "U", mesh.n_cells)
    emin = float(eps0.min()) if eps0 is not None else 1.0
    u_int = umax / max(emin, cfg.eps_min)
    cfl = u_int * dt_cfd / dx_edge
    vals["gas_speed_max"] = u_int
    vals["gas_cfl"] = cfl
    if cfl > GAS_CFL[1]:
        problems.append(f"gas CFL {cfl:.3g} > {GAS_CFL[1]} (|U|/eps = {u_int:.3g} m/s, deltaT {dt_cfd:g} s, "
                        f"cell {dx_edge:.3g} m): lower deltaT in system/controlDict (and coupling_interval)")
    elif cfl > GAS_CFL[0]:
        warnings.append(f"gas CFL {cfl:.3g} > {GAS_CFL[0]}")
    # --- particle Courant number: displacement per coupling step / cell size
    vp0 = float(np.sqrt((st.velocity[:n] ** 2).sum(1)).max()) if n else 0.0
    gmag = float(np.linalg.norm(sim.scene.simulation["gravity"]))
    mech = bool(sim.scene.simulation["mechanics"])
    v_char = max(vp0, umax if mech else 0.0, math.sqrt(gmag * dx_min) if mech else 0.0)
    co = v_char * dt_cfd / dx_edge
    vals["particle_speed_char"] = v_char
    vals["particle_courant"] = co
    if co > PARTICLE_COURANT[1]:
        problems.append(f"particle Courant number {co:.3g} > {PARTICLE_COURANT[1]} (speed {v_char:.3g} m/s "
                        f"x coupling step {dt_cfd:g} s / cell {dx_edge:.3g} m): lower deltaT")
    elif co > PARTICLE_COURANT[0]:
        warnings.append(f"particle Courant number {co:.3g} > {PARTICLE_COURANT[0]}")
    # --- coupling step / relaxation time of the drag. The DEM takes the drag semi-implicitly with
    # beta_imp = beta_A / eps^2 (dem.step.half_kick_implicit, coupling.interface._particle_forces):
    # stable and exact at steady state for any coupling step (docs/models.md, "Semi-implicit
    # drag"), but the particles see the gas of the last frame: beyond m/beta_imp the bed's response
    # to a change of the flow lags by a coupling step more than it takes to happen.
    if mech:
        mass = st.mass[:n]
        eps_c = np.ones(n) if eps0 is None else eps0[np.maximum(cells, 0)]
        eps_c = np.clip(eps_c, cfg.eps_min, 1.0)
        ur = np.full(n, max(umax, 1e-3))
        beta = drag_coefficients(drag_model_id(cfg.drag), np.ascontiguousarray(d), eps_c, gas.rho, gas.mu, ur)
        if case.model_type == "B":
            beta = beta / eps_c
        beta_imp = beta / eps_c if case.model_type == "B" else beta / eps_c ** 2
        tau = float((mass / beta).min())
        k = int(np.argmin(mass / beta_imp))
        tau_imp = float(mass[k] / beta_imp[k])
        vals["particle_relaxation_time"] = tau
        vals["coupling_over_relaxation"] = dt_cfd / tau
        vals["bed_relaxation_time"] = tau_imp
        vals["coupling_over_bed_relaxation"] = dt_cfd / tau_imp
        if dt_cfd / tau_imp > RELAXATION_RATIO:
            k_cfd = max(1, math.floor(tau_imp / dt_dem))
            warnings.append(
                f"coupling step {dt_cfd:g} s is {dt_cfd / tau_imp:.3g} x the drag relaxation time of the bed "
                f"m/beta_imp = {tau_imp:.3g} s (void fraction {float(eps_c[k]):.3g}, |u| = {ur[0]:.3g} m/s): "
                f"stable and exact at steady state, but the particles see the gas one coupling step late, "
                f"longer than the bed takes to respond; for transients (fluidization, bubbles) use deltaT <= "
                f"{k_cfd * dt_dem:.3g} s in system/controlDict with coupling_interval = {k_cfd}")
    # --- DEM checks
    from dem.scene import SceneError
    try:
        rep = sim.check()
    except SceneError as e:
        problems.append(f"{case.dem_file}: {str(e).split(': ', 1)[-1]}")
        rep = {}
    for k in ("dt_over_rayleigh", "dt_over_hertz", "thermal_critical_step", "biot_max"):
        if k in rep:
            vals[k] = rep[k]
    warnings += rep.get("warnings", [])
    if cfg.gas_processes > (os.cpu_count() or 1):
        warnings.append(f"gas_processes {cfg.gas_processes} > {os.cpu_count()} cores (oversubscribed)")
    return dict(values=vals, warnings=warnings, problems=problems)


def format_report(case: CoupledCase, rep: dict) -> str:
    lines = [f"coupled case {case.dir}",
             f"  transport {case.config.transport}, drag {case.config.drag}, void fraction "
             f"{case.config.void_fraction}, model {case.model_type}, interpolation {case.config.interpolation}"]
    for k, v in rep["values"].items():
        lines.append(f"  {k:28s} {v:.4g}" if isinstance(v, float) else f"  {k:28s} {v}")
    for w in rep["warnings"]:
        lines.append(f"  WARNING: {w}")
    for p in rep["problems"]:
        lines.append(f"  PROBLEM: {p}")
    lines.append("  verdict: " + ("OK" if not rep["problems"] else
                                  ("problems, running anyway (coupling.force = true)" if case.config.force
                                   else "refused (fix the problems or set coupling.force = true)")))
    return "\n".join(lines)


def mesh_in_tmp(case_dir: Path):
    """blockMesh in a temporary copy of the OpenFOAM part (for `coupling check`).
    Returns (tmpdir, PolyMesh)."""
    from .mesh import read_polymesh
    tmp = Path(tempfile.mkdtemp(prefix="coupling_check_"))
    for sub in ("0", "constant", "system"):
        shutil.copytree(case_dir / sub, tmp / sub)
    if not (tmp / "constant" / "polyMesh" / "owner").exists():
        fc.block_mesh(tmp)
    return tmp, read_polymesh(str(tmp))
