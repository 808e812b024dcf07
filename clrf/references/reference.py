"""Float64 numpy references of the grid and the shared kernels: the oracle of the tests, and
the grid's gradient self-check compares the device with render_backward at run time.

Same conventions as the OpenCL C sources (see the header of cl/grid_render.cl), written
independently and vectorised over rays: dense arrays instead of links (an empty voxel is a
zero), explicit suffix sums instead of the remaining-radiance accumulator, np.add.at instead
of atomics.
"""
from __future__ import annotations

import numpy as np

T_STOP = 1e-4
COLOR_OFFSET = 0.5
SH_C0 = 0.28209479177387814
SH_C1 = 0.4886025119029199
SH_C2 = (1.0925484305920792, -1.0925484305920792, 0.31539156525252005, -1.0925484305920792,
         0.5462742152960396)
SH_C3 = (-0.5900435899266435, 2.890611442640554, -0.4570457994644658, 0.3731763325901154,
         -0.4570457994644658, 1.445305721320277, -0.5900435899266435)


# ---- safe math (twins of cl/common.h) ----------------------------------------------------
def alpha_of_tau(tau):
    return -np.expm1(-tau)


def sh_basis(dirs, degree: int):
    """Real SH basis [n, (degree+1)^2] at unit directions [n, 3] (cl/sh.h)."""
    d = np.asarray(dirs, np.float64)
    x, y, z = d[:, 0], d[:, 1], d[:, 2]
    out = [np.full_like(x, SH_C0)]
    if degree >= 1:
        out += [-SH_C1 * y, SH_C1 * z, -SH_C1 * x]
    if degree >= 2:
        xx, yy, zz = x * x, y * y, z * z
        out += [SH_C2[0] * x * y, SH_C2[1] * y * z, SH_C2[2] * (2 * zz - xx - yy),
                SH_C2[3] * x * z, SH_C2[4] * (xx - yy)]
    if degree >= 3:
        out += [SH_C3[0] * y * (3 * xx - yy), SH_C3[1] * x * y * z,
                SH_C3[2] * y * (4 * zz - xx - yy), SH_C3[3] * z * (2 * zz - 3 * xx - 3 * yy),
                SH_C3[4] * x * (4 * zz - xx - yy), SH_C3[5] * z * (xx - yy),
                SH_C3[6] * x * (xx - 3 * yy)]
    return np.stack(out, axis=1)


def sh_dir_grad(dirs, w, degree):
    """sum_b w_b dY_b/dd [n, 3] (cl/sh.h sh_dir_grad), by the product rule on
    sh_basis's polynomials, written out per term."""
    x, y, z = dirs[:, 0], dirs[:, 1], dirs[:, 2]
    g = np.zeros_like(dirs)
    if degree >= 1:
        g[:, 0] += -SH_C1 * w[:, 3]
        g[:, 1] += -SH_C1 * w[:, 1]
        g[:, 2] += SH_C1 * w[:, 2]
    if degree >= 2:
        xx, yy, zz = x * x, y * y, z * z
        g[:, 0] += SH_C2[0] * y * w[:, 4] - 2 * SH_C2[2] * x * w[:, 6] + SH_C2[3] * z * w[:, 7] \
            + 2 * SH_C2[4] * x * w[:, 8]
        g[:, 1] += SH_C2[0] * x * w[:, 4] + SH_C2[1] * z * w[:, 5] - 2 * SH_C2[2] * y * w[:, 6] \
            - 2 * SH_C2[4] * y * w[:, 8]
        g[:, 2] += SH_C2[1] * y * w[:, 5] + 4 * SH_C2[2] * z * w[:, 6] + SH_C2[3] * x * w[:, 7]
    if degree >= 3:
        c = SH_C3
        g[:, 0] += (6 * c[0] * x * y * w[:, 9] + c[1] * y * z * w[:, 10]
                    - 2 * c[2] * x * y * w[:, 11] - 6 * c[3] * x * z * w[:, 12]
                    + c[4] * (4 * zz - 3 * xx - yy) * w[:, 13] + 2 * c[5] * x * z * w[:, 14]
                    + c[6] * (3 * xx - 3 * yy) * w[:, 15])
        g[:, 1] += (c[0] * (3 * xx - 3 * yy) * w[:, 9] + c[1] * x * z * w[:, 10]
                    + c[2] * (4 * zz - xx - 3 * yy) * w[:, 11] - 6 * c[3] * y * z * w[:, 12]
                    - 2 * c[4] * x * y * w[:, 13] - 2 * c[5] * y * z * w[:, 14]
                    - 6 * c[6] * x * y * w[:, 15])
        g[:, 2] += (c[1] * x * y * w[:, 10] + 8 * c[2] * y * z * w[:, 11]
                    + c[3] * (6 * zz - 3 * xx - 3 * yy) * w[:, 12] + 8 * c[4] * x * z * w[:, 13]
                    + c[5] * (xx - yy) * w[:, 14])
    return g


