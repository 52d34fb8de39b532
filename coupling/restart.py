"""Restart points of a coupled run: writing one (checkpoints/checkpoint_<step>.npz: the DEM;
checkpoints/coupling_<step>.npz: the exchange-field state of the interface, the gas frame
the next DEM interval uses and the energy ledger; on several DEM ranks a manifest and one
piece per rank in coupling_<step>.pieces/; the gas time folder is the solver's),
finding and loading the latest one for ``--restart`` (later gas time folders are removed),
the first frame of a continued run, and the one line that tells the user how to continue.
"""
from __future__ import annotations

import re
import shutil
from pathlib import Path

import numpy as np

from dem.interrupt import signal_name

from .errors import CouplingRunError

COUPLING_STATE_FORMAT = "thermodem coupling state"
COUPLING_STATE_VERSION = 1      # one file (a run on one DEM rank)
COUPLING_PIECES_VERSION = 2     # a manifest and one piece per DEM rank (coupling_<step>.pieces/)
PIECE_FORMAT = "thermodem coupling state piece"
_PIECE_NAME = re.compile(r"rank\d{5}\.npz")
FLUID_FIELDS = {"U": 3, "T": 1, "gradp": 3, "p": 1}


def _time_dirs(case: Path) -> list[tuple[float, Path]]:
    out = []
    for p in case.iterdir():
        if p.is_dir():
            try:
                out.append((float(p.name), p))
            except ValueError:
                pass
    return sorted(out)


def gas_times(out: Path) -> list[tuple[float, Path]]:
    """The gas time folders of a run: processor0's when the gas ran decomposed (the solver
    wrote there), else the case's."""
    p0 = out / "processor0"
    if p0.is_dir():
        t = [(tv, p) for tv, p in _time_dirs(p0) if tv > 0]
        if t:
            return t
    return [(tv, p) for tv, p in _time_dirs(out) if tv > 0]


def relayout_gas(out: Path, tdir: Path, n_gas: int) -> str | None:
    """Continue the gas of restart time ``tdir`` (a folder of gas_times) on ``n_gas`` processes
    when it was written on another number: reconstructPar, then decomposePar of that time
    (OpenFOAM's own tools); the processor folders of the earlier layout (ours) are replaced.
    Returns what was done (for the log) or None."""
    from dem import outdir
    from . import foam_case as fc
    procs = [p for p in out.glob("processor*") if p.name[9:].isdigit()]
    decomposed = tdir.parent.resolve() != out.resolve()
    written = len(procs) if decomposed else 1
    if written == n_gas:
        return None
    name = tdir.name
    if decomposed:
        outdir.claim(out / name)
        outdir.claim(out / "log.reconstructPar")
        fc.run_foam(["reconstructPar", "-time", name], out, log="log.reconstructPar")
    for p in procs:   # written by this tool (claimed when decomposed)
        shutil.rmtree(p)
    if n_gas > 1:
        for entry in ["log.decomposePar"] + [f"processor{i}" for i in range(n_gas)]:
            outdir.claim(out / entry)
        fc.decompose(out, n_gas, time=name)
    return f"gas fields of t = {name} s moved from {written} to {n_gas} process(es) (reconstructPar/decomposePar)"


def _time_index(tdir: Path) -> int | None:
    f = tdir / "uniform" / "time"
    if not f.exists():
        return None
    m = re.search(r"\bindex\s+(\d+)\s*;", f.read_text())
    return int(m.group(1)) if m else None


def _restart_point_files(out: Path, step: int) -> tuple[Path, Path]:
    """checkpoints/checkpoint_<step>.npz (DEM) and checkpoints/coupling_<step>.npz."""
    d = out / "checkpoints"
    return d / f"checkpoint_{step:08d}.npz", d / f"coupling_{step:08d}.npz"


def _coupling_state(iface, step, t, fluid, ledger=None, split=None):
    """Arrays of checkpoints/coupling_<step>.npz: the exchange-field state of the
    interface (eps, Ksl as last sent: the time-smoothing relaxes from them) and the gas
    frame of this step (U, T, grad p, p), which the next DEM interval uses (a run on one DEM
    rank; on several each writes its piece: _write_state_pieces)."""
    cells = iface.cells
    nc = cells.n_cells
    per_cell = {}
    for key, a in iface.restart_state().items():
        per_cell[f"iface_{key}"] = cells.gather_owned(a) if a.shape[0] == nc and nc else a
    for key in FLUID_FIELDS:
        per_cell[f"fluid_{key}"] = cells.gather_owned(np.ascontiguousarray(fluid[key], dtype=np.float64))
    if cells.rank != 0:
        return None
    d = dict(format=np.str_(COUPLING_STATE_FORMAT), version=np.int64(COUPLING_STATE_VERSION),
             step=np.int64(step), time=np.float64(t))
    d.update(per_cell)
    d["fluid_scalars"] = np.ascontiguousarray(fluid.get("scalars", ()), dtype=np.float64)
    if ledger is not None:
        d.update(ledger.state())
    if split:
        d.update(split.state())
    return d


