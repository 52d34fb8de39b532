"""Stop requests: SIGINT (Ctrl-C) and SIGTERM (a scheduler's end of wall time) set a flag
that the run loops poll between compiled chunks, so a signal never lands inside a kernel or
half way through a file; the loop then checkpoints, closes its outputs and exits 130 / 143.

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

_pending = 0
_installed = 0


class StopRequested(Exception):
    """Raised by a run loop at a safe point after SIGINT or SIGTERM."""

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
    """The shell's convention: 128 + signal number (130 for SIGINT, 143 for SIGTERM)."""
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
    """Context manager: SIGINT and SIGTERM set the stop flag while inside (main thread only;
    elsewhere, and when nested, it does nothing)."""

    def __enter__(self):
        global _installed
        self._old = None
        if threading.current_thread() is threading.main_thread() and not _installed:
            self._old = {s: signal.signal(s, _handler) for s in (signal.SIGINT, signal.SIGTERM)}
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
