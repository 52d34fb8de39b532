# Source me (bash):  . scripts/foam_env.sh
#
# Sets up the OpenFOAM v1912 environment for building and running thermodem's solver.
#   * WM_PROJECT_DIR -> the extracted source tree prepared by scripts/install_openfoam.sh
#     (needed by wmake), or Debian's /usr/share/openfoam when the tree is absent
#     (enough for running blockMesh/decomposePar/the solver).
#   * FOAM_USER_APPBIN / FOAM_USER_LIBBIN -> <project>/build/openfoam/{bin,lib}, put first
#     in PATH / LD_LIBRARY_PATH.
# Honours THERMODEM_CACHE (default ~/.cache/thermodem) and THERMODEM_FOAM_BUILD
# (default <project>/build/openfoam).

_thermodem_root="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd -P)"
_thermodem_tree="${THERMODEM_CACHE:-$HOME/.cache/thermodem}/openfoam-src/openfoam-OpenFOAM-v1912.200626"

# OpenFOAM's bashrc is not 'set -u'/'set -e' clean: relax while sourcing.
_thermodem_opts="$(set +o)"
set +eu
unset WM_PROJECT_DIR FOAM_INST_DIR WM_PROJECT_VERSION
if [ -f "$_thermodem_tree/etc/bashrc" ]; then
    . "$_thermodem_tree/etc/bashrc"
elif [ -f /usr/share/openfoam/etc/bashrc ]; then
    . /usr/share/openfoam/etc/bashrc
else
    echo "foam_env.sh: no OpenFOAM found; run scripts/install_openfoam.sh" >&2
fi
eval "$_thermodem_opts"

export THERMODEM_ROOT="$_thermodem_root"
export THERMODEM_FOAM_BUILD="${THERMODEM_FOAM_BUILD:-$_thermodem_root/build/openfoam}"
export FOAM_USER_APPBIN="$THERMODEM_FOAM_BUILD/bin"
export FOAM_USER_LIBBIN="$THERMODEM_FOAM_BUILD/lib"
export PATH="$FOAM_USER_APPBIN:$PATH"
export LD_LIBRARY_PATH="$FOAM_USER_LIBBIN${LD_LIBRARY_PATH:+:$LD_LIBRARY_PATH}"
unset _thermodem_root _thermodem_tree _thermodem_opts