def pieces_folder(path: Path) -> Path:
    """The folder of a coupling state's pieces: coupling_<step>.npz -> coupling_<step>.pieces."""
    return path.with_suffix(".pieces")


def _share_failure(R, err: str | None, cls=CouplingRunError):
    """Every rank learns whether any failed (a flag reduction); then the first failing rank's
    one line (a fixed-size byte buffer from it) is raised on all (``cls``)."""
    if R.comm is None:
        if err is not None:
            raise cls(err)
        return
    from mpi4py import MPI
    me = R.comm.Get_rank()
    first = np.array([me if err is not None else R.size], np.int64)
    got = np.empty(1, np.int64)
    R.comm.Allreduce(first, got, op=MPI.MIN)
    k = int(got[0])
    if k >= R.size:
        return
    buf = np.zeros(4096, np.uint8)
    if me == k:
        b = f"DEM rank {k} of {R.size}: {err}".encode()[:4096]
        buf[:len(b)] = np.frombuffer(b, np.uint8)
    R.comm.Bcast(buf, root=k)
    raise cls(bytes(buf).rstrip(b"\0").decode(errors="replace"))


def _state_piece(iface, fluid) -> dict:
    """This rank's piece of a restart point's coupling state: the global ids of the cells it
    owns and their rows of every per-cell array (the interface's state, the gas frame)."""
    cells = iface.cells
    nc, own = cells.n_cells, cells.owned
    d = dict(cells=np.ascontiguousarray(cells.global_ids[own], np.int64))
    for key, a in iface.restart_state().items():
        d[f"iface_{key}"] = np.ascontiguousarray(a[own]) if a.shape[0] == nc and nc else a
    for key in FLUID_FIELDS:
        d[f"fluid_{key}"] = np.ascontiguousarray(np.asarray(fluid[key], np.float64)[own])
    return d


def _write_state_pieces(R, iface, path: Path, step, t, fluid, ledger=None, split=None):
    """The coupling state of an MPI run (collective): every rank writes its piece (its owned
    cells: nobody gathers the mesh), atomically and durably, rank 0 then the manifest
    ``path`` (scalars, ledger, each piece's sha256, cell count, id range and box of cell
    centres, so that a restart reads only the pieces that hold its cells) and removes the
    pieces of ``path``'s folder the manifest does not name (ours only). A failure on any
    rank stops every rank with one line naming the rank and the file."""
    from dem.checkpoint import content_digest
    from dem.output import OutputError, save_npz
    cells = iface.cells
    rank = R.comm.Get_rank()
    folder = pieces_folder(path)
    name = f"rank{rank:05d}.npz"
    piece = _state_piece(iface, fluid)
    piece.update(format=np.str_(PIECE_FORMAT), version=np.int64(COUPLING_PIECES_VERSION), step=np.int64(step))
    ids = piece["cells"]
    x = cells.mesh.cell_centres[cells.owned]
    meta = np.zeros(10)
    meta[0] = ids.size
    if ids.size:
        meta[1], meta[2] = ids[0], ids[-1]
        meta[3:6], meta[6:9] = x.min(axis=0), x.max(axis=0)
    err, digest = None, ""
    try:
        if rank == 0:
            folder.mkdir(parents=True, exist_ok=True)
    except OSError as e:
        err = str(OutputError(folder, e))
    _share_failure(R, err, OutputError)
    try:
        digest = content_digest(piece)
        piece["checksum"] = np.str_(digest)
        save_npz(str(folder / name), durable=True, **piece)
    except Exception as e:  # noqa: BLE001 - shared below: every rank stops with this line
        err = str(e) if isinstance(e, OutputError) else str(OutputError(folder / name, e))
    meta[9] = 1.0 if err is None else 0.0
    _share_failure(R, err, OutputError)
    sums = np.zeros((R.size, 64), np.uint8) if R.root else None
    metas = np.zeros((R.size, 10)) if R.root else None
    R.comm.Gather(np.frombuffer(digest.encode().ljust(64, b"\0"), np.uint8).copy(), sums, root=0)
    R.comm.Gather(meta, metas, root=0)

    def manifest():
        d = dict(format=np.str_(COUPLING_STATE_FORMAT), version=np.int64(COUPLING_PIECES_VERSION),
                 step=np.int64(step), time=np.float64(t), n_cells=np.int64(cells.n_global))
        d["fluid_scalars"] = np.ascontiguousarray(fluid.get("scalars", ()), dtype=np.float64)
        if ledger is not None:
            d.update(ledger.state())
        if split:
            d.update(split.state())
        d["pieces"] = np.array([f"rank{r:05d}.npz" for r in range(R.size)], dtype=np.str_)
        d["piece_sha256"] = np.array([bytes(sums[r]).rstrip(b"\0").decode() for r in range(R.size)], dtype=np.str_)
        d["piece_cells"] = metas[:, 0].astype(np.int64)
        d["piece_ids"] = metas[:, 1:3].astype(np.int64)
        d["piece_lo"], d["piece_hi"] = metas[:, 3:6].copy(), metas[:, 6:9].copy()
        save_npz(str(path), durable=True, **d)
        from dem.pieces import remove_stale
        remove_stale(str(folder), set(str(n) for n in d["pieces"]), _PIECE_NAME)
    R.on_root(manifest)   # a failure there stops every rank


