"""Preparing a coupled run's output folder (rank 0): the output-folder rule (dem.outdir: new,
empty or an earlier output, never the case folder), the copy of the case's OpenFOAM part,
its mesh (blockMesh), and the gas case the solver starts from: end time and write
precision in controlDict, the initial void fraction (0/eps), the exchange and the
solver's couplingDict (coupling.transport.open_exchange), the decomposition
(``gas_processes > 1``), the case check and the solver build.
"""
from __future__ import annotations

import shutil
from pathlib import Path

from . import foam_case as fc
from .errors import CouplingRunError
from .transport import open_exchange


def output_rule(case_dir, *, restart: bool, overwrite: bool) -> dict:
    """The output-folder rule of a coupled run (dem.outdir): --out new, empty or an earlier
    output (continued with --restart, replaced with --overwrite), never the case folder, a
    folder inside it or one holding it."""
    return dict(restart=restart, overwrite=overwrite, protect=[Path(case_dir)])


def prepare_output(case, out: Path, *, restart: bool, overwrite: bool = False) -> None:
    """Claim --out (dem.outdir: refused unless new, empty or an earlier output of ours; with
    --overwrite the earlier output's entries are removed, nothing else), copy the case's
    OpenFOAM part into it and mesh it."""
    from dem import outdir
    rule = output_rule(case.dir, restart=restart, overwrite=overwrite)
    if restart:
        outdir.check(out, **rule)
        if not (out / "system" / "controlDict").exists():
            raise CouplingRunError(f"{out}: nothing to restart (no system/controlDict)")
    outdir.claim_folder(out, command="coupling run", **rule)
    write_opener(case, out)
    if restart:
        return
    for sub in ("0", "constant", "system"):
        outdir.claim(out / sub)
        shutil.copytree(case.dir / sub, out / sub)
    for f in ("dem.toml", "coupling.toml"):
        outdir.claim(out / f)
        shutil.copy2(case.dir / f, out / f)
    if not (out / "constant" / "polyMesh" / "owner").exists():
        outdir.claim(out / "log.blockMesh")
        fc.block_mesh(out)


def write_opener(case, out: Path) -> Path:
    """``<case>.foam`` in --out: the empty file by which ParaView (and pyvista's OpenFOAM reader)
    opens the gas case, reconstructed or decomposed (`processor*`), beside the particles'
    ``particles.pvd``. Written once (also into an earlier output continued with --restart that
    lacks it), recorded in the output's manifest."""
    from dem import outdir
    opener = out / f"{case.dir.name}.foam"
    if not opener.exists():
        outdir.claim(opener)
        opener.touch()
    return opener


def prepare_gas(out: Path, cfg, n_cells: int, split, eps0, end: float, *, restart: bool, solver=None, m2m=False,
                gas_dir=None, decomposed=False, log=print):
    """The gas case in --out ready to start (rank 0); returns (exchange, solver executable).
    ``n_cells``: the gas mesh's cells; ``eps0``: the initial void fraction (written on a fresh
    start; None with ``decomposed``: the case was decomposed first and each processor's 0/eps
    written by the DEM ranks, coupling.pieces), ``split``: the tied
    walls (their couplingDict entries), ``end``: the run's end time (s); ``m2m``: the
    many-to-many transport (each rank's exchange is made afterwards:
    coupling.transport.open_m2m); ``gas_dir``: the gas time folder of the restart point (moved
    to this run's gas_processes when it differs)."""
    from dem import outdir
    ctl = out / "system" / "controlDict"
    # 17 significant digits: a written time is a restart point that continues to round-off
    fc.set_entries(ctl, {"endTime": repr(end), "startFrom": "latestTime", "writePrecision": 17})
    # [averaging]: OpenFOAM's fieldAverage in controlDict (coupling.averaging); again on a restart
    from .averaging import write_function_objects
    write_function_objects(ctl, cfg.averaging)
    if not restart and not decomposed:
        fc.write_eps(out, eps0)
    ex = open_exchange(out, cfg, n_cells, split.couplingdict_entries(), m2m=m2m)
    if restart and gas_dir is not None:
        from .restart import relayout_gas
        moved = relayout_gas(out, Path(gas_dir), cfg.gas_processes)   # a restart on another gas layout
        if moved:
            log(f"coupling: {moved}")
    elif cfg.gas_processes > 1 and not decomposed:
        for name in ["log.decomposePar"] + [f"processor{i}" for i in range(cfg.gas_processes)]:
            outdir.claim(out / name)
        fc.decompose(out, cfg.gas_processes)
    fc.check_case(out)
    exe = Path(solver) if solver else fc.build_solver()
    return ex, exe
