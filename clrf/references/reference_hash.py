"""Float64 numpy references of cl/hash.cl (multiresolution hash encoding, its backward, the SH
direction encoding) and of the hash model's occupancy update: the test oracle, not on any
runtime path.

The cell and its weights follow the kernel's float32 arithmetic exactly (u = clamp((x - lo) *
inv_ext, 0, 1) and p = u N rounded to float32; floor and p - floor(p) are exact), so kernel and
reference pick the same vertices; the interpolation and the scatter are done in float64.
"""
from __future__ import annotations

import numpy as np

from .reference import sh_basis, sh_dir_grad

PRIME_Y = 2654435761
PRIME_Z = 805459861
_M32 = (1 << 32) - 1


def level_resolutions(levels: int, n_min: int, n_max: int) -> np.ndarray:
    """N_l = floor(N_min b^l), b = exp((ln N_max - ln N_min) / (L - 1)) (b = 1 for L = 1)."""
    if levels == 1:
        return np.array([int(n_min)], np.int64)
    b = np.exp((np.log(n_max) - np.log(n_min)) / (levels - 1))
    return np.floor(n_min * b ** np.arange(levels) + 1e-9).astype(np.int64)


def unit_coords(x, lo, inv_ext, f64=False):
    """u [n, 3] in [0, 1] (float32 arithmetic, NaN -> 0), returned as float32; ``f64``: the
    same in float64 (for finite differences in x, which float32 would round away)."""
    ft = np.float64 if f64 else np.float32
    x = np.asarray(x, ft)
    with np.errstate(invalid="ignore"):
        u = (x - np.asarray(lo, ft)) * np.asarray(inv_ext, ft)
    u = np.where(np.isnan(u), ft(0), u)
    return np.clip(u, ft(0), ft(1)).astype(ft)


def cell_weights(u, N: int):
    """(i [n, 3] int64 cell, w [n, 3] float64 in [0, 1]) of level resolution N: p = u N in
    u's precision, i = min(floor(p), N - 1), w = p - i."""
    p = (u * u.dtype.type(N)).astype(u.dtype)
    fl = np.minimum(np.floor(p), u.dtype.type(N - 1))
    return fl.astype(np.int64), (p - fl).astype(np.float64)


def cell(u, N: int, T: int):
    """(rows [n, 8] int64, weights [n, 8] float64) of level resolution N (corner k: bit 0 x,
    bit 1 y, bit 2 z), as cl/hash.cl hash_cell."""
    i, w = cell_weights(u, N)
    R = N + 1
    dense = R ** 3 <= T
    rows = np.zeros((u.shape[0], 8), np.int64)
    wts = np.ones((u.shape[0], 8))
    for k in range(8):
        c = np.array([k & 1, (k >> 1) & 1, (k >> 2) & 1])
        v = i + c
        if dense:
            rows[:, k] = v[:, 0] + R * (v[:, 1] + R * v[:, 2])
        else:
            h = (v[:, 0] ^ ((v[:, 1] * PRIME_Y) & _M32) ^ ((v[:, 2] * PRIME_Z) & _M32)) & _M32
            rows[:, k] = h & (T - 1)
        for a in range(3):
            wts[:, k] *= np.where(c[a] == 1, w[:, a], 1.0 - w[:, a])
    return rows, wts


def hash_forward(x, lo, inv_ext, res, table, f64=False):
    """enc [n, L F] of points x [n, 3]; table [L, T, F]; ``f64``: u and p in float64."""
    table = np.asarray(table, np.float64)
    L, T, F = table.shape
    u = unit_coords(x, lo, inv_ext, f64)
    out = np.zeros((u.shape[0], L * F))
    for l in range(L):
        rows, wts = cell(u, int(res[l]), T)
        out[:, l * F:(l + 1) * F] = np.einsum("nk,nkf->nf", wts, table[l][rows])
    return out


def hash_backward(x, lo, inv_ext, res, genc, shape):
    """dL/dtable [L, T, F] (shape) from dL/denc [n, L F]."""
    L, T, F = shape
    g = np.zeros(shape)
    genc = np.asarray(genc, np.float64)
    u = unit_coords(x, lo, inv_ext)
    for l in range(L):
        rows, wts = cell(u, int(res[l]), T)
        for k in range(8):
            np.add.at(g[l], rows[:, k], wts[:, k, None] * genc[:, l * F:(l + 1) * F])
    return g


