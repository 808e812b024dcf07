"""Float64 twin of cl/splat_loss.cl (clrf/splat/loss.py DeviceLoss): the splat model's SSIM with
an 11 x 11 Gaussian window (sigma 1.5, normalised to sum 1, zero padding, every pixel and
channel averaged), its gradient, and the loss (1 - lam) L1 + lam (1 - SSIM) with its gradient.

Written apart from the kernels and from clrf/splat/model.py ``ssim_and_grad``: the window is the
explicit 2-D array w[i, j] = g_i g_j / (sum g)^2, g_k = exp(-k^2 / (2 sigma^2)), k = -5..5
(what scipy.ndimage.gaussian_filter applies for truncate = 5 / 1.5 on each axis), the blur is a
sum of 121 shifted copies of the zero-padded image, and the backward uses the blur's adjoint
written as a scatter (each pixel's value spread back over the window it was gathered from),
not the fact that a symmetric window makes the blur self-adjoint.

With B the blur, mx = B x, my = B y, sxx = B(x^2) - mx^2, syy = B(y^2) - my^2,
sxy = B(x y) - mx my, s = (2 mx my + C1)(2 sxy + C2) / ((mx^2 + my^2 + C1)(sxx + syy + C2)) and
SSIM = mean(s) over the n = H W C elements:
  dSSIM/dx = B^T(g_m - 2 mx g_xx - my g_xy) / n + 2 x B^T(g_xx) / n + y B^T(g_xy) / n,
where g_m, g_xx, g_xy are the partials of s by mx, sxx, sxy at each element.
"""
from __future__ import annotations

import numpy as np

SIGMA = 1.5
RADIUS = 5
C1 = 0.01 ** 2
C2 = 0.03 ** 2


def window(sigma: float = SIGMA, radius: int = RADIUS) -> np.ndarray:
    """The (2 radius + 1)^2 window w[i, j] (offsets i - radius, j - radius), summing to 1."""
    k = np.arange(-radius, radius + 1, dtype=np.float64)
    g = np.exp(-(k * k) / (2.0 * sigma * sigma))
    return np.outer(g, g) / (g.sum() ** 2)


def blur(a, w=None) -> np.ndarray:
    """(B a)[r, c] = sum_{i, j} w[i, j] a[r + i - R, c + j - R] (zero outside), per channel, of
    a [H, W] or [H, W, C] in float64."""
    w = window() if w is None else w
    a = np.asarray(a, np.float64)
    R = w.shape[0] // 2
    H, W = a.shape[:2]
    pad = ((R, R), (R, R)) + ((0, 0),) * (a.ndim - 2)
    p = np.pad(a, pad)
    out = np.zeros_like(a)
    for i in range(2 * R + 1):
        for j in range(2 * R + 1):
            out += w[i, j] * p[i:i + H, j:j + W]
    return out


def blur_adjoint(g, w=None) -> np.ndarray:
    """B^T g: every element g[r, c] spread back onto the pixels (r + i - R, c + j - R) it was
    gathered from, with weight w[i, j]; what falls outside the image is dropped."""
    w = window() if w is None else w
    g = np.asarray(g, np.float64)
    R = w.shape[0] // 2
    H, W = g.shape[:2]
    big = np.zeros((H + 2 * R, W + 2 * R) + g.shape[2:])
    for i in range(2 * R + 1):
        for j in range(2 * R + 1):
            big[i:i + H, j:j + W] += w[i, j] * g
    return big[R:R + H, R:R + W]


def _moments(x, y):
    mx, my = blur(x), blur(y)
    sxx = blur(x * x) - mx * mx
    syy = blur(y * y) - my * my
    sxy = blur(x * y) - mx * my
    return mx, my, sxx, syy, sxy


def ssim_map(x, y) -> np.ndarray:
    """The per-element SSIM s [H, W, C] (float64)."""
    x, y = np.asarray(x, np.float64), np.asarray(y, np.float64)
    mx, my, sxx, syy, sxy = _moments(x, y)
    return ((2 * mx * my + C1) * (2 * sxy + C2)) / ((mx * mx + my * my + C1) * (sxx + syy + C2))


def ssim(x, y) -> float:
    """Mean SSIM over every pixel and channel."""
    return float(np.mean(ssim_map(x, y)))


def ssim_grad(x, y) -> np.ndarray:
    """dSSIM/dx [H, W, C] (float64)."""
    x, y = np.asarray(x, np.float64), np.asarray(y, np.float64)
    n = x.size
    mx, my, sxx, syy, sxy = _moments(x, y)
    num1, num2 = 2 * mx * my + C1, 2 * sxy + C2
    den1, den2 = mx * mx + my * my + C1, sxx + syy + C2
    # quotient rule on s = num1 num2 / (den1 den2)
    g_m = (2 * my * num2 * den1 - num1 * num2 * 2 * mx) / (den1 * den1 * den2)
    g_xx = -num1 * num2 / (den1 * den2 * den2)
    g_xy = 2 * num1 / (den1 * den2)
    return (blur_adjoint(g_m - 2 * mx * g_xx - my * g_xy) + 2 * x * blur_adjoint(g_xx)
            + y * blur_adjoint(g_xy)) / n


def loss(x, y, lam: float) -> dict:
    """{"loss", "l1", "ssim", "mse"} of x against y: loss = (1 - lam) L1 + lam (1 - SSIM), L1
    and MSE the means of |x - y| and (x - y)^2 (SSIM computed whatever lam)."""
    x, y = np.asarray(x, np.float64), np.asarray(y, np.float64)
    d = x - y
    l1, s = float(np.mean(np.abs(d))), ssim(x, y)
    return {"loss": (1 - lam) * l1 + lam * (1 - s), "l1": l1, "ssim": s,
            "mse": float(np.mean(d * d))}


def loss_grad(x, y, lam: float) -> np.ndarray:
    """d loss / dx = (1 - lam) sign(x - y) / n - lam dSSIM/dx (sign(0) = 0)."""
    x, y = np.asarray(x, np.float64), np.asarray(y, np.float64)
    g = (1 - lam) * np.sign(x - y) / x.size
    if lam > 0:
        g = g - lam * ssim_grad(x, y)
    return g
