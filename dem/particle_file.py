"""Packing files of a ``[[particles]] file = "bed.csv"`` group (CSV or NPZ), read and
checked cell by cell.

Every problem raises :class:`ParticleFileError` whose message names the file, the line
(CSV) or the array and row (NPZ), the column and what is allowed, e.g.::

    bed.csv: line 17, column vz: not a finite number ('nan')

``dem.scene`` turns it into a ``SceneError`` that also names the scene file and the key
(``particles[0].file``). Only the first problem is reported.

CSV: a header line of column names (case-insensitive, surrounding blanks ignored), then one
particle per line, every cell a finite number; ``#`` starts a comment line.
NPZ: one 1-D array per column (``x``, ``y``, ``z``, ...) or the 2-D arrays ``position``,
``velocity``, ``angular_velocity`` of shape (n, 3); all of the same length n.
"""
import csv
import io
import os
import zipfile

import numpy as np

REQUIRED = ("x", "y", "z", "radius")
OPTIONAL = ("vx", "vy", "vz", "wx", "wy", "wz", "id", "temperature")
COLUMNS = REQUIRED + OPTIONAL
VECTORS = {"position": ("x", "y", "z"), "velocity": ("vx", "vy", "vz"),
           "angular_velocity": ("wx", "wy", "wz")}
MAX_MAGNITUDE = 1e100   # as dem.scene.MAX_MAGNITUDE
ALLOWED_TEXT = f"need {', '.join(REQUIRED)}; optional {', '.join(OPTIONAL)}"


class ParticleFileError(ValueError):
    """A packing file problem: ``name: where: message``."""


def read(full):
    """Columns of a packing file as float64 arrays of one length (checked finite, at
    least one particle, the required columns present, no unknown or repeated column), and
    a function naming the place of particle k in the file (``line 17`` / ``row 16``)."""
    name = os.path.basename(full)
    if not os.path.exists(full):
        raise ParticleFileError(f"file not found: {full}")
    if os.path.isdir(full):
        raise ParticleFileError(f"{name}: is a folder ({full}); give a CSV or NPZ file")
    if full.lower().endswith(".npz"):
        cols = _read_npz(full, name)
        where = lambda k: f"row {k}"  # noqa: E731
    else:
        cols, lines = _read_csv(full, name)
        where = lambda k: f"line {lines[k]}"  # noqa: E731
    _check_columns(cols, name)
    _check_values(cols, name, where)
    return cols, where


def _check_columns(cols, name):
    """Every required column present, none unknown."""
    missing = [c for c in REQUIRED if c not in cols]
    if missing:
        raise ParticleFileError(f"{name}: missing column {missing[0]!r} ({ALLOWED_TEXT})")
    unknown = [c for c in cols if c not in COLUMNS]
    if unknown:
        _err(name, f"column {unknown[0]!r}", f"unknown column; allowed: {', '.join(COLUMNS)}")


def _err(name, where, msg):
    raise ParticleFileError(f"{name}: {where}: {msg}" if where else f"{name}: {msg}")


def _check_names(names, name, what="column"):
    seen = set()
    for c in names:
        if not c:
            _err(name, f"{what} {len(seen) + 1}", "has no name in the header line")
        if c in seen:
            _err(name, f"{what} {c!r}", "given twice")
        seen.add(c)


def _read_text(full, name):
    try:
        with open(full, "rb") as fh:
            raw = fh.read()
    except OSError as exc:
        _err(name, "", f"cannot read {full}: {exc.strerror or exc}")
    try:
        return raw.decode("utf-8-sig")
    except UnicodeDecodeError as exc:
        line = raw[:exc.start].count(b"\n") + 1
        _err(name, f"line {line}", f"not UTF-8 text (byte 0x{raw[exc.start]:02x}); a packing CSV is "
                                   "plain text with comma-separated numbers (or give an .npz file)")