def _write_restart_point(R, sim, iface, out, step, t, fluid, ledger=None, split=None):
    """A restart point at this step (collective): the coupling state first (one file; on
    several DEM ranks one piece per rank and a manifest), then the DEM checkpoint, each
    written atomically; ``--restart`` only takes a step whose DEM checkpoint exists, so a kill
    between the two writes leaves the previous point."""
    ck, cs = _restart_point_files(out, step)
    from dem.output import save_npz
    if R.size > 1:
        _write_state_pieces(R, iface, cs, step, t, fluid, ledger, split)
    else:
        state = _coupling_state(iface, step, t, fluid, ledger, split)
        R.on_root(lambda: save_npz(str(cs), durable=True, **state))     # a failure there stops every rank
    sim.write_checkpoint(str(ck))
    return ck


class RestartPoints:
    """Writes the restart points of a run (``points(step, t, fluid)``, collective; timed as
    output); rank 0 claims checkpoints/ when made."""

    def __init__(self, R, sim, iface, out: Path, ledger=None, split=None):
        self.R, self.sim, self.iface, self.out, self.ledger, self.split = R, sim, iface, out, ledger, split
        if R.root:
            from dem import outdir
            outdir.claim(out / "checkpoints")
            (out / "checkpoints").mkdir(exist_ok=True)

    def __call__(self, step, t, fluid):
        with self.iface.timer("output"):
            _write_restart_point(self.R, self.sim, self.iface, self.out, step, t, fluid, self.ledger, self.split)


def _load_coupling_state(path: Path, step: int, cells) -> dict:
    """Read and check checkpoints/coupling_<step>.npz (one file, or a manifest and the pieces
    that hold cells of this rank's local mesh: ``cells``, coupling.cells.CellShare); the
    per-cell arrays come back on the local mesh. CouplingRunError naming the file."""
    why = ("it holds the exchange-field state and the last gas frame of the restart point, "
           "written with checkpoints/checkpoint_%08d.npz" % step)
    if not path.is_file():
        raise CouplingRunError(f"{path}: missing ({why}); this output cannot be continued exactly: "
                               f"start the run again without --restart")
    arrays = _read_npz(path, "a coupling state")
    fmt = str(arrays.get("format", ""))
    if fmt != COUPLING_STATE_FORMAT:
        raise CouplingRunError(f"{path}: not a coupling state of thermodem (format {fmt!r})")
    ver = int(arrays.get("version", -1))
    if ver not in (COUPLING_STATE_VERSION, COUPLING_PIECES_VERSION):
        raise CouplingRunError(f"{path}: coupling state version {ver}, this thermodem reads "
                               f"versions {COUPLING_STATE_VERSION} and {COUPLING_PIECES_VERSION}")
    if int(arrays.get("step", -1)) != step:
        raise CouplingRunError(f"{path}: holds step {int(arrays.get('step', -1))}, expected {step}")
    read = []
    if ver == COUPLING_PIECES_VERSION:
        n = int(arrays["n_cells"])
        if n != cells.n_global:
            raise CouplingRunError(f"{path}: written for a mesh of {n} cells, this mesh has {cells.n_global}")
        per_cell, read = _load_pieces(path, arrays, cells)
        arrays.update(per_cell)
    nc = cells.n_global if ver == COUPLING_STATE_VERSION else cells.n_cells
    fluid = {}
    for key, ncomp in FLUID_FIELDS.items():
        a = arrays.get(f"fluid_{key}")
        shape = (nc, ncomp) if ncomp > 1 else (nc,)
        if a is None or a.shape != shape or a.dtype != np.float64 or not np.all(np.isfinite(a)):
            raise CouplingRunError(f"{path}: gas field fluid_{key} missing, not float64 of shape {shape} "
                                   f"(the mesh has {cells.n_global} cells) or not finite")
        fluid[key] = cells.localize(a) if ver == COUPLING_STATE_VERSION else a
    if "fluid_scalars" in arrays:   # the solver's energy ledger of the step (older states: none)
        fluid["scalars"] = np.asarray(arrays["fluid_scalars"], np.float64)
    iface = {key[6:]: (cells.localize(a) if ver == COUPLING_STATE_VERSION else a)
             for key, a in arrays.items() if key.startswith("iface_")}
    for key in ("eps_sent", "ksl_sent"):
        if key not in iface:
            raise CouplingRunError(f"{path}: iface_{key} missing")
    ledger = {key: arrays[key] for key in ("ledger_acc", "ledger_ref", "split_sent") if key in arrays}
    return dict(fluid=fluid, iface=iface, ledger=ledger, time=float(arrays["time"]), path=path, pieces_read=read)


