"""OpenFOAM polyMesh files (ASCII, optionally gzipped): reading the lists of ``points``,
``faces``, ``owner``, ``neighbour`` and the ``boundary`` dictionary, writing a polyMesh
(tests and small generated cases), and the structured hex mesh of a lattice of points.
Arrays only: coupling.mesh builds the PolyMesh (geometry, point location) from them
(``read_polymesh``), and re-exports these functions.

Binary polyMesh files are not supported (clear error): convert them with
``foamFormatConvert`` after setting ``writeFormat ascii`` in controlDict.
"""
from __future__ import annotations

import gzip
import os
import re

import numpy as np
from numba import njit


# --------------------------------------------------------------------------
# ASCII reader
# --------------------------------------------------------------------------
_BLOCK_COMMENT = re.compile(r"/\*.*?\*/", re.S)
_LINE_COMMENT = re.compile(r"//[^\n]*")


def _read_text(path: str) -> str:
    if not os.path.exists(path) and os.path.exists(path + ".gz"):
        path = path + ".gz"
    if path.endswith(".gz"):
        with gzip.open(path, "rb") as fh:
            raw = fh.read()
    else:
        with open(path, "rb") as fh:
            raw = fh.read()
    # Binary files contain arbitrary bytes after the header; decode leniently
    # so that the header can still be read and a clear error raised.
    return raw.decode("latin-1")


def _split_header(text: str, path: str) -> tuple[dict, str]:
    """Return (FoamFile header dict, body with comments removed)."""
    header: dict = {}
    m = re.search(r"\bFoamFile\s*\{", text)
    if m:
        end = text.index("}", m.end())
        for key, val in re.findall(r"(\w+)\s+([^;]*);", text[m.end():end]):
            header[key] = val.strip().strip('"')
        if header.get("format", "ascii").lower() != "ascii":
            raise NotImplementedError(
                f"{path}: polyMesh file is in '{header.get('format')}' format; only "
                "ASCII is supported. Convert with `foamFormatConvert` after setting "
                "`writeFormat ascii;` in system/controlDict (or run `foamFormatConvert "
                "-constant` for the mesh).")
        body = text[:m.start()] + text[end + 1:]
    else:
        body = text
    body = _BLOCK_COMMENT.sub(" ", body)
    body = _LINE_COMMENT.sub(" ", body)
    return header, body


def _numbers(body: str, path: str) -> np.ndarray:
    body = body.replace("(", " ").replace(")", " ")
    toks = body.split()
    try:
        return np.array(toks, dtype=np.float64)
    except ValueError as exc:  # pragma: no cover - malformed file
        raise ValueError(f"{path}: unexpected token in list: {exc}") from None


@njit(cache=True, error_model="numpy")
def _unflatten_faces(flat, start, n_faces):
    """flat = [..., n0, i.., n1, i.., ...] from position start -> CSR."""
    offsets = np.empty(n_faces + 1, np.int64)
    offsets[0] = 0
    pos = start
    for f in range(n_faces):
        if pos >= flat.shape[0]:
            return offsets, np.empty(0, np.int64), -1
        n = np.int64(flat[pos])
        offsets[f + 1] = offsets[f] + n
        pos += 1 + n
    pts = np.empty(offsets[n_faces], np.int64)
    pos = start
    k = 0
    for f in range(n_faces):
        n = np.int64(flat[pos])
        pos += 1
        for j in range(n):
            pts[k] = np.int64(flat[pos + j])
            k += 1
        pos += n
    return offsets, pts, pos


def read_foam_list(path: str):
    """Read one ASCII OpenFOAM list file of polyMesh.

    Returns
    -------
    * ``vectorField`` (points): float array (n, 3)
    * ``labelList`` (owner, neighbour): int64 array (n,)
    * ``faceList`` / ``faceCompactList`` (faces): tuple (offsets, indices)
      in CSR form, ``offsets`` of length nFaces + 1.

    Both the multi-line layout (``N`` newline ``(`` one item per line ``)``)
    and the compact one (``N(...)``, ``4(0 1 2 3)``) are handled, as is the
    uniform ``N{value}`` form for label lists and gzip-compressed files.
    """
    text = _read_text(path)
    header, body = _split_header(text, path)
    cls = header.get("class", "")
    name = os.path.basename(path).replace(".gz", "")
    if not cls:
        cls = {"points": "vectorField", "faces": "faceList"}.get(name, "labelList")

    m = re.match(r"\s*(\d+)\s*\{\s*([^}]*)\}", body)
    if m:  # uniform list N{value}
        n = int(m.group(1))
        if "vector" in cls:
            v = np.array(m.group(2).replace("(", " ").replace(")", " ").split(),
                         dtype=np.float64)
            return np.tile(v, (n, 1))
        return np.full(n, int(float(m.group(2))), dtype=np.int64)

    flat = _numbers(body, path)
    if flat.size == 0:
        raise ValueError(f"{path}: empty list")

    if "vector" in cls:
        n = int(flat[0])
        if flat.size - 1 != 3 * n:
            raise ValueError(f"{path}: header says {n} points but found "
                             f"{(flat.size - 1) / 3:g} vectors")
        return flat[1:].reshape(n, 3).copy()

    if cls == "faceCompactList":
        n_off = int(flat[0])
        offsets = flat[1:1 + n_off].astype(np.int64)
        n_idx = int(flat[1 + n_off])
        idx = flat[2 + n_off:2 + n_off + n_idx].astype(np.int64)
        if idx.size != n_idx or offsets[-1] != n_idx:
            raise ValueError(f"{path}: inconsistent faceCompactList")
        return offsets, idx

    if cls == "faceList":
        n = int(flat[0])
        offsets, pts, end = _unflatten_faces(flat, 1, n)
        if end != flat.size:
            raise ValueError(f"{path}: header says {n} faces but the list has "
                             f"{'fewer' if end < 0 else 'more'} entries")
        return offsets, pts

    # labelList (owner / neighbour)
    n = int(flat[0])
    if flat.size - 1 != n:
        raise ValueError(f"{path}: header says {n} labels but found {flat.size - 1}")
    return flat[1:].astype(np.int64)


