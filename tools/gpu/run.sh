#!/usr/bin/env bash
# One GPU session's measurements, in plans that share one call's budget (~9 minutes):
#   mlp           (default) the fused MLP's GPU tiling (cl/mlp_gpu.h): the MLP tests (the
#                 device's own tiling, then CLRF_FORCE_GPU_KERNELS=1), tools/nerf_bench.py at
#                 GPU batch sizes after the GPU tiling's tuner on the hash networks
#                 (samples/s and the fraction of the FMA peak of the same run,
#                 the GPU tiling and, at 2^16, the CPU tiles), tools/bench.py's peak, NeRF MLP
#                 and hash cases
#   tests         the grid, hash and splat kernel tests on the GPU (its own kernel shapes), and
#                 the splat and MLP ones with CLRF_FORCE_GPU_KERNELS=0 (the CPU shapes there)
#   hash_lego     clrf train --model hash on lego_400, 300 s, every test view; step profiles
#                 of the bounded step (sizes on the device) and of the host-sized one
#   grid_lego     clrf train (the grid) on lego_400, 180 s, every test view
#   hash_bonsai   clrf train --model hash on bonsai_800 at full resolution, 300 s
#   splat_bonsai  clrf train --model splat on bonsai_800 at full resolution, 600 s, from
#                 gpu-data/bonsai_init.ply; longer than one call: the first call stops the run
#                 with SIGINT at the step's limit (a checkpoint), the next resumes it and
#                 evaluates (the run folder is in gpu-runs/, which a warm machine keeps)
# The training plans read gpu-data/ (tools/gpu/pack.py fills it). Everything goes to $OUT
# (default ./gpu-out); summary.txt lists each step's exit status and seconds.
# tools/gpu/README.md has the set-up (wheels in .whl/, the NVIDIA ICD) and the knobs.
#
#   OUT=/tmp/out bash tools/gpu/run.sh
#   RUN_PLAN=tests,hash_lego OUT=/tmp/out bash tools/gpu/run.sh
#   RUN_DEVICE=pocl RUN_SMOKE=1 OUT=/tmp/o bash tools/gpu/run.sh    # the logic, on a CPU
set -u
ROOT="$(cd "$(dirname "${BASH_SOURCE[0]}")/../.." && pwd)"
cd "$ROOT"
OUT="${OUT:-$ROOT/gpu-out}"
mkdir -p "$OUT"
DEVICE="${RUN_DEVICE:-gpu}"          # CLRF_DEVICE for every step
SMOKE="${RUN_SMOKE:-0}"              # 1: tiny sizes, the GPU tiling forced (a CPU check)
PLAN=",${RUN_PLAN:-mlp},"             # the plans to run, in this order
DATA="${RUN_DATA:-$ROOT/gpu-data}"   # tools/gpu/pack.py's folder
RUNS="${RUN_RUNS:-$ROOT/gpu-runs}"   # training runs (kept between calls on a warm machine)
START=$SECONDS
BUDGET="${RUN_BUDGET_S:-530}"        # seconds for all steps; a step gets at most what is left

log() { echo "[$((SECONDS - START))s] $*" | tee -a "$OUT/summary.txt"; }

# step NAME LIMIT_S CMD...: run CMD (stdout+stderr to $OUT/NAME.txt) under min(LIMIT_S, left)
step() {
    local name="$1" limit="$2"; shift 2
    local left=$((BUDGET - (SECONDS - START)))
    if [ "$left" -lt 15 ]; then
        log "$name: skipped (${left}s of the budget left)"
        return 0
    fi
    [ "$limit" -gt "$left" ] && limit=$left
    local t0=$SECONDS
    timeout --kill-after=10 "$limit" "$@" > "$OUT/$name.txt" 2>&1
    local rc=$?
    log "$name: rc=$rc in $((SECONDS - t0))s (limit ${limit}s)$([ $rc -eq 124 ] && echo ', TIMED OUT')"
    return 0
}

: > "$OUT/summary.txt"
log "clrf GPU run: $(git -C "$ROOT" rev-parse --short HEAD 2>/dev/null || echo '?') \
$(git -C "$ROOT" status --short 2>/dev/null | wc -l) changed files; device '$DEVICE', smoke $SMOKE, \
plans ${PLAN:1:-1}"
plan() { case "$PLAN" in *",$1,"*) return 0 ;; *) return 1 ;; esac; }

