"""The splat model's loss on the device (cl/splat_loss.cl, clrf/splat/loss.py DeviceLoss):
(1 - lam) L1 + lam (1 - SSIM) and dL/drgb against the float64 twin
(clrf/references/reference_ssim.py) on sizes that are multiples of nothing (1 x 1, 5 x 7, 37 x 23,
100 x 100), textured, smooth, flat and constant images, identical images (SSIM = 1, no SSIM
gradient) and lam = 0 (no SSIM at all); the twin's window against scipy's Gaussian filter and
its gradient against central differences; every work split and both reductions (double, compensated float pairs); buffer reuse between calls and the
argument checks."""
import numpy as np
import pyopencl.array as cla
import pytest
from scipy.ndimage import gaussian_filter

from clrf.runtime.buildlog import diagnostics
from clrf.runtime.programs import build, build_log, upload
from clrf.splat import loss as sl
from clrf.references import reference_ssim as rf

# ---- tolerances ---------------------------------------------------------------------------------
# (Kept here with their reasons until they join clrf/testing/tolerances.py.) u = 6e-8.
# The twin's window vs scipy.ndimage.gaussian_filter's impulse response (both float64, weights
# <= 0.07 formed by exp and one normalising division): a few ulp, ~1e-17.
SSIM_WINDOW_ATOL = 1e-15
# Mean SSIM, float32 kernels vs float64, on textured images: the moments G(x^2), (G x)^2 are
# O(1) floats rounded a few times (~5 u), their difference sxx is divided by b2 >= C2 = 9e-4,
# so one element of s may carry ~5 u / C2 = 3e-4 relative error where the window is flat, but
# far less on texture (b2 ~ 1e-2..1e-1), and the signs vary over the image: seen <= 9.4e-8
# (PoCL, Intel; sizes 1 x 1 .. 100 x 100, four seeds, both work splits and reductions). 1e-6;
# a wrong sigma (1.6) or padding (reflect) moves SSIM by >= 2e-3, a 13-tap window by 2.7e-5.
SSIM_ATOL = 1e-6
# Mean SSIM on smooth, flat and constant images: there sxx, syy, sxy are 0 (or ~1e-6) and the
# cancellation error above has one sign at every element, so the mean keeps it: seen 7.7e-5
# (x = 0.8, y = 0.3 everywhere: the float32 sums of the window give the same few-ulp error at
# every interior element; the host's float32 version sees 1.7e-6 there, scipy summing in
# double). 3e-4.
SSIM_FLAT_ATOL = 3e-4
# L1 and MSE: double or compensated (double-float) sums, so only the final rounding to float32
# counts (and the division by n, in float for the pairs): seen <= 9.3e-8 relative. 1e-6.
SUM_RTOL = 1e-6
# dL/drgb relative to its largest entry, textured images: per element a few roundings of the
# partials (|ds/dsxy| <= 2 / b2) blurred twice: seen <= 8.4e-7. 1e-5; a dropped chain term,
# a wrong tap or a one-pixel shift at a border is >= 1e-3.
GRAD_REL_TO_MAX = 1e-5
# ... smooth, flat and constant images: the partials ~ 1 / C2 = 1.1e3 carry the relative error
# of sxx above (up to ~1e-4) and cancel in G A + 2 x G Dxx + y G Dxy down to the gradient's
# size: seen <= 4e-4 (the host's float32 version: 2e-4). 2e-3.
GRAD_FLAT_REL_TO_MAX = 2e-3
# n dL/drgb where the exact SSIM gradient is 0 (identical images): the same cancellation of
# terms of size 2 x / C2 <= 2.2e3 at a few u each: seen <= 4.5e-4 (x = y = 1 everywhere). 2e-3.
GRAD_ZERO_N_ATOL = 2e-3
# SSIM of identical images: s = 1 up to the rounding of a1 / b1 and a2 / b2 (mx my vs mx^2 + my^2
# may round differently under contraction): a few u; seen <= 6e-8.
SSIM_ONE_ATOL = 1e-6
# The twin's gradient vs its own central differences (float64, eps 1e-5): truncation
# eps^2 f''' and roundoff 1e-16 / eps are ~1e-11 each; seen <= 1.6e-11 on gradients ~4e-2.
SSIM_FD_EPS = 1e-5
SSIM_FD_ATOL = 1e-9
SSIM_FD_RTOL = 1e-6

