"""Accurate reductions over device arrays: sum of squared differences, MSE and PSNR.

A float32 running sum over millions of values loses about log2(n) bits; the training loss and
PSNR over a whole image set (10^6 - 10^8 rays) need better. The kernel (cl/reduce.cl) has two
accumulators, picked by capability:

- fp64 (devices with ``cl_khr_fp64``): differences formed, squared and summed in double.
- compensated float32 (no fp64, or ``fp64=False``): (hi, lo) float pairs merged with TwoSum,
  each term the exact square of the exact difference (fma); a double-float sum.

Each work-group writes one partial; the host adds the few hundred partials in float64.

Why not pyopencl's ``ReductionKernel``: it needs the Mako template engine, which is not a
dependency of clrf (nor installed in the test environment); the handwritten kernel is 40 lines,
lives in cl/ with the other sources and works with pyopencl alone.

>>> import clrf, clrf.reduce, numpy as np, pyopencl.array as cla
>>> dev = clrf.Device()
>>> a = cla.to_device(dev.queue, np.full(4, 0.5, np.float32))
>>> b = cla.to_device(dev.queue, np.full(4, 0.25, np.float32))
>>> clrf.reduce.sum_squares(dev, a, b), clrf.reduce.mse(dev, a, b)
(0.25, 0.0625)
"""
from __future__ import annotations

import math

import numpy as np
import pyopencl as cl
import pyopencl.array as cla

REDUCE_WG = 64          # work-group size (power of two; clamped to the device's maximum)
MAX_GROUPS = 256        # partials per launch: enough work-groups to fill a GPU


def _wg(device) -> int:
    wg = REDUCE_WG
    while wg > device.caps.max_work_group_size:
        wg //= 2
    return wg


def _check(a, b):
    for name, v in (("a", a), ("b", b)):
        if not isinstance(v, cla.Array) or v.dtype != np.float32:
            raise TypeError(f"{name}: expected a pyopencl float32 array, got "
                            f"{type(v).__name__} {getattr(v, 'dtype', '')}")
        if not v.flags.c_contiguous:
            raise ValueError(f"{name}: must be contiguous")
    if a.shape != b.shape:
        raise ValueError(f"a {a.shape} and b {b.shape} must have the same shape")


def sum_squares(device, a, b, fp64: bool | None = None) -> float:
    """sum_i (a_i - b_i)^2 over two float32 device arrays of the same shape, as a Python float.

    fp64: None picks double accumulation when ``device.caps.fp64``, else the compensated
    float32 scheme; True / False force one (True on a device without fp64 raises).
    """
    _check(a, b)
    if fp64 is None:
        fp64 = bool(device.caps.fp64)
    if fp64 and not device.caps.fp64:
        raise ValueError("sum_squares: fp64=True but the device has no cl_khr_fp64")
    n = int(a.size)
    if n == 0:
        return 0.0
    wg = _wg(device)
    groups = max(1, min(MAX_GROUPS, -(-n // wg)))
    prg = device.program("reduce.cl", {"REDUCE_FP64": int(fp64), "REDUCE_WG": wg})
    part_dtype = np.float64 if fp64 else cl.cltypes.float2
    part = cla.empty(device.queue, groups, part_dtype)
    k = prg.kernel("sum_sq_diff_partial")
    k.set_args(np.int64(n), a.data, b.data, part.data)
    cl.enqueue_nd_range_kernel(device.queue, k, (groups * wg,), (wg,))
    p = part.get()
    if fp64:
        return float(np.sum(p))
    return float(np.sum(p["x"].astype(np.float64)) + np.sum(p["y"].astype(np.float64)))


def mse(device, a, b, fp64: bool | None = None) -> float:
    """Mean of (a - b)^2 over all elements (0.0 for empty arrays)."""
    n = a.size
    return sum_squares(device, a, b, fp64) / n if n else 0.0


def psnr(device, a, b, max_value: float = 1.0, fp64: bool | None = None) -> float:
    """Peak signal-to-noise ratio 10 log10(max_value^2 / MSE) in dB; +inf when a == b."""
    m = mse(device, a, b, fp64)
    if m <= 0.0:
        return math.inf
    return 10.0 * math.log10(max_value * max_value / m)
