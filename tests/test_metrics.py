"""The standard SSIM (11x11 Gaussian window, sigma 1.5, population covariance) against an
independent float64 implementation written here, and its relation to scikit-image's default."""
import numpy as np
import pytest
from scipy.ndimage import gaussian_filter
from skimage.metrics import structural_similarity

from clrf.training.metrics import SSIM_WINDOW, image_metrics, ssim
from clrf.testing.tolerances import SSIM_REF_ATOL


def ref_ssim(a, b, size=11, sigma=1.5, k1=0.01, k2=0.03):
    """Wang et al.'s SSIM, float64: separable Gaussian filter (size taps, normalised), 'valid'
    region only, mean over pixels and channels of [H, W, C] images in [0, 1]."""
    x = np.arange(size) - size // 2
    g = np.exp(-0.5 * (x / sigma) ** 2)
    g /= g.sum()

    def filt(im):   # valid 2-D correlation with g g^T, channel by channel
        h, w = im.shape[0] - size + 1, im.shape[1] - size + 1
        rows = sum(g[i] * im[i:i + h] for i in range(size))
        return sum(g[j] * rows[:, j:j + w] for j in range(size))

    a, b = np.asarray(a, np.float64), np.asarray(b, np.float64)
    c1, c2 = k1 ** 2, k2 ** 2
    mu_a, mu_b = filt(a), filt(b)
    va = filt(a * a) - mu_a ** 2
    vb = filt(b * b) - mu_b ** 2
    cov = filt(a * b) - mu_a * mu_b
    s = ((2 * mu_a * mu_b + c1) * (2 * cov + c2)) / ((mu_a ** 2 + mu_b ** 2 + c1) * (va + vb + c2))
    return float(s.mean())


def _pairs():
    rng = np.random.default_rng(7)
    gt = gaussian_filter(rng.random((64, 48, 3)), (1.5, 1.5, 0))
    gt = (gt - gt.min()) / (gt.max() - gt.min())
    blurred_noisy = np.clip(gaussian_filter(gt, (1.2, 1.2, 0))
                            + rng.normal(0, 0.04, gt.shape), 0, 1)
    shifted = np.clip(gt * 0.8 + 0.15, 0, 1)
    noise = rng.random(gt.shape)
    return gt, {"blurred_noisy": blurred_noisy, "affine": shifted, "noise": noise,
                "same": gt.copy()}


@pytest.mark.parametrize("name", ["blurred_noisy", "affine", "noise", "same"])
def test_ssim_matches_independent_gaussian_ssim(name):
    gt, pairs = _pairs()
    got = ssim(pairs[name], gt)
    want = ref_ssim(pairs[name], gt)
    assert abs(got - want) <= SSIM_REF_ATOL, (got, want)
    assert image_metrics(pairs[name], gt)["ssim"] == got
    if name == "same":
        assert got == pytest.approx(1.0, abs=SSIM_REF_ATOL)


def test_standard_ssim_is_lower_than_skimage_default_on_blurred_noisy():
    """The old figure (7x7 uniform window, sample covariance) reads higher on a blurred, noisy
    render: the uniform 7x7 window averages noise over fewer, equally weighted pixels."""
    gt, pairs = _pairs()
    p = pairs["blurred_noisy"]
    old = structural_similarity(p, gt, channel_axis=-1, data_range=1.0)
    new = ssim(p, gt)
    assert old > new + 0.01, (old, new)
    assert abs(new - ref_ssim(p, gt)) <= SSIM_REF_ATOL


def test_ssim_needs_the_window():
    a = np.zeros((SSIM_WINDOW - 1, 20, 3))
    assert np.isnan(ssim(a, a))
    b = np.zeros((SSIM_WINDOW, SSIM_WINDOW, 3))
    assert ssim(b, b) == pytest.approx(1.0)
    with pytest.raises(ValueError, match="differ"):
        ssim(a, b)


# ---- the colour-corrected PSNR (docs/evaluation.md) ----------------------------------------
def test_a_known_affine_change_per_channel_is_undone_exactly():
    """A render that is the ground truth under r = alpha gt + beta per channel (inside [0, 1];
    the blue channel unchanged): the fit finds the inverse map, the corrected render is the
    ground truth to rounding, and the score is a perfect match's."""
    from clrf.training.metrics import colour_corrected, psnr_color_corrected
    gt = np.random.default_rng(1).uniform(0, 1, (13, 17, 3))
    render = gt * np.array([0.5, 0.8, 1.0]) + np.array([0.2, 0.1, 0.0])
    assert render.min() >= 0 and render.max() <= 1
    np.testing.assert_allclose(colour_corrected(render, gt), gt, rtol=0, atol=1e-12)
    assert psnr_color_corrected(render, gt) > 200
    assert image_metrics(render, gt)["psnr"] < 25          # the plain score sees the change


def test_noise_after_an_affine_change_is_bounded_by_its_own_power():
    """r = alpha (gt + n) + beta: the true inverse map leaves the noise n, so the least-squares
    map's error is at most mean(n^2) (a bound that holds for the sample, not on average); the
    corrected PSNR is never below the plain one (the identity is a candidate map)."""
    from clrf.training.metrics import psnr_color_corrected
    rng = np.random.default_rng(2)
    gt = rng.uniform(0.1, 0.9, (32, 24, 3))
    for sigma in (1e-3, 1e-2, 3e-2):
        n = rng.normal(0, sigma, gt.shape)
        render = 0.6 * (gt + n) + 0.15
        assert render.min() >= 0 and render.max() <= 1
        bound = -10 * np.log10(np.mean(n ** 2))
        got = psnr_color_corrected(render, gt)
        assert bound <= got < bound + 1.0, (sigma, got, bound)
        assert got >= image_metrics(render, gt)["psnr"]


def test_a_constant_channel_maps_to_the_ground_truths_mean():
    from clrf.training.metrics import colour_corrected
    gt = np.random.default_rng(3).uniform(0, 1, (5, 6, 3))
    render = np.full_like(gt, 0.3)
    np.testing.assert_allclose(colour_corrected(render, gt).reshape(-1, 3),
                               np.broadcast_to(gt.reshape(-1, 3).mean(0), (30, 3)), atol=1e-15)
