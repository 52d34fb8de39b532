#!/usr/bin/env bash
# Install what is missing (scripts/setup.sh) and run the test suite.
set -euo pipefail
ROOT="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd -P)"
cd "$ROOT"
bash scripts/setup.sh
exec "${PYTHON:-python3}" -m pytest -q tests "$@"
