#!/usr/bin/env bash
# Install everything thermodem needs on Debian 12 (as root, or with sudo): Open MPI,
# Debian's OpenFOAM v1912 with the headers/wmake to build our gas solver, the solver
# itself (cached on a hash of its sources), and the Python package with its
# dependencies. Idempotent: a second run takes a few seconds.
set -euo pipefail
ROOT="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd -P)"
cd "$ROOT"
log() { echo "[setup] $*" >&2; }

SUDO=""
[ "$(id -u)" = 0 ] || SUDO="sudo"
need=()
for p in openmpi-bin libopenmpi-dev g++ make python3-venv libegl1 libegl-mesa0; do
    dpkg-query -W -f='${Status}' "$p" 2>/dev/null | grep -q "install ok installed" || need+=("$p")
done
if [ ${#need[@]} -gt 0 ]; then
    log "apt-get install ${need[*]}"
    $SUDO apt-get update -qq
    DEBIAN_FRONTEND=noninteractive $SUDO apt-get install -y -qq --no-install-recommends "${need[@]}" >&2
fi

PY="${PYTHON:-python3}"
if ! "$PY" -c "import dem, numba, meshio, mpi4py, pytest, xdist, scipy, pyvista, matplotlib, PIL" >/dev/null 2>&1; then
    log "pip install -e .[test,render]"
    "$PY" -m pip install -q --disable-pip-version-check -e ".[test,render]" >&2
fi

# the package's bytecode, written once here: where PYTHONDONTWRITEBYTECODE is set (as on this
# project's machines) Python would otherwise compile the ~60 modules a run imports in every
# process (0.2 s of each run's start; stale files are ignored by Python after an edit)
"$PY" -m compileall -q -j 0 dem coupling benchmarks >/dev/null 2>&1 || true
if [ "${THERMODEM_NO_OPENFOAM:-0}" != 1 ]; then
    log "OpenFOAM (Debian package + headers for our solver)"
    bash scripts/install_openfoam.sh >/dev/null
    log "building the gas solver (cached)"
    bash scripts/build_openfoam_solver.sh >/dev/null
fi
# one compile step, its warm-up jobs in parallel worker processes (one per usable core,
# dem/compile.py): with OpenFOAM `coupling compile` (the coupling and the DEM kernels), else
# `dem compile`. About 1 to 1.5 minutes the first time on a 2-core machine (load-dependent), then about 8 s.
# THERMODEM_SETUP_CACHE_COPY=DIR (scripts/test.sh sets it to a folder of its own): when this
# compile starts from an empty cache, DIR/<the cache folder's name> receives a hard-linked copy
# of what it wrote (no disk: Numba replaces a cache file by renaming a new one over it, so the
# copy keeps the set-up's files as they were), which tests/test_compile.py examines instead of
# compiling everything again
CACHE_DIR="$("$PY" -c 'import dem, numba; print(numba.config.CACHE_DIR)')"
FRESH=0
[ -e "$CACHE_DIR" ] || FRESH=1
if [ "${THERMODEM_NO_OPENFOAM:-0}" != 1 ]; then
    log "compiling the DEM and coupling kernels into Numba's cache, in parallel (1 to 1.5 minutes on 2 cores the first time, then seconds)"
    "$PY" -m coupling.run compile >&2
else
    log "compiling the DEM kernels into Numba's cache, in parallel (under a minute on 2 cores the first time, then seconds)"
    "$PY" -m dem.cli compile >&2
fi
if [ "$FRESH" = 1 ] && [ -n "${THERMODEM_SETUP_CACHE_COPY:-}" ] && [ ! -e "$THERMODEM_SETUP_CACHE_COPY/$(basename "$CACHE_DIR")" ]; then
    mkdir -p "$THERMODEM_SETUP_CACHE_COPY"
    cp -al "$CACHE_DIR" "$THERMODEM_SETUP_CACHE_COPY/"
fi
log "ready"
