"""A stable sort of uint32 keys on the device for CPUs (cl/sort.cl): least-significant-digit
radix passes of 8 bits, each a counting sort over a few contiguous chunks of the items, one
work-item a chunk. On a CPU this is what pyopencl's RadixSort (built for many narrow work-items)
is not: the 176k depth keys of a splat frame sort in a few milliseconds instead of about 24 (2
vCPUs of a Xeon with AVX-512, PoCL 3.1).

>>> order = key_order(device, keys_d)   # uint32 [n] on the device -> int32 [n]:
>>>                                     # keys[order] ascending, ties in input order
"""
from __future__ import annotations

import numpy as np

from .programs import launch, scratch

RADIX_BITS = 8
MAX_CHUNKS = 64          # work-items of a pass; a few per core balance a CPU's threads
MIN_CHUNK = 1024         # fewer items a chunk cost more in histograms than they save


def program(device):
    """cl/sort.cl on ``device``."""
    return device.program("sort.cl", {"RADIX_BITS": RADIX_BITS})


def chunking(n: int, max_chunks: int | None = None) -> tuple[int, int]:
    """(chunk, nchunks): n items cut into nchunks contiguous chunks of ``chunk`` items (the last
    shorter), at most ``max_chunks`` (default MAX_CHUNKS) of them and none under MIN_CHUNK
    items unless n is."""
    n = max(int(n), 1)
    max_chunks = MAX_CHUNKS if max_chunks is None else int(max_chunks)
    nchunks = max(1, min(max_chunks, n // max(MIN_CHUNK, 1)))
    chunk = -(-n // nchunks)
    return chunk, -(-n // chunk)


def key_order(device, keys, n: int | None = None, key_bits: int = 32):
    """The stable ascending order (int32 [n] on the device) of the first n (default all) uint32
    ``keys`` on the device, whose values are below 2**key_bits. ``keys`` is not changed."""
    n = int(keys.shape[0]) if n is None else int(n)
    if keys.dtype != np.uint32:
        raise TypeError(f"keys: expected uint32, got {keys.dtype}")
    if not 1 <= int(key_bits) <= 32:
        raise ValueError(f"key_bits: must be in 1..32, got {key_bits}")
    if n <= 1:                   # nothing to sort: [] or [0]
        return scratch(device, (n,), np.int32).fill(0)
    prg = program(device)
    count, offsets, scatter = (prg.kernel(k) for k in ("radix_count", "radix_offsets",
                                                        "radix_scatter"))
    chunk, nchunks = chunking(n)
    hist = scratch(device, (nchunks, 1 << RADIX_BITS), np.int32)
    bufs = [(scratch(device, (n,), np.uint32), scratch(device, (n,), np.int32)) for _ in "ab"]
    src_k, src_v = keys, None
    for p, shift in enumerate(range(0, int(key_bits), RADIX_BITS)):
        dst_k, dst_v = bufs[p % 2]
        head = (np.int32(n), np.int32(chunk), np.int32(nchunks), np.int32(shift))
        launch(device, count, nchunks, head + (src_k.data, hist.data), 1)
        launch(device, offsets, 1, (np.int32(nchunks), hist.data), 1)
        launch(device, scatter, nchunks,
               head + (np.int32(p == 0), src_k.data, None if src_v is None else src_v.data,
                       hist.data, dst_k.data, dst_v.data), 1)
        src_k, src_v = dst_k, dst_v
    return src_v


__all__ = ["chunking", "key_order"]