def ray_box(o, d, lo, hi):
    """Slab intersection of o + t d (t >= 0) with [lo, hi]: (t0, t1, hit), arrays [n]."""
    n = o.shape[0]
    t0 = np.zeros(n)
    t1 = np.full(n, np.inf)
    with np.errstate(divide="ignore", invalid="ignore"):
        for a in range(3):
            da, oa = d[:, a], o[:, a]
            zero = da == 0
            outside = (oa < lo[a]) | (oa > hi[a])
            ta = np.where(zero, -np.inf, (lo[a] - oa) / np.where(zero, 1, da))
            tb = np.where(zero, np.inf, (hi[a] - oa) / np.where(zero, 1, da))
            t0 = np.maximum(t0, np.minimum(ta, tb))
            t1 = np.minimum(t1, np.maximum(ta, tb))
            t0 = np.where(zero & outside, np.inf, t0)
            t1 = np.where(zero & outside, -np.inf, t1)
    return t0, t1, t1 > t0


def march_setup(origins, dirs, reso, bbox, step):
    """Per-ray march parameters in float64 (cl/grid_render.cl march_setup)."""
    o = np.asarray(origins, np.float64)
    d = np.asarray(dirs, np.float64)
    bbox = np.asarray(bbox, np.float64)
    reso = np.asarray(reso, np.float64)
    mx = np.max(np.abs(d), axis=1)
    ok = mx > 0
    d = d / np.where(ok, mx, 1)[:, None]
    d = d / np.where(ok, np.linalg.norm(d, axis=1), 1)[:, None]
    scale = reso / (bbox[1] - bbox[0])
    og = (o - bbox[0]) * scale
    dg = d * scale
    t0, t1, hit = ray_box(og, dg, np.zeros(3), reso)
    hit &= ok
    dt = step / np.linalg.norm(dg, axis=1)
    length = np.where(hit, t1 - t0, 0.0)
    t0 = np.where(hit, t0, 0.0)
    p0 = np.clip(og + t0[:, None] * dg, 0, reso)
    nsteps = np.where(hit, np.ceil(length / dt), 0).astype(np.int64)
    return dict(p0=p0, dg=dg, dir=d, t0=t0, len=length, dt=dt, nsteps=nsteps, hit=hit & (nsteps > 0))


def trilerp_corners(p, reso):
    """Corner indices [n, 8, 3] and weights [n, 8] of points p (box units), clamped at the edges."""
    reso = np.asarray(reso)
    u = np.clip(p - 0.5, 0, reso - 1)
    i0 = np.minimum(np.floor(u).astype(np.int64), np.maximum(reso - 2, 0))
    i1 = np.minimum(i0 + 1, reso - 1)
    f = u - i0
    idx = np.empty(p.shape[:1] + (8, 3), np.int64)
    w = np.empty(p.shape[:1] + (8,))
    for c in range(8):
        bits = ((c >> 2) & 1, (c >> 1) & 1, c & 1)
        wc = np.ones(p.shape[0])
        for a in range(3):
            idx[:, c, a] = np.where(bits[a], i1[:, a], i0[:, a])
            wc = wc * np.where(bits[a], f[:, a], 1 - f[:, a])
        w[:, c] = wc
    return idx, w


