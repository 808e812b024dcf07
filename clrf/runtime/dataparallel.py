"""Data-parallel training over MPI ranks: every rank holds the whole model, takes its share of
each batch, and the ranks sum their gradients before the identical optimiser step.

A model that trains this way (the hash grid, clrf/hash/model.py) keeps a ``DataParallel`` in its
``ranks`` attribute. Every rank draws the same batch of B rays (the trainer's ray store is
deterministic in the seed and the step); rank r keeps rows ``share(B)`` = [r B / P, (r + 1) B
/ P) and scales its loss by 1 / B, not by its own row count, so the gradients of the P shares
add up to the one-process gradient of the whole batch. ``sum_gradients`` adds them up: every
gradient buffer (or the spans of it the optimiser steps) goes to the host, is summed at rank 0
(``Reduce``) and sent back to every rank (``Bcast``), so all ranks hold the same bits and,
after the same Adam step, the same parameters; anything a rank derives from them (the
occupancy grid) stays identical without being sent. Bytes per step: each rank sends and
receives its gradients once (4 bytes an entry each way).

>>> dp = DataParallel(comm)
>>> lo, hi = dp.share(4096)                        # rank 1 of 2: (2048, 4096)
>>> dp.sum_gradients([(net_grad, None), (table_grad, spans)])
"""
from __future__ import annotations

import numpy as np
import pyopencl as cl


def shard_bounds(n: int, ranks: int) -> list:
    """[lo, hi) of each of ``ranks`` ranks' rows of n, in rank order (the first n % ranks
    one more)."""
    base, extra = divmod(int(n), int(ranks))
    out, lo = [], 0
    for r in range(int(ranks)):
        hi = lo + base + (1 if r < extra else 0)
        out.append((lo, hi))
        lo = hi
    return out


class DataParallel:
    """The collective operations of one rank of a data-parallel run on ``comm`` (module
    doc)."""

    def __init__(self, comm):
        self.comm = comm
        self.rank, self.size = comm.Get_rank(), comm.Get_size()
        self.bytes_sent = 0          # counters for the scaling benchmark
        self.bytes_received = 0
        self._host = None            # the host buffer of sum_gradients, reused

    def share(self, n: int) -> tuple[int, int]:
        """This rank's rows [lo, hi) of a batch of n rows (``shard_bounds``)."""
        return shard_bounds(n, self.size)[self.rank]

    def total(self, x):
        """The sum of ``x`` (a number) over the ranks, the same on every rank."""
        from mpi4py import MPI
        return self.comm.allreduce(x, op=MPI.SUM)

    def sum_gradients(self, parts):
        """Sums device arrays over the ranks, in place: ``parts`` is a list of (float32 array,
        spans), spans a list of (start, stop) entry ranges of the flat array, or None for all
        of it. Every rank must pass the same shapes and spans."""
        from mpi4py import MPI
        pieces = []
        for arr, spans in parts:
            n = int(arr.size)
            for a, b in ([(0, n)] if spans is None else spans):
                if b > a:
                    pieces.append((arr, int(a), int(b)))
        total = sum(b - a for _, a, b in pieces)
        if total == 0:
            return
        if self._host is None or self._host.size != total:
            self._host = np.empty(total, np.float32)
        host = self._host
        at = 0
        for arr, a, b in pieces:
            if arr.dtype != np.float32:
                raise TypeError(f"sum_gradients: float32 arrays only, got {arr.dtype}")
            cl.enqueue_copy(arr.queue, host[at:at + b - a], arr.base_data,
                            src_offset=arr.offset + 4 * a, is_blocking=False)
            at += b - a
        pieces[0][0].queue.finish()
        if self.rank == 0:
            self.comm.Reduce(MPI.IN_PLACE, host, op=MPI.SUM, root=0)
        else:
            self.comm.Reduce(host, None, op=MPI.SUM, root=0)
        self.comm.Bcast(host, root=0)
        self.bytes_sent += host.nbytes        # this rank's share out, the sum back in
        self.bytes_received += host.nbytes
        at = 0
        for arr, a, b in pieces:
            cl.enqueue_copy(arr.queue, arr.base_data, host[at:at + b - a],
                            dst_offset=arr.offset + 4 * a, is_blocking=False)
            at += b - a
        pieces[0][0].queue.finish()
