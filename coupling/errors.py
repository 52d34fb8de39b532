"""The errors of the coupling package, in one module that every other one imports (and that
imports none of them), so that no import circle is needed to raise or catch one.

* :class:`CaseError` (a problem with an OpenFOAM case file) and its :class:`CaseConfigError`
  (an invalid coupled case: coupling.toml, dem.toml, the case's checks);
* :class:`FoamError` (an OpenFOAM command failed);
* :class:`CouplingError` (the exchange with the gas solver failed; names the peer and the
  coupling step) and its :class:`GasFieldError` (a non-physical gas frame);
* :class:`CouplingRunError` (a coupled run refused: output folder, restart point, end time);
* :class:`RunInterrupted` (a clean stop on SIGINT/SIGTERM after a restart point).

They are also importable from the modules that raised them before (``coupling.foam_case``,
``coupling.case``, ``coupling.exchange``, ``coupling.run``).
"""
from __future__ import annotations

from pathlib import Path

from dem.interrupt import StopRequested


def _rebuilt(cls, args, state):
    e = cls.__new__(cls)
    Exception.__init__(e, *args)
    e.__dict__.update(state)
    return e


class _Picklable:
    """Rebuilt as it was (message and attributes) when sent between MPI ranks (pickled): the
    constructors below take other arguments than the message they store."""

    def __reduce__(self):
        return _rebuilt, (self.__class__, self.args, dict(self.__dict__))


class CaseError(_Picklable, ValueError):
    """A problem with an OpenFOAM case; the message names the offending file."""

    def __init__(self, path, message: str):
        self.path = Path(path)
        super().__init__(f"{self.path}: {message}")


class CaseConfigError(CaseError):
    """Invalid coupled case; the message names the file (and the key)."""

    def __init__(self, path, message: str, key: str | None = None):
        super().__init__(path, f"{key}: {message}" if key else message)
        self.key = key


class FoamError(_Picklable, RuntimeError):
    """An OpenFOAM command failed."""


class CouplingError(_Picklable, RuntimeError):
    """Failure of the coupling exchange; the message names the peer and the step."""

    def __init__(self, message: str, *, peer: str = "CFD", step: int | None = None):
        self.peer = peer
        self.step = step
        where = f" [peer: {peer}, coupling step {step}]" if step is not None else f" [peer: {peer}]"
        super().__init__(message + where)


class GasFieldError(CouplingError):
    """The gas state received from thermoDemFoam is non-physical (non-finite values,
    T <= 0 K, or a gas speed above GAS_SPEED_LIMIT): the gas solution diverged, or a
    sudden change of the void fraction forced it."""


class CouplingRunError(_Picklable, RuntimeError):
    pass


class RunInterrupted(_Picklable, StopRequested):
    """A coupled run stopped cleanly on SIGINT/SIGTERM (of the DEM or of the gas solver)
    after writing a restart point; ``message`` is the one line for the user."""

    def __init__(self, signum, message):
        super().__init__(signum)
        self.message = message
