"""Float64 numpy reference of the multi-sphere-image background (cl/background.cl): the oracle
for tests, not on any runtime path.

Same model, quadrature and compositing as the kernel header, written independently and
vectorised over rays (a Python loop over the L - 1 segments only): explicit suffix sums instead
of the remaining-radiance accumulator, np.add.at instead of atomics. No early stop (the kernel
stops only where float32 transmittance is exactly 0).

Shapes: density [L, H, W] (W = 2 H), color [L, H, W, 3], origins/dirs [n, 3], t_start [n].
"""
from __future__ import annotations

import numpy as np

COLOR_OFFSET = 0.5


def inv_radii(layers: int, r_inner: float):
    """u_l = 1/r_l = (1 - (l + 0.5)/L) / r_inner, l = 0 .. L-1."""
    return (1.0 - (np.arange(layers) + 0.5) / layers) / r_inner


def _rays(origins, dirs, center, t_start):
    o = np.asarray(origins, np.float64).reshape(-1, 3) - np.asarray(center, np.float64)[:3]
    d = np.asarray(dirs, np.float64).reshape(-1, 3)
    norm = np.linalg.norm(d, axis=1)
    valid = np.isfinite(norm) & (norm > 0)
    d = np.where(valid[:, None], d / np.where(valid, norm, 1.0)[:, None], 0.0)
    b = np.sum(o * d, axis=1)
    h2 = np.sum((o - b[:, None] * d) ** 2, axis=1)
    start = np.maximum(np.asarray(t_start, np.float64).reshape(-1), 0.0)
    return o, d, b, h2, start, valid


def _segments(density, r_inner, o, d, b, h2, start):
    """Per segment k: list of (valid mask, delta, idx [n, 8], w [n, 8]) for layers k, k+1."""
    L, H, W = density.shape
    u = inv_radii(L, r_inner)
    tl = [-b + np.sqrt(np.maximum(1.0 / u[l] ** 2 - h2, 0.0)) for l in range(L)]
    segs = []
    for k in range(L - 1):
        a = np.maximum(tl[k], start)
        t1 = tl[k + 1]
        ok = t1 > a
        delta = np.where(ok, t1 - a, 0.0)
        p = o + (0.5 * (a + t1))[:, None] * d
        rho = np.linalg.norm(p, axis=1)
        f = np.clip((u[k] - 1.0 / np.where(rho > 0, rho, 1.0)) * L * r_inner, 0.0, 1.0)
        lon = np.arctan2(p[:, 1], p[:, 0])
        lat = np.arctan2(p[:, 2], np.hypot(p[:, 0], p[:, 1]))
        X = (lon + np.pi) * W / (2 * np.pi) - 0.5
        Y = np.clip((lat + np.pi / 2) * H / np.pi - 0.5, 0.0, H - 1)
        Xf = np.floor(X)
        fx = X - Xf
        j0 = Xf.astype(np.int64) % W
        j1 = (j0 + 1) % W
        i0 = np.minimum(Y.astype(np.int64), max(H - 2, 0))
        i1 = np.minimum(i0 + 1, H - 1)
        fy = Y - i0
        idx, w = [], []
        for lz, wl in ((k, 1 - f), (k + 1, f)):
            for ii, wy in ((i0, 1 - fy), (i1, fy)):
                for jj, wx in ((j0, 1 - fx), (j1, fx)):
                    idx.append((lz * H + ii) * W + jj)
                    w.append(wl * wy * wx)
        segs.append((ok, delta, np.stack(idx, 1), np.stack(w, 1)))
    return segs


def _samples(density, color, r_inner, origins, dirs, t_start, center):
    density = np.asarray(density, np.float64)
    color = np.asarray(color, np.float64)
    o, d, b, h2, start, valid = _rays(origins, dirs, center, t_start)
    segs = _segments(density, r_inner, o, d, b, h2, start)
    n = o.shape[0]
    K = len(segs)
    raw_s = np.zeros((n, K))
    pre = np.zeros((n, K, 3))
    delta = np.zeros((n, K))
    dflat, cflat = density.reshape(-1), color.reshape(-1, 3)
    for k, (ok, dk, idx, w) in enumerate(segs):
        m = ok & valid
        raw_s[:, k] = np.where(m, np.sum(w * dflat[idx], axis=1), 0.0)
        pre[:, k] = np.sum(w[..., None] * cflat[idx], axis=1) + COLOR_OFFSET
        delta[:, k] = np.where(m, dk, 0.0)
    return segs, raw_s, pre, delta, valid