def _samples(density, sh, m, k, rays):
    """Values at segment k of the given rays."""
    s0 = k * m["dt"][rays]
    s1 = np.minimum((k + 1) * m["dt"][rays], m["len"][rays])
    mid = 0.5 * (s0 + s1)
    delta = s1 - s0
    p = m["p0"][rays] + mid[:, None] * m["dg"][rays]
    idx, w = trilerp_corners(p, density.shape)
    dens_c = density[idx[..., 0], idx[..., 1], idx[..., 2]]            # [n, 8]
    sh_c = sh[idx[..., 0], idx[..., 1], idx[..., 2]]                   # [n, 8, C]
    sigma_raw = np.sum(w * dens_c, axis=1)
    co = np.einsum("nc,ncj->nj", w, sh_c)
    return mid, delta, idx, w, sigma_raw, co


def render_forward(density, sh, bbox, origins, dirs, step=0.5, background=(1, 1, 1),
                   t_stop=T_STOP, record=False):
    """Float64 render of dense density [X,Y,Z] and sh [X,Y,Z,3B]. Returns rgb, depth, acc.

    background: three numbers, or [n, 3] (one colour per ray: BG_PER_RAY); rgb includes
    T_end * background. With record=True also returns the per-sample arrays the backward
    reference needs and ``T_end`` [n].
    """
    density = np.asarray(density, np.float64)
    sh = np.asarray(sh, np.float64)
    B = sh.shape[-1] // 3
    degree = int(round(np.sqrt(B))) - 1
    m = march_setup(origins, dirs, density.shape, bbox, step)
    n = m["p0"].shape[0]
    Y = sh_basis(m["dir"], degree)
    bg = np.broadcast_to(np.asarray(background, np.float64), (n, 3))
    rgb = np.zeros((n, 3))
    acc = np.zeros(n)
    depth = np.zeros(n)
    logT = np.zeros(n)
    alive = m["hit"].copy()
    kmax = int(m["nsteps"].max(initial=0))
    rec = []
    for k in range(kmax):
        rays = np.nonzero(alive & (k < m["nsteps"]))[0]
        if rays.size == 0:
            break
        mid, delta, idx, w, sigma_raw, co = _samples(density, sh, m, k, rays)
        sigma = np.maximum(sigma_raw, 0.0)
        tau = sigma * delta
        pre = np.einsum("ncb,nb->nc", co.reshape(-1, 3, B), Y[rays]) + COLOR_OFFSET
        c = np.maximum(pre, 0.0)
        wgt = np.exp(logT[rays]) * alpha_of_tau(tau)
        rgb[rays] += wgt[:, None] * c
        acc[rays] += wgt
        depth[rays] += wgt * (m["t0"][rays] + mid)
        logT[rays] -= tau
        if record:
            rec.append(dict(rays=rays, t=m["t0"][rays] + mid, delta=delta, idx=idx, w=w,
                            sigma_raw=sigma_raw,
                            pre=pre, c=c, wgt=wgt, Tnext=np.exp(logT[rays])))
        stop = rays[np.exp(logT[rays]) < t_stop]
        alive[stop] = False
    T_end = np.exp(logT)
    rgb = rgb + T_end[:, None] * bg
    out = dict(rgb=rgb, depth=depth, acc=acc)
    if record:
        out.update(_rec=rec, _Y=Y, _T_end=T_end, _bg=bg, T_end=T_end)
    return out


