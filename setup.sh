#!/usr/bin/env bash
# One-command set-up: system library for open3d, .venv, CPU torch first, then cpdetect with all extras.
# Idempotent: a re-run with nothing changed only checks a stamp and exits in about a second.
set -euo pipefail
cd "$(dirname "$0")"

# System packages: libusb-1.0-0 (open3d needs it at import) and chromium (the HTML report's browser test).
apt_pkgs=()
ldconfig -p 2>/dev/null | grep -q 'libusb-1.0.so.0' || apt_pkgs+=(libusb-1.0-0)
command -v chromium >/dev/null 2>&1 || apt_pkgs+=(chromium)
if [ ${#apt_pkgs[@]} -gt 0 ]; then
    echo "setup: installing ${apt_pkgs[*]} (apt)"
    SUDO=""; [ "$(id -u)" -ne 0 ] && SUDO="sudo"
    $SUDO apt-get update -qq
    DEBIAN_FRONTEND=noninteractive $SUDO apt-get install -y -qq "${apt_pkgs[@]}" >/dev/null
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
