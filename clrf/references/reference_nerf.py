"""Float64 numpy references of the NeRF kernels (encode, MLP, sampling, compositing): the test
oracle. Not on any runtime path; clrf.references.reference re-exports these.

Conventions are those of the OpenCL sources (see the headers of cl/encode.cl, cl/mlp.cl,
cl/sample.cl, cl/composite.cl), written independently and vectorised over samples: whole-batch
matrix products instead of register tiles, activation derivatives from the pre-activations
(the kernels use the outputs), explicit suffix sums instead of the remaining-radiance
accumulator, searchsorted instead of the CDF walk.
"""
from __future__ import annotations

import numpy as np

__all__ = ["hash_u32", "uniform01", "encode", "encode_backward", "mlp_forward", "mlp_backward",
           "sample_stratified", "sample_importance", "importance_cdf", "merge_sorted",
           "ray_points", "ray_points_grad", "composite_forward", "composite_backward",
           "composite_state", "numeric_gradient", "PDF_PAD"]

PDF_PAD = 1e-5   # cl/sample.cl PDF_PAD
_M32 = np.uint64(0xFFFFFFFF)


# ---- random numbers (twins of cl/common.h) ----------------------------------------------
def hash_u32(x):
    """lowbias32 integer hash, bit-exact with cl/common.h (uint32 arithmetic mod 2^32)."""
    x = np.asarray(x, np.uint64) & _M32
    x ^= x >> np.uint64(16)
    x = (x * np.uint64(0x7FEB352D)) & _M32
    x ^= x >> np.uint64(15)
    x = (x * np.uint64(0x846CA68B)) & _M32
    x ^= x >> np.uint64(16)
    return x


def uniform01(key, counter):
    """[0, 1) with 24 bits, bit-exact with cl/common.h uniform01."""
    h = hash_u32(np.uint64(key) ^ hash_u32(counter))
    return (h >> np.uint64(8)).astype(np.float64) * 2.0 ** -24


# ---- positional encoding ------------------------------------------------------------------
def _scaled(x, scale, exact=False):
    """p = scale * x rounded once to float32, as the kernel computes it, then in float64;
    ``exact``: in float64 throughout (a smooth function of x, for finite differences)."""
    if exact:
        return float(np.float32(scale)) * np.asarray(x, np.float64)
    return (np.float32(scale) * np.asarray(x, np.float32)).astype(np.float64)


def _sincospi(y):
    r = np.fmod(y, 2.0)               # exact: the phase modulo one period, before the pi factor
    return np.sin(np.pi * r), np.cos(np.pi * r)


def encode(x, n_freqs: int, include_input: bool = True, scale: float = 1.0, exact=False):
    """gamma(x) [n, 3*include_input + 6*n_freqs] (cl/encode.cl); ``exact``: ``_scaled``."""
    p = _scaled(x, scale, exact)
    out = [p] if include_input else []
    for k in range(n_freqs):
        s, c = _sincospi(2.0 ** k * p)
        out += [s, c]
    return np.concatenate(out, axis=1) if out else np.zeros((p.shape[0], 0))


def encode_backward(x, grad_out, n_freqs: int, include_input: bool = True, scale: float = 1.0,
                    exact=False):
    """dL/dx [n, 3] from dL/dgamma: d/dx of p, sin(2^k pi p), cos(2^k pi p) with p = s x is
    s, 2^k pi s cos(2^k pi p), -2^k pi s sin(2^k pi p); ``exact``: ``_scaled``."""
    p = _scaled(x, scale, exact)
    g = np.asarray(grad_out, np.float64)
    i0 = 3 if include_input else 0
    dp = g[:, :3].copy() if include_input else np.zeros_like(p)
    for k in range(n_freqs):
        s, c = _sincospi(2.0 ** k * p)
        gs, gc = g[:, i0 + 6 * k: i0 + 6 * k + 3], g[:, i0 + 6 * k + 3: i0 + 6 * k + 6]
        dp += 2.0 ** k * np.pi * (c * gs - s * gc)
    return float(np.float32(scale)) * dp


