#!/usr/bin/env bash
# Set up nasa-td3 on a fresh Debian/Ubuntu machine: system GL libraries for
# headless MuJoCo rendering (EGL), a virtualenv in .venv, and the pinned
# Python packages. Safe to run again: it only does what is missing.
set -euo pipefail
cd "$(dirname "$0")/.."

PYTHON=${PYTHON:-python3}
if ! "$PYTHON" -c 'import sys; sys.exit(sys.version_info < (3, 11))'; then
    echo "setup: Python >= 3.11 is needed ($PYTHON is $("$PYTHON" --version 2>&1))" >&2
    exit 1
fi

# Headless rendering needs EGL with Mesa's software renderer (or a GPU driver).
GL_PACKAGES="libegl1 libgl1 libegl-mesa0 libgl1-mesa-dri libgbm1"
if ! ldconfig -p | grep -q 'libEGL.so.1' || ! ldconfig -p | grep -q 'libEGL_mesa.so.0\|libEGL_nvidia.so.0'; then
    if [ "$(id -u)" = 0 ] && command -v apt-get >/dev/null; then
        echo "setup: installing $GL_PACKAGES"
        apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq $GL_PACKAGES
    else
        echo "setup: missing EGL libraries; install them with: sudo apt-get install $GL_PACKAGES" >&2
        exit 1
    fi
fi

# The dashboard's browser test drives the system's Chromium through Playwright (no browser download).
if ! command -v chromium >/dev/null && ! command -v chromium-browser >/dev/null; then
    if [ "$(id -u)" = 0 ] && command -v apt-get >/dev/null; then
        echo "setup: installing chromium"
        apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq chromium
    else
        echo "setup: no chromium: the dashboard's browser test will skip; install it with: sudo apt-get install chromium" >&2
    fi
fi

if [ ! -x .venv/bin/python ]; then
    "$PYTHON" -m venv .venv
fi
# torch is pinned (a CPU build on these machines; an unpinned torch pulls a CUDA build).
.venv/bin/python -m pip install -q --disable-pip-version-check -e '.[dev]'
echo "setup: ready (.venv)"
