"""The training images on the device (clrf/splat/targets.py DeviceImages): 8-bit images stored
as uint8 and widened to the dataset's float32 bit for bit; others (averaged down, composited on
a background, 16-bit) stored as float16 and widened exactly to numpy's float16 -> float32, within
half an ulp of float16 of the original; one float32 buffer reused; the argument checks; and
the device loss and its gradient against the compact copy equal those against a float32
upload of the same 8-bit image; the dataset's 8-bit store uploads one view at a time."""
import numpy as np
import pytest

from clrf.runtime.programs import upload
from clrf.splat import targets as tg

# float16 keeps 11 significant bits: rounding to nearest is off by at most 2^-11 relative
# (the unit roundoff; values in [2^-14, 1]); below 2^-14 (subnormal halves, spaced 2^-24) by
# at most 2^-25 absolute.
HALF_RTOL = 2.0 ** -11
HALF_ATOL = 2.0 ** -25


def _eight_bit(rng, shape):
    return (rng.integers(0, 256, shape).astype(np.float32) / np.float32(255.0))


def test_levels_are_the_datasets_division():
    # clrf/data/io.py: a.astype(np.float32) / 255.0
    k = np.arange(256, dtype=np.uint8)
    assert np.array_equal(tg.LEVELS, k.astype(np.float32) / 255.0)


def test_exact_8bit_detects_what_uint8_keeps(rng=np.random.default_rng(0)):
    a = _eight_bit(rng, (5, 7, 3))
    assert tg.exact_8bit([a, a[::-1].copy()])
    b = a.copy()
    b[2, 3, 1] = np.nextafter(b[2, 3, 1], np.float32(2))   # one ulp off a level
    assert not tg.exact_8bit([a, b])
    between = (tg.LEVELS[:-1] + tg.LEVELS[1:]) / np.float32(2)   # a 2-pixel average
    assert not tg.exact_8bit([between.reshape(-1, 5, 3)])
    assert not tg.exact_8bit([np.full((2, 2, 3), 1.5, np.float32)])
    assert not tg.exact_8bit([np.full((2, 2, 3), -1 / 255, np.float32)])


def test_uint8_images_widen_bit_for_bit(device):
    rng = np.random.default_rng(1)
    images = {3: _eight_bit(rng, (37, 23, 3)), 8: _eight_bit(rng, (37, 23, 3))}
    images[3][0, 0] = (0.0, 1.0, 0.0)
    d = tg.DeviceImages(device, images)
    assert d.dtype == np.uint8
    assert d.nbytes == 2 * 37 * 23 * 3
    for v in (3, 8, 3):
        got = d.get(v).get()
        assert got.dtype == np.float32 and got.shape == (37, 23, 3)
        assert np.array_equal(got, images[v])
        assert np.array_equal(d.host_copy(v), images[v])
    assert 8 in d and 4 not in d


@pytest.mark.parametrize("rgba", [False, True])
def test_dataset_image_stack_uploads_one_view_at_a_time(device, rgba):
    """The dataset's 8-bit store (clrf/data/images.py ImageStack) through ViewImages: only the
    asked views, each read when needed; RGB levels go up as uint8, RGBA composited on the
    background as float16, and both widen to what the stack reads."""
    from clrf.data.images import ImageStack
    rng = np.random.default_rng(4)
    levels = rng.integers(0, 256, (6, 9, 11, 4 if rgba else 3), dtype=np.uint8)
    stack = ImageStack(levels, (1.0, 0.5, 0.0) if rgba else None)
    views = tg.ViewImages(stack, [5, 1, 2])
    assert list(views) == [5, 1, 2] and len(views) == 3 and 0 not in views
    with pytest.raises(KeyError):
        views[0]
    d = tg.DeviceImages(device, views)
    assert d.dtype == (np.float16 if rgba else np.uint8)
    for v in (1, 5, 2):
        want = stack[v]
        if rgba:
            assert np.array_equal(d.get(v).get(), want.astype(np.float16).astype(np.float32))
        else:
            assert np.array_equal(d.get(v).get(), want)
    assert 0 not in d and 3 not in d


