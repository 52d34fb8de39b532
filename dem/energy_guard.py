"""Energy guard: a closed mechanical system must not gain energy.

Without inputs (no moving or turning wall, no fluid force, gravity not along a periodic axis,
no particle added), contact damping and friction only remove energy, so the mechanical
energy

    E = sum_i (1/2 m v^2 + 1/2 I w^2 - m g . x)  +  sum_contacts (normal + tangential spring energy)

cannot grow. A run forced above the stability limits (time step near the contact time)
creates energy at each contact. ``EnergyGuard.check`` compares E between two compiled
chunks of the run loop (O(N + contacts), in a compiled helper) and raises SimulationError
when it grew by more than

    GAIN_TOLERANCE * (kinetic + rotational + elastic energy, the larger of the two checks,
                      + the work of gravity between them)  +  a round-off floor,

naming the particles with the largest gain, the steps and what to change.

Spring energies: Hertz normal 8/15 E* sqrt(R*) delta^(5/2), Mindlin tangential
1/2 S_t |xi|^2 with S_t = 8 G* sqrt(R* delta) at the current overlap (the no-slip spring
the force law uses; exact only for a fixed overlap, so the tangential part carries a small
error of the order of the tangential energy); linear 1/2 k_n delta^2 and 1/2 k_t |xi|^2.
The tangential part is capped at (mu F_n,el)^2 / (2 S_t), the most a spring at the Coulomb
limit can give back (while sliding, the stored xi also balances the tangential damping force).
Rolling springs (epsd) are not counted (their energy is a small part of the contact
energy; the tolerance covers it). GAIN_TOLERANCE is justified by measurements in
docs/reliability/memory_guard.md (benchmarks/energy_guard.py).
"""
import math

import numpy as np
from numba import njit

from .contact.walls import particle_wall, WF, WI
from .neighbors import pair_distance
from .step import FP, contact_law, pair_material

# relative energy gain between two checks that stops a run (see the module docstring)
GAIN_TOLERANCE = 0.05
# round-off floor, relative to sum m |g| (domain size) + the moving energy
ROUNDOFF = 1e-11


@njit(cache=True, error_model="numpy")
def particle_energies(P, C, W, TB, prm, nown, t, out):
    """Mechanical energy per owned particle into out[:nown, 0..3]: kinetic (+ rotational),
    potential (-m g.x), elastic (half of each pair contact, all of each wall contact).
    Returns the total elastic energy. P, C, W, TB, prm: the bundles of dem.schema."""
    x, v, w, r, m, inv_i, mat = P.position, P.velocity, P.angular_velocity, P.radius, P.mass, P.inv_inertia, P.material
    nb, nnb, hist, wnb, wnn, whist = C.nb, C.nnb, C.hist, P.wnb, P.wnn, P.whist
    wf, wi, tab, lo, hi, periodic = W.wf, W.wi, TB.tab, prm.lo, prm.hi, prm.periodic
    fp = prm.fp
    law = contact_law(prm.ip, fp)
    g = fp[FP.gx:FP.gz + 1]
    el_tot = 0.0
    for i in range(nown):
        ke = 0.5 * m[i] * (v[i, 0] * v[i, 0] + v[i, 1] * v[i, 1] + v[i, 2] * v[i, 2])
        ke += 0.5 * (w[i, 0] * w[i, 0] + w[i, 1] * w[i, 1] + w[i, 2] * w[i, 2]) / inv_i[i]
        out[i, 0] = ke
        out[i, 1] = -m[i] * (g[0] * x[i, 0] + g[1] * x[i, 1] + g[2] * x[i, 2])
        out[i, 2] = 0.0
    for i in range(nown):
        for s in range(nnb[i]):
            j = nb[i, s]
            dist = pair_distance(x, i, j, lo, hi, periodic)
            rs = r[i] + r[j]
            if dist >= rs:
                continue
            delta = rs - dist
            rstar = r[i] * r[j] / rs
            mstar = m[i] * m[j] / (m[i] + m[j])
            e = _spring_energy(law, pair_material(tab, mat[i], mat[j]), delta, rstar, mstar,
                               (hist[i, s, 0], hist[i, s, 1], hist[i, s, 2]))
            el_tot += e if j < nown else 0.5 * e
            out[i, 2] += 0.5 * e
            if j < nown:
                out[j, 2] += 0.5 * e
        for q in range(wnn[i]):
            wl = wnb[i, q]
            dist, nx, ny, nz = particle_wall(wf, wi, P.mcon, wl, i, x[i, 0], x[i, 1], x[i, 2], t)
            if dist >= r[i]:
                continue
            mw = np.int32(wi[wl, WI.mat])
            e = _spring_energy(law, pair_material(tab, mat[i], mw), r[i] - dist, r[i], m[i],
                               (whist[i, wl, 0], whist[i, wl, 1], whist[i, wl, 2]))
            el_tot += e
            out[i, 2] += e
    return el_tot


