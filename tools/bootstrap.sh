#!/usr/bin/env bash
# Create/refresh .venv with the pinned, tested versions. Idempotent: a second run only checks a stamp.
# Usage: tools/bootstrap.sh [PYTHON]
set -euo pipefail
cd "$(dirname "$0")/.."
PY=${1:-python3}
VENV=.venv
STAMP=$VENV/.mpchair-installed
# The stamp records what was installed; a change to either input file reinstalls.
want=$(cat pyproject.toml constraints.txt | sha256sum | cut -c1-16)

# Open3D's wheel links libusb-1.0 at import time.
if ! ldconfig -p 2>/dev/null | grep -q 'libusb-1.0.so.0'; then
  if [ "$(id -u)" = 0 ] && command -v apt-get >/dev/null; then
    echo "bootstrap: installing the system library libusb-1.0-0 (needed by Open3D)"
    apt-get install -y -qq libusb-1.0-0 >/dev/null 2>&1 || { apt-get update -qq >/dev/null 2>&1 && apt-get install -y -qq libusb-1.0-0 >/dev/null 2>&1; } \
      || echo "bootstrap: could not install libusb-1.0-0; Open3D features will be unavailable"
  else
    echo "bootstrap: Open3D needs libusb-1.0: run 'sudo apt-get install libusb-1.0-0' (Open3D features fail clearly until then)"
  fi
fi

if [ -f "$STAMP" ] && [ "$(cat "$STAMP")" = "$want" ]; then
  exit 0
fi
[ -x "$VENV/bin/python" ] || "$PY" -m venv "$VENV"
PIP="$VENV/bin/python -m pip"
# torch first, CPU build unless a GPU is present, so that pip never resolves a multi-GB CUDA build on a CPU machine.
TORCH=$(grep -E '^torch==' constraints.txt)
if $VENV/bin/python -c "import torch" 2>/dev/null; then
  :
elif ls /opt/wheels/torch-*+cpu-*.whl >/dev/null 2>&1 || command -v nvidia-smi >/dev/null; then
  $PIP install -q "$TORCH"
else
  $PIP install -q "$TORCH" --index-url https://download.pytorch.org/whl/cpu || $PIP install -q "$TORCH"
fi
$PIP install -q -c constraints.txt -e '.[dev,open3d,rerun,ros,deploy]'
echo "$want" > "$STAMP"
echo "bootstrap: .venv ready"
