"""The fused MLP's tile tuner: times the candidate tiles (clrf/nerf/tiling.py) of an MLP shape
on a device with the runtime's interleaved timing (clrf/runtime/measure.py) and caches the
fastest, which every MLP of that shape on that device then uses.

    python -m clrf.nerf.autotune --preset tiny      # the shape `clrf train --model nerf` builds
    python -m clrf.nerf.autotune --width 256 --depth 8 --skip 4 --color-width 128 --in-dim 63 \\
        --dir-dim 27     # times the candidates, prints them, caches the best
"""
from __future__ import annotations

import argparse
import sys
import time
from dataclasses import asdict, replace
from pathlib import Path

import numpy as np
import pyopencl.array as cla

from ..runtime.measure import interleaved_medians
from .mlp import MLP
from .tiling import cache_path, candidates, store_tiling


def time_candidates(device, spec, tiles, n: int = 4096, rounds: int = 5) -> list:
    """Median wall seconds of one forward + backward (n samples) per tile, timed in
    interleaved rounds (each round runs every tile once) after one warm-up each."""
    q = device.queue
    rng = np.random.default_rng(0)
    x = cla.to_device(q, rng.random((n, spec.in_dim), np.float32))
    d = cla.to_device(q, rng.random((n, spec.dir_dim), np.float32))
    ds = cla.to_device(q, rng.random(n, np.float32))
    dr = cla.to_device(q, rng.random((n, 3), np.float32))
    nets = [MLP(device, replace(spec, **asdict(t))) for t in tiles]

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


def main(argv=None) -> int:
    from ..runtime.device import Device, DeviceError
    ap = argparse.ArgumentParser(prog="python -m clrf.nerf.autotune",
                                 description="Time fused-MLP tiles on a device; cache the best.")
    ap.add_argument("--device", default=None, help="'cpu', 'gpu', 'P:D' or an implementation ('pocl', 'intel', ...; default CLRF_DEVICE)")
    ap.add_argument("--preset", default="original", choices=("tiny", "original"),
                    help="the NeRF preset whose MLP shape to tune (the flags below override it); "
                         "'tiny' is what `clrf train --model nerf` uses by default")
    ap.add_argument("--width", type=int, default=None)
    ap.add_argument("--depth", type=int, default=None)
    ap.add_argument("--skip", type=int, default=None, help="-1: no skip connection")
    ap.add_argument("--color-width", type=int, default=None)
    ap.add_argument("--in-dim", type=int, default=None, help="encoded position dims")
    ap.add_argument("--dir-dim", type=int, default=None, help="encoded direction dims")
    ap.add_argument("--hidden-act", default=None, choices=("relu", "softplus"))
    ap.add_argument("--sigma-act", default=None, choices=("relu", "softplus"))
    ap.add_argument("--samples", type=int, default=4096, help="samples per timed pass")
    ap.add_argument("--rounds", type=int, default=5, help="interleaved timing rounds")
    a = ap.parse_args(argv)
    if a.samples < 1 or a.rounds < 1:
        print("clrf: error: --samples and --rounds must be >= 1", file=sys.stderr)
        return 2
    from .config import NerfConfig
    over = {k: getattr(a, k) for k in ("width", "depth", "skip", "color_width", "hidden_act",
                                       "sigma_act") if getattr(a, k) is not None}
    cfg = NerfConfig.from_preset(a.preset, **over)
    for ok, name, msg in cfg.checks():   # the ranges a run config would be held to
        if not ok:
            key = name.split(".")[-1]
            print(f"clrf: error: --{key.replace('_', '-')} {msg} (got {getattr(cfg, key)})",
                  file=sys.stderr)
            return 2
    dims = {k: getattr(a, k) for k in ("in_dim", "dir_dim") if getattr(a, k) is not None}
    spec = replace(cfg.mlp_spec(), **dims)
    from ..runtime.programs import BuildError
    try:
        dev = Device(a.device)
        best, res = tune(dev, spec, a.samples, a.rounds)
    except (DeviceError, BuildError) as e:
        print(f"clrf: error: {str(e).splitlines()[0]}", file=sys.stderr)
        return 2
    flop = spec.flops_per_sample()[1] * a.samples
    print(f"device {dev}")
    for t, s in res:
        mark = "*" if t == best else " "
        print(f"{mark} rows {t.rows:2d} cols {t.cols} dw_rows {t.dw_rows:2d} dw_cols {t.dw_cols} "
              f"dw_chunk {t.dw_chunk:4d}: fwd+bwd {s * 1e3:8.2f} ms  {flop / s / 1e9:7.1f} GFLOP/s")
    print(f"cached in {cache_path()}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
