#!/usr/bin/env bash
# README command 1: install what the demo needs (this package, no extras), then run the demo.
set -euo pipefail
cd "$(dirname "$0")/.."
bash scripts/install.sh
PY=${PYTHON:-python3}
exec "$PY" -m hsi_torch demo "$@"
