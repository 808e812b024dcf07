"""The splat model's colour transform per training image (cl/splat_exposure.cl,
clrf/splat/exposure.py) against its float64 twin (clrf/references/reference_exposure.py), on
every OpenCL implementation: apply, the backward pass (dL/drgb and dL/dP, also against finite
differences of the twin), the Adam step with its pull toward the identity, stiff inputs, and
NeRF-W's half-fitted protocol. The model's use of it: tests/test_splat_exposure_model.py."""
import numpy as np
import pytest

from clrf.references import reference_exposure as ref
from clrf.runtime.programs import download, upload
from clrf.splat.exposure import CHUNK, Exposure
from clrf.testing import tolerances as tol

SIZES = [1, 7, CHUNK - 1, CHUNK, CHUNK + 1, 3 * CHUNK + 5]


def _rows(rng, n_images):
    P = np.tile(ref.IDENTITY, (n_images, 1)) + rng.normal(0, 0.2, (n_images, ref.ROW))
    return P.astype(np.float32)


def _exposure(device, P):
    exp = Exposure(device, len(P), lr=0.01, reg=0.0)
    exp.P = upload(device.queue, np.ascontiguousarray(P))
    return exp


@pytest.mark.parametrize("n", SIZES)
def test_apply_matches_the_twin(device, n):
    rng = np.random.default_rng(n)
    P = _rows(rng, 3)
    rgb = rng.uniform(0, 1, (n, 3)).astype(np.float32)
    exp = _exposure(device, P)
    got = download(exp.apply(upload(device.queue, rgb), 2))
    np.testing.assert_allclose(got, ref.apply(rgb, P, 2), rtol=tol.EXPOSURE_RTOL,
                               atol=tol.EXPOSURE_ATOL)


@pytest.mark.parametrize("n", SIZES)
def test_backward_matches_the_twin(device, n):
    rng = np.random.default_rng(100 + n)
    P = _rows(rng, 4)
    rgb = rng.uniform(0, 1, (n, 3)).astype(np.float32)
    g = rng.normal(0, 1, (n, 3)).astype(np.float32)
    exp = _exposure(device, P)
    grad_rgb, partials = exp.backward(upload(device.queue, rgb), upload(device.queue, g), 1)
    want_rgb, want_p = ref.backward(rgb, g, P, 1)
    np.testing.assert_allclose(download(grad_rgb), want_rgb, rtol=tol.EXPOSURE_GRAD_RTOL,
                               atol=tol.EXPOSURE_ATOL)
    got_p = download(partials).astype(np.float64).sum(axis=0)
    np.testing.assert_allclose(got_p, want_p, rtol=tol.EXPOSURE_GRAD_RTOL,
                               atol=tol.EXPOSURE_SUM_ATOL_PER_SQRT_N * n ** 0.5)


def test_twin_gradient_matches_finite_differences():
    """The twin's dL/dP and dL/drgb against central differences of L = sum(w * out)."""
    rng = np.random.default_rng(5)
    P = _rows(rng, 2).astype(np.float64)
    rgb = rng.uniform(0, 1, (9, 3))
    w = rng.normal(0, 1, (9, 3))
    grad_rgb, grad_p = ref.backward(rgb, w, P, 1)
    h = 1e-6
    for k in range(ref.ROW):
        Pp, Pm = P.copy(), P.copy()
        Pp[1, k] += h
        Pm[1, k] -= h
        fd = (np.sum(w * ref.apply(rgb, Pp, 1)) - np.sum(w * ref.apply(rgb, Pm, 1))) / (2 * h)
        assert fd == pytest.approx(grad_p[k], rel=tol.FD_RTOL, abs=tol.FD_ATOL)
    for i in range(3):
        x1, x0 = rgb.copy(), rgb.copy()
        x1[4, i] += h
        x0[4, i] -= h
        fd = (np.sum(w * ref.apply(x1, P, 1)) - np.sum(w * ref.apply(x0, P, 1))) / (2 * h)
        assert fd == pytest.approx(grad_rgb[4, i], rel=tol.FD_RTOL, abs=tol.FD_ATOL)


def test_adam_step_matches_the_twin_and_pulls_toward_identity(device):
    rng = np.random.default_rng(9)
    P = _rows(rng, 3)
    n = 2 * CHUNK + 3
    rgb = rng.uniform(0, 1, (n, 3)).astype(np.float32)
    g = rng.normal(0, 1e-3, (n, 3)).astype(np.float32)
    exp = Exposure(device, 3, lr=0.02, reg=0.5)
    exp.P = upload(device.queue, np.ascontiguousarray(P))
    want_P, want_m, want_v = P.astype(np.float64), np.zeros((3, 12)), np.zeros((3, 12))
    for t in (1, 2, 3):
        rows = download(exp.P)
        _, grad_p = ref.backward(rgb, g, rows, 2)
        exp.backward_and_step(upload(device.queue, rgb), upload(device.queue, g), 2)
        want_P, want_m, want_v = ref.adam(want_P, want_m, want_v, 2, grad_p, 0.02, 0.5, 0.9,
                                          0.999, 1e-15, t)
    got = exp.rows()
    np.testing.assert_allclose(got, want_P, rtol=0, atol=tol.EXPOSURE_ADAM_ATOL)
    assert np.array_equal(got[:2], P[:2])             # other rows untouched
    assert exp.steps.tolist() == [0, 0, 3]
    # a zero image gradient: only the pull, so the row moves toward the identity
    before = np.abs(got[2] - ref.IDENTITY).sum()
    for _ in range(5):
        exp.backward_and_step(upload(device.queue, rgb),
                              upload(device.queue, np.zeros_like(g)), 2)
    assert np.abs(exp.rows()[2] - ref.IDENTITY).sum() < before


def test_stiff_inputs_leave_finite_rows(device):
    """Huge and non-finite gradients: a NaN gradient skips the step; huge ones move a row by
    about the learning rate (Adam's normalised step), never to inf."""
    exp = Exposure(device, 2, lr=0.01, reg=1e-3)
    rgb = np.full((CHUNK + 1, 3), 0.5, np.float32)
    for scale in (1e30, 0.0):
        g = np.full_like(rgb, scale)
        exp.backward_and_step(upload(device.queue, rgb), upload(device.queue, g), 0)
    rows = exp.rows()
    assert np.all(np.isfinite(rows))
    assert np.abs(rows[0] - ref.IDENTITY).max() <= 0.02 + 1e-6
    g = np.full_like(rgb, np.nan)
    before = exp.rows()
    exp.backward_and_step(upload(device.queue, rgb), upload(device.queue, g), 0)
    assert np.array_equal(exp.rows(), before)


def test_half_fitted_protocol_recovers_a_colour_change():
    rng = np.random.default_rng(3)
    render = rng.uniform(0.1, 0.7, (16, 20, 3))     # no channel leaves [0, 1] below
    A = np.diag([1.3, 0.9, 1.1])
    target = np.clip(render @ A.T + 0.02, 0, 1)
    fitted, plain = ref.half_fitted_psnr(render, target)
    assert fitted > 100 and plain < 30
