#!/usr/bin/env bash
# README command 2: install what the tests need (the test extras, deepinv), then run the suite.
set -euo pipefail
cd "$(dirname "$0")/.."
bash scripts/install.sh test
PY=${PYTHON:-python3}
exec "$PY" -m pytest -q "$@"
