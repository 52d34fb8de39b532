"""One coupling step of the unresolved CFD-DEM coupling (DEM side).

:class:`CouplingInterface` turns the DEM state into the DEM -> CFD frame (eps, Ksl, Us,
Simp, Sexp; docs/coupling_protocol.md) and the gas frame into particle data for the DEM
(force, gas velocity, gas temperature, void fraction), using the same particle -> cell
stencil (``coupling.voidfraction``) for every exchanged quantity.

Time staggering (explicit, as CFDEMcoupling): at coupling time t_{n-1}, with the gas
state of t_{n-1} and the particles at t_{n-1},

1. locate the particles (hint: their previous cells), build the stencil, void fraction;
2. interpolate U, T, grad p to the particles; eps at the particle from the sent field;
3. beta_p from the drag law with |u_f - u_p|; particle force
   model A: beta_p (u_f - u_p) - V_p grad p  (p includes hydrostatics: buoyancy inside)
   model B: beta_p/eps (u_f - u_p) - rho_f V_p g;
4. Ksl = sum_p w beta_p / V_c, Us = beta-weighted mean particle velocity (so that
   Ksl (U - Us) is the summed drag of the cell's particles for a uniform U);
5. hA_p = sim.thermal.convection_h() (same compiled Nusselt functions as the DEM heat
   step), Simp = sum w hA / V, Sexp = sum w hA T_p / V.

The frame for step n is sent, then the gas (t_{n-1} -> t_n) and the DEM (k steps,
t_{n-1} -> t_n, fixed fluid data) advance concurrently, and the gas state of t_n is
received.

Time smoothing (``smoothing_time`` tau > 0): eps and Ksl sent to the gas relax towards
the instantaneous values, ``x <- x + (1 - exp(-dt/tau)) (x_new - x)``; the gas solver is
sensitive to sudden eps changes (a particle crossing a face with the ``centre`` model).
Particles see the smoothed eps (the gas and the particles use the same void fraction).
"""
from __future__ import annotations

import math
import time
from collections import namedtuple
from dataclasses import dataclass, field

import numpy as np
from numba import njit

from . import voidfraction as vf
from .drag import drag_coefficient, drag_model_id
from .forces import (C_VM, LIFT_MODELS, TORQUE_MODELS, magnus_oesterle_bui_dinh_1998,
                     rotational_drag_dennis_1980, saffman_mei_1992)
from .interpolate import cell_gradient, interpolate

__all__ = ["GasProperties", "CouplingInterface", "PhaseTimer"]


@dataclass
class GasProperties:
    rho: float          # kg/m^3
    nu: float           # m^2/s
    cp: float           # J/(kg K)
    k: float            # W/(m K)

    @property
    def mu(self) -> float:
        return self.rho * self.nu


class PhaseTimer:
    """Accumulated wall time per phase (seconds) and call counts."""

    PHASES = ("locate", "void_fraction", "interpolation", "exchange_terms", "exchange",
              "dem", "gas_wait", "output")

    def __init__(self):
        self.total = {p: 0.0 for p in self.PHASES}
        self.count = {p: 0 for p in self.PHASES}

    def add(self, phase: str, seconds: float) -> None:
        self.total[phase] = self.total.get(phase, 0.0) + seconds
        self.count[phase] = self.count.get(phase, 0) + 1

    class _Ctx:
        def __init__(self, timer, phase):
            self.timer, self.phase = timer, phase

        def __enter__(self):
            self.t0 = time.perf_counter()

        def __exit__(self, *exc):
            self.timer.add(self.phase, time.perf_counter() - self.t0)

    def __call__(self, phase: str):
        return PhaseTimer._Ctx(self, phase)

    def table(self, wall: float | None = None) -> list[tuple[str, float, float]]:
        tot = wall if wall else sum(self.total.values())
        return [(p, s, s / tot if tot > 0 else 0.0) for p, s in self.total.items()]


