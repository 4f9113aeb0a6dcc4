#!/usr/bin/env bash
# Set up o3drbf on a fresh Debian machine: system libraries Open3D and
# offscreen rendering need, a .venv, and the Python packages.
# Idempotent: each step is skipped when already done.
set -euo pipefail
cd "$(dirname "$0")/.."

PYTHON=${PYTHON:-python3}
SYSTEM_PACKAGES="libusb-1.0-0 libgomp1 libgl1 libegl1 xvfb"

missing=()
for p in $SYSTEM_PACKAGES; do
  dpkg-query -W -f='${Status}' "$p" 2>/dev/null | grep -q "install ok installed" || missing+=("$p")
done
if [ ${#missing[@]} -gt 0 ]; then
  if [ "$(id -u)" = "0" ] && command -v apt-get >/dev/null 2>&1; then
    echo "setup: installing system packages: ${missing[*]}"
    export DEBIAN_FRONTEND=noninteractive
    apt-get update -qq >/dev/null || echo "setup: 'apt-get update' failed; trying the install anyway"
    apt-get install -y -qq --no-install-recommends "${missing[@]}" >/dev/null \
      || echo "setup: WARNING: could not install ${missing[*]}; Open3D may fail to import (it needs libusb-1.0-0). Install them as root: apt-get install ${missing[*]}"
  else
    echo "setup: WARNING: system packages missing: ${missing[*]}. Not root or no apt-get, so not installing them."
    echo "setup:          Open3D needs libusb-1.0-0; viewer tests need xvfb. Ask an administrator: apt-get install ${missing[*]}"
  fi
fi

if [ ! -x .venv/bin/python ]; then
  echo "setup: creating .venv with $($PYTHON --version)"
  "$PYTHON" -m venv .venv
fi
if [ ! -f .venv/.installed ] || [ pyproject.toml -nt .venv/.installed ]; then
  echo "setup: installing Python packages into .venv (a few minutes the first time)"
  .venv/bin/python -m pip install -q --upgrade pip "setuptools>=77" wheel
  .venv/bin/python -m pip install -q -e ".[test]"
  touch .venv/.installed
fi
.venv/bin/python -c "import open3d, o3drbf" || { echo "setup: ERROR: 'import open3d, o3drbf' failed in .venv (see above)"; exit 1; }
# Compile the Numba kernels into their cache once (again after a source change), so no run pays for it.
if [ ! -f .venv/.warmed ] || [ -n "$(find o3drbf -name '*.py' -newer .venv/.warmed -print -quit)" ]; then
  echo "setup: compiling o3drbf's kernels (once)"
  .venv/bin/python scripts/warm_up.py && touch .venv/.warmed
fi
echo "setup: ready (.venv)"
