"""``python -m clrf.nerf.autotune``: tune the fused MLP's tiles (clrf/mlp/autotune.py) for the
shape of a NeRF preset, or any shape given by flags: the CPU register tiles, or on a device
that runs the GPU tiling (GPUs; CLRF_FORCE_GPU_KERNELS=1) that tiling, at 2^18 samples.

    python -m clrf.nerf.autotune --preset tiny      # the shape `clrf train --model nerf` builds
    python -m clrf.nerf.autotune --width 256 --depth 8 --skip 4 --color-width 128 --in-dim 63 \\
        --dir-dim 27     # times the candidates, prints them, caches the best
"""
from __future__ import annotations

import argparse
import sys
from dataclasses import replace

from ..mlp.autotune import tune_command


def main(argv=None) -> int:
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
    ap.add_argument("--samples", type=int, default=None,
                    help="samples per timed pass (default 4096; 2^18 for the GPU tiling)")
    ap.add_argument("--rounds", type=int, default=5, help="interleaved timing rounds")
    a = ap.parse_args(argv)
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
    return tune_command(a.device, replace(cfg.mlp_spec(), **dims), a.samples, a.rounds)


if __name__ == "__main__":
    sys.exit(main())