@dataclass
class CouplingInterface:
    mesh: object                      # coupling.mesh.PolyMesh: the whole mesh; then this rank's local mesh
    sim: object                       # dem.Simulation
    gas: GasProperties
    drag: str = "di_felice_1994"
    void_fraction: str = "divided"
    drag_void_fraction: str = "cell"  # | voronoi | kernel (coupling.particle_void)
    drag_averaging_length: float | None = None
    interpolation: str = "cell"
    model_type: str = "A"
    eps_min: float = 0.3
    smoothing_time: float = 0.0       # s, 0 = off
    gravity: np.ndarray = field(default_factory=lambda: np.array([0.0, 0.0, -9.81]))
    n_satellites: int = 29
    heat: bool = True
    drag_integration: str = "implicit_bed"   # | implicit_particle | explicit (docs/models.md)
    torque: str = "none"              # | rotational_drag (coupling.forces)
    lift: str = "none"                # | saffman_mei | magnus
    virtual_mass: bool = False
    averaging: bool = False           # [averaging]: the frame's particle columns (coupling.averaging)
    timer: PhaseTimer = field(default_factory=PhaseTimer)
    mesh_source: object = None        # callable giving the whole mesh again (coupling.cells.CellShare)

    @classmethod
    def for_case(cls, case, mesh, source=None):
        """The interface of a coupled case (coupling.case.CoupledCase) on ``mesh`` (the whole
        mesh; each DEM rank keeps the cells it sees: coupling.cells): the settings of its
        coupling.toml, its gas, its model type and its scene's gravity."""
        cfg = case.config
        return cls(mesh, case.sim, case.gas, mesh_source=source, drag=cfg.drag, void_fraction=cfg.void_fraction,
                   drag_void_fraction=cfg.drag_void_fraction, drag_averaging_length=cfg.drag_averaging_length,
                   interpolation=cfg.interpolation, model_type=case.model_type, eps_min=cfg.eps_min,
                   smoothing_time=cfg.smoothing_time,
                   gravity=np.asarray(case.sim.scene.simulation["gravity"], float),
                   n_satellites=cfg.n_satellites, heat=cfg.heat, drag_integration=cfg.drag_integration,
                   torque=cfg.torque, lift=cfg.lift, virtual_mass=cfg.virtual_mass,
                   averaging=cfg.averaging is not None)

    def __post_init__(self):
        self.drag_id = drag_model_id(self.drag)
        self.drag_mode = DRAG_INTEGRATION[self.drag_integration]
        if self.torque not in TORQUE_MODELS:
            raise ValueError(f"torque must be one of {', '.join(TORQUE_MODELS)}, got {self.torque!r}")
        if self.lift not in LIFT_MODELS:
            raise ValueError(f"lift must be one of {', '.join(LIFT_MODELS)}, got {self.lift!r}")
        self.torque_id = TORQUE_MODELS[self.torque]
        self.lift_id = LIFT_MODELS[self.lift]
        self.virtual_mass = bool(self.virtual_mass)
        self.u_prev = None            # gas velocity of the last frame (virtual mass: dU/dt)
        if self.model_type not in ("A", "B"):
            raise ValueError(f"modelType must be A or B, got {self.model_type!r}")
        # the gas cells this DEM rank owns and sees, and its local mesh of them (coupling.cells;
        # serial: the whole mesh); every per-cell array here is of the local mesh
        from .cells import CellShare
        self.cells = CellShare(self.mesh, self.sim.par, source=self.mesh_source,
                               halo=self.sim.world.halo(bound=True) if self.sim.par is not None else 0.0)
        self.mesh = self.cells.mesh
        self.V = self.mesh.cell_volumes
        self._layout = self.cells.layout
        self._frame = None            # the last frame prepare returned (moved with a new local mesh)
        self.hint = None
        self.eps_sent = None
        self.ksl_sent = None
        self.us_sent = None           # Us of the last frame: the particle velocity the gas responded to
        self.heat = bool(self.heat) and self.sim.thermal is not None
        self.last = {}
        self.n_lost = 0
        self._mapped = None
        self._map_cache = None        # (positions, radii, stencil, eps) of the last mapping
        # eps_min clipping of the last mapping: cells, solid volume removed (m^3), its
        # fraction of the particle volume, smallest unclipped eps and its cell
        self.clip = dict(cells=0, volume=0.0, fraction=0.0, eps_raw_min=1.0, cell=-1)
        self.eps_change = (0.0, -1)   # largest |eps_n - eps_(n-1)| sent to the gas, and its cell
        # the void fraction each particle's drag sees (coupling.particle_void); "cell": the
        # stencil's mean of the cells', as the gas sees it
        from .particle_void import ParticleVoidFraction
        self.local_void = ParticleVoidFraction(self.drag_void_fraction, self.sim.world.rmax, self.drag_averaging_length)
        st = self.sim.state
        self.rmin = float(self.cells.allmin(float(st.radius[:st.n_owned].min(initial=math.inf))))

    def _note_clipping(self, eps_raw) -> None:
        """The eps_min clipping of the cells this rank owns, summed over the ranks."""
        cs = self.cells
        own = cs.owned
        e = eps_raw[own]
        low = e < self.eps_min
        c = int(np.argmin(e)) if e.size else -1
        vol = float(((self.eps_min - e[low]) * self.V[own][low]).sum()) if low.any() else 0.0
        vp = (4.0 / 3.0) * math.pi * float((self.sim.state.radius[:self.sim.state.n_owned] ** 3).sum())
        n_low, vol, vp = cs.allsum(np.array([float(low.sum()), vol, vp]))
        e_min, c = cs.argmin(float(e[c]) if c >= 0 else 1.0, int(cs.global_ids[own[c]]) if c >= 0 else -1)
        self.clip = dict(cells=int(n_low), volume=float(vol), fraction=float(vol / vp) if vp > 0 else 0.0,
                         eps_raw_min=float(e_min), cell=int(c))

    def map_particles(self) -> None:
        """Locate the particles and build the stencil / void fraction now (e.g. right after
        the DEM interval, while the gas solver is still busy); ``prepare`` reuses it if
        the DEM has not moved since. After a re-cut of the DEM boxes ``prepare`` does it (the
        cells a rank sees change there, with the gas frame it is given)."""
        if self.cells.needs_refresh(self.sim.world.halo(bound=True) if self.sim.par is not None else 0.0):
            return
        pw, eps = self._stencil()
        self._mapped = (self.sim.step_count, pw, eps)

    def _moved(self, fluid):
        """After a re-plan of the cells (collective): a rebuilt local mesh takes the per-cell
        state that persists (eps, Ksl, Us as last sent, the last gas velocity, the last frame,
        the gas frame ``fluid`` in place) to its numbering, the owners' values fill the new
        halo cells, the stencil is built again."""
        cs = self.cells
        self.hint = None
        self._map_cache = None
        if cs.layout != self._layout:
            self.mesh = cs.mesh
            self.V = self.mesh.cell_volumes
            self._layout = cs.layout
        moved = []
        for k in ("eps_sent", "ksl_sent", "us_sent", "u_prev"):
            a = getattr(self, k)
            if a is not None:
                a = np.ascontiguousarray(cs.carry(a), dtype=np.float64)
                setattr(self, k, a)
                moved.append(a)
        for d in (self._frame, fluid):
            if not d:
                continue
            for k in sorted(d):
                a = d[k]
                if isinstance(a, np.ndarray) and a.ndim and a.dtype == np.float64 and k != "scalars":
                    d[k] = np.ascontiguousarray(cs.carry(a))
                    moved.append(d[k])
        cs.update(*moved)

    # ------------------------------------------------------------------ particle -> mesh
    def _stencil(self, fluid=None):
        st = self.sim.state
        n = st.n_owned
        par = self.sim.par
        if par is not None and par.exchanges != getattr(self, "_exchanges_seen", -1):
            self.hint = None  # particles moved between ranks: rows changed
            self._map_cache = None
            self._exchanges_seen = par.exchanges
        flow = self.sim.world.flow
        if flow is not None and flow.changes != getattr(self, "_flow_seen", -1):
            self.hint = None  # particles entered or left: rows changed
            self._map_cache = None
            self._flow_seen = flow.changes
        pos, rad = st.position[:n], st.radius[:n]
        prev = self._map_cache
        same = (prev is not None and prev[0].shape == pos.shape and np.array_equal(prev[0], pos)
                and np.array_equal(prev[1], rad))
        if par is not None:
            same = bool(self.cells.allmin(int(same)))   # the sums below are collective: every rank agrees
            if self.cells.refresh(self.sim.world.halo(bound=True)):   # the DEM boxes were re-cut: who sees what
                self._moved(fluid)
                same, prev = False, None
        if same:
            # particles have not moved (held bed, mechanics = false): same stencil, exactly
            return prev[2], prev[3]
        with self.timer("locate"):
            cells = self.mesh.locate(pos, hint=self.hint)
        with self.timer("void_fraction"):
            pw = vf.compute_weights(self.mesh, pos, rad, self.void_fraction, located=cells,
                                    n_satellites=self.n_satellites,
                                    out=prev[2] if prev is not None else None)
            self.cells.check_stencil(pw.cells)
            (solid,) = self.cells.assemble(vf.solid_volume(pw, rad))
            eps = 1.0 - solid / self.V
            self._note_clipping(eps)
            eps = np.maximum(eps, self.eps_min)
        self.hint = pw.centre_cell
        self.n_lost = pw.n_lost
        self._map_cache = (pos.copy(), rad.copy(), pw, eps)
        return pw, eps

    def initial_void_fraction(self) -> np.ndarray:
        """Void fraction of the initial packing (write it into 0/eps before the solver
        starts, so that the gas sees no jump of eps at the first step)."""
        pw, eps = self._stencil()
        self.eps_sent = eps.copy()
        return eps

    def restart_state(self) -> dict:
        """State of the exchange fields that the next coupling step reads besides the
        particles and the gas: eps and Ksl as last sent (the time-smoothing relaxes from
        them). (The cell hints need not be kept: they only speed up the search.)"""
        nc = self.V.shape[0]
        d = dict(eps_sent=np.zeros(0) if self.eps_sent is None else np.asarray(self.eps_sent, float),
                 ksl_sent=np.zeros(0) if self.ksl_sent is None else np.asarray(self.ksl_sent, float),
                 us_sent=np.zeros((0, 3)) if self.us_sent is None else np.asarray(self.us_sent, float),
                 u_prev=np.zeros((0, 3)) if self.u_prev is None else np.asarray(self.u_prev, float))
        for k in ("eps_sent", "ksl_sent", "us_sent", "u_prev"):
            if d[k].shape[0] not in (0, nc):
                raise ValueError(f"{k} has {d[k].shape[0]} rows, the mesh {nc} cells")
        return d

    def restore_state(self, d: dict) -> None:
        """Undo :meth:`restart_state` (after :meth:`initial_void_fraction`): the next
        ``prepare`` relaxes from exactly the eps and Ksl the gas last received. Raises
        ValueError naming the array that does not fit this mesh / these particles."""
        nc = self.V.shape[0]
        for k, shape in (("eps_sent", (nc,)), ("ksl_sent", (nc,)), ("us_sent", (nc, 3)), ("u_prev", (nc, 3))):
            a = np.ascontiguousarray(d.get(k, np.zeros(0)), dtype=np.float64)
            if a.size == 0:
                setattr(self, k, None)
                continue
            if a.shape != shape or not np.all(np.isfinite(a)):
                raise ValueError(f"{k} has shape {a.shape}, the mesh {nc} cells (or holds non-finite values)")
            setattr(self, k, a.copy())

    def reset_hints(self):
        """Call after the DEM reordered its particles (sim.sort_particles)."""
        self.hint = None
        self._map_cache = None

    def _relax(self, old, new, dt):
        if old is None or self.smoothing_time <= 0.0:
            return new.copy()
        a = 1.0 - math.exp(-dt / self.smoothing_time)
        return old + a * (new - old)

    # ------------------------------------------------------------------ one step
    def prepare(self, fluid: dict, dt_cfd: float) -> dict:
        """Compute the DEM -> CFD fields from the current particles and ``fluid`` (the
        gas state of the same time) and give the DEM its fluid data for the next
        interval. Returns the frame fields (eps, Ksl, Us, Simp, Sexp)."""
        sim = self.sim
        st = sim.state
        n = st.n_owned
        pos, rad, vel = st.position[:n], st.radius[:n], st.velocity[:n]
        if self._mapped is not None and self._mapped[0] == sim.step_count:
            pw, eps_raw = self._mapped[1], self._mapped[2]
        else:
            pw, eps_raw = self._stencil(fluid)
        self._mapped = None
        fluid = {k: self.cells.localize(v) for k, v in fluid.items()}   # (the API may give whole-mesh arrays)
        eps = self._relax(self.eps_sent, eps_raw, dt_cfd)
        if self.eps_sent is not None and eps.size:
            own = self.cells.owned
            de = np.abs(eps[own] - self.eps_sent[own])
            c = int(np.argmax(de)) if de.size else -1
            self.eps_change = self.cells.argmax(float(de[c]) if c >= 0 else 0.0,
                                                int(self.cells.global_ids[own[c]]) if c >= 0 else -1)
        self.cells.update(eps)   # the owners' relaxed eps in the halo cells (after a re-cut: new halo cells)
        self.eps_sent = eps

        with self.timer("interpolation"):
            cells = pw.centre_cell
            lost = cells < 0
            if self.interpolation == "cell":
                uf, gradp, tg, eps_p = _gather_cell(pw.cells, pw.weights, cells, fluid["U"], fluid["gradp"],
                                                    fluid["T"], eps)
            else:
                m = self.interpolation
                uf = interpolate(self.mesh, fluid["U"], pos, cells, m)
                gradp = interpolate(self.mesh, fluid["gradp"], pos, cells, m)
                tg = interpolate(self.mesh, fluid["T"], pos, cells, m)
                _, _, _, eps_p = _gather_cell(pw.cells, pw.weights, cells, fluid["U"], fluid["gradp"],
                                              fluid["T"], eps)
                uf[lost] = 0.0
                gradp[lost] = 0.0
                tg[lost] = np.nan
            extra = self.torque_id != 0 or self.lift_id != 0 or self.virtual_mass
            if extra:
                # gas velocity gradient (least squares, coupling.interpolate.cell_gradient):
                # G[c, i, j] = d u_i / d x_j; vorticity and, for virtual mass, Du/Dt per cell
                U = np.ascontiguousarray(fluid["U"], dtype=np.float64)
                G = cell_gradient(self.mesh, U)
                acc = (_material_derivative(U, G, np.zeros((0, 3)) if self.u_prev is None else self.u_prev, dt_cfd)
                       if self.virtual_mass else np.zeros((0, 3)))
                self.u_prev = U.copy()

        eps_loc = _CELL_VOID
        uloc = uf
        if self.local_void.method != "cell":
            with self.timer("void_fraction"):
                # the drag law at the void fraction around each particle, written against the
                # cells' (docs/models.md, "The void fraction a particle's drag sees")
                eps_p = _stencil_inverse_square_mean(pw.cells, pw.weights, eps)
                eps_loc = self.local_void(sim, eps_p, self.rmin, self.eps_min)
                eps_loc[lost] = 1.0
                uloc = _local_gas_velocity(uf, vel, eps_p, eps_loc)

        with self.timer("exchange_terms"):
            # the particle velocity the gas of this frame responded to: Us of the last frame at the
            # particle (its own velocity at the first frame)
            up = vel if self.us_sent is None else _gather_vector(pw.cells, pw.weights, self.us_sent, vel)
            at = AtParticles(rad, vel, uf, cells)
            force, beta, bimp, fexp, fdrag, fpres = _particle_forces(
                self.drag_id, self.model_type == "B", self.drag_mode, at, st.cg[:n], gradp, eps_p, eps_loc, up,
                self.gas.rho, self.gas.mu, self.gravity)
            tframe = None
            parts = dict(drag=fdrag, pressure=fpres)   # the fluid force by term (the output's fields)
            if extra:
                flift, fvm, texp, krot, madd, tframe = _extra_terms(
                    self.torque_id, self.lift_id, self.virtual_mass, at, st.angular_velocity[:n],
                    G, acc, self.gas.rho, self.gas.mu, C_VM)
                # lift and the Du_f/Dt part of the virtual mass: explicit, held over the interval
                fadd = flift + fvm
                fexp += fadd
                force += fadd
                if self.lift_id:
                    parts["lift"] = flift
                if self.virtual_mass:
                    parts["virtual_mass"] = fvm
            fl = dict(torque=texp if self.torque_id else None, torque_drag=krot if self.torque_id else None,
                      added_mass=madd if self.virtual_mass else None) if extra else {}
            # semi-implicit drag: the DEM takes the fluid force's response to the particle velocity,
            # -beta_imp (v - v_frame), implicitly in v; it gets beta_imp and the explicit part
            if self.heat:
                tgas = np.where(lost, st.temperature[:n], tg)
                # the Nusselt correlations at the same local void fraction, with the interstitial
                # gas velocity there (the superficial slip eps |u - v| of the cell kept)
                sim.set_fluid(force=fexp, drag=bimp, velocity=uloc, temperature=tgas,
                              porosity=eps_p if eps_loc.shape[0] == 0 else eps_loc, **fl)
                hA = sim.thermal.convection_h()[:n]
                hA[lost] = 0.0
                Tp = st.temperature[:n]
            else:
                sim.set_fluid(force=fexp, drag=bimp, **fl)
                hA = np.zeros(n)
                Tp = np.zeros(n)
            sums = _scatter_sums(pw.cells, pw.weights, beta, vel, hA, Tp, self.V.shape[0])
            sums = self.cells.assemble(*sums)
            ksl_raw, us, simp, sexp = _finish_terms(*sums, self.V)
            ksl = self._relax(self.ksl_sent, ksl_raw, dt_cfd)
            self.ksl_sent = ksl
            self.us_sent = us
            if self.averaging:   # the particles on the cells for the time averages (collective)
                from .averaging import particle_columns
                cols = particle_columns(pw, rad, vel, Tp if self.heat else None, self.V, self.cells)
        self.last = dict(beta=beta, force=force, hA=hA, eps_p=eps_p, eps_loc=eps_loc, uf=uf, eps_raw=eps_raw,
                         Tg=tg, torque=tframe, ids=st.id[:n].copy(), parts=parts)
        self._frame = dict(eps=eps, Ksl=ksl, Us=us, Simp=simp, Sexp=sexp)
        if self.averaging:
            self._frame["particle_columns"] = cols
        return self._frame

    def advance_dem(self, k: int) -> None:
        """The DEM's ``k`` steps of a coupling interval; with inlets or outlets (dem.flow) in pieces
        up to each of their events, which then act (a new particle feels the gas from the next
        interval on: its fluid force and drag are zero until then)."""
        sim = self.sim
        with self.timer("dem"):
            if sim.world.flow is None:
                sim.step(k)
            else:
                sim.world.flow.advance(sim, k)


