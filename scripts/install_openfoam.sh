#!/usr/bin/env bash
# Install Debian 12's OpenFOAM v1912 (binaries + libraries in /usr) and prepare the
# matching source tree (headers + wmake) needed to compile our own solver against it.
#
# Idempotent: every step is skipped when its result is already present.
# Must run as root on Debian 12 (bookworm) for the apt steps; if everything is
# already installed it works as any user.
#
# Environment:
#   THERMODEM_CACHE   cache root (default ~/.cache/thermodem); the source goes to
#                     $THERMODEM_CACHE/openfoam-src
#
# On success prints the path of the prepared OpenFOAM tree (WM_PROJECT_DIR).
set -euo pipefail

CACHE_ROOT="${THERMODEM_CACHE:-$HOME/.cache/thermodem}"
SRC_CACHE="$CACHE_ROOT/openfoam-src"
TREE_NAME="openfoam-OpenFOAM-v1912.200626"
TREE="$SRC_CACHE/$TREE_NAME"
STAMP="$TREE/.thermodem-prepared-v4"   # bump when the preparation changes
# v4: thermoDemFoam uses the incompressible turbulence framework: the TurbulenceModels /
#     transportModels headers and the Debian libraries are verified below

log() { echo "[install_openfoam] $*" >&2; }
die() { echo "[install_openfoam] ERROR: $*" >&2; exit 1; }

SUDO=""
if [ "$(id -u)" != 0 ]; then
    if command -v sudo >/dev/null 2>&1; then SUDO="sudo"; fi
fi

# ---------------------------------------------------------------- 1. packages
need_pkgs=()
for p in openfoam openmpi-bin libopenmpi-dev g++ make bzip2; do
    if ! dpkg-query -W -f='${Status}' "$p" 2>/dev/null | grep -q "install ok installed"; then
        need_pkgs+=("$p")
    fi
done
apt_updated=0
if [ ${#need_pkgs[@]} -gt 0 ]; then
    log "installing: ${need_pkgs[*]}"
    $SUDO apt-get update -qq
    apt_updated=1
    DEBIAN_FRONTEND=noninteractive $SUDO apt-get install -y -qq --no-install-recommends \
        "${need_pkgs[@]}" >&2
else
    log "packages already installed"
fi
[ -f /usr/share/openfoam/etc/bashrc ] || die "openfoam package installed but /usr/share/openfoam/etc/bashrc missing"

# ---------------------------------------------------------------- 2. source tarball
if [ -f "$STAMP" ]; then
    log "source tree ready: $TREE"
    echo "$TREE"
    exit 0
fi

mkdir -p "$SRC_CACHE"
orig=$(ls "$SRC_CACHE"/openfoam_1912*.orig.tar.* 2>/dev/null | head -n1 || true)
if [ -z "$orig" ]; then
    # deb-src entry for bookworm main, mirroring debian.sources
    srcfile=/etc/apt/sources.list.d/thermodem-debian-src.sources
    if ! grep -rqs "deb-src" /etc/apt/sources.list /etc/apt/sources.list.d/ 2>/dev/null; then
        log "adding deb-src entry $srcfile"
        uris="http://deb.debian.org/debian"
        signed="/usr/share/keyrings/debian-archive-keyring.gpg"
        if [ -f /etc/apt/sources.list.d/debian.sources ]; then
            u=$(awk '/^URIs:/{print $2; exit}' /etc/apt/sources.list.d/debian.sources)
            s=$(awk '/^Signed-By:/{print $2; exit}' /etc/apt/sources.list.d/debian.sources)
            [ -n "$u" ] && uris="$u"
            [ -n "$s" ] && signed="$s"
        fi
        $SUDO tee "$srcfile" >/dev/null <<EOF
Types: deb-src
URIs: $uris
Suites: bookworm bookworm-updates
Components: main
Signed-By: $signed
EOF
        apt_updated=0
    fi
    if [ "$apt_updated" = 0 ]; then
        $SUDO apt-get update -qq
    fi
    log "downloading openfoam source package into $SRC_CACHE"
    (cd "$SRC_CACHE" && apt-get source --download-only openfoam >&2)
    orig=$(ls "$SRC_CACHE"/openfoam_1912*.orig.tar.* 2>/dev/null | head -n1 || true)
    [ -n "$orig" ] || die "apt-get source did not produce openfoam_1912*.orig.tar.* in $SRC_CACHE"
else
    log "reusing $orig"
fi

# ---------------------------------------------------------------- 3. extract
# TurbulenceModels + transportModels: thermoDemFoam's turbulence option
# (incompressible::turbulenceModel, singlePhaseTransportModel)
libs="OpenFOAM OSspecific finiteVolume meshTools fvOptions sampling surfMesh fileFormats
      TurbulenceModels transportModels dynamicMesh dynamicFvMesh"
members="$TREE_NAME/META-INFO $TREE_NAME/bin $TREE_NAME/etc $TREE_NAME/wmake"
for l in $libs; do members="$members $TREE_NAME/src/$l"; done
log "extracting headers/wmake from $(basename "$orig")"
rm -rf "$TREE"
# shellcheck disable=SC2086
tar -xf "$orig" -C "$SRC_CACHE" $members

# ---------------------------------------------------------------- 4. wmake + lnInclude
(
    set +eu
    unset WM_PROJECT_DIR FOAM_INST_DIR WM_PROJECT WM_PROJECT_VERSION
    # shellcheck disable=SC1091
    . "$TREE/etc/bashrc" || true
    [ -n "$WM_DIR" ] || { echo "OpenFOAM bashrc did not set WM_DIR" >&2; exit 1; }
    log "building wmake tools (WM_OPTIONS=$WM_OPTIONS)"
    "$WM_DIR/src/Allmake" >&2 || exit 1
    for l in $libs; do
        if [ -d "$FOAM_SRC/$l" ]; then
            wmakeLnInclude -u "$FOAM_SRC/$l" >&2 || exit 1
        fi
    done
    # OS layer and the TurbulenceModels / transportModels sub-libraries
    wmakeLnInclude -u "$FOAM_SRC/OSspecific/${WM_OSTYPE:-POSIX}" >&2 || exit 1
    for d in "$FOAM_SRC"/TurbulenceModels/* "$FOAM_SRC"/transportModels/*; do
        if [ -f "$d/Make/files" ]; then wmakeLnInclude -u "$d" >&2 || exit 1; fi
    done
    # headers included by thermoDemFoam (see its Make/options)
    for h in TurbulenceModels/turbulenceModels/lnInclude/turbulenceModel.H \
             TurbulenceModels/incompressible/lnInclude/turbulentTransportModel.H \
             transportModels/incompressible/singlePhaseTransportModel/singlePhaseTransportModel.H
    do
        [ -f "$FOAM_SRC/$h" ] || { echo "missing header $FOAM_SRC/$h" >&2; exit 1; }
    done
    exit 0
) || die "wmake tools / lnInclude failed"

# Debian's libraries linked by thermoDemFoam's Make/options (in /usr/lib or a subfolder)
for l in finiteVolume fvOptions meshTools sampling turbulenceModels \
         incompressibleTurbulenceModels incompressibleTransportModels; do
    found=$(ls /usr/lib/lib$l.so /usr/lib/*/lib$l.so /usr/lib/openfoam*/lib$l.so \
               /usr/lib/openfoam*/*/lib$l.so 2>/dev/null | head -n1 || true)
    [ -n "$found" ] || die "lib$l.so not found under /usr/lib (is Debian's openfoam package complete?)"
done

touch "$STAMP"
log "source tree ready: $TREE"
echo "$TREE"
