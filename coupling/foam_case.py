"""Helpers around an OpenFOAM case for the thermoDemFoam coupling (ASCII cases).

* environment / build:  :func:`foam_env`, :func:`build_solver`
* meshing:              :func:`block_mesh`, :func:`decompose`
* geometry:             :func:`read_cell_centres`, :func:`read_cell_volumes`
* fields:               :func:`read_internal_field`, :func:`write_internal_field`, :func:`write_eps`
* dictionaries:         :func:`parse_foam_dict`, :func:`set_entries`, :func:`write_coupling_dict`
* running:              :func:`start_solver` (serial or ``mpirun --allow-run-as-root -np N``)
* checks:               :func:`check_case` (raises :class:`CaseError` naming the file)

Only numpy and the standard library are used. OpenFOAM commands run with the environment
of ``scripts/foam_env.sh`` (installed by ``scripts/install_openfoam.sh``).
"""
from __future__ import annotations

import math
import os
import re
import shutil
import subprocess
from dataclasses import dataclass
from functools import lru_cache
from pathlib import Path
from typing import Iterable, Mapping

import numpy as np

from .errors import CaseError, FoamError  # noqa: F401 - raised here, importable from here

ROOT = Path(__file__).resolve().parent.parent
SCRIPTS = ROOT / "scripts"
TEMPLATES = ROOT / "openfoam_cases"
SOLVER_NAME = "thermoDemFoam"

REQUIRED_FIELDS = ("U", "p", "T", "eps")
REQUIRED_FILES = (
    "constant/transportProperties",
    "constant/turbulenceProperties",
    "constant/g",
    "system/controlDict",
    "system/fvSchemes",
    "system/fvSolution",
)

__all__ = [
    "CaseError", "FoamError", "foam_env", "build_solver", "copy_template", "run_foam",
    "block_mesh", "decompose", "read_cell_centres", "read_cell_volumes",
    "read_internal_field", "write_internal_field", "write_eps", "parse_foam_dict",
    "set_entries", "write_coupling_dict", "start_solver", "check_case", "patch_names",
    "cell_proc_addressing",
]


# system/couplingDict transport
TRANSPORTS = ("file", "socket", "m2m", "none")

# constant/turbulenceProperties simulationType (OpenFOAM's incompressible turbulence models)
SIMULATION_TYPES = ("laminar", "RAS", "LES")
# fields of the turbulence models checked for boundary conditions when present in 0/
TURBULENCE_FIELDS = ("nut", "k", "epsilon", "omega", "nuTilda")


# --------------------------------------------------------------------------- environment

@lru_cache(maxsize=1)
def _env_cached() -> tuple[tuple[str, str], ...]:
    script = SCRIPTS / "foam_env.sh"
    out = subprocess.run(
        ["bash", "-c", f'. "{script}" >/dev/null 2>&1; env -0'],
        check=True, capture_output=True,
    ).stdout
    pairs = []
    for item in out.split(b"\0"):
        if b"=" in item:
            k, v = item.split(b"=", 1)
            pairs.append((k.decode(), v.decode(errors="replace")))
    return tuple(pairs)


def foam_env(extra: Mapping[str, str] | None = None) -> dict[str, str]:
    """Environment with OpenFOAM set up (``scripts/foam_env.sh``)."""
    env = {k: v for k, v in _env_cached() if not k.startswith(_MPI_JOB_VARS)}
    if extra:
        env.update(extra)
    return env


# variables of the launcher that started the DEM ranks: a solver started from a DEM rank
# (its own mpirun, blockMesh, decomposePar) must not take itself for part of that job
_MPI_JOB_VARS = ("OMPI_", "PMIX_", "PMI_", "OPAL_", "PRTE_", "HYDRA_")


