#!/usr/bin/env bash
# Set up clrf in ./.venv: a fresh virtual environment, `pip install ".[pocl,EXTRAS]"`, and the
# fastest OpenCL device this machine can have. clrf probes every device once and picks the one
# that measures fastest (`clrf devices`). pip's PoCL (3.0, LLVM 14) either cannot compile for
# CPUs newer than its LLVM (AMD Zen 5: "unknown target CPU") or, on some CPUs, compiles for a
# generic x86-64 target that runs about ten times slower than the distribution's PoCL. In both
# cases this installs the distribution's PoCL (Debian/Ubuntu: pocl-opencl-icd, with `sudo -n`
# when not root), probes again and prints the device clrf now picks.
#   bash tools/setup.sh          # runtime only
#   bash tools/setup.sh test     # plus the test dependencies
# Non-interactive. Exit status 0 when a working device exists (possibly a slow one, with the
# advice printed), 1 when none works.
set -euo pipefail
cd "$(dirname "$0")/.."
extras="pocl${1:+,$1}"
py=${PYTHON:-python3}
rm -rf .venv
"$py" -m venv .venv
.venv/bin/python -m pip install -q --upgrade pip
.venv/bin/python -m pip install -q ".[${extras}]"

# `clrf devices --check` prints the default device and its probe figure; exit 0: fine,
# 3: the best device is a slow driver, anything else: no working device. Run outside the
# checkout so the installed package is what is checked.
check() { (cd /tmp && env -u CLRF_DEVICE "$OLDPWD/.venv/bin/python" -m clrf.cli devices --check); }
status=0
check || status=$?
if [ "$status" -ne 0 ]; then
    if [ "$status" -eq 3 ]; then
        echo "clrf: the best OpenCL device is a slow driver; installing the distribution's PoCL" >&2
    else
        echo "clrf: no working OpenCL device; installing the distribution's PoCL" >&2
    fi
    sudo=""
    if [ "$(id -u)" -ne 0 ]; then sudo="sudo -n"; fi
    if ! command -v apt-get >/dev/null; then
        echo "clrf: no apt-get here; install your distribution's PoCL (or another OpenCL CPU" \
             "driver) and rerun" >&2
    elif [ -n "$sudo" ] && ! sudo -n true 2>/dev/null; then
        echo "clrf: not root and sudo needs a password; run" \
             "\`sudo apt-get install pocl-opencl-icd\` and rerun" >&2
    elif $sudo env DEBIAN_FRONTEND=noninteractive apt-get update -qq &&
         $sudo env DEBIAN_FRONTEND=noninteractive apt-get install -y -qq pocl-opencl-icd >/dev/null; then
        status=0
        check || status=$?
    else
        echo "clrf: apt-get install pocl-opencl-icd failed" >&2
    fi
fi
if [ "$status" -ne 0 ] && [ "$status" -ne 3 ]; then
    exit 1
fi
