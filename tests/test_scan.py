"""clrf/runtime/scan.py: row offsets from counts on the device, against numpy's cumsum."""
import numpy as np
import pyopencl.array as cla
import pytest

from clrf.runtime.scan import capped_offsets, row_offsets


@pytest.mark.parametrize("n", [1, 7, 1000, 70001])
def test_row_offsets_match_cumsum(device, n):
    """Counts with zeros and long runs: offsets[0] is 0, offsets[i + 1] the inclusive sum, the
    total the last; only the first n counts are read."""
    rng = np.random.default_rng(n)
    counts = rng.integers(0, 40, n + 5).astype(np.int32)
    counts[rng.random(n + 5) < 0.3] = 0
    d = cla.to_device(device.queue, counts)
    offsets, total = row_offsets(device, d, n)
    want = np.concatenate([[0], np.cumsum(counts[:n], dtype=np.int64)])
    np.testing.assert_array_equal(offsets.get(), want)
    assert total == int(want[-1]) and isinstance(total, int)


def test_row_offsets_of_nothing(device):
    offsets, total = row_offsets(device, cla.zeros(device.queue, 4, np.int32), 0)
    assert total == 0 and offsets.get().tolist() == [0]


def test_row_offsets_refuse_a_total_past_int32(device):
    """A total of 2^31 is summed in 64 bits and refused, not wrapped to a negative offset."""
    d = cla.to_device(device.queue, np.array([1 << 30, 1 << 30], np.int32))
    with pytest.raises(ValueError, match="exceed the int32 offsets"):
        row_offsets(device, d)


@pytest.mark.parametrize("cap", [0, 1, 100, 1234, 1 << 20])
def test_capped_offsets_match_clipped_cumsum(device, cap):
    """Offsets capped at a bounded buffer's capacity, its live count, and the whole total,
    nothing read back: a ray that crosses the cap keeps what fits, later ones nothing."""
    counts = np.random.default_rng(cap).integers(0, 9, 300).astype(np.int32)
    want = np.concatenate([[0], np.cumsum(counts)])
    offsets, count, total = capped_offsets(device, cla.to_device(device.queue, counts), 300, cap)
    np.testing.assert_array_equal(offsets.get(), np.minimum(want, cap))
    assert count.get()[0] == min(want[-1], cap) and total.get()[0] == want[-1]
    offsets, count, total = capped_offsets(device, cla.to_device(device.queue, counts), 0, cap)
    assert offsets.get().tolist() == [0] and count.get()[0] == 0 and total.get()[0] == 0
    with pytest.raises(ValueError, match="capacity"):
        capped_offsets(device, cla.to_device(device.queue, counts), 300, -1)


def test_one_off_work_is_left_out_of_timed_work(device):
    """Program builds (pyopencl's own kernels too), a kernel's first launch at a work-group
    size and a scan's first run count as one-off work (programs.one_off_seconds, which the
    trainer's clock leaves out); the same launch, reduction or scan again does not."""
    from clrf.runtime.device import Device
    from clrf.runtime.programs import launch
    # a new context of the same device: nothing built or run in it yet
    dev = Device(f"{device.platform_index}:{device.device_index}")
    q = dev.queue
    t0 = dev.build_seconds
    k = dev.program("probe.cl").kernel("clrf_probe")            # a[i] += 1
    t1 = dev.build_seconds
    assert t1 > t0
    a = cla.zeros(q, 64, np.float32)
    launch(dev, k, 64, (a.data,), 16)
    t2 = dev.build_seconds
    assert t2 > t1                   # first launch at 16
    launch(dev, k, 64, (a.data,), 16)
    assert dev.build_seconds == t2
    launch(dev, k, 64, (a.data,), 32)
    t3 = dev.build_seconds
    assert t3 > t2                   # another work-group size
    np.testing.assert_array_equal(a.get(), np.full(64, 3.0, np.float32))
    assert float(cla.sum(a, queue=q).get()) == 192.0   # pyopencl builds its reduction here
    t4 = dev.build_seconds
    assert t4 > t3
    assert float(cla.sum(a, queue=q).get()) == 192.0
    assert dev.build_seconds == t4
    counts = cla.to_device(q, np.arange(10, dtype=np.int32))
    row_offsets(dev, counts)         # the scan's build and first run
    t5 = dev.build_seconds
    assert t5 > t4
    offsets, total = row_offsets(dev, counts)
    assert dev.build_seconds == t5 and total == 45
    np.testing.assert_array_equal(offsets.get(), np.r_[0, np.cumsum(np.arange(10))])


def test_a_library_kernels_first_run_is_one_off(device):
    """``first_run``: the first run of one of pyopencl's kernels that clrf calls every step (the
    splat model's image widening, an ElementwiseKernel; cla.sum in the hash model) counts as
    one-off work on its device, later runs do not; the work is done either way."""
    from clrf.runtime.device import Device
    from clrf.runtime.programs import first_run
    from clrf.splat.targets import DeviceImages
    dev = Device(f"{device.platform_index}:{device.device_index}")
    img = (np.arange(4 * 5 * 3).reshape(4, 5, 3) % 256 / 255.0).astype(np.float32)
    images = DeviceImages(dev, {0: img, 1: img[::-1].copy()})
    t0 = dev.build_seconds
    np.testing.assert_array_equal(images.get(1).get(), img[::-1])
    t1 = dev.build_seconds
    assert t1 > t0                   # the kernel's build and first launch
    np.testing.assert_array_equal(images.get(0).get(), img)
    assert dev.build_seconds == t1
    ran = []
    with first_run(dev, "a key"):
        ran.append(1)
    t2 = dev.build_seconds
    assert t2 > t1
    with first_run(dev, "a key"):
        ran.append(2)
    assert dev.build_seconds == t2 and ran == [1, 2]
