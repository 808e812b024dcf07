"""Host side of cl/splat_loss.cl: the splat model's training loss
L = (1 - lam) L1 + lam (1 - SSIM) of a render against its target and dL/drgb, all on the device
(the math, the window, the layouts and the work split are in the kernel file's header; float64
twin: clrf/references/reference_ssim.py; the host float32 version it replaces: clrf/splat/model.py
``loss_and_grad``).

One object per image size; its scratch planes, the gradient and the statistics are allocated
once and overwritten by every call, so a training step allocates nothing but the reduction's
small per-group partials (from the device's memory pool) and reads nothing back:

>>> loss = DeviceLoss(dev, height, width, lam=0.2)
>>> grad_d, stats_d = loss.loss_and_grad(rgb_d, target_d)   # [H, W, 3] and [4] device arrays
>>> g2d = rast.rasterize_backward(proj, bins, ras, cam, grad_d, bg)
>>> loss.read(stats_d)                                      # 16 bytes read, when wanted
{'loss': ..., 'l1': ..., 'ssim': ..., 'mse': ...}

A step runs four kernels (horizontal blur of x, y, x^2, y^2, xy; vertical blur, the SSIM map
and its partials; horizontal and vertical blur of the partials, the gradient), one pyopencl
ReductionKernel for sum |x - y|, sum of the SSIM map and sum (x - y)^2, and a one-work-item
kernel that forms (loss, L1, SSIM, MSE) from the three sums. The sums are taken in double
where the device has fp64, else as compensated float pairs (cl/reduce.h's TwoSum): either way
they carry ~1e-7 relative error or less at any image size. With lam = 0 only the L1 gradient
and the reduction run, and SSIM reads 1 (not computed), as in model.py's ``loss_and_grad``.

Device memory: 9 planes of scratch plus the gradient, 10 x 12 H W bytes (1600 x 1000: 192 MB).
"""
from __future__ import annotations

import functools
import warnings

import numpy as np
import pyopencl as cl
import pyopencl.cltypes  # noqa: F401  (cl.cltypes.float8, double4)
from pyopencl.reduction import ReductionKernel

from ..runtime.programs import cl_dir, device_empty, download, launch, scratch
from .raster import _check_device_array

SSIM_SIGMA = 1.5
SSIM_RADIUS = 5                 # 11 taps per axis (scipy's truncate = SSIM_RADIUS / SSIM_SIGMA)
SSIM_C1 = 0.01 ** 2
SSIM_C2 = 0.03 ** 2
STATS = ("loss", "l1", "ssim", "mse")   # the entries of the stats array, in order


def ssim_window(sigma: float = SSIM_SIGMA, radius: int = SSIM_RADIUS) -> np.ndarray:
    """The 1-D Gaussian taps w_k, k = -radius..radius, float64, summing to 1: scipy.ndimage's
    gaussian_filter1d weights for truncate = radius / sigma."""
    k = np.arange(-int(radius), int(radius) + 1, dtype=np.float64)
    w = np.exp(-0.5 * (k / float(sigma)) ** 2)
    return w / w.sum()


def defines() -> dict:
    """The -D defines of cl/splat_loss.cl: the taps at offsets 0..5 (as float32) and C1, C2."""
    w = ssim_window()[SSIM_RADIUS:]
    d = {f"SSIM_W{k}": float(w[k]) for k in range(SSIM_RADIUS + 1)}
    d.update(SSIM_C1=SSIM_C1, SSIM_C2=SSIM_C2)
    return d


def program(device):
    """cl/splat_loss.cl on ``device``."""
    return device.program("splat_loss.cl", defines())


