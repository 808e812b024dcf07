#!/usr/bin/env bash
# Set up clrf in ./.venv: a fresh virtual environment, `pip install ".[pocl,EXTRAS]"`, and a
# working OpenCL device. pip's PoCL (3.0, LLVM 14) cannot compile kernels for CPUs newer than
# its LLVM (e.g. AMD Zen 5: "unknown target CPU"); when no device works, this installs the
# distribution's PoCL (Debian/Ubuntu: pocl-opencl-icd), which clrf then picks automatically.
#   bash tools/setup.sh          # runtime only
#   bash tools/setup.sh test     # plus the test dependencies
set -euo pipefail
cd "$(dirname "$0")/.."
extras="pocl${1:+,$1}"
py=${PYTHON:-python3}
rm -rf .venv
"$py" -m venv .venv
.venv/bin/python -m pip install -q --upgrade pip
.venv/bin/python -m pip install -q ".[${extras}]"
probe() { (cd /tmp && "$OLDPWD/.venv/bin/python" -c "import clrf; print('clrf: OpenCL device', clrf.Device())"); }
if ! probe 2>/dev/null; then
    echo "clrf: no working OpenCL device from pip's PoCL; installing the system PoCL" >&2
    sudo=""
    [ "$(id -u)" -ne 0 ] && sudo="sudo"
    if command -v apt-get >/dev/null; then
        $sudo apt-get update -qq && $sudo apt-get install -y -qq pocl-opencl-icd >/dev/null
    else
        echo "clrf: no apt-get here; install your platform's OpenCL CPU driver (PoCL) and rerun" >&2
        exit 1
    fi
    probe
fi
