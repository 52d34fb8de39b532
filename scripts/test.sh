#!/usr/bin/env bash
# Install what is missing (scripts/setup.sh) and run the test suite on the machine's cores in
# parallel: one pytest-xdist worker per usable core (THERMODEM_TEST_WORKERS=N to choose, 0 for one
# process), each test module on one worker so that its module fixtures are computed once
# (--dist loadscope); the 20 slowest tests are listed at the end. Extra arguments go to pytest, e.g. `bash scripts/test.sh -k restart`.
set -euo pipefail
ROOT="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd -P)"
cd "$ROOT"
# the set-up's compile, when it starts from an empty cache, leaves a hard-linked copy of what it
# compiled here for tests/test_compile.py (scripts/setup.sh); removed at exit
SETUP_COPY="$(mktemp -d "${TMPDIR:-/tmp}/thermodem-setup-cache.XXXXXX")"
trap 'rm -rf "$SETUP_COPY"' EXIT
THERMODEM_SETUP_CACHE_COPY="$SETUP_COPY/cache" bash scripts/setup.sh
export THERMODEM_TEST_SETUP_CACHE="$SETUP_COPY/cache"
PY="${PYTHON:-python3}"
WORKERS="${THERMODEM_TEST_WORKERS:-$("$PY" -c 'import os; print(len(os.sched_getaffinity(0)))')}"
if [ "$WORKERS" = 0 ]; then
    "$PY" -m pytest -q --durations=20 tests "$@"; exit $?
fi
"$PY" -m pytest -q -n "$WORKERS" --dist loadscope --durations=20 tests "$@"
