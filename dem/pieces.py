"""Per-rank pieces of an MPI run's output (checkpoint.npz, final.npz) that can be read by row range.

A piece is an uncompressed ``.npz`` (``np.savez``) holding one rank's rows ordered by particle id
(every array whose first dimension is the row count) and, for a checkpoint, the contact records
of those rows (``rec_*`` arrays) listed under the row of each of their particles in the piece, with
``rec_start`` (rows + 1 offsets: the records of rows [a, b) are ``rec_start[a]:rec_start[b]``).
Beside them:

    format, format_version   what the piece is
    block_rows               B: the rows are verified in blocks of B rows
    block_sha                (blocks, 32) uint8: sha256 of each block (the rows of every array,
                             their rec_start entries and their records)
    checksum                 sha256 (hex) over the name, dtype and shape of every entry, the
                             scalars and ``block_sha``: the piece's digest, named in the manifest

so that a reader of rows [a, b) opens only the members' headers (:class:`NpzMembers`: the offset
of each array's data in the file, no decompression: np.savez stores), checks the digest against
the manifest, then reads and verifies the blocks that cover [a, b) and nothing else (at most
2 (B - 1) rows more than asked). B grows with the piece (about 256 blocks a piece, 16 to 1024
rows), so the digests are a few bytes a row and the slack about 1 % of a piece.
"""
import hashlib
import os
import struct
import zipfile

import numpy as np

PIECE_VERSION = 2
_META = ("format", "format_version", "block_rows", "block_sha", "checksum")


class PieceError(Exception):
    """A piece that cannot be used: ``str()`` says which file and what is wrong."""


