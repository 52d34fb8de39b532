"""Writers: VTK (.vtu via meshio) + a ParaView .pvd series, history.csv, final.npz and
atomic checkpoints. Every file is written to a temporary name in the same folder and
renamed, so a reader (or a crash) never sees half a file and nothing written is lost."""
import math
import os
import tempfile

import numpy as np

from .outdir import claim


def atomic_write(path, write):
    """Call ``write(tmp_path)`` then rename onto ``path``. The target is first recorded in
    the manifest of the output folder that holds it (dem.outdir.claim)."""
    claim(path)
    d = os.path.dirname(os.path.abspath(path))
    os.makedirs(d, exist_ok=True)
    suffix = os.path.splitext(path)[1]
    fd, tmp = tempfile.mkstemp(dir=d, prefix=".tmp_", suffix=suffix)
    os.close(fd)
    try:
        write(tmp)
        umask = os.umask(0)
        os.umask(umask)
        os.chmod(tmp, 0o666 & ~umask)  # mkstemp creates 0600; give the usual permissions
        os.replace(tmp, path)
    except BaseException:
        if os.path.exists(tmp):
            os.unlink(tmp)
        raise


def save_npz(path, **arrays):
    def w(tmp):
        with open(tmp, "wb") as fh:
            np.savez(fh, **arrays)
    atomic_write(path, w)


class VTKSeries:
    """One .vtu per output and a .pvd index that ParaView opens as a time series."""

    def __init__(self, out_dir, name="particles"):
        self.dir = os.path.join(out_dir, "vtk")
        self.name = name
        self.entries = []
        self.pvd = os.path.join(out_dir, f"{name}.pvd")
        if os.path.exists(self.pvd):  # continuing a run: keep earlier entries
            import re
            txt = open(self.pvd).read()
            self.entries = [(float(t), f) for t, f in re.findall(r'timestep="([^"]+)"[^>]*file="([^"]+)"', txt)]

    def write(self, time, index, points, fields):
        import meshio
        n = points.shape[0]
        fname = f"{self.name}_{index:06d}.vtu"
        path = os.path.join(self.dir, fname)
        mesh = meshio.Mesh(points, [("vertex", np.arange(n).reshape(-1, 1))],
                           point_data={k: np.ascontiguousarray(v) for k, v in fields.items()})
        atomic_write(path, lambda tmp: meshio.write(tmp, mesh, file_format="vtu"))
        self.entries = [e for e in self.entries if e[0] < time - 1e-15] + [(time, f"vtk/{fname}")]
        lines = ['<?xml version="1.0"?>',
                 '<VTKFile type="Collection" version="0.1" byte_order="LittleEndian">', "  <Collection>"]
        lines += [f'    <DataSet timestep="{t:.10g}" group="" part="0" file="{f}"/>' for t, f in self.entries]
        lines += ["  </Collection>", "</VTKFile>", ""]
        atomic_write(self.pvd, lambda tmp: open(tmp, "w").write("\n".join(lines)))


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
        atomic_write(self.path, lambda tmp: open(tmp, "w").write(text))