def build_solver(force: bool = False) -> Path:
    """Build (or reuse) thermoDemFoam; returns the binary's path."""
    cmd = ["bash", str(SCRIPTS / "build_openfoam_solver.sh")] + (["--force"] if force else [])
    r = subprocess.run(cmd, capture_output=True, text=True)
    if r.returncode != 0:
        raise FoamError(f"building {SOLVER_NAME} failed:\n{r.stderr[-4000:]}")
    return Path(r.stdout.strip().splitlines()[-1])


def copy_template(name: str, dest: str | os.PathLike, *, overwrite: bool = False) -> Path:
    """Copy ``openfoam_cases/<name>`` to ``dest``. ``overwrite``: ``dest`` may be an earlier
    copy (its entries are replaced); a folder holding anything this tool did not write is
    refused either way (dem.outdir.OutputFolderError)."""
    from dem import outdir
    src = TEMPLATES / name
    if not (src / "system" / "controlDict").exists():
        raise CaseError(src, "not an OpenFOAM case template (no system/controlDict)")
    dest = Path(dest)
    if dest.exists() and not overwrite and os.listdir(dest):
        raise FileExistsError(dest)
    outdir.claim_folder(dest, overwrite=overwrite, command=f"copy_template {name}", what="case folder")
    for entry in src.iterdir():
        if entry.name != "README.md":
            outdir.claim(dest / entry.name)
    shutil.copytree(src, dest, ignore=shutil.ignore_patterns("README.md"), dirs_exist_ok=True)
    return dest


def run_foam(args: list[str], case: str | os.PathLike, *, log: str | None = None,
             env: Mapping[str, str] | None = None, timeout: float | None = 600) -> str:
    """Run an OpenFOAM utility in ``case``; raise :class:`FoamError` with the log tail."""
    case = Path(case)
    e = foam_env(env)
    r = subprocess.run(args + ["-case", str(case)], capture_output=True, text=True, env=e,
                       timeout=timeout)
    text = r.stdout + r.stderr
    if log:
        (case / log).write_text(text)
    if r.returncode != 0:
        raise FoamError(f"{' '.join(args)} failed in {case} (exit {r.returncode}):\n"
                        f"{text[-3000:]}")
    return text


def block_mesh(case) -> None:
    run_foam(["blockMesh"], case, log="log.blockMesh")


def decompose(case, n: int | None = None, *, method: str | None = None,
              split: tuple[int, int, int] | None = None, time: str | None = None) -> None:
    """Run decomposePar (-force). Optionally set numberOfSubdomains / method / split n;
    ``time``: decompose the fields of that time folder only (a restart on more processes)."""
    case = Path(case)
    d = case / "system" / "decomposeParDict"
    if n is not None or method is not None or split is not None:
        entries = {}
        if n is not None:
            entries["numberOfSubdomains"] = str(int(n))
        if method is not None:
            entries["method"] = method
        text = d.read_text()
        text = _set_entries_text(text, entries)
        if split is not None:
            text = re.sub(r"(\bn\s+)\([^)]*\)", rf"\g<1>({split[0]} {split[1]} {split[2]})", text)
        elif n is not None:
            # keep simple/hierarchical split consistent: split the last direction with n
            m = re.search(r"\bn\s+\(\s*(\d+)\s+(\d+)\s+(\d+)\s*\)", text)
            if m and int(m.group(1)) * int(m.group(2)) * int(m.group(3)) != n:
                text = re.sub(r"(\bn\s+)\([^)]*\)", rf"\g<1>(1 1 {int(n)})", text)
        d.write_text(text)
    run_foam(["decomposePar", "-force"] + (["-time", str(time)] if time is not None else []), case,
             log="log.decomposePar")


# --------------------------------------------------------------------------- parsing

_COMMENT = re.compile(r"//[^\n]*|/\*.*?\*/", re.S)
_TOKEN = re.compile(r'"(?:[^"\\]|\\.)*"|[{};]|[^\s{};"]+')


def strip_comments(text: str) -> str:
    return _COMMENT.sub(" ", text)


