#!/usr/bin/env bash
# One-command set-up: system library for open3d, .venv, CPU torch first, then cpdetect with all extras.
# Idempotent: a re-run with nothing changed only checks a stamp and exits in about a second.
set -euo pipefail
cd "$(dirname "$0")"

need_libusb() { ! ldconfig -p 2>/dev/null | grep -q 'libusb-1.0.so.0'; }
if need_libusb; then
    echo "setup: installing libusb-1.0-0 (needed by open3d)"
    SUDO=""; [ "$(id -u)" -ne 0 ] && SUDO="sudo"
    $SUDO apt-get update -qq
    DEBIAN_FRONTEND=noninteractive $SUDO apt-get install -y -qq libusb-1.0-0 >/dev/null
fi

PY="${PYTHON:-python3}"
[ -x .venv/bin/python ] || "$PY" -m venv .venv

stamp=.venv/.cpdetect-setup
want="$(cat pyproject.toml setup.sh | sha256sum | cut -d' ' -f1)"
if [ -f "$stamp" ] && [ "$(cat "$stamp")" = "$want" ] && .venv/bin/python -c "import cpdetect" 2>/dev/null; then
    echo "setup: up to date"
    exit 0
fi

export PIP_DISABLE_PIP_VERSION_CHECK=1
# torch first and pinned: an unpinned torch would pull several GB of CUDA packages.
.venv/bin/pip install -q "torch==2.13.0"
.venv/bin/pip install -q -e ".[learned,dask,dev]"
echo "$want" > "$stamp"
echo "setup: done"