# ---- MLP ----------------------------------------------------------------------------------
def _act(x, name):
    if name == "relu":
        return np.maximum(x, 0.0)
    if name == "softplus":
        return np.logaddexp(x, 0.0)
    if name == "sigmoid":
        return 0.5 * (1.0 + np.tanh(0.5 * x))
    if name == "trunc_exp":             # cl/mlp.cl ACT_TRUNC_EXP
        return np.exp(np.minimum(x, 15.0))
    return x


def _act_grad(x, name):
    """d act / dx at the pre-activation x."""
    if name == "relu":
        return (x > 0).astype(np.float64)
    if name == "softplus":
        return _act(x, "sigmoid")
    if name == "sigmoid":
        s = _act(x, "sigmoid")
        return s * (1 - s)
    if name == "trunc_exp":             # exp at the clamped value, also beyond the clamp
        return np.exp(np.minimum(x, 15.0))
    return np.ones_like(x)


def _layers(params, layout):
    p = np.asarray(params, np.float64)
    out = []
    for L in layout.layers:
        Wm = p[L["w_off"]:L["b_off"]].reshape(L["nout"], L["nin"])
        out.append((Wm, p[L["b_off"]:L["b_off"] + L["nout"]]))
    return out


def _layer_acts(spec, layout):
    """Activation per output column of every layer (the head: sigma_act on column 0 only)."""
    D = spec.depth
    acts = []
    for l, L in enumerate(layout.layers):
        if l < D or D < l < layout.n_layers - 1:      # trunk and colour hidden layers
            a = [spec.hidden_act] * L["nout"]
        elif l == D:
            a = [spec.sigma_act] + ["none"] * (L["nout"] - 1)
        else:
            a = ["sigmoid"] * L["nout"]
        acts.append(np.array(a))
    return acts


def _apply(z, acts, grad=False):
    out = np.empty_like(z)
    for name in set(acts.tolist()):
        cols = acts == name
        out[:, cols] = (_act_grad if grad else _act)(z[:, cols], name)
    return out


def mlp_forward(params, spec, layout, x_enc, d_enc, record=False):
    """sigma [n], rgb [n, 3] of the padded-layout MLP in float64 (cl/mlp.cl)."""
    x = np.asarray(x_enc, np.float64)
    d = np.asarray(d_enc, np.float64)
    n = x.shape[0]
    S = np.zeros((n, layout.nslot))          # slot values, as the kernel's scratch row A
    sl = layout.slots
    S[:, sl["SL_X"]:sl["SL_X"] + spec.in_dim] = x
    if sl["SL_XS"] >= 0:
        S[:, sl["SL_XS"]:sl["SL_XS"] + spec.in_dim] = x
    S[:, sl["SL_DV"]:sl["SL_DV"] + spec.dir_dim] = d
    pre = []
    for (Wm, b), L, acts in zip(_layers(params, layout), layout.layers, _layer_acts(spec, layout)):
        z = S[:, L["in_off"]:L["in_off"] + L["nin"]] @ Wm.T + b
        pre.append(z)
        S[:, L["out_off"]:L["out_off"] + L["nout"]] = _apply(z, acts)
    sigma = S[:, sl["SL_HD"]].copy()
    rgb = S[:, sl["SL_RGB"]:sl["SL_RGB"] + 3].copy()
    if record:
        return sigma, rgb, S, pre
    return sigma, rgb


def mlp_backward(params, spec, layout, x_enc, d_enc, dsigma, drgb):
    """Analytic gradients of sum(dsigma*sigma) + sum(drgb*rgb): dict(params [n_params] in the
    packed layout, x_enc [n, in_dim], d_enc [n, dir_dim])."""
    sigma, rgb, S, pre = mlp_forward(params, spec, layout, x_enc, d_enc, record=True)
    Gv = np.zeros_like(S)                    # dL/d(slot value)
    sl = layout.slots
    Gv[:, sl["SL_HD"]] = dsigma
    Gv[:, sl["SL_RGB"]:sl["SL_RGB"] + 3] = drgb
    grad = np.zeros(layout.n_params)
    layers = _layers(params, layout)
    acts = _layer_acts(spec, layout)
    for l in reversed(range(layout.n_layers)):
        L = layout.layers[l]
        Wm, _ = layers[l]
        gz = Gv[:, L["out_off"]:L["out_off"] + L["nout"]] * _apply(pre[l], acts[l], grad=True)
        xin = S[:, L["in_off"]:L["in_off"] + L["nin"]]
        grad[L["w_off"]:L["b_off"]] = (gz.T @ xin).ravel()
        grad[L["b_off"]:L["b_off"] + L["nout"]] = gz.sum(axis=0)
        Gv[:, L["in_off"]:L["in_off"] + L["nin"]] += gz @ Wm
    dx = Gv[:, sl["SL_X"]:sl["SL_X"] + spec.in_dim].copy()
    if sl["SL_XS"] >= 0:
        dx += Gv[:, sl["SL_XS"]:sl["SL_XS"] + spec.in_dim]
    dd = Gv[:, sl["SL_DV"]:sl["SL_DV"] + spec.dir_dim].copy()
    return dict(params=grad, x_enc=dx, d_enc=dd)