def hash_dx(x, lo, inv_ext, res, table, genc, f64=False):
    """dL/dx [n, 3] of points x [n, 3] from dL/denc genc [n, L F] (cl/hash.cl hash_dx): per
    level dL/dw_a = sum_c (c_a ? 1 : -1) prod_{b != a} (c_b ? w_b : 1 - w_b) genc_l . table[l,
    row_c], times N_l, summed over levels, times inv_ext_a where 0 <= (x_a - lo_a) inv_ext_a
    <= 1 (else 0). The derivative of the cell the forward reads (one-sided on its faces)."""
    table = np.asarray(table, np.float64)
    L, T, F = table.shape
    genc = np.asarray(genc, np.float64)
    ft = np.float64 if f64 else np.float32
    with np.errstate(invalid="ignore"):
        raw = (np.asarray(x, ft) - np.asarray(lo, ft)) * np.asarray(inv_ext, ft)
        inside = (raw >= 0) & (raw <= 1)
    u = unit_coords(x, lo, inv_ext, f64)
    g = np.zeros((u.shape[0], 3))
    for l in range(L):
        N = int(res[l])
        rows, _ = cell(u, N, T)
        _, w = cell_weights(u, N)
        s = np.einsum("nf,nkf->nk", genc[:, l * F:(l + 1) * F], table[l][rows])
        for k in range(8):
            c = [k & 1, (k >> 1) & 1, (k >> 2) & 1]
            f = [w[:, a] if c[a] else 1.0 - w[:, a] for a in range(3)]
            for a in range(3):
                b0, b1 = [b for b in range(3) if b != a]
                g[:, a] += (1.0 if c[a] else -1.0) * f[b0] * f[b1] * s[:, k] * N
    return g * np.asarray(inv_ext, np.float64) * inside


def sh_encode(d):
    """SH basis (degree 3, 16 coefficients) of d / |d| [n, 16]; zero d -> basis at 0."""
    d = np.asarray(d, np.float64)
    n = np.linalg.norm(d, axis=1, keepdims=True)
    return sh_basis(np.where(n > 0, d / np.where(n > 0, n, 1), 0.0), 3)


# ---- occupancy grid and compaction (cl/hash_occ.cl) -----------------------------------------
def occ_cells(xyz, lo, inv_ext, R):
    """Cell index [n] of each point (float32 u as the kernel), -1 outside the closed box."""
    x = np.asarray(xyz, np.float32)
    u = (x - np.asarray(lo, np.float32)) * np.asarray(inv_ext, np.float32)
    inside = np.all((u >= 0) & (u <= 1), axis=1)
    c = np.minimum((u * np.float32(R)).astype(np.int64), R - 1)
    idx = c[:, 0] + R * (c[:, 1] + R * c[:, 2])
    return np.where(inside, idx, -1)


def compact(xyz, occ, lo, inv_ext, R):
    """Indices (ray-major) of the points inside the box in occupied cells."""
    c = occ_cells(xyz, lo, inv_ext, R)
    live = (c >= 0) & (np.asarray(occ)[np.maximum(c, 0)] != 0)
    return np.flatnonzero(live)


