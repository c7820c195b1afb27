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
# The viewer tests (napari, Qt) need a virtual X server and Qt's X libraries; on Debian/Ubuntu
# as root they are installed once (skipped when present; elsewhere those tests skip).
if ! command -v Xvfb >/dev/null 2>&1 || ! ldconfig -p 2>/dev/null | grep -q libxcb-icccm.so.4; then
  if [ "$(id -u)" = "0" ] && command -v apt-get >/dev/null 2>&1; then
    echo "[install] Xvfb and Qt's X libraries (for the viewer tests)"
    export DEBIAN_FRONTEND=noninteractive
    { apt-get update -qq && apt-get install -y -qq --no-install-recommends xvfb xauth \
        libgl1 libegl1 libglx-mesa0 libgl1-mesa-dri libxkbcommon-x11-0 libxcb-icccm4 \
        libxcb-image0 libxcb-keysyms1 libxcb-randr0 libxcb-render-util0 libxcb-xinerama0 \
        libxcb-xkb1 libxcb-shape0 libxcb-xfixes0 libfontconfig1 libdbus-1-3 >/dev/null; } \
      || echo "[install] could not install Xvfb; the viewer tests will skip"
  fi
fi
stamp=".install-stamp"
if [ ! -f "$stamp" ] || [ pyproject.toml -nt "$stamp" ] || [ setup.py -nt "$stamp" ] || ! "$PY" -c "import hsi_torch" >/dev/null 2>&1; then
  echo "[install] installing hsi-torch and its dependencies"
  "$PY" -m pip install --quiet -e ".[test]"
  touch "$stamp"
fi
