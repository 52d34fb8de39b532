"""The writers: what a run reports and writes, from the declared state (dem.schema).

    out = Writers(world, stepper)
    out.history_row(); out.write_vtk(vtk); out.final_arrays(); out.wall_heat_totals()

Owns the rows of history.csv (sums, minima and maxima over the ranks), the wall heat totals,
the per-particle output fields (every array declared with an ``output`` name), final.npz (one
file ordered by id in a serial run; under MPI one piece per rank and a manifest, dem.final), the
VTK frames (under MPI each rank writes
its own piece: no rank gathers the particles of the others), and the writes of one rank: under
MPI a write that fails on any rank is held (the other ranks are on their way to the next
collective call) until :meth:`settle_writes` raises it on every rank, naming that rank.
"""
import math
import os

import numpy as np

from .contact.walls import per_wall

from . import schema as S
from .output import OutputError
from .thermal.kernel import MECHANISMS as THERMAL_MECHANISMS


class Writers:
    def __init__(self, world, stepper):
        self.world = world
        self.state = world.state
        self.stepper = stepper
        self.par = stepper.par
        self.hold = False           # inside a run under MPI: hold a rank's write failures
        self._failure = None

    @property
    def is_root(self):
        """True on the rank that writes files (always in a serial run)."""
        return self.par is None or self.par.rank == 0

    # ------------------------------------------------------------------ writes of one rank
    def root_write(self, write):
        """A write done by the root alone. Inside run() under MPI an OutputError is held (the other ranks are on their way to
        the next collective call) until :meth:`settle_writes` raises it on every rank; elsewhere it
        is raised at once."""
        try:
            write()
        except OutputError as exc:
            if self.par is None or not self.hold:
                raise
            if self._failure is None:
                self._failure = exc

    def root_first(self, write):
        """A write done by the root that the other ranks wait for (collective under MPI: the
        folder they then write in). A failure raises the same OutputError, naming the root, on
        every rank at once, inside run() or not: a rank never waits for a root that gave up."""
        if self.par is None:
            write()
            return
        err = None
        if self.is_root:
            try:
                write()
            except OutputError as exc:
                err = str(exc)
        self._raise_any(err)   # an Allreduce: no rank goes on before the root has written

    def each_rank_write(self, write):
        """A write done by every rank, each its own file (collective under MPI): a failure on any
        rank raises the same OutputError, naming that rank, on every rank at once."""
        if self.par is None:
            write()
            return
        err = None
        try:
            write()
        except OutputError as exc:
            err = str(exc)
        self._raise_any(err)

    def _raise_any(self, msg):
        """Collective: when any rank has a failure message, raise it on every rank, naming the rank
        (one Allreduce of a flag; the messages are gathered only when a write failed)."""
        if not self.par.allmax(1.0 if msg is not None else 0.0):
            return
        msgs = self.par.comm.allgather(msg)
        rank = next(r for r, m in enumerate(msgs) if m)
        raise OutputError(message=f"{msgs[rank]} [rank {rank} of {len(msgs)}]")

    def settle_writes(self):
        """Raise a held OutputError of any rank on every rank, naming that rank (collective under
        MPI)."""
        if self.par is None:
            return
        held, self._failure = self._failure, None
        try:
            self._raise_any(str(held) if held is not None else None)
        except OutputError:
            self.hold = False
            raise

    def begin(self):
        """A run starts: no failure held yet, failures held from now on."""
        self._failure = None
        self.hold = True

    # ------------------------------------------------------------------ history
    def history_columns(self):
        cols = ["time", "kinetic_energy", "rotational_energy", "contacts", "max_overlap_ratio"]
        if self.world.thermal is not None:
            cols += self.world.thermal.history_columns()
        if self.world.flow is not None:
            cols += self.world.flow.history_columns()
        return cols

    def history_row(self):
        """One row of history.csv (collective in a parallel run: sums, minima, maxima)."""
        w = self.world
        st = self.state
        th = w.thermal
        et, er = st.kinetic_energy()
        maxov = self._overlap_stats()
        if self.par is None:
            row = dict(time=w.time, kinetic_energy=et, rotational_energy=er,
                       contacts=self.stepper.last_contacts, max_overlap_ratio=maxov)
            if th is not None:
                row.update(th.history_row())
            if w.flow is not None:
                row.update(zip(w.flow.history_columns(), w.flow.history_values()))
            return row
        p = self.par
        n = st.n_owned
        vals = [et, er, float(self.stepper.pair_count), float(n)]
        if th is not None:
            T = st.temperature[:n]
            vals += [float(np.sum(T / st.inv_heat_capacity[:n])), float(T.sum())]
            vals += list(th.tot[:len(THERMAL_MECHANISMS)]) + list(per_wall(th.wtot, w.scene.walls))
        tot = p.allsum(np.array(vals))
        row = dict(time=w.time, kinetic_energy=tot[0], rotational_energy=tot[1],
                   contacts=int(tot[2]) // 2, max_overlap_ratio=p.allmax(maxov))
        if th is not None:
            T = st.temperature[:n]
            tmin = p.allmin(float(T.min()) if n else math.inf)
            tmax = p.allmax(float(T.max()) if n else -math.inf)
            row.update(thermal_energy=tot[4], T_mean=tot[5] / max(tot[3], 1), T_min=tmin, T_max=tmax)
            k = 6
            for m in THERMAL_MECHANISMS:
                row[f"E_{m}"] = tot[k]
                k += 1
            for wall in w.scene.walls:
                row[f"E_wall_{wall['name']}"] = tot[k]
                k += 1
        if w.flow is not None:
            row.update(zip(w.flow.history_columns(), p.allsum(np.array(w.flow.history_values()))))
        return row

    def _overlap_stats(self):
        from .stats import max_overlap_ratio
        st = self.state
        return max_overlap_ratio(st.n, st.position, st.radius, st.nb, st.nnb, st.lo, st.hi,
                                 st.periodic, st.wf, st.wi, self.world.nwalls, self.world.time)

    def wall_heat_totals(self):
        """Heat through each wall since the start (J), summed over the ranks (collective):
        [n_walls, 3] of (all paths, across the gas gap, by radiation); None without heat or
        walls."""
        walls = self.world.scene.walls
        nw = len(walls)
        if self.world.thermal is None or nw == 0:
            return None
        st = self.state
        a = np.c_[per_wall(st.wtot, walls), per_wall(st.wgap, walls), per_wall(st.wrad, walls)].astype(float)
        if self.par is not None:
            a = np.asarray(self.par.allsum(a.ravel()), float).reshape(nw, 3)
        return a

    # ------------------------------------------------------------------ per-particle output
    def output_arrays(self):
        """The owned rows of every enabled array declared with an output name (dem.schema); with
        [output] heat_by_mechanism, the columns of qmech as ``heat_<mechanism>``
        (dem.thermal.heat.QM): heat_direct, heat_indirect, heat_wall, heat_conv, heat_rad,
        heat_gen, heat_src (W), those of the mechanisms the scene runs."""
        st = self.state
        n = st.n_owned
        out = {f.output: getattr(st, f.name)[:n] for f in S.FIELDS
               if f.output and f.owner == "particle" and S.enabled(f, st.features)}
        if self.world.scene.output.get("contacts"):
            out.update(self.contact_fields())
        if st.features.get("heat_output"):
            from .thermal.heat import QM
            for k, name in enumerate(QM._fields):
                if name != "SIZE" and k in self.world.thermal.mechanism_columns():
                    out[f"heat_{name}"] = np.ascontiguousarray(st.qmech[:n, k])
        return out

    def contact_fields(self):
        """[output] contacts: per owned particle ``contact_force`` (N, the sum of its contact
        forces of the last evaluation, pairs and walls: the total force less gravity and the
        fluid's explicit force) and ``coordination`` (its touching particles and walls now)."""
        from .stats import touching_pairs, wall_touches
        st = self.state
        w = self.world
        n = st.n_owned
        body = st.mass[:n, None] * np.asarray(w.scene.simulation["gravity"], float)[None, :]
        cf = st.force[:n] - body
        if st.external_force.shape[0] >= n and n:
            cf = cf - st.external_force[:n]
        _, _, _, _, cnt = touching_pairs(st)
        nw = wall_touches(st.position, st.radius, st.wnb, st.wnn, st.wf, st.wi, st.mcon, n, w.time)
        return {"contact_force": np.ascontiguousarray(cf), "coordination": (cnt[:n] + nw).astype(np.float64)}

    def contact_network(self):
        """[output] contacts: this rank's touching pairs as lines between the two centres (the
        second by the minimum image), each pair once over the ranks (a pair with a ghost on the
        rank of the smaller id; a line from the smaller id, a, to the larger, b), with cell data
        ``normal_force`` (N, the elastic normal force of
        the run's law at the overlap: Hertz 4/3 E* sqrt(R*) delta^3/2, linear k_n delta),
        ``overlap`` (m), ``id_a``, ``id_b`` and, with heat, ``heat_flow`` (W, from a to b through
        the pair's conductance of the last evaluation at the temperatures now: direct and gas
        gap). Returns (points (2k, 3), lines (k, 2), cell fields)."""
        from .stats import touching_pairs
        from . import step as K
        st = self.state
        ii, jj, dd, ss, _ = touching_pairs(st)
        ids = st.id
        keep = (jj < st.n_owned) | (ids[ii] < ids[jj])
        ii, jj, dd, ss = ii[keep], jj[keep], dd[keep], ss[keep]
        h = None
        if self.world.thermal is not None:   # (the slot's conductance, before a and b are ordered)
            h = st.Hd[ii, ss] + (st.Hi[ii, ss] if st.Hi.shape[0] == st.Hd.shape[0] else 0.0)
        swap = ids[ii] > ids[jj]   # each line from the smaller id to the larger: the same on any ranks
        ii, jj = np.where(swap, jj, ii), np.where(swap, ii, jj)
        x = st.position
        dv = x[jj] - x[ii]
        L = st.hi - st.lo
        for k in range(3):
            if st.periodic[k]:
                dv[:, k] -= L[k] * np.floor(dv[:, k] / L[k] + 0.5)
        pts = np.empty((2 * ii.size, 3))
        pts[0::2] = x[ii]
        pts[1::2] = x[ii] + dv
        lines = np.arange(2 * ii.size, dtype=np.int64).reshape(-1, 2)
        ri, rj = st.radius[ii], st.radius[jj]
        delta = ri + rj - dd
        rstar = ri * rj / (ri + rj)
        mi, mj = st.material[ii], st.material[jj]
        estar = st.tab[K.TAB.estar, mi, mj]
        if st.ip[K.IP.contact] == 0:
            fn = 4.0 / 3.0 * estar * np.sqrt(rstar) * delta ** 1.5
        else:
            kn = float(st.fp[K.FP.linkn])
            if kn <= 0.0:   # the Hertz-equivalent stiffness at the characteristic velocity (dem.step._pair_law)
                mstar = 1.0 / (st.inv_mass[ii] + st.inv_mass[jj])
                sr = np.sqrt(rstar)
                vc = float(st.fp[K.FP.vchar])
                kn = 16.0 / 15.0 * sr * estar * (15.0 * mstar * vc * vc / (16.0 * sr * estar)) ** 0.2
            fn = kn * delta
        cells = {"normal_force": fn, "overlap": delta, "id_a": ids[ii].astype(np.float64),
                 "id_b": ids[jj].astype(np.float64)}
        if h is not None:
            cells["heat_flow"] = h * (st.temperature[ii] - st.temperature[jj])
        return pts, lines, {k: np.ascontiguousarray(v) for k, v in cells.items()}

    def particle_fields(self):
        """Per-particle fields of the VTK output (float64; the position goes apart)."""
        f = {k: (a if a.dtype == np.float64 else a.astype(np.float64))
             for k, a in self.output_arrays().items() if k != "position"}
        if self.par is not None:
            f["rank"] = np.full(self.state.n_owned, float(self.par.rank))
        return f

    def gather_by_id(self, arrays):
        """Owned rows of every rank, concatenated and ordered by particle id, on the root
        (None elsewhere); a serial run just orders its rows."""
        parts = [arrays] if self.par is None else self.par.gather(arrays)
        return None if parts is None else by_id(parts)

    def final_arrays(self):
        """Per-particle results ordered by id (collective; None on ranks other than the root)."""
        out = self.gather_by_id(self.output_arrays())
        if out is not None:
            out["time"] = np.float64(self.world.time)
        return out

    def write_final(self, path):
        """final.npz (collective): a serial run writes the arrays ordered by id in one file; under
        MPI each rank writes its own rows as a piece and the root the manifest after every piece is
        on disk (dem.final: nothing is gathered but a digest and three numbers per rank), then
        removes the pieces of earlier final outputs. A rank that cannot write its piece stops every
        rank at once (naming it); the previous final output stays as it was."""
        from . import final as F
        from .output import save_npz
        folder = F.pieces_folder(path)
        if self.par is None:
            fa = self.final_arrays()
            written = []
            self.root_write(lambda: written.append(save_npz(path, **fa)))
            if written and os.path.isdir(folder):   # an earlier MPI run's final output in this folder
                F.remove_stale_pieces(folder, ())
            return
        from .output import make_folder
        par = self.par
        comm = par.comm
        self.root_first(lambda: make_folder(folder))
        # a fresh token per final output (a piece never replaces one that a manifest names), sent
        # by the root once the folder exists: no rank writes in it before
        token = np.array([int.from_bytes(os.urandom(4), "little") if self.is_root else 0], np.int64)
        comm.Bcast(token, root=0)
        name = F.piece_name(self.world.step_count, int(token[0]), par.rank)
        got = []
        self.each_rank_write(lambda: got.append(F.write_piece(os.path.join(folder, name), self.output_arrays())))
        digest, rows, idmin, idmax = got[0]
        sums = np.empty((par.size, 64), np.uint8) if self.is_root else None
        info = np.empty((par.size, 3), np.int64) if self.is_root else None
        comm.Gather(np.frombuffer(digest.encode(), np.uint8).copy(), sums, root=0)
        comm.Gather(np.array([rows, idmin, idmax], np.int64), info, root=0)
        if self.is_root:
            names = [F.piece_name(self.world.step_count, int(token[0]), r) for r in range(par.size)]
            digests = [bytes(d).decode() for d in sums]
            man = F.manifest(self.world.time, self.world.step_count, names, digests, info)
            written = []
            self.root_write(lambda: written.append(save_npz(path, durable=True, **man)))
            if written:
                F.remove_stale_pieces(folder, set(names))

    def vtk_series(self, out_dir, name="particles"):
        """The VTK series of this rank (dem.output.VTKSeries: every rank writes its own piece
        under MPI; the root the frame and the .pvd). Collective under MPI: the root creates the
        vtk/ folder (recorded in the output folder's manifest) before any rank writes in it."""
        from .output import VTKSeries, make_folder
        if self.par is None:
            return VTKSeries(out_dir, name=name)
        vtk = VTKSeries(out_dir, name=name, rank=self.par.rank, ranks=self.par.size)
        self.root_first(lambda: make_folder(vtk.dir))
        return vtk

    def write_vtk(self, vtk, **extra):
        """One VTK output of the owned particles of every rank (collective; ``vtk``: this rank's
        :meth:`vtk_series`); ``extra``: more per-particle fields. One process writes the frame
        ordered by id; under MPI each rank writes its own rows as a piece (nothing is gathered
        but one flag per rank on the root: which ranks wrote a piece)."""
        st = self.state
        w = self.world
        f = dict(self.particle_fields(), **extra)
        pos = st.position[:st.n_owned]
        if self.par is None:
            f["position"] = pos
            f = by_id([f])
            pos = f.pop("position")
            self.root_write(lambda: vtk.write(w.time, w.step_count, pos, f))
            return
        self.each_rank_write(lambda: vtk.write_piece(w.step_count, pos, f) if st.n_owned else None)
        wrote = self.par.comm.gather(st.n_owned > 0, root=0)   # one flag per rank, on the root
        if self.is_root:
            pieces = [r for r, has in enumerate(wrote) if has]
            self.root_write(lambda: vtk.write_frame(w.time, w.step_count, pieces, f))


    def write_contacts(self, series):
        """One frame of contacts.pvd (collective; ``series``: this rank's
        :meth:`vtk_series` named "contacts"): the contact network of :meth:`contact_network`,
        one .vtu in a serial run, under MPI a piece per rank that has a pair and the root's
        .pvtu naming them (cell data)."""
        w = self.world
        if self.par is not None and w.thermal is not None:
            # the ghosts' temperatures of now (a step forwards them before its own heat exchange)
            self.par.forward(w, motion=False, temperature=True)
        pts, lines, cells = self.contact_network()
        if self.par is None:
            self.root_write(lambda: series.write_lines(w.time, w.step_count, pts, lines, cells))
            return
        has = lines.shape[0] > 0
        self.each_rank_write(lambda: series.write_lines_piece(w.step_count, pts, lines, cells) if has else None)
        wrote = self.par.comm.gather(has, root=0)
        if self.is_root:
            pieces = [r for r, h in enumerate(wrote) if h]
            self.root_write(lambda: series.write_frame(w.time, w.step_count, pieces, cells, cells=True))


def by_id(parts):
    """Dicts of per-particle arrays (one per rank, each with an ``id``) as one, ordered by id."""
    out = {k: np.concatenate([p[k] for p in parts]) for k in parts[0]}
    order = np.argsort(out["id"], kind="stable")
    return {k: np.ascontiguousarray(v[order]) for k, v in out.items()}
