"""Float64 numpy references of cl/hash.cl (multiresolution hash encoding, its backward, the SH
direction encoding) and of the hash model's occupancy update: the test oracle, not on any
runtime path.

The cell and its weights follow the kernel's float32 arithmetic exactly (u = clamp((x - lo) *
inv_ext, 0, 1) and p = u N rounded to float32; floor and p - floor(p) are exact), so kernel and
reference pick the same vertices; the interpolation and the scatter are done in float64.
"""
from __future__ import annotations

import numpy as np

from .reference import sh_basis

PRIME_Y = 2654435761
PRIME_Z = 805459861
_M32 = (1 << 32) - 1


def level_resolutions(levels: int, n_min: int, n_max: int) -> np.ndarray:
    """N_l = floor(N_min b^l), b = exp((ln N_max - ln N_min) / (L - 1)) (b = 1 for L = 1)."""
    if levels == 1:
        return np.array([int(n_min)], np.int64)
    b = np.exp((np.log(n_max) - np.log(n_min)) / (levels - 1))
    return np.floor(n_min * b ** np.arange(levels) + 1e-9).astype(np.int64)


def unit_coords(x, lo, inv_ext):
    """u [n, 3] in [0, 1] (float32 arithmetic, NaN -> 0), returned as float32."""
    x = np.asarray(x, np.float32)
    with np.errstate(invalid="ignore"):
        u = (x - np.asarray(lo, np.float32)) * np.asarray(inv_ext, np.float32)
    u = np.where(np.isnan(u), np.float32(0), u)
    return np.clip(u, np.float32(0), np.float32(1)).astype(np.float32)


def cell(u, N: int, T: int):
    """(rows [n, 8] int64, weights [n, 8] float64) of level resolution N (corner k: bit 0 x,
    bit 1 y, bit 2 z), as cl/hash.cl hash_cell."""
    p = (u * np.float32(N)).astype(np.float32)
    fl = np.minimum(np.floor(p), np.float32(N - 1))
    w = (p - fl).astype(np.float64)
    i = fl.astype(np.int64)
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


def hash_forward(x, lo, inv_ext, res, table):
    """enc [n, L F] of points x [n, 3]; table [L, T, F]."""
    table = np.asarray(table, np.float64)
    L, T, F = table.shape
    u = unit_coords(x, lo, inv_ext)
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


def sh_encode(d):
    """SH basis (degree 3, 16 coefficients) of d / |d| [n, 16]; zero d -> basis at 0."""
    d = np.asarray(d, np.float64)
    n = np.linalg.norm(d, axis=1, keepdims=True)
    return sh_basis(np.where(n > 0, d / np.where(n > 0, n, 1), 0.0), 3)
