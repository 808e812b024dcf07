#!/usr/bin/env bash
# Set up clrf in ./.venv: `pip install ".[pocl,EXTRAS]"` into the virtual environment (made
# when there is none, or anew with --fresh), and the fastest OpenCL device this machine can
# have. Extras add up: `setup.sh test` then `setup.sh view` leaves both installed (the venv
# records what it holds in .venv/clrf-setup.txt), and a call that would install nothing new
# (the same extras, the same clrf source) installs nothing. clrf probes every device once and picks the one
# that measures fastest (`clrf devices`). pip's PoCL (3.0, LLVM 14) either cannot compile for
# CPUs newer than its LLVM (AMD Zen 5: "unknown target CPU") or, on some CPUs, compiles for a
# generic x86-64 target that runs about ten times slower than the distribution's PoCL. In both
# cases this installs the distribution's PoCL (Debian/Ubuntu: pocl-opencl-icd, with `sudo -n`
# when not root), probes again and prints the device clrf now picks.
#   bash tools/setup.sh          # runtime only
#   bash tools/setup.sh test     # plus the test dependencies
#   bash tools/setup.sh test,mpi # plus mpi4py for `mpirun -n N clrf train`; installs Debian's
#                                # Open MPI first (openmpi-bin libopenmpi-dev) when mpicc or
#                                # mpirun is missing
#   bash tools/setup.sh intel    # plus Intel's oneAPI OpenCL CPU runtime, from PyPI into the
#                                # venv, registered for the venv's Python only (clrf/runtime/icd.py:
#                                # no root, no system file changed, the system's drivers stay)
#   bash tools/setup.sh impls    # plus Mesa's rusticl and the Oclgrind simulator (Debian
#                                # mesa-opencl-icd oclgrind), the other implementations the
#                                # tests run every kernel on when present
#   bash tools/setup.sh gpucc    # plus the offline GPU compilers of tools/gpu_builds.py
#                                # (every kernel built for AMD, Intel and NVIDIA GPUs, no GPU
#                                # needed): Debian's clang-19, libclc-19's bitcode unpacked
#                                # into .gpucc/ (not installed: the package would remove
#                                # mesa-opencl-icd, whose rusticl needs libclc-15) and Intel's
#                                # ocloc (intel-opencl-icd, or intel-ocloc where it is split
#                                # off); NVIDIA's ptxas is used when the CUDA toolkit has it
#   bash tools/setup.sh view      # plus the web viewer (`clrf view`, `clrf train --view`)
#   bash tools/setup.sh view,test # plus headless Chromium for the viewer's browser test:
#                                # Debian's chromium and chromium-driver when chromium or
#                                # chromedriver is missing (Selenium drives it; no download)
#   bash tools/setup.sh web      # plus viser's web client for `clrf export --web DIR` (a
#                                # static page of a splat scene); web,test: headless Chromium
#                                # too (as view,test), for that page's browser test
#   bash tools/setup.sh eval     # plus LPIPS for `clrf eval`: torch ($CLRF_TORCH, default
#                                # torch==2.13.0) and the lpips package's weight files, installed
#                                # without lpips's torchvision, which clrf does not use
#   bash tools/setup.sh process  # plus pycolmap and imageio-ffmpeg for `clrf process` (pose a
#                                # video or a folder of photos); PyPI wheels, no system package
#   bash tools/setup.sh test,peers # plus taichi for the Taichi peers of tools/bench.py
#   bash tools/setup.sh --fresh test # a new .venv with exactly these extras
# Non-interactive. Exit status 0 when a working device exists (possibly a slow one, with the
# advice printed), 1 when none works.
set -euo pipefail
cd "$(dirname "$0")/.."
fresh=0
if [ "${1:-}" = "--fresh" ]; then fresh=1; shift; fi
if [ "${2:-}" = "--fresh" ]; then fresh=1; set -- "$1"; fi
py=${PYTHON:-python3}
# what an existing venv already holds (its extras, and the stamp of the source it was
# installed from); --fresh or no usable venv: nothing
record=.venv/clrf-setup.txt
had_extras="" had_stamp=""
if [ "$fresh" -eq 0 ] && [ -x .venv/bin/python ] && [ -f "$record" ]; then
    { read -r had_extras; read -r had_stamp; } < "$record" || true
fi
# the extras asked for now plus those installed before, each once
all_extras=""
IFS=, read -ra asked <<< "${had_extras:+$had_extras,}${1:-}"
for e in "${asked[@]}"; do
    case ",$all_extras," in *",$e,"*) ;; *) [ -n "$e" ] && all_extras="${all_extras:+$all_extras,}$e" ;; esac