def read_boundary(path: str) -> list[dict]:
    """Parse constant/polyMesh/boundary -> list of dicts with at least
    name, type, nFaces, startFace (ints converted)."""
    text = _read_text(path)
    _, body = _split_header(text, path)
    patches = []
    for name, content in re.findall(r"([^\s{}()]+)\s*\{([^}]*)\}", body):
        d = {"name": name}
        for key, val in re.findall(r"(\w+)\s+([^;]*);", content):
            val = val.strip()
            d[key] = int(val) if re.fullmatch(r"-?\d+", val) else val
        patches.append(d)
    return patches


# --------------------------------------------------------------------------
# Writer (used by tests and small generated cases)
# --------------------------------------------------------------------------
def _header(cls: str, obj: str, note: str = "") -> str:
    note_line = f'    note        "{note}";\n' if note else ""
    return ("/*--------------------------------*- C++ -*----------------------------------*\\\n"
            "  written by coupling.mesh\n"
            "\\*---------------------------------------------------------------------------*/\n"
            "FoamFile\n{\n    version     2.0;\n    format      ascii;\n"
            f"    class       {cls};\n{note_line}    location    \"constant/polyMesh\";\n"
            f"    object      {obj};\n}}\n"
            "// * * * * * * * * * * * * * * * * * * * * * * * * * * * * * * * * * * * * * //\n\n")


def write_polymesh(directory: str, points, face_offsets, face_points, owner, neighbour,
                   boundary: list[dict], style: str = "multiline") -> None:
    """Write an ASCII polyMesh.  ``style='multiline'`` writes faces and label
    lists one item per line (blockMesh layout); ``style='compact'`` writes
    each list in ``N(...)`` form and faces as multi-line ``n`` / ``(`` / ids
    / ``)`` blocks, exercising the other layouts the reader accepts."""
    os.makedirs(directory, exist_ok=True)
    points = np.asarray(points, float)
    owner = np.asarray(owner, np.int64)
    neighbour = np.asarray(neighbour, np.int64)
    n_cells = int(max(owner.max(), neighbour.max() if neighbour.size else -1)) + 1
    note = f"nPoints:{len(points)} nCells:{n_cells} nFaces:{len(owner)} " \
           f"nInternalFaces:{len(neighbour)}"
    with open(os.path.join(directory, "points"), "w") as fh:
        fh.write(_header("vectorField", "points"))
        fh.write(f"{len(points)}\n(\n")
        fh.write("\n".join(f"({p[0]:.17g} {p[1]:.17g} {p[2]:.17g})" for p in points))
        fh.write("\n)\n")
    with open(os.path.join(directory, "faces"), "w") as fh:
        fh.write(_header("faceList", "faces"))
        nf = len(face_offsets) - 1
        fh.write(f"{nf}\n(\n")
        lines = []
        for f in range(nf):
            ids = face_points[face_offsets[f]:face_offsets[f + 1]]
            if style == "compact":
                lines.append(f"{len(ids)}\n(\n" + "\n".join(str(i) for i in ids) + "\n)")
            else:
                lines.append(f"{len(ids)}(" + " ".join(str(i) for i in ids) + ")")
        fh.write("\n".join(lines))
        fh.write("\n)\n")
    for name, arr in (("owner", owner), ("neighbour", neighbour)):
        with open(os.path.join(directory, name), "w") as fh:
            fh.write(_header("labelList", name, note))
            if style == "compact":
                fh.write(f"{len(arr)}(" + " ".join(str(i) for i in arr) + ")\n")
            else:
                fh.write(f"{len(arr)}\n(\n" + "\n".join(str(i) for i in arr) + "\n)\n")
    with open(os.path.join(directory, "boundary"), "w") as fh:
        fh.write(_header("polyBoundaryMesh", "boundary"))
        fh.write(f"{len(boundary)}\n(\n")
        for p in boundary:
            fh.write(f"    {p['name']}\n    {{\n        type            {p.get('type', 'patch')};\n"
                     f"        nFaces          {p['nFaces']};\n"
                     f"        startFace       {p['startFace']};\n    }}\n")
        fh.write(")\n")