# The reduction's map and merge. fp64: lanes (|x - y|, s, (x - y)^2, 0) in double (the
# difference of two floats is exact there). Else lanes (0, 1) |x - y|, (2, 3) s, (4, 5)
# (x - y)^2 as float pairs (hi, lo) merged with TwoSum on the heads (cl/reduce.h).
_PREAMBLE_F64 = """
#pragma OPENCL EXTENSION cl_khr_fp64 : enable
inline double4 loss_terms(float x, float y, float s) {
    const double d = (double)x - (double)y;
    return (double4)(fabs(d), (double)s, d * d, 0.0);
}
"""
_PREAMBLE_PAIRS = """
#define REDUCE_FP64 0
#include "reduce.h"
inline float8 loss_terms(float x, float y, float s) {
    float2 d = two_sum(x, -y);               /* x - y == d.x + d.y exactly */
    float2 a = d.x < 0.0f ? -d : d;          /* |x - y| (d.y is 0 when d.x is) */
    float2 q = sq_diff(x, y);
    return (float8)(a.x, a.y, s, 0.0f, q.x, q.y, 0.0f, 0.0f);
}
inline float8 loss_add(float8 a, float8 b) {
    return (float8)(acc_add(a.s01, b.s01), acc_add(a.s23, b.s23), acc_add(a.s45, b.s45),
                    0.0f, 0.0f);
}
"""


@functools.lru_cache(maxsize=None)
def _sums_kernel(context, fp64: bool) -> ReductionKernel:
    """The reduction over the n elements, built once per (context, accumulator); never with
    fast math (TwoSum must not be folded)."""
    dtype, neutral, merge, preamble = (
        (cl.cltypes.double4, "(double4)(0.0)", "a + b", _PREAMBLE_F64) if fp64 else
        (cl.cltypes.float8, "(float8)(0.0f)", "loss_add(a, b)", _PREAMBLE_PAIRS))
    with warnings.catch_warnings():
        # pyopencl warns on any non-empty build log, chatter included (programs.build)
        warnings.simplefilter("ignore", cl.CompilerWarning)
        return ReductionKernel(
            context, dtype, neutral=neutral, reduce_expr=merge,
            map_expr="loss_terms(x[i], y[i], has_ssim ? s[i] : 0.0f)",
            arguments="__global const float *x, __global const float *y, "
                      "__global const float *s, const int has_ssim",
            preamble=preamble, options=[f"-I{cl_dir()}"], name="splat_loss_sums")