def _read_npz(path: Path, what: str) -> dict:
    try:
        with np.load(path, allow_pickle=False) as z:
            return {key: z[key] for key in z.files}
    except Exception as e:  # noqa: BLE001 - zip CRC, truncation, not an npz
        raise CouplingRunError(f"{path}: cannot be read as {what} ({type(e).__name__}: {e}); "
                               f"the file is damaged: restart from an earlier restart point by removing "
                               f"the later OpenFOAM time directories, or start again without --restart") from None


def _load_pieces(path: Path, arrays: dict, cells):
    """The per-cell arrays of the local mesh from the pieces of the manifest ``arrays`` that
    can hold its cells (id range and box of cell centres overlap this rank's), each verified
    against its sha256; every cell of the local mesh must be found. Returns (arrays, names
    of the pieces read)."""
    from dem.checkpoint import content_digest
    names, sums = arrays["pieces"], arrays["piece_sha256"]
    gid = cells.global_ids
    x = cells.mesh.cell_centres
    which = []
    if gid.size:
        lo, hi = x.min(axis=0), x.max(axis=0)
        ids = arrays["piece_ids"]
        for k in range(len(names)):
            if (arrays["piece_cells"][k] > 0 and ids[k, 0] <= gid[-1] and ids[k, 1] >= gid[0]
                    and np.all(arrays["piece_lo"][k] <= hi) and np.all(arrays["piece_hi"][k] >= lo)):
                which.append(k)
    out, seen = {}, np.zeros(gid.size, bool)
    folder = pieces_folder(path)
    for k in which:
        f = folder / str(names[k])
        if not f.is_file():
            raise CouplingRunError(f"{f}: missing (a piece of the restart point {path.name}: copy the manifest "
                                   f"and the folder {folder.name} together)")
        piece = _read_npz(f, "a coupling state piece")
        digest = str(piece.pop("checksum", ""))
        if str(piece.get("format", "")) != PIECE_FORMAT or digest != str(sums[k]) or content_digest(piece) != digest:
            raise CouplingRunError(f"{f}: corrupted (its content does not match the sha256 the manifest "
                                   f"{path.name} names); restart from an earlier restart point")
        j = cells.local(piece["cells"])
        m = j >= 0
        seen[j[m]] = True
        for key, a in piece.items():
            if not (key.startswith("iface_") or key.startswith("fluid_")):
                continue
            if key not in out:
                out[key] = (np.zeros((gid.size,) + a.shape[1:]) if a.shape[0] == piece["cells"].size and a.size
                            else a)
            if a.shape[0] == piece["cells"].size and a.size:
                out[key][j[m]] = a[m]
    if gid.size and not seen.all():
        c = int(gid[np.flatnonzero(~seen)[0]])
        raise CouplingRunError(f"{path}: no piece holds gas cell {c} (pieces read: "
                               f"{[str(names[k]) for k in which]}); the restart point is incomplete")
    return out, [str(names[k]) for k in which]


