"""Prefix sums on the device: the offsets of variable-length rows (samples per ray, entries per
tile) from their counts, with pyopencl's scan kernel. The counts never cross to the host; the
one value read back is the total, which sizes the buffers that follow.

>>> offsets, total = row_offsets(device, counts_d)   # counts int32 [n] on the device
>>> offsets                                          # int32 [n + 1]: 0, c0, c0 + c1, ...
>>> offsets, count, total = capped_offsets(device, counts_d, n, cap)   # nothing read back
"""
from __future__ import annotations

import warnings

import numpy as np
import pyopencl as cl
from pyopencl.scan import GenericScanKernel
from pyopencl.tools import context_dependent_memoize

from .programs import one_off, scratch

_scans_run = set()   # id() of the (memoized, kept) scan kernels that have run once


def run_scan(queue, scan, *args, **kwargs):
    """``scan(*args, queue=queue, **kwargs)``; its first run counts as one-off work
    (programs.one_off: PoCL compiles the scan's kernels for their work-group sizes there)."""
    if id(scan) in _scans_run:
        return scan(*args, queue=queue, **kwargs)
    _scans_run.add(id(scan))
    with one_off(queue):
        return scan(*args, queue=queue, **kwargs)


@context_dependent_memoize
def _offsets_scan(context, capped: bool = False):
    """The int32 counts -> int32 [n + 1] offsets scan of ``context`` (built once): offsets[0] is
    0 and offsets[i + 1] the inclusive sum to i; the total also in a one-item int64 array
    (summed in 64 bits, so that a total past 2^31 is seen, not wrapped). ``capped``: every
    offset at most ``cap`` (two more arguments), and the capped total also in a one-item int32
    array ``count`` (the live rows of a bounded buffer of cap rows)."""
    arguments = ("__global const int *counts, __global int *offsets, __global long *total, "
                 "const int n")
    item, last = "item", "total[0] = item;"
    if capped:
        arguments += ", __global int *count, const int cap"
        item = "min(item, (long)cap)"
        last = "total[0] = item; count[0] = (int)min(item, (long)cap);"
    with warnings.catch_warnings():
        # pyopencl warns on any non-empty build log, chatter included (programs.build)
        warnings.simplefilter("ignore", cl.CompilerWarning)
        return GenericScanKernel(
            context, np.int64, arguments=arguments,
            input_expr="counts[i]", scan_expr="a+b", neutral="0",
            output_statement=f"offsets[i + 1] = (int){item}; if (i == 0) offsets[0] = 0; "
                             f"if (i + 1 == n) {{ {last} }}")


def capped_offsets(device, counts, n: int, cap: int):
    """(offsets int32 [n + 1], count int32 [1], total int64 [1]), all on the device, of the
    first n int32 ``counts`` with every offset capped at ``cap`` (rows past cap are dropped: a
    bounded buffer of cap rows). count holds the capped total, total the whole one. Nothing is
    read back: the kernels that follow read count on the device (common.h live_rows)."""
    n, cap = int(n), int(cap)
    if not 0 <= cap < 1 << 31:
        raise ValueError(f"capacity {cap}: must be in 0 .. 2^31 - 1")
    offsets = scratch(device, (n + 1,), np.int32)
    count = scratch(device, (1,), np.int32)
    total = scratch(device, (1,), np.int64)
    if n == 0:
        offsets.fill(0)
        count.fill(0)
        total.fill(0)
        return offsets, count, total
    run_scan(device.queue, _offsets_scan(device.context, True), counts, offsets, total,
             np.int32(n), count, np.int32(cap), size=n)
    return offsets, count, total


def row_offsets(device, counts, n: int | None = None, what: str = "rows"):
    """(offsets int32 [n + 1] on the device, total) of the first n (default all) int32
    ``counts`` on the device. Reads one int64 back. Raises ValueError (naming the rows as
    ``what``) when the total does not fit the int32 offsets."""
    n = int(counts.shape[0]) if n is None else int(n)
    offsets = scratch(device, (n + 1,), np.int32)
    if n == 0:
        offsets.fill(0)
        return offsets, 0
    total = scratch(device, (1,), np.int64)
    run_scan(device.queue, _offsets_scan(device.context), counts, offsets, total, np.int32(n),
             size=n)
    m = int(total.get()[0])
    if m >= 1 << 31:
        raise ValueError(f"{m} {what} exceed the int32 offsets")
    return offsets, m


__all__ = ["capped_offsets", "row_offsets"]
