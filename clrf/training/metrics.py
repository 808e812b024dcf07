"""Image metrics: PSNR (from an MSE), the standard SSIM and LPIPS (``clrf.training.perceptual``, optional)
per view; accurate sum of squares / MSE / PSNR of device arrays (pyopencl ReductionKernel over
cl/reduce.h).

SSIM is the one of the published NeRF / mip-NeRF 360 / 3DGS / nerfstudio tables: an 11 x 11
Gaussian window with sigma 1.5, population (not sample) covariances, K1 = 0.01, K2 = 0.03,
data range 1, the SSIM map averaged over the valid region (windows wholly inside the image) and
the three channels. Until 2026-11-24 clrf reported scikit-image's default instead (7 x 7 uniform
window, sample covariance), which reads higher on blurred, noisy renders; results written before
then carry that figure (docs/evaluation.md).
"""
from __future__ import annotations

import functools
import math

import numpy as np
import pyopencl as cl
import pyopencl.array as cla
from pyopencl.reduction import ReductionKernel
from skimage.metrics import structural_similarity

from .perceptual import LpipsUnavailable, lpips, lpips_status  # noqa: F401 - re-exported
from ..runtime.programs import cl_dir


def psnr_from_mse(mse: float) -> float:
    """PSNR in dB for images in [0, 1]; inf for a perfect match."""
    return float("inf") if mse <= 0 else -10.0 * math.log10(mse)


SSIM_SIGMA = 1.5
SSIM_WINDOW = 11          # 2 * int(3.5 * sigma + 0.5) + 1: scikit-image's truncation at 3.5 sigma
SSIM_NAME = "gaussian11"  # how result files name the SSIM they hold ("ssim_window")


def ssim(pred: np.ndarray, gt: np.ndarray) -> float:
    """Standard SSIM of two [H, W, 3] (or [H, W]) images in [0, 1], H, W >= SSIM_WINDOW.

    Per pixel, with Gaussian-weighted means mu, variances s^2 and covariance s_pg over the
    11 x 11 window (sigma 1.5), C1 = 0.01^2, C2 = 0.03^2:
    ((2 mu_p mu_g + C1)(2 s_pg + C2)) / ((mu_p^2 + mu_g^2 + C1)(s_p^2 + s_g^2 + C2)),
    averaged over the pixels whose window lies inside the image and over the channels.
    Images smaller than the window have no standard SSIM: NaN.
    """
    p = np.asarray(pred, np.float64)
    g = np.asarray(gt, np.float64)
    if p.shape != g.shape:
        raise ValueError(f"ssim: shapes {p.shape} and {g.shape} differ")
    if min(p.shape[:2]) < SSIM_WINDOW:
        return float("nan")
    return float(structural_similarity(p, g, channel_axis=-1 if p.ndim == 3 else None,
                                       data_range=1.0, gaussian_weights=True, sigma=SSIM_SIGMA,
                                       use_sample_covariance=False))


def colour_corrected(pred: np.ndarray, gt: np.ndarray) -> np.ndarray:
    """``pred`` [..., 3] (clipped to [0, 1], as it is scored) under the affine map of each
    channel that brings it closest to ``gt`` in least squares, r' = a r + b with
    a = cov(r, g) / var(r), b = mean(g) - a mean(r) (float64; a constant channel maps to gt's
    mean), clipped to [0, 1] (which can only bring it nearer a gt in [0, 1]).

    >>> gt = np.random.default_rng(0).uniform(0, 1, (4, 4, 3))
    >>> bool(np.allclose(colour_corrected(0.5 * gt + 0.2, gt), gt))   # undone exactly
    True
    """
    r = np.clip(np.asarray(pred, np.float64), 0, 1).reshape(-1, 3)
    g = np.asarray(gt, np.float64)[..., :3].reshape(-1, 3)
    rm, gm = r.mean(0), g.mean(0)
    var = ((r - rm) ** 2).mean(0)
    cov = ((r - rm) * (g - gm)).mean(0)
    a = np.where(var > 0, cov / np.where(var > 0, var, 1.0), 0.0)
    return np.clip(a * (r - rm) + gm, 0, 1).reshape(np.shape(pred))


def psnr_color_corrected(pred: np.ndarray, gt: np.ndarray) -> float:
    """PSNR of ``colour_corrected(pred, gt)``: a score blind to a gain and an offset per
    channel (a capture's exposure and white balance), never below the plain PSNR (the identity
    is one of the maps). docs/evaluation.md compares it with gsplat's and multinerf's."""
    g = np.asarray(gt, np.float64)[..., :3]
    return psnr_from_mse(float(np.mean((colour_corrected(pred, g) - g) ** 2)))


def image_metrics(pred: np.ndarray, gt: np.ndarray) -> dict:
    """PSNR, the standard SSIM (``ssim``) and the colour-corrected PSNR
    (``psnr_color_corrected``) of one [H, W, 3] prediction (clipped to [0, 1]) against ground
    truth; MSE accumulated in float64."""
    p = np.clip(np.asarray(pred, np.float64), 0, 1)
    g = np.asarray(gt, np.float64)
    mse = float(np.mean((p - g) ** 2))
    return {"psnr": psnr_from_mse(mse), "ssim": ssim(p, g), "mse": mse,
            "psnr_color_corrected": psnr_color_corrected(p, g)}


@functools.lru_cache(maxsize=None)
def _sum_sq_kernel(context, fp64: bool) -> ReductionKernel:
    return ReductionKernel(
        context, np.float64 if fp64 else cl.cltypes.float2, neutral="ACC_ZERO",
        reduce_expr="acc_add(a, b)", map_expr="sq_diff(x[i], y[i])",
        arguments="__global const float *x, __global const float *y",
        preamble=f"#define REDUCE_FP64 {int(fp64)}\n#include \"reduce.h\"\n",
        options=[f"-I{cl_dir()}"])


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

    fp64: None picks double accumulation when ``device.caps.fp64``, else compensated float32
    (double-float pairs, cl/reduce.h); True / False force one (True without fp64 raises).

    >>> a = cla.to_device(dev.queue, np.full(4, 0.5, np.float32))
    >>> sum_squares(dev, a, cla.to_device(dev.queue, np.full(4, 0.25, np.float32)))
    0.25
    """
    _check(a, b)
    if fp64 is None:
        fp64 = bool(device.caps.fp64)
    if fp64 and not device.caps.fp64:
        raise ValueError("sum_squares: fp64=True but the device has no cl_khr_fp64")
    if a.size == 0:
        return 0.0
    r = _sum_sq_kernel(device.context, bool(fp64))(a, b, queue=device.queue).get()
    return float(r) if fp64 else float(np.float64(r["x"]) + np.float64(r["y"]))


def mse(device, a, b, fp64: bool | None = None) -> float:
    """Mean of (a - b)^2 over all elements (0.0 for empty arrays)."""
    n = a.size
    return sum_squares(device, a, b, fp64) / n if n else 0.0


def psnr(device, a, b, max_value: float = 1.0, fp64: bool | None = None) -> float:
    """Peak signal-to-noise ratio 10 log10(max_value^2 / MSE) in dB; +inf when a == b."""
    return psnr_from_mse(mse(device, a, b, fp64) / (max_value * max_value))
