"""Checkpoint files that carry what they need, and restarts with an edited scene.

A checkpoint is an ``.npz`` holding the arrays of :meth:`dem.checkpointer.Checkpointer.arrays`
plus four entries written here:

    format          "thermodem-checkpoint"
    format_version  FORMAT_VERSION (int64)
    record          JSON text: the particle count, the step, the materials and walls by
                    name with every property, the simulation / domain / contact / thermal
                    settings and digests of the scene's particle definitions
    checksum        sha256 (hex) over the name, dtype, shape and bytes of every other entry

Reading (:func:`read`) refuses, with a :class:`CheckpointError` (exit 2, one line naming
the file and what is wrong), a missing file, a folder, an empty / truncated / corrupted
file, a file that is not a checkpoint (``final.npz``, any other npz, text) and a checkpoint
without a format version; :func:`validate` then checks every array's dtype and shape
against the particle count and the walls, and the indices that kernels follow, so that
nothing malformed reaches compiled code.

Restart with an edited scene (:func:`plan_restart`): the record is compared with the
scene; each difference is either applied consistently (:func:`apply_edits` rewrites the
checkpoint's arrays for the new scene, and the change is listed) or refused with a
:class:`dem.scene.SceneError` naming the key. docs/reliability/checkpoint.md lists which.
"""
import hashlib
import math
import json
import os
import re

import numpy as np

from .errors import SceneError
from .parcels import parcel_factors

FORMAT = "thermodem-checkpoint"
FORMAT_VERSION = 1       # a serial checkpoint (one file), and the manifests of version-1 pieces
MANIFEST_VERSION = 2     # a manifest of pieces read by row range (dem.pieces)
META = ("format", "format_version", "record", "checksum")


class CheckpointError(SceneError):
    """A checkpoint that cannot be used: ``file: message`` (bad input, exit 2)."""

    def __init__(self, file, message, key=""):
        super().__init__(file, key, message)


# ---------------------------------------------------------------------------- writing

# Arrays that checkpoints of earlier versions do not hold: such a checkpoint still continues.
# th_Hwg (the gas-gap part of each wall conductance) is recomputed from the restored state;
# th_wgap (heat across the gas gap per wall since the start) starts at 0, so a continued run
# counts the gap heat of the earlier part as contact heat (issue 14: the wall records by path);
# th_wrad (radiation per wall) likewise starts at 0.
ADDED_LATER = ("th_Hwg", "th_wgap", "th_wrad")

def content_digest(arrays):
    """sha256 over every entry but ``checksum``: name, dtype, shape, then the bytes."""
    h = hashlib.sha256()
    for k in sorted(arrays):
        if k == "checksum":
            continue
        a = np.ascontiguousarray(arrays[k])
        h.update(f"{k}\0{a.dtype.str}\0{a.shape}\0".encode())
        h.update(a.tobytes())
    return h.hexdigest()


def with_meta(arrays, record, version=FORMAT_VERSION):
    """``arrays`` plus format, version, record and checksum (what :func:`write` saves)."""
    out = dict(arrays)
    out["format"] = np.str_(FORMAT)
    out["format_version"] = np.int64(version)
    out["record"] = np.str_(json.dumps(record, sort_keys=True))
    out["checksum"] = np.str_(content_digest(out))
    return out


def write(path, arrays, record):
    """Write a checkpoint atomically (dem.output.save_npz): a serial checkpoint in format
    FORMAT_VERSION, a manifest of pieces in MANIFEST_VERSION."""
    from .output import save_npz
    version = MANIFEST_VERSION if is_manifest(arrays) else FORMAT_VERSION
    save_npz(path, durable=True, **with_meta(arrays, record, version))


# ---------------------------------------------------------------------------- pieces (MPI)
# An MPI run's checkpoint is a manifest (the .npz above, with the run's scalars, totals and the list
# of pieces with their sha256) and one piece per rank in the folder beside it (pieces_folder):
# that rank's particles and contact records. No rank gathers another's particles. The pieces of a
# step are written first (each atomically and durably), the manifest last, and the pieces no
# manifest names any more are removed after it: a kill -9 at any instant leaves the previous
# manifest with every piece it names.
#
# Pieces of version 2 (manifest format_version 2, entry piece_version) hold their rows ordered by id
# and their contact records listed under each of those rows they involve, verified by block (dem.pieces): a restart on M
# ranks reads rows [r N / M, (r + 1) N / M) of the pieces' concatenation on rank r, whatever the
# pieces, loading no piece whole. Version-1 pieces (whole-piece sha256) are still read, every M-th.
PIECE_FORMAT = "thermodem-checkpoint-piece"
PIECE_KEYS = ("pieces", "piece_sha256", "piece_rows", "piece_version")
_PIECE_NAME = re.compile(r"step\d{10}_rank\d{5}\.npz")


def pieces_folder(path):
    """The folder of a checkpoint's pieces: ``checkpoint.npz`` -> ``checkpoint.pieces``."""
    p = os.fspath(path)
    return (p[:-4] if p.endswith(".npz") else p) + ".pieces"


def piece_name(step, rank):
    return f"step{step:010d}_rank{rank:05d}.npz"


def write_piece(path, arrays):
    """One rank's piece (version 2), atomically and durably: ``arrays`` are the particle arrays and
    the contact records (rec_*); rows are ordered by id and each record listed under the rows it involves. Returns its
    digest (named in the manifest)."""
    from .pieces import anchor_records, write_piece as write
    order = np.argsort(arrays["state_id"], kind="stable")
    n = order.size
    rows = {k: np.ascontiguousarray(v[order] if v.ndim and v.shape[0] == n else v)   # a disabled array: empty
            for k, v in arrays.items() if not k.startswith("rec_")}
    rec = {k: v for k, v in arrays.items() if k.startswith("rec_")}
    if rec:
        rows.update(anchor_records(rows["state_id"], rec))
    return write(path, rows, rows["state_id"].size, PIECE_FORMAT)


