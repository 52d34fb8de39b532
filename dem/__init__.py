"""thermodem: a Numba thermal DEM solver with an OpenFOAM coupling.

Public API::

    import dem
    sim = dem.Simulation.from_file("examples/settle_box.toml")
    sim.run(end_time=0.1)
    sim.state.position
"""
__version__ = "0.1.0"

import os as _os

# Numba colours its error messages with colorama, whose exit hook then writes an ANSI reset
# to stdout: a stray "ESC[0m" at the end of MPI runs' output (and of a pipe). Plain text.
_os.environ.setdefault("NUMBA_DISABLE_ERROR_MESSAGE_HIGHLIGHTING", "1")


def source_digest():
    """SHA-256 (hex) over the sources of this package and of ``coupling`` (every ``*.py``, in
    path order): what the compiled kernels, and anything a run of them made, depend on."""
    import hashlib
    import os
    root = os.path.dirname(os.path.abspath(__file__))
    h = hashlib.sha256()
    for base in (root, os.path.join(os.path.dirname(root), "coupling")):
        for dirpath, dirs, files in os.walk(base):
            dirs[:] = sorted(d for d in dirs if d != "__pycache__")
            for f in sorted(files):
                if f.endswith(".py"):
                    with open(os.path.join(dirpath, f), "rb") as fh:
                        h.update(f.encode() + fh.read())
    return h.hexdigest()


def _numba_cache_dir():
    """Numba's on-disk cache keyed by a hash of this package's sources (source_digest).

    Numba invalidates a cached kernel only when the file defining it changes, not when a
    function it calls (in another file) does; keying the cache folder on all sources
    makes any edit or upgrade recompile once, and never run stale machine code.
    """
    import os
    import numba
    if os.environ.get("NUMBA_CACHE_DIR"):
        return
    cache = os.path.join(os.environ.get("XDG_CACHE_HOME", os.path.expanduser("~/.cache")),
                         "thermodem", "numba", source_digest()[:16])
    numba.config.CACHE_DIR = cache


_numba_cache_dir()


def _threading_layer():
    """Numba's threads (``--threads N``): OpenMP first, then TBB, then its own work queue, unless
    the user chose (NUMBA_THREADING_LAYER or NUMBA_THREADING_LAYER_PRIORITY). Numba's default
    order puts TBB first, and a library loaded beside ours can bring libtbb along: on the shared
    10k bed TBB ran 2 threads at 0.84x of 1 thread, GNU OpenMP at 1.8x (docs/notebook.md,
    "Threads inside a process")."""
    import os
    import numba
    if os.environ.get("NUMBA_THREADING_LAYER") or os.environ.get("NUMBA_THREADING_LAYER_PRIORITY"):
        return
    os.environ["NUMBA_THREADING_LAYER_PRIORITY"] = "omp tbb workqueue"  # (Numba re-reads its settings)
    numba.config.THREADING_LAYER_PRIORITY = ["omp", "tbb", "workqueue"]


_threading_layer()


def __getattr__(name):  # lazy: importing dem.thermal must not pull in the solver
    if name in ("Simulation",):
        from .simulation import Simulation
        return Simulation
    if name in ("SceneError",):
        from .errors import SceneError
        return SceneError
    raise AttributeError(name)
