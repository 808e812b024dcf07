"""Float64 twin of cl/bilateral.cl: the bilateral grid of Wang et al. 2024 ("Bilateral Guided
Radiance Field Processing", as gsplat's ``use_bilateral_grid`` / ``post_processing =
"bilateral_grid"``), a per-view colour correction (clrf/corrections/bilateral.py).

Grid of one view: G [L, GY, GX, 12] (luminance bins, height bins, width bins; gsplat's shape
(X, Y, W) = (16, 16, 8)), each cell a 3 x 4 affine colour transform, row-major: entry
k = 4 i + j is A_ij (j < 3) or b_i (j = 3). A pixel (px, py) of an H x W render with colour
rgb is sliced trilinearly at

    u = (px + 1/2) / W (GX - 1),   w = (py + 1/2) / H (GY - 1),
    z = clamp(lum(rgb) (L - 1), 0, L - 1),   lum = 0.299 r + 0.587 g + 0.114 b

(gsplat: pixel centres over the image mapped to [0, 1], a grid sampled with aligned corners and
the border clamp, the guidance BT.601's grey), giving M(p) = sum_c w_c(u, w, z) G_c, and

    out = A rgb + b                        a capture without alpha;
    out = A (rgb - T bg) + (1 - T) b + T bg   a masked (RGBA) capture rendered on bg: the
                                           scene's light c = rgb - T bg is transformed, its
                                           background stays bg.

Every grid starts at the identity (A = I, b = 0). The prior is gsplat's total variation of a
grid, TV(G) = sum_d sum (G[i+1] - G[i])^2 / n_d over the three axes d, n_d the number of
differences along d times 12.
"""
from __future__ import annotations

import numpy as np

CHANNELS = 12
GREY = np.array([0.299, 0.587, 0.114])   # BT.601 luma weights (gsplat's rgb2gray)
IDENTITY = np.array([1, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1, 0], np.float64)


def identity_grid(gx: int, gy: int, gl: int) -> np.ndarray:
    """G [L, GY, GX, 12] at the identity transform."""
    return np.tile(IDENTITY, (gl, gy, gx, 1))


def _axis(t, n):
    """(i0, i1, f) of coordinates t [m] on an axis of n cells (f the weight of i1)."""
    if n == 1:
        z = np.zeros(len(t), np.int64)
        return z, z, np.zeros(len(t))
    i0 = np.minimum(np.floor(t).astype(np.int64), n - 2)
    return i0, i0 + 1, t - i0


def coordinates(rgb, H, W, shape):
    """(u, w, z, z_free) of each pixel of an [H, W, 3] render (row-major pixels): grid
    coordinates; z_free marks where z is not clamped (0 < lum (L - 1) < L - 1)."""
    gl, gy, gx = shape
    py, px = np.divmod(np.arange(H * W), W)
    u = (px + 0.5) / W * (gx - 1)
    w = (py + 0.5) / H * (gy - 1)
    zr = np.asarray(rgb, np.float64).reshape(-1, 3) @ GREY * (gl - 1)
    return u, w, np.clip(zr, 0, gl - 1), (zr > 0) & (zr < gl - 1)


def _corners(G, rgb, H, W):
    """[(weight [n], d weight / dz [n], cell index (z, y, x) arrays)] of the 8 corners."""
    gl, gy, gx = G.shape[:3]
    u, w, z, _ = coordinates(rgb, H, W, (gl, gy, gx))
    (x0, x1, fx), (y0, y1, fy), (z0, z1, fz) = _axis(u, gx), _axis(w, gy), _axis(z, gl)
    out = []
    for zi, wz, dz in ((z0, 1 - fz, -1.0), (z1, fz, 1.0)):
        for yi, wy in ((y0, 1 - fy), (y1, fy)):
            for xi, wx in ((x0, 1 - fx), (x1, fx)):
                out.append((wx * wy * wz, dz * wx * wy, (zi, yi, xi)))
    return out


def slice_grid(G, rgb, H, W):
    """M [n, 12]: the grid's transform at each pixel of the [H, W, 3] render rgb."""
    G = np.asarray(G, np.float64)
    M = np.zeros((H * W, CHANNELS))
    for wc, _, idx in _corners(G, rgb, H, W):
        M += wc[:, None] * G[idx]
    return M