def manifest(arrays, pieces):
    """The manifest's arrays: ``arrays`` (scalars and totals) and the pieces [(name, sha256, rows)]."""
    from .pieces import PIECE_VERSION
    out = dict(arrays)
    out["pieces"] = np.array([p[0] for p in pieces], dtype=np.str_)
    out["piece_sha256"] = np.array([p[1] for p in pieces], dtype=np.str_)
    out["piece_rows"] = np.array([p[2] for p in pieces], dtype=np.int64)
    out["piece_version"] = np.int64(PIECE_VERSION)
    return out


def is_manifest(arrays):
    return "pieces" in arrays


def remove_stale_pieces(folder, keep):
    """Remove the pieces in ``folder`` (our names only) that the manifest no longer names."""
    from .pieces import remove_stale
    remove_stale(folder, keep, _PIECE_NAME)


def _read_piece(path, name, digest):
    """The arrays of piece ``name`` of the checkpoint ``path``, verified against the manifest."""
    piece = os.path.join(pieces_folder(path), name)
    try:
        with np.load(piece, allow_pickle=False) as z:
            arrays = {k: z[k] for k in z.files}
    except FileNotFoundError:
        raise CheckpointError(path, f"piece {piece} is missing (a checkpoint written on several ranks is "
                                    f"the manifest and the folder of its pieces: copy both)") from None
    except Exception as exc:  # noqa: BLE001  (BadZipFile, EOFError, OSError, zlib errors ...)
        raise CheckpointError(path, f"piece {piece} is corrupted or truncated ({type(exc).__name__}: "
                                    f"{_short(exc)})") from None
    if str(arrays.get("format", "")) != PIECE_FORMAT or "checksum" not in arrays:
        raise CheckpointError(path, f"piece {piece} is not a checkpoint piece")
    if str(arrays["checksum"]) != digest or content_digest(arrays) != digest:
        raise CheckpointError(path, f"piece {piece} is corrupted: its content does not match the sha256 "
                                    f"the manifest names (changed after it was written)")
    for k in ("format", "format_version", "checksum"):
        arrays.pop(k)
    return arrays


def load_pieces(path, arrays, which):
    """The manifest ``arrays`` of version-1 pieces with the particles and contact records of its
    pieces ``which`` (indices), every piece verified against its sha256: particle rows ordered by
    id, each contact record once. With no piece to read (more ranks than pieces) the arrays have
    no row."""
    names, sums = arrays["pieces"], arrays["piece_sha256"]
    read = list(which) or [0]
    parts = [_read_piece(path, str(names[k]), str(sums[k])) for k in read]
    if not list(which):
        parts = [{k: v[:0] for k, v in parts[0].items()}]
    return _combine(arrays, parts)


def load_slices(path, arrays, slices):
    """(the manifest ``arrays`` of version-2 pieces with rows [lo, hi) of its pieces, for each
    (piece, lo, hi) of ``slices``, and their contact records; rows read from the files): rows
    ordered by id, each record once, only the blocks of the slices read, each verified."""
    from .pieces import PieceError, read_rows
    names, sums = arrays["pieces"], arrays["piece_sha256"]
    parts, read = [], 0
    for k, lo, hi in (slices or [(0, 0, 0)]):
        piece = os.path.join(pieces_folder(path), str(names[k]))
        if not os.path.exists(piece):
            raise CheckpointError(path, f"piece {piece} is missing (a checkpoint written on several ranks is "
                                        f"the manifest and the folder of its pieces: copy both)")
        try:
            got, n = read_rows(piece, PIECE_FORMAT, str(sums[k]), lo, hi)
        except PieceError as exc:
            raise CheckpointError(path, str(exc)) from None
        if got["state_id"].size != hi - lo:
            raise CheckpointError(path, f"piece {piece} holds fewer rows than the manifest names")
        got.pop("rec_start", None)
        parts.append(got)
        read += n
    return _combine(arrays, parts), read


def shares(arrays, rank, size):
    """The slices (piece, lo, hi) of a version-2 manifest that rank ``rank`` of ``size`` reads."""
    from .pieces import shares as cut
    return cut(arrays["piece_rows"], rank, size)


def sliced(arrays):
    """A manifest of version-2 pieces (read by row range)."""
    return "piece_version" in arrays


def _combine(arrays, parts):
    out = {k: v for k, v in arrays.items() if k not in PIECE_KEYS}
    keys = sorted(set().union(*parts))
    rows = {k: np.concatenate([p[k] for p in parts if k in p]) for k in keys}
    order = np.argsort(rows["state_id"], kind="stable")
    for k, v in rows.items():
        if not k.startswith("rec_"):
            out[k] = np.ascontiguousarray(v[order])
    if "rec_a" in rows:  # a pair across two ranks is recorded in both pieces: keep one
        _, first = np.unique(np.stack([rows["rec_a"], rows["rec_b"]], axis=1), axis=0, return_index=True)
        for k, v in rows.items():
            if k.startswith("rec_"):
                out[k] = np.ascontiguousarray(v[first])
    return out


def load(path):
    """(arrays, record) of a whole checkpoint, one file or a manifest with its pieces (verified)."""
    arrays, record = read(path)
    if is_manifest(arrays) and sliced(arrays):
        arrays, _ = load_slices(path, arrays, [(k, 0, int(n)) for k, n in enumerate(arrays["piece_rows"])])
    elif is_manifest(arrays):
        arrays = load_pieces(path, arrays, range(len(arrays["pieces"])))
    return arrays, record


