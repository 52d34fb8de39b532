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
    drag_void_fraction = "cell"   # cell | voronoi | kernel: the void fraction each particle's drag sees
    drag_averaging_length = 0.003 # m, support of the kernel method (kernel only; default 3 largest diameters)
    interpolation = "cell"        # cell | idw | linear
    eps_min = 0.3                 # lower bound of the DEM void fraction
    smoothing_time = 0.0          # s, time relaxation of eps / Ksl (0 = off)
    gas_processes = 1             # MPI ranks of thermoDemFoam (decomposePar when > 1)
    timeout = 60                  # s waiting for one frame
    send_velocity = "cell"        # cell | flux (system/couplingDict sendVelocity)
    heat = true                   # exchange heat (needs [thermal] convection in dem.toml)
    end_time = 0.5                # s, optional: must equal endTime of system/controlDict (the case's end time)
    output_interval = 0.01        # s, DEM output (default: dem.toml simulation.output_interval)
    force = false                 # run despite failed checks (reported as problems)
    solver_nice = 0               # nice level of the solver (serial runs; 0 = unchanged)
    torque = "none"               # none | rotational_drag: fluid torque on the particles (docs/models.md)
    lift = "none"                 # none | saffman_mei | magnus: lift force
    virtual_mass = false          # virtual (added) mass force, C_vm = 0.5

``[averaging]`` (optional; coupling.averaging): time-averaged particle fields on the gas mesh,
written by OpenFOAM's fieldAverage into the time folders::

    [averaging]
    start = 0.1                   # s (default 0)
    window = 0.05                 # s, optional (fieldAverage window, approximate)
    fields = ["void_fraction", "particle_velocity", "particle_temperature", "heat_source"]