def structured_hex_mesh(X: np.ndarray):
    """Hexahedral mesh from a structured point array ``X`` of shape
    (nx+1, ny+1, nz+1, 3) (any, possibly distorted, positions).

    Cell (i, j, k) gets index ``i + nx*(j + ny*k)`` (blockMesh order).
    Internal faces are sorted by (owner, neighbour) (upper-triangular order as
    OpenFOAM requires), boundary faces follow in six patches
    xmin, xmax, ymin, ymax, zmin, zmax.

    Returns (points, face_offsets, face_points, owner, neighbour, boundary).
    """
    X = np.asarray(X, float)
    nx, ny, nz = X.shape[0] - 1, X.shape[1] - 1, X.shape[2] - 1
    pid = np.arange((nx + 1) * (ny + 1) * (nz + 1)).reshape(nz + 1, ny + 1, nx + 1).transpose(2, 1, 0)
    points = X.transpose(2, 1, 0, 3).reshape(-1, 3)

    def cid(i, j, k):
        return i + nx * (j + ny * k)

    I, J, K = np.meshgrid(np.arange(nx + 1), np.arange(ny + 1), np.arange(nz + 1), indexing="ij")
    faces_int, own_int, nei_int = [], [], []
    bfaces = {n: ([], []) for n in ("xmin", "xmax", "ymin", "ymax", "zmin", "zmax")}

    # x-faces: normal +x : (i,j,k) (i,j+1,k) (i,j+1,k+1) (i,j,k+1)
    i, j, k = I[:, :ny, :nz].ravel(), J[:, :ny, :nz].ravel(), K[:, :ny, :nz].ravel()
    q = np.stack([pid[i, j, k], pid[i, j + 1, k], pid[i, j + 1, k + 1], pid[i, j, k + 1]], 1)
    _split_faces(q, i, nx, cid(i - 1, j, k), cid(i, j, k), faces_int, own_int, nei_int,
                 bfaces["xmin"], bfaces["xmax"])
    # y-faces: normal +y : (i,j,k) (i,j,k+1) (i+1,j,k+1) (i+1,j,k)
    i, j, k = I[:nx, :, :nz].ravel(), J[:nx, :, :nz].ravel(), K[:nx, :, :nz].ravel()
    q = np.stack([pid[i, j, k], pid[i, j, k + 1], pid[i + 1, j, k + 1], pid[i + 1, j, k]], 1)
    _split_faces(q, j, ny, cid(i, j - 1, k), cid(i, j, k), faces_int, own_int, nei_int,
                 bfaces["ymin"], bfaces["ymax"])
    # z-faces: normal +z : (i,j,k) (i+1,j,k) (i+1,j+1,k) (i,j+1,k)
    i, j, k = I[:nx, :ny, :].ravel(), J[:nx, :ny, :].ravel(), K[:nx, :ny, :].ravel()
    q = np.stack([pid[i, j, k], pid[i + 1, j, k], pid[i + 1, j + 1, k], pid[i, j + 1, k]], 1)
    _split_faces(q, k, nz, cid(i, j, k - 1), cid(i, j, k), faces_int, own_int, nei_int,
                 bfaces["zmin"], bfaces["zmax"])

    fi = np.concatenate(faces_int)
    oi = np.concatenate(own_int)
    ni = np.concatenate(nei_int)
    order = np.lexsort((ni, oi))
    faces = [fi[order]]
    owner = [oi[order]]
    boundary = []
    start = len(order)
    for name, (fl, ol) in bfaces.items():
        f = np.concatenate(fl) if fl else np.zeros((0, 4), np.int64)
        o = np.concatenate(ol) if ol else np.zeros(0, np.int64)
        faces.append(f)
        owner.append(o)
        boundary.append({"name": name, "type": "wall", "nFaces": len(o), "startFace": start})
        start += len(o)
    faces = np.concatenate(faces).astype(np.int64)
    owner = np.concatenate(owner).astype(np.int64)
    face_offsets = np.arange(0, 4 * len(faces) + 1, 4, dtype=np.int64)
    return points, face_offsets, faces.ravel(), owner, ni[order].astype(np.int64), boundary


def _split_faces(q, idx, n, c_lo, c_hi, faces_int, own_int, nei_int, b_lo, b_hi):
    inner = (idx > 0) & (idx < n)
    faces_int.append(q[inner])
    own_int.append(c_lo[inner])
    nei_int.append(c_hi[inner])
    lo = idx == 0
    b_lo[0].append(q[lo][:, ::-1])  # reversed: outward normal -axis
    b_lo[1].append(c_hi[lo])
    hi = idx == n
    b_hi[0].append(q[hi])
    b_hi[1].append(c_lo[hi])


# --------------------------------------------------------------------------
# Geometry kernels (OpenFOAM primitiveMesh decomposition)
# --------------------------------------------------------------------------