# ---------------------------------------------------------------------------- reading
def read(path):
    """(arrays, record) of a checkpoint, every entry read and the checksum verified."""
    path = os.fspath(path)
    if not os.path.exists(path):
        raise CheckpointError(path, "checkpoint not found")
    if os.path.isdir(path):
        raise CheckpointError(path, "is a folder, not a checkpoint file (give the checkpoint.npz "
                                    "inside an output folder)")
    if os.path.getsize(path) == 0:
        raise CheckpointError(path, "checkpoint is empty (0 bytes): it was never completely written")
    try:
        with open(path, "rb") as fh:
            magic = fh.read(4)
    except OSError as exc:
        raise CheckpointError(path, f"cannot read the checkpoint: {exc.strerror or exc}") from None
    if magic == b"\x93NUM":
        raise CheckpointError(path, "not a checkpoint: a single .npy array, not an .npz archive")
    if magic[:2] != b"PK":
        raise CheckpointError(path, "not a checkpoint: not an .npz archive (text or another format)")
    try:
        with np.load(path, allow_pickle=False) as z:
            arrays = {k: z[k] for k in z.files}
    except Exception as exc:  # noqa: BLE001  (BadZipFile, EOFError, OSError, zlib errors ...)
        raise CheckpointError(path, f"checkpoint is corrupted or truncated, or not a checkpoint "
                                    f"({type(exc).__name__}: {_short(exc)})") from None
    if "format" not in arrays:
        raise CheckpointError(path, _foreign_message(path, arrays))
    if str(arrays["format"]) == "thermodem-final":
        raise CheckpointError(path, "is a results file (an MPI run's final.npz), not a checkpoint: continue "
                                    "from checkpoint.npz in the same output folder")
    if str(arrays["format"]) != FORMAT:
        raise CheckpointError(path, f"not a thermodem checkpoint (format {str(arrays['format'])[:40]!r})")
    version = _scalar(path, arrays, "format_version", int)
    if version != FORMAT_VERSION and not (version == MANIFEST_VERSION and is_manifest(arrays)):
        raise CheckpointError(path, f"checkpoint format version {version}; this thermodem reads version "
                                    f"{FORMAT_VERSION} (and {MANIFEST_VERSION} for a manifest of pieces): continue "
                                    f"it with the thermodem that wrote it")
    for k in ("record", "checksum"):
        if k not in arrays or arrays[k].dtype.kind != "U" or arrays[k].ndim != 0:
            raise CheckpointError(path, f"checkpoint is damaged: entry {k!r} missing or malformed")
    if content_digest(arrays) != str(arrays["checksum"]):
        raise CheckpointError(path, "checkpoint is corrupted: its content does not match its sha256 "
                                    "checksum (changed after it was written)")
    try:
        record = json.loads(str(arrays["record"]))
    except ValueError:
        raise CheckpointError(path, "checkpoint is damaged: its record is not valid JSON") from None
    for k in META:
        arrays.pop(k)
    return arrays, record


def _short(exc, n=120):
    s = str(exc).replace("\n", " ")
    return s if len(s) <= n else s[:n] + "..."


def _foreign_message(path, arrays):
    names = sorted(arrays)
    if {"id", "position", "time"} <= set(names) and "state_id" not in names:
        return ("is a results file (final.npz or failed_state.npz), not a checkpoint: continue from "
                "checkpoint.npz in the same output folder")
    if "state_id" in names and "dt" in names:
        return ("checkpoint written by an earlier thermodem without a format version or checksum: it "
                "cannot be checked against the scene, so it is not read; start the run again, or continue "
                "it with the thermodem that wrote it")
    shown = ", ".join(names[:6]) + (", ..." if len(names) > 6 else "")
    return f"not a thermodem checkpoint (an npz holding {shown or 'no arrays'})"


def _scalar(path, arrays, key, kind):
    a = arrays.get(key)
    if a is None or a.ndim != 0:
        raise CheckpointError(path, f"checkpoint is damaged: entry {key!r} missing or not a scalar")
    try:
        return kind(a)
    except (TypeError, ValueError):
        raise CheckpointError(path, f"checkpoint is damaged: entry {key!r} = {a!r}") from None


class ArrayView:
    """The read arrays with the ``np.load`` interface the loaders use (``z[k]``, ``z.files``)."""

    def __init__(self, arrays):
        self._a = arrays
        self.files = list(arrays)

    def __getitem__(self, k):
        return self._a[k]

    def __contains__(self, k):
        return k in self._a


# ---------------------------------------------------------------------------- validation
F8, I8, I4, U1 = np.dtype(np.float64), np.dtype(np.int64), np.dtype(np.int32), np.dtype(np.uint8)


def _features(record):
    """The features (dem.schema) of the run that wrote the checkpoint: recorded since the
    declared state; derived for older checkpoints (None: either form is accepted)."""
    if isinstance(record.get("features"), dict):
        return {k: bool(v) for k, v in record["features"].items()}
    thermal = record["thermal"] is not None
    return {"heat": thermal, "epsd": record["contact"]["rolling"] == "epsd", "fluid": False}


