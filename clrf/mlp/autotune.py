"""The fused MLP's tile tuner: times the candidate tiles (clrf/mlp/tiling.py) of an MLP shape
on a device with the runtime's interleaved timing (clrf/runtime/measure.py) and caches the
fastest, which every MLP of that shape on that device then uses. It tunes the CPU register
tiles; a device that runs the GPU tiling (GPUs, CLRF_FORCE_GPU_KERNELS=1) uses the cached tile
only with CLRF_FORCE_GPU_KERNELS=0.

Its command line takes the shapes of the NeRF presets: ``python -m clrf.nerf.autotune``.
"""
from __future__ import annotations

import time
from dataclasses import replace
from pathlib import Path

import numpy as np
import pyopencl.array as cla

from ..runtime.measure import interleaved_medians
from .mlp import MLP
from .tiling import cache_path, candidates, store_tiling, tile_fields


def time_candidates(device, spec, tiles, n: int = 4096, rounds: int = 5) -> list:
    """Median wall seconds of one forward + backward (n samples) per tile, timed in
    interleaved rounds (each round runs every tile once) after one warm-up each."""
    q = device.queue
    rng = np.random.default_rng(0)
    x = cla.to_device(q, rng.random((n, spec.in_dim), np.float32))
    d = cla.to_device(q, rng.random((n, spec.dir_dim), np.float32))
    ds = cla.to_device(q, rng.random(n, np.float32))
    dr = cla.to_device(q, rng.random((n, 3), np.float32))
    if getattr(device.tuning, "gpu_kernels", False):   # the CPU tiles, also where the GPU tiling
        device = device.with_tuning(gpu_kernels=False)  # is the default (clrf/mlp/tiling.py)
    nets = [MLP(device, replace(spec, **tile_fields(t))) for t in tiles]

    def run(net):
        def step():
            net.forward(x, d)
            net.backward(ds, dr)
            q.finish()
        return step

    return interleaved_medians([run(net) for net in nets], rounds)


def tune(device, spec, n: int = 4096, rounds: int = 5, path: Path | None = None):
    """Time ``candidates`` for ``spec`` on ``device``, cache the fastest and return
    (best MLPTiling, [(tiling, median seconds)])."""
    tiles = candidates(device.caps, spec)
    secs = time_candidates(device, spec, tiles, n, rounds)
    best = min(range(len(tiles)), key=secs.__getitem__)
    store_tiling(device.caps, spec, tiles[best],
                 {"fwdbwd_s": secs[best], "samples": n, "rounds": rounds,
                  "tuned_at": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime())}, path)
    return tiles[best], list(zip(tiles, secs))
