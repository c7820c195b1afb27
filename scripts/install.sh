#!/usr/bin/env bash
# Idempotent set-up used by both README commands: a CPU torch first (so no CUDA build is pulled),
# then this package. An already-installed torch is left alone.
#   bash scripts/install.sh          the demo's needs only: `pip install -e .` (no extras)
#   bash scripts/install.sh test     `pip install -e '.[test]'` (the test extras, deepinv and its
#                                    torchvision, torch held at the installed version), Xvfb for
#                                    the viewer tests
set -euo pipefail
cd "$(dirname "$0")/.."
PY=${PYTHON:-python3}
MODE=${1:-run}
case "$MODE" in
  run | test) ;;
  *) echo "usage: bash scripts/install.sh [test]" >&2; exit 2 ;;
esac
if ! "$PY" -c "import torch" >/dev/null 2>&1; then
  echo "[install] torch not found: installing torch==2.13.0 (CPU build)"
  "$PY" -m pip install --quiet torch==2.13.0
fi
if [ "$MODE" = "test" ]; then
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
  stamp=".install-stamp-test"
  spec=".[test]"
else
  stamp=".install-stamp"
  spec="."
fi
no_deepinv() {  # deepinv is not installed (found, not imported: its torchvision may not import)
  ! "$PY" -c "import importlib.util as u, sys; sys.exit(u.find_spec('deepinv') is None)" 2>/dev/null
}
if [ ! -f "$stamp" ] || [ pyproject.toml -nt "$stamp" ] || [ setup.py -nt "$stamp" ] \
    || ! "$PY" -c "import hsi_torch" >/dev/null 2>&1 || { [ "$MODE" = "test" ] && no_deepinv; }; then
  # torch is held at the installed version by a constraint file: the test extras' deepinv pulls
  # torchvision, and an unconstrained pip would replace a CPU torch with the CUDA build that the
  # newest torchvision requires. (The registry's torchvision for a CPU torch cannot load its
  # compiled operators; the test suite declares the two its import needs: tests/conftest.py.)
  constraints=$(mktemp)
  trap 'rm -f "$constraints"' EXIT
  "$PY" -c "import torch; print('torch==' + torch.__version__.split('+')[0])" >"$constraints"
  echo "[install] installing hsi-torch ($spec; $(cat "$constraints") held)"
  "$PY" -m pip install --quiet -e "$spec" -c "$constraints"
  touch "$stamp"
fi