# ---- Python: the system's (or $PYTHON) with pyopencl, numpy and pytest, else a venv from .whl/
PY="${PYTHON:-python3}"
need='import pyopencl, numpy, pytest, pytools'
if ! "$PY" -c "$need" 2>/dev/null; then
    if [ -x "$ROOT/.venv/bin/python" ] && "$ROOT/.venv/bin/python" -c "$need" 2>/dev/null; then
        PY="$ROOT/.venv/bin/python"
    elif [ -d "$ROOT/.whl" ]; then
        VENV="${RUN_VENV:-/tmp/clrf-gpu-venv}"
        log "installing from .whl/ into $VENV"
        "$PY" -m venv --system-site-packages "$VENV" >> "$OUT/setup.txt" 2>&1
        "$VENV/bin/python" -m pip install --no-index --find-links "$ROOT/.whl" \
            pyopencl numpy pytest >> "$OUT/setup.txt" 2>&1
        PY="$VENV/bin/python"
        if ! "$PY" -c "$need" >> "$OUT/setup.txt" 2>&1; then
            log "the wheels in .whl/ did not install (setup.txt)"
            exit 1
        fi
    else
        log "no pyopencl/numpy/pytest in $PY and no .whl/ folder: see tools/gpu/README.md"
        exit 1
    fi
fi
export PYTHONPATH="$ROOT${PYTHONPATH:+:$PYTHONPATH}"
export XDG_CACHE_HOME="${XDG_CACHE_HOME:-$OUT/cache}"   # probe and tile caches of this run only
log "python: $("$PY" -c 'import sys, pyopencl as cl, numpy as np
print(sys.version.split()[0], "pyopencl", cl.VERSION_TEXT, "numpy", np.__version__)')"

