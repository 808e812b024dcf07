"""clrf/runtime/sort.py (cl/sort.cl): the stable order of uint32 keys on the device, against
numpy's stable argsort."""
import numpy as np
import pyopencl.array as cla
import pytest

from clrf.runtime import sort
from clrf.runtime.sort import chunking, key_order


def _keys(n, seed, bits=32):
    rng = np.random.default_rng(seed)
    k = rng.integers(0, 1 << bits, n, dtype=np.uint64).astype(np.uint32)
    k[rng.random(n) < 0.3] = k[0]                  # many ties, which must keep input order
    return k


@pytest.mark.parametrize("n", [2, 5, 1023, 1024, 1025, 70001, 66 * 1024 + 3])
def test_key_order_is_the_stable_argsort(device, n):
    """Sizes under, at and past one chunk and past the most chunks (64 x 1024); the keys are
    left as they were."""
    k = _keys(n, n)
    d = cla.to_device(device.queue, k)
    order = key_order(device, d)
    assert order.dtype == np.int32 and order.shape == (n,)
    np.testing.assert_array_equal(order.get(), np.argsort(k, kind="stable"))
    np.testing.assert_array_equal(d.get(), k)


def test_key_order_of_the_first_n_and_fewer_bits(device):
    """Only the first n keys are sorted; key_bits 12 sorts keys below 2^12 in two passes."""
    k = _keys(5000, 3, bits=12)
    order = key_order(device, cla.to_device(device.queue, k), 4000, key_bits=12)
    np.testing.assert_array_equal(order.get(), np.argsort(k[:4000], kind="stable"))


def test_key_order_with_many_small_chunks(device, monkeypatch):
    """Chunks of 3 items (64 of them over 192 keys): every chunk boundary splits runs of ties."""
    monkeypatch.setattr(sort, "MIN_CHUNK", 3)
    k = (np.arange(192) % 4).astype(np.uint32)[::-1].copy()
    assert chunking(192) == (3, 64)
    order = key_order(device, cla.to_device(device.queue, k))
    np.testing.assert_array_equal(order.get(), np.argsort(k, kind="stable"))


def test_key_order_of_none_and_one(device):
    assert key_order(device, cla.zeros(device.queue, 0, np.uint32)).shape == (0,)
    assert key_order(device, cla.zeros(device.queue, 1, np.uint32)).get().tolist() == [0]


def test_key_order_bad_input(device):
    with pytest.raises(TypeError, match="uint32"):
        key_order(device, cla.zeros(device.queue, 4, np.int32))
    with pytest.raises(ValueError, match="key_bits"):
        key_order(device, cla.zeros(device.queue, 4, np.uint32), key_bits=0)


@pytest.mark.parametrize("n,most,want", [(1, 64, (1, 1)), (5000, 64, (1250, 4)),
                                         (10 ** 6, 64, (15625, 64)), (10 ** 6, 8, (125000, 8))])
def test_chunking(n, most, want):
    chunk, nchunks = chunking(n, most)
    assert (chunk, nchunks) == want and (nchunks - 1) * chunk < n <= nchunks * chunk