# ---- sampling -----------------------------------------------------------------------------
def sample_stratified(n, K, near, far, jitter=False, key=0):
    k = np.arange(K, dtype=np.float64)[None, :]
    counter = np.arange(n * K, dtype=np.uint64).reshape(n, K)
    u = uniform01(key, counter) if jitter else np.full((n, K), 0.5)
    return near + (far - near) * (k + u) / K


def sample_importance(t_c, w, Nf, near, far, jitter=False, key=0):
    """Inverse-CDF samples [n, Nf] from coarse distances t_c [n, Kc] and weights w [n, Kc]."""
    t_c = np.asarray(t_c, np.float64)
    w = np.nan_to_num(np.asarray(w, np.float64), nan=0.0)
    n, Kc = t_c.shape
    edges = np.concatenate([np.full((n, 1), near), 0.5 * (t_c[:, 1:] + t_c[:, :-1]),
                            np.full((n, 1), far)], axis=1)
    p = np.maximum(w, 0.0) + PDF_PAD
    cdf = np.concatenate([np.zeros((n, 1)), np.cumsum(p, axis=1)], axis=1)
    counter = np.arange(n * Nf, dtype=np.uint64).reshape(n, Nf)
    v = uniform01(key, counter) if jitter else np.full((n, Nf), 0.5)
    target = (np.arange(Nf)[None, :] + v) / Nf * cdf[:, -1:]
    out = np.empty((n, Nf))
    for i in range(n):
        b = np.clip(np.searchsorted(cdf[i], target[i], side="right") - 1, 0, Kc - 1)
        frac = np.clip((target[i] - cdf[i, b]) / p[i, b], 0.0, 1.0)
        out[i] = edges[i, b] + (edges[i, b + 1] - edges[i, b]) * frac
    return np.clip(out, near, far)


def importance_cdf(t_c, w, near, far, t):
    """The (unnormalised) CDF of the importance pdf of each ray, evaluated at t [n, M]: the
    well-conditioned quantity to compare samples in (a sample in a nearly empty bin moves a lot
    for a tiny change of the CDF)."""
    t_c = np.asarray(t_c, np.float64)
    w = np.nan_to_num(np.asarray(w, np.float64), nan=0.0)
    n = t_c.shape[0]
    edges = np.concatenate([np.full((n, 1), near), 0.5 * (t_c[:, 1:] + t_c[:, :-1]),
                            np.full((n, 1), far)], axis=1)
    cdf = np.concatenate([np.zeros((n, 1)), np.cumsum(np.maximum(w, 0.0) + PDF_PAD, axis=1)],
                         axis=1)
    return np.stack([np.interp(t[i], edges[i], cdf[i]) for i in range(n)]), cdf[:, -1]


def merge_sorted(a, b):
    return np.sort(np.concatenate([a, b], axis=1), axis=1, kind="stable")


def ray_points(origins, dirs, t):
    o = np.asarray(origins, np.float64)
    d = np.asarray(dirs, np.float64)
    d = d / np.linalg.norm(d, axis=1, keepdims=True)
    t = np.asarray(t, np.float64)
    x = o[:, None, :] + t[..., None] * d[:, None, :]
    return x.reshape(-1, 3), np.repeat(d, t.shape[1], axis=0)