# --------------------------------------------------------------------------- kernels

@njit(cache=True, error_model="numpy")
def _gather_cell(scells, sweights, cells, U, gradp, T, eps):
    """Cell values of U, grad p, T at the particles (centre cell) and the stencil-weighted
    void fraction eps_p (what the gas sees where the particle's volume went)."""
    n = cells.shape[0]
    uf = np.zeros((n, 3))
    gp = np.zeros((n, 3))
    tg = np.full(n, np.nan)
    ep = np.ones(n)
    for p in range(n):
        c = cells[p]
        if c < 0:
            continue
        for i in range(3):
            uf[p, i] = U[c, i]
            gp[p, i] = gradp[c, i]
        tg[p] = T[c]
        ws = 0.0
        es = 0.0
        for j in range(scells.shape[1]):
            cj = scells[p, j]
            if cj >= 0:
                ws += sweights[p, j]
                es += sweights[p, j] * eps[cj]
        if ws > 0.0:
            ep[p] = es / ws
    return uf, gp, tg, ep


_CELL_VOID = np.zeros(0)   # no local void fraction: the drag law at the cells' (drag_void_fraction = "cell")


@njit(cache=True, error_model="numpy")
def _stencil_inverse_square_mean(scells, sweights, eps):
    """The cell void fraction at each particle as its drag's exchange needs it,
    ebar = (sum_c w_c / eps_c^2 / sum_c w_c)^(-1/2) over its stencil: the particle's
    coefficient K is shared to the cells by w_c, and a cell's gas feels K_c u_s / eps_c^2
    (model A), so the bed's pressure drop is sum_p K_p u_s / ebar_p^2 exactly. 1 outside the
    mesh."""
    n = scells.shape[0]
    out = np.ones(n)
    for p in range(n):
        ws = 0.0
        s = 0.0
        for j in range(scells.shape[1]):
            c = scells[p, j]
            if c >= 0:
                ws += sweights[p, j]
                s += sweights[p, j] / (eps[c] * eps[c])
        if ws > 0.0 and s > 0.0:
            out[p] = 1.0 / math.sqrt(s / ws)
    return out