def validate(path, arrays, record, subset=False):
    """Every array declared in dem.schema with a checkpoint key: dtype and shape against the
    record (particles, walls, slots, the features the run enabled), and the indices the
    kernels follow (neighbours, walls, materials, contact records) in range. ``subset``: the
    arrays hold some of the particles (the pieces one rank reads of an MPI checkpoint)."""
    from . import schema as S
    try:
        N = int(record["particles"]["n"]) if not subset else int(arrays["state_id"].shape[0])
        nw = sum(int(w.get("slots", 1)) for w in record["walls"])   # wall rows (a mesh wall has several)
        nmat = len(record["materials"])
        feats = _features(record)
        flow = record.get("flow") or {}   # the inlets and outlets by name (dem.flow)
        n_in = len(flow.get("inlets", []))
        n_flow = n_in + len(flow.get("outlets", []))
    except (KeyError, TypeError, ValueError, AttributeError):
        raise CheckpointError(path, "checkpoint is damaged: its record lacks particles, walls or materials") \
            from None
    W1 = max(nw, 1)

    def need(key, dtype, *shapes, required=True):
        a = arrays.get(key)
        if a is None:
            if required:
                raise CheckpointError(path, f"checkpoint is damaged: array {key!r} is missing")
            return None
        if a.dtype != dtype or a.shape not in shapes:
            want = " or ".join(str(s) for s in shapes)
            raise CheckpointError(path, f"checkpoint is damaged: array {key!r} has shape {a.shape} dtype "
                                        f"{a.dtype}, expected {want} {dtype} for {N} particles and {nw} "
                                        f"walls")
        return a

    for k in ("step_count", "ranks"):
        need(k, I8, ())
    for k in ("dt", "fp_tbuild"):
        need(k, F8, ())
    need("forces_ready", np.dtype(np.bool_), ())
    if int(arrays["step_count"]) < 0:
        raise CheckpointError(path, "checkpoint is damaged: negative step_count")
    # the adaptive skin and its gap density (checkpoints before it ran the scene's fixed skin)
    for k, lo in (("fp_skin", 0.0), ("fp_gapd", -1.0)):
        a = need(k, F8, (), required=False)
        if a is not None and not (math.isfinite(float(a)) and float(a) > lo):
            raise CheckpointError(path, f"checkpoint is damaged: {k} = {float(a)!r}")

    def declared(owner, rows, slots=1):
        for f in S.of(owner):
            if not f.checkpoint:
                continue
            if f.checkpoint in ADDED_LATER and f.checkpoint not in arrays:
                continue  # an older checkpoint: the loader fills it (Simulation.load_checkpoint)
            on = feats.get(f.when, None) if f.when is not None else True
            full = f.shape(rows, W1, slots) if owner != "wall" else (W1,)
            if f.when == "flow":   # one row per inlet and outlet of the record
                full = (n_flow, 3)
            elif owner == "param":
                from .thermal.heat import TOT
                full = (TOT.SIZE,)
            if on is None:  # an older checkpoint: either form
                need(f.checkpoint, f.dtype, full, f.shape(0), required=False)
            elif on:
                need(f.checkpoint, f.dtype, full)
            else:
                need(f.checkpoint, f.dtype, f.shape(0), required=False)

    declared("particle", N)
    if feats.get("heat"):
        declared("wall", N)
        declared("param", N)
    elif feats.get("flow"):   # the particles in and out (dem.flow), with or without heat
        need("flow_tot", F8, (n_flow, 3))
    if feats.get("flow"):
        need("flow_next_id", I8, ())
        need("flow_owed", F8, (n_in,))
    ids = arrays["state_id"]
    mat = arrays["state_material"]
    if np.unique(ids).size != N:
        raise CheckpointError(path, "checkpoint is damaged: particle ids are not unique")
    if N and (mat.min() < 0 or mat.max() >= nmat):
        raise CheckpointError(path, f"checkpoint is damaged: material index out of range 0..{nmat - 1}")
    for f in ("position", "velocity", "angular_velocity", "radius", "mass"):
        if not np.all(np.isfinite(arrays[f"state_{f}"])):
            raise CheckpointError(path, f"checkpoint holds non-finite particle {f.replace('_', ' ')}s")
    if N and not (np.all(arrays["state_radius"] > 0) and np.all(arrays["state_mass"] > 0)):
        raise CheckpointError(path, "checkpoint is damaged: a particle radius or mass is not positive")
    _check_slots(path, "wnb", arrays["wnb"], arrays["wnn"], nw, W1)
    if "nb" in arrays:  # the serial, bit-exact layout: the neighbour list and its slots
        nb = arrays["nb"]
        if nb.dtype != I4 or nb.ndim != 2 or nb.shape[0] != N or nb.shape[1] < 1:
            raise CheckpointError(path, f"checkpoint is damaged: array 'nb' has shape {nb.shape} dtype "
                                        f"{nb.dtype}, expected ({N}, slots) int32")
        declared("pair", N, nb.shape[1])
        _check_slots(path, "nb", nb, arrays["nnb"], N, nb.shape[1])
    elif int(arrays["ranks"]) == 1:
        raise CheckpointError(path, "checkpoint is damaged: array 'nb' (neighbour list) is missing")
    if "rec_a" in arrays:
        M = arrays["rec_a"].shape[0] if arrays["rec_a"].ndim == 1 else -1
        a = need("rec_a", I8, (M,))
        b = need("rec_b", I8, (M,))
        need("rec_hist", F8, (M, 3))
        need("rec_rhist", F8, (M, 3), required=False)
        need("rec_age", F8, (M, 2), required=False)
        if M and not subset and not (np.all(np.isin(a, ids)) and np.all(np.isin(b, ids))):
            raise CheckpointError(path, "checkpoint is damaged: a contact record names an unknown particle")


def _check_slots(path, key, idx, count, limit, slots):
    """Indices in the used slots of a list lie in [0, limit); counts in [0, slots]."""
    if count.size and (count.min() < 0 or count.max() > min(slots, limit if key == "wnb" else slots)):
        raise CheckpointError(path, f"checkpoint is damaged: counts of {key!r} out of range")
    used = np.arange(idx.shape[1])[None, :] < count[:, None]
    v = idx[used]
    if v.size and (v.min() < 0 or v.max() >= limit):
        raise CheckpointError(path, f"checkpoint is damaged: {key!r} holds an index out of range")


# ---------------------------------------------------------------------------- the record
WALL_GEOMETRY = ("type", "point", "normal", "u_axis", "extent", "axis", "radius", "inside", "length",
                 "velocity", "angular_velocity", "rotation_center",
                 "file", "scale", "rotate", "translate", "digest", "slots", "oscillation")   # a mesh wall's (the digest: its triangles)
THERMAL_CHOICES = ("direct", "contact_radius", "correction", "indirect", "convection", "radiation",
                   "friction_heat", "partition", "porosity", "integrator", "time_step")
THERMAL_PARAMS = ("direct_factor", "impact_ct", "impact_cn", "chi")
THERMAL_PARAM_KEYS = {"impact_ct": "impact_heat_ct", "impact_cn": "impact_heat_cn", "chi": "friction_heat_chi"}


