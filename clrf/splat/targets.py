"""The training images on the device, stored compactly.

A splat run uploads every training image once and compares each step's render with one of
them, so the images are the largest allocation that does not depend on the Gaussian count (at
bonsai_800's full 800 x 533, 255 float32 images take 1.3 GB, on a CPU device of host memory).
They are stored in the fewest bytes that keep them:

- ``uint8`` (a quarter of float32) when every value is exactly k / 255 in float32, as an 8-bit
  capture read at its own resolution is (clrf/data/io.py divides by 255); the float32 value is
  looked up in a table of the 256 values numpy computes, so the step's target is the dataset's
  image bit for bit;
- else ``float16`` (half of float32; images averaged down by ``train.downscale``, 16-bit or HDR
  captures): the nearest half to each value, a relative error of at most 2^-11 (just below
  1.0 at most 2^-12, 0.06 of an 8-bit level).

``get(v)`` widens image v into one float32 buffer on the device (an elementwise kernel of
pyopencl: a table lookup, or ``vload_half``), which the loss kernels read as before. Its
float64 twin is numpy's own conversion (``host_copy``).
"""
from __future__ import annotations

from collections.abc import Mapping

import numpy as np
import pyopencl.array as cla
from pyopencl.elementwise import ElementwiseKernel
from pyopencl.tools import context_dependent_memoize

from ..runtime.levels import LEVELS, levels_of
from ..runtime.programs import first_run, scratch, upload


def exact_8bit(images) -> bool:
    """Whether every value of ``images`` (float32) is one of LEVELS."""
    return all(levels_of(np.asarray(img, np.float32)) is not None for img in images)


def encode(img, dtype) -> np.ndarray:
    """One float32 image as stored for ``dtype``: uint8 its levels k; float16 the nearest
    halves, as their uint16 bits (what the device kernel reads)."""
    a = np.ascontiguousarray(img, np.float32)
    if dtype == np.uint8:
        return np.rint(a * 255.0).astype(np.uint8)
    return a.astype(np.float16).view(np.uint16)


def decode(stored) -> np.ndarray:
    """What the device makes of a stored image (``encode``'s output), in numpy: float32."""
    if stored.dtype == np.uint8:
        return LEVELS[stored]
    return stored.view(np.float16).astype(np.float32)


@context_dependent_memoize
def _widen(context, dtype):
    """The kernel that widens a stored image (``dtype``: uint8 levels or float16 bits) to
    float32, built once a context and type."""
    if np.dtype(dtype) == np.uint8:
        return ElementwiseKernel(context, "float *y, const uchar *x, const float *levels",
                                 "y[i] = levels[x[i]]", "splat_target_from_u8")
    # the half type may only be pointed to without cl_khr_fp16: vload_half reads it
    return ElementwiseKernel(context, "float *y, const ushort *x",
                             "y[i] = vload_half(i, (__global const half *)x)",
                             "splat_target_from_f16")


class ViewImages(Mapping):
    """``{view: images[view]}`` for ``views`` of an image stack (an array, or the dataset's
    ImageStack), each image read when asked for: DeviceImages reads them one at a time, so no
    float32 copy of every training image is made."""

    def __init__(self, images, views):
        self.images, self.views = images, [int(v) for v in views]

    def __getitem__(self, v) -> np.ndarray:
        if int(v) not in self.views:
            raise KeyError(v)
        return np.asarray(self.images[int(v)], np.float32)

    def __iter__(self):
        return iter(self.views)

    def __len__(self) -> int:
        return len(self.views)


class DeviceImages:
    """Images ``{view: float32 [H, W, 3]}`` of one size on ``device``, stored as uint8 where
    that is exact, else as float16 (module docstring). ``images`` is any mapping; its images are
    read one at a time (``ViewImages``)."""

    def __init__(self, device, images: dict):
        if not images:
            raise ValueError("DeviceImages: no images")
        shapes = {np.shape(a) for a in images.values()}
        if len(shapes) != 1:
            raise ValueError(f"DeviceImages: the images differ in shape: {sorted(shapes)}")
        self.device = device
        self.shape = shapes.pop()
        self.dtype = np.dtype(np.uint8 if exact_8bit(images.values()) else np.float16)
        q = device.queue
        self._stored = {int(k): upload(q, encode(a, self.dtype)) for k, a in images.items()}
        self._levels = upload(q, LEVELS) if self.dtype == np.uint8 else None
        self._kernel = _widen(device.context, self.dtype)
        self._out = None

    @property
    def nbytes(self) -> int:
        """Bytes the stored images take on the device."""
        return sum(a.nbytes for a in self._stored.values())

    def __contains__(self, v) -> bool:
        return int(v) in self._stored

    def get(self, v: int) -> cla.Array:
        """Image ``v`` as a float32 device array [H, W, 3]: this object's buffer, overwritten by
        the next call (enqueued on the device's in-order queue after what reads it now)."""
        stored = self._stored[int(v)]
        if self._out is None:
            self._out = scratch(self.device, self.shape)
        q = self.device.queue
        with first_run(self.device, ("widen", self.dtype)):
            if self.dtype == np.uint8:
                self._kernel(self._out, stored, self._levels, queue=q)
            else:
                self._kernel(self._out, stored, queue=q)
        return self._out

    def host_copy(self, v: int) -> np.ndarray:
        """The float32 image ``get(v)`` makes, computed in numpy from the stored copy."""
        return decode(self._stored[int(v)].get())


__all__ = ["DeviceImages", "LEVELS", "ViewImages", "exact_8bit", "encode", "decode"]
