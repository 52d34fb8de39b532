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
    missing = [c for c in REQUIRED if c not in cols]
    if missing:
        raise ParticleFileError(f"{name}: missing column {missing[0]!r} ({ALLOWED_TEXT})")
    unknown = [c for c in cols if c not in COLUMNS]
    if unknown:
        _err(name, f"column {unknown[0]!r}", f"unknown column; allowed: {', '.join(COLUMNS)}")
    _check_values(cols, name, where)
    return cols, where


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


def _read_csv(full, name):
    text = _read_text(full, name)
    lines = [(k + 1, ln) for k, ln in enumerate(text.splitlines())
             if ln.strip() and not ln.lstrip().startswith("#")]
    if not lines:
        _err(name, "", f"empty file; the first line names the columns ({ALLOWED_TEXT}), "
                       "then one particle per line")
    hline, header = lines[0]
    names = [c.strip().lower() for c in next(csv.reader([header]))]
    try:
        [float(c) for c in names]
        numeric = True
    except ValueError:
        numeric = False
    if numeric:
        _err(name, f"line {hline}", f"the first line must name the columns ({ALLOWED_TEXT}), got numbers")
    _check_names(names, name)
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


def _check_values(cols, name, where):
    """Physical bounds of the columns."""
    def first_bad(mask, col, msg):
        bad = np.nonzero(mask)[0]
        if bad.size:
            _err(name, f"{where(bad[0])}, column {col}", f"{msg}, got {float(cols[col][bad[0]])!r}")
    for c, a in cols.items():
        first_bad(np.abs(a) > MAX_MAGNITUDE, c, f"too large to compute with (|value| <= {MAX_MAGNITUDE:g}); "
                                               "check the units")
    first_bad(~(cols["radius"] > 0), "radius", "must be > 0")
    if "temperature" in cols:
        first_bad(~(cols["temperature"] > 0), "temperature", "must be > 0 K")
    if "id" in cols:
        ids = cols["id"]
        first_bad((ids != np.round(ids)) | (ids < 0) | (ids >= 2 ** 53), "id", "must be a whole number >= 0")
        s = np.argsort(ids, kind="stable")
        eq = np.nonzero(ids[s][1:] == ids[s][:-1])[0]
        if eq.size:
            k = eq[np.argmin(s[1:][eq])]
            later, earlier = s[k + 1], s[k]
            _err(name, f"{where(later)}, column id", f"id {int(ids[later])} repeats (also on "
                                                     f"{where(earlier)}); ids must be unique")