SIZES = [(1, 1), (5, 7), (37, 23), (100, 100)]
TEXTURED = ("noisy", "random", "outrange")
FLAT = ("smooth", "flat_bright", "piecewise", "constant")


# ---- helpers ------------------------------------------------------------------------------------
def _images(kind, h, w, seed=0):
    """(x, y) float32 [h, w, 3]: a render-like x against a target y."""
    rng = np.random.default_rng(seed)
    shape = (h, w, 3)
    if kind == "noisy":            # the target plus noise, clipped to [0, 1]
        y = rng.uniform(0, 1, shape)
        x = np.clip(y + rng.normal(0, 0.2, shape), 0, 1)
    elif kind == "random":         # unrelated images
        y, x = rng.uniform(0, 1, shape), rng.uniform(0, 1, shape)
    elif kind == "outrange":       # a render overshooting [0, 1]
        y, x = rng.uniform(0, 1, shape), rng.uniform(-0.3, 1.3, shape)
    elif kind == "smooth":         # slow ramps, tiny differences
        r, c = np.mgrid[0:h, 0:w]
        y = 0.5 + 0.4 * np.sin(r[..., None] / 7.0 + c[..., None] / 5.0 + np.arange(3))
        x = y + 0.02 * np.cos(r[..., None] / 3.0) + rng.normal(0, 0.002, shape)
    elif kind == "flat_bright":    # a white background with 1e-3 noise in both
        y, x = 0.95 + rng.normal(0, 1e-3, shape), 0.95 + rng.normal(0, 1e-3, shape)
    elif kind == "piecewise":      # 8 x 8 constant blocks
        def blocks():
            b = rng.uniform(0, 1, (h // 8 + 1, w // 8 + 1, 3))
            return np.repeat(np.repeat(b, 8, 0), 8, 1)[:h, :w]
        y, x = blocks(), blocks()
    elif kind == "constant":
        y, x = np.full(shape, 0.3), np.full(shape, 0.8)
    else:
        raise ValueError(kind)
    return x.astype(np.float32), y.astype(np.float32)


def _close_rel(got, want, rel, name="", scale=None):
    """max |got - want| <= rel * scale (scale: max |want| by default)."""
    if scale is None:
        scale = max(float(np.abs(want).max(initial=0.0)), 1e-300)
    err = float(np.abs(np.asarray(got, np.float64) - want).max(initial=0.0))
    assert err <= rel * scale, f"{name}: max error {err:.3g} > {rel} * {scale:.3g}"


def _run(device, x, y, lam):
    """(grad [H, W, 3], stats dict) of DeviceLoss on host images."""
    loss = sl.DeviceLoss(device, x.shape[0], x.shape[1], lam)
    q = device.queue
    grad, stats = loss.loss_and_grad(upload(q, x), upload(q, y))
    return grad.get(), loss.read(stats)


def _ssim_from(x, y, blur):
    mx, my = blur(x), blur(y)
    sxx, syy, sxy = blur(x * x) - mx * mx, blur(y * y) - my * my, blur(x * y) - mx * my
    return float(np.mean((2 * mx * my + rf.C1) * (2 * sxy + rf.C2)
                         / ((mx * mx + my * my + rf.C1) * (sxx + syy + rf.C2))))


# ---- constants, window and the twin ---------------------------------------------------------
def test_constants_match_twin():
    assert (rf.SIGMA, rf.RADIUS, rf.C1, rf.C2) == \
        (sl.SSIM_SIGMA, sl.SSIM_RADIUS, sl.SSIM_C1, sl.SSIM_C2)
    w1 = sl.ssim_window()
    assert w1.shape == (11,) and w1.sum() == pytest.approx(1.0, abs=SSIM_WINDOW_ATOL)
    np.testing.assert_allclose(np.outer(w1, w1), rf.window(), rtol=0, atol=SSIM_WINDOW_ATOL)
    d = sl.defines()
    for k in range(6):
        assert d[f"SSIM_W{k}"] == float(w1[5 + k]) == float(w1[5 - k])


def test_window_is_scipys_gaussian_filter():
    """The twin's 11 x 11 window is the impulse response of scipy.ndimage.gaussian_filter
    (float64) with the loss's parameters."""
    imp = np.zeros((21, 21, 1))
    imp[10, 10, 0] = 1.0
    resp = gaussian_filter(imp, sigma=(sl.SSIM_SIGMA, sl.SSIM_SIGMA, 0), mode="constant",
                           cval=0.0, truncate=sl.SSIM_RADIUS / sl.SSIM_SIGMA)[..., 0]
    want = np.zeros((21, 21))
    want[5:16, 5:16] = rf.window()
    np.testing.assert_allclose(resp, want, rtol=0, atol=SSIM_WINDOW_ATOL)
    # the twin's blur and its adjoint on the same impulse
    np.testing.assert_allclose(rf.blur(imp)[..., 0], want, rtol=0, atol=SSIM_WINDOW_ATOL)
    np.testing.assert_allclose(rf.blur_adjoint(imp)[..., 0], want, rtol=0,
                               atol=SSIM_WINDOW_ATOL)


@pytest.mark.parametrize("kind", ["noisy", "smooth"])
def test_twin_gradient_vs_central_differences(kind):
    x, y = (np.float64(a) for a in _images(kind, 6, 5, seed=1))
    g = rf.ssim_grad(x, y)
    fd = np.zeros_like(x)
    for idx in np.ndindex(x.shape):
        p, m = x.copy(), x.copy()
        p[idx] += SSIM_FD_EPS
        m[idx] -= SSIM_FD_EPS
        fd[idx] = (rf.ssim(p, y) - rf.ssim(m, y)) / (2 * SSIM_FD_EPS)
    assert np.abs(fd).max() > 1e-3
    np.testing.assert_allclose(g, fd, rtol=SSIM_FD_RTOL, atol=SSIM_FD_ATOL)


def test_twin_loss_gradient_vs_central_differences():
    """The whole loss, with |x - y| = 0.1 everywhere (central differences stay off the kink)."""
    rng = np.random.default_rng(2)
    y = rng.uniform(0, 1, (5, 6, 3))
    x = y + np.where(rng.uniform(size=y.shape) < 0.5, 0.1, -0.1)
    lam = 0.3
    g = rf.loss_grad(x, y, lam)
    fd = np.zeros_like(x)
    for idx in np.ndindex(x.shape):
        p, m = x.copy(), x.copy()
        p[idx] += SSIM_FD_EPS
        m[idx] -= SSIM_FD_EPS
        fd[idx] = (rf.loss(p, y, lam)["loss"] - rf.loss(m, y, lam)["loss"]) / (2 * SSIM_FD_EPS)
    np.testing.assert_allclose(g, fd, rtol=SSIM_FD_RTOL, atol=SSIM_FD_ATOL)


def test_the_checks_can_fail():
    """The tolerances have teeth: a gradient without the chain through mx in sxy, a wrong sigma
    and a wrong padding are caught by the comparisons above."""
    x, y = (np.float64(a) for a in _images("noisy", 37, 23, seed=3))
    g = rf.ssim_grad(x, y)
    mx, my = rf.blur(x), rf.blur(y)
    sxx, syy = rf.blur(x * x) - mx ** 2, rf.blur(y * y) - my ** 2
    a1, b1, b2 = 2 * mx * my + rf.C1, mx * mx + my * my + rf.C1, sxx + syy + rf.C2
    wrong = g + rf.blur_adjoint(my * 2 * a1 / (b1 * b2)) / x.size     # "- my g_xy" dropped
    assert np.abs(wrong - g).max() > 100 * GRAD_REL_TO_MAX * np.abs(g).max()
    s = rf.ssim(x, y)
    assert abs(_ssim_from(x, y, lambda a: rf.blur(a, rf.window(1.6))) - s) > 100 * SSIM_ATOL
    reflect = _ssim_from(x, y, lambda a: gaussian_filter(a, (1.5, 1.5, 0), mode="reflect",
                                                         truncate=5 / 1.5))
    assert abs(reflect - s) > 100 * SSIM_ATOL
    assert abs(_ssim_from(x, y, lambda a: rf.blur(a, rf.window(1.5, 6))) - s) > 10 * SSIM_ATOL


# ---- the device against the twin ----------------------------------------------------------------
def test_splat_loss_builds_without_diagnostics(device):
    prg = build(device, "splat_loss.cl", sl.defines())
    found = diagnostics(build_log(prg.cl_program, device))
    assert found == [], "\n".join(x.text for x in found)


@pytest.mark.parametrize("kind", TEXTURED + FLAT)
@pytest.mark.parametrize("height,width", SIZES)
@pytest.mark.parametrize("lam", [1.0, 0.2])
def test_device_loss_matches_twin(device, height, width, kind, lam):
    """lam = 1: the gradient is -dSSIM/dx alone; lam = 0.2 (the config's default) mixes in
    the L1 term's sign(x - y) / n."""
    x, y = _images(kind, height, width, seed=height * 1000 + width)
    grad, stats = _run(device, x, y, lam)
    want = rf.loss(x, y, lam)
    ssim_tol = SSIM_ATOL if kind in TEXTURED else SSIM_FLAT_ATOL
    assert stats["ssim"] == pytest.approx(want["ssim"], abs=ssim_tol)
    assert stats["l1"] == pytest.approx(want["l1"], rel=SUM_RTOL)
    assert stats["mse"] == pytest.approx(want["mse"], rel=SUM_RTOL)
    assert stats["loss"] == pytest.approx(want["loss"], rel=SUM_RTOL, abs=lam * ssim_tol)
    assert grad.shape == x.shape and grad.dtype == np.float32
    _close_rel(grad, rf.loss_grad(x, y, lam),
               GRAD_REL_TO_MAX if kind in TEXTURED else GRAD_FLAT_REL_TO_MAX, "grad")


@pytest.mark.parametrize("height,width", SIZES)
@pytest.mark.parametrize("flat", [False, True])
def test_device_identical_images(device, height, width, flat):
    """x = y: SSIM = 1, loss 0, and the gradient vanishes (sign(0) = 0, SSIM at its maximum)."""
    y = (np.full((height, width, 3), 0.9) if flat
         else np.random.default_rng(5).uniform(0, 1, (height, width, 3))).astype(np.float32)
    for lam in (1.0, 0.2):
        grad, stats = _run(device, y, y, lam)
        assert stats["ssim"] == pytest.approx(1.0, abs=SSIM_ONE_ATOL)
        assert stats["l1"] == 0.0 and stats["mse"] == 0.0
        assert abs(stats["loss"]) <= lam * SSIM_ONE_ATOL
        assert np.abs(grad).max() * y.size <= GRAD_ZERO_N_ATOL


@pytest.mark.parametrize("height,width", [(1, 1), (37, 23)])
def test_device_lam_zero_is_l1_only(device, height, width):
    """lam = 0 skips the SSIM kernels: the gradient is exactly sign(x - y) / n (in float32) and
    SSIM reads 1 (not computed), as in model.py's loss_and_grad."""
    x, y = _images("noisy", height, width, seed=6)
    x[0, 0] = y[0, 0]                                   # sign(0) = 0
    grad, stats = _run(device, x, y, 0.0)
    n = x.size
    np.testing.assert_array_equal(grad, np.float32(1.0 / n) * np.sign(x - y).astype(np.float32))
    want = rf.loss(x, y, 0.0)
    assert stats["ssim"] == 1.0
    assert stats["loss"] == pytest.approx(want["l1"], rel=SUM_RTOL)
    assert stats["l1"] == pytest.approx(want["l1"], rel=SUM_RTOL)
    assert stats["mse"] == pytest.approx(want["mse"], rel=SUM_RTOL)


def test_device_reuses_its_buffers(device):
    """One object serves many steps: the same gradient and stats arrays come back, overwritten
    with each call's values (nothing stale from the previous images); ``out`` is honoured."""
    h, w = 37, 23
    loss = sl.DeviceLoss(device, h, w, 0.2)
    q = device.queue
    first = None
    for seed, kind in ((8, "noisy"), (9, "piecewise"), (10, "random")):
        x, y = _images(kind, h, w, seed=seed)
        grad, stats = loss.loss_and_grad(upload(q, x), upload(q, y))
        if first is None:
            first = (grad, stats)
        assert grad is first[0] and stats is first[1]
        want = rf.loss(x, y, 0.2)
        assert loss.read()["mse"] == pytest.approx(want["mse"], rel=SUM_RTOL)
        _close_rel(grad.get(), rf.loss_grad(x, y, 0.2),
                   GRAD_REL_TO_MAX if kind in TEXTURED else GRAD_FLAT_REL_TO_MAX, kind)
    out = cla.zeros(q, (h, w, 3), np.float32)
    got, _ = loss.loss_and_grad(upload(q, x), upload(q, y), out=out)
    assert got is out
    np.testing.assert_array_equal(out.get(), first[0].get())     # the last call's images


@pytest.mark.parametrize("span", [None, 1, 7, 48, 10 ** 6])
@pytest.mark.parametrize("fp64", [False, True])
def test_device_work_splits_and_accumulators(device, span, fp64):
    """Every work split (whole rows: the CPU default; one float: the GPU default; chunks that
    end inside a row's border or interior, 7 and 48 of the 69 floats of a 23-pixel row) and
    both reductions (double, compensated float pairs) give the same loss."""
    if fp64 and not device.caps.fp64:
        pytest.skip("no cl_khr_fp64 on this device")
    q = device.queue
    for (h, w), kind in (((37, 23), "noisy"), ((5, 7), "piecewise"), ((1, 1), "random")):
        x, y = _images(kind, h, w, seed=11)
        loss = sl.DeviceLoss(device, h, w, 0.2, fp64=fp64, span=span)
        grad, stats = loss.loss_and_grad(upload(q, x), upload(q, y))
        stats = loss.read(stats)
        want = rf.loss(x, y, 0.2)
        ssim_tol = SSIM_ATOL if kind in TEXTURED else SSIM_FLAT_ATOL
        assert stats["ssim"] == pytest.approx(want["ssim"], abs=ssim_tol)
        for k in ("l1", "mse"):
            assert stats[k] == pytest.approx(want[k], rel=SUM_RTOL), k
        assert stats["loss"] == pytest.approx(want["loss"], rel=SUM_RTOL, abs=0.2 * ssim_tol)
        _close_rel(grad.get(), rf.loss_grad(x, y, 0.2),
                   GRAD_REL_TO_MAX if kind in TEXTURED else GRAD_FLAT_REL_TO_MAX, f"{h}x{w}")


def test_device_loss_bad_inputs(device):
    q = device.queue
    loss = sl.DeviceLoss(device, 5, 7, 0.2)
    good = cla.zeros(q, (5, 7, 3), np.float32)
    with pytest.raises(ValueError, match="shape"):
        loss.loss_and_grad(cla.zeros(q, (7, 5, 3), np.float32), good)
    with pytest.raises(TypeError, match="dtype"):
        loss.loss_and_grad(good, cla.zeros(q, (5, 7, 3), np.float64))
    with pytest.raises(TypeError, match="pyopencl"):
        loss.loss_and_grad(np.zeros((5, 7, 3), np.float32), good)
    with pytest.raises(ValueError, match="contiguous"):
        wide = cla.zeros(q, (5, 7, 6), np.float32)
        loss.loss_and_grad(good, wide[:, :, :3])
    with pytest.raises(ValueError, match="out"):
        loss.loss_and_grad(good, good, out=cla.zeros(q, (5, 7), np.float32))
    with pytest.raises(ValueError, match="out"):
        loss.loss_and_grad(good, cla.zeros(q, (5, 7, 3), np.float32), out=good)
    with pytest.raises(ValueError, match="lam"):
        sl.DeviceLoss(device, 5, 7, 1.5)
    with pytest.raises(ValueError, match="height"):
        sl.DeviceLoss(device, 0, 7, 0.2)
    with pytest.raises(ValueError, match="width"):
        sl.DeviceLoss(device, 5, 2.5, 0.2)
    with pytest.raises(ValueError, match="span"):
        sl.DeviceLoss(device, 5, 7, 0.2, span=0)
    if not device.caps.fp64:
        with pytest.raises(ValueError, match="fp64"):
            sl.DeviceLoss(device, 5, 7, 0.2, fp64=True)
