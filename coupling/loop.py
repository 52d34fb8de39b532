"""The driver loop of a coupled run, written once: the same on every DEM rank, for a fresh
start and a restart alike. It talks to the gas solver only through a link of
coupling.transport (first/send/receive, own_stop), to the particles only through the
coupling interface (coupling.interface: prepare, advance_dem, map_particles), and hands
the output steps and restart points to the callables it is given (coupling.diagnostics
Outputs, coupling.restart RestartPoints).
"""
from __future__ import annotations

from dataclasses import dataclass


@dataclass(frozen=True)
class LoopPlan:
    """The coupling steps of a run: ``n_steps`` from global index ``i0`` at ``t_start`` (s),
    CFD step ``dt`` (s) = ``k`` DEM steps; output every ``out_every`` coupling steps, a
    restart point every ``write_every`` (0: none between start and end); ``restart`` with
    the loaded coupling state ``cstate`` (coupling.restart) or a fresh start (None)."""

    n_steps: int
    i0: int
    t_start: float
    dt: float
    k: int
    out_every: int
    write_every: int
    restart: bool = False
    cstate: dict | None = None


class CoupledLoop:
    """The coupled loop, the same on every DEM rank (rank 0 talks to the gas solver through
    its link, the other ranks receive what rank 0 got: :mod:`coupling.transport`), for a
    fresh start and a restart alike. Coupling step s
    (global index ``step = i0 + s``, time t -> t + dt):

    1. a stop request of this process (rank 0; every rank learns it with the next frame)
       makes this the last step;
    2. ``iface.prepare``: the exchange fields of the particles at t, the fluid force and heat
       set as the DEM's input for the interval (Simulation.set_fluid);
    3. (first step of a fresh run) the output of t = t_start;
    4. the frame is sent (FINAL flag on the last step), the DEM advances ``k`` steps while
       the gas solves the same interval, the particles are mapped for the next step;
    5. the gas frame of t + dt is received and checked (check_gas_fields);
    6. output every ``out_every`` coupling steps, a restart point every ``write_every``
       steps (the solver's writeInterval), both at the last step (end, stop or the solver's
       FINAL frame)."""

    def __init__(self, link, iface, watch, output, restart_point, plan: LoopPlan, *, log, ledger=None,
                 particle_energy=None, split=None):
        from dem.operations import Every
        self.link, self.iface, self.watch = link, iface, watch
        self.output, self.restart_point = output, restart_point
        self.n_steps, self.i0, self.t_start, self.dt, self.k = plan.n_steps, plan.i0, plan.t_start, plan.dt, plan.k
        self.outputs = Every(plan.out_every)            # in coupling steps of this run
        self.restart_points = Every(plan.write_every)   # in coupling steps since t = 0 (OpenFOAM's writes)
        self.restart, self.cstate, self.log = plan.restart, plan.cstate, log
        self.ledger, self.particle_energy = ledger, particle_energy   # the energy balance (coupling.energy)
        self.split = split   # tied walls: the particles' paths per cell (coupling.energy.FluxSplit)
        self.step, self.t = self.i0, self.t_start
        self.stop_sig = 0   # SIGINT/SIGTERM of this process (rank 0 decides for every DEM rank)
        self.peer_sig = 0   # the signal that stopped the gas solver (other ranks: either signal)

    def run(self):
        from dem.operations import PAUSE
        link, iface, dt = self.link, self.iface, self.dt
        fluid = link.first(self.i0, self.t_start, self.cstate)
        ledger = self.ledger
        if ledger is not None:
            ledger.check(fluid["scalars"], self.i0)
            ledger.begin(fluid["scalars"], self.particle_energy())   # collective
        for s in range(1, self.n_steps + 1):
            self.step = step = self.i0 + s
            self.stop_sig = self.stop_sig or link.own_stop()
            last = s == self.n_steps or bool(self.stop_sig)   # a stop request ends this coupling step
            frame = iface.prepare(fluid, dt)
            if self.split:
                frame["wall_columns"] = self.split.columns(iface.sim, dt, iface.cells)   # collective
            self.watch.after_prepare(iface, self.t)
            if s == 1 and not self.restart:
                self.output(fluid, frame, self.t, step - 1)
            link.send(step, frame, self.t + dt, last)
            iface.advance_dem(self.k)
            self.t = t = self.t_start + s * dt
            if s < self.n_steps:   # (also on a stop step: every DEM rank does it, collectively)
                iface.map_particles()   # overlaps with the gas solve
            fluid, final, self.peer_sig = link.receive(step, t, iface.eps_change, self.stop_sig)
            if ledger is not None:
                ledger.check(fluid["scalars"], step)
                ledger.add(fluid["scalars"], dt)
            self.watch.after_receive(fluid, t)
            # peer_sig implies a FINAL frame; on the other ranks it also carries rank 0's stop
            done = last or final or bool(self.peer_sig)
            if self.outputs.fires(s, PAUSE) or done:
                self.output(fluid, frame, t, step)
            if done or self.restart_points.fires(step, PAUSE):
                self.restart_point(step, t, fluid)
            if done:
                if final and not last and not self.peer_sig:
                    self.log(f"coupling: the solver reached its endTime at step {step} (t = {t:g} s)")
                break