One end time per case: ``endTime`` of system/controlDict. ``end_time`` of coupling.toml and
``[simulation] end_time`` of dem.toml may be omitted (they take controlDict's) and are refused
by ``load_case`` when they differ from it (``coupling run --end-time`` overrides for one run).

Checks (``check_coupled_case``), in the spirit of CFDEMcoupling's: CFD deltaT =
coupling_interval x DEM dt; gas CFL; particle Courant number (displacement per coupling step /
cell edge, at the speed of what can move the particles: ``_particle_speeds``); coupling step /
the relaxation time of the semi-implicit drag m/beta_imp (at the initial void fraction at the
particle; a warning only: the scheme is stable at any step, docs/models.md "Semi-implicit drag"); the void fraction's averaging length / particle diameter for the case's void-fraction
model (warning under 3, a stronger warning for cells under 1 diameter: ``_cell_size_advice``);
the initial void fraction clipped at eps_min (warning, a problem when more than 5 % of the
particle volume is clipped); the Biot number h (V/A) / k_p from the case's Nusselt correlation
at its gas speed (warning above 0.1: ``_biot_check``); gas properties of dem.toml [gas] equal
to constant/transportProperties; particles inside the mesh; plus the DEM's own time-step checks
(``Simulation.check``) and ``foam_case.check_case``. docs/models.md, "Checks", derives them.
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
from .errors import CaseConfigError  # noqa: F401 - raised here, importable from here
from .drag import DRAG_MODELS, drag_coefficients, drag_model_id
from .forces import LIFT_MODELS, TORQUE_MODELS
from .interface import GasProperties
from .interpolate import METHODS as INTERP_METHODS
from .particle_void import METHODS as DRAG_VOID_METHODS
from .voidfraction import MODELS as VF_MODELS

__all__ = ["CaseConfigError", "CouplingConfig", "CoupledCase", "load_case", "check_coupled_case",
           "gas_properties", "format_report"]

# limits of the checks: (warn above, error above)
PARTICLE_COURANT = (0.1, 0.5)
GAS_CFL = (0.5, 1.0)
RELAXATION_RATIO = 1.0           # CFD deltaT / (m / beta_imp): a warning (accuracy of transients)
CELL_DIAMETERS = 3.0             # warn when the cell size is below this many diameters
CLIPPED_VOLUME = 0.05            # refuse when eps_min clipping hides more of the particle volume


@dataclass
class CouplingConfig:
    transport: str = "socket"
    coupling_interval: int = 1
    drag: str = "di_felice_1994"
    drag_integration: str = "implicit_bed"
    void_fraction: str = "divided"
    drag_void_fraction: str = "cell"
    drag_averaging_length: float | None = None
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
    torque: str = "none"
    lift: str = "none"
    virtual_mass: bool = False
    exchange_host: str = "127.0.0.1"   # where the DEM ranks listen for the gas processors (m2m); "auto": the node's address
    walls: list = field(default_factory=list)   # [[walls]] ties of DEM walls to gas patches (coupling.energy)
    averaging: object = None   # [averaging]: time-averaged fields on the gas mesh (coupling.averaging.AveragingConfig)


_KEYS = {
    "transport": (str, ("file", "socket")),
    "coupling_interval": (int, (1, None)),
    "drag": (str, tuple(DRAG_MODELS)),
    "drag_integration": (str, ("implicit_bed", "implicit_particle", "explicit")),
    "void_fraction": (str, VF_MODELS),
    "drag_void_fraction": (str, DRAG_VOID_METHODS),
    "drag_averaging_length": (float, (0.0, None)),
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
    "torque": (str, tuple(TORQUE_MODELS)),
    "lift": (str, tuple(LIFT_MODELS)),
    "virtual_mass": (bool, None),
    "exchange_host": (str, "an IPv4 address (such as 127.0.0.1, the default: every process on this machine) or "
                           "\"auto\" (each DEM rank its node's address, for gas processes on other nodes)"),
}


def exchange_address(host: str) -> str:
    """The IPv4 address a DEM rank listens on for coupling.exchange_host (``auto``: this
    node's address, as its host name resolves)."""
    import socket
    return socket.gethostbyname(socket.gethostname()) if host == "auto" else host


def _valid_host(val) -> bool:
    import ipaddress
    if val == "auto":
        return True
    try:
        ipaddress.IPv4Address(val)
    except ValueError:
        return False
    return True


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
    extra = sorted(set(data) - {"coupling", "walls", "averaging"})
    if extra:
        raise CaseConfigError(path, f"unknown table(s) {extra}; allowed: [coupling], [[walls]] (a DEM wall "
                                    f"tied to a gas patch) and [averaging] (time-averaged fields on the gas mesh)")
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
        elif typ is str and isinstance(allowed, str):   # a free value, described by ``allowed``
            if not isinstance(val, str) or not _valid_host(val):
                raise CaseConfigError(path, f"{val!r} is not {allowed}", k)
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
    if cfg.drag_averaging_length is not None and cfg.drag_void_fraction != "kernel":
        raise CaseConfigError(path, f"is the support of the kernel method: set drag_void_fraction = \"kernel\" "
                                    f"(now \"{cfg.drag_void_fraction}\"; voronoi averages over its particles' "
                                    f"first shells) or remove it", "coupling.drag_averaging_length")
    if "walls" in data:
        from .energy import parse_ties
        cfg.walls = parse_ties(path, data["walls"])
    if "averaging" in data:
        from .averaging import parse_averaging
        cfg.averaging = parse_averaging(path, data["averaging"])
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
        """The case's one end time: endTime of system/controlDict (dem.toml and coupling.toml
        may repeat it, equal; load_case refuses a disagreement)."""
        return self.control["endTime"]

    @property
    def end_time_source(self) -> str:
        """Where the end time comes from (for messages)."""
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
    end = ctl["endTime"]
    ctl_file = case_dir / "system" / "controlDict"
    if cfg.end_time is not None and not _same_time(cfg.end_time, end):
        raise CaseConfigError(cfg_file, _end_time_conflict(cfg.end_time, "end_time", cfg_file, end, ctl_file),
                              "coupling.end_time")
    sim = None
    if build_sim:
        from dem import scene as scene_mod
        try:
            # without simulation.end_time the scene takes the case's (controlDict endTime)
            scene = scene_mod.load(str(dem_file), end_time=end)
        except SceneError as e:
            raise CaseConfigError(dem_file, str(e).split(": ", 1)[-1]) from None
        cgs = scene_mod.parcel_factors(scene)
        if cgs is not None:
            for key, val in (("torque", cfg.torque), ("lift", cfg.lift)):
                if val != "none":
                    raise CaseConfigError(cfg_file, f"{key} = \"{val}\" with coarse-grained particles "
                                                    f"(dem.toml coarse_graining = {max(scene.group_cg):g}): the fluid "
                                                    f"{key} of a parcel is not derived (its rotation is not its "
                                                    f"real particles'); use {key} = \"none\"", key)
        if scene.end_time_in_file and not _same_time(scene.simulation["end_time"], end):
            raise CaseConfigError(dem_file, _end_time_conflict(scene.simulation["end_time"], "[simulation] end_time",
                                                               dem_file, end, ctl_file), "simulation.end_time")
        from .particle_void import ParticleVoidFraction
        method, ell = cfg.drag_void_fraction, cfg.drag_averaging_length
        scene.ghost_reach = lambda rmax: ParticleVoidFraction.ghost_reach(method, rmax, ell)
        try:
            sim = dem.Simulation(scene)  # memory checked before allocating
        except SceneError as e:
            raise CaseConfigError(dem_file, str(e).split(": ", 1)[-1]) from None
        if ell is not None and ell < 2.0 * sim.world.rmax:
            raise CaseConfigError(cfg_file, f"{ell:g} m is less than the largest particle diameter "
                                            f"{2.0 * sim.world.rmax:.4g} m: a kernel narrower than a particle "
                                            f"measures the particle, not the packing around it; use at least "
                                            f"{2.0 * sim.world.rmax:.4g} m (the default is 3 diameters)",
                                  "coupling.drag_averaging_length")
    if cfg.averaging is not None:
        from .averaging import check_averaging
        heat = cfg.heat and (sim is None or (sim.thermal is not None and sim.thermal.cfg["convection"] != "none"))
        cfg.averaging = check_averaging(cfg_file, cfg.averaging, end=end, dt=ctl["deltaT"], heat=heat)
    case = CoupledCase(case_dir, cfg, dem_file, cfg_file, gas, mt, ctl, sim)
    from .energy import check_tie_names
    check_tie_names(case)
    return case


END_TIME_RTOL = 1e-9


def _same_time(a: float, b: float) -> bool:
    return math.isclose(a, b, rel_tol=END_TIME_RTOL, abs_tol=0.0)


def _end_time_conflict(value: float, key: str, path: Path, end: float, ctl_file: Path) -> str:
    """The message refusing a second end time that disagrees with controlDict's."""
    return (f"{key} = {value:.9g} s disagrees with endTime = {end:.9g} s of {ctl_file}: a coupled case has one "
            f"end time, the endTime of system/controlDict. Remove end_time from {path.name} (it then takes "
            f"controlDict's) or make the two equal; to run one time to another end, give coupling run "
            f"--end-time T")


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


# Random close packing of equal spheres (Scott & Kilgour 1969, J. Phys. D 2, 863: 0.637): the
# densest a settling random packing gets.
RANDOM_CLOSE_PACKING = 0.637
# A packing rests when its particles touch: a mechanically stable packing of frictional spheres
# has a mean coordination number of at least 4 (isostatic limit; Silbert et al. 2002, Phys.
# Rev. E 65, 031304), walls included; without the wall contacts the check counts, 3.
COORDINATION_AT_REST = 3.0
TOUCH_GAP = 1e-3      # touching: centre distance <= (1 + TOUCH_GAP) (R_i + R_j)


def _touches(x, r) -> float:
    """Particle ends of the touching pairs among these particles (2 per pair; walls not
    counted): divided by the particle count, the mean coordination number."""
    from scipy.spatial import cKDTree
    n = len(r)
    if n < 2:
        return 0.0
    pairs = cKDTree(x).query_pairs(2 * float(r.max()) * (1 + TOUCH_GAP), output_type="ndarray")
    if not len(pairs):
        return 0.0
    i, j = pairs[:, 0], pairs[:, 1]
    touch = np.linalg.norm(x[i] - x[j], axis=1) <= (1 + TOUCH_GAP) * (r[i] + r[j])
    return 2.0 * float(touch.sum())


def _particle_speeds(sim, gas, u_s, d, n, red) -> tuple[dict, dict]:
    """The speeds that can move the particles of a mechanics run in the first coupling steps
    (the particle Courant rule takes the largest; docs/models.md "Particle Courant number"):

    * ``particle_speed_initial``: the largest initial particle speed.
    * ``particle_settling_speed``: a packing whose particles do not touch (mean coordination
      number below COORDINATION_AT_REST, e.g. a loose insertion) cannot rest: it settles
      under gravity. Its mean solid fraction phi = V_solid / (H A) (H: its extent along g,
      A: the domain's cross-section normal to g) rises at most to random close packing, so
      its top falls at most H_fall = H (1 - phi / RANDOM_CLOSE_PACKING), at up to
      sqrt(2 g H_fall) (free fall; the gas drag only slows it). 0 for a packing at rest
      (touching particles: a settled bed, a lattice) or without gravity.
    * ``gas_excess_speed``: the gas moves a resting bed only if its superficial speed u_s
      (the largest of 0/U) exceeds the minimum fluidization velocity U_mf (Wen & Yu 1966, of
      the particle that is lifted first). Then the gas in excess of U_mf crosses the bed as
      bubbles, which carry the particles (two-phase theory, Toomey & Johnstone 1952): the
      particle speed scale is u_s - U_mf. Below U_mf: 0 (the drag does not lift the bed).
    Returns (speeds, info): info holds ``coordination_number``, ``packing_fraction`` phi and
    ``u_mf``. ``red``: the reductions over the DEM ranks (coupling.cells.CellShare), each of
    which holds its own ``n`` particles; a pair of particles on two ranks is not counted in the
    coordination number (a few % of the pairs, at the cuts: it only decides loose or at rest)."""
    from .drag import wen_yu_1966_umf
    st = sim.state
    out, info = {}, {}
    n_all = red.allsum(float(n))
    if not n_all:
        return out, info
    out["particle_speed_initial"] = red.allmax(float(np.sqrt((st.velocity[:n] ** 2).sum(1)).max(initial=0.0)))
    g = np.asarray(sim.scene.simulation["gravity"], float)
    gmag = float(np.linalg.norm(g))
    r = st.radius[:n]
    if gmag > 0:
        e = g / gmag
        z = st.position[:n] @ e
        top = red.allmax(float((z + r).max(initial=-np.inf)))
        bottom = red.allmin(float((z - r).min(initial=np.inf)))
        v_solid, touches = red.allsum(np.array([(4.0 / 3.0 * math.pi * r ** 3).sum(), _touches(st.position[:n], r)]))
        H = top - bottom
        lo, hi = np.asarray(sim.scene.domain["min"], float), np.asarray(sim.scene.domain["max"], float)
        box = hi - lo
        A = float(np.prod(box)) / float(np.abs(box * e).sum())   # volume / extent along g
        phi = float(v_solid) / (H * A)
        z_c = float(touches) / n_all
        h_fall = max(0.0, H * (1.0 - phi / RANDOM_CLOSE_PACKING)) if z_c < COORDINATION_AT_REST else 0.0
        info["coordination_number"] = z_c
        info["packing_fraction"] = phi
        out["particle_settling_speed"] = math.sqrt(2.0 * gmag * h_fall)
    if u_s > 0:
        rho_p = st.mass[:n] / (4.0 / 3.0 * math.pi * r ** 3)
        pairs = np.unique(np.stack([d, rho_p], axis=1), axis=0)
        umf = red.allmin(min((wen_yu_1966_umf(float(dd), float(rr), gas.rho, gas.mu, gmag) for dd, rr in pairs),
                             default=math.inf))
        info["u_mf"] = umf
        out["gas_excess_speed"] = max(0.0, u_s - umf)
    return out, info


def _biot_check(case, thermal, u_s, d, eps0, cells, n, vals, warnings, red):
    """Bi = h L_c / k_p with L_c = V/A = R/3 (lumped-capacitance convention) for every
    particle, h = Nu k_f / d from the case's convection correlation (the compiled function
    the heat step uses, dem.thermal kernel.convection_biot) at the case's gas speed: u_s,
    the largest speed of 0/U, is the superficial velocity (the inlet value, where eps = 1);
    in the bed the interstitial gas speed is u_s / eps, so for particles at rest the
    correlations' Re = eps rho |u_f - v_p| d / mu = rho u_s d / mu; eps (Gunn, Li-Mason) is
    the initial void fraction of the particle's cell. Reports the particle with the largest
    Bi (over every DEM rank: ``red``, coupling.cells.CellShare.best); warns above 0.1."""
    from dem.thermal.convection import BIOT_LUMPED
    gas = case.gas
    eps_p = eps0[np.maximum(cells, 0)] if eps0 is not None else np.ones(n)
    re = gas.rho * u_s * d / gas.mu
    nu, h, bi = thermal.convection_biot(re, eps_p)
    mine = [-np.inf, 0.0, 0.0, 0.0, 0.0, 0.0]
    if n:
        i = int(np.argmax(bi))
        mine = [bi[i], re[i], nu[i], h[i], d[i], case.sim.state.id[i]]
    best, (re_i, nu_i, h_i, d_i, id_i) = red.best(mine[0], mine[1:])
    if best == -np.inf:   # no particle on any rank
        return
    vals["biot_gas_speed"] = float(u_s)
    vals["biot_reynolds"] = float(re_i)
    vals["biot_nusselt"] = float(nu_i)
    vals["biot_h"] = float(h_i)
    vals["biot"] = float(best)
    if best > BIOT_LUMPED:
        kp = float(h_i * d_i / (6 * best))   # Bi = h (d/2) / (3 k_p)
        name = thermal.cfg["convection"]
        warnings.append(
            f"Biot number h (V/A) / k_p = h R / (3 k_p) = {best:.3g} > {BIOT_LUMPED:g} (particle id "
            f"{int(id_i)}: d = {d_i:.3g} m, k_p = {kp:.3g} W/(m K); {name} Nu = {nu_i:.3g} at Re = "
            f"{re_i:.4g} from the {u_s:.3g} m/s of 0/U, h = {h_i:.3g} W/(m2 K)): the DEM gives each particle "
            f"one (lumped) temperature and ignores the temperature gradients inside it; its surface, which "
            f"exchanges the heat, differs from the mean by about 0.6 Bi = {60 * best:.2g} % of the "
            f"surface-to-gas difference (quasi-steady sphere), so the heat exchanged is off by about as much. "
            f"Bi < {BIOT_LUMPED:g} needs smaller particles, a slower gas or a more conductive material "
            f"(thermal_conductivity in dem.toml, only if the material has it); otherwise read the particle "
            f"temperatures as mean temperatures")


def wider_void_fraction_models(model: str) -> str | None:
    """The void-fraction models that spread a particle wider than ``model`` (for advice that
    never names the model in use); None for 'smoothed', the widest."""
    return {"centre": "'divided' or 'smoothed'", "divided": "'smoothed'"}.get(model)


def _cell_size_advice(mesh, cfg: CouplingConfig, dmax: float, dx_min: float, red=None, own=slice(None)) -> dict:
    """The cell-size rule of the unresolved model, for the case's void-fraction model.

    What the rule protects is the volume over which the void fraction is averaged: one
    particle of volume V_p changes a cell's solid fraction by V_p / V_avg, and the drag and
    heat-transfer closures assume an average over many particles. V_avg is the cell for
    'centre' and 'divided' (divided spreads a particle only over the cells it overlaps),
    and the kernel volume, about 2.1 cells, for 'smoothed' (voidfraction.averaging_volume,
    measured on the mesh with the model's own stencil). The rule: the averaging length
    L = V_avg^(1/3) (smallest over the cells) at least CELL_DIAMETERS largest diameters.
    The advice names only what changes L for the current model: 'smoothed' for 'centre'
    and 'divided' when it passes on this mesh, else the cell size that passes with the
    model in use (and with 'smoothed')."""
    from .voidfraction import averaging_volume
    model = cfg.void_fraction
    need = CELL_DIAMETERS * dmax

    def length(m):   # red: a local mesh, the smallest over the ranks' owned cells
        v = averaging_volume(mesh, m, dmax / 2, n_satellites=cfg.n_satellites)[own]
        return float(np.cbrt(red.allmin(float(v.min(initial=np.inf))) if red is not None else v.min()))

    L = length(model)
    ok = L >= need * (1 - 1e-9)
    cell_for = lambda m, Lm: need * dx_min / Lm   # noqa: E731  the cell size that makes L = need
    blockmesh = "(system/blockMeshDict)"
    if model == "smoothed":
        advice = f"use cells of at least {cell_for(model, L):.3g} m {blockmesh}; the case already uses 'smoothed'"
        clip = (f"the case already uses void_fraction = 'smoothed' (the widest stencil): use cells of at least "
                f"{cell_for(model, L):.3g} m {blockmesh}")
    else:
        Ls = length("smoothed")
        cs = cell_for("smoothed", Ls)
        if Ls >= need * (1 - 1e-9):
            advice = (f"use void_fraction = 'smoothed' in coupling.toml (now '{model}'; it averages over "
                      f"{Ls:.3g} m = {Ls / dmax:.2f} diameters on this mesh) or cells of at least "
                      f"{cell_for(model, L):.3g} m {blockmesh}")
        else:
            advice = (f"use cells of at least {cell_for(model, L):.3g} m with '{model}' or {cs:.3g} m with "
                      f"void_fraction = 'smoothed' {blockmesh}")
        spread = ("'divided' or 'smoothed' (they spread a particle over the cells it overlaps, or over a "
                  "kernel of about 2 cells)" if model == "centre" else
                  "'smoothed' (it spreads a particle over a kernel of about 2 cells)")
        clip = (f"use void_fraction = {spread} in coupling.toml (now '{model}') or cells of at least "
                f"{cell_for(model, L):.3g} m {blockmesh}")
    what = "the cells" if model != "smoothed" else "the smoothing kernel (about 2 cells)"
    message = (f"void fraction averaged over {L:.3g} m = {L / dmax:.2f} particle diameters (< {CELL_DIAMETERS:g}; "
               f"void_fraction = '{model}' averages over {what}; smallest cell {dx_min:.3g} m): one particle "
               f"changes a cell's void fraction by up to {(math.pi / 6) * dmax ** 3 / L ** 3:.2g}, so the void "
               f"fraction and drag of the unresolved model are inaccurate; {advice}")
    return dict(length=L, ok=ok, message=message, advice=advice, clip_advice=clip)


def check_coupled_case(case: CoupledCase, mesh, *, eps0: np.ndarray | None = None,
                       clip: dict | None = None, ranks=None, umax: float | None = None) -> dict:
    """Run the coupling checks on a loaded case and its mesh. Returns a report dict with
    'values', 'warnings', 'problems'. Raises :class:`CaseConfigError` on the first hard
    error (inconsistent input); failed limits go to 'problems' (the caller refuses to run
    unless coupling.force = true). ``eps0``: initial void fraction (after clipping);
    ``clip``: its clipping (CouplingInterface.clip). ``ranks``: the DEM ranks' reductions
    (coupling.cells.CellShare, the interface's) when each rank holds its own particles: every
    rank then gets the same report, over all particles; None: one process. When ``mesh`` is
    the rank's local mesh (``mesh.global_ids`` set: coupling.pieces), the mesh values are
    reduced over the ranks' owned cells (the same numbers as on the whole mesh) and ``eps0``
    is of the local mesh; ``umax``: the largest |U| of 0/U when already known (the pieces'
    0/U files, coupling.pieces.PieceTable)."""
    from .cells import CellShare
    red = ranks if ranks is not None else CellShare.serial(mesh.n_cells)
    local = ranks is not None and ranks.par is not None and mesh.global_ids is not None
    own = ranks.owned if local else slice(None)
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
    V = mesh.cell_volumes[own]
    v_min = red.allmin(float(V.min(initial=np.inf))) if local else V.min()
    dx_min = float(np.cbrt(v_min))
    h = mesh.cell_vhi[own] - mesh.cell_vlo[own]
    dx_edge = float(red.allmin(float(h.min(initial=np.inf))) if local else h.min())   # smallest cell edge (Courant)
    st = sim.state
    n = st.n_owned
    d = 2 * st.radius[:n]
    d_max = red.allmax(float(d.max(initial=0.0)))
    vals["particles"] = int(red.allsum(float(n)))
    vals["cells"] = int(red.allsum(float(V.size))) if local else mesh.n_cells
    vals["cell_size_min"] = dx_min
    vals["cell_over_diameter"] = dx_min / d_max
    cell_advice = _cell_size_advice(mesh, cfg, d_max, dx_min, red=red if local else None, own=own)
    vals["averaging_length"] = cell_advice["length"]
    vals["averaging_over_diameter"] = cell_advice["length"] / d_max
    if dx_min < d_max * (1 - 1e-9):
        warnings.append(f"smallest cell {dx_min:.3g} m is {dx_min / d_max:.2f} particle diameters: particles "
                        f"larger than the cells are outside the unresolved model (void fraction clipped at "
                        f"eps_min, drag and heat exchange inconsistent between gas and particles, with every "
                        f"void_fraction model); {cell_advice['advice']}")
    elif not cell_advice["ok"]:
        warnings.append(cell_advice["message"])
    # --- initial void fraction below eps_min (clipped: solid volume the gas does not see)
    if clip is not None:
        vals["eps_initial_raw_min"] = clip["eps_raw_min"]
        vals["eps_clipped_cells"] = clip["cells"]
        vals["eps_clipped_volume_fraction"] = clip["fraction"]
        if clip["cells"]:
            msg = (f"initial void fraction below coupling.eps_min = {cfg.eps_min:g} in {clip['cells']} cell(s) "
                   f"(lowest 1 - V_solid/V_cell = {clip['eps_raw_min']:.3g}): clipping hides "
                   f"{100 * clip['fraction']:.3g} % of the particle volume from the gas; "
                   f"{cell_advice['clip_advice']}")
            (problems if clip["fraction"] > CLIPPED_VOLUME else warnings).append(
                msg + (f" (refused above {100 * CLIPPED_VOLUME:g} %)" if clip["fraction"] > CLIPPED_VOLUME else ""))
    vals["cell_over_particle_volume"] = float(v_min / ((math.pi / 6) * d_max ** 3))
    # particles in the mesh (the one of smallest id named, on every rank)
    cells = mesh.locate(st.position[:n])
    out = np.flatnonzero(cells < 0)
    first = int(out[np.argmin(st.id[out])]) if out.size else -1
    n_out = int(red.allsum(float(out.size)))
    if n_out:
        id_out, x_out = red.best(float(st.id[first]) if first >= 0 else np.inf,
                                 st.position[first] if first >= 0 else np.zeros(3), largest=False)
        blo, bhi = mesh.bbox_lo, mesh.bbox_hi
        if local:
            blo = red.allmin(mesh.cell_vlo[own].min(axis=0, initial=np.inf))
            bhi = red.allmax(mesh.cell_vhi[own].max(axis=0, initial=-np.inf))
        raise CaseConfigError(case.dem_file, f"{n_out} particle(s) outside the OpenFOAM mesh "
                              f"(first: id {int(id_out)} at {x_out.tolist()}); mesh "
                              f"bounding box {blo.tolist()} .. {bhi.tolist()}")
    # --- gas CFL (interstitial speed ~ superficial / eps)
    if umax is None:
        umax = _max_speed_of_field(case.dir / "0" / "U", mesh.n_cells)
    emin = red.allmin(float(eps0.min())) if eps0 is not None else 1.0
    u_int = umax / max(emin, cfg.eps_min)
    cfl = u_int * dt_cfd / dx_edge
    vals["gas_speed_max"] = u_int
    vals["gas_cfl"] = cfl
    if cfl > GAS_CFL[1]:
        problems.append(f"gas CFL {cfl:.3g} > {GAS_CFL[1]} (|U|/eps = {u_int:.3g} m/s, deltaT {dt_cfd:g} s, "
                        f"cell {dx_edge:.3g} m): lower deltaT in system/controlDict (and coupling_interval)")
    elif cfl > GAS_CFL[0]:
        warnings.append(f"gas CFL {cfl:.3g} > {GAS_CFL[0]}")
    # --- Biot number of the particles in the case's gas stream
    # (parcels: the real particles' diameter, whose laws they follow; docs/models.md "Coarse graining")
    d_real = 2 * st.real_radius(n)
    if thermal is not None and cfg.heat:
        _biot_check(case, thermal, umax, d_real, eps0, cells, n, vals, warnings, red)
    # --- particle Courant number: displacement per coupling step / cell size
    mech = bool(sim.scene.simulation["mechanics"])
    speeds, info = _particle_speeds(sim, gas, umax, d_real, n, red) if mech else ({}, {})
    vals.update(info)
    vals.update(speeds)
    v_char = max(speeds.values(), default=0.0)
    if mech:
        vals["particle_speed_char"] = v_char
    co = v_char * dt_cfd / dx_edge
    vals["particle_courant"] = co
    if co > PARTICLE_COURANT[0]:
        source = max(speeds, key=speeds.get)
        why = {"particle_speed_initial": "the largest initial particle speed",
               "particle_settling_speed": "the fall of the loose packing as it settles, sqrt(2 g H_fall)",
               "gas_excess_speed": "the gas above minimum fluidization, U - U_mf"}[source]
        k_pass = int(math.floor(PARTICLE_COURANT[0] * dx_edge / (v_char * dt_dem) * (1 + 1e-9)))
        fix = (f"set deltaT = {k_pass * dt_dem:.6g} s in system/controlDict and coupling_interval = {k_pass} in "
               f"coupling.toml (Courant {v_char * k_pass * dt_dem / dx_edge:.2g})" if k_pass >= 1 else
               f"even one DEM step ({dt_dem:g} s) moves a particle {v_char * dt_dem / dx_edge:.2g} cells: lower the "
               f"DEM time_step below {PARTICLE_COURANT[0] * dx_edge / v_char:.3g} s, with deltaT = coupling_interval x "
               f"time_step, or use coarser cells")
        msg = (f"particle Courant number {co:.3g} > {{limit}}: particles move up to {v_char:.3g} m/s ({why}) x "
               f"coupling step {dt_cfd:g} s = {co:.2g} of the smallest cell edge {dx_edge:.3g} m per coupling step, "
               f"so the gas sees a void fraction and drag that lag the particles; {fix}")
        if co > PARTICLE_COURANT[1]:
            problems.append(msg.format(limit=PARTICLE_COURANT[1]))
        else:
            warnings.append(msg.format(limit=PARTICLE_COURANT[0]))
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
        tau = red.allmin(float((mass / beta).min(initial=np.inf)))
        k = int(np.argmin(mass / beta_imp)) if n else -1
        tau_imp, (eps_k,) = red.best(float(mass[k] / beta_imp[k]) if n else np.inf, [eps_c[k] if n else 0.0],
                                     largest=False)
        vals["particle_relaxation_time"] = tau
        vals["coupling_over_relaxation"] = dt_cfd / tau
        vals["bed_relaxation_time"] = tau_imp
        vals["coupling_over_bed_relaxation"] = dt_cfd / tau_imp
        if dt_cfd / tau_imp > RELAXATION_RATIO:
            k_cfd = max(1, math.floor(tau_imp / dt_dem))
            warnings.append(
                f"coupling step {dt_cfd:g} s is {dt_cfd / tau_imp:.3g} x the drag relaxation time of the bed "
                f"m/beta_imp = {tau_imp:.3g} s (void fraction {float(eps_k):.3g}, |u| = {max(umax, 1e-3):.3g} m/s): "
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
    for k in ("dt_over_rayleigh", "dt_over_hertz", "thermal_critical_step"):
        if k in rep:
            vals[k] = rep[k]
    # the DEM's own Biot number is at the gas velocity it has before the first exchange (none:
    # the stagnant Nu); the coupled one above, at the gas speed of 0/U, replaces it
    warnings += [w for w in rep.get("warnings", []) if not w.startswith("Biot number")]
    if cfg.gas_processes > (os.cpu_count() or 1):
        warnings.append(f"gas_processes {cfg.gas_processes} > {os.cpu_count()} cores (oversubscribed)")
    return dict(values=vals, warnings=warnings, problems=problems)


def _drag_void_text(case, rep) -> str:
    """What the drag void fraction averages over (coupling.particle_void), against the gas cells."""
    from .particle_void import ParticleVoidFraction
    cfg = case.config
    ratio = rep["values"].get("cell_over_diameter")
    rmax = float(case.sim.world.rmax) if case.sim is not None else 0.0
    if rmax <= 0.0:
        return cfg.drag_void_fraction
    text = ParticleVoidFraction(cfg.drag_void_fraction, rmax, cfg.drag_averaging_length, n_directions=2).averaging()
    if ratio is None:
        return text
    if cfg.drag_void_fraction != "cell":
        return text + f"; the gas cells are {ratio:.2g} diameters"
    if ratio >= 2.0:
        text += (f" (cells of {ratio:.2g} diameters: where a packed bed fills a cell in part, its ends, the "
                 f"cell's void fraction is high and the drag low, 7 % less pressure drop on cells of 3 "
                 f"diameters in benchmarks/ergun_column.py; drag_void_fraction = \"voronoi\" takes it around "
                 f"each particle, docs/models.md)")
    return text


def format_report(case: CoupledCase, rep: dict) -> str:
    lines = [f"coupled case {case.dir}",
             f"  transport {case.config.transport}, drag {case.config.drag}, void fraction "
             f"{case.config.void_fraction}, model {case.model_type}, interpolation {case.config.interpolation}",
             f"  drag void fraction {case.config.drag_void_fraction}: {_drag_void_text(case, rep)}"]
    cfg = case.config
    if cfg.torque != "none" or cfg.lift != "none" or cfg.virtual_mass:
        lines.append(f"  fluid torque {cfg.torque}, lift {cfg.lift}, virtual mass "
                     f"{'on (C_vm 0.5)' if cfg.virtual_mass else 'off'} (docs/models.md)")
    if cfg.averaging is not None:
        lines.append(f"  {cfg.averaging.report()}")
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
