#!/usr/bin/env bash
# README command 1: install what is needed, then run the end-to-end demo.
set -euo pipefail
cd "$(dirname "$0")/.."
bash scripts/install.sh
PY=${PYTHON:-python3}
exec "$PY" -m hsi_torch demo "$@"
