"""``python -m clrf.nerf.autotune``: tune the fused MLP's tiles (clrf/mlp/autotune.py) for the
shape of a NeRF preset, or any shape given by flags.

    python -m clrf.nerf.autotune --preset tiny      # the shape `clrf train --model nerf` builds
    python -m clrf.nerf.autotune --width 256 --depth 8 --skip 4 --color-width 128 --in-dim 63 \\
        --dir-dim 27     # times the candidates, prints them, caches the best
"""
from __future__ import annotations

import argparse
import sys
from dataclasses import replace

from ..mlp.autotune import tune
from ..mlp.tiling import cache_path


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
    if dev.tuning.gpu_kernels:
        print("note: this device runs the fused MLP's GPU tiling, which takes its sizes from the "
              "device; the tuned CPU tile is used with CLRF_FORCE_GPU_KERNELS=0")
    return 0


if __name__ == "__main__":
    sys.exit(main())