def block_rows(rows):
    return int(min(1024, max(16, -(-rows // 256))))


def anchor_records(ids, rec):
    """The records ``rec`` (dict of rec_* arrays, key pairs rec_a / rec_b) listed under the row (in
    ``ids``, ascending) of each of their particles that ``ids`` holds (a record of two particles
    of the piece is listed twice, so that the reader of either row has it; a record of neither
    is dropped), ordered by row, and ``rec_start``."""
    n = ids.size
    a, b = rec["rec_a"], rec["rec_b"]
    ia = np.minimum(np.searchsorted(ids, a), max(n - 1, 0))
    ib = np.minimum(np.searchsorted(ids, b), max(n - 1, 0))
    has_a = (ids[ia] == a) if n else np.zeros(a.size, bool)
    has_b = (ids[ib] == b) if n else np.zeros(b.size, bool)
    which = np.concatenate([np.nonzero(has_a)[0], np.nonzero(has_b)[0]])
    row = np.concatenate([ia[has_a], ib[has_b]])
    order = np.argsort(row, kind="stable")
    which, row = which[order], row[order]
    out = {k: np.ascontiguousarray(v[which]) for k, v in rec.items()}
    out["rec_start"] = np.searchsorted(row, np.arange(n + 1)).astype(np.int64)
    return out


def _header_digest(entries, scalars, bsha):
    """The piece's digest: names, dtypes, shapes of ``entries`` {name: (dtype, shape)}, the bytes
    of ``scalars`` and the block digests."""
    h = hashlib.sha256()
    for k in sorted(entries):
        if k == "checksum":
            continue
        dt, shape = entries[k]
        h.update(f"{k}\0{np.dtype(dt).str}\0{tuple(shape)}\0".encode())
    for k in sorted(scalars):
        h.update(k.encode() + b"\0" + np.ascontiguousarray(scalars[k]).tobytes())
    h.update(np.ascontiguousarray(bsha, np.uint8).tobytes())
    return h.hexdigest()


def _block_digest(rows_of, rec_of, rec_start):
    """sha256 of one block: its rows of every row array, its rec_start entries, its records."""
    h = hashlib.sha256()
    for k in sorted(rows_of):
        h.update(k.encode() + b"\0" + np.ascontiguousarray(rows_of[k]).tobytes())
    h.update(np.ascontiguousarray(rec_start).tobytes())
    for k in sorted(rec_of):
        h.update(k.encode() + b"\0" + np.ascontiguousarray(rec_of[k]).tobytes())
    return np.frombuffer(h.digest(), np.uint8)


def _split(arrays, n):
    """(row arrays, record arrays, other arrays) of a piece of ``n`` rows."""
    rows, rec, other = {}, {}, {}
    for k, v in arrays.items():
        if k.startswith("rec_") and k != "rec_start":
            rec[k] = v
        elif k != "rec_start" and v.ndim >= 1 and v.shape[0] == n and k not in _META:
            rows[k] = v
        elif k not in _META and k != "rec_start":
            other[k] = v
    return rows, rec, other


def make_piece(arrays, rows, fmt):
    """``arrays`` (rows ordered by id; optional rec_* arrays ordered by anchor with rec_start)
    with the format, the block digests and the checksum: (entries to save, digest)."""
    out = {k: np.ascontiguousarray(v) for k, v in arrays.items()}
    if any(k.startswith("rec_") for k in out) and "rec_start" not in out:
        raise ValueError("records without rec_start")
    rs = out.get("rec_start", np.zeros(rows + 1, np.int64))
    R, C, other = _split(out, rows)
    B = block_rows(rows)
    nb = -(-rows // B)
    bsha = np.zeros((nb, 32), np.uint8)
    for k in range(nb):
        lo, hi = k * B, min((k + 1) * B, rows)
        bsha[k] = _block_digest({n: v[lo:hi] for n, v in R.items()}, {n: v[rs[lo]:rs[hi]] for n, v in C.items()},
                                rs[lo:hi + 1] if "rec_start" in out else np.zeros(0, np.int64))
    out["format"] = np.str_(fmt)
    out["format_version"] = np.int64(PIECE_VERSION)
    out["block_rows"] = np.int64(B)
    out["block_sha"] = bsha
    entries = {k: (v.dtype, v.shape) for k, v in out.items()}
    scalars = dict(format=out["format"], format_version=out["format_version"], block_rows=out["block_rows"])
    scalars.update({k: v for k, v in other.items()})   # whole small entries (empty arrays of disabled features)
    digest = _header_digest(entries, scalars, bsha)
    out["checksum"] = np.str_(digest)
    return out, digest


def write_piece(path, arrays, rows, fmt):
    """Write a piece atomically and durably; returns its digest (named in the manifest)."""
    from .output import save_npz
    out, digest = make_piece(arrays, rows, fmt)
    save_npz(path, durable=True, **out)
    return digest


class NpzMembers:
    """The arrays of an uncompressed .npz read by row range without loading them whole: each
    member's dtype, shape and the offset of its data in the file (zip local header + .npy
    header)."""

    def __init__(self, path):
        self.path = path
        self.fh = open(path, "rb")
        self.members = {}
        try:
            with zipfile.ZipFile(self.fh) as z:
                infos = z.infolist()
            for info in infos:
                if info.compress_type != zipfile.ZIP_STORED or not info.filename.endswith(".npy"):
                    raise PieceError(f"{path}: member {info.filename} is compressed or not an array")
                self.fh.seek(info.header_offset)
                head = self.fh.read(30)
                if head[:4] != b"PK\x03\x04":
                    raise PieceError(f"{path}: damaged zip header of {info.filename}")
                nlen, xlen = struct.unpack("<HH", head[26:30])
                self.fh.seek(info.header_offset + 30 + nlen + xlen)
                version = np.lib.format.read_magic(self.fh)
                read_header = (np.lib.format.read_array_header_1_0 if version == (1, 0)
                               else np.lib.format.read_array_header_2_0)
                shape, fortran, dtype = read_header(self.fh)
                if fortran or dtype.hasobject:
                    raise PieceError(f"{path}: member {info.filename} is not a plain C-ordered array")
                self.members[info.filename[:-4]] = (dtype, tuple(shape), self.fh.tell())
        except PieceError:
            self.fh.close()
            raise
        except Exception as exc:  # noqa: BLE001  (BadZipFile, struct, ValueError of a damaged header)
            self.fh.close()
            raise PieceError(f"{path}: corrupted or truncated ({type(exc).__name__}: {str(exc)[:100]})") from None

    def close(self):
        self.fh.close()

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()

    def rows(self, name, lo, hi):
        """Rows [lo, hi) of member ``name``."""
        dtype, shape, off = self.members[name]
        per = int(np.prod(shape[1:], dtype=np.int64)) if len(shape) > 1 else 1
        count = (hi - lo) * per
        if shape == () or count == 0:
            if shape == ():
                return self.whole(name)
            return np.zeros((0,) + shape[1:], dtype)
        self.fh.seek(off + lo * per * dtype.itemsize)
        a = np.fromfile(self.fh, dtype, count)
        if a.size != count:
            raise PieceError(f"{self.path}: truncated ({name})")
        return a.reshape((hi - lo,) + shape[1:])

    def whole(self, name):
        dtype, shape, off = self.members[name]
        n = int(np.prod(shape, dtype=np.int64))
        self.fh.seek(off)
        a = np.fromfile(self.fh, dtype, n)
        if a.size != n:
            raise PieceError(f"{self.path}: truncated ({name})")
        return a.reshape(shape)


def read_rows(path, fmt, digest, lo=0, hi=None):
    """(arrays of rows [lo, hi) with their records, rows read from the file) of the piece ``path``
    whose digest the manifest names ``digest``: only the blocks covering [lo, hi) are read, each
    verified. Raises PieceError naming the file."""
    if not os.path.exists(path):
        raise PieceError(f"piece {path} is missing")
    with NpzMembers(path) as z:
        m = z.members
        for k in _META:
            if k not in m:
                raise PieceError(f"piece {path} is not a piece of this format (no {k!r})")
        try:
            head = {k: z.whole(k) for k in ("format", "format_version", "block_rows", "checksum")}
        except ValueError:
            raise PieceError(f"piece {path} is corrupted") from None
        if str(head["format"]) != fmt:
            raise PieceError(f"piece {path} is not a {fmt}")
        n = None
        for k, (dt, shape, _) in m.items():
            if k in ("id", "state_id"):
                n = shape[0]
        if n is None:
            raise PieceError(f"piece {path} holds no particle ids")
        hi = n if hi is None else hi
        bsha = z.whole("block_sha")
        entries = {k: (dt, shape) for k, (dt, shape, _) in m.items()}
        rowk = [k for k, (dt, shape, _) in m.items() if k not in _META and k != "rec_start"
                and not k.startswith("rec_") and len(shape) >= 1 and shape[0] == n]
        reck = [k for k in m if k.startswith("rec_") and k != "rec_start"]
        otherk = [k for k in m if k not in _META and k not in rowk and k not in reck and k != "rec_start"]
        scalars = dict(format=head["format"], format_version=head["format_version"],
                       block_rows=head["block_rows"])
        scalars.update({k: z.whole(k) for k in otherk})
        if str(head["checksum"]) != digest or _header_digest(entries, scalars, bsha) != digest:
            raise PieceError(f"piece {path} is corrupted: its content does not match the sha256 the manifest "
                             f"names (changed after it was written)")
        B = int(head["block_rows"])
        if B < 1 or bsha.shape != (-(-n // B), 32) or not (0 <= lo <= hi <= n):
            raise PieceError(f"piece {path} is damaged (blocks)")
        k0, k1 = lo // B, -(-hi // B)
        r0, r1 = k0 * B, min(k1 * B, n)
        if r1 <= r0:
            r0 = r1 = lo
        rows = {k: z.rows(k, r0, r1) for k in rowk}
        has_rs = "rec_start" in m
        rs = z.rows("rec_start", r0, r1 + 1) if has_rs and n else np.zeros(1, np.int64)
        rec = {k: z.rows(k, int(rs[0]), int(rs[-1])) for k in reck}
        for k in range(k0, k1):
            lo_b, hi_b = k * B - r0, min((k + 1) * B, n) - r0
            blk = _block_digest({q: v[lo_b:hi_b] for q, v in rows.items()},
                                {q: v[rs[lo_b] - rs[0]:rs[hi_b] - rs[0]] for q, v in rec.items()},
                                rs[lo_b:hi_b + 1] if has_rs else np.zeros(0, np.int64))
            if not np.array_equal(blk, bsha[k]):
                raise PieceError(f"piece {path} is corrupted: its content does not match the sha256 the manifest "
                                 f"names (rows {k * B}..{min((k + 1) * B, n) - 1} changed after it was written)")
        out = {k: np.ascontiguousarray(v[lo - r0:hi - r0]) for k, v in rows.items()}
        out.update({k: z.whole(k) for k in otherk})
        if has_rs and n:
            a, b = int(rs[lo - r0] - rs[0]), int(rs[hi - r0] - rs[0])
            out.update({k: np.ascontiguousarray(v[a:b]) for k, v in rec.items()})
        elif reck:
            out.update({k: v[:0] for k, v in rec.items()})
        return out, r1 - r0


def shares(piece_rows, rank, size):
    """The slices [(piece index, lo, hi)] rank ``rank`` of ``size`` reads of pieces holding
    ``piece_rows`` rows: rows [rank N / size, (rank + 1) N / size) of their concatenation."""
    rows = np.asarray(piece_rows, np.int64)
    N = int(rows.sum())
    a, b = rank * N // size, (rank + 1) * N // size
    start = np.concatenate([[0], np.cumsum(rows)])
    out = []
    for k in range(rows.size):
        lo, hi = max(a, int(start[k])), min(b, int(start[k + 1]))
        if hi > lo:
            out.append((k, lo - int(start[k]), hi - int(start[k])))
    return out


def remove_stale(folder, keep, name_pattern):
    """Remove the pieces in ``folder`` that the manifest just written does not name (``keep``),
    ours only: names that match ``name_pattern`` (a compiled regex of the caller's piece names)."""
    for name in os.listdir(folder):
        if name_pattern.fullmatch(name) and name not in keep:
            try:
                os.unlink(os.path.join(folder, name))
            except OSError:
                pass
