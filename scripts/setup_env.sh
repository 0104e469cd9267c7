#!/usr/bin/env bash
# Creates .venv and installs mapkit with its test extras; idempotent and quiet when up to date.
set -euo pipefail
cd "$(dirname "$0")/.."
VENV=${VENV:-.venv}
PYTHON=${PYTHON:-python3}

# open3d's shared library links against libusb-1.0 (Debian: libusb-1.0-0).
if ! ldconfig -p 2>/dev/null | grep -q 'libusb-1.0.so.0'; then
  if [ "$(id -u)" = 0 ] && command -v apt-get >/dev/null; then
    echo "setup: installing Debian package libusb-1.0-0 (needed by open3d)"
    (apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq libusb-1.0-0) >/dev/null
  else
    echo "setup: open3d needs libusb-1.0; run: sudo apt-get install libusb-1.0-0" >&2
    exit 1
  fi
fi

if [ ! -x "$VENV/bin/python" ]; then
  echo "setup: creating $VENV"
  "$PYTHON" -m venv "$VENV"
fi
stamp="$VENV/.mapkit-installed"
hash=$(cat pyproject.toml | sha256sum | cut -c1-16)
if [ -f "$stamp" ] && [ "$(cat "$stamp")" = "$hash" ]; then
  exit 0
fi
echo "setup: installing mapkit and its dependencies into $VENV (first run takes a few minutes)"
# torch first and pinned: the machine's local CPU wheel; a resolver left alone would fetch CUDA builds.
"$VENV/bin/pip" install -q --disable-pip-version-check torch==2.13.0 2>&1 | grep -v "is ignored" || true
"$VENV/bin/pip" install -q --disable-pip-version-check -e ".[test]" 2>&1 | grep -v "is ignored" || true
"$VENV/bin/python" -c "import mapkit, open3d, torch, zarr, rosbags, cyclonedds" || { echo "setup: install failed" >&2; exit 1; }
echo "$hash" > "$stamp"
echo "setup: done"
