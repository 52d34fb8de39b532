"""Restart points of a coupled run: writing one (checkpoints/checkpoint_<step>.npz: the DEM;
checkpoints/coupling_<step>.npz: the exchange-field state of the interface, the gas frame
the next DEM interval uses and the energy ledger; the gas time folder is the solver's),
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
COUPLING_STATE_VERSION = 1
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
    frame of this step (U, T, grad p, p), which the next DEM interval uses. Collective: each
    rank holds its owned cells' values (coupling.cells), rank 0 gets the whole arrays (None
    elsewhere)."""
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


def _write_restart_point(R, sim, iface, out, step, t, fluid, ledger=None, split=None):
    """A restart point at this step (collective): the coupling state first, then the DEM
    checkpoint, each written atomically; ``--restart`` only takes a step whose DEM
    checkpoint exists, so a kill between the two writes leaves the previous point."""
    ck, cs = _restart_point_files(out, step)
    from dem.output import save_npz
    state = _coupling_state(iface, step, t, fluid, ledger, split)   # collective
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


def _load_coupling_state(path: Path, step: int, n_cells: int) -> dict:
    """Read and check checkpoints/coupling_<step>.npz; CouplingRunError naming the file."""
    why = ("it holds the exchange-field state and the last gas frame of the restart point, "
           "written with checkpoints/checkpoint_%08d.npz" % step)
    if not path.is_file():
        raise CouplingRunError(f"{path}: missing ({why}); this output cannot be continued exactly: "
                               f"start the run again without --restart")
    try:
        with np.load(path, allow_pickle=False) as z:
            arrays = {key: z[key] for key in z.files}
    except Exception as e:  # noqa: BLE001 - zip CRC, truncation, not an npz
        raise CouplingRunError(f"{path}: cannot be read as a coupling state ({type(e).__name__}: {e}); "
                               f"the file is damaged: restart from an earlier restart point by removing "
                               f"the later OpenFOAM time directories, or start again without --restart") from None
    fmt = str(arrays.get("format", ""))
    if fmt != COUPLING_STATE_FORMAT:
        raise CouplingRunError(f"{path}: not a coupling state of thermodem (format {fmt!r})")
    ver = int(arrays.get("version", -1))
    if ver != COUPLING_STATE_VERSION:
        raise CouplingRunError(f"{path}: coupling state version {ver}, this thermodem reads "
                               f"version {COUPLING_STATE_VERSION}")
    if int(arrays.get("step", -1)) != step:
        raise CouplingRunError(f"{path}: holds step {int(arrays.get('step', -1))}, expected {step}")
    fluid = {}
    for key, ncomp in FLUID_FIELDS.items():
        a = arrays.get(f"fluid_{key}")
        shape = (n_cells, ncomp) if ncomp > 1 else (n_cells,)
        if a is None or a.shape != shape or a.dtype != np.float64 or not np.all(np.isfinite(a)):
            raise CouplingRunError(f"{path}: gas field fluid_{key} missing, not float64 of shape {shape} "
                                   f"(the mesh has {n_cells} cells) or not finite")
        fluid[key] = a
    if "fluid_scalars" in arrays:   # the solver's energy ledger of the step (older states: none)
        fluid["scalars"] = np.asarray(arrays["fluid_scalars"], np.float64)
    iface = {key[6:]: a for key, a in arrays.items() if key.startswith("iface_")}
    for key in ("eps_sent", "ksl_sent"):
        if key not in iface:
            raise CouplingRunError(f"{path}: iface_{key} missing")
    ledger = {key: arrays[key] for key in ("ledger_acc", "ledger_ref", "split_sent") if key in arrays}
    return dict(fluid=fluid, iface=iface, ledger=ledger, time=float(arrays["time"]), path=path)


def _restart(out: Path, sim, dt, log, R, n_cells):
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
    cstate = _load_coupling_state(_restart_point_files(out, idx)[1], idx, n_cells)
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
    i0, t_start, cstate = _restart(out, sim, dt, R.log(log), R, iface.mesh.n_cells)
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
