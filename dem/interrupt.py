"""Stop requests: SIGINT (Ctrl-C), SIGTERM (a scheduler's end of wall time) and SIGUSR1 (a
scheduler's warning before it, e.g. Slurm's ``--signal=USR1@120``; the one stop signal Open MPI's
mpirun forwards to every rank at once) set a flag that the run loops poll between compiled
chunks, so a signal never lands inside a kernel or half way through a file; the loop then
checkpoints, closes its outputs and exits 128 + the signal's number (130 / 143 / 138).

    with StopSignals():           # installs the handlers, restores the old ones on exit
        while ...:
            advance_one_chunk()
            if stop_requested():  # (MPI: agree on it with an allreduce MAX first)
                raise StopRequested(stop_requested())

A second signal of either kind while the first is being served raises KeyboardInterrupt at
once (a user who presses Ctrl-C twice wants out); files are still safe because every write
is atomic (dem.output.atomic_write).
"""
import signal
import threading

# the signals that ask a run to stop at its next safe point
STOP_SIGNALS = (signal.SIGINT, signal.SIGTERM, signal.SIGUSR1)

_pending = 0
_installed = 0


class StopRequested(Exception):
    """Raised by a run loop at a safe point after a stop signal (STOP_SIGNALS)."""

    def __init__(self, signum):
        self.signum = int(signum)
        super().__init__(f"stopped by {signal_name(self.signum)}")

    @property
    def exit_code(self):
        return exit_code(self.signum)


def signal_name(signum):
    try:
        return signal.Signals(signum).name
    except ValueError:
        return f"signal {signum}"


def exit_code(signum):
    """The shell's convention: 128 + signal number (130 SIGINT, 143 SIGTERM, 138 SIGUSR1)."""
    return 128 + int(signum)


def _handler(signum, frame):
    global _pending
    if _pending:
        raise KeyboardInterrupt(f"second {signal_name(signum)}")
    _pending = signum


def stop_requested():
    """The signal number of a pending stop request, 0 if none."""
    return _pending


def request_stop(signum=signal.SIGTERM):
    """Ask the running loop to stop as if ``signum`` had arrived (tests, other threads)."""
    global _pending
    _pending = int(signum)


def clear():
    global _pending
    _pending = 0


class StopSignals:
    """Context manager: the STOP_SIGNALS set the stop flag while inside (main thread only;
    elsewhere, and when nested, it does nothing)."""

    def __enter__(self):
        global _installed
        self._old = None
        if threading.current_thread() is threading.main_thread() and not _installed:
            self._old = {s: signal.signal(s, _handler) for s in STOP_SIGNALS}
            _installed = 1
            clear()
        return self

    def __exit__(self, *exc):
        global _installed
        if self._old is not None:
            for s, h in self._old.items():
                signal.signal(s, h)
            _installed = 0
        return False