def _terms(rgb, T, background):
    """(x, y): out = A x + y b (+ T bg masked); x = rgb, y = 1 without T."""
    x = np.asarray(rgb, np.float64).reshape(-1, 3)
    if T is None:
        return x, np.ones(len(x))
    T = np.asarray(T, np.float64).reshape(-1)
    return x - T[:, None] * np.asarray(background, np.float64)[:3], 1 - T


def apply(G, rgb, H, W, T=None, background=None):
    """out [n, 3] of the render rgb [H, W, 3]; T [H, W] and its ``background`` given: a
    masked capture (module doc)."""
    M = slice_grid(G, rgb, H, W).reshape(-1, 3, 4)
    x, y = _terms(rgb, T, background)
    out = np.einsum("nij,nj->ni", M[:, :, :3], x) + y[:, None] * M[:, :, 3]
    if T is not None:
        out += np.asarray(T, np.float64).reshape(-1, 1) * np.asarray(background)[:3]
    return out


def backward(G, rgb, H, W, grad_out, T=None, background=None):
    """(dL/drgb [n, 3], dL/dG [L, GY, GX, 12]) from dL/dout [n, 3] of ``apply`` (T held
    fixed). dL/dM = g x^T (A) and g y (b); dL/dG_c = sum_p w_c dL/dM; dL/drgb = A^T g plus
    the guidance's share, (dL/dM . dM/dz) (L - 1) GREY where z is not clamped."""
    G = np.asarray(G, np.float64)
    g = np.asarray(grad_out, np.float64).reshape(-1, 3)
    x, y = _terms(rgb, T, background)
    dM = np.concatenate([g[:, :, None] * x[:, None, :], (g * y[:, None])[:, :, None]],
                        axis=2).reshape(-1, CHANNELS)
    M = slice_grid(G, rgb, H, W).reshape(-1, 3, 4)
    d_rgb = np.einsum("nij,ni->nj", M[:, :, :3], g)
    dMdz = np.zeros_like(dM)
    dG = np.zeros_like(G)
    for wc, dz, idx in _corners(G, rgb, H, W):
        np.add.at(dG, idx, wc[:, None] * dM)
        dMdz += dz[:, None] * G[idx]
    gl = G.shape[0]
    _, _, _, free = coordinates(rgb, H, W, G.shape[:3])
    dz_total = np.where(free, (dM * dMdz).sum(axis=1), 0.0) * (gl - 1)
    return d_rgb + dz_total[:, None] * GREY, dG


def tv(G) -> float:
    """gsplat's total variation of one grid G [L, GY, GX, 12] (module doc)."""
    G = np.asarray(G, np.float64)
    total = 0.0
    for ax in range(3):
        d = np.diff(G, axis=ax)
        if d.size:
            total += float((d * d).sum()) / d.size
    return total


def tv_grad(G) -> np.ndarray:
    """d TV / dG [L, GY, GX, 12]: along each axis with n_d differences, 2 / n_d times each
    entry's difference from its lower neighbour minus its upper neighbour's from it."""
    G = np.asarray(G, np.float64)
    out = np.zeros_like(G)
    for ax in range(3):
        d = np.diff(G, axis=ax)
        if not d.size:
            continue
        s = 2.0 / d.size * d
        lo = [slice(None)] * 4
        hi = [slice(None)] * 4
        lo[ax], hi[ax] = slice(1, None), slice(None, -1)
        out[tuple(lo)] += s
        out[tuple(hi)] -= s
    return out


def step_gradient(grids, v, data_grad, weight):
    """The gradient every grid [V, L, GY, GX, 12] takes in a training step of view v: its data
    gradient (view v's only; v < 0: none) plus weight / V times each grid's TV gradient
    (gsplat's loss: weight * TV summed over the grids / V)."""
    grids = np.asarray(grids, np.float64)
    out = np.stack([tv_grad(g) for g in grids]) * (weight / len(grids))
    if v >= 0:
        out[v] += np.asarray(data_grad, np.float64)
    return out


def lr_factor(progress: float, warmup: float, final: float) -> float:
    """gsplat's schedule of the grids' rate as a budget fraction: linear from 0.01 to 1 over
    ``warmup``, times a log-linear decay to ``final`` at the end."""
    ramp = 0.01 + 0.99 * min(max(progress, 0.0) / warmup, 1.0) if warmup > 0 else 1.0
    return ramp * final ** min(max(progress, 0.0), 1.0)
