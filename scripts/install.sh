#!/usr/bin/env bash
# Idempotent set-up used by both README commands: a CPU torch first (so no CUDA build is pulled),
# then this package with its dependencies. An already-installed torch is left alone.
set -euo pipefail
cd "$(dirname "$0")/.."
PY=${PYTHON:-python3}
if ! "$PY" -c "import torch" >/dev/null 2>&1; then
  echo "[install] torch not found: installing torch==2.13.0 (CPU build)"
  "$PY" -m pip install --quiet torch==2.13.0
fi
stamp=".install-stamp"
if [ ! -f "$stamp" ] || [ pyproject.toml -nt "$stamp" ] || ! "$PY" -c "import hsi_torch" >/dev/null 2>&1; then
  echo "[install] installing hsi-torch and its dependencies"
  "$PY" -m pip install --quiet -e ".[test]"
  touch "$stamp"
fi
