"""Thin host wrappers of the NeRF-path kernels other than the MLP (cl/encode.cl, cl/sample.cl,
cl/composite.cl), with the rays' camera gradient (``ray_points_backward``) and composite state
(``composite_state``) of the per-view corrections. All take and return pyopencl arrays
(float32, C order); shapes are in each docstring and the math in the kernel file headers.

>>> t = sample_stratified(dev, n=2, K=4, near=2.0, far=6.0)     # jitter off: bin centres
>>> t.get()
array([[2.5, 3.5, 4.5, 5.5], [2.5, 3.5, 4.5, 5.5]], dtype=float32)
"""
from __future__ import annotations

import numpy as np

from ..runtime.programs import device_empty, float4, launch

# Work-group sizes come from device.tuning (clrf/runtime/tuning.py): elementwise_local_size,
# per_ray_local_size, encode_local_size.


def enc_dim(n_freqs: int, include_input: bool = True) -> int:
    return 3 * int(include_input) + 6 * n_freqs


def _empty(device, shape):
    return device_empty(device.queue, shape, np.float32)


def _encode_prg(device, n_freqs, include_input):
    return device.program("encode.cl", {"ENC_FREQS": n_freqs,
                                        "ENC_INCLUDE_INPUT": int(include_input)})


def encode(device, x, n_freqs: int, include_input: bool = True, scale: float = 1.0, out=None):
    """gamma(scale * x): x [n, 3] -> [n, 3*include_input + 6*n_freqs]."""
    n = int(x.shape[0])
    out = out if out is not None else _empty(device, (n, enc_dim(n_freqs, include_input)))
    prg = _encode_prg(device, n_freqs, include_input)
    launch(device, prg.kernel("encode_forward"), 3 * max(n_freqs, 1) * ((n + 15) // 16),
           (np.int32(n), np.float32(scale), x.data, out.data), device.tuning.encode_local_size)
    return out


def encode_backward(device, x, grad_out, n_freqs: int, include_input: bool = True,
                    scale: float = 1.0):
    """dL/dx [n, 3] from dL/dgamma [n, enc_dim]."""
    n = int(x.shape[0])
    gx = _empty(device, (n, 3))
    prg = _encode_prg(device, n_freqs, include_input)
    launch(device, prg.kernel("encode_backward"), n,
           (np.int32(n), np.float32(scale), x.data, grad_out.data, gx.data),
           device.tuning.elementwise_local_size)
    return gx


def _sample_prg(device):
    return device.program("sample.cl", {})


def sample_stratified(device, n: int, K: int, near: float, far: float, jitter: bool = False,
                      key: int = 0, out=None):
    """t [n, K]: one sample per equal bin of [near, far], at the centre or jittered."""
    out = out if out is not None else _empty(device, (n, K))
    launch(device, _sample_prg(device).kernel("sample_stratified"), n * K,
           (np.int32(n), np.int32(K), np.float32(near), np.float32(far), np.int32(bool(jitter)),
            np.uint32(key), out.data), device.tuning.elementwise_local_size)
    return out


def sample_importance(device, t_c, weights, Nf: int, near: float, far: float,
                      jitter: bool = False, key: int = 0, out=None):
    """t_f [n, Nf] (sorted) drawn from the piecewise-constant pdf of weights [n, Kc] over the
    bins around t_c [n, Kc]."""
    n, Kc = (int(s) for s in t_c.shape)
    out = out if out is not None else _empty(device, (n, Nf))
    launch(device, _sample_prg(device).kernel("sample_importance"), n,
           (np.int32(n), np.int32(Kc), np.int32(Nf), np.float32(near), np.float32(far),
            t_c.data, weights.data, np.int32(bool(jitter)), np.uint32(key), out.data),
           device.tuning.per_ray_local_size)
    return out


def merge_sorted(device, a, b, out=None):
    """Per-ray merge of sorted a [n, Ka] and b [n, Kb] -> [n, Ka + Kb]."""
    n, Ka = (int(s) for s in a.shape)
    Kb = int(b.shape[1])
    out = out if out is not None else _empty(device, (n, Ka + Kb))
    launch(device, _sample_prg(device).kernel("merge_sorted"), n,
           (np.int32(n), np.int32(Ka), np.int32(Kb), a.data, b.data, out.data),
           device.tuning.per_ray_local_size)
    return out


def ray_points(device, origins, dirs, t, xyz=None, vdir=None):
    """Sample points [n*K, 3] = o + t d/|d| and unit directions [n*K, 3] for t [n, K]."""
    n, K = (int(s) for s in t.shape)
    xyz = xyz if xyz is not None else _empty(device, (n * K, 3))
    vdir = vdir if vdir is not None else _empty(device, (n * K, 3))
    launch(device, _sample_prg(device).kernel("ray_points"), n * K,
           (np.int32(n), np.int32(K), origins.data, dirs.data, t.data, xyz.data, vdir.data),
           device.tuning.elementwise_local_size)
    return xyz, vdir


def ray_points_backward(device, dirs, t, gx, gv, out, accumulate: bool = False):
    """dL/d(origin, direction) [n, 6] into ``out`` (written, or added to with accumulate) of
    rays dirs [n, 3] whose samples ``ray_points(o, dirs, t)`` got dL/dpoint gx [n*K, 3] and
    dL/dview-direction gv [n*K, 3] (t held constant: cl/sample.cl)."""
    n, K = (int(s) for s in t.shape)
    launch(device, _sample_prg(device).kernel("ray_points_backward"), n,
           (np.int32(n), np.int32(K), dirs.data, t.data, gx.data, gv.data,
            np.int32(bool(accumulate)), out.data), device.tuning.per_ray_local_size)
    return out


class RaySamples:
    """The composite state of n rays of K samples each as the colour corrections of ray
    batches read it (cl/composite.cl composite_state; the hash marcher's Packed has the same
    members): state [n, 8], offsets [n + 1] (int32), dt [n*K], n rays, m samples."""

    def __init__(self, state, offsets, dt, n: int, m: int):
        self.state, self.offsets, self.dt, self.n, self.m = state, offsets, dt, n, m


def composite_state(device, t, sigma, rgb, far: float) -> RaySamples:
    """The rays' state on a black background (colour, acc, depth, logT) and their samples'
    segment lengths for t [n, K], sigma [n*K], rgb [n*K, 3]."""
    n, K = (int(s) for s in t.shape)
    state, dt = _empty(device, (n, 8)), _empty(device, n * K)
    offsets = device_empty(device.queue, n + 1, np.int32)
    launch(device, _composite_prg(device, 0).kernel("composite_state"), n,
           (np.int32(n), np.int32(K), np.float32(far), t.data, sigma.data, rgb.data,
            state.data, offsets.data, dt.data), device.tuning.per_ray_local_size)
    return RaySamples(state, offsets, dt, n, n * K)


def _bg4(background):
    bg = np.broadcast_to(np.asarray(background, np.float64), (3,))
    return float4(bg[0], bg[1], bg[2], 0.0)


def _composite_prg(device, grad_mode: int):
    return device.program("composite.cl", {"GRAD_MODE": grad_mode})


def composite_forward(device, t, sigma, rgb, far: float, background=(0, 0, 0),
                      want_weights: bool = False):
    """dict of rgb [n, 3], depth [n], acc [n] (+ weights [n, K]) for t [n, K], sigma [n*K],
    rgb [n*K, 3]."""
    n, K = (int(s) for s in t.shape)
    out = {"rgb": _empty(device, (n, 3)), "depth": _empty(device, n), "acc": _empty(device, n)}
    if want_weights:
        out["weights"] = _empty(device, (n, K))
    prg = _composite_prg(device, 0)
    launch(device, prg.kernel("composite_forward"), n,
           (np.int32(n), np.int32(K), np.float32(far), t.data, sigma.data, rgb.data,
            _bg4(background), out["rgb"].data, out["depth"].data, out["acc"].data,
            out["weights"].data if want_weights else None), device.tuning.per_ray_local_size)
    return out


def composite_backward(device, t, sigma, rgb, far: float, ray_in, background=(0, 0, 0),
                       mse: bool = False, loss_scale: float = 1.0, want_weights: bool = False,
                       out=None):
    """dL/dsigma [n*K] and dL/drgb [n*K, 3] as dict(sigma=, rgb=), plus ``sq_err`` [n] (the
    per-ray squared error summed over channels) when mse=True, where ray_in holds the target
    and L = loss_scale * sum |rgb - target|^2; else ray_in holds dL/drgb [n, 3]."""
    n, K = (int(s) for s in t.shape)
    if out is None:
        out = {"sigma": _empty(device, n * K), "rgb": _empty(device, (n * K, 3))}
        if mse:
            out["sq_err"] = _empty(device, n)
        if want_weights:
            out["weights"] = _empty(device, (n, K))
    prg = _composite_prg(device, int(bool(mse)))
    launch(device, prg.kernel("composite_backward"), n,
           (np.int32(n), np.int32(K), np.float32(far), t.data, sigma.data, rgb.data,
            _bg4(background), ray_in.data, out["sq_err"].data if mse else None,
            np.float32(loss_scale), out["sigma"].data, out["rgb"].data,
            out["weights"].data if "weights" in out else None), device.tuning.per_ray_local_size)
    return out