def render_backward(density, sh, bbox, origins, dirs, grad_rgb, step=0.5, background=(1, 1, 1),
                    t_stop=T_STOP, mask=None, grad_T=None):
    """Analytic gradient of sum(grad_rgb * rgb) w.r.t. dense density and sh (float64), and
    ``background`` [n, 3] = T_end g, the gradient w.r.t. a per-ray background (background
    may be three numbers or [n, 3]; summed over rays this is the constant's gradient).

    Uses explicit suffix sums S_k = sum_{j>k} w_j (g.c_j) + T_end (g.bg). ``mask`` [X,Y,Z]
    marks the allocated voxels (default: where any value is non-zero, as SparseGrid.from_dense
    allocates); the others are constants and get no gradient. ``grad_T`` [n] adds a loss
    term's derivative with respect to each ray's final transmittance (e.g. beta_grad_T).
    """
    density = np.asarray(density, np.float64)
    sh = np.asarray(sh, np.float64)
    B = sh.shape[-1] // 3
    g = np.asarray(grad_rgb, np.float64)
    f = render_forward(density, sh, bbox, origins, dirs, step, background, t_stop, record=True)
    rec, Y, T_end, bg = f["_rec"], f["_Y"], f["_T_end"], f["_bg"]
    n = g.shape[0]
    K = len(rec)
    # per-ray, per-step contributions w_k (g.c_k), laid out [n, K] to take suffix sums
    wgc = np.zeros((n, K))
    for k, r in enumerate(rec):
        wgc[r["rays"], k] = r["wgt"] * np.sum(g[r["rays"]] * r["c"], axis=1)
    suffix = np.cumsum(wgc[:, ::-1], axis=1)[:, ::-1]           # sum_{j>=k}
    after = suffix - wgc                                        # sum_{j>k}
    bgterm = T_end * (np.sum(g * bg, axis=1)
                      + (0.0 if grad_T is None else np.asarray(grad_T, np.float64)))
    gd = np.zeros_like(density)
    gs = np.zeros_like(sh)
    for k, r in enumerate(rec):
        rays = r["rays"]
        gc = np.sum(g[rays] * r["c"], axis=1)
        S = after[rays, k] + bgterm[rays]
        dsig = r["delta"] * (r["Tnext"] * gc - S) * (r["sigma_raw"] > 0)
        idx, w = r["idx"], r["w"]
        np.add.at(gd, (idx[..., 0], idx[..., 1], idx[..., 2]), w * dsig[:, None])
        dpre = r["wgt"][:, None] * g[rays] * (r["pre"] > 0) * (r["sigma_raw"] > 0)[:, None]
        dco = (dpre[:, :, None] * Y[rays][:, None, :]).reshape(len(rays), 3 * B)
        np.add.at(gs, (idx[..., 0], idx[..., 1], idx[..., 2]), w[..., None] * dco[:, None, :])
    if mask is None:
        mask = (density != 0) | np.any(sh != 0, axis=-1)
    return dict(density=gd * mask, sh=gs * mask[..., None], background=T_end[:, None] * g)


# ---- each ray's gradient with respect to its origin and direction (GRID_POSE_GRAD) ---------
def trilerp_weight_grad(p, reso):
    """dw_c/dp [n, 8, 3] of trilerp_corners' weights at points p [n, 3] (box units): 0 along
    an axis where the interpolation is clamped (the outer half voxels, a 1-voxel axis)."""
    reso = np.asarray(reso)
    u = np.clip(p - 0.5, 0, reso - 1)
    i0 = np.minimum(np.floor(u).astype(np.int64), np.maximum(reso - 2, 0))
    f = u - i0
    raw = p - 0.5
    slope = ((reso >= 2) & (raw > 0) & (raw < reso - 1)).astype(np.float64)
    out = np.empty(p.shape[:1] + (8, 3))
    for c in range(8):
        bits = ((c >> 2) & 1, (c >> 1) & 1, c & 1)
        wa = [np.where(bits[a], f[:, a], 1 - f[:, a]) for a in range(3)]
        da = [np.where(bits[a], 1.0, -1.0) * slope[:, a] for a in range(3)]
        out[:, c, 0] = da[0] * wa[1] * wa[2]
        out[:, c, 1] = wa[0] * da[1] * wa[2]
        out[:, c, 2] = wa[0] * wa[1] * da[2]
    return out


def held_samples(density, sh, bbox, origins, dirs, step=0.5, t_stop=T_STOP):
    """The samples render_forward takes, as (t, delta, live) [n, K]: each one's world distance
    along the unit direction, its segment length, and whether it is there (the march of a
    ray stops at T < t_stop). What GRID_POSE_GRAD holds constant while the ray moves."""
    f = render_forward(density, sh, bbox, origins, dirs, step, (0, 0, 0), t_stop, record=True)
    n, K = np.asarray(origins).shape[0], len(f["_rec"])
    t, delta, live = np.zeros((n, K)), np.zeros((n, K)), np.zeros((n, K), bool)
    for k, r in enumerate(f["_rec"]):
        t[r["rays"], k], delta[r["rays"], k], live[r["rays"], k] = r["t"], r["delta"], True
    return t, delta, live