@pytest.mark.parametrize("kind", ["averaged", "composited", "sixteen_bit"])
def test_other_images_widen_to_numpys_halves(device, kind):
    rng = np.random.default_rng(2)
    if kind == "averaged":      # train.downscale: 4 x 4 means of 8-bit values
        full = _eight_bit(rng, (40, 28, 3))
        img = full.reshape(10, 4, 7, 4, 3).mean((1, 3), dtype=np.float32)
    elif kind == "composited":  # RGBA on a white background, some values tiny
        rgb, a = _eight_bit(rng, (10, 7, 3)), _eight_bit(rng, (10, 7, 1))
        img = (rgb * a + (1 - a)).astype(np.float32)
        img[0, 0] = (1e-6, 3e-5, 0.5)
    else:                       # 16-bit PNG levels
        img = (rng.integers(0, 65536, (10, 7, 3)) / np.float32(65535.0)).astype(np.float32)
    other = np.ascontiguousarray(img[::-1])
    d = tg.DeviceImages(device, {0: img, 5: other})
    assert d.dtype == np.float16
    assert d.nbytes == 2 * img.size * 2
    for v, ref in ((0, img), (5, other)):
        got = d.get(v).get()
        twin = ref.astype(np.float16).astype(np.float32)   # the float64-free twin: exact
        assert np.array_equal(got, twin)
        assert np.array_equal(d.host_copy(v), twin)
        np.testing.assert_allclose(got, ref, rtol=HALF_RTOL, atol=HALF_ATOL)
        # and float16 is not float32: the values moved (a check that could fail)
        assert not np.array_equal(got, ref)


def test_the_buffer_is_reused_and_in_order(device):
    rng = np.random.default_rng(3)
    images = {0: _eight_bit(rng, (6, 5, 3)), 1: _eight_bit(rng, (6, 5, 3))}
    d = tg.DeviceImages(device, images)
    a = d.get(0)
    snap = a.get()
    b = d.get(1)
    assert b.data.int_ptr == a.data.int_ptr
    assert np.array_equal(snap, images[0]) and np.array_equal(b.get(), images[1])


def test_bad_arguments(device):
    with pytest.raises(ValueError, match="no images"):
        tg.DeviceImages(device, {})
    with pytest.raises(ValueError, match="differ in shape"):
        tg.DeviceImages(device, {0: np.zeros((2, 2, 3), np.float32),
                                 1: np.zeros((2, 3, 3), np.float32)})


def test_loss_on_compact_targets_matches_float32(device):
    """The loss and dL/drgb of one render against DeviceImages equal those against the image
    uploaded as float32 (8-bit images: the widened copy is bit for bit the same)."""
    from clrf.splat.config import SplatConfig
    from clrf.splat.loss import DeviceLoss
    from clrf.splat.raster import SplatCamera, SplatRasterizer

    rng = np.random.default_rng(4)
    H, W = 24, 32
    img = _eight_bit(rng, (H, W, 3))
    d = tg.DeviceImages(device, {0: img})
    loss = DeviceLoss(device, H, W, SplatConfig().lambda_dssim)
    rast = SplatRasterizer(device, 0, 16)
    n = 50
    g = {"means": np.c_[rng.uniform(-1, 1, (n, 2)), rng.uniform(3, 5, n)].astype(np.float32),
         "log_scales": np.full((n, 3), -2.0, np.float32),
         "quats": np.tile(np.float32([1, 0, 0, 0]), (n, 1)),
         "opacity_logits": np.zeros(n, np.float32),
         "sh": rng.normal(0, 0.5, (n, 1, 3)).astype(np.float32)}
    cam = SplatCamera(np.eye(4, dtype=np.float64), 30.0, 30.0, W / 2, H / 2, W, H)
    _, _, ras = rast.forward(rast.upload(g), cam)
    g1, s1 = loss.loss_and_grad(ras.rgb, d.get(0))
    g1, s1 = g1.get(), s1.get()
    g2, s2 = loss.loss_and_grad(ras.rgb, upload(device.queue, img))
    assert np.array_equal(g1, g2.get()) and np.array_equal(s1, s2.get())
    assert s1[0] > 0