class DeviceLoss:
    """(1 - lam) L1 + lam (1 - SSIM) and its gradient for float32 [height, width, 3] images on
    ``device`` (0 <= lam <= 1; clrf's splat config calls it lambda_dssim).

    fp64: the reduction's accumulator, None: double where ``device.caps.fp64``, else
    compensated float pairs; True / False force one (True without fp64 raises). span: the
    floats of a row one work-item takes (cl/splat_loss.cl), None: whole rows on CPU devices
    (loops the compiler vectorises), 1 elsewhere."""

    def __init__(self, device, height: int, width: int, lam: float, fp64: bool | None = None,
                 span: int | None = None):
        for name, v in (("height", height), ("width", width)):
            if int(v) != v or int(v) < 1:
                raise ValueError(f"{name}: must be an integer >= 1, got {v}")
        lam = float(lam)
        if not (0.0 <= lam <= 1.0):
            raise ValueError(f"lam: must be in [0, 1], got {lam}")
        self.device = device
        self.height, self.width, self.lam = int(height), int(width), lam
        self.shape = (self.height, self.width, 3)
        self.n = n = 3 * self.height * self.width
        if n >= 2 ** 31:
            raise ValueError(f"image {self.height} x {self.width}: over 2^31 floats; the "
                             f"kernels index with int")
        row_len = 3 * self.width
        if span is None:
            span = row_len if device.is_cpu else 1
        if int(span) != span or int(span) < 1:
            raise ValueError(f"span: must be an integer >= 1, got {span}")
        self.span = min(int(span), row_len)
        self.chunks = -(-row_len // self.span)          # work-items per row
        # one row per work-group on CPUs (the row loop is what vectorises)
        self.local_size = 1 if self.span > 1 else device.tuning.elementwise_local_size
        if fp64 is None:
            fp64 = bool(device.caps.fp64)
        if fp64 and not device.caps.fp64:
            raise ValueError("DeviceLoss: fp64=True but the device has no cl_khr_fp64")
        self.fp64 = bool(fp64)
        self.program = program(device)
        self._sums_kernel = _sums_kernel(device.context, self.fp64)
        self.has_ssim = lam > 0.0
        if self.has_ssim:
            self._P = scratch(device, (5, n))      # the horizontal pass; later R = its first 3
            self._Q = scratch(device, (3, n))      # scaled partials (A, Dxx, Dxy)
            self._s = scratch(device, (n,))        # the SSIM map
        else:
            self._P = self._Q = None
            self._s = scratch(device, (1,))        # a valid argument, never read
        self.grad = scratch(device, self.shape)
        self.stats = scratch(device, (len(STATS),))
        self._sums = device_empty(device.queue, (),
                               cl.cltypes.double4 if self.fp64 else cl.cltypes.float8)

    def loss_and_grad(self, rgb_d, target_d, out=None):
        """(grad, stats) for the render ``rgb_d`` and the target ``target_d`` (float32
        [H, W, 3] C-contiguous device arrays): grad = dL/drgb [H, W, 3] (``out`` if given, not
        one of the inputs; else this object's own array, OVERWRITTEN by the next call) and
        stats = this object's float32 device array [4] of STATS (loss, L1, SSIM, MSE; also
        overwritten by the next call). Everything is enqueued on device.queue; nothing is read
        back."""
        _check_device_array("rgb", rgb_d, self.shape)
        _check_device_array("target", target_d, self.shape)
        if out is not None:
            _check_device_array("out", out, self.shape)
            if out.data.int_ptr in (rgb_d.data.int_ptr, target_d.data.int_ptr):
                raise ValueError("out: must not be rgb or target (the kernels read them while "
                                 "writing the gradient)")
        grad = self.grad if out is None else out
        dev, prg, n = self.device, self.program, self.n
        x, y = rgb_d.data, target_d.data
        i32, f32 = np.int32, np.float32
        inv_n = 1.0 / n
        l1_scale = f32((1.0 - self.lam) * inv_n)
        if self.has_ssim:
            hw = (i32(self.width), i32(self.height), i32(self.span))
            items, ls = self.height * self.chunks, self.local_size
            P, Q = self._P.data, self._Q.data
            launch(dev, prg.kernel("ssim_blur_h5"), items, hw + (x, y, P), ls)
            launch(dev, prg.kernel("ssim_terms"), items,
                   hw + (P, f32(-self.lam * inv_n), self._s.data, Q), ls)
            launch(dev, prg.kernel("ssim_blur_h3"), items, hw + (Q, P), ls)
            launch(dev, prg.kernel("ssim_loss_grad"), items,
                   hw + (x, y, P, l1_scale, grad.data), ls)
        else:
            launch(dev, prg.kernel("l1_loss_grad"), n, (i32(n), x, y, l1_scale, grad.data),
                   dev.tuning.elementwise_local_size)
        self._sums_kernel(rgb_d, target_d, self._s, i32(self.has_ssim), queue=dev.queue,
                          allocator=dev.pool, out=self._sums)
        launch(dev, prg.kernel("loss_stats_f64" if self.fp64 else "loss_stats"), 1,
               (self._sums.data, i32(n), f32(self.lam), i32(self.has_ssim),
                self.stats.data), 1)
        return grad, self.stats

    def read(self, stats=None) -> dict:
        """A stats array (default: this object's, i.e. the last call's) as {STATS name: float};
        waits for the queue."""
        s = download(self.stats if stats is None else stats)
        return {k: float(v) for k, v in zip(STATS, s)}


__all__ = ["DeviceLoss", "STATS", "ssim_window", "defines", "SSIM_SIGMA", "SSIM_RADIUS",
           "SSIM_C1", "SSIM_C2"]