def render_held(density, sh, bbox, origins, dirs, t, delta, live, background=(1, 1, 1),
                grad_rgb=None, grad_T=None, magnitude=False):
    """rgb [n, 3] of rays (origins, dirs) through samples at the given distances ``t`` along
    each unit direction with segment lengths ``delta`` (``held_samples``), no termination: the
    renderer's function of the ray with its sample distances held. With ``grad_rgb`` also the
    gradient of sum(grad_rgb * rgb) (+ grad_T [n] times each ray's T_end) with respect to
    (origin, direction) [n, 6] (cl/grid_render.cl GRID_POSE_GRAD, derived here independently:
    suffix sums, dense corner arrays). With ``magnitude`` also [n]: per ray the sum of the
    magnitudes of the terms the gradient adds up (each sample's corner terms, dL/dsigma's
    as |remaining radiance| + |T g.c|, times 1 + t_k, and the SH direction terms; over |d|
    where |d| < 1): the scale of a float32 evaluation's rounding (tests' tolerances)."""
    density = np.asarray(density, np.float64)
    sh = np.asarray(sh, np.float64)
    B = sh.shape[-1] // 3
    degree = int(round(np.sqrt(B))) - 1
    o, d = np.asarray(origins, np.float64), np.asarray(dirs, np.float64)
    n, K = t.shape
    dn = np.linalg.norm(d, axis=1)
    dh = d / np.where(dn > 0, dn, 1)[:, None]
    bbox = np.asarray(bbox, np.float64)
    reso = np.asarray(density.shape)
    scale = reso / (bbox[1] - bbox[0])
    Y = sh_basis(dh, degree)
    bg = np.broadcast_to(np.asarray(background, np.float64), (n, 3))
    rgb, logT, rec = np.zeros((n, 3)), np.zeros(n), []
    for k in range(K):
        rays = np.nonzero(live[:, k])[0]
        if rays.size == 0:
            continue
        p = (o[rays] + t[rays, k, None] * dh[rays] - bbox[0]) * scale
        idx, w = trilerp_corners(p, reso)
        dens_c = density[idx[..., 0], idx[..., 1], idx[..., 2]]
        sh_c = sh[idx[..., 0], idx[..., 1], idx[..., 2]]
        sigma_raw = np.sum(w * dens_c, axis=1)
        co = np.einsum("nc,ncj->nj", w, sh_c)
        pre = np.einsum("ncb,nb->nc", co.reshape(-1, 3, B), Y[rays]) + COLOR_OFFSET
        c = np.maximum(pre, 0.0)
        tau = np.maximum(sigma_raw, 0.0) * delta[rays, k]
        wgt = np.exp(logT[rays]) * alpha_of_tau(tau)
        rgb[rays] += wgt[:, None] * c
        logT[rays] -= tau
        rec.append(dict(k=k, rays=rays, p=p, dens_c=dens_c, sh_c=sh_c, sigma_raw=sigma_raw,
                        co=co, pre=pre, c=c, wgt=wgt, Tnext=np.exp(logT[rays])))
    T_end = np.exp(logT)
    rgb = rgb + T_end[:, None] * bg
    if grad_rgb is None:
        return rgb
    g = np.asarray(grad_rgb, np.float64)
    wgc = np.zeros((n, K))
    for r in rec:
        wgc[r["rays"], r["k"]] = r["wgt"] * np.sum(g[r["rays"]] * r["c"], axis=1)
    after = np.cumsum(wgc[:, ::-1], axis=1)[:, ::-1] - wgc          # sum_{j>k}
    after_abs = np.cumsum(np.abs(wgc)[:, ::-1], axis=1)[:, ::-1]    # sum_{j>=k} |.|
    bgterm = T_end * (np.sum(g * bg, axis=1)
                      + (0.0 if grad_T is None else np.asarray(grad_T, np.float64)))
    g_o, g_dh, g_Y = np.zeros((n, 3)), np.zeros((n, 3)), np.zeros((n, B))
    mag, mag_Y = np.zeros(n), np.zeros((n, B))
    for r in rec:
        rays, k, m = r["rays"], r["k"], r["rays"].size
        on = r["sigma_raw"] > 0
        gc = np.sum(g[rays] * r["c"], axis=1)
        dsig = delta[rays, k] * (r["Tnext"] * gc - (after[rays, k] + bgterm[rays])) * on
        dpre = r["wgt"][:, None] * g[rays] * (r["pre"] > 0) * on[:, None]
        q = np.einsum("mcjb,mb->mcj", r["sh_c"].reshape(m, 8, 3, B), Y[rays])   # corner colours
        s_c = dsig[:, None] * r["dens_c"] + np.einsum("mj,mcj->mc", dpre, q)
        dw = trilerp_weight_grad(r["p"], reso)
        gx = np.einsum("mc,mca->ma", s_c, dw) * scale
        g_o[rays] += gx
        g_dh[rays] += t[rays, k, None] * gx
        g_Y[rays] += np.einsum("mj,mjb->mb", dpre, r["co"].reshape(m, 3, B))
        if magnitude:
            dsig_mag = delta[rays, k] * (r["Tnext"] * np.abs(gc) + after_abs[rays, k]
                                         + np.abs(bgterm[rays])) * on
            s_mag = (dsig_mag[:, None] * np.abs(r["dens_c"])
                     + np.einsum("mj,mcj->mc", np.abs(dpre), np.abs(q)))
            term = np.einsum("mc,mca->m", s_mag, np.abs(dw) * scale)
            mag[rays] += (1.0 + np.abs(t[rays, k])) * term
            mag_Y[rays] += np.einsum("mj,mjb->mb", np.abs(dpre),
                                     np.abs(r["co"].reshape(m, 3, B)))
    g_dh += sh_dir_grad(dh, g_Y, degree)
    g_d = (g_dh - dh * np.sum(dh * g_dh, axis=1, keepdims=True)) / np.where(dn > 0, dn, 1)[:, None]
    out = np.concatenate([g_o, g_d], axis=1)
    if not magnitude:
        return rgb, out
    mag += np.sum(np.abs(sh_dir_grad(np.abs(dh), mag_Y, degree)), axis=1)
    return rgb, out, mag * np.maximum(1.0, 1.0 / np.where(dn > 0, dn, 1))