# ---- NVIDIA's OpenCL driver: an ICD file naming libnvidia-opencl.so.1 where none is registered
if [ -z "${OCL_ICD_VENDORS:-}" ] && ! grep -qsl nvidia /etc/OpenCL/vendors/*.icd; then
    lib=""
    for cand in /usr/local/nvidia/lib64/libnvidia-opencl.so.1 \
                /usr/lib/x86_64-linux-gnu/libnvidia-opencl.so.1 /usr/lib64/libnvidia-opencl.so.1 \
                $(ldconfig -p 2>/dev/null | awk '/libnvidia-opencl.so.1/ {print $NF}'); do
        [ -e "$cand" ] && { lib="$cand"; break; }
    done
    if [ -n "$lib" ]; then
        mkdir -p "$OUT/vendors"
        echo "$lib" > "$OUT/vendors/nvidia.icd"
        export OCL_ICD_VENDORS="$OUT/vendors"
        log "OCL_ICD_VENDORS=$OCL_ICD_VENDORS ($lib)"
    fi
fi
command -v nvidia-smi > /dev/null && nvidia-smi > "$OUT/nvidia_smi.txt" 2>&1
export CLRF_DEVICE="$DEVICE" CLRF_TEST_IMPLS=default CLRF_TEST_SOURCE_TREE=1   # the checkout, on purpose

step devices 60 "$PY" -m clrf.cli devices

# ---- headline: the first call of a session, in the issue's order of priority: the kernel tests
# on the device's own shapes (MLP tiling included), the fused MLP at 2^18 samples, lego_400 hash
# for RUN_HASH_S seconds (default 180) with its step profile (the bounded step and its host share)
if plan headline; then
    KT=(tests/test_mlp_gpu.py tests/test_render.py tests/test_hash_encode.py tests/test_hash_kernels.py
        tests/test_hash_bounded.py tests/test_splat_kernels.py tests/test_sort.py tests/test_scan.py)
    [ "$SMOKE" = 1 ] && KT=(tests/test_mlp_gpu.py::test_small_network_under_every_pass
                            tests/test_sort.py)
    step kernel_tests 170 "$PY" -m pytest -q -p no:cacheprovider -rfE "${KT[@]}"
    if [ "$SMOKE" = 1 ]; then
        NB=(--gpu-samples 256 --repeats 1 --min-sample-s 0.01 --force-gpu-kernels)
    else
        NB=(--gpu-samples 262144 --repeats 3)
    fi
    step nerf_bench_2e18 70 "$PY" tools/nerf_bench.py --gpu-sizes "${NB[@]}" \
        --out "$OUT/nerf_bench_2e18.json"
fi

# ---- mlp: the MLP tests on the device's own tiling (the GPU tiling on a GPU), then forced by
# the environment; tools/nerf_bench.py at GPU sizes; tools/bench.py's cases of the earlier runs
if plan mlp; then
    TESTS=(tests/test_mlp_gpu.py tests/test_nerf_mlp.py)
    if [ "$SMOKE" = 1 ]; then
        TESTS=(tests/test_mlp_gpu.py::test_small_network_under_every_pass
               "tests/test_mlp_gpu.py::test_matches_reference_at_awkward_batches"
               tests/test_nerf_mlp.py::test_forward_matches_reference)
    fi
    step tests_native 120 "$PY" -m pytest -q -p no:cacheprovider "${TESTS[@]}"
    CLRF_FORCE_GPU_KERNELS=1 step tests_forced 90 "$PY" -m pytest -q -p no:cacheprovider "${TESTS[@]}"
    # the device's tiling at 2^16, 2^18, 2^20; the CPU tiles at 2^16 beside it (on the H100
    # they ran at 0.8 % of the FMA peak)
    if [ "$SMOKE" = 1 ]; then
        NB=(--gpu-samples 256 --repeats 1 --min-sample-s 0.01 --force-gpu-kernels)
        NB_CPU=(--gpu-samples 256 --repeats 1 --min-sample-s 0.01)
    else
        NB=(--repeats 5)
        NB_CPU=(--gpu-samples 65536 --repeats 3)
    fi
    # the tuner on the GPU tiling (the hash model's networks, 2^18 samples): its table of
    # candidates against the default, and the cache ($OUT/cache) this call's later steps read
    if [ "$SMOKE" = 1 ]; then
        CLRF_FORCE_GPU_KERNELS=1 step tune_hash 150 "$PY" -m clrf.hash.autotune --preset tiny \
            --samples 256 --rounds 1
    else
        step tune_hash 90 "$PY" -m clrf.hash.autotune --rounds 5
    fi
    cp "$XDG_CACHE_HOME/clrf/mlp_tiling.json" "$OUT/" 2> /dev/null
    step nerf_bench_gpu 150 "$PY" tools/nerf_bench.py --gpu-sizes "${NB[@]}" --out "$OUT/nerf_bench_gpu.json"
    step nerf_bench_cpu_tiles 45 "$PY" tools/nerf_bench.py --gpu-sizes --tilings cpu \
        --gpu-configs small-4x64,hash-1x64-c2 "${NB_CPU[@]}" --out "$OUT/nerf_bench_cpu_tiles.json"
    if [ "$SMOKE" = 1 ]; then
        CLRF_FORCE_GPU_KERNELS=1 step bench 60 "$PY" tools/bench.py --device "$DEVICE" --quick \
            --only 'peak/fma' --only 'nerf/mlp/small-4x64/*' --out "$OUT/bench.json"
    else
        step bench 90 "$PY" tools/bench.py --device "$DEVICE" --only 'peak/*' --only 'nerf/mlp/*' \
            --only 'hash*' --only 'grid.gpu/*' --only 'splat.raster.clrf/*' --max-seconds 3 \
            --out "$OUT/bench.json"
    fi
fi

# ---- tests: the kernel tests of the grid, the hash model and splatting on the device's own
# shapes, then the splat rasteriser's and the MLP's CPU shapes on the same device
if plan tests; then
    KT=(tests/test_render.py tests/test_grid_ops.py tests/test_hash_encode.py
        tests/test_hash_kernels.py tests/test_splat_kernels.py tests/test_splat_loss.py
        tests/test_sort.py tests/test_scan.py tests/test_hash_bounded.py)
    [ "$SMOKE" = 1 ] && KT=(tests/test_sort.py tests/test_splat_kernels.py -k "binning or no_gaussians")
    step kernel_tests 240 "$PY" -m pytest -q -p no:cacheprovider "${KT[@]}"
    CLRF_FORCE_GPU_KERNELS=0 step kernel_tests_cpu_shapes 120 "$PY" -m pytest -q \
        -p no:cacheprovider tests/test_splat_kernels.py tests/test_nerf_mlp.py \
        $([ "$SMOKE" = 1 ] && echo "-k binning")
fi

# ---- training plans: train_run NAME LIMIT_S ARGS...: clrf train into $RUNS/NAME (resumed
# when a checkpoint is there), stopped with SIGINT at the limit (it saves a checkpoint); the
# run's small files are copied to $OUT/NAME_*
train_run() {
    local name="$1" limit="$2"; shift 2
    local dir="$RUNS/$name" left=$((BUDGET - (SECONDS - START)))
    [ "$limit" -gt "$left" ] && limit=$left
    if [ "$limit" -lt 60 ]; then
        log "$name: skipped (${left}s of the budget left)"
        return 0
    fi
    mkdir -p "$RUNS"
    if [ -f "$dir/ckpt.npz" ]; then
        set -- --out "$dir" --resume
        log "$name: resuming the run in $dir"
    else
        set -- --out "$dir" "$@"
    fi
    step "$name" "$limit" timeout -s INT -k 15 "$((limit - 20))" \
        "$PY" -m clrf.cli --device "$DEVICE" train "$@"
    for f in eval.json metrics.csv config.json error_vs_time.png; do
        [ -f "$dir/$f" ] && cp "$dir/$f" "$OUT/${name}_$f"
    done
    [ -f "$dir/eval.json" ] || log "$name: no eval.json yet (resume it: the same plan again)"
}
need_data() {
    [ -e "$DATA/$1" ] && return 0
    log "$2: skipped, no $DATA/$1 (python tools/gpu/pack.py $2)"
    return 1
}
SECS() { [ "$SMOKE" = 1 ] && echo 10 || echo "$1"; }
SMALL=()    # smoke runs on a CPU: small images
[ "$SMOKE" = 1 ] && SMALL=(--set train.downscale=8 --set train.eval_downscale=2)

if plan headline && need_data lego_400 headline; then
    train_run hash_lego_180 "$(( ${RUN_HASH_S:-180} + 90 ))" --model hash --data "$DATA/lego_400" \
        --max-seconds "$(SECS "${RUN_HASH_S:-180}")" "${SMALL[@]}"
    [ -f "$RUNS/hash_lego_180/ckpt.npz" ] && step profile_hash_lego_bounded_on 40 "$PY" \
        tools/profile_step.py --ckpt "$RUNS/hash_lego_180" --device "$DEVICE" --steps 40 \
        --bounded on --json "$OUT/profile_hash_lego_bounded_on.json"
fi
if plan hash_lego && need_data lego_400 hash_lego; then
    train_run hash_lego 480 --model hash --data "$DATA/lego_400" --max-seconds "$(SECS 300)" "${SMALL[@]}"
    # the bounded step (sizes on the device: the GPU default) and the host-sized one
    for b in on off; do
        [ -f "$RUNS/hash_lego/ckpt.npz" ] && step "profile_hash_lego_bounded_$b" 45 "$PY" \
            tools/profile_step.py --ckpt "$RUNS/hash_lego" --device "$DEVICE" --steps 40 \
            --bounded "$b" --json "$OUT/profile_hash_lego_bounded_$b.json"
    done
fi
if plan grid_lego && need_data lego_400 grid_lego; then
    train_run grid_lego 360 --data "$DATA/lego_400" --max-seconds "$(SECS 180)" "${SMALL[@]}"
fi
if plan hash_bonsai && need_data bonsai_800 hash_bonsai; then
    train_run hash_bonsai 480 --model hash --data "$DATA/bonsai_800" --max-seconds "$(SECS 300)" "${SMALL[@]}"
fi
if plan splat_bonsai && need_data bonsai_init.ply splat_bonsai; then
    train_run splat_bonsai 500 --model splat --data "$DATA/bonsai_800" \
        --set "splat.init_ply=$DATA/bonsai_init.ply" --max-seconds "$(SECS 600)" "${SMALL[@]}"
fi

log "done in $((SECONDS - START))s; files in $OUT"