def _composite(raw_s, pre, delta):
    tau = np.maximum(raw_s, 0.0) * delta
    cum = np.cumsum(tau, axis=1)
    T_before = np.exp(-(cum - tau))
    wts = T_before * -np.expm1(-tau)
    return tau, wts, np.exp(-cum[:, -1]) if tau.shape[1] else np.ones(tau.shape[0])


def forward(density, color, r_inner, origins, dirs, t_start, center=(0, 0, 0),
            background=(0, 0, 0)):
    """(rgb [n, 3], T [n]): rgb = sum_k w_k c_k + T bg, T = exp(-sum_k sigma_k delta_k)."""
    _, raw_s, pre, delta, _ = _samples(density, color, r_inner, origins, dirs, t_start, center)
    _, wts, T = _composite(raw_s, pre, delta)
    c = np.maximum(pre, 0.0)
    rgb = np.sum(wts[..., None] * c, axis=1) + T[:, None] * np.asarray(background, np.float64)
    return rgb, T


def backward(density, color, r_inner, origins, dirs, t_start, grad_rgb, center=(0, 0, 0),
             background=(0, 0, 0)):
    """(dL/d density [L, H, W], dL/d color [L, H, W, 3]) for dL/d rgb = grad_rgb [n, 3].

    dL/dsigma_k = delta_k (T_{k+1} g.c_k - sum_{j>k} w_j g.c_j - T_end g.bg), chained through
    the ReLU and the trilinear weights; dL/dpre_k = w_k g [pre_k > 0]."""
    density = np.asarray(density, np.float64)
    segs, raw_s, pre, delta, valid = _samples(density, color, r_inner, origins, dirs, t_start,
                                              center)
    tau, wts, T_end = _composite(raw_s, pre, delta)
    g = np.asarray(grad_rgb, np.float64).reshape(-1, 3)
    c = np.maximum(pre, 0.0)
    gc = np.sum(g[:, None, :] * c, axis=2)
    T_after = np.exp(-np.cumsum(tau, axis=1))
    wgc = wts * gc
    suffix = np.cumsum(wgc[:, ::-1], axis=1)[:, ::-1] - wgc      # sum_{j>k} w_j g.c_j
    rem = suffix + (T_end * (g @ np.asarray(background, np.float64)))[:, None]
    dsigma = delta * (T_after * gc - rem) * (raw_s > 0)
    dpre = wts[..., None] * g[:, None, :] * (pre > 0)
    gd = np.zeros(density.size)
    gcol = np.zeros((density.size, 3))
    for k, (ok, _, idx, w) in enumerate(segs):
        m = ok & valid
        np.add.at(gd, idx[m], w[m] * dsigma[m, k][:, None])
        np.add.at(gcol, idx[m], w[m][..., None] * dpre[m, k][:, None, :])
    return gd.reshape(density.shape), gcol.reshape(density.shape + (3,))


def finite_difference(density, color, r_inner, origins, dirs, t_start, grad_rgb, which, index,
                      center=(0, 0, 0), background=(0, 0, 0), eps=1e-4):
    """Central difference of L = sum(grad_rgb * rgb) with respect to density[index]
    (which == "density") or color[index] (which == "color")."""
    params = {"density": np.array(density, np.float64), "color": np.array(color, np.float64)}
    vals = []
    for s in (eps, -eps):
        p = {k: v.copy() for k, v in params.items()}
        p[which][index] += s
        rgb, _ = forward(p["density"], p["color"], r_inner, origins, dirs, t_start, center,
                         background)
        vals.append(np.sum(np.asarray(grad_rgb, np.float64) * rgb))
    return (vals[0] - vals[1]) / (2 * eps)
