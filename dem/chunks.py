"""Compiled chunks of bounded wall time, and the stop poll between them.

A run advances in calls of the compiled step loop (chunks). A signal is only served between
chunks (dem.interrupt), so a chunk must not run for long: ChunkClock sizes each chunk from the
measured step rate to last about ``target`` seconds. The chunk size only decides where the
loop pauses: the step arithmetic does not depend on it (dem.step.advance computes each step's
time from its step number), so results are bit-identical whatever the chunk sizes.

Under MPI every rank must pause at the same step and agree on stopping: ``agree`` takes the
maximum of the stop flags and the minimum of the proposed chunk sizes over the ranks, in one
Allreduce.
"""
import os
import time

from .interrupt import stop_requested

TARGET_SECONDS = 1.0   # wall time of one chunk: a signal is served within about this
FIRST_CHUNK = 10       # steps of the first chunk, before any rate is known
MAX_GROWTH = 4.0       # a chunk grows at most this factor over the previous one


class ChunkClock:
    """Proposes the number of steps of the next chunk from the measured rate."""

    def __init__(self, target=None, first=FIRST_CHUNK):
        if target is None:  # THERMODEM_CHUNK_SECONDS: how promptly a signal is served (0: every step)
            target = float(os.environ.get("THERMODEM_CHUNK_SECONDS", TARGET_SECONDS))
        self.target = float(target)
        self.steps = int(first)
        self._t0 = None

    def start(self):
        self._t0 = time.perf_counter()

    def done(self, steps):
        """Record that the chunk started by start() did ``steps`` steps; adapt the size."""
        if self._t0 is None or steps <= 0:
            return
        wall = time.perf_counter() - self._t0
        self._t0 = None
        if wall <= 0:
            proposal = self.steps * MAX_GROWTH
        else:
            proposal = steps * self.target / wall
        # only a chunk that ran its full size measures the rate its size was meant for
        cap = max(self.steps, steps) * MAX_GROWTH
        self.steps = max(1, int(min(proposal, cap)))


def agree(par, chunk):
    """(stop signal number or 0, chunk size) agreed by every rank (par: the run's
    ParallelDomain, None for a serial run). Collective under MPI."""
    flag = stop_requested()
    if par is None:
        return flag, chunk
    sig, neg = par.flags(float(flag), -float(chunk))
    return int(sig), max(1, int(-neg))