@njit(cache=True, error_model="numpy")
def _spring_energy(law, pm, delta, rstar, mstar, h):
    """Normal spring energy + the recoverable tangential spring energy of one contact by the
    run's law (dem.step.ContactLaw) for the material pair ``pm`` (dem.step.PairMaterial),
    ``h`` the stored tangential spring (a 3-tuple).

    The tangential part is 1/2 S_t |xi|^2, capped at (mu F_n,el)^2 / (2 S_t): a spring held
    at the Coulomb limit while sliding stores xi = -(F_t + c_t v_t) / S_t (the damping part
    included), of which only what the Coulomb force can give back is recoverable."""
    hx, hy, hz = h
    estar, gstar, mu = pm.estar, pm.gstar, pm.mu
    h2 = hx * hx + hy * hy + hz * hz
    if law.model == 0:  # Hertz-Mindlin
        sq = math.sqrt(rstar * delta)
        en = 8.0 / 15.0 * estar * sq * delta * delta
        fn = 4.0 / 3.0 * estar * sq * delta
        st = 8.0 * gstar * sq
    else:
        kn = law.lin_kn
        if kn <= 0.0:
            sr = math.sqrt(rstar)
            vchar = law.vchar
            kn = 16.0 / 15.0 * sr * estar * (15.0 * mstar * vchar * vchar / (16.0 * sr * estar)) ** 0.2
        en = 0.5 * kn * delta * delta
        fn = kn * delta
        st = law.kt_ratio * kn
    if st <= 0.0:
        return en
    return en + 0.5 * min(st * h2, (mu * fn) ** 2 / st)


def inputs_of(world):
    """Why the system is not closed (a list of reasons; empty: the guard applies); ``world``:
    dem.world.World."""
    why = []
    st = world.state
    if not world.scene.simulation["mechanics"]:
        why.append("mechanics frozen")
    nw = world.nwalls
    if nw and (np.any(st.wf[:nw, WF.vx:WF.vx + 3] != 0.0) or np.any(st.wf[:nw, WF.ox:WF.ox + 3] != 0.0)
               or any(w.get("oscillation") for w in world.scene.walls)):
        why.append("a wall moves or turns")
    g = np.asarray(st.fp[FP.gx:FP.gz + 1])
    if np.any(st.periodic & (g != 0.0)):
        why.append("gravity along a periodic axis")
    if st.features.get("fluid"):
        why.append("fluid forces")
    if world.flow is not None:
        why.append("particles enter or leave")
    return why


