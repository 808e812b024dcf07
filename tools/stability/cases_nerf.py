"""NeRF kernel cases: encoding, sampling, compositing, the fused MLP."""
from __future__ import annotations

import numpy as np
import pyopencl.array as cla

from .framework import EXACT, GRAD, NERF_ENCODE, RENDER


# ---- NeRF kernels (cl/encode.cl, cl/sample.cl, cl/composite.cl, cl/mlp.cl) -------------------
def nerf_encode_large(run):
    """Positional encoding at |x| up to 1e3 with 16 frequencies (2^15 pi x ~ 1e8 rad) against
    float64 of the same float32 inputs: the power-of-two argument reduction keeps it exact."""
    from clrf.nerf import ops as nerf_ops
    from clrf.references import reference_nerf as rn
    x = np.concatenate([run.rng.uniform(-1e3, 1e3, (run.size(300, 3000), 3)),
                        [[0.0, 1e3, -1e3], [0.5, 999.999, -0.25], [1e-30, -1e-30, 2.0 ** -20]]])
    x = x.astype(np.float32)
    xd = cla.to_device(run.device.queue, x)
    for L in (10, 16):
        got = nerf_ops.encode(run.device, xd, L).get()
        run.compare(f"L={L} vs float64", got, rn.encode(x.astype(np.float64), L), NERF_ENCODE)
        run.finite(f"L={L} finite", got)


def nerf_importance_degenerate(run):
    """Inverse-CDF sampling from all-zero, one-hot, tiny (1e-30) and huge (1e30) weights: finite,
    sorted, inside [near, far]."""
    from clrf.nerf import ops as nerf_ops
    q = run.device.queue
    n, Kc, Nf = 5, 16, 32
    near, far = 2.0, 6.0
    t_c = np.tile(np.linspace(near, far, Kc, dtype=np.float32), (n, 1))
    w = np.zeros((n, Kc), np.float32)
    w[1, 7] = 1.0                      # one-hot
    w[2] = 1e-30                       # tiny everywhere
    w[3] = 1e30                        # huge everywhere
    w[4, 0] = w[4, -1] = 1.0           # mass at both ends only
    for jitter in (False, True):
        t = nerf_ops.sample_importance(run.device, cla.to_device(q, t_c), cla.to_device(q, w),
                                       Nf, near, far, jitter=jitter, key=7).get()
        run.finite(f"jitter {jitter} finite", t)
        run.compare(f"jitter {jitter} sorted (1 = yes)", np.all(np.diff(t, axis=1) >= 0, 1), 1.0,
                    EXACT)
        run.compare(f"jitter {jitter} inside [near, far] (1 = yes)",
                    np.all((t >= near) & (t <= far), 1), 1.0, EXACT)


def nerf_near_equals_far(run):
    """near == far: every stratified sample is near, every segment has length 0, and the
    composite is the background with acc 0 and finite gradients."""
    from clrf.nerf import ops as nerf_ops
    q = run.device.queue
    n, K = 4, 8
    t = nerf_ops.sample_stratified(run.device, n, K, 3.0, 3.0, jitter=True, key=3)
    run.compare("samples == near", t.get(), 3.0, EXACT)
    sig = cla.to_device(q, np.full(n * K, 1e3, np.float32))
    rgb = cla.to_device(q, np.full((n * K, 3), 0.5, np.float32))
    out = nerf_ops.composite_forward(run.device, t, sig, rgb, 3.0, background=(0.2, 0.4, 0.6))
    run.compare("acc == 0", out["acc"].get(), 0.0, EXACT)
    run.compare("rgb == background", out["rgb"].get(), np.tile([0.2, 0.4, 0.6], (n, 1)), RENDER)
    g = nerf_ops.composite_backward(run.device, t, sig, rgb, 3.0,
                                    cla.to_device(q, np.ones((n, 3), np.float32)),
                                    background=(0.2, 0.4, 0.6))
    run.finite("gradients finite", *[v.get() for v in g.values()])


def nerf_composite_stiff(run):
    """Per-sample compositing with densities 0..1e30 (and negative) against float64, gradients
    finite and equal to the analytic reference."""
    from clrf.nerf import ops as nerf_ops
    from clrf.references import reference_nerf as rn
    q = run.device.queue
    n, K = 6, 64
    t = np.tile(np.linspace(2.0, 6.0, K, dtype=np.float32), (n, 1))
    sig = np.zeros((n, K), np.float32)
    sig[0] = 0.0
    sig[1] = 1e-12
    sig[2] = run.rng.uniform(0, 5, K)
    sig[3, 10] = 1e30                  # one-hot weight
    sig[4] = 1e30
    sig[5] = run.rng.uniform(-5, 5, K)  # negative raw densities (ReLU)
    rgb = run.rng.uniform(0, 1, (n, K, 3)).astype(np.float32)
    far = 6.0
    args = (cla.to_device(q, t), cla.to_device(q, sig.reshape(-1)),
            cla.to_device(q, rgb.reshape(-1, 3)), far)
    out = nerf_ops.composite_forward(run.device, *args, background=(1, 1, 1))
    r = rn.composite_forward(t, sig, rgb, far, (1, 1, 1))
    run.compare("rgb vs float64", out["rgb"].get(), r["rgb"], RENDER)
    run.compare("acc vs float64", out["acc"].get(), r["acc"], RENDER)
    run.compare("one-hot acc == 1", out["acc"].get()[3], 1.0, RENDER)
    gr = run.rng.normal(size=(n, 3)).astype(np.float32)
    g = nerf_ops.composite_backward(run.device, *args, cla.to_device(q, gr), background=(1, 1, 1))
    rg = rn.composite_backward(t, sig, rgb, far, gr, (1, 1, 1))
    run.finite("gradients finite", *[v.get() for v in g.values()])
    run.compare("dL/dsigma vs float64", g["sigma"].get().reshape(n, K), rg["sigma"], GRAD)


def nerf_mlp_saturated(run):
    """The fused MLP with inputs of magnitude 1e3 (saturating softplus/sigmoid): outputs finite,
    sigma >= 0 and rgb in [0, 1]; input, weight and bias gradients finite."""
    from clrf.mlp.mlp import MLP, MLPSpec
    q = run.device.queue
    for act in ("relu", "softplus"):
        spec = MLPSpec(width=16, depth=2, skip=-1, color_width=16, in_dim=9, dir_dim=9,
                       sigma_act=act)
        net = MLP(run.device, spec, seed=1)
        n = 37
        x = (run.rng.choice([-1e3, 1e3], (n, 9)) * run.rng.uniform(0.5, 1, (n, 9))).astype(np.float32)
        sigma, rgb = net.forward(cla.to_device(q, x), cla.to_device(q, x))
        s, c = sigma.get(), rgb.get()
        run.finite(f"{act}: outputs finite", s, c)
        run.compare(f"{act}: sigma >= 0 (1 = yes)", np.all(s >= 0), 1.0, EXACT)
        run.compare(f"{act}: rgb in [0, 1] (1 = yes)", np.all((c >= 0) & (c <= 1)), 1.0, EXACT)
        gx = net.backward(cla.to_device(q, np.ones(n, np.float32)),
                          cla.to_device(q, np.ones((n, 3), np.float32)), want_input=True)
        run.finite(f"{act}: gradients finite", net.grad.get(), *[a.get() for a in gx])
