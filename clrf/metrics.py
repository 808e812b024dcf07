"""Image metrics: PSNR (from an MSE) and SSIM (scikit-image), per view and mean."""
from __future__ import annotations

import math

import numpy as np
from skimage.metrics import structural_similarity


def psnr_from_mse(mse: float) -> float:
    """PSNR in dB for images in [0, 1]; inf for a perfect match."""
    return float("inf") if mse <= 0 else -10.0 * math.log10(mse)


def image_metrics(pred: np.ndarray, gt: np.ndarray) -> dict:
    """PSNR and SSIM of one [H, W, 3] prediction (clipped to [0, 1]) against ground truth.

    MSE is accumulated in float64. SSIM uses scikit-image's defaults (7x7 uniform window)
    with data_range 1 over the three channels.
    """
    p = np.clip(np.asarray(pred, np.float64), 0, 1)
    g = np.asarray(gt, np.float64)
    mse = float(np.mean((p - g) ** 2))
    ssim = float(structural_similarity(p, g, channel_axis=-1, data_range=1.0))
    return {"psnr": psnr_from_mse(mse), "ssim": ssim, "mse": mse}
