import os
import sys

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
if ROOT not in sys.path:
    sys.path.insert(0, ROOT)

# The suite runs on the machine's cores in parallel (scripts/test.sh: pytest-xdist workers), so an
# `mpirun -np 2` of one test can start while another worker holds a core: every MPI launch of the
# tests (theirs and the coupling's) may place more ranks than free cores, and an idle rank yields.
os.environ.setdefault("OMPI_MCA_rmaps_base_oversubscribe", "1")
os.environ.setdefault("OMPI_MCA_mpi_yield_when_idle", "1")
# ... and no rank is bound to a core: two jobs of two ranks would each bind their rank 0 to core 0,
# where the scheduler could not move either away from the other
os.environ.setdefault("OMPI_MCA_hwloc_base_binding_policy", "none")

import fcntl  # noqa: E402
import subprocess  # noqa: E402
import tempfile  # noqa: E402
from contextlib import contextmanager  # noqa: E402
from pathlib import Path  # noqa: E402

import pytest  # noqa: E402


@contextmanager
def machine_lock(name: str):
    """An exclusive lock shared by every worker of the suite (a file lock in the temporary folder):
    what one worker builds once (the solver) the others wait for and then reuse."""
    path = os.path.join(tempfile.gettempdir(), f"thermodem-tests-{name}.lock")
    with open(path, "a+") as fh:
        fcntl.flock(fh, fcntl.LOCK_EX)
        try:
            yield
        finally:
            fcntl.flock(fh, fcntl.LOCK_UN)


@pytest.fixture(scope="session")
def solver() -> Path:
    """thermoDemFoam, installed (OpenFOAM + headers) and built (cached) on first use; workers of a
    parallel run take turns, so one builds and the others find the build."""
    from coupling import foam_case as fc
    with machine_lock("solver"):
        r = subprocess.run(["bash", os.path.join(ROOT, "scripts", "install_openfoam.sh")],
                           capture_output=True, text=True)
        assert r.returncode == 0, f"install_openfoam.sh failed:\n{r.stderr[-3000:]}"
        exe = fc.build_solver()
    assert exe.is_file() and os.access(exe, os.X_OK)
    return exe


# The modules in the order of their total time, longest first (a 2-worker run of
# `bash scripts/test.sh --durations=0` on a fresh clone, 2026-12-07, 2 cores): a parallel run
# gives each worker whole modules (--dist loadscope) in collection order, and a long module started
# last would run alone at the end. A module not listed runs after these in its usual order.
SLOW_MODULES = (
    "test_coupled_m2m", "test_parallel", "test_reliability_signals", "test_reliability_mpi",
    "test_setup_mpi", "test_parallel_io", "test_coupled", "test_wall_heat", "test_drag_void_fraction",
    "test_threads", "test_compile", "test_coupled_drag", "test_reliability_coupled_restart",
    "test_reliability_outdir", "test_reliability_checkpoint", "test_settling", "test_coarse_graining",
    "test_coupling_checks", "test_openfoam_solver", "test_coupled_pieces", "test_impacts", "test_implicit_mpi",
    "test_fluidization_curve",
)


def pytest_collection_modifyitems(session, config, items):
    rank = {name: k for k, name in enumerate(SLOW_MODULES)}

    def key(item):
        name = item.module.__name__.rsplit(".", 1)[-1] if getattr(item, "module", None) else ""
        return rank.get(name, len(SLOW_MODULES))
    items.sort(key=key)     # stable: within a module, and among the others, the collected order