def ray_grad(density, sh, bbox, origins, dirs, grad_rgb, step=0.5, background=(1, 1, 1),
             t_stop=T_STOP, grad_T=None):
    """[n, 6] float64 twin of render_backward's ray_grad (GRID_POSE_GRAD): the gradient of
    sum(grad_rgb * rgb) with respect to each ray's origin and direction, the sample distances
    of render_forward's march held (``held_samples``, ``render_held``)."""
    t, delta, live = held_samples(density, sh, bbox, origins, dirs, step, t_stop)
    return render_held(density, sh, bbox, origins, dirs, t, delta, live, background, grad_rgb,
                       grad_T)[1]


def ray_exit(origins, dirs, reso, bbox, step=0.5):
    """Float64 twin of cl/grid_render.cl ray_exit: box exit distance along the unit direction,
    0 where the ray misses the box."""
    m = march_setup(origins, dirs, reso, bbox, step)
    return np.where(m["hit"], m["t0"] + m["len"], 0.0)


BETA_EPS = 1e-3


def beta_loss(T, scale, eps=BETA_EPS):
    """Beta prior of final transmittances T: scale * sum[log(T + eps) + log(1 - T + eps)]."""
    T = np.asarray(T, np.float64)
    return scale * np.sum(np.log(T + eps) + np.log(1 - T + eps))


def beta_grad_T(T, scale, eps=BETA_EPS):
    T = np.asarray(T, np.float64)
    return scale * (1 / (T + eps) - 1 / (1 - T + eps))