def _header_names(name, hline, header):
    """The column names of a CSV header line (checked: names, not numbers; known, not repeated)."""
    names = [c.strip().lower() for c in next(csv.reader([header]))]
    try:
        [float(c) for c in names]
        numeric = True
    except ValueError:
        numeric = False
    if numeric:
        _err(name, f"line {hline}", f"the first line must name the columns ({ALLOWED_TEXT}), got numbers")
    _check_names(names, name)
    return names


def _read_csv(full, name):
    text = _read_text(full, name)
    lines = [(k + 1, ln) for k, ln in enumerate(text.splitlines())
             if ln.strip() and not ln.lstrip().startswith("#")]
    if not lines:
        _err(name, "", f"empty file; the first line names the columns ({ALLOWED_TEXT}), "
                       "then one particle per line")
    hline, header = lines[0]
    names = _header_names(name, hline, header)
    rows = lines[1:]
    if not rows:
        _err(name, "", f"no particles: only the header line (columns {', '.join(names)})")
    ncol = len(names)
    body = "\n".join(ln for _, ln in rows)
    try:  # fast path: a clean file
        arr = np.loadtxt(io.StringIO(body), delimiter=",", dtype=float, ndmin=2)
        if arr.shape[1] != ncol:
            raise ValueError("column count")
    except ValueError:
        arr = _scan_csv(rows, names, name)
    bad = np.argwhere(~np.isfinite(arr))
    if bad.size:
        r, c = bad[0]
        cell = next(csv.reader([rows[r][1]]))[c].strip()
        _err(name, f"line {rows[r][0]}, column {names[c]}", f"not a finite number ({cell!r}); every cell "
                                                            "must be a finite number")
    return {c: np.ascontiguousarray(arr[:, k]) for k, c in enumerate(names)}, [ln for ln, _ in rows]


def _scan_csv(rows, names, name):
    """Slow path: find the first bad cell with its line and column."""
    ncol = len(names)
    out = np.empty((len(rows), ncol))
    for r, (lineno, ln) in enumerate(rows):
        cells = next(csv.reader([ln]))
        if len(cells) != ncol:
            _err(name, f"line {lineno}", f"{len(cells)} cells, the header has {ncol} "
                                         f"({', '.join(names)})")
        for c, cell in enumerate(cells):
            s = cell.strip()
            if not s:
                _err(name, f"line {lineno}, column {names[c]}", "empty cell; every cell must be a finite number")
            try:
                out[r, c] = float(s)
            except ValueError:
                _err(name, f"line {lineno}, column {names[c]}", f"not a number ({s!r}); every cell must be "
                                                                "a finite number")
    return out


def _read_npz(full, name):
    try:
        z = np.load(full, allow_pickle=False)
    except (OSError, ValueError, zipfile.BadZipFile, EOFError) as exc:
        _err(name, "", f"not a readable NPZ file ({exc}); write it with numpy.savez")
    if not isinstance(z, np.lib.npyio.NpzFile):
        _err(name, "", "not an NPZ archive (a single .npy array?); write it with numpy.savez(x=..., ...)")
    cols = {}
    try:
        with z:
            keys = list(z.files)
            _check_names([k for k in keys if k not in VECTORS], name, "array")
            for k in keys:
                try:
                    a = z[k]
                except Exception as exc:  # noqa: BLE001  (corrupt member, pickled object)
                    _err(name, f"array {k!r}", f"cannot be read ({exc})")
                if a.dtype.kind not in "iuf" or a.dtype.kind == "b":
                    _err(name, f"array {k!r}", f"must hold numbers, got dtype {a.dtype}")
                a = np.asarray(a, float)
                if k in VECTORS:
                    if a.ndim != 2 or a.shape[1] != 3:
                        _err(name, f"array {k!r}", f"must have shape (n, 3), got {a.shape}")
                    for j, c in enumerate(VECTORS[k]):
                        if c in cols:
                            _err(name, f"array {k!r}", f"gives {c!r} twice (also a separate array)")
                        cols[c] = np.ascontiguousarray(a[:, j])
                else:
                    if a.ndim != 1:
                        _err(name, f"array {k!r}", f"must be 1-D (one value per particle), got shape {a.shape}")
                    if k in cols:
                        _err(name, f"array {k!r}", "given twice")
                    cols[k] = a
    except zipfile.BadZipFile as exc:
        _err(name, "", f"not a readable NPZ file ({exc})")
    if not cols:
        _err(name, "", f"no arrays ({ALLOWED_TEXT})")
    lengths = {c: a.size for c, a in cols.items()}
    n = lengths.get("x", next(iter(lengths.values())))
    for c, m in lengths.items():
        if m != n:
            _err(name, f"array {c!r}", f"has {m} values but 'x' has {n}; every array needs one value "
                                       "per particle")
    if n == 0:
        _err(name, "", "no particles (arrays of length 0)")
    for c, a in cols.items():
        bad = np.nonzero(~np.isfinite(a))[0]
        if bad.size:
            _err(name, f"row {bad[0]}, column {c}", f"not a finite number ({float(a[bad[0]])!r}); every value must "
                                                    "be a finite number")
    return cols


