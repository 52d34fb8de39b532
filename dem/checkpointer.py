"""The checkpointer: writes, verifies and loads checkpoints of a running simulation.

    ck = Checkpointer(sim)      # the Simulation: its world, stepper and writers, and the scene
    ck.write(path); ck.prepare(path); ck.load(path)

Owns what a checkpoint holds (every array declared with a ``checkpoint`` key in dem.schema,
the run totals and the clock), the serial layout (the neighbour list and its history slots:
a bit-exact continuation) and the portable layout (per-particle arrays by id and the contact
history as id-keyed records: any number of ranks continues it), and the restart with an edited
scene (dem.checkpoint: format, validation and the plan of the edits).
"""
import os

import numpy as np

from . import schema as S
from . import step as K
from .errors import SceneError, SimulationError


class Checkpointer:
    def __init__(self, sim):
        self.sim = sim
        self.world = sim.world
        self.state = sim.world.state
        self.stepper = sim.stepper
        self.writers = sim.writers
        self.par = sim.stepper.par
        self._ready = None               # (path, arrays, record, plan) of prepare()
        self._recompute = False          # an older checkpoint lacked a conductance
        self.applied = []                # the scene edits the last restart applied
        self.rows_read = None            # (rows taken, rows read) of the pieces at the last prepare

    def _checkpointed(self, owner):
        """The enabled arrays of ``owner`` with a checkpoint key (dem.schema)."""
        return [f for f in S.of(owner) if f.checkpoint and S.enabled(f, self.state.features)]

    # ------------------------------------------------------------------ writing
    def _common(self):
        """The run's scalars a checkpoint holds beside the arrays."""
        st = self.state
        w = self.world
        out = dict(fp_tbuild=np.float64(st.fp[K.FP.tbuild]), fp_skin=np.float64(st.fp[K.FP.skin]),
                   fp_gapd=np.float64(st.fp[K.FP.gapd]), step_count=np.int64(w.step_count),
                   dt=np.float64(w.dt), forces_ready=np.bool_(self.stepper.forces_ready),
                   scene_file=np.str_(os.path.abspath(w.scene.file)),
                   ranks=np.int64(1 if self.par is None else self.par.size))
        if w.flow is not None:   # the next id and the inlets' debts (the same on every rank)
            out.update(w.flow.saved())
        return out

    def _total_fields(self):
        """The run totals' declared arrays: heat per mechanism and per wall (with heat), the
        particles in and out (dem.flow)."""
        fs = self._checkpointed("wall") + self._checkpointed("param")
        return fs if self.world.thermal is not None else [f for f in fs if f.when == "flow"]

    def _totals(self):
        """The run totals (heat per mechanism and per wall), summed over the ranks (collective)."""
        st = self.state
        totals = {f.checkpoint: getattr(st, f.name) for f in self._total_fields()}
        return totals if self.par is None else {k: self.par.allsum(v) for k, v in totals.items()}

    def _records(self):
        from .parallel import records
        return {f"rec_{k}": v for k, v in records.extract(self.state).items() if v is not None}

    def arrays(self):
        """Everything needed to continue a serial run, as declared in dem.schema: the
        per-particle arrays, the neighbour list and its history slots (bit-exact restart), the
        contact history as id-keyed records (so that any number of ranks can continue it), the
        totals and the clock."""
        st = self.state
        arr = {f.checkpoint: getattr(st, f.name) for f in self._checkpointed("particle") + self._checkpointed("pair")}
        arr.update(**self._common(), **self._records(), **self._totals())
        return arr

    def write(self, path):
        """Write a checkpoint (collective): one process, :meth:`arrays` with a format version,
        the scene's record and a checksum (dem.checkpoint); under MPI, one piece per rank and
        the root's manifest (:meth:`_write_pieces`)."""
        from . import checkpoint as ckpt
        if self.par is not None:
            return self._write_pieces(path)
        arr = self.arrays()
        record = ckpt.scene_record(self.sim)
        self.writers.root_write(lambda: ckpt.write(path, arr, record))

    def _write_pieces(self, path):
        """Each rank writes its owned particles and contact records as a piece; the root writes
        the manifest after every piece is on disk (a gather of one (name, sha256, rows) per
        rank), then removes the pieces of earlier checkpoints. A rank that cannot write its
        piece stops every rank at once (naming it) and the previous checkpoint stays as it was."""
        from . import checkpoint as ckpt
        from .output import make_folder
        st = self.state
        par = self.par
        folder = ckpt.pieces_folder(path)
        self.writers.root_first(lambda: make_folder(folder))   # before any rank writes in it
        n = st.n_owned
        piece = {f.checkpoint: getattr(st, f.name)[:n] for f in self._checkpointed("particle")}
        piece.update(self._records())
        name = ckpt.piece_name(self.world.step_count, par.rank)
        digest = []
        self.writers.each_rank_write(lambda: digest.append(ckpt.write_piece(os.path.join(folder, name), piece)))
        sums = np.empty((par.size, 64), np.uint8) if self.writers.is_root else None
        rows = np.empty(par.size, np.int64) if self.writers.is_root else None
        par.comm.Gather(np.frombuffer(digest[0].encode(), np.uint8).copy(), sums, root=0)   # typed: no pickle
        par.comm.Gather(np.array([n], np.int64), rows, root=0)
        manifest = dict(**self._common(), **self._totals())   # collective sums, on every rank
        if self.writers.is_root:
            pieces = [(ckpt.piece_name(self.world.step_count, r), bytes(sums[r]).decode(), int(rows[r]))
                      for r in range(par.size)]
            arr = ckpt.manifest(manifest, pieces)
            record = ckpt.scene_record(self.sim)
            written = []
            self.writers.root_write(lambda: written.append(ckpt.write(path, arr, record)))
            if written:
                ckpt.remove_stale_pieces(folder, {p[0] for p in pieces})

    # ------------------------------------------------------------------ loading
    def prepare(self, path):
        """Read and verify a checkpoint and plan the restart with this scene: raises
        dem.errors.SceneError (bad file, or a refused scene edit) before any output is written
        or any kernel compiled. :meth:`load` uses the result. An MPI checkpoint (a manifest and
        its pieces) is read by slices: rank r of M reads rows [r N / M, (r + 1) N / M) of the
        pieces, whatever their number (the particles then travel to their owners); the pieces of
        an older checkpoint, every M-th whole. Collective under MPI (a refusal on one rank is
        raised on every rank)."""
        from . import checkpoint as ckpt
        if self.par is None:
            return self._prepare(path)
        err = None
        try:
            plan = self._prepare(path)
        except SceneError as exc:
            err = (exc.file, exc.path, exc.message)
        errs = [e for e in self.par.comm.allgather(err) if e is not None]
        if errs:
            raise ckpt.CheckpointError(errs[0][0], errs[0][2], key=errs[0][1] or "")
        self._report_rows()
        return plan

    def _report_rows(self):
        """The rows each rank took and read from the pieces (collective; one line on the root)."""
        got = np.array(self.rows_read if self.rows_read is not None else (-1, -1), np.int64)
        every = np.empty((self.par.size, 2), np.int64)
        self.par.comm.Allgather(got, every)
        if self.writers.is_root and every[0, 0] >= 0:
            n = int(every[:, 0].sum())
            print(f"restart: {n} particles read by slices on {self.par.size} ranks (at most "
                  f"{-(-n // self.par.size)} each): rows taken per rank {every[:, 0].tolist()}, rows read "
                  f"per rank {every[:, 1].tolist()}", flush=True)

    def _prepare(self, path):
        from . import checkpoint as ckpt
        arrays, record = ckpt.read(path)
        subset = False
        self.rows_read = None
        if ckpt.is_manifest(arrays) and ckpt.sliced(arrays):   # each rank an even share of the rows
            rank, size = (0, 1) if self.par is None else (self.par.rank, self.par.size)
            arrays, read = ckpt.load_slices(path, arrays, ckpt.shares(arrays, rank, size))
            self.rows_read = (arrays["state_id"].size, read)
            subset = self.par is not None
        elif ckpt.is_manifest(arrays):   # version-1 pieces: every size-th piece, whole
            n = len(arrays["pieces"])
            which = range(n) if self.par is None else range(self.par.rank, n, self.par.size)
            arrays = ckpt.load_pieces(path, arrays, which)
            subset = self.par is not None
        ckpt.validate(path, arrays, record, subset=subset)
        plan = ckpt.plan_restart(self.sim, path, arrays, record)
        self._ready = (os.fspath(path), arrays, record, plan, subset)
        return plan

    def load(self, path):
        """Continue from a checkpoint. Unchanged scene: the serial layout restarts bit-exact.
        Edited scene: the changes of dem.checkpoint.plan_restart are applied to the checkpoint's
        arrays and listed on stdout ("restart: applied ...")."""
        from . import checkpoint as ckpt
        if self._ready is None or self._ready[0] != os.fspath(path):
            self.prepare(path)
        _, arrays, record, plan, subset = self._ready
        self._ready = None
        ckpt.apply_edits(arrays, plan, self.sim)
        self.world.n_total = int(record["particles"]["n"])   # (the particles of that time: dem.flow)
        z = ckpt.ArrayView(arrays)
        self._recompute = False
        if self.par is not None or int(z["ranks"]) != 1 or "nb" not in z.files or plan.rebuild:
            self._load_portable(path, z, subset)
        else:
            self._load_serial(z)
        if plan.recompute_forces or self._recompute:
            self.stepper.recompute_forces_keeping_history()
        self.applied = plan.applied
        if self.writers.is_root:
            for line in plan.applied:
                print(f"restart: applied {line}", flush=True)

    def _load_array(self, f, z, rows, path=None):
        """Set the declared array ``f`` from the checkpoint (the given rows); False when an
        older checkpoint lacks it (dem.checkpoint.ADDED_LATER)."""
        from .checkpoint import ADDED_LATER
        if f.checkpoint not in z.files:
            if f.checkpoint not in ADDED_LATER:
                where = f"{path}: " if path is not None else ""
                raise SimulationError(f"{where}checkpoint lacks {f.checkpoint!r} (thermal or contact settings "
                                      f"changed?)")
            if f.owner == "particle":  # a conductance among them: recompute forces and conductances
                self._recompute = True
            return False
        a = z[f.checkpoint]
        setattr(self.state, f.name, np.ascontiguousarray(a if rows is None else a[rows], f.dtype))
        return True

    def _load_clock(self, z):
        self.world.set_step(int(z["step_count"]))
        self.stepper.forces_ready = bool(z["forces_ready"])

    def _load_serial(self, z):
        """The serial layout: every checkpointed array as written (bit-exact continuation)."""
        st = self.state
        for f in self._checkpointed("particle") + self._checkpointed("pair"):
            self._load_array(f, z, None)
        st.n_owned = st.id.shape[0]   # (particles enter and leave: dem.flow)
        st.allocate()  # what an older checkpoint lacks (dem.checkpoint.ADDED_LATER)
        self._load_totals(z, root=True)
        st.fp[K.FP.tbuild] = float(z["fp_tbuild"])
        self._load_skin(z)
        if st.mtn.shape[0]:   # the mesh walls' candidate triangles of the saved lists (not saved)
            self.stepper.phases(K.PH_CANDIDATES, 0)
        self._load_clock(z)

    def _load_skin(self, z):
        """An adaptive skin (neighbor_skin = "auto") continues with the checkpoint's skin and gap
        density (a fixed skin is the scene's). A checkpoint from before the adaptive skin ran
        the largest; its gap density is measured at the next build."""
        st = self.state
        if not st.ip[K.IP.autoskin]:
            return
        skin = float(z["fp_skin"]) if "fp_skin" in z.files else st.fp[K.FP.skinmax]
        st.fp[K.FP.skin] = min(skin, st.fp[K.FP.skinmax])
        st.fp[K.FP.gapd] = float(z["fp_gapd"]) if "fp_gapd" in z.files else 0.0

    def _load_totals(self, z, root):
        """Run totals (heat per mechanism and per wall, particles in and out): on the root only,
        zero elsewhere; the flow's next id and debts on every rank."""
        st = self.state
        for f in self._total_fields():
            getattr(st, f.name)[:] = z[f.checkpoint] if root and f.checkpoint in z.files else 0.0
        if self.world.flow is not None and "flow_next_id" in z.files:
            self.world.flow.load(z)

    def _load_portable(self, path, z, subset=False):
        """Continue from a checkpoint written on any number of ranks: per-particle arrays by
        id, the neighbour list rebuilt here, the contact history restored from its records.
        ``subset``: this rank read some pieces of an MPI checkpoint; it takes all their rows and
        the exchange that builds the neighbours sends each particle (with its records) to its owner."""
        from .parallel import records
        st = self.state
        w = self.world
        pos = z["state_position"]
        if self.par is not None and not subset:
            rows = np.nonzero(self.par.dec.owner(pos) == self.par.rank)[0]
        else:
            rows = np.arange(pos.shape[0])
        st.enable(fluid=False)  # the coupling sets the fluid data again
        for f in self._checkpointed("particle"):
            self._load_array(f, z, rows, path)
        st.n_owned = rows.size
        st.n_ghost = 0
        st.allocate()  # the arrays a checkpoint does not hold (scratch), sized for these rows
        st.ip[K.IP.nown] = rows.size
        rec = {k: (z[f"rec_{k}"] if f"rec_{k}" in z.files else None) for k in records.FIELDS}
        if rec["a"] is None:
            rec = None
        self._load_clock(z)
        self._load_totals(z, root=self.writers.is_root)
        if subset:   # the boxes are cut for the checkpoint's particles, then each goes to its owner
            self.par.recut_pending = True
        self._load_skin(z)
        self.stepper.restore_neighbors(rec)
        th = w.thermal
        if th is not None:
            th.update_porosity(w.time)
            self.stepper.forward_porosity()
            if not w.scene.simulation["mechanics"]:
                self.stepper.compute_forces()  # the frozen packing's conductances
