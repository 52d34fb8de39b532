"""Blocks of rows: how a process cuts its particles among its threads (docs/architecture.md,
"Threads inside a process"), and the pairs across blocks kept between neighbour builds
(Params.xcnt, slots dem.schema.XC). A leaf module, so that every kernel that runs on blocks (the
interact phase and the kicks of dem.step, the neighbour rebuild of dem.neighbors, the heat step
and the implicit solvers of dem.thermal) takes the same cut without importing the others."""
import numpy as np
from numba import njit, prange

from .schema import XC

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


@njit(cache=True, error_model="numpy", inline="always")
def kept_cross_counts(xc, n, nown, nblk):
    """The pairs across blocks kept in ``xc`` (Params.xcnt, slots XC) for this key (block
    count, rows, owned rows), as nblk + 1 offsets (dem.step.interact_blocks, which counts and
    keeps them; the heat step's radiation pass takes them as room for its own pairs across
    blocks, a subset); empty when they must be counted (another key, or a rebuild cleared them;
    empty rather than None: an optional array cannot enter a parallel loop).
    The count reads the whole half list, 4 % of a 2-thread step of the shared 50k bed, and
    changes only with the list."""
    if xc.shape[0] >= XC.start + nblk + 1 and xc[XC.nblk] == nblk and xc[XC.n] == n and xc[XC.nown] == nown:
        return xc[XC.start:XC.start + nblk + 1].copy()
    return np.empty(0, np.int64)


def cross_count_slots(threads):
    """Params.xcnt for a process on ``threads`` threads: the key and room for as many blocks."""
    return np.zeros(XC.SIZE + threads, np.int64)


@njit(cache=True, error_model="numpy", inline="always")
def keep_cross_counts(xc, cnt, n, nown, nblk):
    """Keep the offsets ``cnt`` under their key (see kept_cross_counts), when ``xc`` has room."""
    if xc.shape[0] >= XC.start + nblk + 1:
        for b in range(nblk + 1):
            xc[XC.start + b] = cnt[b]
        xc[XC.n] = n
        xc[XC.nown] = nown
        xc[XC.nblk] = nblk


@njit(cache=True, error_model="numpy", parallel=True)
def cross_counts(nb, nnb, mask, bounds):
    """Offsets (nblk + 1) of each block's pairs across blocks: the half-list pairs (i, j) of the
    block's rows whose j lies in another block, counted on the blocks at once. ``mask``: a flag
    per list slot (only the flagged pairs count, e.g. Pairs.rnear), or an empty array (every
    pair counts)."""
    nblk = bounds.shape[0] - 1
    masked = mask.shape[0] > 0
    cnt = np.zeros(nblk + 1, np.int64)
    for b in prange(nblk):
        i0 = bounds[b]
        i1 = bounds[b + 1]
        c = 0
        for i in range(i0, i1):
            for s in range(nnb[i]):
                j = nb[i, s]
                if (j < i0 or j >= i1) and (not masked or mask[i, s]):
                    c += 1
        cnt[b + 1] = c
    for b in range(nblk):
        cnt[b + 1] += cnt[b]
    return cnt


@njit(cache=True, error_model="numpy")
def add_buffered(y, xj, xq, cnt, end):
    """y[xj[k]] += xq[k] over each block's range [cnt[b], end[b]) of a buffer of shares for
    rows of other blocks, in block order and buffer order. Returns False, having added nothing,
    when a block met more pairs across blocks than its room (end[b] > cnt[b + 1]: a neighbour
    list changed without its count being cleared)."""
    for b in range(end.shape[0]):
        if end[b] > cnt[b + 1]:
            return False
    for b in range(end.shape[0]):
        for k in range(cnt[b], end[b]):
            y[xj[k]] += xq[k]
    return True


@njit(cache=True, error_model="numpy", inline="always")
def block_sum(part, k):
    """Column k of per-block partial sums ``part`` (one row per block) added in block order,
    from 0.0: a sum over blocks that does not depend on which thread finished first."""
    s = 0.0
    for c in range(part.shape[0]):
        s += part[c, k]
    return s
