"""Float64 twin of cl/splat_exposure.cl (the splat model's colour transform per training image)
and the evaluation protocol of NeRF in the Wild for captures with changing exposure: fit a
transform on the left half of a test image, score the right half.

Row v of P [V, 12]: A (3 x 3, row-major), then b (3); out = A rgb + b per pixel.
"""
from __future__ import annotations

import numpy as np

ROW = 12
IDENTITY = np.array([1, 0, 0, 0, 1, 0, 0, 0, 1, 0, 0, 0], np.float64)


def split(row):
    """(A [3, 3], b [3]) of a 12-float row."""
    row = np.asarray(row, np.float64)
    return row[:9].reshape(3, 3), row[9:12]


def apply(rgb, P, v):
    """out [n, 3] = A_v rgb + b_v for rgb [n, 3]."""
    A, b = split(np.asarray(P, np.float64).reshape(-1, ROW)[v])
    return np.asarray(rgb, np.float64).reshape(-1, 3) @ A.T + b


def backward(rgb, grad_out, P, v):
    """(dL/drgb [n, 3], dL/dP_v [12]) from dL/dout ``grad_out`` [n, 3]."""
    A, _ = split(np.asarray(P, np.float64).reshape(-1, ROW)[v])
    x = np.asarray(rgb, np.float64).reshape(-1, 3)
    g = np.asarray(grad_out, np.float64).reshape(-1, 3)
    return g @ A, np.concatenate([(g.T @ x).ravel(), g.sum(axis=0)])


def adam(P, m, vm, v, grad_row, lr, reg, b1, b2, eps, t):
    """Adam step t (1-based) of row v, with the pull 2 reg (P - I) added to ``grad_row``;
    returns new (P, m, vm), float64 copies."""
    P = np.array(P, np.float64).reshape(-1, ROW)
    m = np.array(m, np.float64).reshape(-1, ROW)
    vm = np.array(vm, np.float64).reshape(-1, ROW)
    g = np.asarray(grad_row, np.float64) + 2.0 * reg * (P[v] - IDENTITY)
    m[v] = b1 * m[v] + (1 - b1) * g
    vm[v] = b2 * vm[v] + (1 - b2) * g * g
    P[v] -= lr * (m[v] / (1 - b1 ** t)) / (np.sqrt(vm[v] / (1 - b2 ** t)) + eps)
    return P, m, vm


def fit_affine(render, target):
    """The 12-float row (A, b) that maps ``render`` [..., 3] closest to ``target`` in least
    squares (float64)."""
    x = np.asarray(render, np.float64).reshape(-1, 3)
    y = np.asarray(target, np.float64).reshape(-1, 3)
    X = np.concatenate([x, np.ones((len(x), 1))], axis=1)
    sol, *_ = np.linalg.lstsq(X, y, rcond=None)          # [4, 3]: A^T over b
    return np.concatenate([sol[:3].T.ravel(), sol[3]])


def half_fitted_psnr(render, target):
    """NeRF-W's protocol: (PSNR of the right half after the transform fitted on the left half,
    PSNR of the right half as rendered) for one image [H, W, 3] in [0, 1]."""
    render = np.asarray(render, np.float64)
    target = np.asarray(target, np.float64)
    w = render.shape[1] // 2
    row = fit_affine(render[:, :w], target[:, :w])
    right = apply(render[:, w:].reshape(-1, 3), row[None], 0).reshape(render[:, w:].shape)

    def psnr(a, b):
        mse = float(np.mean((np.clip(a, 0, 1) - b) ** 2))
        return float(-10 * np.log10(max(mse, 1e-12)))
    return psnr(right, target[:, w:]), psnr(render[:, w:], target[:, w:])