@njit(cache=True, error_model="numpy")
def _local_gas_velocity(uf, vel, ebar, eloc):
    """Interstitial gas velocity around each particle: v + (u_f - v) ebar / eps_loc, the
    superficial slip of its cell, ebar (u_f - v), through its own void fraction."""
    n = uf.shape[0]
    out = np.empty((n, 3))
    for p in range(n):
        g = ebar[p] / eloc[p]
        for i in range(3):
            out[p, i] = vel[p, i] + (uf[p, i] - vel[p, i]) * g
    return out


# how the DEM integrates the drag over a coupling step (coupling.toml drag_integration;
# docs/models.md, "Semi-implicit drag and the stability of the coupled step")
DRAG_EXPLICIT, DRAG_IMPLICIT_PARTICLE, DRAG_IMPLICIT_BED = 0, 1, 2
DRAG_INTEGRATION = {"explicit": DRAG_EXPLICIT, "implicit_particle": DRAG_IMPLICIT_PARTICLE,
                    "implicit_bed": DRAG_IMPLICIT_BED}


@njit(cache=True, error_model="numpy")
def _gather_vector(scells, sweights, field, own):
    """Stencil-weighted mean of a per-cell vector field at each particle (``own`` where the
    particle has no cell)."""
    n = scells.shape[0]
    out = np.empty((n, 3))
    for p in range(n):
        ws = 0.0
        a0 = a1 = a2 = 0.0
        for j in range(scells.shape[1]):
            c = scells[p, j]
            if c >= 0:
                w = sweights[p, j]
                ws += w
                a0 += w * field[c, 0]
                a1 += w * field[c, 1]
                a2 += w * field[c, 2]
        if ws > 0.0:
            out[p, 0] = a0 / ws
            out[p, 1] = a1 / ws
            out[p, 2] = a2 / ws
        else:
            out[p, 0] = own[p, 0]
            out[p, 1] = own[p, 1]
            out[p, 2] = own[p, 2]
    return out