def parse_foam_dict(text_or_path) -> dict:
    """Parse an OpenFOAM dictionary into nested dicts of strings (values joined by spaces).

    Good for the small dictionaries of a case (not for big nonuniform lists)."""
    if isinstance(text_or_path, Path) or (isinstance(text_or_path, str) and "\n" not in text_or_path
                                          and Path(text_or_path).exists()):
        text = Path(text_or_path).read_text()
    else:
        text = text_or_path
    toks = _TOKEN.findall(strip_comments(text))
    pos = 0

    def parse_block():
        nonlocal pos
        out: dict = {}
        while pos < len(toks):
            t = toks[pos]
            if t == "}":
                pos += 1
                return out
            if t == ";":
                pos += 1
                continue
            key = t.strip('"')
            pos += 1
            if pos < len(toks) and toks[pos] == "{":
                pos += 1
                out[key] = parse_block()
                continue
            vals = []
            depth = 0
            while pos < len(toks):
                v = toks[pos]
                if v == ";" and depth == 0:
                    pos += 1
                    break
                if v == "}" and depth == 0:
                    break
                if v == "{":
                    depth += 1
                elif v == "}":
                    depth -= 1
                vals.append(v)
                pos += 1
            out[key] = " ".join(vals)
        return out

    return parse_block()


def read_float(path, d: dict, key: str) -> float:
    if key not in d:
        raise CaseError(path, f"entry '{key}' missing")
    tok = d[key].split()
    # accept "nu 1.5e-05;" and "nu [0 2 -1 0 0 0 0] 1.5e-05;"
    try:
        return float(tok[-1])
    except (ValueError, IndexError):
        raise CaseError(path, f"entry '{key}' is not a number: {d[key]!r}") from None


def _set_entries_text(text: str, entries: Mapping[str, object]) -> str:
    for key, value in entries.items():
        pat = re.compile(rf"^(\s*){re.escape(key)}\s+[^;]*;", re.M)
        if pat.search(text):
            text = pat.sub(lambda m: f"{m.group(1)}{key} {value};", text, count=1)
        else:
            marker = "// ****"
            i = text.rfind(marker)
            line = f"{key} {value};\n"
            text = text[:i] + line + "\n" + text[i:] if i >= 0 else text + "\n" + line
    return text


def set_entries(path, entries: Mapping[str, object]) -> None:
    """Set top-level ``key value;`` entries of a dictionary file (added if missing)."""
    path = Path(path)
    path.write_text(_set_entries_text(path.read_text(), entries))


_HEADER = """/*--------------------------------*- C++ -*----------------------------------*\\
  written by coupling/foam_case.py
\\*---------------------------------------------------------------------------*/
FoamFile
{{
    version     2.0;
    format      ascii;
    class       {cls};
    location    "{loc}";
    object      {obj};
}}
// * * * * * * * * * * * * * * * * * * * * * * * * * * * * * * * * * * * * * //

"""


@dataclass(frozen=True)
class LinkOptions:
    """The rest of system/couplingDict's transport settings (the defaults are the coupled
    run's): ``connect_timeout`` (s; None: ``timeout``), the file transport's ``directory``,
    ``poll_interval`` (s) and ``keep_files``, the socket's ``path`` (a Unix socket instead of
    a port), ``host`` and the solver's ``role`` (client: it connects to the DEM), the m2m
    transport's plan folder ``m2m_directory`` (absolute, or relative to the case)."""

    connect_timeout: float | None = None
    directory: str = "coupling"
    poll_interval: float = 0.002
    keep_files: bool = False
    path: str | None = None
    host: str = "127.0.0.1"
    role: str = "client"
    m2m_directory: str | None = None