def ray_points_grad(dirs, t, gx, gv):
    """dL/d(origin, direction) [n, 6] of rays whose samples x_k = o + t_k d / |d|, seen along
    v_k = d / |d| (``ray_points``), got dL/dx gx [n*K, 3] and dL/dv gv [n*K, 3]; t [n, K]
    held constant (cl/sample.cl ray_points_backward)."""
    d = np.asarray(dirs, np.float64)
    length = np.linalg.norm(d, axis=1)
    dh = d / length[:, None]
    t = np.asarray(t, np.float64)
    n, K = t.shape
    gx = np.asarray(gx, np.float64).reshape(n, K, 3)
    gv = np.asarray(gv, np.float64).reshape(n, K, 3)
    go = gx.sum(axis=1)
    gdh = np.einsum("nk,nkc->nc", t, gx) + gv.sum(axis=1)
    gd = (gdh - dh * np.sum(dh * gdh, axis=1, keepdims=True)) / length[:, None]
    return np.concatenate([go, gd], axis=1)


# ---- compositing --------------------------------------------------------------------------
def _deltas(t, far):
    t = np.asarray(t, np.float64)
    nxt = np.concatenate([t[:, 1:], np.full((t.shape[0], 1), far)], axis=1)
    return np.maximum(nxt - t, 0.0)


def composite_forward(t, sigma, rgb, far, background=(0, 0, 0)):
    """rgb [n,3], depth [n], acc [n], weights [n,K] of per-sample lists (cl/composite.cl).
    sigma [n, K], rgb [n, K, 3]."""
    sig = np.asarray(sigma, np.float64)
    sig = np.where(sig > 0, sig, 0.0)
    c = np.asarray(rgb, np.float64)
    tau = sig * _deltas(t, far)
    logT = -np.concatenate([np.zeros((tau.shape[0], 1)), np.cumsum(tau, axis=1)], axis=1)
    w = np.exp(logT[:, :-1]) * -np.expm1(-tau)
    bg = np.broadcast_to(np.asarray(background, np.float64), (3,))
    T_end = np.exp(logT[:, -1])
    col = np.einsum("nk,nkc->nc", w, c) + T_end[:, None] * bg
    return dict(rgb=col, depth=np.sum(w * np.asarray(t, np.float64), axis=1), acc=w.sum(axis=1),
                weights=w, T_end=T_end, Tnext=np.exp(logT[:, 1:]))


def composite_backward(t, sigma, rgb, far, grad_rgb, background=(0, 0, 0)):
    """dL/dsigma [n, K], dL/drgb [n, K, 3] of L = sum(grad_rgb * rgb_out), explicit suffix sums."""
    f = composite_forward(t, sigma, rgb, far, background)
    g = np.asarray(grad_rgb, np.float64)
    c = np.asarray(rgb, np.float64)
    bg = np.broadcast_to(np.asarray(background, np.float64), (3,))
    w = f["weights"]
    gc = np.einsum("nc,nkc->nk", g, c)
    wgc = w * gc
    after = np.cumsum(wgc[:, ::-1], axis=1)[:, ::-1] - wgc          # sum_{j>k}
    R = after + (f["T_end"] * (g @ bg))[:, None]
    dsig = _deltas(t, far) * (f["Tnext"] * gc - R)
    dsig = np.where(np.asarray(sigma, np.float64) > 0, dsig, 0.0)
    return dict(sigma=dsig, rgb=w[..., None] * g[:, None, :])


def composite_state(t, sigma, rgb, far):
    """(state [n, 8], dt [n, K]) of cl/composite.cl composite_state: the colour on black, acc,
    depth, logT, 0, 0; the segment lengths."""
    f = composite_forward(t, sigma, rgb, far)
    n = f["rgb"].shape[0]
    state = np.zeros((n, 8))
    state[:, :3], state[:, 3], state[:, 4] = f["rgb"], f["acc"], f["depth"]
    with np.errstate(divide="ignore"):
        state[:, 5] = np.log(f["T_end"])
    return state, _deltas(t, far)


def numeric_gradient(fn, x, eps):
    """Central differences of the scalar fn at every entry of the float64 array x."""
    x = np.array(x, np.float64)
    out = np.zeros_like(x)
    it = np.nditer(x, flags=["multi_index"])
    for _ in it:
        i = it.multi_index
        xp, xm = x.copy(), x.copy()
        xp[i] += eps
        xm[i] -= eps
        out[i] = (fn(xp) - fn(xm)) / (2 * eps)
    return out
