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

# Open3D's wheel links libusb-1.0 at import time. The library list is read whole before it is searched: with
# pipefail, `ldconfig -p | grep -q` fails whenever grep stops early and ldconfig dies of SIGPIPE, which made the
# bootstrap "install" a library that was there.
have_libusb() {
  local libs
  libs=$(ldconfig -p 2>/dev/null || true)
  [[ "$libs" == *libusb-1.0.so.0* ]] && return 0
  # no ld.so cache (some containers): look in the usual folders
  compgen -G '/usr/lib*/libusb-1.0.so.0' >/dev/null || compgen -G '/usr/lib/*/libusb-1.0.so.0' >/dev/null \
    || compgen -G '/lib/*/libusb-1.0.so.0' >/dev/null
}
if ! have_libusb; then
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
# pip runs quietly (its full log is thousands of lines): say what comes and how long it took. The duration quoted is
# measured: a fresh .venv took about 5 min on a shared 2-core machine with the wheels cached locally (make demo 4 min
# 48 s in all, issue 50); downloading the wheels adds the download time.
START=$SECONDS
echo "bootstrap: creating $VENV with the pinned versions of constraints.txt: about 5 min on 2 cores with the wheels"
echo "bootstrap: cached, plus their download otherwise; pip is quiet until it is done"
[ -x "$VENV/bin/python" ] || "$PY" -m venv "$VENV"
PIP="$VENV/bin/python -m pip"
# torch first, CPU build unless a GPU is present, so that pip never resolves a multi-GB CUDA build on a CPU machine.
TORCH=$(grep -E '^torch==' constraints.txt)
if ! $VENV/bin/python -c "import torch" 2>/dev/null; then
  echo "bootstrap: [1/2] PyTorch ($TORCH)"
  if ls /opt/wheels/torch-*+cpu-*.whl >/dev/null 2>&1 || command -v nvidia-smi >/dev/null; then
    $PIP install -q "$TORCH"
  else
    $PIP install -q "$TORCH" --index-url https://download.pytorch.org/whl/cpu || $PIP install -q "$TORCH"
  fi
fi
echo "bootstrap: [2/2] mpchair and its dependencies (Open3D, ONNX Runtime, OpenVINO, Rerun, the test tools)"
$PIP install -q -c constraints.txt -e '.[dev,open3d,rerun,ros,deploy]'
echo "$want" > "$STAMP"
took=$((SECONDS - START))
echo "bootstrap: .venv ready ($((took / 60)) min $((took % 60)) s)"