def write_coupling_dict(case, transport: str = "file", *, timeout: float = 60, port: int | None = None,
                        send_velocity: str = "cell", tied: dict | None = None,
                        options: LinkOptions = LinkOptions(),
                        m2m_directory: str | os.PathLike | None = None, particle_fields: bool = False) -> Path:
    """Write ``system/couplingDict`` (transport file | socket | m2m | none).

    ``port``: the socket transport's TCP port (or ``options.path``). ``send_velocity``: "cell" (momentum velocity, default) or "flux" (reconstructed from
    the face fluxes, exact mass flow). ``tied``: {patches, fixed_flux, fluxes} of the walls
    tied to DEM walls (coupling.energy.FluxSplit): two frame columns each (the particles'
    contact and gas-gap heat per cell), and a fixed-flux one gives the gas the rest of q_w.
    ``m2m_directory`` (or ``options.m2m_directory``): the m2m transport's plan folder, written
    by the DEM ranks (docs/coupling_protocol.md, "Many-to-many transport (m2m)"); that
    dictionary has an ``m2m { directory ...; }`` block instead of the file and socket ones.
    ``particle_fields``: each frame holds the five particle columns of the time averages after
    the exchange ones (coupling.averaging; the solver's ``particleFields``)."""
    o = options
    connect_timeout, directory, poll_interval, keep_files = o.connect_timeout, o.directory, o.poll_interval, o.keep_files
    path, host, role = o.path, o.host, o.role
    if send_velocity not in ("cell", "flux"):
        raise ValueError("send_velocity must be cell or flux")
    if transport not in TRANSPORTS:
        raise ValueError("transport must be file, socket, m2m or none")
    if transport == "socket" and (port is None) == (path is None):
        raise ValueError("socket transport needs exactly one of port or path")
    if m2m_directory is None:
        m2m_directory = o.m2m_directory
    if transport == "m2m" and m2m_directory is None:
        raise ValueError("m2m transport needs m2m_directory (the DEM ranks' plan folder)")
    sock = f'        host        "{host}";\n        role        {role};\n'
    if port is not None:
        sock += f"        port        {int(port)};\n"
    if path is not None:
        sock += f'        path        "{path}";\n'
    head = (
        f"transport       {transport};\n"
        f"timeout         {timeout};\n"
        f"connectTimeout  {connect_timeout if connect_timeout is not None else timeout};\n"
        f"sendVelocity    {send_velocity};\n"
        + (f"tiedPatches     ({' '.join(tied['patches'])});\n"
           f"tiedFixedFlux   ({' '.join(str(int(bool(x))) for x in tied['fixed_flux'])});\n"
           f"tiedHeatFlux    ({' '.join(repr(float(q)) for q in tied['fluxes'])});\n"
           if tied and tied.get("patches") else "")
        + ("particleFields  true;\n" if particle_fields else "")
        + "\n"
    )
    if transport == "m2m":
        body = head + f'm2m\n{{\n    directory   "{os.fspath(m2m_directory)}";\n}}\n'
    else:
        body = head + (
            "file\n{\n"
            f'    directory   "{directory}";\n'
            f"    pollInterval {poll_interval};\n"
            f"    keepFiles   {'true' if keep_files else 'false'};\n"
            "}\n\nsocket\n{\n" + sock.replace("        ", "    ") + "}\n"
        )
    out = Path(case) / "system" / "couplingDict"
    out.write_text(_HEADER.format(cls="dictionary", loc="system", obj="couplingDict") + body)
    return out


# --------------------------------------------------------------------------- fields

_INTERNAL = re.compile(
    r"internalField\s+(?:(uniform)\s+(\([^)]*\)|[^;\s]+)\s*;|nonuniform\s+List<(\w+)>\s*(\d+)\s*\()",
    re.S,
)


