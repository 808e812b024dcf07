"""Compositing of per-sample lists (cl/composite.cl) vs float64, finite differences, extremes."""
import numpy as np
import pyopencl.array as cla
import pytest

from clrf.nerf import ops
from clrf.references import reference_nerf as ref
from clrf.testing import tolerances as tol

FAR = 6.0


def dev_arr(device, a):
    return cla.to_device(device.queue, np.ascontiguousarray(a, np.float32))


def make(n, K, seed=0, sigma_scale=2.0):
    rng = np.random.default_rng(seed)
    t = np.sort(rng.uniform(2.0, FAR, (n, K)), axis=1).astype(np.float32)
    sig = (rng.exponential(size=(n, K)) * sigma_scale).astype(np.float32)
    sig[rng.random((n, K)) < 0.3] = 0.0
    sig[rng.random((n, K)) < 0.1] = -1.0     # negative: contributes nothing
    rgb = rng.random((n, K, 3)).astype(np.float32)
    return t, sig, rgb


def run_forward(device, t, sig, rgb, bg):
    n, K = t.shape
    out = ops.composite_forward(device, dev_arr(device, t), dev_arr(device, sig.reshape(-1)),
                                dev_arr(device, rgb.reshape(-1, 3)), FAR, bg, want_weights=True)
    return {k: v.get() for k, v in out.items()}


@pytest.mark.parametrize("n,K", [(0, 3), (1, 1), (7, 64), (20, 7)])
@pytest.mark.parametrize("bg", [(0, 0, 0), (1, 1, 1)])
def test_forward_matches_reference(device, n, K, bg):
    t, sig, rgb = make(n, K, seed=n + K)
    out = run_forward(device, t, sig, rgb, bg)
    r = ref.composite_forward(t, sig, rgb, FAR, bg)
    for k in ("rgb", "acc", "weights"):
        np.testing.assert_allclose(out[k], r[k].reshape(out[k].shape), rtol=tol.COMPOSITE_RTOL,
                                   atol=tol.COMPOSITE_ATOL)
    np.testing.assert_allclose(out["depth"], r["depth"], rtol=tol.DEPTH_RTOL, atol=tol.DEPTH_ATOL)


def test_toy_values(device):
    # one sample at t = 2 with sigma = ln 2 over [2, 3] (far = 3): alpha = 1/2, rgb red over
    # a white background -> (1, 0.5, 0.5); acc 0.5; depth 0.5 * 2 = 1.
    out = ops.composite_forward(device, dev_arr(device, [[2.0]]), dev_arr(device, [np.log(2)]),
                                dev_arr(device, [[1, 0, 0]]), 3.0, (1, 1, 1))
    np.testing.assert_allclose(out["rgb"].get(), [[1, 0.5, 0.5]], atol=tol.TOY_ATOL)
    np.testing.assert_allclose(out["acc"].get(), [0.5], atol=tol.TOY_ATOL)
    np.testing.assert_allclose(out["depth"].get(), [1.0], atol=tol.TOY_ATOL)


def run_backward(device, t, sig, rgb, g, bg):
    out = ops.composite_backward(device, dev_arr(device, t), dev_arr(device, sig.reshape(-1)),
                                 dev_arr(device, rgb.reshape(-1, 3)), FAR, dev_arr(device, g), bg)
    n, K = t.shape
    return out["sigma"].get().reshape(n, K), out["rgb"].get().reshape(n, K, 3)


@pytest.mark.parametrize("n,K", [(1, 1), (7, 64), (13, 9)])
@pytest.mark.parametrize("bg", [(0, 0, 0), (1, 0.5, 0.25)])
def test_backward_matches_reference(device, n, K, bg):
    t, sig, rgb = make(n, K, seed=3 * n + K)
    g = np.random.default_rng(n).normal(size=(n, 3)).astype(np.float32)
    ds, dc = run_backward(device, t, sig, rgb, g, bg)
    r = ref.composite_backward(t, sig, rgb, FAR, g, bg)
    np.testing.assert_allclose(ds, r["sigma"], rtol=tol.COMPOSITE_GRAD_RTOL,
                               atol=tol.COMPOSITE_GRAD_ATOL)
    np.testing.assert_allclose(dc, r["rgb"], rtol=tol.COMPOSITE_GRAD_RTOL,
                               atol=tol.COMPOSITE_GRAD_ATOL)


