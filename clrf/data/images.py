"""A capture's images in host memory, stored as 8-bit levels where that is exact.

Every loader hands the models float32 RGB in [0, 1], composited on the capture's background. An
8-bit file read at its own resolution holds only the 256 values k / 255 (clrf/data/io.py divides
by 255 in float32), so such images are kept as their levels k (uint8, a quarter of the bytes)
and widened on access through a table of those 256 float32 values (clrf/runtime/levels.py); an
RGBA capture keeps its four channels and is composited on access by the loader's own function.
Readers get the values the loader used to store, bit for bit. Images averaged down by a
downscale factor (or resampled, or read from 16-bit or float files) hold other values and stay a
float32 array.

``collect`` builds the store one image at a time, so a loader never holds a float32 copy of
every image at once: bonsai_800's 292 photos at 800 x 533 take 0.37 GB instead of 1.5 GB, and
loading them no longer peaks at three float32 copies (the list, the stack and its cast).

>>> s = ImageStack(np.array([[[[0, 128, 255]]]], np.uint8))
>>> s.shape, s.dtype, float(s[0, 0, 0, 2])
((1, 1, 1, 3), dtype('float32'), 1.0)
"""
from __future__ import annotations

import numpy as np

from ..runtime.levels import LEVELS, levels_of


def composite(rgba: np.ndarray, background) -> np.ndarray:
    """RGB over ``background``: rgb * alpha + bg * (1 - alpha); RGB images pass through."""
    if rgba.shape[-1] == 3:
        return rgba
    a = rgba[..., 3:4]
    return rgba[..., :3] * a + np.asarray(background, np.float32) * (1.0 - a)


class ImageStack:
    """8-bit images that read as float32: ``levels`` uint8 [N, H, W, C] (C = 3, or 4 with a
    ``background``: RGBA read as RGB composited on it) or [N, H, W] (an alpha channel).
    Indexing takes numpy's keys on the image axes (an int, a slice, an index array, a tuple of
    them) and returns float32 arrays; ``np.asarray`` and every other ndarray method make the
    whole float32 stack."""

    dtype = np.dtype(np.float32)

    def __init__(self, levels: np.ndarray, background=None):
        levels = np.asarray(levels)
        if levels.dtype != np.uint8 or levels.ndim not in (3, 4):
            raise ValueError(f"ImageStack: levels must be uint8 [N, H, W(, C)], got "
                             f"{levels.dtype} {levels.shape}")
        rgba = levels.ndim == 4 and levels.shape[-1] == 4
        if rgba != (background is not None):
            raise ValueError("ImageStack: a background goes with RGBA levels, and only with them")
        self.levels = levels
        self.background = None if background is None else tuple(float(c) for c in background)

    @property
    def shape(self) -> tuple:
        s = self.levels.shape
        return s[:3] + (3,) if self.background is not None else s

    @property
    def ndim(self) -> int:
        return self.levels.ndim

    @property
    def nbytes(self) -> int:
        """Bytes stored (the levels), a quarter of the float32 stack's or less."""
        return self.levels.nbytes

    def __len__(self) -> int:
        return len(self.levels)

    def _read(self, key) -> np.ndarray:
        a = LEVELS[self.levels[key]]
        return a if self.background is None else composite(a, self.background)

    def __getitem__(self, key) -> np.ndarray:
        k = key if isinstance(key, tuple) else (key,)
        if self.background is not None and (len(k) > 3 or any(x is Ellipsis for x in k)):
            return np.asarray(self)[key]           # a key on the channels: read everything
        return self._read(key)

    def __array__(self, dtype=None, copy=None) -> np.ndarray:
        a = self._read(slice(None))
        return a if dtype is None else a.astype(dtype, copy=False)

    def __iter__(self):
        for i in range(len(self)):
            yield self[i]

    def copy(self) -> np.ndarray:
        """A writable float32 copy of every image."""
        return np.asarray(self)

    def __getattr__(self, name):
        """Any other ndarray attribute (``mean``, ``std``, ``astype``, ...) of the float32
        stack, made for the call."""
        if name.startswith("_") or name in ("levels", "background"):
            raise AttributeError(name)
        return getattr(np.asarray(self), name)

    def __repr__(self) -> str:
        return (f"ImageStack({self.shape}, float32 read from uint8 levels, "
                f"{self.nbytes / 2**20:.1f} MiB)")


def collect(images, n: int, background=None) -> tuple:
    """(images, alpha) of ``n`` float32 [H, W, C] arrays of one shape (C = 3 or 4), taken one at
    a time: an ImageStack of their levels where every value of every image is k / 255, else a
    float32 array [n, H, W, 3] of them composited on ``background`` (``composite``); alpha the
    RGBA images' coverage [n, H, W] (an ImageStack, or float32), None for RGB images or RGBA ones
    that are opaque everywhere."""
    store, fallback, i = None, None, -1
    for i, img in enumerate(images):
        a = np.asarray(img)
        if store is None and fallback is None:
            if a.ndim != 3 or a.shape[-1] not in (3, 4):
                raise ValueError(f"collect: images must be [H, W, 3 or 4], got {a.shape}")
            if a.shape[-1] == 4 and background is None:
                raise ValueError("collect: RGBA images need a background to composite on")
            store, first = np.empty((n,) + a.shape, np.uint8), a.shape
        elif a.shape != first:
            raise ValueError(f"collect: image {i} is {a.shape}, the first {first}")
        if fallback is None:
            k = levels_of(a)
            if k is not None:
                store[i] = k
                continue
            fallback = _widened(store, i, background)
            store = None
        _put(fallback, i, a, background)
    if i + 1 != n:
        raise ValueError(f"collect: {i + 1} images, expected {n}")
    if fallback is not None:
        rgb, alpha = fallback
        return rgb, (None if alpha is None or np.all(alpha >= 1.0) else alpha)
    if store is None:
        return np.zeros((0, 0, 0, 3), np.float32), None
    if store.shape[-1] == 3:
        return ImageStack(store), None
    if np.all(store[..., 3] == 255):        # opaque: rgb * 1 + bg * 0 is rgb itself
        return ImageStack(np.ascontiguousarray(store[..., :3])), None
    return ImageStack(store, background), ImageStack(store[..., 3])


def _widened(store, i: int, background) -> tuple:
    """(rgb float32 [n, H, W, 3], alpha float32 [n, H, W] or None) with the first i images of
    the uint8 ``store`` read into them."""
    n, h, w, c = store.shape
    out = (np.empty((n, h, w, 3), np.float32), np.empty((n, h, w), np.float32) if c == 4 else None)
    for j in range(i):
        _put(out, j, LEVELS[store[j]], background)
    return out


def _put(out, i: int, a, background) -> None:
    rgb, alpha = out
    rgb[i] = composite(a, background)
    if alpha is not None:
        alpha[i] = a[..., 3]


__all__ = ["ImageStack", "collect", "composite"]
