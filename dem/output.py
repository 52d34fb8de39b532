"""Writers: VTK (.vtu via meshio) + a ParaView .pvd series, history.csv, final.npz and
atomic checkpoints. Every file is written to a temporary name in the same folder and
renamed, so a reader (or a crash) never sees half a file and nothing written is lost."""
import errno
import math
import os
import tempfile

import numpy as np

from .outdir import TMP_PREFIX, claim  # noqa: F401  (TMP_PREFIX: every temporary file of ours)

# errors of a full or unwritable disk: reported as OutputError (one line, no traceback)
DISK_ERRNOS = {errno.ENOSPC: "the disk is full", errno.EDQUOT: "the disk quota is exceeded",
               errno.EROFS: "the file system is read-only", errno.EACCES: "permission denied",
               errno.EPERM: "permission denied", errno.EFBIG: "the file is too large for the file system"}


class OutputError(RuntimeError):
    """An output file could not be written (disk full, quota, read-only, permissions). The
    message names the file and what to do; the file's previous version is untouched."""

    def __init__(self, path=None, exc=None, message=None):
        if message is not None:  # relayed from the rank that writes
            self.path, self.errno = path, None
            super().__init__(message)
            return
        self.path = str(path)
        self.errno = getattr(exc, "errno", None)
        why = DISK_ERRNOS.get(self.errno, getattr(exc, "strerror", None) or str(exc))
        folder = os.path.dirname(os.path.abspath(self.path))
        fix = ("make it writable" if self.errno in (errno.EROFS, errno.EACCES, errno.EPERM)
               else "free space there")
        super().__init__(f"cannot write {self.path}: {why}. The previous version of that file (if any) "
                         f"and the other files in {folder} are intact; {fix}, or choose another output "
                         f"folder")


def _fsync_path(path, directory=False):
    fd = os.open(path, os.O_RDONLY | (os.O_DIRECTORY if directory else 0))
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


def atomic_write(path, write, durable=False):
    """Call ``write(tmp_path)`` then rename it onto ``path``: a kill -9 at any instant leaves
    either the old or the new file, complete (the rename is atomic; what a killed process
    wrote stays in the page cache). ``durable``: also fsync the data before the rename and
    the folder after it, so that a power cut or an OS crash cannot leave an empty or partial
    file either (checkpoints; ~15 ms per file on ext4, too much for every VTK output). A full
    or unwritable disk raises OutputError naming ``path``; the temporary file is removed and
    the old ``path`` stays as it was."""
    d = os.path.dirname(os.path.abspath(path))
    suffix = os.path.splitext(path)[1]
    tmp = None
    try:
        claim(path)   # recorded in the manifest of the output folder that holds it (dem.outdir)
        os.makedirs(d, exist_ok=True)
        fd, tmp = tempfile.mkstemp(dir=d, prefix=TMP_PREFIX, suffix=suffix)
        os.close(fd)
        write(tmp)
        umask = os.umask(0)
        os.umask(umask)
        os.chmod(tmp, 0o666 & ~umask)  # mkstemp creates 0600; give the usual permissions
        if durable:
            _fsync_path(tmp)
        os.replace(tmp, path)
        tmp = None
        if durable:
            _fsync_path(d, directory=True)
    except OSError as exc:
        if exc.errno in DISK_ERRNOS:
            raise OutputError(path, exc) from None
        raise
    finally:
        if tmp is not None:
            try:
                os.unlink(tmp)
            except OSError:
                pass


def write_text(path, text):
    """Write ``text`` to ``path`` atomically (see atomic_write)."""
    def w(tmp):
        with open(tmp, "w") as fh:
            fh.write(text)
    atomic_write(path, w)


def remove_stale_temporaries(folder):
    """Remove the temporary files (TMP_PREFIX) a killed earlier run left in ``folder`` and its
    vtk/ and checkpoints/ subfolders; returns their paths. Only files carrying our prefix are
    touched. Call it before a run starts writing in the folder."""
    removed = []
    for sub in ("", "vtk", "checkpoints"):
        d = os.path.join(folder, sub)
        try:
            names = os.listdir(d)
        except OSError:
            continue
        for name in names:
            p = os.path.join(d, name)
            if name.startswith(TMP_PREFIX) and os.path.isfile(p) and not os.path.islink(p):
                try:
                    os.unlink(p)
                    removed.append(p)
                except OSError:
                    pass
    return removed