def read_internal_field(path, n_cells: int | None = None) -> np.ndarray:
    """Internal field of an ASCII volField file: (n,) for scalars, (n, 3) for vectors."""
    path = Path(path)
    text = path.read_text()
    m = _INTERNAL.search(text)
    if not m:
        raise CaseError(path, "no ASCII internalField found (binary or compressed?)")
    if m.group(1):
        val = m.group(2)
        if val.startswith("("):
            v = np.array(val.strip("()").split(), dtype=float)
        else:
            v = np.array(float(val))
        if n_cells is None:
            raise CaseError(path, "uniform internalField: n_cells needed")
        return np.tile(v, (n_cells, 1)) if v.ndim else np.full(n_cells, float(v))
    kind, n = m.group(3), int(m.group(4))
    start = m.end()
    if "\n" in text[m.end(4):start]:
        end = text.index("\n)", start)
    else:  # short lists (up to 10 entries) are written on one line: n(a b c)
        depth, end = 1, start
        while depth and end < len(text):
            depth += (text[end] == "(") - (text[end] == ")")
            end += 1
        end -= 1
    body = text[start:end]
    if kind == "scalar":
        a = np.array(body.split(), dtype=float)
        shape = (n,)
    elif kind == "vector":
        a = np.array(body.replace("(", " ").replace(")", " ").split(), dtype=float)
        shape = (n, 3)
    else:
        raise CaseError(path, f"unsupported field type List<{kind}>")
    if a.size != int(np.prod(shape)):
        raise CaseError(path, f"internalField has {a.size} numbers, expected {np.prod(shape)}")
    return a.reshape(shape)


def _format_list(values: np.ndarray) -> str:
    v = np.asarray(values, dtype=float)
    if v.ndim == 1:
        body = "\n".join(repr(float(x)) for x in v)
        kind = "scalar"
    else:
        body = "\n".join(f"({x!r} {y!r} {z!r})" for x, y, z in v.astype(float).tolist())
        kind = "vector"
    return f"nonuniform List<{kind}> \n{len(v)}\n(\n{body}\n)\n"


def write_internal_field(path, values: np.ndarray) -> None:
    """Replace the internalField of an ASCII volField file (boundaryField kept)."""
    path = Path(path)
    text = path.read_text()
    m = re.search(r"internalField\s+", text)
    if not m:
        raise CaseError(path, "no internalField entry")
    start = m.end()
    # end of the internalField entry: the ';' after the value (list closes with '\n)')
    if text.startswith("nonuniform", start):
        end = text.index("\n)", start) + 2
        end = text.index(";", end)
    else:
        end = text.index(";", start)
    path.write_text(text[:start] + _format_list(values) + text[end:])


def cell_proc_addressing(case) -> list[np.ndarray]:
    """Global cell index of each local cell, per processor directory (sorted)."""
    case = Path(case)
    out = []
    procs = sorted((p for p in case.glob("processor*") if p.name[9:].isdigit()),
                   key=lambda p: int(p.name[9:]))
    for p in procs:
        f = p / "constant" / "polyMesh" / "cellProcAddressing"
        text = strip_comments(f.read_text())
        text = text[text.index("}", text.index("FoamFile")) + 1:]
        m = re.search(r"(\d+)\s*\(", text)
        if not m:
            raise CaseError(f, "cannot parse (binary format?)")
        n = int(m.group(1))
        vals = np.array(text[m.end():text.index(")", m.end())].split(), dtype=np.int64)
        if vals.size != n:
            raise CaseError(f, f"{vals.size} entries, header says {n}")
        out.append(vals)
    return out


def write_eps(case, eps: np.ndarray, time: str = "0") -> None:
    """Write the initial void fraction into ``<time>/eps`` (and processor*/<time>/eps)."""
    case = Path(case)
    eps = np.asarray(eps, dtype=float)
    if eps.ndim != 1 or np.any(~np.isfinite(eps)) or np.any(eps <= 0) or np.any(eps > 1):
        raise ValueError("eps must be a 1-D array with 0 < eps <= 1")
    f = case / time / "eps"
    if not f.exists():
        raise CaseError(f, "missing (copy it from a template)")
    write_internal_field(f, eps)
    for addr, proc in zip(cell_proc_addressing(case),
                          sorted((p for p in case.glob("processor*") if p.name[9:].isdigit()),
                                 key=lambda p: int(p.name[9:]))):
        pf = proc / time / "eps"
        if pf.exists():
            write_internal_field(pf, eps[addr])