done
set -- "$all_extras"
extras="pocl${1:+,$1}"
# extra "eval" is installed on its own after the others (see below), not through pip's extras
want_eval=0
case ",${1:-}," in *,eval,*) want_eval=1 ;; esac
extras=",${extras},"
extras=${extras//,eval,/,}
extras=${extras#,}
extras=${extras%,}

sudo=""
if [ "$(id -u)" -ne 0 ]; then sudo="sudo -n"; fi
# apt_install WHAT PKG...: install distribution packages without prompting (sudo -n when not
# root); prints why not and returns 1 when it cannot. WHAT names them for the message.
apt_install() {
    local what=$1
    shift
    if ! command -v apt-get >/dev/null; then
        echo "clrf: no apt-get here; install $what and rerun" >&2
        return 1
    elif [ -n "$sudo" ] && ! sudo -n true 2>/dev/null; then
        echo "clrf: not root and sudo needs a password; run" \
             "\`sudo apt-get install $*\` and rerun" >&2
        return 1
    elif $sudo env DEBIAN_FRONTEND=noninteractive apt-get update -qq &&
         $sudo env DEBIAN_FRONTEND=noninteractive apt-get install -y -qq "$@" >/dev/null; then
        return 0
    fi
    echo "clrf: apt-get install $* failed" >&2
    return 1
}

# extra "mpi": mpi4py is built against the system's MPI, so that comes first
case ",${1:-}," in
    *,mpi,*)
        if ! command -v mpicc >/dev/null || ! command -v mpirun >/dev/null; then
            echo "clrf: extra 'mpi': installing Open MPI (openmpi-bin libopenmpi-dev)" >&2
            apt_install "an MPI library with mpicc and mpirun (Open MPI, MPICH)" \
                openmpi-bin libopenmpi-dev || exit 1
        fi ;;
esac

# extra "impls": the other OpenCL implementations the tests check the kernels on
case ",${1:-}," in
    *,impls,*)
        if [ ! -e /etc/OpenCL/vendors/rusticl.icd ] || ! command -v oclgrind >/dev/null; then
            echo "clrf: extra 'impls': installing Mesa's rusticl and Oclgrind" \
                 "(mesa-opencl-icd oclgrind)" >&2
            apt_install "Mesa's OpenCL and Oclgrind" mesa-opencl-icd oclgrind || exit 1
        fi ;;
esac
extras=${extras//,impls/}
# extra "gpucc": offline compilers for AMD, Intel and NVIDIA GPUs (tools/gpu_builds.py)
case ",${1:-}," in
    *,gpucc,*)
        gpucc_pkgs=""
        command -v clang-19 >/dev/null || gpucc_pkgs="clang-19"
        if ! command -v ocloc >/dev/null; then
            # newer Debian/Ubuntu ship ocloc on its own (intel-ocloc); bookworm in the ICD
            if apt-cache show intel-ocloc >/dev/null 2>&1; then
                gpucc_pkgs="$gpucc_pkgs intel-ocloc"
            else
                gpucc_pkgs="$gpucc_pkgs intel-opencl-icd"
            fi
        fi
        if [ -n "$gpucc_pkgs" ]; then
            echo "clrf: extra 'gpucc': installing$( printf ' %s' $gpucc_pkgs )" >&2
            # shellcheck disable=SC2086
            apt_install "clang-19 and Intel's ocloc" $gpucc_pkgs || exit 1
        fi
        clc=.gpucc/libclc
        if [ ! -e "$clc/usr/lib/clc/gfx1100-amdgcn-mesa-mesa3d.bc" ]; then
            echo "clrf: extra 'gpucc': unpacking libclc-19's bitcode into $clc" >&2
            tmp=$(mktemp -d)
            # apt-get download runs as the calling user and writes into the current folder
            if ! (cd "$tmp" && apt-get download libclc-19 >/dev/null); then
                echo "clrf: apt-get download libclc-19 failed" >&2
                rm -rf "$tmp"
                exit 1
            fi
            rm -rf "$clc"
            mkdir -p "$clc"
            dpkg-deb -x "$tmp"/libclc-19_*.deb "$clc"
            rm -rf "$tmp"
        fi ;;
esac
extras=${extras//,gpucc/}
# extras "view" or "web" with "test": the browser tests need a system Chromium and its driver
case ",${1:-}," in
    *,view,*|*,web,*)
        case ",${1:-}," in
            *,test,*)
                if ! { command -v chromium >/dev/null || command -v chromium-browser >/dev/null; } ||
                   ! command -v chromedriver >/dev/null; then
                    echo "clrf: extras '${1}': installing headless Chromium" \
                         "(chromium chromium-driver) for the browser tests" >&2
                    apt_install "Chromium and its WebDriver (chromium, chromedriver)" \
                        chromium chromium-driver || exit 1
                fi ;;
        esac ;;