def _plain(x):
    """JSON-ready copy (numpy arrays and scalars to lists and floats)."""
    if isinstance(x, dict):
        return {str(k): _plain(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [_plain(v) for v in x]
    if isinstance(x, np.ndarray):
        return _plain(x.tolist())
    if isinstance(x, (bool, np.bool_)):
        return bool(x)
    if isinstance(x, (int, np.integer)):
        return int(x)
    if isinstance(x, (float, np.floating)):
        return float(x)
    return x


def _digest(*arrays):
    h = hashlib.sha256()
    for a in arrays:
        a = np.ascontiguousarray(a)
        h.update(f"{a.dtype.str}{a.shape}".encode())
        h.update(a.tobytes())
    return h.hexdigest()[:32]


def particle_digests(scene):
    """Digests of the scene's particle definitions, ordered by id (cached on the scene)."""
    d = getattr(scene, "particle_digests", None)
    if d is not None:
        return d
    order = np.argsort(scene.id, kind="stable")
    names = np.array([m["name"] for m in scene.materials])[scene.material[order]]
    d = dict(ids=_digest(np.asarray(scene.id, np.int64)[order]),
             radius=_digest(np.asarray(scene.radius, float)[order]),
             material="".join(hashlib.sha256("\n".join(names.tolist()).encode()).hexdigest()[:32]),
             position=_digest(np.asarray(scene.position, float)[order]),
             velocity=_digest(np.asarray(scene.velocity, float)[order]),
             angular_velocity=_digest(np.asarray(scene.angular_velocity, float)[order]),
             group=_digest(np.asarray(scene.group, np.int32)[order]))
    if scene.thermal is not None:
        d["temperature"] = _digest(np.asarray(scene.thermal["temperature"], float)[order])
    cg = parcel_factors(scene)
    if cg is not None:   # parcels (a scene without them records nothing new)
        d["coarse_graining"] = _digest(np.asarray(cg, float)[order])
    scene.particle_digests = d  # a Scene holds plain validated data: a public, derived entry
    return d


def scene_record(sim):
    """What a restart compares: the scene's settings, materials and walls by name."""
    sc = sim.scene
    mats = [_plain(m) for m in sc.materials]
    walls = []
    for k, w in enumerate(sc.walls):
        rec = {key: _plain(w[key]) for key in WALL_GEOMETRY if key in w}
        rec.update(name=w["name"], material=sc.materials[w["material"]]["name"])
        if sc.thermal is not None:
            tw = sc.thermal["walls"][k]
            rec["thermal"] = _plain({key: tw[key] for key in ("condition", "temperature", "heat_flux", "table")})
        walls.append(rec)
    thermal = None
    if sc.thermal is not None:
        th = sc.thermal
        thermal = {key: _plain(th[key]) for key in THERMAL_CHOICES + THERMAL_PARAMS}
        thermal.update(gas=_plain(th["gas"]), gas_velocity=_plain(th["gas_velocity"]),
                       sources=_plain(th["sources"]))
    simulation = {k: _plain(v) for k, v in sc.simulation.items()}
    from . import schema as S
    flow = sim.world.flow.record() if sim.world.flow is not None else None
    return dict(particles=dict(n=int(sim.n_particles), n0=int(sc.n_total), digests=particle_digests(sc)),
                flow=flow,
                step_count=int(sim.step_count), time=float(sim.time), dt=float(sim.dt),
                reach=float(sim.world.reach), simulation=simulation, domain=_plain(sc.domain),
                contact=_plain(sc.contact), materials=mats, walls=walls, thermal=thermal,
                features={k: bool(v) for k, v in sim.state.features.items()
                          if k not in S.COUPLING_FEATURES},
                output=_plain(sc.output), parallel=_plain(sc.parallel))


# ---------------------------------------------------------------------------- restart plan
class Plan:
    """What a restart with this scene does to the checkpoint's arrays."""

    def __init__(self):
        self.applied = []          # one line per applied change
        self.material_map = None   # old material index -> new index
        self.wall_map = None       # old wall index -> new index
        self.nwalls_old = 0
        self.walls_old = []
        self.density = set()       # new material indices whose mass changes
        self.heat_capacity = set()  # new material indices whose heat capacity changes
        self.rebuild = False       # neighbour / wall lists must be rebuilt (portable load)
        self.recompute_forces = False  # the physics changed: forces at the restart time again
        self.gas_temperature = None
        self.gas_velocity = None
        self.gas_porosity = None
        self.sources = False


def _fmt(x):
    if isinstance(x, float):
        return f"{x:g}"
    if isinstance(x, list):
        return "[" + ", ".join(_fmt(e) for e in x) + "]"
    if isinstance(x, dict):
        return "{" + ", ".join(f"{k} = {_fmt(v)}" for k, v in x.items()) + "}"
    return repr(x) if isinstance(x, str) else str(x)


def _refuse(sim, ck_path, key, old, new, why):
    raise SceneError(sim.scene.file, key,
                     f"changed from {_fmt(old)} to {_fmt(new)} since the checkpoint {ck_path} was written; "
                     f"{why}. Restore the value to continue this run, or start a new run")


SIM_APPLIED = {"end_time": "", "output_interval": "", "checkpoint_interval": "", "sort_interval": "",
               "force": "", "max_overlap_ratio": "", "initial_overlap_ratio": "(no effect after the start)",
               "seed": "(no effect after the start)", "gravity": "", "neighbor_skin": "(lists rebuilt)",
               "neighbor_skin_auto": "(lists rebuilt)"}
# [simulation] entries newer than some checkpoints: what a checkpoint without them ran
SIM_ADDED = {"neighbor_skin_auto": False}
SIM_REFUSED = {"time_step": "the contact history and every integrated quantity assume one step",
               "mechanics": "frozen and moving packings keep different arrays"}
CONTACT_REFUSED = {"model": "the contact history holds the springs of the former model",
                   "rolling": "the rolling history exists only with the model that wrote it"}
# [contact] keys newer than some checkpoints: what a checkpoint without them ran
CONTACT_ADDED = {"tangential": "rescaled"}


def plan_restart(sim, ck_path, arrays, record):
    """Compare the checkpoint's record with the scene of ``sim``: a :class:`Plan` of the
    changes to apply, or :class:`dem.scene.SceneError` naming the first refused key."""
    now = scene_record(sim)
    plan = Plan()
    n_ck = int(record["particles"].get("n0", record["particles"]["n"]))   # the scene's, not the flow's
    if n_ck != sim.scene.n_total:
        raise SceneError(sim.scene.file, "particles",
                         f"the scene defines {sim.scene.n_total} particles, the checkpoint {ck_path} was written by a "
                         f"scene of {n_ck}; particles cannot be added or removed on restart (start a new run, or "
                         f"add an [[inlets]] entry)")
    old_flow, new_flow = record.get("flow"), now.get("flow")
    if (old_flow or None) != (new_flow or None):
        raise SceneError(sim.scene.file, "inlets" if (new_flow or old_flow or {}).get("inlets") else "outlets",
                         f"the inlets and outlets {_fmt(new_flow)} differ from those of the run that wrote the "
                         f"checkpoint {ck_path} ({_fmt(old_flow)}); their names cannot change on restart (their "
                         f"totals continue); their rates, regions and intervals can")
    _plan_simulation(sim, ck_path, record, now, plan)
    for k in ("min", "max", "periodic"):
        if record["domain"][k] != now["domain"][k]:
            _refuse(sim, ck_path, f"domain.{k}", record["domain"][k], now["domain"][k],
                    "particle positions were wrapped and binned in the former domain")
    _plan_contact(sim, ck_path, record, now, plan)
    _plan_materials(sim, ck_path, arrays, record, now, plan)
    _plan_particles(sim, ck_path, record, now)
    _plan_walls(sim, ck_path, arrays, record, now, plan)
    _plan_thermal(sim, ck_path, record, now, plan)
    for sec in ("output", "parallel"):
        for k, new in now[sec].items():
            old = record[sec].get(k)
            if old != new:
                plan.applied.append(f"{sec}.{k} {_fmt(old)} -> {_fmt(new)}")
    if now["reach"] != record["reach"]:
        plan.rebuild = True
    return plan


def _plan_particles(sim, ck_path, record, now):
    labels = dict(ids="particle ids", coarse_graining="coarse-graining factors (particles[].coarse_graining)",
                  radius="radii", material="materials of the particles",
                  position="initial positions", velocity="initial velocities",
                  angular_velocity="initial angular velocities", group="particle groups",
                  temperature="initial temperatures (thermal.initial_temperature, initial_regions or "
                              "particles[].temperature)")
    old, new = record["particles"]["digests"], now["particles"]["digests"]
    for k in labels:   # the serial digests, or the sums of a scene set up per rank (dem.parallel.setup)
        if any(d in old and d in new and old[d] != new[d] for d in (k, k + "_sum")):
            raise SceneError(sim.scene.file, "particles",
                             f"the {labels[k]} differ from the scene that wrote the checkpoint {ck_path}; "
                             f"particle definitions are initial conditions and cannot change on restart "
                             f"(the checkpoint's particles continue). Restore them, or start a new run")


def _plan_simulation(sim, ck_path, record, now, plan):
    old_s, new_s = record["simulation"], now["simulation"]
    if record["dt"] != now["dt"]:
        key = "thermal.time_step" if (sim.scene.thermal or {}).get("time_step") else "simulation.time_step"
        _refuse(sim, ck_path, key, record["dt"], now["dt"], SIM_REFUSED["time_step"])
    for k, new in new_s.items():
        old = old_s.get(k, SIM_ADDED.get(k))
        if old == new:
            continue
        if k in SIM_REFUSED:
            _refuse(sim, ck_path, f"simulation.{k}", old, new, SIM_REFUSED[k])
        note = SIM_APPLIED.get(k, "")
        plan.applied.append(f"simulation.{k} {_fmt(old)} -> {_fmt(new)}" + (f" {note}" if note else ""))
        if k in ("neighbor_skin", "neighbor_skin_auto"):
            plan.rebuild = True
        if k == "gravity":
            plan.recompute_forces = True


def _plan_contact(sim, ck_path, record, now, plan):
    for k, new in now["contact"].items():
        old = record["contact"].get(k, CONTACT_ADDED.get(k))
        if old == new:
            continue
        if k in CONTACT_REFUSED:
            _refuse(sim, ck_path, f"contact.{k}", old, new, CONTACT_REFUSED[k])
        plan.applied.append(f"contact.{k} {_fmt(old)} -> {_fmt(new)}")
        plan.recompute_forces = True


def _plan_materials(sim, ck_path, arrays, record, now, plan):
    old_names = [m["name"] for m in record["materials"]]
    new_index = {m["name"]: k for k, m in enumerate(now["materials"])}
    mat = arrays["state_material"]
    counts = np.bincount(mat, minlength=len(old_names)) if mat.size else np.zeros(len(old_names), int)
    mapping = np.zeros(max(len(old_names), 1), np.int32)
    for k, name in enumerate(old_names):
        if name not in new_index:
            if counts[k]:
                raise SceneError(sim.scene.file, f"materials[{name}]",
                                 f"removed, but {counts[k]} particles of the checkpoint {ck_path} are made of "
                                 f"it; a material used by particles cannot be removed on restart (change its "
                                 f"properties instead, or start a new run)")
            plan.applied.append(f"materials[{name}] removed (no particle uses it)")
            continue
        mapping[k] = new_index[name]
    plan.material_map = mapping
    if any(new_index.get(name) != k for k, name in enumerate(old_names) if name in new_index):
        plan.applied.append("materials renumbered by name: " + ", ".join(
            f"{name} {k} -> {new_index[name]}" for k, name in enumerate(old_names)
            if name in new_index and new_index[name] != k))
    old_by_name = {m["name"]: (k, m) for k, m in enumerate(record["materials"])}
    for m in now["materials"]:
        name = m["name"]
        if name not in old_by_name:
            plan.applied.append(f"materials[{name}] added")
            continue
        k, old = old_by_name[name]
        j = new_index[name]
        for key in sorted(set(old) | set(m)):
            if key == "name" or old.get(key) == m.get(key):
                continue
            what = "contact tables"
            if key == "density":
                plan.density.add(j)
                what = f"mass and inertia of {counts[k]} particles"
            elif key == "heat_capacity":
                plan.heat_capacity.add(j)
                what = f"heat capacity of {counts[k]} particles"
            elif key not in ("youngs_modulus", "poisson_ratio", "restitution", "friction", "rolling_friction"):
                what = "thermal tables"
            plan.applied.append(f"materials[{name}].{key} {_fmt(old.get(key))} -> {_fmt(m.get(key))} ({what})")
            plan.recompute_forces = True


def _plan_walls(sim, ck_path, arrays, record, now, plan):
    old_w, new_w = record["walls"], now["walls"]
    old_names = [w["name"] for w in old_w]
    new_names = [w["name"] for w in new_w]
    plan.nwalls_old = len(old_w)
    plan.walls_old = old_w
    if old_w == new_w:
        plan.wall_map = np.arange(max(len(old_w), 1), dtype=np.int32)
        return
    for names, where in ((old_names, f"the checkpoint {ck_path}"), (new_names, "the scene")):
        dup = sorted({n for n in names if names.count(n) > 1})
        if dup:
            raise SceneError(sim.scene.file, "walls",
                             f"the walls changed and {where} has several walls named {dup[0]!r}; walls are "
                             f"matched by name on restart: give every wall a unique name")
    new_index = {n: k for k, n in enumerate(new_names)}
    mapping = np.zeros(max(len(old_w), 1), np.int32)
    for k, w in enumerate(old_w):
        name = w["name"]
        if name not in new_index:
            raise SceneError(sim.scene.file, f"walls[{name}]",
                             f"removed since the checkpoint {ck_path} was written; a wall cannot be removed on "
                             f"restart (particles may rest on it and its heat totals are in the history). "
                             f"Unnamed walls are named wall0, wall1, ... by position: name your walls "
                             f"and add new ones after them")
        nw_ = new_w[new_index[name]]
        for key in WALL_GEOMETRY:
            if w.get(key) != nw_.get(key):
                _refuse(sim, ck_path, f"walls[{name}].{key}", w.get(key), nw_.get(key),
                        "a wall's position at time t is point + velocity t from t = 0: a changed geometry "
                        "or motion would move it under the particles in contact")
        if w["material"] != nw_["material"]:
            plan.applied.append(f"walls[{name}].material {w['material']!r} -> {nw_['material']!r}")
            plan.recompute_forces = True
        old_t, new_t = w.get("thermal"), nw_.get("thermal")
        if old_t != new_t:
            for key in sorted(set(old_t or {}) | set(new_t or {})):
                a, b = (old_t or {}).get(key), (new_t or {}).get(key)
                if a != b:
                    plan.applied.append(f"walls[{name}].thermal.{key} {_fmt(a)} -> {_fmt(b)}")
        mapping[k] = new_index[name]
    if [new_index[n] for n in old_names] != list(range(len(old_names))):
        plan.applied.append("walls renumbered by name")
    for name in new_names:
        if name not in old_names:
            _check_added_wall(sim, ck_path, arrays, record, new_index[name], name)
            plan.applied.append(f"walls[{name}] added ({len(new_w)} walls; wall lists rebuilt)")
    plan.wall_map = mapping
    plan.rebuild = True
    plan.recompute_forces = True


def _check_added_wall(sim, ck_path, arrays, record, k, name):
    """An added wall must not cut through the checkpoint's particles beyond the overlap
    bound (the first step would stop the run): refused here, before anything is written."""
    from .stats import max_overlap_ratio
    x, r = arrays["state_position"], arrays["state_radius"]
    n = r.shape[0]
    w = sim.scene.walls[k]
    if w["type"] == "mesh":   # the particles in the mesh's frame at that time (dem.contact.mesh)
        from .contact.mesh import nearest, mesh_frame_points
        s = w["surface"]
        X = mesh_frame_points(w, x, float(record["time"]))
        d, _ = nearest(X, r, s.verts, s.faces, s.bins(float(2.0 * r.max(initial=1e-3))))
        ov = float(np.max((r - d) / r, initial=0.0))
    else:
        row = int(sim.world.wall_first[k])
        wf = np.ascontiguousarray(sim.state.wf[row:row + 1])
        wi = np.ascontiguousarray(sim.state.wi[row:row + 1])
        ov = max_overlap_ratio(n, x, r, np.zeros((n, 1), np.int32), np.zeros(n, np.int32), sim.state.lo,
                               sim.state.hi, sim.state.periodic, wf, wi, 1, float(record["time"]))
    bound = sim.scene.simulation["max_overlap_ratio"]
    if ov > bound:
        raise SceneError(sim.scene.file, f"walls[{name}]",
                         f"added, but at the checkpoint's time t = {record['time']:.6g} s it cuts through "
                         f"particles (overlap up to {ov:.3g} of a radius, above simulation.max_overlap_ratio "
                         f"= {bound:g}); place the new wall clear of the particles")


def _plan_thermal(sim, ck_path, record, now, plan):
    old, new = record["thermal"], now["thermal"]
    if old is None and new is None:
        return
    if (old is None) != (new is None):
        raise SceneError(sim.scene.file, "thermal",
                         f"the [thermal] section was {'added' if old is None else 'removed'} since the checkpoint "
                         f"{ck_path} was written; heat transfer cannot be switched on restart (start a new run)")
    for k in THERMAL_CHOICES:
        if old[k] != new[k]:
            _refuse(sim, ck_path, f"thermal.{k}", old[k], new[k],
                    "the model choices decide which thermal arrays a run keeps and what they mean")
    for k in THERMAL_PARAMS:
        if old[k] != new[k]:
            plan.applied.append(f"thermal.{THERMAL_PARAM_KEYS.get(k, k)} {_fmt(old[k])} -> {_fmt(new[k])}")
    for k in sorted(set(old["gas"]) | set(new["gas"])):
        a, b = old["gas"].get(k), new["gas"].get(k)
        if a == b or k == "velocity":  # the magnitude of gas_velocity, listed below
            continue
        note = ""
        if k == "temperature":
            plan.gas_temperature = b
            note = " (gas temperature at every particle)"
        elif k == "porosity":
            plan.gas_porosity = b
        plan.applied.append(f"gas.{k} {_fmt(a)} -> {_fmt(b)}{note}")
        plan.recompute_forces = True
    if old["gas_velocity"] != new["gas_velocity"]:
        plan.gas_velocity = new["gas_velocity"]
        plan.applied.append(f"gas.velocity {_fmt(old['gas_velocity'])} -> {_fmt(new['gas_velocity'])} "
                            f"(gas velocity at every particle)")
    if old["sources"] != new["sources"]:
        plan.sources = True
        plan.applied.append(f"thermal.sources {_fmt(old['sources'])} -> {_fmt(new['sources'])}")


# ---------------------------------------------------------------------------- applying it
def apply_edits(arrays, plan, sim):
    """Rewrite the checkpoint's arrays (rows in checkpoint order) for the scene of ``sim``."""
    if plan.material_map is not None and arrays["state_material"].size:
        arrays["state_material"] = np.ascontiguousarray(plan.material_map[arrays["state_material"]], np.int32)
    _apply_material_properties(arrays, plan, sim)
    if plan.rebuild or (plan.wall_map is not None and len(sim.scene.walls) != plan.nwalls_old):
        _remap_walls(arrays, plan, sim)
    th = sim.thermal
    if th is None:
        return
    n = arrays["state_id"].shape[0]
    if plan.gas_temperature is not None:
        arrays["th_tf"] = np.full(n, float(plan.gas_temperature))
    if plan.gas_velocity is not None:
        arrays["th_uf"] = np.tile(np.asarray(plan.gas_velocity, float), (n, 1))
    if plan.gas_porosity is not None and not th.local_porosity:
        arrays["th_por"] = np.full(n, float(plan.gas_porosity))
    if plan.sources:
        q = np.zeros(n)
        for s in th.cfg["sources"]:
            if "power" in s:
                q[arrays["state_group"] == s["group"]] += s["power"]
        arrays["th_qsrc"] = q if np.any(q != 0) else np.zeros(0)


def _apply_material_properties(arrays, plan, sim):
    """Mass, inertia and heat capacity of every particle of a material whose density or heat
    capacity changed, with the formulas of dem.state.State (a fresh run gets the same bits)."""
    mats = sim.scene.materials
    mat = arrays["state_material"]
    r = arrays["state_radius"]
    for j in sorted(plan.density | plan.heat_capacity):
        sel = mat == j
        if not np.any(sel):
            continue
        if j in plan.density:
            m = 4.0 / 3.0 * np.pi * r[sel] ** 3 * float(mats[j]["density"])
            arrays["state_mass"][sel] = m
            arrays["state_inv_mass"][sel] = 1.0 / m
            arrays["state_inv_inertia"][sel] = 1.0 / (0.4 * m * r[sel] ** 2)
        if sim.thermal is not None and "state_inv_heat_capacity" in arrays:
            cp = float(mats[j]["heat_capacity"])
            arrays["state_inv_heat_capacity"][sel] = 1.0 / (arrays["state_mass"][sel] * cp)


def _remap_walls(arrays, plan, sim):
    """Per-wall columns of the histories moved to each wall's new index; added walls start
    with none. The wall lists themselves are rebuilt by the loader."""
    from .contact.walls import wall_rows
    old_w = plan.walls_old
    f_old, o_old = wall_rows(old_w)
    f_new, o_new = wall_rows(sim.scene.walls)
    nw_new = o_new.size
    W1 = max(nw_new, 1)
    # rows: each old wall's rows onto its new wall's (a wall keeps its type, so its row count)
    src = np.arange(o_old.size)
    dst = (f_new[plan.wall_map[o_old]] + (src - f_old[o_old])).astype(np.int64) if src.size else src
    row_map = np.zeros(max(o_old.size, 1), np.int32)
    row_map[src] = dst

    wnb, wnn = arrays["wnb"], arrays["wnn"]
    new = np.zeros((wnb.shape[0], W1), np.int32)
    used = np.arange(wnb.shape[1])[None, :] < wnn[:, None]
    if plan.nwalls_old:
        new[:, :wnb.shape[1]] = np.where(used, row_map[np.where(used, wnb, 0)], 0)
    from . import schema as S
    for f in S.of("particle"):
        a = arrays.get(f.checkpoint) if f.checkpoint else None
        if a is None or a.shape[0] == 0 or f.tail[:1] not in (("W",), ("Q",)):
            continue
        b = np.zeros((a.shape[0], W1) + a.shape[2:], a.dtype)
        if f.tail[0] == "W":  # one column per wall: moved with the wall
            b[:, dst] = a[:, src]
        arrays[f.checkpoint] = b  # per candidate: rebuilt (wnb below) or recomputed (Hw)
    for key in (f.checkpoint for f in S.of("wall") if f.checkpoint):   # per-wall totals
        if key in arrays:
            w = np.zeros(W1)
            w[dst] = arrays[key][src]
            arrays[key] = w
    arrays["wnb"] = new  # the candidates' wall indices, renumbered
    arrays["wnn"] = np.ascontiguousarray(wnn, np.int32)