def _post_process_field(case, func: str, names: Iterable[str]) -> dict[str, np.ndarray]:
    case = Path(case)
    tdir = case / "0"
    existed = {n: (tdir / n).exists() for n in names}
    run_foam(["postProcess", "-func", func, "-time", "0"], case, log=None)
    out = {}
    try:
        for n in names:
            out[n] = read_internal_field(tdir / n)
    finally:
        for n, ex in existed.items():
            if not ex:
                for suffix in ("", "x", "y", "z"):
                    (tdir / f"{n}{suffix}").unlink(missing_ok=True)
    return out


def read_cell_centres(case) -> np.ndarray:
    """Cell centres (n_cells, 3) in global cell order (runs postProcess writeCellCentres)."""
    return _post_process_field(case, "writeCellCentres", ["C"])["C"]


def read_cell_volumes(case) -> np.ndarray:
    """Cell volumes (n_cells,) (runs postProcess writeCellVolumes)."""
    return _post_process_field(case, "writeCellVolumes", ["V"])["V"]


# --------------------------------------------------------------------------- running

def start_solver(case, *, nprocs: int = 1, solver: str | os.PathLike | None = None,
                 log: str | os.PathLike | None = "log.thermoDemFoam",
                 env: Mapping[str, str] | None = None, extra_args: Iterable[str] = (),
                 own_session: bool = False) -> subprocess.Popen:
    """Start thermoDemFoam as a subprocess (serial, or mpirun -np N ... -parallel).

    stdout+stderr go to ``case/log`` (or a pipe if ``log`` is None). ``own_session``:
    start it in its own session, so that a Ctrl-C in the terminal reaches only the DEM,
    which then stops the solver cleanly at the end of the coupling step (a solver that
    gets SIGINT/SIGTERM itself also ends its step, writes and flags FINAL)."""
    case = Path(case).resolve()
    exe = str(solver) if solver else SOLVER_NAME
    args = [exe, "-case", str(case), *extra_args]
    if nprocs > 1:
        if not (case / "processor0").exists():
            raise CaseError(case, "not decomposed (run decompose first)")
        mpi = ["mpirun", "-np", str(nprocs)]
        if os.geteuid() == 0:
            mpi.append("--allow-run-as-root")
        if nprocs > (os.cpu_count() or 1):
            mpi.append("--oversubscribe")
        args = mpi + args + ["-parallel"]
    e = foam_env(env)
    if log is None:
        return subprocess.Popen(args, env=e, stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
                                text=True, start_new_session=own_session)
    logf = open(case / log, "w")
    try:
        return subprocess.Popen(args, env=e, stdout=logf, stderr=subprocess.STDOUT,
                                start_new_session=own_session)
    finally:
        logf.close()


# --------------------------------------------------------------------------- checks

def patch_names(case) -> list[str]:
    """Boundary patch names from constant/polyMesh/boundary, else system/blockMeshDict."""
    case = Path(case)
    b = case / "constant" / "polyMesh" / "boundary"
    if b.exists():
        text = strip_comments(b.read_text())
        text = text[text.index("}", text.index("FoamFile")) + 1:]
        return re.findall(r"(\w+)\s*\{", text)
    bm = case / "system" / "blockMeshDict"
    if bm.exists():
        text = strip_comments(bm.read_text())
        i = text.find("boundary")
        if i < 0:
            raise CaseError(bm, "no boundary list")
        j = text.index("(", i)
        depth, k = 0, j
        while True:
            if text[k] == "(":
                depth += 1
            elif text[k] == ")":
                depth -= 1
                if depth == 0:
                    break
            k += 1
        inner = text[j + 1:k]
        names, depth = [], 0
        for tok in re.findall(r"[{}]|[A-Za-z_][\w.:-]*", inner):
            if tok == "{":
                depth += 1
            elif tok == "}":
                depth -= 1
            elif depth == 0:
                names.append(tok)
        return names
    raise CaseError(case / "constant/polyMesh/boundary", "no mesh and no system/blockMeshDict")