def _bound_checks(cols):
    """The physical bounds of the columns, in the order they are checked: (bad-row mask,
    column, what is allowed)."""
    checks = [(np.abs(a) > MAX_MAGNITUDE, c, f"too large to compute with (|value| <= {MAX_MAGNITUDE:g}); "
                                              "check the units") for c, a in cols.items()]
    checks.append((~(cols["radius"] > 0), "radius", "must be > 0"))
    if "temperature" in cols:
        checks.append((~(cols["temperature"] > 0), "temperature", "must be > 0 K"))
    if "id" in cols:
        ids = cols["id"]
        checks.append(((ids != np.round(ids)) | (ids < 0) | (ids >= 2 ** 53), "id", "must be a whole number >= 0"))
    return checks


def _check_values(cols, name, where):
    """Physical bounds of the columns (:func:`_bound_checks`), then unique ids."""
    for mask, col, msg in _bound_checks(cols):
        bad = np.nonzero(mask)[0]
        if bad.size:
            _err(name, f"{where(bad[0])}, column {col}", f"{msg}, got {float(cols[col][bad[0]])!r}")
    if "id" in cols:
        ids = cols["id"]
        s = np.argsort(ids, kind="stable")
        eq = np.nonzero(ids[s][1:] == ids[s][:-1])[0]
        if eq.size:
            k = eq[np.argmin(s[1:][eq])]
            later, earlier = s[k + 1], s[k]
            _err(name, f"{where(later)}, column id", f"id {int(ids[later])} repeats (also on "
                                                     f"{where(earlier)}); ids must be unique")


# ---------------------------------------------------------------------------- by slices (MPI)
# Under ``mpirun -np N`` (N > 1) each rank reads only its slice of the rows: a CSV by byte
# ranges aligned to line starts, an NPZ member by row range (a stored member by its offset in
# the archive, a deflated one by streamed decompression that discards the rows before the
# slice). Every problem is agreed over the ranks (dem.parallel.setup.SetupComm.agree): the
# first in file order wins and every rank raises the same ParticleFileError, with the line or
# row a serial read names.
_ROW = 1 << 40   # ordering key of an agreed problem: check index * _ROW + row (or line)


class Part:
    """This rank's slice of a packing file: ``cols`` (the local rows), ``start`` (global row of
    the first local row), ``n_total`` (rows of the whole file), ``where(k)`` (the place of local
    row k in the file: ``line 17`` / ``row 16``), ``rows_read``."""

    def __init__(self, cols, start, n_total, where):
        self.cols, self.start, self.n_total, self.where = cols, start, n_total, where
        self.rows_read = next(iter(cols.values())).size if cols else 0


