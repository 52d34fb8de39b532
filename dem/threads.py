"""Threads inside a process: how many, and asking Numba for them.

A process runs its pair loop, walls, kicks and neighbour rebuild on ``k`` threads by cutting its
rows into ``k`` blocks (dem.step.interact_blocks, dem.neighbors.build_half_list): no two threads
write the same row, and every sum runs in an
order fixed by ``k``, so a run is deterministic for a given thread count (results differ from
another count at round-off, as with another number of MPI ranks). ``--threads auto`` (the
command line's default) takes the cores this process may run on (its CPU affinity, which
``mpirun`` narrows when it binds ranks to cores), shared among the ranks of this node.
"""
import os


class ThreadsError(ValueError):
    """A thread count that cannot be used (the message names the option and what is allowed)."""


def cores_available():
    """Cores this process may run on (its CPU affinity; the machine's count where unknown)."""
    try:
        return len(os.sched_getaffinity(0))
    except (AttributeError, OSError):
        return os.cpu_count() or 1


def limit():
    """The most threads Numba can start in this process (NUMBA_NUM_THREADS, by default the
    machine's CPUs)."""
    import numba
    return int(numba.config.NUMBA_NUM_THREADS)


def local_ranks(comm):
    """Ranks of ``comm`` on this node (1 without MPI)."""
    if comm is None:
        return 1
    from mpi4py import MPI
    node = comm.Split_type(MPI.COMM_TYPE_SHARED)
    try:
        return node.Get_size()
    finally:
        node.Free()


def auto(comm=None, reserve=0):
    """``auto``: this process's cores, shared among the ranks of its node, less ``reserve``
    cores kept for other processes that compute at the same time (a coupled run's gas solver
    processes: their share per DEM rank), at least 1."""
    return max(1, min(limit(), cores_available() // local_ranks(comm) - int(reserve)))


def parse(text, option="--threads"):
    """'auto' or a whole number >= 1 (as given on the command line); ThreadsError otherwise."""
    if text is None or str(text).strip().lower() == "auto":
        return "auto"
    try:
        k = int(str(text).strip())
    except ValueError:
        k = 0
    if k < 1:
        raise ThreadsError(f"{option} {text}: allowed are 'auto' or a whole number >= 1")
    return k


def argument(text):
    """argparse ``type`` of ``--threads`` (dem run, coupling run): 'auto' or a count >= 1."""
    import argparse
    try:
        return parse(text)
    except ThreadsError as exc:
        raise argparse.ArgumentTypeError(str(exc).split(": ", 1)[1]) from None


def resolve(value, comm=None, option="--threads", reserve=0):
    """The thread count of ``value`` ('auto', None or a count), checked against what Numba can
    start here; ``reserve``: see :func:`auto`."""
    value = parse(value, option) if not isinstance(value, int) else value
    if value == "auto":
        return auto(comm, reserve)
    if value < 1:
        raise ThreadsError(f"{option} {value}: allowed are 'auto' or a whole number >= 1")
    if value > limit():
        bound = (comm is not None and comm.Get_size() > 1) or any(
            int(os.environ.get(v, "1") or 1) > 1 for v in ("OMPI_COMM_WORLD_SIZE", "PMI_SIZE"))
        hint = (f"; mpirun binds each rank to its cores: give each rank {value} with "
                f"`mpirun --map-by slot:PE={value}` (or `--bind-to none`)" if bound else
                f"; use {limit()} or fewer, or more MPI ranks across nodes")
        raise ThreadsError(f"{option} {value}: this process may run at most {limit()} thread(s) (the CPUs it "
                           f"may use, or NUMBA_NUM_THREADS){hint}")
    return value


def apply(k):
    """Ask Numba for ``k`` threads in this (the calling) thread of the process."""
    import numba
    numba.set_num_threads(max(1, min(int(k), limit())))