# What the force kernels read of each particle at the frame, one record (a named tuple of
# arrays): radius, velocity, gas velocity at the particle, centre cell (-1: outside the mesh).
AtParticles = namedtuple("AtParticles", "rad vel uf cells")


@njit(cache=True, error_model="numpy")
def _particle_forces(model_id, model_b, mode, at, cg, gradp, eps_p, eps_loc, up, rho, mu, g):
    """beta_p (drag law; /eps for model B) and the fluid force on each particle at the frame:
    A: beta (u_f - u_p) - V_p grad p;  B: beta (u_f - u_p) - rho V_p g.

    ``eps_loc`` (empty: the cells') the void fraction around each particle, ``eps_p`` then the
    cells' at it as the exchange sees them (ebar): the law is evaluated at eps_loc with the
    slip there, |u_f - u_p| ebar / eps_loc, and the coefficient written against the cell's
    gas, K = beta(eps_loc) (ebar / eps_loc)^2 (model A; B: beta(eps_loc) / eps_loc
    (ebar / eps_loc)): the fluid force on a particle held in a bed, K u_f plus its share of
    the pressure gradient, is then its law's at eps_loc wherever the cell faces cut the bed
    (docs/models.md, "The void fraction a particle's drag sees").
    A parcel (cg: its coarse-graining factor; empty without coarse graining) takes the drag of its
    cg^3 real particles: beta = cg^3 beta(d / cg), the law at the real diameter (its Re and drag
    coefficient), and V_p its own volume (cg^3 real volumes; docs/models.md, "Coarse graining").

    Returns (force, beta, beta_imp, F_exp, F_drag, F_p): F_drag = beta (u_f - u_p) and F_p the
    pressure-gradient (A) or buoyancy (B) part, force = F_drag + F_p (the output's fields), and for the drag integration of the DEM
    (dem.step.half_kick_implicit: v_new = (v + h (F_other + F_exp) / m) / (1 + h beta_imp / m)),
    by ``mode`` (DRAG_*):

    * implicit_bed: beta_imp = beta_A / eps_p^2 (= beta / eps_p for model B), the rate at which
      the fluid force on a particle of a bed falls when the bed moves (the gas responding
      through continuity and its pressure gradient), and F_exp = force + beta u_p +
      (beta_imp - beta) up, ``up`` the particle velocity the gas of this frame responded to
      (Us of the previous frame at the particle): the force the DEM integrates is then
      F_0 - beta_imp v, stable and monotone for any coupling step (docs/models.md,
      "Semi-implicit drag and the stability of the coupled step");
    * implicit_particle: beta_imp = beta, F_exp = force + beta u_p (the drag alone implicit);
    * explicit: beta_imp = 0, F_exp = force (held over the coupling step).

    In every mode the force at the frame's velocities is the frame force, so the terminal
    velocity of any step is the drag law's. ``at``: the particles' AtParticles."""
    rad, vel, uf, cells = at.rad, at.vel, at.uf, at.cells
    n = rad.shape[0]
    force = np.zeros((n, 3))
    fexp = np.zeros((n, 3))
    beta = np.zeros(n)
    bimp = np.zeros(n)
    fdrag = np.zeros((n, 3))
    fpres = np.zeros((n, 3))
    has_cg = cg.shape[0] > 0
    local = eps_loc.shape[0] > 0
    for p in range(n):
        if cells[p] < 0:
            continue
        d = 2.0 * rad[p]
        r0 = uf[p, 0] - vel[p, 0]
        r1 = uf[p, 1] - vel[p, 1]
        r2 = uf[p, 2] - vel[p, 2]
        ur = math.sqrt(r0 * r0 + r1 * r1 + r2 * r2)
        if local:
            el = eps_loc[p]
            gr = eps_p[p] / el
            if has_cg:
                b = drag_coefficient(model_id, d / cg[p], el, rho, mu, ur * gr) * cg[p] ** 3
            else:
                b = drag_coefficient(model_id, d, el, rho, mu, ur * gr)
            if model_b:
                b *= gr / el
            else:
                b *= gr * gr
        else:
            if has_cg:
                b = drag_coefficient(model_id, d / cg[p], eps_p[p], rho, mu, ur) * cg[p] ** 3
            else:
                b = drag_coefficient(model_id, d, eps_p[p], rho, mu, ur)
            if model_b:
                b /= eps_p[p]
        beta[p] = b
        e = eps_p[p]
        if mode == DRAG_IMPLICIT_BED:
            bi = b / e if model_b else b / (e * e)
        elif mode == DRAG_IMPLICIT_PARTICLE:
            bi = b
        else:
            bi = 0.0
        bimp[p] = bi
        vp = math.pi / 6.0 * d * d * d
        fdrag[p, 0] = b * r0
        fdrag[p, 1] = b * r1
        fdrag[p, 2] = b * r2
        for i in range(3):
            if model_b:
                rest = -rho * vp * g[i]
            else:
                rest = -vp * gradp[p, i]
            fpres[p, i] = rest
            force[p, i] = fdrag[p, i] + rest
            if mode == DRAG_IMPLICIT_BED:
                fexp[p, i] = force[p, i] + b * vel[p, i] + (bi - b) * up[p, i]
            else:
                fexp[p, i] = force[p, i] + bi * vel[p, i]
    return force, beta, bimp, fexp, fdrag, fpres