def read_part(full, sc):
    """This rank's slice of a packing file (:class:`Part`), checked as :func:`read` checks
    the whole file; ``sc``: a dem.parallel.setup.SetupComm."""
    name = os.path.basename(full)
    if not os.path.exists(full):
        raise ParticleFileError(f"file not found: {full}")
    if os.path.isdir(full):
        raise ParticleFileError(f"{name}: is a folder ({full}); give a CSV or NPZ file")
    if full.lower().endswith(".npz"):
        cols, start, total = _read_npz_part(full, name, sc)
        where = lambda k: f"row {start + k}"  # noqa: E731
        lines = np.arange(start, start + next(iter(cols.values())).size, dtype=np.int64)
    else:
        cols, lines, start, total = _read_csv_part(full, name, sc)
        where = lambda k: f"line {lines[k]}"  # noqa: E731
    _check_columns(cols, name)
    _check_values_part(cols, name, where, start, lines, sc)
    return Part(cols, start, total, where)


def _shared(sc, key, text):
    """Raise the first problem of any rank (key: its place in file order) on every rank."""
    msg = sc.agree(key, text)
    if msg is not None:
        raise ParticleFileError(msg)


def _line_starts(fh, size, sc):
    """[begin, end) bytes of this rank's slice: an even split of the file moved forward to
    the next line start (each rank finds its own two ends; neighbours agree by construction)."""
    def start_of(cut):
        if cut <= 0:
            return 0
        if cut >= size:
            return size
        fh.seek(cut - 1)
        pos = cut - 1
        while True:
            chunk = fh.read(65536)
            if not chunk:
                return size
            i = chunk.find(b"\n")
            if i >= 0:
                return pos + i + 1
            pos += len(chunk)
    return start_of(size * sc.rank // sc.size), start_of(size * (sc.rank + 1) // sc.size)


def _read_csv_part(full, name, sc):
    try:
        size = os.path.getsize(full)
        with open(full, "rb") as fh:
            a, b = _line_starts(fh, size, sc)
            fh.seek(a)
            raw = fh.read(b - a)
        err = None
    except OSError as exc:
        raw, err = b"", f"{name}: cannot read {full}: {exc.strerror or exc}"
    _shared(sc, 0 if err else None, err)
    before = sc.exscan(raw.count(b"\n"))     # lines that end before this slice
    text, bad = None, None
    try:
        text = raw.decode("utf-8-sig" if sc.rank == 0 else "utf-8")
    except UnicodeDecodeError as exc:
        line = before + raw[:exc.start].count(b"\n") + 1
        bad = (line, f"{name}: line {line}: not UTF-8 text (byte 0x{raw[exc.start]:02x}); a packing CSV is "
                     "plain text with comma-separated numbers (or give an .npz file)")
    _shared(sc, bad[0] if bad else None, bad[1] if bad else None)
    del raw
    lines = [(before + k + 1, ln) for k, ln in enumerate(text.splitlines())
             if ln.strip() and not ln.lstrip().startswith("#")]
    del text
    # the header: the first content line of the file, on the lowest rank that has one
    header = sc.agree(lines[0][0] if lines else None, lambda: f"{lines[0][0]}\n{lines[0][1]}")
    if header is None:
        _err(name, "", f"empty file; the first line names the columns ({ALLOWED_TEXT}), "
                       "then one particle per line")
    hl, header = header.split("\n", 1)
    hline = int(hl)
    if lines and lines[0][0] == hline:
        lines = lines[1:]
    names = _header_names(name, hline, header)
    total = int(sc.sum(len(lines)))
    if total == 0:
        _err(name, "", f"no particles: only the header line (columns {', '.join(names)})")
    ncol = len(names)
    arr, bad = np.empty((0, ncol)), None
    if lines:
        try:
            arr = np.loadtxt(io.StringIO("\n".join(ln for _, ln in lines)), delimiter=",", dtype=float, ndmin=2)
            if arr.shape[1] != ncol:
                raise ValueError("column count")
        except ValueError:
            try:
                arr = _scan_csv(lines, names, name)
            except ParticleFileError:
                for row in lines:   # which line: the first that fails alone (an error path only)
                    try:
                        _scan_csv([row], names, name)
                    except ParticleFileError as exc:
                        bad = (row[0], str(exc))
                        break
    _shared(sc, bad[0] if bad else None, bad[1] if bad else None)
    rows = np.nonzero(~np.isfinite(arr).all(1))[0]
    bad = None
    if rows.size:
        r = rows[0]
        c = int(np.nonzero(~np.isfinite(arr[r]))[0][0])
        cell = next(csv.reader([lines[r][1]]))[c].strip()
        bad = (lines[r][0], f"{name}: line {lines[r][0]}, column {names[c]}: not a finite number ({cell!r}); "
                            "every cell must be a finite number")
    _shared(sc, bad[0] if bad else None, bad[1] if bad else None)
    start = sc.exscan(len(lines))
    cols = {c: np.ascontiguousarray(arr[:, k]) for k, c in enumerate(names)}
    return cols, np.array([ln for ln, _ in lines], np.int64), start, total


def _member_reader(z, k):
    """(shape, fortran order, dtype, a function reading rows [a, b) of member ``k``)."""
    names = z.zip.namelist()
    info = z.zip.getinfo(k + ".npy" if k + ".npy" in names else k)
    with z.zip.open(info) as fh:
        version = np.lib.format.read_magic(fh)
        if version == (1, 0):
            shape, fortran, dtype = np.lib.format.read_array_header_1_0(fh)
        elif version == (2, 0):
            shape, fortran, dtype = np.lib.format.read_array_header_2_0(fh)
        else:
            raise ValueError(f"npy format version {version} (write it with numpy.savez)")
        data0 = fh.tell()
    if dtype.hasobject:
        raise ValueError("holds Python objects (pickled), not numbers")
    item = dtype.itemsize
    width = int(np.prod(shape[1:], dtype=np.int64)) if len(shape) > 1 else 1
    n = shape[0] if shape else 1
    raw_offset = None
    if info.compress_type == zipfile.ZIP_STORED and not info.flag_bits & 0x1:
        with open(z.zip.filename, "rb") as f:   # the member's bytes sit in the archive as they are
            f.seek(info.header_offset)
            head = f.read(30)
            raw_offset = info.header_offset + 30 + int.from_bytes(head[26:28], "little") \
                + int.from_bytes(head[28:30], "little") + data0

    def rows(a, b):
        m = b - a
        spans = ([(a * width * item, m * width * item)] if not fortran or width == 1 else
                 [((j * n + a) * item, m * item) for j in range(width)])
        parts = []
        if raw_offset is not None:
            with open(z.zip.filename, "rb") as f:
                for off, ln in spans:
                    f.seek(raw_offset + off)
                    parts.append(f.read(ln))
        else:
            with z.zip.open(info) as fh:   # streamed: the prefix is decompressed and discarded
                for off, ln in spans:
                    fh.seek(data0 + off)
                    parts.append(fh.read(ln))
        if any(len(p) != ln for p, (_, ln) in zip(parts, spans)):
            raise ValueError("the archive member is shorter than its header says (truncated file?)")
        if not fortran or width == 1:
            out = np.frombuffer(parts[0], dtype).reshape((m,) + tuple(shape[1:]))
        else:
            out = np.stack([np.frombuffer(p, dtype) for p in parts], 1).reshape((m,) + tuple(shape[1:]))
        return out
    return shape, dtype, rows


def _read_npz_part(full, name, sc):
    try:
        z = np.load(full, allow_pickle=False)
    except (OSError, ValueError, zipfile.BadZipFile, EOFError) as exc:
        _err(name, "", f"not a readable NPZ file ({exc}); write it with numpy.savez")
    if not isinstance(z, np.lib.npyio.NpzFile):
        _err(name, "", "not an NPZ archive (a single .npy array?); write it with numpy.savez(x=..., ...)")
    members = []
    with z:
        keys = list(z.files)
        _check_names([k for k in keys if k not in VECTORS], name, "array")
        seen = set()
        for k in keys:
            try:
                shape, dtype, rows = _member_reader(z, k)
            except Exception as exc:  # noqa: BLE001  (corrupt member, pickled object)
                _err(name, f"array {k!r}", f"cannot be read ({exc})")
            if dtype.kind not in "iuf":
                _err(name, f"array {k!r}", f"must hold numbers, got dtype {dtype}")
            if k in VECTORS:
                if len(shape) != 2 or shape[1] != 3:
                    _err(name, f"array {k!r}", f"must have shape (n, 3), got {shape}")
                for c in VECTORS[k]:
                    if c in seen:
                        _err(name, f"array {k!r}", f"gives {c!r} twice (also a separate array)")
                    seen.add(c)
            else:
                if len(shape) != 1:
                    _err(name, f"array {k!r}", f"must be 1-D (one value per particle), got shape {shape}")
                if k in seen:
                    _err(name, f"array {k!r}", "given twice")
                seen.add(k)
            members.append((k, shape[0], rows))
        if not members:
            _err(name, "", f"no arrays ({ALLOWED_TEXT})")
        lengths = {}
        for k, m, _ in members:
            for c in (VECTORS[k] if k in VECTORS else (k,)):
                lengths[c] = m
        n = lengths.get("x", next(iter(lengths.values())))
        for c, m in lengths.items():
            if m != n:
                _err(name, f"array {c!r}", f"has {m} values but 'x' has {n}; every array needs one value "
                                           "per particle")
        if n == 0:
            _err(name, "", "no particles (arrays of length 0)")
        a, b = n * sc.rank // sc.size, n * (sc.rank + 1) // sc.size
        cols, bad = {}, None
        for j, (k, _, rows) in enumerate(members):
            try:
                v = np.asarray(rows(a, b), float)
            except Exception as exc:  # noqa: BLE001  (truncated or corrupt member)
                bad = (j, f"{name}: array {k!r}: cannot be read ({exc})")
                break
            if k in VECTORS:
                for i, c in enumerate(VECTORS[k]):
                    cols[c] = np.ascontiguousarray(v[:, i])
            else:
                cols[k] = v
        _shared(sc, bad[0] if bad else None, bad[1] if bad else None)
    bad = None
    for j, (c, v) in enumerate(cols.items()):
        r = np.nonzero(~np.isfinite(v))[0]
        if r.size:
            bad = (j * _ROW + a + r[0], f"{name}: row {a + r[0]}, column {c}: not a finite number "
                                        f"({float(v[r[0]])!r}); every value must be a finite number")
            break
    _shared(sc, bad[0] if bad else None, bad[1] if bad else None)
    return cols, a, n


def _check_values_part(cols, name, where, start, lines, sc):
    """:func:`_check_values` on a slice: each check's first bad row in file order over the ranks."""
    bad = None
    for j, (mask, col, msg) in enumerate(_bound_checks(cols)):
        r = np.nonzero(mask)[0]
        if r.size:
            k = int(r[0])
            bad = (j * _ROW + start + k, f"{name}: {where(k)}, column {col}: {msg}, got {float(cols[col][k])!r}")
            break
    _shared(sc, bad[0] if bad else None, bad[1] if bad else None)
    if "id" in cols:
        n = cols["id"].size
        dup = sc.duplicates(cols["id"].astype(np.int64), np.arange(start, start + n), lines)
        if dup is not None:
            later, earlier, i, line_later, line_earlier = dup
            csv_file = not name.lower().endswith(".npz")
            w = (lambda ln: f"line {ln}") if csv_file else (lambda ln: f"row {ln}")
            _err(name, f"{w(line_later)}, column id", f"id {i} repeats (also on {w(line_earlier)}); ids must be unique")
