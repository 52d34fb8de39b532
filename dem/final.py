"""final.npz: the per-particle results at the end of a run, written and read.

A serial run writes one ``final.npz`` (every array with an output name in dem.schema, rows ordered
by id, and ``time``). An MPI run writes no gathered file: each rank writes its own rows (ordered
by id) as a piece in ``final.pieces/`` (dem.pieces: verifiable by block), then rank 0 writes the
manifest ``final.npz``:

    format, format_version   "thermodem-final", FINAL_VERSION
    time, step_count, ranks  the run's scalars
    pieces, piece_sha256     the pieces' file names and digests
    piece_rows, piece_id_min, piece_id_max
    checksum                 sha256 over every other entry

Pieces first (each atomically and durably), the manifest last, then the pieces of ours it does not
name are removed: a kill -9 at any instant leaves the previous final output whole (its manifest
names its own pieces, still there) or none, never a manifest with another run's pieces.

:func:`read` returns the arrays of either form ordered by id (every piece verified; a damaged or
missing piece is refused naming it); ``dem gather OUT`` (:func:`gather`) writes them as one
plain ``final_gathered.npz``, like a serial run's final.npz.
"""
import os
import re

import numpy as np

from .errors import SceneError

FORMAT = "thermodem-final"
FINAL_VERSION = 1
PIECE_FORMAT = "thermodem-final-piece"
GATHERED = "final_gathered.npz"
_PIECE_NAME = re.compile(r"step\d{10}_[0-9a-f]{8}_rank\d{5}\.npz")


class FinalError(SceneError):
    """A final output that cannot be read: ``file: message`` (bad input, exit 2)."""

    def __init__(self, file, message):
        super().__init__(file, "", message)


class FinalArrays(dict):
    """The arrays of a final output by name (also ``.files``, as np.load's result has)."""

    @property
    def files(self):
        return list(self)

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        return False


def pieces_folder(path):
    p = os.fspath(path)
    return (p[:-4] if p.endswith(".npz") else p) + ".pieces"


def piece_name(step, token, rank):
    return f"step{step:010d}_{token:08x}_rank{rank:05d}.npz"


# ---------------------------------------------------------------------------- writing (MPI)
def write_piece(path, arrays):
    """One rank's rows (ordered here by id) as a piece; returns (digest, rows, id min, id max)."""
    from .pieces import write_piece as write
    order = np.argsort(arrays["id"], kind="stable")
    rows = {k: np.ascontiguousarray(v[order] if v.ndim and v.shape[0] == order.size else v)
            for k, v in arrays.items()}
    n = rows["id"].size
    digest = write(path, rows, n, PIECE_FORMAT)
    ids = rows["id"]
    return digest, n, int(ids[0]) if n else -1, int(ids[-1]) if n else -1


def manifest(time, step, names, digests, info):
    """The manifest's arrays (``info``: rows, id min, id max per piece) with its checksum."""
    from .checkpoint import content_digest
    info = np.asarray(info, np.int64).reshape(-1, 3)
    out = dict(format=np.str_(FORMAT), format_version=np.int64(FINAL_VERSION), time=np.float64(time),
               step_count=np.int64(step), ranks=np.int64(len(names)),
               pieces=np.array(names, dtype=np.str_), piece_sha256=np.array(digests, dtype=np.str_),
               piece_rows=info[:, 0].copy(), piece_id_min=info[:, 1].copy(), piece_id_max=info[:, 2].copy())
    out["checksum"] = np.str_(content_digest(out))
    return out


def remove_stale_pieces(folder, keep):
    """Remove the pieces in ``folder`` (our names only) that the manifest does not name."""
    from .pieces import remove_stale
    remove_stale(folder, keep, _PIECE_NAME)


# ---------------------------------------------------------------------------- reading
def _load_npz(path):
    try:
        with np.load(path, allow_pickle=False) as z:
            return {k: z[k] for k in z.files}
    except FileNotFoundError:
        raise FinalError(path, "not found") from None
    except Exception as exc:  # noqa: BLE001  (BadZipFile, EOFError, OSError, ValueError ...)
        raise FinalError(path, f"corrupted or truncated, or not an npz file ({type(exc).__name__})") from None


def is_manifest(arrays):
    return str(arrays.get("format", "")) == FORMAT


def read_manifest(path):
    """The verified manifest arrays of an MPI run's final.npz (FinalError otherwise)."""
    from .checkpoint import content_digest
    path = os.fspath(path)
    arrays = _load_npz(path)
    if not is_manifest(arrays):
        raise FinalError(path, "not the manifest of an MPI run's final output")
    if int(arrays.get("format_version", -1)) != FINAL_VERSION:
        raise FinalError(path, f"final output format version {arrays.get('format_version')}; this thermodem "
                               f"reads version {FINAL_VERSION}")
    if "checksum" not in arrays or content_digest(arrays) != str(arrays["checksum"]):
        raise FinalError(path, "corrupted: its content does not match its sha256 checksum")
    return arrays


def read(path):
    """The per-particle results of a run's final.npz ordered by id, with ``time``: the file itself
    (serial run) or the manifest's pieces, each verified (MPI run). FinalError (exit 2) names a
    missing or damaged file or piece."""
    from .pieces import PieceError, read_rows
    path = os.fspath(path)
    arrays = _load_npz(path)
    if not is_manifest(arrays):
        return FinalArrays(arrays)
    man = read_manifest(path)
    folder = pieces_folder(path)
    parts = []
    for name, digest, rows in zip(man["pieces"], man["piece_sha256"], man["piece_rows"]):
        piece = os.path.join(folder, str(name))
        try:
            got, _ = read_rows(piece, PIECE_FORMAT, str(digest))
        except PieceError as exc:
            raise FinalError(path, f"{exc} (an MPI run's final output is the manifest and the folder of its "
                                   f"pieces: copy both)") from None
        if got["id"].size != int(rows):
            raise FinalError(path, f"piece {piece} holds {got['id'].size} rows, the manifest names {int(rows)}")
        parts.append(got)
    out = {k: np.concatenate([p[k] for p in parts]) for k in parts[0]}
    order = np.argsort(out["id"], kind="stable")
    res = FinalArrays({k: np.ascontiguousarray(v[order]) for k, v in out.items()})
    res["time"] = np.float64(man["time"])
    return res


def gather(out_dir):
    """``dem gather OUT``: OUT/final.npz (either form) as one plain OUT/final_gathered.npz ordered
    by id; refuses to replace a file the tool did not write. Returns the path written."""
    from . import outdir
    from .output import save_npz
    src = os.path.join(out_dir, "final.npz")
    if not os.path.isfile(src):
        raise FinalError(src, "not found: give the output folder of a finished run")
    dst = os.path.join(out_dir, GATHERED)
    listed = None
    try:
        listed = outdir.read_manifest(out_dir)
    except outdir.OutputFolderError:
        pass
    if os.path.lexists(dst) and not (listed is not None and GATHERED in listed):
        raise FinalError(dst, "exists and was not written by dem gather; it is left untouched: move it away "
                              "to gather again")
    arrays = read(src)
    outdir.claim_file(dst, what="dem gather's output")   # recorded in the folder's manifest
    save_npz(dst, **arrays)
    return dst
