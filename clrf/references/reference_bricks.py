"""Float64 reference of the distributed (brick) render: the partial of one brick and its backward
(cl/grid_render.cl with BRICK, clrf/grid/bricks.py). Not on any runtime path.

A brick with voxels [lo, hi) owns the samples whose trilinear cell has its lower corner in
[lo, hi) on every axis (reference.trilerp_corners); its partial is the single-grid march over
those samples only, starting with T = 1. No early termination (the distributed render has none).
Composition and backward inputs are clrf.grid.bricks.compose / backward_inputs (float64 numpy),
checked here against reference.render_forward / render_backward on whole grids.
"""
from __future__ import annotations

import numpy as np

from .reference import COLOR_OFFSET, _samples, alpha_of_tau, march_setup, sh_basis


def _owned(idx, lo, hi):
    i0 = idx[:, 0, :]                          # corner 0 = lower corner of the cell
    return np.all((i0 >= np.asarray(lo)) & (i0 < np.asarray(hi)), axis=1)


def _march(density, sh, bbox, origins, dirs, lo, hi, step, mask):
    """Per-sample records of the brick's owned samples (in march order)."""
    density = np.asarray(density, np.float64)
    sh = np.asarray(sh, np.float64)
    B = sh.shape[-1] // 3
    degree = int(round(np.sqrt(B))) - 1
    if mask is None:
        mask = (density != 0) | np.any(sh != 0, axis=-1)
    m = march_setup(origins, dirs, density.shape, bbox, step)
    n = m["p0"].shape[0]
    Y = sh_basis(m["dir"], degree)
    logT = np.zeros(n)
    key = np.full(n, -1, np.int64)
    recs = []
    for k in range(int(m["nsteps"].max(initial=0))):
        rays = np.nonzero(m["hit"] & (k < m["nsteps"]))[0]
        if rays.size == 0:
            break
        mid, delta, idx, w, sigma_raw, co = _samples(density, sh, m, k, rays)
        own = _owned(idx, lo, hi)
        any_alloc = np.any(mask[idx[..., 0], idx[..., 1], idx[..., 2]], axis=1)
        first = own & any_alloc & (key[rays] < 0)
        key[rays[first]] = k
        sel = own
        rays, mid, delta, idx, w = rays[sel], mid[sel], delta[sel], idx[sel], w[sel]
        sigma_raw, co = sigma_raw[sel], co[sel]
        sigma = np.maximum(sigma_raw, 0.0)
        tau = sigma * delta
        pre = np.einsum("ncb,nb->nc", co.reshape(-1, 3, B), Y[rays]) + COLOR_OFFSET
        wgt = np.exp(logT[rays]) * alpha_of_tau(tau)
        logT[rays] -= tau
        recs.append(dict(rays=rays, mid=mid, delta=delta, idx=idx, w=w, sigma_raw=sigma_raw,
                         pre=pre, c=np.maximum(pre, 0.0), wgt=wgt, Tnext=np.exp(logT[rays])))
    return m, Y, recs, logT, key, mask


def render_partial(density, sh, bbox, origins, dirs, lo, hi, step=0.5, mask=None):
    """Partial of the brick [lo, hi): rgb [n,3] (premultiplied), logT, depth (sum w' t), acc
    [n] and key [n] (first owned sample with an allocated corner, -1 if none)."""
    m, _, recs, logT, key, _ = _march(density, sh, bbox, origins, dirs, lo, hi, step, mask)
    n = m["p0"].shape[0]
    rgb = np.zeros((n, 3))
    acc = np.zeros(n)
    depth = np.zeros(n)
    for r in recs:
        rays = r["rays"]
        np.add.at(rgb, rays, r["wgt"][:, None] * r["c"])
        np.add.at(acc, rays, r["wgt"])
        np.add.at(depth, rays, r["wgt"] * (m["t0"][rays] + r["mid"]))
    return dict(rgb=rgb, logT=logT, depth=depth, acc=acc, key=key)


def backward_partial(density, sh, bbox, origins, dirs, lo, hi, ray_in4, step=0.5, mask=None):
    """Dense gradients of the brick's samples given ray_in4 [n, 4] = (T_b g, R_b): the BRICK
    backward, with explicit suffix sums: dL/dsigma_k = delta_k (T'_{k+1} (g'.c_k) - S_k),
    S_k = sum_{j>k in brick} w'_j (g'.c_j) + R_b."""
    m, Y, recs, _, _, mask = _march(density, sh, bbox, origins, dirs, lo, hi, step, mask)
    density = np.asarray(density, np.float64)
    sh = np.asarray(sh, np.float64)
    B = sh.shape[-1] // 3
    gin = np.asarray(ray_in4, np.float64)
    g, R = gin[:, 0:3], gin[:, 3]
    n = gin.shape[0]
    K = len(recs)
    wgc = np.zeros((n, K))
    for k, r in enumerate(recs):
        wgc[r["rays"], k] = r["wgt"] * np.sum(g[r["rays"]] * r["c"], axis=1)
    after = np.cumsum(wgc[:, ::-1], axis=1)[:, ::-1] - wgc
    gd = np.zeros_like(density)
    gs = np.zeros_like(sh)
    for k, r in enumerate(recs):
        rays = r["rays"]
        gc = np.sum(g[rays] * r["c"], axis=1)
        dsig = r["delta"] * (r["Tnext"] * gc - (after[rays, k] + R[rays])) * (r["sigma_raw"] > 0)
        idx, w = r["idx"], r["w"]
        np.add.at(gd, (idx[..., 0], idx[..., 1], idx[..., 2]), w * dsig[:, None])
        dpre = r["wgt"][:, None] * g[rays] * (r["pre"] > 0) * (r["sigma_raw"] > 0)[:, None]
        dco = (dpre[:, :, None] * Y[rays][:, None, :]).reshape(len(rays), 3 * B)
        np.add.at(gs, (idx[..., 0], idx[..., 1], idx[..., 2]), w[..., None] * dco[:, None, :])
    return dict(density=gd * mask, sh=gs * mask[..., None])


def pack(part) -> np.ndarray:
    """[n, 7] float64 in the layout of clrf.grid.bricks.pack_partials."""
    n = part["logT"].shape[0]
    out = np.empty((n, 7))
    out[:, 0:3] = part["rgb"]
    out[:, 3] = part["logT"]
    out[:, 4] = part["depth"]
    out[:, 5] = part["acc"]
    out[:, 6] = part["key"]
    return out
