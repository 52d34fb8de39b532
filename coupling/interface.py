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
from dataclasses import dataclass, field

import numpy as np

from . import voidfraction as vf
from .drag import drag_coefficients, drag_model_id
from .interpolate import interpolate

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
    mesh: object                      # coupling.mesh.PolyMesh
    sim: object                       # dem.Simulation
    gas: GasProperties
    drag: str = "di_felice_1994"
    void_fraction: str = "divided"
    interpolation: str = "cell"
    model_type: str = "A"
    eps_min: float = 0.3
    smoothing_time: float = 0.0       # s, 0 = off
    gravity: np.ndarray = field(default_factory=lambda: np.array([0.0, 0.0, -9.81]))
    n_satellites: int = 29
    heat: bool = True
    timer: PhaseTimer = field(default_factory=PhaseTimer)

    def __post_init__(self):
        self.drag_id = drag_model_id(self.drag)
        if self.model_type not in ("A", "B"):
            raise ValueError(f"modelType must be A or B, got {self.model_type!r}")
        self.V = self.mesh.cell_volumes
        self.hint = None
        self.eps_sent = None
        self.ksl_sent = None
        self.heat = bool(self.heat) and self.sim.thermal is not None
        self.last = {}
        self.n_lost = 0

    # ------------------------------------------------------------------ particle -> mesh
    def _stencil(self):
        st = self.sim.state
        n = st.n_owned
        pos, rad = st.position[:n], st.radius[:n]
        with self.timer("locate"):
            cells = self.mesh.locate(pos, hint=self.hint)
        with self.timer("void_fraction"):
            pw = vf.compute_weights(self.mesh, pos, rad, self.void_fraction, cell_hint=cells,
                                    n_satellites=self.n_satellites)
            eps = 1.0 - vf.solid_volume(pw, rad) / self.V
            eps = np.maximum(eps, self.eps_min)
        self.hint = pw.centre_cell
        self.n_lost = pw.n_lost
        return pw, eps

    def initial_void_fraction(self) -> np.ndarray:
        """Void fraction of the initial packing (write it into 0/eps before the solver
        starts, so that the gas sees no jump of eps at the first step)."""
        pw, eps = self._stencil()
        self.eps_sent = eps.copy()
        return eps

    def reset_hints(self):
        """Call after the DEM reordered its particles (sim.sort_particles)."""
        self.hint = None

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
        pw, eps_raw = self._stencil()
        eps = self._relax(self.eps_sent, eps_raw, dt_cfd)
        self.eps_sent = eps

        with self.timer("interpolation"):
            cells = pw.centre_cell
            m = self.interpolation
            uf = interpolate(self.mesh, fluid["U"], pos, cells, m)
            gradp = interpolate(self.mesh, fluid["gradp"], pos, cells, m)
            tg = interpolate(self.mesh, fluid["T"], pos, cells, m) if self.heat else None
            # void fraction at the particle: stencil-weighted mean of the sent field, so a
            # particle spread over several cells sees what the gas sees there
            c = np.where(pw.cells >= 0, pw.cells, 0)
            wsum = pw.weights.sum(axis=1)
            eps_p = np.where(wsum > 0, (pw.weights * eps[c]).sum(axis=1) / np.where(wsum > 0, wsum, 1), 1.0)
            lost = cells < 0
            if np.any(lost):  # outside the mesh: no fluid force, gas at rest
                uf[lost] = 0.0
                gradp[lost] = 0.0
                if tg is not None:
                    tg[lost] = np.nan

        with self.timer("exchange_terms"):
            d = 2.0 * rad
            rel = uf - vel
            ur = np.sqrt((rel * rel).sum(axis=1))
            beta = drag_coefficients(self.drag_id, np.ascontiguousarray(d), np.ascontiguousarray(eps_p),
                                     self.gas.rho, self.gas.mu, ur)
            if self.model_type == "B":
                beta = beta / eps_p
            beta[lost] = 0.0
            vp = (math.pi / 6.0) * d ** 3
            force = beta[:, None] * rel
            if self.model_type == "A":
                force -= vp[:, None] * gradp
            else:
                force -= self.gas.rho * vp[:, None] * self.gravity[None, :]
            force[lost] = 0.0
            ksl_raw = vf.drag_coefficient_sum(pw, beta, self.V)
            ksl = self._relax(self.ksl_sent, ksl_raw, dt_cfd)
            self.ksl_sent = ksl
            us = vf.mean_particle_velocity(pw, rad, vel, weights=np.where(beta > 0, beta, vp * 1e-30))
            if self.heat:
                tgas = np.where(lost, st.temperature[:n], tg)
                sim.set_fluid(force=force, velocity=uf, temperature=tgas, porosity=eps_p)
                hA = sim.thermal.convection_h()[:n]
                hA[lost] = 0.0
                simp, sexp = vf.heat_sources(pw, hA, st.temperature[:n], self.V)
            else:
                sim.set_fluid(force=force)
                hA = np.zeros(n)
                simp = np.zeros(self.mesh.n_cells)
                sexp = np.zeros(self.mesh.n_cells)
        self.last = dict(beta=beta, force=force, hA=hA, eps_p=eps_p, uf=uf, eps_raw=eps_raw,
                         Tg=tg)
        return dict(eps=eps, Ksl=ksl, Us=us, Simp=simp, Sexp=sexp)

    def advance_dem(self, k: int) -> None:
        with self.timer("dem"):
            self.sim.step(k)
