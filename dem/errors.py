"""The errors every part of dem raises, in one module that imports nothing of dem (so that
no import circle runs through an exception class).

SceneError         bad input: ``file: key.path: message`` (exit status 2 at the command line)
SimulationError    the run went unstable or cannot continue: who, when and what to change
"""


class SceneError(ValueError):
    """Invalid scene: ``file: key.path: message``."""

    def __init__(self, file, path, message):
        self.file, self.path, self.message = file, path, message
        super().__init__(f"{file}: {path}: {message}" if path else f"{file}: {message}")


class SimulationError(RuntimeError):
    """The run went unstable or cannot continue; the message says who, when and what to change."""