def occ_points(m, key, R, lo, ext, start=0, stride=1):
    """(cells [m], points [m, 3]) measured by the occupancy update at sweep positions start ..
    start + m - 1 of the order p -> p * stride mod R^3 (bit-exact cells)."""
    from .reference_nerf import uniform01
    j = np.arange(m, dtype=np.uint64)
    R3 = R ** 3
    c = ((start + j.astype(np.int64)) % R3) * stride % R3
    ijk = np.stack([c % R, (c // R) % R, c // (R * R)], 1).astype(np.float64)
    jit = np.stack([uniform01(key, 4 * j + k) for k in (1, 2, 3)], 1)
    return c, np.asarray(lo) + (ijk + jit) / R * np.asarray(ext)


def occ_update(ema, cells, sigma, decay, thr):
    """(ema', occ'): measured cells decay, then max with the new densities (NaN / negative ->
    0; never-measured cells take them), occupied = never measured or above thr."""
    e = np.array(ema, np.float64)
    e = np.where(e >= 0, e * decay, e)
    s = np.where(np.isnan(sigma), 0.0, np.maximum(np.asarray(sigma, np.float64), 0.0))
    for c, v in zip(cells, s):
        e[c] = max(e[c], v)
    return e, ((e < 0) | (e > thr)).astype(np.uint8)


# ---- packed samples and compositing (cl/hash_march.cl) ---------------------------------------
def contract(y):
    """The scene contraction of normalised points y [m, 3] (the inner box is [-1, 1]^3), with
    the max-norm: y where max|y_i| <= 1, else (2 - 1/n) y / n."""
    y = np.asarray(y, np.float64)
    n = np.max(np.abs(y), axis=1, keepdims=True)
    return np.where(n <= 1, y, (2 - 1 / np.maximum(n, 1)) * y / np.maximum(n, 1))


def bins(n, S, near, far, jitter=False, key=0, log=False):
    """(t [n, S], dt [n, S]) of the stratified bins: even in t, or even in log t (``log``)."""
    from .reference_nerf import sample_stratified
    if not log:
        t = sample_stratified(n, S, near, far, jitter, key)
        return t, np.full_like(t, (far - near) / S)
    s = sample_stratified(n, S, 0.0, 1.0, jitter, key)
    lr = np.log(far / near)
    k = np.arange(S, dtype=np.float64)[None, :]
    return near * np.exp(lr * s), np.broadcast_to(near * np.exp(lr * k / S) * np.expm1(lr / S),
                                                   s.shape).copy()


def march_samples(origins, dirs, S, near, far, occ, lo, inv_ext, R, jitter=False, key=0,
                  centre=None, half=None):
    """(offsets [n+1], t [M], dt [M], xyz [M, 3], vdir [M, 3]) of the live samples of every
    bin; with ``centre``/``half`` (the inner box) log-spaced bins and contracted points."""
    from .reference_nerf import ray_points
    n = np.asarray(origins).shape[0]
    contracted = centre is not None
    t, dt = bins(n, S, near, far, jitter, key, log=contracted)
    xyz, vdir = ray_points(origins, dirs, t)
    if contracted:
        xyz = contract((xyz - np.asarray(centre)) / np.asarray(half))
    live = compact(xyz, occ, lo, inv_ext, R)
    counts = np.bincount(live // S, minlength=n)
    off = np.concatenate([[0], np.cumsum(counts)])
    return off, t.reshape(-1)[live], dt.reshape(-1)[live], xyz[live], vdir[live]


def packed_forward(offsets, t, dt, sigma, rgb, background=(0, 0, 0)):
    """rgb [n, 3], acc [n], depth [n], weights [M] of packed samples (no early termination);
    dt: each sample's segment [M], or one for all."""
    s = np.where(np.asarray(sigma, np.float64) > 0, np.asarray(sigma, np.float64), 0.0)
    dt = np.broadcast_to(np.asarray(dt, np.float64), s.shape)
    c = np.asarray(rgb, np.float64)
    n = len(offsets) - 1
    out = {"rgb": np.zeros((n, 3)), "acc": np.zeros(n), "depth": np.zeros(n),
           "weights": np.zeros(len(s)), "T_end": np.ones(n)}
    bg = np.broadcast_to(np.asarray(background, np.float64), (3,))
    for i in range(n):
        a, b = offsets[i], offsets[i + 1]
        tau = s[a:b] * dt[a:b]
        logT = -np.concatenate([[0.0], np.cumsum(tau)])
        w = np.exp(logT[:-1]) * -np.expm1(-tau)
        out["weights"][a:b] = w
        out["T_end"][i] = np.exp(logT[-1])
        out["rgb"][i] = w @ c[a:b] + out["T_end"][i] * bg
        out["acc"][i] = w.sum()
        out["depth"][i] = w @ np.asarray(t, np.float64)[a:b]
    return out


def packed_backward(offsets, t, dt, sigma, rgb, background, target, loss_scale):
    """dsigma [M], drgb [M, 3], sq_err [n] of loss_scale sum |rgb - target|^2 (suffix sums)."""
    f = packed_forward(offsets, t, dt, sigma, rgb, background)
    dt = np.broadcast_to(np.asarray(dt, np.float64), np.shape(sigma))
    diff = f["rgb"] - np.asarray(target, np.float64)
    g = 2 * loss_scale * diff
    c = np.asarray(rgb, np.float64)
    bg = np.broadcast_to(np.asarray(background, np.float64), (3,))
    dsig = np.zeros(len(c))
    drgb = np.zeros_like(c)
    for i in range(len(offsets) - 1):
        a, b = offsets[i], offsets[i + 1]
        w = f["weights"][a:b]
        gc = c[a:b] @ g[i]
        wgc = w * gc
        after = np.cumsum(wgc[::-1])[::-1] - wgc
        R = after + f["T_end"][i] * (g[i] @ bg)
        tau = np.where(np.asarray(sigma)[a:b] > 0, np.asarray(sigma, np.float64)[a:b],
                       0) * dt[a:b]
        Tnext = np.exp(-np.cumsum(tau))
        dsig[a:b] = np.where(np.asarray(sigma)[a:b] > 0, dt[a:b] * (Tnext * gc - R), 0.0)
        drgb[a:b] = w[:, None] * g[i][None, :]
    return {"sigma": dsig, "rgb": drgb, "sq_err": np.sum(diff ** 2, axis=1)}


def packed_keep(offsets, dt, sigma, t_stop):
    """Per ray the number of leading samples whose transmittance in front is >= t_stop (the
    first sample always kept); also returns that transmittance [M] (float64)."""
    s = np.where(np.asarray(sigma, np.float64) > 0, np.asarray(sigma, np.float64), 0.0)
    tau = s * np.broadcast_to(np.asarray(dt, np.float64), s.shape)
    n = len(offsets) - 1
    keep = np.zeros(n, np.int64)
    T_front = np.ones(len(s))
    for i in range(n):
        a, b = offsets[i], offsets[i + 1]
        T = np.exp(-np.concatenate([[0.0], np.cumsum(tau[a:b])[:-1]])) if b > a else np.ones(0)
        T_front[a:b] = T
        below = np.flatnonzero(T[1:] < t_stop)
        keep[i] = (below[0] + 1) if len(below) else b - a
    return keep, T_front


# ---- the camera gradient of a ray batch (cl/hash_march.cl packed_ray_grad) --------------------
def contract_vjp(x, gp, centre, half):
    """dL/dx [m, 3] at world points x of dL/dp at p = contract((x - centre) / half)."""
    y = (np.asarray(x, np.float64) - np.asarray(centre)) / np.asarray(half)
    gp = np.asarray(gp, np.float64)
    a = np.abs(y)
    n = a.max(axis=1)
    out = gp.copy()
    far = n > 1
    nf = n[far]
    out[far] = gp[far] * ((2 - 1 / nf) / nf)[:, None]
    k = np.sum(y[far] * gp[far], axis=1) * 2 * (1 - nf) / nf ** 3
    m = np.argmax(a[far], axis=1)          # the first axis on ties, as the kernel
    rows = np.flatnonzero(far)
    out[rows, m] += k * np.sign(y[rows, m])
    return out / np.asarray(half)


def ray_grad(offsets, t, origins, dirs, gp, gsh=None, centre=None, half=None):
    """dL/d(origin, direction) [n, 6] of rays x_k = o + t_k d / |d| from the samples' dL/dp
    gp [M, 3] (p: the point the encoding reads, contracted with ``centre``/``half``) and dL/dY
    gsh [M, 16] (the view direction's SH basis) or None."""
    o = np.asarray(origins, np.float64)
    d = np.asarray(dirs, np.float64)
    length = np.linalg.norm(d, axis=1)
    dh = d / length[:, None]
    t = np.asarray(t, np.float64)
    ray = np.repeat(np.arange(len(o)), np.diff(offsets))
    gx = np.asarray(gp, np.float64)
    if centre is not None:
        gx = contract_vjp(o[ray] + t[:, None] * dh[ray], gx, centre, half)
    gd_s = t[:, None] * gx
    if gsh is not None:
        gd_s = gd_s + sh_dir_grad(dh[ray], np.asarray(gsh, np.float64), 3)
    go = np.zeros_like(o)
    gd = np.zeros_like(o)
    np.add.at(go, ray, gx)
    np.add.at(gd, ray, gd_s)
    gd = (gd - dh * np.sum(dh * gd, axis=1, keepdims=True)) / length[:, None]
    return np.concatenate([go, gd], axis=1)