def prepare_output_folder(folder):
    """Create ``folder`` (OutputError if that is impossible) and remove the temporary files a
    killed earlier run left there (remove_stale_temporaries)."""
    try:
        os.makedirs(folder, exist_ok=True)
    except OSError as exc:
        if exc.errno == errno.EEXIST:
            raise OutputError(message=f"cannot write into {folder}: it is a file, not a folder; "
                                      f"choose another output folder") from None
        if exc.errno in DISK_ERRNOS:
            raise OutputError(folder, exc) from None
        raise
    return remove_stale_temporaries(folder)


def save_npz(path, durable=False, **arrays):
    """``np.savez`` of ``arrays`` to ``path`` atomically (durable: fsync'ed, for checkpoints)."""
    def w(tmp):
        with open(tmp, "wb") as fh:
            np.savez(fh, **arrays)
    atomic_write(path, w, durable=durable)


class VTKSeries:
    """One frame per output and a .pvd index that ParaView opens as a time series.

    One process: a frame is ``vtk/<name>_<step>.vtu``. An MPI run (``ranks`` > 1): every rank
    writes its own piece ``vtk/<name>_<step>_p<rank>.vtu`` (its owned particles: no rank gathers
    the others'), and the root writes the frame ``vtk/<name>_<step>.pvtu`` naming the pieces
    (ParaView and pyvista open it as one data set; :func:`read_frames` reads it back). Every rank
    constructs the series; only the root reads and writes the .pvd."""

    def __init__(self, out_dir, name="particles", rank=0, ranks=1):
        self.dir = os.path.join(out_dir, "vtk")
        self.name = name
        self.rank, self.ranks = int(rank), int(ranks)
        self.entries = []
        self.pvd = os.path.join(out_dir, f"{name}.pvd")
        if self.rank == 0 and os.path.exists(self.pvd):  # continuing a run: keep earlier entries
            self.entries = pvd_entries(self.pvd)

    def piece_path(self, index, rank):
        return os.path.join(self.dir, f"{self.name}_{index:06d}_p{rank:04d}.vtu")

    def write(self, time, index, points, fields):
        """The whole frame from one process (a serial run)."""
        fname = f"{self.name}_{index:06d}.vtu"
        write_vtu(os.path.join(self.dir, fname), points, fields)
        self._index(time, fname)

    def write_piece(self, index, points, fields):
        """This rank's piece of frame ``index`` (an MPI run; every rank with particles)."""
        write_vtu(self.piece_path(index, self.rank), points, fields)

    def write_surface(self, time, index, points, triangles, cell_fields):
        """A frame of triangles (the mesh walls where they are at ``time``), one process."""
        import meshio
        fname = f"{self.name}_{index:06d}.vtu"
        mesh = meshio.Mesh(points, [("triangle", triangles)],
                           cell_data={k: [np.ascontiguousarray(v)] for k, v in cell_fields.items()})
        atomic_write(os.path.join(self.dir, fname), lambda tmp: meshio.write(tmp, mesh, file_format="vtu"))
        self._index(time, fname)

    def write_lines(self, time, index, points, lines, cell_fields):
        """A frame of line segments (the contact network) from one process."""
        fname = f"{self.name}_{index:06d}.vtu"
        write_lines_vtu(os.path.join(self.dir, fname), points, lines, cell_fields)
        self._index(time, fname)

    def write_lines_piece(self, index, points, lines, cell_fields):
        """This rank's piece of a frame of line segments (an MPI run)."""
        write_lines_vtu(self.piece_path(index, self.rank), points, lines, cell_fields)

    def write_frame(self, time, index, pieces, fields, cells=False):
        """The root: the .pvtu of frame ``index`` naming the pieces of the ranks ``pieces``
        (those that own particles), with the arrays of ``fields`` (name -> an array of the
        piece's dtype and components: point data, or cell data with ``cells``), and its entry in
        the .pvd."""
        fname = f"{self.name}_{index:06d}.pvtu"
        arrays = "".join(f'      <PDataArray type="Float64" Name="{k}" NumberOfComponents="{_components(a)}"/>\n'
                         for k, a in fields.items())
        sources = "".join(f'    <Piece Source="{os.path.basename(self.piece_path(index, r))}"/>\n' for r in pieces)
        text = ('<?xml version="1.0"?>\n'
                '<VTKFile type="PUnstructuredGrid" version="0.1" byte_order="LittleEndian">\n'
                '  <PUnstructuredGrid GhostLevel="0">\n'
                + (f'    <PCellData>\n{arrays}    </PCellData>\n' if cells else
                   f'    <PPointData>\n{arrays}    </PPointData>\n') +
                '    <PPoints>\n      <PDataArray type="Float64" NumberOfComponents="3"/>\n    </PPoints>\n'
                '    <PCells>\n      <PDataArray type="Int64" Name="connectivity"/>\n'
                '      <PDataArray type="Int64" Name="offsets"/>\n'
                '      <PDataArray type="UInt8" Name="types"/>\n    </PCells>\n'
                f'{sources}  </PUnstructuredGrid>\n</VTKFile>\n')
        write_text(os.path.join(self.dir, fname), text)
        self._index(time, fname)

    def _index(self, time, fname):
        self.entries = [e for e in self.entries if e[0] < time - 1e-15] + [(time, f"vtk/{fname}")]
        lines = ['<?xml version="1.0"?>',
                 '<VTKFile type="Collection" version="0.1" byte_order="LittleEndian">', "  <Collection>"]
        lines += [f'    <DataSet timestep="{t:.10g}" group="" part="0" file="{f}"/>' for t, f in self.entries]
        lines += ["  </Collection>", "</VTKFile>", ""]
        write_text(self.pvd, "\n".join(lines))


