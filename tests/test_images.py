"""The host image store (clrf/data/images.py): 8-bit images kept as their levels read back as
the float32 the loaders made before, bit for bit; other images stay float32; loading never
holds a float32 copy of every image."""
from __future__ import annotations

import tracemalloc

import imageio.v3 as iio
import numpy as np
import pytest

from clrf.data.images import ImageStack, collect, composite
from clrf.runtime.levels import LEVELS, levels_of
from clrf.data.io import downscale_image, load_images, read_image

BG = (1.0, 0.25, 0.0)


def _rgb8(n=5, h=6, w=7, seed=0):
    return np.random.default_rng(seed).integers(0, 256, (n, h, w, 3), dtype=np.uint8)


def _rgba8(n=5, h=6, w=7, seed=1):
    a = np.random.default_rng(seed).integers(0, 256, (n, h, w, 4), dtype=np.uint8)
    a[:, 0, 0, 3] = 0                      # some fully transparent, some opaque pixels
    a[:, 0, 1, 3] = 255
    return a


def _float(u8):
    return u8.astype(np.float32) / 255.0   # what clrf/data/io.py read_image does


def test_levels_are_read_images_values():
    assert np.array_equal(LEVELS, _float(np.arange(256, dtype=np.uint8)))
    u = _rgb8()
    assert np.array_equal(levels_of(_float(u)), u)
    assert levels_of(_float(u) * np.float32(0.5)) is None          # 127.5 / 255
    assert levels_of(np.full((2, 2, 3), np.nan, np.float32)) is None
    assert levels_of(_float(u).astype(np.float64)) is None         # float32 only


def test_rgb_levels_read_back_bit_for_bit():
    u = _rgb8()
    want = _float(u)
    s, alpha = collect(iter(want), len(want))
    assert isinstance(s, ImageStack) and alpha is None
    assert s.shape == want.shape and s.dtype == np.float32 and len(s) == len(want)
    assert s.nbytes * 4 == want.nbytes
    idx = np.array([3, 0, 3])
    r, c = np.array([1, 5]), np.array([0, 6])
    for key in (2, -1, slice(1, 4), idx, (idx,), (2, 3), (idx[:2], r, c), (slice(None), 1, 2),
                (1, slice(None), 3, 0)):
        got = s[key]
        assert got.dtype == np.float32 and np.array_equal(got, want[key]), key
    assert np.array_equal(np.asarray(s), want)
    assert np.array_equal(np.asarray(s, np.float64), want.astype(np.float64))
    assert np.array_equal(np.stack(list(s)), want)
    assert s.mean() == want.mean() and s.max() == want.max()          # ndarray methods
    c = s.copy()
    c[0] = 0                                                          # a writable copy
    assert np.array_equal(s[0], want[0])


def test_rgba_levels_composite_on_access():
    u = _rgba8()
    f = _float(u)
    want = np.stack([composite(a, BG) for a in f])
    s, alpha = collect(iter(f), len(f), BG)
    assert isinstance(s, ImageStack) and s.shape == want.shape
    assert np.array_equal(np.asarray(s), want)
    assert np.array_equal(s[1:3], want[1:3]) and np.array_equal(s[4, 2], want[4, 2])
    assert np.array_equal(s[..., 1], want[..., 1])                   # a key on the channels
    assert np.array_equal(s[0, 1, 2, 0], want[0, 1, 2, 0])
    assert isinstance(alpha, ImageStack) and np.array_equal(np.asarray(alpha), f[..., 3])
    assert s.nbytes == u.nbytes                                       # alpha shares the levels


def test_opaque_rgba_is_kept_as_rgb():
    u = _rgba8()
    u[..., 3] = 255
    s, alpha = collect(iter(_float(u)), len(u), BG)
    assert alpha is None and s.background is None and s.levels.shape[-1] == 3
    assert np.array_equal(np.asarray(s), _float(u)[..., :3])


@pytest.mark.parametrize("channels", [3, 4])
def test_other_values_stay_float32(channels):
    """One image averaged down (not k / 255) anywhere in the stack: every image float32, the
    ones before it read back from their levels, composited as they would have been."""
    f = _float(_rgba8() if channels == 4 else _rgb8())
    f[3] = f[3] * np.float32(0.7)
    s, alpha = collect(iter(f), len(f), BG if channels == 4 else None)
    assert type(s) is np.ndarray and s.dtype == np.float32
    assert np.array_equal(s, np.stack([composite(a, BG) for a in f]))
    if channels == 4:
        assert type(alpha) is np.ndarray and np.array_equal(alpha, f[..., 3])
    else:
        assert alpha is None


def test_collect_refuses_what_it_cannot_store():
    f = _float(_rgb8())
    with pytest.raises(ValueError, match="image 2 is"):
        collect(iter([f[0], f[1], f[2][:3]]), 3)
    with pytest.raises(ValueError, match="4 images, expected 5"):
        collect(iter(f[:4]), 5)
    with pytest.raises(ValueError, match="need a background"):
        collect(iter(_float(_rgba8())), 5)
    with pytest.raises(ValueError, match="uint8"):
        ImageStack(f)
    with pytest.raises(ValueError, match="background"):
        ImageStack(_rgb8(), BG)
    s, alpha = collect(iter([]), 0)
    assert s.shape == (0, 0, 0, 3) and alpha is None


def _write(tmp_path, arrays):
    paths = []
    for i, a in enumerate(arrays):
        p = tmp_path / f"{i:03d}.png"
        iio.imwrite(p, a)
        paths.append(p)
    return paths


@pytest.mark.parametrize("channels", [3, 4])
def test_load_images_matches_the_float32_path(tmp_path, channels):
    """load_images reads the files into what reading, downscaling and compositing each one
    and stacking them gives, bit for bit, at the files' size and downscaled."""
    u = _rgba8(4, 16, 12) if channels == 4 else _rgb8(4, 16, 12)
    paths = _write(tmp_path, u)
    for factor in (1, 2):
        want = np.stack([composite(downscale_image(read_image(p), factor), BG) for p in paths])
        images, alpha, hw = load_images(paths, downscale=factor, background=BG)
        assert hw == (16, 12) and isinstance(images, ImageStack) == (factor == 1)
        assert np.array_equal(np.asarray(images), want)
        if channels == 4:
            a = np.stack([downscale_image(read_image(p), factor)[..., 3] for p in paths])
            assert np.array_equal(np.asarray(alpha), a)
        else:
            assert alpha is None


def test_loading_holds_no_float32_stack(tmp_path):
    """Peak memory of loading 8-bit files: the levels and a few single images, never the
    float32 stack (before: the list of float32 images, their stack and its cast at once)."""
    u = _rgb8(24, 128, 128, seed=3)
    paths = _write(tmp_path, u)
    stack = u.nbytes * 4
    tracemalloc.start()
    try:
        images, _, _ = load_images(paths)
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    assert np.array_equal(np.asarray(images), _float(u))
    print(f"float32 stack {stack / 2**20:.1f} MiB, peak while loading {peak / 2**20:.1f} MiB")
    assert peak < 0.5 * stack