esac

# a stamp of what pip would install: the extras, the
# Python and every file of the package's source. The same stamp as the venv's record: nothing
# to install. (Standard library only; an empty stamp always installs.)
stamp=$("$py" -c '
import hashlib, pathlib, sys
h = hashlib.sha256(("|".join(sorted(set(filter(None, sys.argv[1].split(","))))) + sys.version).encode())
for top in ("setup.cfg", "setup.py", "pyproject.toml", "README.md", "clrf", "cl"):
    p = pathlib.Path(top)
    for f in sorted([p] if p.is_file() else p.rglob("*")):
        if f.is_file() and "__pycache__" not in f.parts and f.name != "_build_commit.py":
            h.update(str(f).encode() + b"\0" + f.read_bytes())
print(h.hexdigest())' "$all_extras" 2>/dev/null) || stamp=""
new_venv=0
if [ "$fresh" -eq 1 ] || [ ! -x .venv/bin/python ]; then
    rm -rf .venv
    "$py" -m venv .venv
    new_venv=1
fi
if [ "$new_venv" -eq 1 ] || [ -z "$stamp" ] || [ "$stamp" != "$had_stamp" ]; then
    if [ "$new_venv" -eq 1 ]; then
        .venv/bin/python -m pip install -q --upgrade pip
    fi
    .venv/bin/python -m pip install -q ".[${extras}]"
    case ",${1:-}," in
        *,intel,*) .venv/bin/python -m clrf.runtime.icd register ;;
    esac
    rm -f "$record"          # written again once everything asked for is in
else
    echo "clrf: .venv already holds clrf with extras '${all_extras:-none}'; nothing to install" >&2
fi
if [ "$want_eval" -eq 1 ] && ! .venv/bin/python -c "import torch, lpips" >/dev/null 2>&1; then
    # LPIPS: clrf builds AlexNet / VGG-16 itself with torch, so torch (a CPU build is enough)
    # and the lpips package's linear-layer weights are all it needs. torch==2.13.0 is the CPU
    # wheel (191 MB, about 830 MB installed) that this project's machines keep on disk; from
    # PyPI elsewhere it is a CUDA build of several GB: set CLRF_TORCH to a torch already at
    # hand. The backbones' ImageNet weights are never downloaded (docs/evaluation.md).
    .venv/bin/python -m pip install -q "${CLRF_TORCH:-torch==2.13.0}"
    .venv/bin/python -m pip install -q --no-deps "lpips==0.1.4"
fi
if [ "$want_eval" -eq 1 ] && ! .venv/bin/python -c "import gsplat.exporter" >/dev/null 2>&1; then
    # gsplat's exporter writes the compressed PLY and .splat that tests/test_splat_compressed.py
    # reads (files clrf did not write); it needs torch and numpy only, no CUDA or compiler, so
    # gsplat goes in without its other dependencies (jaxtyping, rich, ninja: its CUDA build's)
    .venv/bin/python -m pip install -q --no-deps "gsplat==1.5.3"
fi

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
    if apt_install "your distribution's PoCL (or another OpenCL CPU driver)" pocl-opencl-icd; then
        # the venv's own vendors folder (extra 'intel') links the system's .icd files that
        # existed when it was written: write it again so the new PoCL is seen
        case ",${1:-}," in
            *,intel,*) .venv/bin/python -m clrf.runtime.icd register ;;
        esac
        status=0
        check || status=$?
    fi
fi
# still no fast driver (no apt-get here, or no root): Intel's CPU runtime comes from PyPI and
# runs clrf's kernels on Intel and AMD CPUs alike; clrf picks it where it measures faster
case ",${1:-}," in
    *,intel,*) ;;
    *)
        if [ "$status" -ne 0 ]; then
            echo "clrf: trying Intel's CPU runtime from PyPI (extra 'intel')" >&2
            if .venv/bin/python -m pip install -q ".[pocl,intel]" &&
               .venv/bin/python -m clrf.runtime.icd register; then
                status=0
                check || status=$?
            fi
        fi ;;
esac
if [ "$status" -ne 0 ] && [ "$status" -ne 3 ]; then
    exit 1
fi
if [ -n "$stamp" ]; then
    printf '%s\n%s\n' "$all_extras" "$stamp" > "$record"
fi
