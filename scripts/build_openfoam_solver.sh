#!/usr/bin/env bash
# Build thermodem's OpenFOAM solver (thermoDemFoam) with wmake against Debian's
# OpenFOAM v1912 libraries.
#
#   scripts/build_openfoam_solver.sh [--force]
#
# * Needs the tree prepared by scripts/install_openfoam.sh (run it first).
# * The sources (openfoam_cases/solver/thermoDemFoam) are copied to
#   build/openfoam/src/<sha256> and built there, so the repository stays clean.
# * The binary goes to build/openfoam/bin (FOAM_USER_APPBIN). It is rebuilt only
#   when the sha256 over the solver sources changes (stamp build/openfoam/bin/
#   thermoDemFoam.sha256) or with --force.
# * Prints the absolute path of the binary on stdout (all logs go to stderr).
set -euo pipefail

ROOT="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd -P)"
SOLVER=thermoDemFoam
SRC="$ROOT/openfoam_cases/solver/$SOLVER"
FORCE=0
[ "${1:-}" = "--force" ] && FORCE=1

log() { echo "[build_openfoam_solver] $*" >&2; }
die() { echo "[build_openfoam_solver] ERROR: $*" >&2; exit 1; }

[ -f "$SRC/Make/files" ] || die "solver sources not found in $SRC"

# shellcheck disable=SC1091
. "$ROOT/scripts/foam_env.sh"
[ -n "${WM_PROJECT_DIR:-}" ] || die "OpenFOAM environment not found; run scripts/install_openfoam.sh"
command -v wmake >/dev/null 2>&1 || die "wmake not found (WM_PROJECT_DIR=$WM_PROJECT_DIR); run scripts/install_openfoam.sh"

# sha256 over relative names + contents of all source files
hash=$(
    cd "$SRC" &&
    find . -type f \( -name '*.C' -o -name '*.H' -o -path './Make/files' -o -path './Make/options' \) \
        -not -path './Make/linux64*' -print | LC_ALL=C sort |
    while read -r f; do echo "== $f"; cat "$f"; done | sha256sum | cut -c1-64
)
# environment parts that change the binary
hash=$(printf '%s %s %s\n' "$hash" "$WM_OPTIONS" "$(g++ -dumpfullversion 2>/dev/null || echo gcc)" | sha256sum | cut -c1-64)

BIN="$FOAM_USER_APPBIN/$SOLVER"
STAMP="$BIN.sha256"

if [ "$FORCE" = 0 ] && [ -x "$BIN" ] && [ -f "$STAMP" ] && [ "$(cat "$STAMP")" = "$hash" ]; then
    log "up to date ($hash)"
    echo "$BIN"
    exit 0
fi

mkdir -p "$FOAM_USER_APPBIN" "$FOAM_USER_LIBBIN" "$THERMODEM_FOAM_BUILD/src"
WORK="$THERMODEM_FOAM_BUILD/src/$hash"
rm -rf "$WORK"
mkdir -p "$WORK"
cp -r "$SRC/." "$WORK/"
rm -rf "$WORK"/Make/linux64* "$WORK"/lnInclude

log "building $SOLVER in $WORK"
t0=$(date +%s)
if ! (cd "$WORK" && wmake -s >&2 2> "$WORK/wmake.log" || { cat "$WORK/wmake.log" >&2; exit 1; }); then
    die "wmake failed (log: $WORK/wmake.log)"
fi
[ -x "$BIN" ] || die "wmake finished but $BIN is missing (log: $WORK/wmake.log)"
echo "$hash" > "$STAMP"
log "built $BIN in $(( $(date +%s) - t0 )) s"

# keep only the newest build directory
for d in "$THERMODEM_FOAM_BUILD"/src/*; do
    [ "$d" = "$WORK" ] || rm -rf "$d"
done
echo "$BIN"