def max_weight(density, bbox, origins, dirs, step=0.5, t_stop=T_STOP):
    """Dense [X,Y,Z]: max over rays and samples of w_sample * w_corner (render_max_weight)."""
    density = np.asarray(density, np.float64)
    sh = np.zeros(density.shape + (3,))
    f = render_forward(density, sh, bbox, origins, dirs, step, (0, 0, 0), t_stop, record=True)
    out = np.zeros_like(density)
    for r in f["_rec"]:
        idx, w = r["idx"], r["w"]
        vals = w * (r["wgt"] * (r["sigma_raw"] > 0))[:, None]
        np.maximum.at(out, (idx[..., 0], idx[..., 1], idx[..., 2]), vals)
    return out


def finite_difference(density, sh, bbox, origins, dirs, grad_rgb, which, index, eps=1e-4,
                      **kw):
    """Central difference of sum(grad_rgb * rgb) w.r.t. one dense entry (float64); which is
    "density", "sh" or "background" (a per-ray background [n, 3] passed as background=)."""
    arrs = {"density": np.array(density, np.float64), "sh": np.array(sh, np.float64)}
    if which == "background":
        arrs["background"] = np.array(kw.pop("background"), np.float64)

    def loss(delta):
        a = {k: v.copy() for k, v in arrs.items()}
        a[which][index] += delta
        if "background" in a:
            kw["background"] = a["background"]
        out = render_forward(a["density"], a["sh"], bbox, origins, dirs, **kw)
        return float(np.sum(np.asarray(grad_rgb, np.float64) * out["rgb"]))

    return (loss(eps) - loss(-eps)) / (2 * eps)


# ---- optimiser, regularisers, structure changes (cl/optim.cl, cl/grid_ops.cl) -------------
GRAD_CLAMP = 1e18


def update_rows(param, grad, state, touched, lr, beta=0.95, eps=1e-8, mode="rmsprop",
                columns=None):
    """Float64 twin of update_rows: returns (param, state); rows not touched are unchanged,
    nor columns j with j % group >= live (``columns`` (group, live); None: all step)."""
    p = np.array(param, np.float64)
    s = np.array(state, np.float64)
    g = np.asarray(grad, np.float64)
    g = np.clip(np.where(np.isnan(g), 0.0, g), -GRAD_CLAMP, GRAD_CLAMP)   # NaN: skipped like 0
    t = np.asarray(touched, bool)
    if p.ndim == 1:
        p, s, g = p[:, None], s[:, None], g[:, None]
    m = t[:, None] & (g != 0)
    if columns is not None:
        m &= (np.arange(p.shape[1]) % int(columns[0]) < int(columns[1]))[None, :]
    if mode == "rmsprop":
        s_new = np.where(s == 0, g * g, beta * s + (1 - beta) * g * g)
        s = np.where(m, s_new, s)
        p = np.where(m, p - lr * g / (np.sqrt(s) + eps), p)
    else:
        p = np.where(m, p - lr * g, p)
    return p.reshape(np.shape(param)), s.reshape(np.shape(state))


def tv_grad(alloc, data, start, n_cells, scale, empty_is_zero, lambda_sparsity=0.0, eps=1e-9):
    """Float64 TV (+ Cauchy sparsity) gradient, dense [X,Y,Z,D], over a wrapped cell window."""
    alloc = np.asarray(alloc, bool)
    v = np.asarray(data, np.float64)
    if v.ndim == 3:
        v = v[..., None]
    X, Y, Z = alloc.shape
    total = X * Y * Z
    grad = np.zeros_like(v)
    cells = (start + np.arange(min(n_cells, total))) % total
    xs, ys, zs = np.unravel_index(cells, alloc.shape)
    sel = alloc[xs, ys, zs]
    xs, ys, zs = xs[sel], ys[sel], zs[sel]
    c = v[xs, ys, zs]                                            # [m, D]
    diffs, nbrs = [], []
    for a, (dx, dy, dz) in enumerate(((1, 0, 0), (0, 1, 0), (0, 0, 1))):
        nx, ny, nz = xs + dx, ys + dy, zs + dz
        inside = (nx < X) & (ny < Y) & (nz < Z)
        nxc, nyc, nzc = np.minimum(nx, X - 1), np.minimum(ny, Y - 1), np.minimum(nz, Z - 1)
        nal = inside & alloc[nxc, nyc, nzc]
        va = np.where(nal[:, None], v[nxc, nyc, nzc], c)
        if empty_is_zero:
            va = np.where((inside & ~nal)[:, None], 0.0, va)
        diffs.append(va - c)
        nbrs.append((nal, nxc, nyc, nzc))
    r = np.sqrt(eps + sum(d * d for d in diffs))
    np.add.at(grad, (xs, ys, zs), -sum(diffs) * scale / r)
    for d, (nal, nx, ny, nz) in zip(diffs, nbrs):
        np.add.at(grad, (nx[nal], ny[nal], nz[nal]), (d * scale / r)[nal])
    if lambda_sparsity > 0 and v.shape[-1] == 1:
        s = c[:, 0]
        np.add.at(grad[..., 0], (xs, ys, zs), lambda_sparsity * 4 * s / (1 + 2 * s * s))
    return grad