def check_case(case, *, coupled: bool = True) -> None:
    """Check an OpenFOAM case for thermoDemFoam; raise :class:`CaseError` naming the file.

    Checks: required files/fields, every patch has a boundary condition in every field
    (and no unknown patch), gas properties physical (transportModel Newtonian; nu, rho,
    cp > 0; k >= 0 or Pr > 0; Prt > 0), constant/turbulenceProperties (required, as by
    OpenFOAM's turbulence framework: simulationType laminar | RAS | LES; RAS/LES need
    0/nut; the turbulence fields present in 0/ are checked like U, p, T, eps),
    modelType A/B, couplingDict transport, eps within (0, 1]."""
    case = Path(case)
    if not case.is_dir():
        raise CaseError(case, "case directory does not exist")
    for rel in REQUIRED_FILES:
        if not (case / rel).exists():
            if rel == "constant/turbulenceProperties":
                raise CaseError(case / rel, "missing (thermoDemFoam reads it through OpenFOAM's "
                                "turbulence framework; for laminar gas write "
                                "'simulationType laminar;')")
            raise CaseError(case / rel, "missing")
    for fld in REQUIRED_FIELDS:
        if not (case / "0" / fld).exists():
            raise CaseError(case / "0" / fld, f"missing field '{fld}'")

    tp_path = case / "constant" / "transportProperties"
    tp = parse_foam_dict(tp_path)
    tm = tp.get("transportModel")
    if tm is None:
        raise CaseError(tp_path, "entry 'transportModel' missing (add 'transportModel Newtonian;' "
                        "for OpenFOAM's singlePhaseTransportModel)")
    if tm != "Newtonian":
        raise CaseError(tp_path, f"transportModel {tm!r} not supported (use Newtonian: the drag "
                        "correlations of the DEM use the constant viscosity rho*nu)")
    nu, rho = read_float(tp_path, tp, "nu"), read_float(tp_path, tp, "rho")
    cp = read_float(tp_path, tp, "cp") if "cp" in tp else 1005.0
    for name, v in (("nu", nu), ("rho", rho), ("cp", cp)):
        if not np.isfinite(v) or v <= 0:
            raise CaseError(tp_path, f"non-physical gas property {name} = {v} (must be > 0)")
    if "k" in tp:
        k = read_float(tp_path, tp, "k")
        if not np.isfinite(k) or k < 0:
            raise CaseError(tp_path, f"non-physical gas property k = {k} (must be >= 0)")
    elif "Pr" in tp:
        pr = read_float(tp_path, tp, "Pr")
        if not np.isfinite(pr) or pr <= 0:
            raise CaseError(tp_path, f"non-physical gas property Pr = {pr} (must be > 0)")
    if "Prt" in tp:
        prt = read_float(tp_path, tp, "Prt")
        if not np.isfinite(prt) or prt <= 0:
            raise CaseError(tp_path, f"non-physical turbulent Prandtl number Prt = {prt} (must be > 0)")
    if nu > 1e-2:
        raise CaseError(tp_path, f"nu = {nu} m^2/s is not a gas kinematic viscosity")

    turb_path = case / "constant" / "turbulenceProperties"
    sim_type = parse_foam_dict(turb_path).get("simulationType")
    if sim_type not in SIMULATION_TYPES:
        raise CaseError(turb_path, f"simulationType {sim_type!r} unknown (use "
                        + ", ".join(SIMULATION_TYPES) + ")")
    fields = list(REQUIRED_FIELDS)
    if sim_type != "laminar":
        if not (case / "0" / "nut").exists():
            raise CaseError(case / "0" / "nut", f"missing field 'nut' (needed by simulationType "
                            f"{sim_type}, with e.g. nutkWallFunction on walls)")
        fields += [f for f in TURBULENCE_FIELDS if (case / "0" / f).exists()]

    cpp = case / "constant" / "couplingProperties"
    if cpp.exists():
        mt = parse_foam_dict(cpp).get("modelType", "A")
        if mt not in ("A", "B"):
            raise CaseError(cpp, f"modelType {mt!r} unknown (use A or B)")

    cd = case / "system" / "couplingDict"
    if coupled:
        if not cd.exists():
            raise CaseError(cd, "missing (write it with write_coupling_dict)")
        tr = parse_foam_dict(cd).get("transport", "none")
        if tr not in TRANSPORTS:
            raise CaseError(cd, f"transport {tr!r} unknown (use file, socket, m2m or none)")

    patches = set(patch_names(case))
    for fld in fields:
        p = case / "0" / fld
        d = parse_foam_dict(p)
        bf = d.get("boundaryField")
        if not isinstance(bf, dict):
            raise CaseError(p, "no boundaryField")
        # regex patch keys (e.g. ".*Walls") cover several patches
        covered = set()
        for key in bf:
            rx = re.compile(key.strip('"'))
            covered |= {q for q in patches if rx.fullmatch(q)}
        missing = sorted(patches - covered)
        if missing:
            raise CaseError(p, f"missing boundary condition for patch(es) {missing}")
        unknown = sorted(k for k in bf if not any(re.fullmatch(k.strip('"'), q) for q in patches))
        if unknown:
            raise CaseError(p, f"boundary condition for unknown patch(es) {unknown}")
    _check_uniform_values(case)
    if (case / "constant" / "polyMesh" / "owner").exists():
        n = _n_cells_from_owner(case)
        eps = read_internal_field(case / "0" / "eps", n)
        if np.any(eps <= 0) or np.any(eps > 1):
            raise CaseError(case / "0" / "eps", "void fraction outside (0, 1]")


