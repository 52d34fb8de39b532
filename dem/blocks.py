"""Blocks of rows: how a process cuts its particles among its threads (docs/architecture.md,
"Threads inside a process"). A leaf module, so that every kernel that runs on blocks (the
interact phase and the kicks of dem.step, the heat step of dem.thermal.heat) takes the same
cut without importing the others."""
import numpy as np
from numba import njit

# fewest owned rows per block: below it a thread's share is too small to pay its start (a few
# microseconds per parallel loop); the block count is then lowered, which keeps small scenes serial
MIN_BLOCK_ROWS = 1024


@njit(cache=True, error_model="numpy", inline="always")
def block_count(threads, nown):
    """How many blocks of rows the kernels run at once: the threads asked for, at most one per
    MIN_BLOCK_ROWS owned rows. A function of the thread count and the owned rows alone, so that
    a run is deterministic for a given thread count."""
    return max(1, min(threads, nown // MIN_BLOCK_ROWS))


@njit(cache=True, error_model="numpy", inline="always")
def block_bounds(nown, n, nblk):
    """Rows of each block: equal shares of the owned rows (the particles are stored in cell
    order, dem.neighbors.sort_permutation: a block is a slab of the domain, and most pairs stay
    inside one); the ghosts [nown, n) join the last block."""
    bounds = np.empty(nblk + 1, np.int64)
    for b in range(nblk):
        bounds[b] = (nown * b) // nblk
    bounds[nblk] = n
    return bounds
