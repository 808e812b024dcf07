"""8-bit levels: the 256 float32 values an 8-bit image file reads as (k / 255 in float32, as
clrf/data/io.py divides), and which float32 images hold only those.

The host's image store (clrf/data/images.py) and the splat model's training images on the device
(clrf/splat/targets.py) keep such images as their levels k, a quarter of the bytes, and widen
them through ``LEVELS``: the same values bit for bit.

>>> levels_of(LEVELS[[0, 128, 255]]).tolist(), levels_of(np.float32([0.5]))
([0, 128, 255], None)
"""
from __future__ import annotations

import numpy as np

LEVELS = np.arange(256, dtype=np.float32) / np.float32(255.0)


def levels_of(image) -> np.ndarray | None:
    """The uint8 levels k with LEVELS[k] == image exactly (a float32 array), or None where some
    value is not one of the 256."""
    a = np.asarray(image)
    if a.dtype != np.float32:
        return None
    k = np.rint(a * np.float32(255.0))
    if not np.all((k >= 0) & (k <= 255)):          # also false for NaN
        return None
    k = k.astype(np.uint8)
    return k if np.array_equal(LEVELS[k], a) else None


__all__ = ["LEVELS", "levels_of"]
