#!/usr/bin/env bash
# One-step set-up of bimfactor on a fresh Debian/Ubuntu machine with Python 3.11; safe to run again.
#
#   bash tools/setup.sh            (from the repository root, as root or as a user with sudo)
#
# 1. system library libusb-1.0 (Open3D's native library links against it), via apt-get when missing
# 2. .venv with python3 (PYTHON=/path/to/python3.11 to choose another interpreter)
# 3. pip upgraded, torch 2.13.0 installed FIRST (the CPU wheel; an unpinned torch pulls GBs of CUDA
#    packages), then bimfactor itself in editable mode with its dev and ocr extras (pytest, ruff; ONNX
#    Runtime for the door-plate reader), then RapidOCR without its declared dependencies: it asks for the GUI
#    build of OpenCV, which would replace the headless one bimfactor uses (and needs libGL).
set -euo pipefail

cd "$(dirname "${BASH_SOURCE[0]}")/.."
PYTHON="${PYTHON:-python3}"
VENV=".venv"
TORCH_VERSION="2.13.0"
RAPIDOCR_VERSION="1.4.4"

say() { printf '[setup] %s\n' "$*"; }

as_root() {
    if [ "$(id -u)" -eq 0 ]; then
        "$@"
    elif command -v sudo >/dev/null 2>&1; then
        sudo "$@"
    else
        say "need root (or sudo) for: $*" >&2
        exit 1
    fi
}

apt_install() {
    if ! command -v apt-get >/dev/null 2>&1; then
        say "apt-get not found: install $* with your system's package manager" >&2
        exit 1
    fi
    if [ -z "${APT_UPDATED:-}" ]; then
        as_root env DEBIAN_FRONTEND=noninteractive apt-get update -qq
        APT_UPDATED=1
    fi
    as_root env DEBIAN_FRONTEND=noninteractive apt-get install -y -qq --no-install-recommends "$@" >/dev/null
}

# 1. System libraries.
if ! ldconfig -p 2>/dev/null | grep -q 'libusb-1.0'; then
    say "installing libusb-1.0-0"
    apt_install libusb-1.0-0
fi

# 2. Virtual environment.
if ! command -v "$PYTHON" >/dev/null 2>&1; then
    say "$PYTHON not found: install Python 3.11 (Debian: apt-get install python3 python3-venv)" >&2
    exit 1
fi
if ! "$PYTHON" -c 'import sys; sys.exit(0 if sys.version_info >= (3, 11) else 1)'; then
    say "$PYTHON is $("$PYTHON" --version 2>&1); bimfactor needs Python >= 3.11 (set PYTHON=...)" >&2
    exit 1
fi
if [ ! -x "$VENV/bin/python" ]; then
    if ! "$PYTHON" -c 'import ensurepip' >/dev/null 2>&1; then
        say "installing python3-venv (ensurepip is missing)"
        apt_install python3-venv
    fi
    say "creating $VENV with $("$PYTHON" --version 2>&1)"
    "$PYTHON" -m venv "$VENV"
fi

# 3. Python packages.
PIP=("$VENV/bin/python" -m pip --quiet --disable-pip-version-check)
say "upgrading pip"
"${PIP[@]}" install --upgrade pip
say "installing torch==$TORCH_VERSION (CPU wheel)"
"${PIP[@]}" install --progress-bar off "torch==$TORCH_VERSION"
say "installing bimfactor (editable) with dev and ocr extras"
"${PIP[@]}" install --progress-bar off -e '.[dev,ocr]'
say "installing rapidocr-onnxruntime $RAPIDOCR_VERSION (door-plate OCR; its models ship in the wheel)"
"${PIP[@]}" install --progress-bar off --no-deps "rapidocr-onnxruntime==$RAPIDOCR_VERSION"

if "$VENV/bin/python" -m pip list --format=freeze 2>/dev/null | grep -qi '^nvidia-'; then
    say "warning: CUDA packages (nvidia-*) are installed in $VENV; a CPU-only torch was intended" >&2
fi
say "done: $("$VENV/bin/bimfactor" --version | head -n 1)"
