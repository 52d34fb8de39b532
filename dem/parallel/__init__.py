"""MPI parallel layer (mpi4py): domain decomposition, ghosts, migration, reductions.

A run is parallel when it is started by ``mpirun -np N`` with N > 1; mpi4py is imported
only then (a serial run never initialises MPI). See docs/scaling.md for the design and
the measured figures.
"""
import os
import sys

_ENV_SIZE = ("OMPI_COMM_WORLD_SIZE", "PMI_SIZE", "PMIX_SIZE", "MPI_LOCALNRANKS", "SLURM_NTASKS")


def launched_size():
    """Number of ranks the launcher started (1 outside mpirun), without initialising MPI."""
    for k in _ENV_SIZE[:3]:
        v = os.environ.get(k)
        if v:
            try:
                return int(v)
            except ValueError:
                pass
    return 1


def launched_rank():
    """This process's rank as the launcher numbered it (0 outside mpirun), without MPI."""
    for k in ("OMPI_COMM_WORLD_RANK", "PMI_RANK", "PMIX_RANK"):
        v = os.environ.get(k)
        if v and v.isdigit():
            return int(v)
    return 0


def world():
    """COMM_WORLD when started by mpirun with more than one rank, else None."""
    if launched_size() <= 1:
        return None
    from mpi4py import MPI
    comm = MPI.COMM_WORLD
    if comm.Get_size() <= 1:
        return None
    _abort_on_uncaught(comm)
    return comm


def _abort_on_uncaught(comm):
    """An exception that no handler catches on one rank would leave the other ranks waiting
    in their next collective forever: print it, say which rank stopped, and abort the whole
    job (mpirun then ends every rank). Expected failures (bad input, unstable runs, a failed
    particle exchange) are shared between the ranks and never get here."""
    if getattr(sys.excepthook, "_dem_abort", False):
        return
    previous = sys.excepthook

    def hook(kind, value, tb):
        try:
            previous(kind, value, tb)
            sys.stderr.write(f"error: rank {comm.Get_rank()} stopped on an unexpected {kind.__name__}; "
                             "aborting every rank of the run\n")
            sys.stderr.flush()
        finally:
            comm.Abort(130 if issubclass(kind, KeyboardInterrupt) else 3)
    hook._dem_abort = True
    sys.excepthook = hook
