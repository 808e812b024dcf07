"""The fused MLP's tile tuner: times the candidate tiles (clrf/mlp/tiling.py) of an MLP shape
on a device with the runtime's interleaved timing (clrf/runtime/measure.py) and caches the
fastest, which every MLP of that shape on that device then uses. On a device that runs the GPU
tiling (GPUs, CLRF_FORCE_GPU_KERNELS=1) it tunes that (``gpu_candidates``, at GPU_SAMPLES
samples a pass: a batch that fills a GPU), elsewhere the CPU register tiles (4,096 samples).

Its command lines take the shapes of the NeRF presets (``python -m clrf.nerf.autotune``) and
of the hash model's (``python -m clrf.hash.autotune``).
"""
from __future__ import annotations

import time
from dataclasses import replace
from pathlib import Path

import numpy as np
import pyopencl.array as cla

from ..runtime.measure import interleaved_medians
from .mlp import MLP
from .tiling import (GPU_FIELDS, MLPTiling, cache_path, candidates, gpu_candidates,
                     store_tiling, tile_fields)


GPU_SAMPLES = 1 << 18   # the GPU tuner's samples a pass: about a hash-model step's


def _inputs(device, spec, n: int):
    """Random inputs and output gradients of n samples (device arrays)."""
    q = device.queue
    rng = np.random.default_rng(0)
    return (cla.to_device(q, rng.random((n, spec.in_dim), np.float32)),
            cla.to_device(q, rng.random((n, spec.dir_dim), np.float32)),
            cla.to_device(q, rng.random(n, np.float32)),
            cla.to_device(q, rng.random((n, 3), np.float32)))


def _fwdbwd(net, x, d, ds, dr):
    """A callable: one forward + backward of net, waited for."""
    def step():
        net.forward(x, d)
        net.backward(ds, dr)
        net.device.queue.finish()
    return step


def time_candidates(device, spec, tiles, n: int = 4096, rounds: int = 5) -> list:
    """Median wall seconds of one forward + backward (n samples) per CPU tile, timed in
    interleaved rounds (each round runs every tile once) after one warm-up each."""
    x, d, ds, dr = _inputs(device, spec, n)
    if getattr(device.tuning, "gpu_kernels", False):   # the CPU tiles, also where the GPU tiling
        device = device.with_tuning(gpu_kernels=False)  # is the default (clrf/mlp/tiling.py)
    nets = [MLP(device, replace(spec, **tile_fields(t))) for t in tiles]
    return interleaved_medians([_fwdbwd(net, x, d, ds, dr) for net in nets], rounds)


def time_gpu_candidates(device, spec, tilings, n: int = GPU_SAMPLES, rounds: int = 5) -> list:
    """[(MLPTiling as built, median seconds of one forward + backward of n samples)] for the
    GPU tilings that build on ``device`` (an MLP halves a work-group its kernels cannot hold:
    duplicates are timed once), timed in interleaved rounds; those that do not build are left
    out."""
    from ..runtime.programs import BuildError
    x, d, ds, dr = _inputs(device, spec, n)
    dev = device.with_tuning(gpu_kernels=True)
    nets = []
    for g in tilings:
        try:
            net = MLP(dev, spec, tiling=MLPTiling(gpu=g))
        except BuildError:
            continue
        if all(net.tiling != other.tiling for other in nets):
            nets.append(net)
    secs = interleaved_medians([_fwdbwd(net, x, d, ds, dr) for net in nets], rounds)
    return [(net.tiling, s) for net, s in zip(nets, secs)]


def tune(device, spec, n: int | None = None, rounds: int = 5, path: Path | None = None):
    """Time the candidates for ``spec`` on ``device`` (the GPU tiling's where the device runs
    it, else the CPU tiles'), cache the fastest and return (best MLPTiling, [(tiling, median
    seconds)]). n: samples a pass (default GPU_SAMPLES for the GPU tiling, else 4,096)."""
    if getattr(device.tuning, "gpu_kernels", False):
        n = GPU_SAMPLES if n is None else int(n)
        timed = time_gpu_candidates(device, spec, gpu_candidates(device.caps), n, rounds)
        if not timed:
            raise RuntimeError("no GPU tiling of the fused MLP builds on this device")
        tiles, secs = [t for t, _ in timed], [s for _, s in timed]
    else:
        n = 4096 if n is None else int(n)
        tiles = candidates(device.caps, spec)
        secs = time_candidates(device, spec, tiles, n, rounds)
    best = min(range(len(tiles)), key=secs.__getitem__)
    store_tiling(device.caps, spec, tiles[best],
                 {"fwdbwd_s": secs[best], "samples": n, "rounds": rounds,
                  "tuned_at": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime())}, path)
    return tiles[best], list(zip(tiles, secs))


def describe(t: MLPTiling) -> str:
    """One line of a tiling's fields (the GPU tiling's, "auto" where the kernel chooses)."""
    if t.gpu is None:
        return (f"rows {t.rows:2d} cols {t.cols} dw_rows {t.dw_rows:2d} dw_cols {t.dw_cols} "
                f"dw_chunk {t.dw_chunk:4d}")
    return " ".join(f"{k} {'auto' if getattr(t.gpu, k) is None else getattr(t.gpu, k)}"
                    for k in GPU_FIELDS)


def tune_command(device_spec, spec, samples, rounds: int, log=print) -> int:
    """The tuner's command line (clrf.nerf.autotune, clrf.hash.autotune): tune ``spec`` on the
    device, print every candidate's time and GFLOP/s, the choice and the cache; 2 on a bad
    device, build failure or bad sizes."""
    import sys
    from ..runtime.device import Device, DeviceError
    from ..runtime.programs import BuildError
    if (samples is not None and samples < 1) or rounds < 1:
        print("clrf: error: --samples and --rounds must be >= 1", file=sys.stderr)
        return 2
    try:
        dev = Device(device_spec)
        best, res = tune(dev, spec, samples, rounds)
    except (DeviceError, BuildError, RuntimeError) as e:
        print(f"clrf: error: {str(e).splitlines()[0]}", file=sys.stderr)
        return 2
    n = samples or (GPU_SAMPLES if best.gpu is not None else 4096)
    flop = spec.flops_per_sample()[1] * n
    log(f"device {dev}; {'GPU tiling' if best.gpu is not None else 'CPU tiles'}, {n} samples")
    for t, s in res:
        mark = "*" if t == best else " "
        log(f"{mark} {describe(t)}: fwd+bwd {s * 1e3:8.2f} ms  {flop / s / 1e9:7.1f} GFLOP/s")
    log(f"cached in {cache_path()}")
    return 0
