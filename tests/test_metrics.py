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