class EnergyGuard:
    """Checks at chunk boundaries of Simulation.run that the closed system gains no energy."""

    def __init__(self, sim, tolerance=None):
        self.sim = sim
        self.tolerance = GAIN_TOLERANCE if tolerance is None else tolerance
        self.why_off = inputs_of(sim.world)
        self.max_ratio = -math.inf  # largest gain / scale seen (for measuring the tolerance)
        self.prev = None
        if not self.why_off:
            self.prev = self._measure()

    @property
    def active(self):
        return not self.why_off

    def _measure(self):
        """(step, time, ids sorted, energies by id [n, 3] (kinetic, potential, elastic), totals)."""
        from . import step as K
        s = self.sim
        st = s.state
        nown = st.n_owned
        out = np.zeros((nown, 3))
        P, C, W, TB, prm = st.bundles()
        el = particle_energies(P, C, W, TB, prm, nown, s.time, out)
        g = float(np.linalg.norm(st.fp[K.FP.gx:K.FP.gz + 1]))
        tot = np.array([out[:, 0].sum(), out[:, 1].sum(), el, float(np.sum(st.mass[:nown])) * g])
        if s.par is not None:
            tot = s.par.allsum(tot)
        order = np.argsort(st.id[:nown], kind="stable")
        return s.step_count, s.time, st.id[:nown][order], out[order], tot

    def check(self):
        """Compare with the previous check; raise SimulationError on a gain above tolerance."""
        if not self.active:
            return
        if inputs_of(self.sim.world):  # fluid forces were set since (a coupled run): not closed any more
            self.why_off = inputs_of(self.sim.world)
            return
        cur = self._measure()
        s0, t0, ids0, e0, tot0 = self.prev
        s1, t1, ids1, e1, tot1 = cur
        self.prev = cur
        if s1 == s0:
            return
        E0 = tot0[0] + tot0[1] + tot0[2]
        E1 = tot1[0] + tot1[1] + tot1[2]
        moving = max(tot0[0] + tot0[2], tot1[0] + tot1[2])
        scale = moving + abs(tot1[1] - tot0[1])
        sim = self.sim
        floor = ROUNDOFF * (tot1[3] * float(np.max(sim.state.hi - sim.state.lo)) + moving) + 1e-300
        gain = E1 - E0
        ratio = gain / max(scale, floor)
        self.max_ratio = max(self.max_ratio, ratio)
        if gain <= self.tolerance * scale + floor:
            return
        from .errors import SimulationError
        raise SimulationError(self._message(gain, scale, s0, t0, s1, t1, ids0, e0, ids1, e1))

    def _message(self, gain, scale, s0, t0, s1, t1, ids0, e0, ids1, e1):
        sim = self.sim
        top = self._top_gainers(ids0, e0, ids1, e1)
        who = ", ".join(f"id {int(i)} (+{g:.3g} J)" for i, g in top)
        tr, th = sim.time_scales()[:2]
        fr, fh = sim.dt / tr, sim.dt / th
        from . import scene as scene_mod
        advice = (f"time_step {sim.dt:.3g} s is {fr:.3g} of the Rayleigh time {tr:.3g} s and {fh:.3g} of the "
                  f"Hertz collision time {th:.3g} s: reduce time_step below "
                  f"{min(scene_mod.RAYLEIGH_FRACTION * tr, scene_mod.HERTZ_FRACTION * th):.3g} s "
                  f"({scene_mod.RAYLEIGH_FRACTION} t_R, {scene_mod.HERTZ_FRACTION} t_H)")
        if sim.scene.simulation["force"]:
            advice += " and remove simulation.force = true"
        else:
            advice += " (or raise youngs_modulus / lower the impact speeds)"
        return (f"energy guard: the mechanical energy of this closed system (no moving wall, no fluid force) "
                f"grew by {gain:.3g} J, {100 * gain / scale:.3g} % of its kinetic + elastic energy "
                f"(allowed {100 * self.tolerance:g} %), between step {s0} (t = {t0:.6g} s) and step {s1} "
                f"(t = {t1:.6g} s); largest gains: {who or 'on another rank'}. The contacts are not resolved: "
                f"{advice}")

    def _top_gainers(self, ids0, e0, ids1, e1, k=3):
        """(id, gain) of the k particles with the largest energy gain (all ranks)."""
        pos = np.searchsorted(ids0, ids1)
        pos = np.minimum(pos, max(ids0.size - 1, 0))
        known = (ids0.size > 0) & (ids0[pos] == ids1) if ids0.size else np.zeros(ids1.size, bool)
        gain = np.full(ids1.size, -np.inf)
        gain[known] = e1[known].sum(1) - e0[pos[known]].sum(1)
        best = np.argsort(gain)[::-1][:k]
        top = [(int(ids1[b]), float(gain[b])) for b in best if np.isfinite(gain[b]) and gain[b] > 0]
        par = self.sim.par
        if par is not None:
            allt = [t for part in par.comm.allgather(top) for t in part]
            top = sorted(allt, key=lambda t: -t[1])[:k]
        return top