def _check_uniform_values(case) -> None:
    """The ``uniform`` values of 0/T (finite, > 0 K) and 0/U (finite vectors): a NaN or a
    negative absolute temperature is a typing error, refused naming the file and entry."""
    for fld, positive in (("T", True), ("U", False)):
        p = Path(case) / "0" / fld
        if not p.exists():
            continue
        d = parse_foam_dict(p)
        entries = [("internalField", d.get("internalField"))]
        bf = d.get("boundaryField")
        if isinstance(bf, dict):
            for patch, spec in bf.items():
                if isinstance(spec, dict):
                    entries += [(f"boundaryField.{patch}.{k}", v) for k, v in spec.items()]
        for key, val in entries:
            # the word ``uniform`` and its value; not a type such as ``uniformFixedValue``
            m = re.match(r"uniform(?![A-Za-z0-9_])(.*)$", val, re.S) if isinstance(val, str) else None
            if m is None:
                continue
            raw = m.group(1).strip()
            try:
                vals = [float(x) for x in raw.strip("()").split()]
            except ValueError:
                raise CaseError(p, f"{key}: 'uniform {raw}' is not a number") from None
            if not all(math.isfinite(x) for x in vals):
                raise CaseError(p, f"{key}: 'uniform {raw}' is not a finite number")
            not_a_temperature = key.rsplit(".", 1)[-1] in ("gradient", "refGradient", "valueFraction")
            if positive and not not_a_temperature and any(x <= 0 for x in vals):
                raise CaseError(p, f"{key}: 'uniform {raw}': a temperature must be > 0 K")


def _n_cells_from_owner(case) -> int:
    f = Path(case) / "constant" / "polyMesh" / "owner"
    with open(f) as fh:
        head = fh.read(4096)
    m = re.search(r"nCells:\s*(\d+)", head)
    if not m:
        raise CaseError(f, "no nCells in note")
    return int(m.group(1))
