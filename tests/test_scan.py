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
