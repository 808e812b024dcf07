"""``python -m clrf.hash.autotune``: tune the fused MLP (clrf/mlp/autotune.py) for the networks
of a hash preset: the CPU register tiles, or on a device that runs the GPU tiling (GPUs;
CLRF_FORCE_GPU_KERNELS=1) that tiling, at 2^18 samples a pass (about one training step's).
Every hash model of that shape on that device then uses the choice.

    python -m clrf.hash.autotune                    # the full (default) preset's networks
    python -m clrf.hash.autotune --preset tiny --device gpu
"""
from __future__ import annotations

import argparse
import sys

from ..mlp.autotune import tune_command


def main(argv=None) -> int:
    from .config import HASH_PRESETS, HashConfig
    from .model import mlp_spec
    ap = argparse.ArgumentParser(prog="python -m clrf.hash.autotune",
                                 description="Time the hash model's fused-MLP tiles on a "
                                             "device; cache the best.")
    ap.add_argument("--device", default=None,
                    help="'cpu', 'gpu', 'P:D' or an implementation (default CLRF_DEVICE)")
    ap.add_argument("--preset", default="full", choices=sorted(HASH_PRESETS),
                    help="the hash preset whose networks to tune")
    ap.add_argument("--samples", type=int, default=None,
                    help="samples per timed pass (default 4096; 2^18 for the GPU tiling)")
    ap.add_argument("--rounds", type=int, default=5, help="interleaved timing rounds")
    a = ap.parse_args(argv)
    return tune_command(a.device, mlp_spec(HashConfig.from_preset(a.preset)), a.samples,
                        a.rounds)


if __name__ == "__main__":
    sys.exit(main())
