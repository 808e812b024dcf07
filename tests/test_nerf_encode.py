"""Positional encoding (cl/encode.cl) vs the float64 reference."""
import numpy as np
import pyopencl.array as cla
import pytest

from clrf.nerf import ops
from clrf.references import reference_nerf as ref
from clrf.testing import tolerances as tol


@pytest.mark.parametrize("n", [0, 1, 7, 65])
@pytest.mark.parametrize("freqs,include", [(10, True), (4, False), (0, True)])
def test_encode_matches_reference(device, n, freqs, include):
    rng = np.random.default_rng(n + freqs)
    x = rng.uniform(-2, 2, (n, 3)).astype(np.float32)
    out = ops.encode(device, cla.to_device(device.queue, x), freqs, include, scale=0.3)
    assert out.shape == (n, ops.enc_dim(freqs, include))
    np.testing.assert_allclose(out.get(), ref.encode(x, freqs, include, 0.3), rtol=0,
                               atol=tol.ENCODE_ATOL)


def test_encode_toy_values(device):
    # p = 0.5: sin(pi/2) = 1, cos(pi/2) = 0; k = 1: sin(pi) = 0, cos(pi) = -1.
    x = np.array([[0.5, 0.0, -0.5]], np.float32)
    out = ops.encode(device, cla.to_device(device.queue, x), 2, True).get()[0]
    expect = [0.5, 0, -0.5, 1, 0, -1, 0, 1, 0, 0, 0, 0, -1, 1, -1]
    np.testing.assert_allclose(out, expect, rtol=0, atol=tol.ENCODE_ATOL)


def test_encode_large_inputs_high_frequencies(device):
    """|x| up to 1e3 with 16 frequencies (phase up to 2^15 * 1e3 * pi): still a few ulp."""
    rng = np.random.default_rng(3)
    x = (rng.uniform(-1, 1, (257, 3)) * 10.0 ** rng.uniform(-3, 3, (257, 3))).astype(np.float32)
    out = ops.encode(device, cla.to_device(device.queue, x), 16, True).get()
    np.testing.assert_allclose(out, ref.encode(x, 16, True), rtol=0, atol=tol.ENCODE_ATOL)


@pytest.mark.parametrize("n", [0, 1, 33])
def test_encode_backward_matches_reference(device, n):
    rng = np.random.default_rng(5)
    x = rng.uniform(-3, 3, (n, 3)).astype(np.float32)
    g = rng.normal(size=(n, ops.enc_dim(16, True))).astype(np.float32)
    q = device.queue
    gx = ops.encode_backward(device, cla.to_device(q, x), cla.to_device(q, g), 16, True, 0.7).get()
    expect = ref.encode_backward(x, g, 16, True, 0.7)
    scale = max(np.abs(expect).max(initial=0), 1.0)
    np.testing.assert_allclose(gx, expect, rtol=0, atol=tol.ENCODE_GRAD_RTOL * scale)


def test_encode_reference_backward_vs_finite_differences():
    rng = np.random.default_rng(6)
    x = rng.uniform(-1, 1, (3, 3))
    g = rng.normal(size=(3, ops.enc_dim(3, True)))

    def loss(xx):
        # the float64 encoding of a float64 input (no float32 rounding) for differentiation
        p = 0.7 * xx
        parts = [p] + [f(np.pi * 2.0 ** k * p) for k in range(3) for f in (np.sin, np.cos)]
        return float(np.sum(g * np.concatenate(parts, axis=1)))

    fd = ref.numeric_gradient(loss, x, 1e-6)
    x32 = x.astype(np.float32).astype(np.float64)
    an = ref.encode_backward(x32, g, 3, True, 0.7)
    fd32 = ref.numeric_gradient(loss, x32, 1e-6)
    np.testing.assert_allclose(an, fd32, rtol=tol.ENCODE_FD_RTOL, atol=tol.ENCODE_FD_ATOL)
    assert np.all(np.isfinite(fd))
