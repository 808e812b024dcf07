"""The training images on the device, stored compactly, or streamed from the host.

A splat run compares each step's render with one training image. Resident (the default on a
device of its own memory), every training image is uploaded once, and the images are the largest
allocation that does not depend on the Gaussian count (at bonsai_800's full 800 x 533, 255
float32 images take 1.3 GB). They are stored in the fewest bytes that keep them:

- ``uint8`` (a quarter of float32) when every value is exactly k / 255 in float32, as an 8-bit
  capture read at its own resolution is (clrf/data/io.py divides by 255); the float32 value is
  looked up in a table of the 256 values numpy computes, so the step's target is the dataset's
  image bit for bit;
- else ``float16`` (half of float32; images averaged down by ``train.downscale``, 16-bit or HDR
  captures): the nearest half to each value, a relative error of at most 2^-11 (just below
  1.0 at most 2^-12, 0.06 of an 8-bit level).

Where the device's memory is the host's (HOST_UNIFIED_MEMORY: PoCL's and Intel's CPU runtimes,
integrated GPUs), that copy would sit beside the dataset's own in the same memory (bonsai's
full size: 0.33 GB of uint8 twice), so there the images are streamed (``splat.images_on_device``,
``resident``): a step copies its one view from the host's dataset, the uint8 levels of an 8-bit
ImageStack into a one-view staging buffer (widened as above), any other image as its float32
values. Either way the step's target is the dataset's float32 image bit for bit (streamed
images are never rounded to float16).

``get(v)`` makes image v in one float32 buffer on the device (an elementwise kernel of
pyopencl: a table lookup, or ``vload_half``; or the float32 copy itself), which the loss kernels
read as before. Its float64 twin is numpy's own conversion (``host_copy``).
"""
from __future__ import annotations

from collections.abc import Mapping

import numpy as np
import pyopencl as cl
import pyopencl.array as cla
from pyopencl.elementwise import ElementwiseKernel
from pyopencl.tools import context_dependent_memoize

from ..runtime.levels import LEVELS, levels_of
from ..runtime.programs import device_empty, first_run, scratch, upload


def host_unified(caps) -> bool:
    """Whether the device of ``caps`` (Capabilities, or None: not known) reports that its
    memory is the host's."""
    return bool(getattr(caps, "host_unified_memory", False))


def resident(setting: str, caps) -> bool:
    """Whether the training images are uploaded once (splat.images_on_device ``setting``:
    "true"; "false": streamed; "auto": resident unless the device's memory is the host's)."""
    if setting == "auto":
        return not host_unified(caps)
    return setting == "true"


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

    @property
    def image_shape(self) -> tuple:
        """The shape every image of the stack has, known without reading one."""
        return tuple(self.images.shape[1:])

    @property
    def levels(self):
        """The stack's uint8 levels [N, H, W, 3] where its images read as their LEVELS (an RGB
        ImageStack), else None (a float32 array, or RGBA levels composited on reading)."""
        # an ImageStack is recognised by its attributes: a representation imports no clrf.data
        s = self.images
        levels = getattr(s, "levels", None)
        if (isinstance(levels, np.ndarray) and levels.dtype == np.uint8 and levels.ndim == 4
                and levels.shape[-1] == 3 and getattr(s, "background", None) is None):
            return levels
        return None


class DeviceImages:
    """Images ``{view: float32 [H, W, 3]}`` of one size for ``device``. ``resident``: stored on
    the device, as uint8 where that is exact, else as float16; else streamed, each ``get``
    copying its view from ``images`` (module docstring). ``images`` is any mapping; its images
    are read one at a time (``ViewImages``, whose uint8 levels a streamed copy takes where it has
    them). ``dtype``: what is stored or copied per view (uint8, float16 or float32)."""

    def __init__(self, device, images: dict, resident: bool = True):
        if not images:
            raise ValueError("DeviceImages: no images")
        if isinstance(images, ViewImages):
            shapes = {images.image_shape}
        else:
            shapes = {np.shape(a) for a in images.values()}
        if len(shapes) != 1:
            raise ValueError(f"DeviceImages: the images differ in shape: {sorted(shapes)}")
        self.device, self.resident = device, bool(resident)
        self.shape = shapes.pop()
        self._views = frozenset(int(k) for k in images)
        q = device.queue
        self._stored, self._host, self._host_levels, self._staging = {}, None, None, None
        if self.resident:
            self.dtype = np.dtype(np.uint8 if exact_8bit(images.values()) else np.float16)
            self._stored = {int(k): upload(q, encode(a, self.dtype)) for k, a in images.items()}
        else:
            self._host = images
            self._host_levels = getattr(images, "levels", None)
            self.dtype = np.dtype(np.float32 if self._host_levels is None else np.uint8)
            if self.dtype == np.uint8:
                self._staging = device_empty(q, self.shape, np.uint8)
        self._levels = upload(q, LEVELS) if self.dtype == np.uint8 else None
        self._kernel = _widen(device.context, self.dtype) if self.dtype != np.float32 else None
        self._out = None
        self._copy = None     # the last streamed copy's event (it holds the host array)

    @property
    def nbytes(self) -> int:
        """Bytes the stored images take on the device: every view's copy when resident;
        streamed, the one view's uint8 staging buffer (0 where views are copied as float32).
        Neither counts the float32 buffer ``get`` returns or the 256 levels' table."""
        if not self.resident:
            return 0 if self._staging is None else self._staging.nbytes
        return sum(a.nbytes for a in self._stored.values())

    def __contains__(self, v) -> bool:
        return int(v) in self._views

    def get(self, v: int) -> cla.Array:
        """Image ``v`` as a float32 device array [H, W, 3]: this object's buffer, overwritten by
        the next call (enqueued on the device's in-order queue after what reads it now)."""
        v = int(v)
        if v not in self._views:
            raise KeyError(v)
        if self._out is None:
            self._out = scratch(self.device, self.shape)
        q = self.device.queue
        if self.resident:
            stored = self._stored[v]
        elif self._staging is None:
            self._copy = self._upload(self._out, self._host[v])
            return self._out
        else:
            self._copy = self._upload(self._staging, self._host_levels[v])
            stored = self._staging
        with first_run(self.device, ("widen", self.dtype)):
            if self.dtype == np.uint8:
                self._kernel(self._out, stored, self._levels, queue=q)
            else:
                self._kernel(self._out, stored, queue=q)
        return self._out

    def _upload(self, dst: cla.Array, host) -> cl.Event:
        """Copy ``host`` into ``dst`` on the in-order queue: after what reads ``dst`` now,
        before what follows. Not blocking: the event pyopencl returns holds the host array until
        the copy is done and waits for it when dropped, so it is kept until the next copy
        replaces it (a wait, if any, for the copy a step before)."""
        a = np.ascontiguousarray(host, dst.dtype)
        return cl.enqueue_copy(self.device.queue, dst.data, a, is_blocking=False)

    def host_copy(self, v: int) -> np.ndarray:
        """The float32 image ``get(v)`` makes, computed in numpy: from the stored copy, or
        streamed, the host's image itself."""
        if not self.resident:
            if int(v) not in self._views:
                raise KeyError(v)
            return np.array(self._host[int(v)], np.float32)
        return decode(self._stored[int(v)].get())


__all__ = ["DeviceImages", "LEVELS", "ViewImages", "exact_8bit", "encode", "decode",
           "host_unified", "resident"]