@njit(cache=True, error_model="numpy")
def _material_derivative(U, G, u_prev, dt):
    """Du/Dt of the gas per cell: (U - U_prev) / dt + (U . grad) U, i.e. the change of the gas
    velocity of the cell between the last two frames plus the convective part from the
    least-squares gradient G[c, i, j] = d u_i / d x_j. At the first frame (no U_prev: a
    start, or a restart point written before this option was on) the time part is 0."""
    nc = U.shape[0]
    a = np.zeros((nc, 3))
    have = u_prev.shape[0] == nc
    for c in range(nc):
        for i in range(3):
            s = G[c, i, 0] * U[c, 0] + G[c, i, 1] * U[c, 1] + G[c, i, 2] * U[c, 2]
            if have:
                s += (U[c, i] - u_prev[c, i]) / dt
            a[c, i] = s
    return a


@njit(cache=True, error_model="numpy")
def _extra_terms(torque_id, lift_id, vm, at, angvel, G, acc, rho, mu, cvm):
    """Fluid torque, lift and virtual mass of each particle at the frame (coupling.forces),
    from the gas velocity uf at the particle and the gradient G of its cell (vorticity
    om = curl u_f, Omega_f = om / 2). Returns

    * flift, fvm: the lift and C_vm rho_f V_p Du_f/Dt (their sum is added to the explicit force);
    * texp, krot: the explicit part k_rot Omega_f of the torque and k_rot, for the DEM's
      implicit angular kick (torque k_rot (Omega_f - omega));
    * madd: the added mass C_vm rho_f V_p (the DEM's kick takes -madd dv/dt implicitly);
    * tframe: the torque k_rot (Omega_f - omega_p) at the frame (for the record).
    ``at``: the particles' AtParticles."""
    rad, vel, uf, cells = at.rad, at.vel, at.uf, at.cells
    n = rad.shape[0]
    flift = np.zeros((n, 3))
    fvm = np.zeros((n, 3))
    texp = np.zeros((n, 3))
    krot = np.zeros(n)
    madd = np.zeros(n)
    tframe = np.zeros((n, 3))
    for p in range(n):
        c = cells[p]
        if c < 0:
            continue
        d = 2.0 * rad[p]
        om0 = G[c, 2, 1] - G[c, 1, 2]
        om1 = G[c, 0, 2] - G[c, 2, 0]
        om2 = G[c, 1, 0] - G[c, 0, 1]
        w0 = 0.5 * om0 - angvel[p, 0]
        w1 = 0.5 * om1 - angvel[p, 1]
        w2 = 0.5 * om2 - angvel[p, 2]
        ur0 = uf[p, 0] - vel[p, 0]
        ur1 = uf[p, 1] - vel[p, 1]
        ur2 = uf[p, 2] - vel[p, 2]
        if torque_id == 1:
            k = rotational_drag_dennis_1980(d, rho, mu, math.sqrt(w0 * w0 + w1 * w1 + w2 * w2))
            krot[p] = k
            texp[p, 0] = 0.5 * k * om0
            texp[p, 1] = 0.5 * k * om1
            texp[p, 2] = 0.5 * k * om2
            tframe[p, 0] = k * w0
            tframe[p, 1] = k * w1
            tframe[p, 2] = k * w2
        if lift_id == 1:
            f0, f1, f2 = saffman_mei_1992(d, rho, mu, ur0, ur1, ur2, om0, om1, om2)
        elif lift_id == 2:
            f0, f1, f2 = magnus_oesterle_bui_dinh_1998(d, rho, mu, ur0, ur1, ur2, w0, w1, w2)
        else:
            f0, f1, f2 = 0.0, 0.0, 0.0
        flift[p, 0] = f0
        flift[p, 1] = f1
        flift[p, 2] = f2
        if vm:
            ma = cvm * rho * math.pi / 6.0 * d * d * d
            madd[p] = ma
            for i in range(3):
                fvm[p, i] = ma * acc[c, i]
    return flift, fvm, texp, krot, madd, tframe