def prune_keep(alloc, maxw, density, weight_thresh, density_thresh=np.inf, dilate=True):
    """Dense bool mask of kept voxels (threshold, then 26-neighbourhood dilation)."""
    alloc = np.asarray(alloc, bool)
    keep = alloc & ((np.asarray(maxw) >= weight_thresh) | (np.asarray(density) >= density_thresh))
    if not dilate:
        return keep
    X, Y, Z = alloc.shape
    pad = np.pad(keep, 1)
    out = np.zeros_like(keep)
    for dx in (-1, 0, 1):
        for dy in (-1, 0, 1):
            for dz in (-1, 0, 1):
                out |= pad[1 + dx:1 + dx + X, 1 + dy:1 + dy + Y, 1 + dz:1 + dz + Z]
    return out & alloc


def resample(density, sh, keep, new_reso):
    """Float64 resample of the kept voxels: (density, sh, alloc) dense at new_reso."""
    density = np.asarray(density, np.float64)
    sh = np.asarray(sh, np.float64)
    keep = np.asarray(keep, bool)
    old = np.array(density.shape)
    new = np.array(new_reso)
    g = np.stack(np.meshgrid(*[np.arange(r) for r in new], indexing="ij"), -1).reshape(-1, 3)
    p = (g + 0.5) * old / new
    idx, w = trilerp_corners(p, old)
    kc = keep[idx[..., 0], idx[..., 1], idx[..., 2]]
    w = w * kc
    alloc = np.any(kc & (w > 0), axis=1)
    d = np.sum(w * density[idx[..., 0], idx[..., 1], idx[..., 2]], axis=1)
    s = np.einsum("nc,ncj->nj", w, sh[idx[..., 0], idx[..., 1], idx[..., 2]])
    shape = tuple(new)
    return (np.where(alloc, d, 0).reshape(shape), (s * alloc[:, None]).reshape(shape + (-1,)),
            alloc.reshape(shape))


def pcg_hash(x):
    x = np.asarray(x, np.uint64) & 0xFFFFFFFF
    state = (x * 747796405 + 2891336453) & 0xFFFFFFFF
    word = (((state >> ((state >> 28) + 4)) ^ state) * 277803737) & 0xFFFFFFFF
    return ((word >> 22) ^ word) & 0xFFFFFFFF


def batch_indices(seed, n, n_src):
    """Source ray indices of batch slots 0..n-1 (cl/batch.cl gather_batch)."""
    h = pcg_hash(np.uint64(seed) ^ pcg_hash(np.arange(n, dtype=np.uint64)))
    return ((h * np.uint64(n_src)) >> np.uint64(32)).astype(np.int64)


def recomposite(colours, alpha, old_bg, new_bg):
    """Colours of an RGBA capture composited on old_bg, moved onto new_bg (cl/batch.cl
    recomposite): c + (1 - alpha) (new_bg - old_bg), float64."""
    c = np.asarray(colours, np.float64)
    clear = 1.0 - np.asarray(alpha, np.float64)[:, None]
    return c + clear * (np.asarray(new_bg, np.float64) - np.asarray(old_bg, np.float64))


# NeRF references (encoding, MLP, sampling, compositing, Adam) live in their own module.
from .reference_nerf import *  # noqa: E402,F401,F403