def _restart(out: Path, sim, dt, log, R, cells):
    """Continue from the latest restart point: the latest OpenFOAM time directory whose
    step has a DEM checkpoint (checkpoints/checkpoint_<step>.npz) and a coupling state
    (checkpoints/coupling_<step>.npz). Loads both (the coupling state is returned, to be
    applied after the initial void fraction), removes later gas time directories.
    Returns (step index, time, coupling state)."""
    cks = {int(m.group(1)): p for p in (out / "checkpoints").glob("checkpoint_*.npz")
           if (m := re.match(r"checkpoint_(\d+)\.npz", p.name))}
    gas_times_ = gas_times(out)
    best = None
    for tv, p in gas_times_:
        idx = _time_index(p)
        if idx is None:
            idx = int(round(tv / dt))
        if idx in cks:
            best = (idx, tv, p)
    if best is None:
        raise CouplingRunError(f"{out}: no OpenFOAM time directory with a matching DEM checkpoint "
                               f"(checkpoints/checkpoint_<step>.npz); gas times: "
                               f"{[p.name for _, p in gas_times_]}, DEM checkpoints: {sorted(cks)}")
    idx, tv, p = best
    cstate, err = None, None
    try:
        cstate = _load_coupling_state(_restart_point_files(out, idx)[1], idx, cells)
    except CouplingRunError as e:
        err = str(e)
    _share_failure(R, err)   # a rank that cannot read its cells stops every rank
    R.barrier()  # every rank has chosen the same restart point before rank 0 prunes
    if R.root:
        for tv2, p2 in _time_dirs(out):
            if tv2 > tv + 1e-12:
                shutil.rmtree(p2)
        for proc in out.glob("processor*"):
            for tv2, p2 in _time_dirs(proc):
                if tv2 > tv + 1e-12:
                    shutil.rmtree(p2)
    sim.load_checkpoint(str(cks[idx]))
    if abs(sim.time - tv) > 1e-9 * max(1.0, tv):
        raise CouplingRunError(f"{cks[idx]}: DEM time {sim.time} does not match the gas time {tv}")
    log(f"coupling: restarting from t = {tv:g} s (step {idx}, {cks[idx].name}, {cstate['path'].name})")
    cstate["gas_dir"] = p
    return idx, tv, cstate


def resume(R, out: Path, iface, ledger, split, dt, log):
    """Load the latest restart point into the DEM (iface.sim), the interface, the energy
    ledger and the tied walls' split. Returns (step index, time, coupling state)."""
    sim = iface.sim
    i0, t_start, cstate = _restart(out, sim, dt, R.log(log), R, iface.cells)
    iface.reset_hints()
    iface.restore_state(cstate["iface"])  # the relaxation continues from what the gas last got
    ledger.restore(cstate["ledger"])      # the balance continues from its start (if recorded)
    split.restore(cstate["ledger"], sim)
    return i0, t_start, cstate


def restored_frame(fluid, cstate, cells=None):
    """The gas state the first DEM interval uses. After a restart the solver's frame is
    replaced by the one the DEM used at that step in the interrupted run (stored in the
    restart point), so the particles see exactly the same fluid data; the largest
    difference between the two is kept (0 when the gas fields were restored exactly).
    ``cells`` (coupling.cells.CellShare, many-to-many): compared on this rank's owned cells,
    the largest over the ranks (collective)."""
    if cstate is None:
        return fluid
    saved = cstate["fluid"]
    own = slice(None) if cells is None else cells.owned
    diff = max(float(np.max(np.abs(np.asarray(fluid[k])[own] - np.asarray(saved[k])[own]), initial=0.0))
               for k in FLUID_FIELDS)
    cstate["frame_difference"] = diff if cells is None else cells.allmax(diff)
    return dict(fluid, **saved)


def continue_command(case_dir, out, end_time, transport, nranks):
    """The exact command that continues this run from its latest restart point."""
    import shlex
    cmd = ([f"mpirun -np {nranks}"] if nranks > 1 else []) + [
        "coupling run", shlex.quote(str(case_dir)), "--out", shlex.quote(str(out)), "--restart"]
    if end_time is not None:
        cmd += ["--end-time", repr(float(end_time))]
    if transport is not None:
        cmd += ["--transport", transport]
    return " ".join(cmd)


def stopped_line(signum, own, t, step, out, cont):
    """The one line of a run stopped by a signal: where its restart point is, how to continue."""
    who = "" if own else " of the gas solver"
    ck = out / "checkpoints" / f"checkpoint_{step:08d}.npz"
    return (f"stopped by {signal_name(signum)}{who} at t = {t:.9g} s (coupling step {step}); "
            f"restart point {ck} (gas: {out}/<time>); continue with: {cont}")
