"""Random-number keys of the training steps: the kernels' counter-based generators
(cl/common.h) take one 32-bit key per (seed, step, stream), so a run is reproducible and no
generator state lives on the device."""
from __future__ import annotations


def step_key(seed: int, it: int, stream: int) -> int:
    """A 32-bit random-number key per (seed, step, stream): splitmix-style mixing."""
    x = (seed * 0x9E3779B97F4A7C15 + it * 0xBF58476D1CE4E5B9 + stream * 0x94D049BB133111EB)
    x &= (1 << 64) - 1
    x ^= x >> 31
    x = (x * 0xD6E8FEB86659FD93) & ((1 << 64) - 1)
    return int(x >> 32)