def test_mse_mode_loss_and_gradient(device):
    n, K = 9, 16
    t, sig, rgb = make(n, K, seed=5)
    target = np.random.default_rng(5).random((n, 3)).astype(np.float32)
    scale = 1.0 / (3 * n)
    out = ops.composite_backward(device, dev_arr(device, t), dev_arr(device, sig.reshape(-1)),
                                 dev_arr(device, rgb.reshape(-1, 3)), FAR,
                                 dev_arr(device, target), (1, 1, 1), mse=True, loss_scale=scale,
                                 want_weights=True)
    f = ref.composite_forward(t, sig, rgb, FAR, (1, 1, 1))
    np.testing.assert_allclose(out["sq_err"].get(), np.sum((f["rgb"] - target) ** 2, axis=1),
                               rtol=tol.COMPOSITE_RTOL, atol=tol.COMPOSITE_ATOL)
    np.testing.assert_allclose(out["weights"].get(), f["weights"], rtol=tol.COMPOSITE_RTOL,
                               atol=tol.COMPOSITE_ATOL)
    r = ref.composite_backward(t, sig, rgb, FAR, 2 * scale * (f["rgb"] - target), (1, 1, 1))
    np.testing.assert_allclose(out["sigma"].get().reshape(n, K), r["sigma"],
                               rtol=tol.COMPOSITE_GRAD_RTOL, atol=tol.COMPOSITE_GRAD_ATOL)


def test_reference_backward_vs_finite_differences():
    n, K = 3, 6
    t, sig, rgb = make(n, K, seed=7)
    sig = np.abs(sig).astype(np.float64) + 0.1          # stay away from the kink at 0
    g = np.random.default_rng(7).normal(size=(n, 3))
    bg = (0.3, 0.6, 0.9)
    r = ref.composite_backward(t, sig, rgb, FAR, g, bg)

    def loss(s=sig, c=rgb):
        return float(np.sum(g * ref.composite_forward(t, s, c, FAR, bg)["rgb"]))

    fd_s = ref.numeric_gradient(lambda s: loss(s=s), sig, tol.COMPOSITE_FD_EPS)
    np.testing.assert_allclose(r["sigma"], fd_s, rtol=0, atol=tol.COMPOSITE_FD_ATOL)
    fd_c = ref.numeric_gradient(lambda c: loss(c=c), rgb.astype(np.float64), tol.COMPOSITE_FD_EPS)
    np.testing.assert_allclose(r["rgb"], fd_c, rtol=0, atol=tol.COMPOSITE_FD_ATOL)


@pytest.mark.parametrize("sigma", [0.0, 1e-8, 1.0, 1e4, 1e10, 1e20, 1e30])
@pytest.mark.parametrize("spacing", [1e-6, 1e-2, 1.0])
def test_scale_sweep_finite(device, sigma, spacing):
    """Densities 0 .. 1e30 times segment lengths 1e-6 .. 1: finite outputs and gradients,
    weights in [0, 1] summing to <= 1."""
    n, K = 4, 32
    t = (2.0 + spacing * np.arange(K))[None].repeat(n, 0).astype(np.float32)
    sig = np.full((n, K), sigma, np.float32)
    sig[1, ::2] = 0.0
    sig[2, :K // 2] = 0.0
    rgb = np.random.default_rng(1).random((n, K, 3)).astype(np.float32)
    out = run_forward(device, t, sig, rgb, (1, 1, 1))
    for v in out.values():
        assert np.all(np.isfinite(v))
    assert np.all(out["weights"] >= 0) and np.all(out["acc"] <= 1 + tol.TOY_ATOL)
    ds, dc = run_backward(device, t, sig, rgb, np.ones((n, 3), np.float32), (1, 1, 1))
    assert np.all(np.isfinite(ds)) and np.all(np.isfinite(dc))


def test_huge_density_in_one_bin_is_one_hot(device):
    n, K = 1, 16
    t = np.linspace(2, 5, K, dtype=np.float32)[None]
    sig = np.zeros((n, K), np.float32)
    sig[0, 6] = 1e10
    rgb = np.random.default_rng(2).random((n, K, 3)).astype(np.float32)
    out = run_forward(device, t, sig, rgb, (1, 1, 1))
    expect = np.zeros(K)
    expect[6] = 1.0
    np.testing.assert_allclose(out["weights"][0], expect, atol=tol.COMPOSITE_ATOL)
    np.testing.assert_allclose(out["rgb"][0], rgb[0, 6], atol=tol.COMPOSITE_ATOL)


def test_long_ray_matches_float64(device):
    """2048 samples, nearly opaque by the end: Kahan log-transmittance and prefix keep float32
    within the usual budget."""
    n, K = 3, 2048
    t, sig, rgb = make(n, K, seed=11, sigma_scale=0.02)
    sig = np.abs(sig)
    g = np.random.default_rng(11).normal(size=(n, 3)).astype(np.float32)
    out = run_forward(device, t, sig, rgb, (1, 1, 1))
    r = ref.composite_forward(t, sig, rgb, FAR, (1, 1, 1))
    np.testing.assert_allclose(out["rgb"], r["rgb"], rtol=tol.COMPOSITE_RTOL,
                               atol=tol.COMPOSITE_ATOL)
    ds, _ = run_backward(device, t, sig, rgb, g, (1, 1, 1))
    rb = ref.composite_backward(t, sig, rgb, FAR, g, (1, 1, 1))
    np.testing.assert_allclose(ds, rb["sigma"], rtol=tol.COMPOSITE_GRAD_RTOL,
                               atol=tol.COMPOSITE_GRAD_ATOL)
