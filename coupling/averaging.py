"""Time-averaged particle fields on the gas mesh (``[averaging]`` of coupling.toml).

The averaging is OpenFOAM's own: the ``fieldAverage`` function object in the run's
system/controlDict (written here), on fields the solver holds as registered volFields, so the
means are written by each gas processor into its time folders and continued on a restart from
fieldAverage's own state (``uniform/functionObjects/functionObjectProperties`` and the mean
fields of the restart time). The DEM adds five columns to each frame (:func:`particle_columns`:
the solid fraction and the solid-volume-weighted particle velocity and temperature of the
void fraction's stencil); the solver's ``thermoDemParticleMeans`` divides the means
(docs/models.md, "Time-averaged fields on the gas mesh")::

    [averaging]
    start = 0.1        # s: the samples of the coupling steps ending at t >= start (default 0)
    window = 0.05      # s, optional: fieldAverage's window (approximate): once this long is
                       #   averaged, each sample enters with weight dt/window
    fields = ["void_fraction", "particle_velocity", "particle_temperature", "heat_source"]

Written fields (per time folder, per processor when decomposed): ``epsMean`` (the void fraction
the gas used), ``alphapMean`` (solid fraction), ``UpMean``, ``TpMean`` (solids-volume-weighted
particle velocity and temperature), ``QpMean`` (the particles' heat into the gas, W/m^3); the
instantaneous ``alphap``, ``alphapUp``, ``alphapTp``, ``Qp`` beside them.
"""
from __future__ import annotations

import math
import re
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from . import voidfraction as vf
from .errors import CaseConfigError

__all__ = ["FIELDS", "AveragingConfig", "parse_averaging", "check_averaging", "write_function_objects",
           "particle_columns", "N_COLUMNS"]

# [averaging] fields -> the solver's fields fieldAverage averages (their means: <name>Mean)
FIELDS = {
    "void_fraction": ("eps", "alphap"),
    "particle_velocity": ("alphap", "alphapUp"),
    "particle_temperature": ("alphap", "alphapTp"),
    "heat_source": ("Qp",),
}
# [averaging] fields -> the means the solver writes in the time folders
WRITTEN = {
    "void_fraction": ("epsMean", "alphapMean"),
    "particle_velocity": ("UpMean",),
    "particle_temperature": ("TpMean",),
    "heat_source": ("QpMean",),
}
HEAT_FIELDS = ("particle_temperature", "heat_source")   # need coupling.heat and a [thermal] section
N_COLUMNS = 5          # frame columns: alphap, alphap Up (3), alphap Tp
FO_AVERAGE = "thermodemAverages"
FO_MEANS = "thermodemParticleMeans"


@dataclass(frozen=True)
class AveragingConfig:
    start: float = 0.0
    window: float | None = None
    fields: tuple[str, ...] = tuple(FIELDS)
    fields_given: bool = False

    def report(self) -> str:
        """What `coupling check` says of the averaging: from when, over what window, and the
        fields written in the time folders."""
        span = (f"a moving window of about {self.window:g} s" if self.window is not None
                else "everything from then on")
        names = [n for f in self.fields for n in WRITTEN[f]]
        return (f"averaging from t = {self.start:g} s over {span}: {', '.join(self.fields)} "
                f"(written as {', '.join(names)} in the time folders)")

    def averaged(self) -> list[str]:
        """The solver fields fieldAverage averages, each once, in a fixed order."""
        out = []
        for f in self.fields:
            out += [n for n in FIELDS[f] if n not in out]
        return out


def _number(path, key, val, *, positive: bool) -> float:
    if isinstance(val, bool) or not isinstance(val, (int, float)) or not math.isfinite(val):
        raise CaseConfigError(path, f"must be a finite number (seconds), got {val!r}", key)
    if (val <= 0) if positive else (val < 0):
        raise CaseConfigError(path, f"must be {'> 0' if positive else '>= 0'} s, got {val!r}", key)
    return float(val)


def parse_averaging(path: Path, table) -> AveragingConfig:
    """The ``[averaging]`` table of coupling.toml, every key checked (CaseConfigError naming
    the file, the key and what is allowed)."""
    if not isinstance(table, dict):
        raise CaseConfigError(path, "must be a table: [averaging] with start, window, fields", "averaging")
    allowed = ("start", "window", "fields")
    for key in table:
        if key not in allowed:
            raise CaseConfigError(path, f"unknown key; valid keys: {', '.join(allowed)}", f"averaging.{key}")
    start = _number(path, "averaging.start", table.get("start", 0.0), positive=False)
    window = table.get("window")
    if window is not None:
        window = _number(path, "averaging.window", window, positive=True)
    fields = table.get("fields")
    given = fields is not None
    if given:
        if not isinstance(fields, list) or not fields or not all(isinstance(f, str) for f in fields):
            raise CaseConfigError(path, f"must be a non-empty list of names out of {', '.join(FIELDS)}, got "
                                        f"{fields!r}", "averaging.fields")
        bad = [f for f in fields if f not in FIELDS]
        if bad:
            raise CaseConfigError(path, f"{bad[0]!r} is not one of {', '.join(FIELDS)}", "averaging.fields")
        if len(set(fields)) != len(fields):
            raise CaseConfigError(path, f"lists a field twice: {fields!r}", "averaging.fields")
        fields = tuple(fields)
    else:
        fields = tuple(FIELDS)
    return AveragingConfig(start=start, window=window, fields=fields, fields_given=given)