@njit(cache=True, error_model="numpy")
def _scatter_sums(scells, sweights, beta, vel, hA, Tp, nc):
    """Per-cell sums over this rank's particles: sum w beta, sum w beta u_p, sum w hA,
    sum w hA T_p (summed over the ranks, then finished by _finish_terms)."""
    ksl = np.zeros(nc)
    us = np.zeros((nc, 3))
    simp = np.zeros(nc)
    sexp = np.zeros(nc)
    for p in range(scells.shape[0]):
        for j in range(scells.shape[1]):
            c = scells[p, j]
            if c < 0:
                continue
            w = sweights[p, j]
            wb = w * beta[p]
            ksl[c] += wb
            for i in range(3):
                us[c, i] += wb * vel[p, i]
            wh = w * hA[p]
            simp[c] += wh
            sexp[c] += wh * Tp[p]
    return ksl, us, simp, sexp


@njit(cache=True, error_model="numpy")
def _finish_terms(ksl, us, simp, sexp, V):
    """Ksl = sum w beta / V, Us = sum w beta u_p / sum w beta (volume-free beta-weighted
    mean), Simp = sum w hA / V, Sexp = sum w hA T_p / V, with the same stencil."""
    nc = V.shape[0]
    for c in range(nc):
        if ksl[c] > 0.0:
            for i in range(3):
                us[c, i] /= ksl[c]
        else:
            for i in range(3):
                us[c, i] = 0.0
        ksl[c] /= V[c]
        simp[c] /= V[c]
        sexp[c] /= V[c]
    return ksl, us, simp, sexp
