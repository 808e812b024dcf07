"""The device memory ledger (clrf/runtime/devmem.py): what it counts, when it lets go of an
array, the pool's held and in-use blocks, the peaks, and a model's share of it."""
import gc

import numpy as np
import pyopencl as cl
import pyopencl.array as cla
import pytest

from clrf.runtime.device import Device
from clrf.runtime.devmem import counted
from clrf.runtime.programs import device_empty, device_zeros, scratch, upload


@pytest.fixture
def fresh(device):
    """A new context of the session device: its own pool and ledger, nothing held yet."""
    return Device(f"{device.platform_index}:{device.device_index}")


def released():
    gc.collect()   # (CPython frees on the last reference; this only makes it certain)


def test_arrays_are_counted_while_any_view_of_them_lives(fresh):
    mem, q = fresh.memory, fresh.queue
    assert (mem.buffer_bytes, mem.held_bytes, mem.in_use_bytes) == (0, 0, 0)
    a = upload(q, np.arange(1000, dtype=np.float32))
    assert mem.buffer_bytes == 4000
    z = device_zeros(q, (10, 5), np.int32)
    e = device_empty(q, 7, np.float64)
    assert mem.buffer_bytes == 4000 + 200 + 56 == mem.held_bytes == mem.in_use_bytes
    np.testing.assert_array_equal(z.get(), np.zeros((10, 5), np.int32))
    np.testing.assert_array_equal(a.get(), np.arange(1000, dtype=np.float32))
    views = [a.reshape(10, 100), a[3:7]]
    del a
    released()
    assert mem.buffer_bytes == 4256          # the views hold the buffer
    np.testing.assert_array_equal(views[1].get(), [3, 4, 5, 6])
    del views
    released()
    assert mem.buffer_bytes == 256
    del z, e
    released()
    assert mem.buffer_bytes == 0


def test_arrays_made_from_counted_ones_are_counted(fresh):
    """pyopencl's arithmetic and zeros_like take the operand's allocator."""
    mem, q = fresh.memory, fresh.queue
    a = upload(q, np.full(256, 2.0, np.float32))
    b = a * 3
    c = cla.zeros_like(a)
    assert mem.buffer_bytes == 3 * 1024
    np.testing.assert_array_equal(b.get(), np.full(256, 6.0, np.float32))
    del b, c
    released()
    assert mem.buffer_bytes == 1024


def test_pool_blocks_are_held_until_the_pool_lets_them_go(fresh):
    mem = fresh.memory
    s = scratch(fresh, (1000,))
    assert mem.in_use_bytes >= 4000 and mem.held_bytes >= mem.in_use_bytes
    assert mem.active_blocks == 1 and mem.buffer_bytes == 0
    del s
    released()
    assert mem.in_use_bytes == 0 and mem.held_bytes >= 4000    # kept for reuse
    assert mem.held_blocks == 1
    s = scratch(fresh, (900,))                                 # the same bin: reused
    assert mem.held_blocks == 0 and mem.active_blocks == 1
    del s
    released()
    mem.free_held()
    assert mem.held_bytes == 0


def test_peaks_keep_the_largest_and_start_again_from_now(fresh):
    mem, q = fresh.memory, fresh.queue
    keep = upload(q, np.zeros(100, np.float32))
    big = device_empty(q, 1 << 18)                            # 1 MiB
    s = scratch(fresh, (1 << 16,))                            # 256 KiB from the pool
    top_held, top_use = mem.held_bytes, mem.in_use_bytes
    assert top_held >= 400 + (1 << 20) + (1 << 18)
    del big, s
    released()
    assert mem.peak_held == top_held and mem.peak_in_use == top_use
    assert mem.in_use_bytes == 400
    mem.reset_peaks()
    assert (mem.peak_held, mem.peak_in_use) == (mem.held_bytes, 400)
    s = mem.summary()
    assert s == {"held_bytes": mem.held_bytes, "in_use_bytes": 400,
                 "peak_held_bytes": mem.held_bytes, "peak_in_use_bytes": 400}
    assert "device memory: peak" in mem.describe()
    del keep


def test_a_queue_that_no_device_made_is_not_counted(device):
    ctx = cl.Context([device.cl_device])
    q = cl.CommandQueue(ctx)
    assert counted(q) is None
    a = device_zeros(q, 16)                                   # pyopencl's own buffer
    np.testing.assert_array_equal(a.get(), np.zeros(16, np.float32))


def _splat_model(dev, n, images_on_device="auto"):
    from clrf import registry
    from clrf.data import load_dataset
    from clrf.training.config import build_config
    ds = load_dataset(None)
    cfg = build_config("procedural", overrides={"train": {"model": "splat"},
                                                "splat": {"preset": "tiny", "init_points": n,
                                                          "max_gaussians": n,
                                                          "images_on_device": images_on_device}})
    return registry.get("splat").create(dev, cfg, ds, ds.background)


def test_a_splat_models_device_memory_grows_with_its_gaussians(device):
    """Each Gaussian's parameters and both Adam moments (59 floats each at SH degree 3) are
    counted, so 10x the Gaussians take at least that much more; the steps' arrays (the
    projection, the tile lists, the gradients) come on top."""
    peaks = {}
    for n in (300, 3000):
        dev = Device(f"{device.platform_index}:{device.device_index}")
        m = _splat_model(dev, n)
        held = dev.memory.in_use_bytes
        assert held >= 3 * 59 * 4 * m.n
        for it in range(2):
            assert np.isfinite(m.train_step(it))
        peaks[n] = dev.memory.peak_in_use
        assert peaks[n] > held                                 # a step's arrays
        del m
    assert peaks[3000] - peaks[300] >= 3 * 59 * 4 * (3000 - 300)


@pytest.mark.parametrize("images_on_device", ["true", "false"])
@pytest.mark.slow
def test_the_memory_guards_splat_estimate_matches_what_a_run_holds(device, images_on_device):
    """The memory guard's device terms for a splat run (clrf/splat/budget.py, per Gaussian and
    per pixel, and the training images resident or streamed) against the ledger's peak over a
    few training steps: on the safe side, and not so far above it that the guard would refuse
    runs that fit (the guard adds the runtime's own growth on top)."""
    from clrf.data import load_dataset
    from clrf.splat.budget import copies_on, splat_stage, target_pixels
    ds = load_dataset(None)
    H, W = ds.hw
    for n in (3000, 20000):
        dev = Device(f"{device.platform_index}:{device.device_index}")
        m = _splat_model(dev, n, images_on_device)
        for it in range(3):
            assert np.isfinite(m.train_step(it))
        assert m._targets.resident is (images_on_device == "true")
        train = target_pixels(m.config, dev.caps, H * W, len(ds.split["train"]) * H * W)
        est = splat_stage(m.config, m.n, H * W, train, copies_on(dev.caps)).total
        ratio = est / dev.memory.peak_held
        assert 1.0 <= ratio <= 1.6, (n, est, dev.memory.peak_held)
        del m
