"""Starting the gas solver of a coupled run (rank 0): thermoDemFoam as a child process in its
own session (coupling.foam_case.start_solver, niced by ``solver_nice``), or, with
``--external-solver``, the command the user runs in a second terminal; the MPI variables a
``mpirun -np 1`` left that the solver's own mpirun must not inherit; the tail of its log for
an error message.
"""
from __future__ import annotations

import os
import sys
from pathlib import Path

from . import foam_case as fc


def scrub_mpi_env():
    """Started by mpirun -np 1: the solver's own mpirun must not inherit our MPI job."""
    for k in list(os.environ):
        if k.startswith(("OMPI_", "PMIX_", "PMI_", "OPAL_", "PRTE_", "HYDRA_")):
            del os.environ[k]


class ExternalSolver:
    """Stand-in for the solver process when the user starts it by hand (second terminal)."""

    pid = None

    def poll(self):
        return 0

    def wait(self, timeout=None):
        return 0

    def kill(self):
        pass


def start_solver(out, cfg, exe, external_solver, log):
    """The gas solver process (rank 0): started here, or by the user (external_solver)."""
    from dem import outdir
    if external_solver:
        par = (f"mpirun --allow-run-as-root -np {cfg.gas_processes} " if cfg.gas_processes > 1 else "")
        log("coupling: start the gas solver yourself, in a second terminal:\n"
            f"  . {Path(__file__).resolve().parent.parent / 'scripts' / 'foam_env.sh'} && "
            f"{par}{exe} -case {out}{' -parallel' if cfg.gas_processes > 1 else ''}\n"
            f"coupling: waiting up to {cfg.timeout:g} s for it ({cfg.transport} transport)")
        sys.stdout.flush()
        proc = ExternalSolver()
    else:
        outdir.claim(out / "log.thermoDemFoam")
        proc = fc.start_solver(out, nprocs=cfg.gas_processes, solver=exe, own_session=True)
    if cfg.solver_nice and proc.pid:
        try:  # a woken solver then does not preempt the DEM (the critical path) on busy cores
            os.setpriority(os.PRIO_PROCESS, proc.pid, cfg.solver_nice)
        except OSError:
            pass
    return proc


def log_tail(path: Path, n=12) -> str:
    """The last ``n`` lines of the solver's log, indented (empty if unreadable)."""
    try:
        lines = path.read_text(errors="replace").splitlines()
    except OSError:
        return ""
    return "\n".join("    " + x for x in lines[-n:])