def check_averaging(path: Path, avg: AveragingConfig, *, end: float, dt: float, heat: bool) -> AveragingConfig:
    """``avg`` against the case: a start before the end time, a window of at least one
    coupling step, the heat fields only with heat (dropped from the default list without it).
    Returns the configuration the run uses."""
    if avg.start >= end - 0.5 * dt:
        raise CaseConfigError(path, f"{avg.start:g} s is not before the end time {end:g} s: nothing would be "
                                    f"averaged; give a start in [0, {end:g}) s", "averaging.start")
    if avg.window is not None and avg.window < dt * (1 - 1e-9):
        raise CaseConfigError(path, f"{avg.window:g} s is shorter than one coupling step (deltaT {dt:g} s); "
                                    f"give at least {dt:g} s, or remove window for the mean since start",
                              "averaging.window")
    if not heat:
        need = [f for f in avg.fields if f in HEAT_FIELDS]
        if need and avg.fields_given:
            raise CaseConfigError(path, f"{need[0]!r} needs the heat exchange (coupling.heat = true and a "
                                        f"[thermal] section with convection in dem.toml); remove it or turn "
                                        f"the heat on", "averaging.fields")
        avg = AveragingConfig(avg.start, avg.window, tuple(f for f in avg.fields if f not in HEAT_FIELDS), False)
    return avg


# --------------------------------------------------------------------------- controlDict

_BEGIN, _END = "// thermodem [averaging] begin", "// thermodem [averaging] end"


def function_objects(avg: AveragingConfig) -> str:
    """The controlDict entries of ``avg``: fieldAverage (mean, base time, from ``start``,
    written at the write times; ``window``: windowType approximate) and, for the particle
    velocity and temperature, thermoDemParticleMeans after it."""
    opts = "mean on; prime2Mean off; base time;"
    if avg.window is not None:
        opts += f" window {avg.window!r}; windowType approximate;"
    items = "\n".join(f"            {name} {{ {opts} }}" for name in avg.averaged())
    text = (f"    {FO_AVERAGE}\n    {{\n        type fieldAverage;\n        libs (fieldFunctionObjects);\n"
            f"        timeStart {avg.start!r};\n        writeControl writeTime;\n"
            f"        restartOnRestart false;\n        fields\n        (\n{items}\n        );\n    }}\n")
    if {"particle_velocity", "particle_temperature"} & set(avg.fields):
        text += (f"    {FO_MEANS}\n    {{\n        type thermoDemParticleMeans;\n"
                 f"        timeStart {avg.start!r};\n        writeControl writeTime;\n    }}\n")
    return text


def write_function_objects(ctl: Path, avg: AveragingConfig | None) -> None:
    """Put the entries of ``avg`` into ``ctl`` (system/controlDict), between marker comments
    inside its ``functions`` dictionary (added when absent); replaces the entries an earlier
    write put there, so a restart writes them again. ``None`` removes them."""
    text = ctl.read_text()
    text = re.sub(rf"\n?[ \t]*{re.escape(_BEGIN)}.*?{re.escape(_END)}[^\n]*\n", "\n", text, flags=re.S)
    if avg is None:
        ctl.write_text(text)
        return
    block = f"{_BEGIN}\n{function_objects(avg)}    {_END}\n"
    m = re.search(r"^functions\s*\{[^\n]*\n", text, flags=re.M)
    if m is None:
        marker = "// ****"
        i = text.rfind(marker)
        i = len(text) if i < 0 else i
        text = text[:i] + "functions\n{\n    " + block + "}\n\n" + text[i:]
    else:
        text = text[:m.end()] + "    " + block + text[m.end():]
    ctl.write_text(text)


# --------------------------------------------------------------------------- DEM side

def particle_columns(pw, rad, vel, temp, V, cells) -> np.ndarray:
    """The frame's particle columns of the cells of this rank's local mesh, (n_cells, 5):
    alphap = sum_p w V_p / V_c, alphap Up = sum_p w V_p u_p / V_c (3), alphap Tp =
    sum_p w V_p T_p / V_c, over the void fraction's stencil ``pw`` (w: the share of particle
    p's volume V_p in cell c), summed over the DEM ranks that see each cell (``cells``:
    coupling.cells.CellShare, collective). ``temp``: None without heat (column 0)."""
    vp = vf.particle_volumes(rad)
    n = vp.shape[0]
    vals = np.zeros((n, N_COLUMNS))
    vals[:, 0] = vp
    vals[:, 1:4] = vp[:, None] * vel
    if temp is not None:
        vals[:, 4] = vp * temp
    (sums,) = cells.assemble(vf.accumulate(pw, vals))
    return sums / V[:, None]