def _components(a):
    return 1 if a.ndim == 1 else int(a.shape[1])


def make_folder(path):
    """Create the folder ``path``, recorded first in the manifest of the output folder that holds
    it (dem.outdir.claim); a full or unwritable disk raises OutputError naming it."""
    try:
        claim(path)
        os.makedirs(path, exist_ok=True)
    except OSError as exc:
        if exc.errno in DISK_ERRNOS:
            raise OutputError(path, exc) from None
        raise


def write_vtu(path, points, fields):
    """Particles as vertices with per-point ``fields``, one .vtu file (atomic)."""
    import meshio
    n = points.shape[0]
    mesh = meshio.Mesh(points, [("vertex", np.arange(n).reshape(-1, 1))],
                       point_data={k: np.ascontiguousarray(v) for k, v in fields.items()})
    atomic_write(path, lambda tmp: meshio.write(tmp, mesh, file_format="vtu"))


def write_lines_vtu(path, points, lines, cell_fields):
    """Line segments (pairs of point indices) with per-segment ``cell_fields``, one .vtu (atomic)."""
    import meshio
    mesh = meshio.Mesh(points, [("line", np.asarray(lines, np.int64).reshape(-1, 2))],
                       cell_data={k: [np.ascontiguousarray(v)] for k, v in cell_fields.items()})
    atomic_write(path, lambda tmp: meshio.write(tmp, mesh, file_format="vtu"))


def pvd_entries(pvd):
    """[(time, file relative to the .pvd's folder)] of a .pvd series."""
    import re
    with open(pvd) as fh:
        txt = fh.read()
    return [(float(t), f) for t, f in re.findall(r'timestep="([^"]+)"[^>]*file="([^"]+)"', txt)]


def read_frame(path):
    """(points, point_data) of one frame: a .vtu, or a .pvtu whose pieces are concatenated."""
    import re
    import meshio
    if not path.endswith(".pvtu"):
        m = meshio.read(path)
        return m.points, dict(m.point_data)
    with open(path) as fh:
        sources = re.findall(r'<Piece Source="([^"]+)"', fh.read())
    parts = [meshio.read(os.path.join(os.path.dirname(path), s)) for s in sources]
    if not parts:
        return np.zeros((0, 3)), {}
    points = np.concatenate([m.points for m in parts])
    return points, {k: np.concatenate([m.point_data[k] for m in parts]) for k in parts[0].point_data}


def read_frames(out_dir, name="particles"):
    """[(time, frame path, points, point_data)] of every frame of a run's .pvd series, the rows of
    each frame ordered by particle id (serial frames and MPI pieces alike)."""
    pvd = os.path.join(out_dir, f"{name}.pvd")
    out = []
    for t, f in pvd_entries(pvd):
        path = os.path.join(out_dir, f)
        points, data = read_frame(path)
        order = np.argsort(data["id"], kind="stable") if "id" in data else np.arange(points.shape[0])
        out.append((t, path, points[order], {k: v[order] for k, v in data.items()}))
    return out


class History:
    """history.csv, one line per output; rewritten atomically."""

    def __init__(self, path, columns, keep_until=None):
        self.path = path
        self.columns = columns
        self.rows = []
        if keep_until is not None and os.path.exists(path):
            data = np.genfromtxt(path, delimiter=",", names=True)
            if data.size:
                data = np.atleast_1d(data)
                # by column name: a restart that added a wall adds its E_wall_ column (empty before)
                names = list(data.dtype.names)
                self.rows = [[float(r[c]) if c in names else math.nan for c in columns]
                             for r in data if r[0] <= keep_until + 1e-15]

    def add(self, values):
        self.rows.append([float(values[c]) for c in self.columns])
        text = ",".join(self.columns) + "\n" + "".join(
            ",".join(f"{v:.12g}" for v in r) + "\n" for r in self.rows)
        write_text(self.path, text)
