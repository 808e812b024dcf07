"""The training images on the device (clrf/splat/targets.py DeviceImages): 8-bit images stored
as uint8 and widened to the dataset's float32 bit for bit; others (averaged down, composited on
a background, 16-bit) stored as float16 and widened exactly to numpy's float16 -> float32, within
half an ulp of float16 of the original; one float32 buffer reused; the argument checks; and
the device loss and its gradient against the compact copy equal those against a float32
upload of the same 8-bit image; the dataset's 8-bit store uploads one view at a time. Streamed
(splat.images_on_device): each view copied from the host, its uint8 levels or its float32
values, to the dataset's float32 image bit for bit, in order with what reads the buffer, in
less device memory; which mode "auto" picks; the setting's check."""
import gc

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


def _stack(rng, n=6, h=9, w=11):
    from clrf.data.images import ImageStack
    return ImageStack(rng.integers(0, 256, (n, h, w, 3), dtype=np.uint8))


def test_streamed_8bit_stack_is_the_datasets_image(device):
    """An RGB ImageStack streams its uint8 levels through the one-view staging buffer and
    widens them to what the stack reads, bit for bit, in one reused buffer."""
    stack = _stack(np.random.default_rng(5))
    d = tg.DeviceImages(device, tg.ViewImages(stack, [5, 1, 2]), resident=False)
    assert not d.resident and d.dtype == np.uint8
    assert d.nbytes == 9 * 11 * 3                   # the staging buffer alone
    ptr = d.get(1).data.int_ptr
    for v in (1, 5, 2, 5):
        got = d.get(v)
        assert got.data.int_ptr == ptr
        got = got.get()
        assert got.dtype == np.float32 and got.shape == (9, 11, 3)
        assert np.array_equal(got, stack[v])
        assert np.array_equal(d.host_copy(v), stack[v])
    assert 2 in d and 0 not in d
    with pytest.raises(KeyError):
        d.get(0)


@pytest.mark.parametrize("kind", ["averaged", "dict", "composited"])
def test_streamed_float_images_are_copied_exactly(device, kind):
    """Images that are not 8-bit levels (averaged down, any mapping of float32 arrays, an RGBA
    stack composited on its background) stream as their float32 values: exact, where the
    resident store rounds them to float16."""
    from clrf.data.images import ImageStack
    rng = np.random.default_rng(6)
    if kind == "composited":
        levels = rng.integers(0, 256, (4, 7, 5, 4), dtype=np.uint8)
        stack = ImageStack(levels, (1.0, 0.5, 0.0))
    else:
        full = _eight_bit(rng, (4, 28, 20, 3))
        stack = full.reshape(4, 7, 4, 5, 4, 3).mean((2, 4), dtype=np.float32)
    views = [3, 0]
    images = {v: stack[v] for v in views} if kind == "dict" else tg.ViewImages(stack, views)
    d = tg.DeviceImages(device, images, resident=False)
    assert d.dtype == np.float32 and d.nbytes == 0
    for v in (0, 3, 0):
        want = np.asarray(stack[v], np.float32)
        assert np.array_equal(d.get(v).get(), want)
        assert np.array_equal(d.host_copy(v), want)
        assert not np.array_equal(want.astype(np.float16).astype(np.float32), want)


@pytest.mark.parametrize("floats", [False, True])
def test_a_streamed_copy_waits_for_what_reads_the_buffer(device, floats):
    """The next view's copy is queued after a kernel that reads the previous one (the loss of
    a step): that kernel sees the previous view."""
    rng = np.random.default_rng(7)
    stack = _stack(rng, 3, 64, 48)
    if floats:
        stack = np.asarray(stack) * np.float32(0.5)
    d = tg.DeviceImages(device, tg.ViewImages(stack, [0, 1, 2]), resident=False)
    assert d.dtype == (np.float32 if floats else np.uint8)
    first = d.get(0)
    doubled = first * 2          # queued before the next copy
    d.get(1)
    assert np.array_equal(doubled.get(), np.asarray(stack[0]) * 2)
    assert np.array_equal(d.get(2).get(), np.asarray(stack[2]))


def test_resident_and_streamed_device_memory(device):
    """In the device's memory ledger (clrf/runtime/devmem.py), resident images hold a copy of
    every view and streamed ones only the staging buffer (both: the 256 levels' table), and the
    two make the same float32 images."""
    stack = _stack(np.random.default_rng(8), 8, 40, 30)
    views = tg.ViewImages(stack, range(8))
    mem = device.memory
    held = {}
    for res in (True, False):
        gc.collect()
        before = mem.buffer_bytes
        d = tg.DeviceImages(device, views, resident=res)
        assert d.resident is res and d.dtype == np.uint8
        held[res] = mem.buffer_bytes - before
        assert held[res] == d.nbytes + tg.LEVELS.nbytes
        for v in (3, 7):
            assert np.array_equal(d.get(v).get(), stack[v])
        del d
    assert held[True] == 8 * 40 * 30 * 3 + tg.LEVELS.nbytes
    assert held[False] == 40 * 30 * 3 + tg.LEVELS.nbytes < held[True]


def test_auto_streams_where_the_devices_memory_is_the_hosts(device, monkeypatch):
    """splat.images_on_device "auto": streamed on a device that reports host-unified memory
    (the CPU runtimes the tests run on), resident where it does not (and where the device is
    not known); the memory guard's image term follows the same decision."""
    from clrf.splat.budget import target_pixels
    from clrf.splat.config import SplatConfig
    caps = device.caps
    assert tg.resident("true", caps) and not tg.resident("false", caps)
    assert tg.resident("auto", caps) is not caps.host_unified_memory
    if device.is_cpu:
        assert caps.host_unified_memory and not tg.resident("auto", caps)
    assert tg.resident("auto", None)
    sc = SplatConfig()
    assert sc.images_on_device == "auto"
    assert target_pixels(sc, caps, 100, 5000) == (5000 if tg.resident("auto", caps) else 100)
    monkeypatch.setattr(tg, "host_unified", lambda caps: False)
    assert tg.resident("auto", caps)
    assert target_pixels(sc, caps, 100, 5000) == 5000


def test_the_setting_is_checked():
    from clrf.training.config import ConfigError, build_config
    for value, want in (("true", "true"), (False, "false"), (True, "true")):
        cfg = build_config("procedural", overrides={"splat": {"images_on_device": value}})
        assert cfg.splat.images_on_device == want
    with pytest.raises(ConfigError, match=r"splat\.images_on_device = 'yes': must be one of "
                                          r"\['auto', 'true', 'false'\]"):
        build_config("procedural", overrides={"splat": {"images_on_device": "yes"}})
