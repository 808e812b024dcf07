"""Host side of cl/hash.cl: the multiresolution hash encoding (tables, forward, backward) and the
SH direction encoding. Math and layouts are in the kernel file's header.

>>> enc = HashEncoding(dev, levels=16, features=2, log2_t=19, n_min=16, n_max=2048,
...                    box=((-1.5,) * 3, (1.5,) * 3), seed=0)
>>> y = enc.forward(x_d)            # x_d [n, 3] device -> y [n, L F] device
>>> enc.backward(x_d, dy_d)         # enc.grad [L, T, F] += dL/dtable
>>> gx = enc.dx(x_d, dy_d)          # dL/dx [n, 3] device (pose refinement)
"""
from __future__ import annotations

import math

import numpy as np
import pyopencl as cl
import pyopencl.array as cla

from ..runtime.programs import count_arg, float4, launch, scratch, upload

INIT_SCALE = 1e-4   # tables start uniform in +-INIT_SCALE (the published initialisation)
SH_DIM = 16         # hash_sh_encode: degree 3 (4 bands), 16 coefficients


def level_resolutions(levels: int, n_min: int, n_max: int) -> np.ndarray:
    """N_l = floor(N_min b^l), b = exp((ln N_max - ln N_min) / (L - 1)), int32 [L]; the 1e-9
    keeps N_{L-1} = N_max where b^(L-1) rounds just below it."""
    if levels < 1 or n_min < 1 or n_max < n_min:
        raise ValueError(f"hash levels: need levels >= 1 and 1 <= n_min <= n_max, got "
                         f"{levels}, {n_min}, {n_max}")
    if levels == 1:
        return np.array([n_min], np.int32)
    b = math.exp((math.log(n_max) - math.log(n_min)) / (levels - 1))
    return np.array([math.floor(n_min * b ** l + 1e-9) for l in range(levels)], np.int32)


def box_args(box):
    """(lo, inv_ext) as float4 kernel arguments for box = (lo[3], hi[3]) with hi > lo."""
    lo = np.asarray(box[0], np.float64)
    hi = np.asarray(box[1], np.float64)
    if lo.shape != (3,) or hi.shape != (3,) or not np.all(np.isfinite(lo)) \
            or not np.all(np.isfinite(hi)) or not np.all(hi > lo):
        raise ValueError(f"hash box: need finite lo < hi per axis, got {box}")
    inv = 1.0 / (hi - lo)
    f4 = float4
    return f4(*lo, 0.0), f4(*inv, 0.0), lo.astype(np.float32), inv.astype(np.float32)


def program(device, levels: int, features: int, log2_t: int):
    """cl/hash.cl for ``levels`` x ``features`` tables of 2^log2_t rows on ``device``: the
    table gradient owned per level (no atomics) where the device's tuning has gradient slots
    (CPUs), else added with atomics."""
    return device.program("hash.cl", {
        "HASH_LEVELS": int(levels), "HASH_FEATURES": int(features), "HASH_LOG2_T": int(log2_t),
        "HASH_GRAD_OWNED": int(int(device.tuning.grad_slots) > 0)})


class HashEncoding:
    """The tables [L, T, F] (float32) and their gradient on a device. The backward's
    accumulation follows device.tuning.grad_slots like the grid's: 0 (GPUs) float atomics,
    > 0 (CPUs) one work-item per level owning that level's table (``owned``; no atomics, no
    scratch)."""

    def __init__(self, device, levels=16, features=2, log2_t=19, n_min=16, n_max=2048,
                 box=((-1.0,) * 3, (1.0,) * 3), seed=0, table=None):
        self.device = device
        self.levels, self.features, self.log2_t = int(levels), int(features), int(log2_t)
        if self.features not in (1, 2, 4):
            raise ValueError(f"hash features: must be 1, 2 or 4, got {features}")
        if not 1 <= self.log2_t <= 24:
            raise ValueError(f"hash log2_t: must be in 1..24, got {log2_t}")
        self.T = 1 << self.log2_t
        self.res_host = level_resolutions(self.levels, int(n_min), int(n_max))
        self.lo4, self.inv4, self.lo, self.inv_ext = box_args(box)
        self.box = (tuple(float(v) for v in box[0]), tuple(float(v) for v in box[1]))
        self.owned = int(device.tuning.grad_slots) > 0
        self.program = program(device, self.levels, self.features, self.log2_t)
        q = device.queue
        self.shape = (self.levels, self.T, self.features)
        if table is None:
            rng = np.random.default_rng(seed)
            table = rng.uniform(-INIT_SCALE, INIT_SCALE, self.shape)
        table = np.asarray(table, np.float32)
        if table.shape != self.shape:
            raise ValueError(f"hash table: expected shape {self.shape}, got {table.shape}")
        self.res = upload(q, self.res_host)
        self.table = upload(q, np.ascontiguousarray(table))
        self.grad = cla.zeros_like(self.table)

    @property
    def dim(self) -> int:
        return self.levels * self.features

    @property
    def n_params(self) -> int:
        return int(self.table.size)

    def used_spans(self) -> list[tuple[int, int]]:
        """(start, stop) ranges of the flat table that a point can reach: a dense level
        ((N_l + 1)^3 <= T) uses its first (N_l + 1)^3 rows only, a hashed level all T. The
        optimiser steps these alone (lego_400: 68 % of the entries); adjacent
        ranges are merged."""
        spans = []
        for l, N in enumerate(self.res_host):
            rows = min(self.T, (int(N) + 1) ** 3)
            a = l * self.T * self.features
            b = a + rows * self.features
            if spans and spans[-1][1] == a:
                spans[-1] = (spans[-1][0], b)
            else:
                spans.append((a, b))
        return spans

    def forward(self, x, out=None, count=None):
        """enc [n, L F] of points x [n, 3] (device float32); ``count`` (int32 [1] on the
        device, or None): only its first count rows (a bounded buffer of n)."""
        n = int(x.shape[0])
        out = out if out is not None else scratch(self.device, (n, self.dim))
        self._launch_points_levels(
            self.program.kernel("hash_forward"), n,
            (np.int32(n), count_arg(count), x.data, self.lo4, self.inv4, self.res.data,
             self.table.data, out.data))
        return out

    def _launch_points_levels(self, kernel, n, args):
        """A 2-D launch over (point, level): n rounded up to the local size, L levels."""
        if n <= 0:
            return
        ls = max(1, min(int(self.device.tuning.elementwise_local_size),
                        self.device.caps.max_work_group_size))
        kernel.set_args(*args)
        cl.enqueue_nd_range_kernel(self.device.queue, kernel, (-(-n // ls) * ls, self.levels),
                                   (ls, 1))

    def backward(self, x, genc, count=None):
        """self.grad += dL/dtable for dL/denc genc [n, L F] at points x [n, 3] (the first
        ``count`` rows: see forward)."""
        n = int(x.shape[0])
        if n == 0:
            return
        args = (np.int32(n), count_arg(count), x.data, self.lo4, self.inv4, self.res.data,
                genc.data,
                self.grad.data, self.grad.data)
        k = self.program.kernel("hash_backward")
        if not self.owned:
            self._launch_points_levels(k, n, args)
            return
        k.set_args(*args)   # one work-item (and work-group) per level
        cl.enqueue_nd_range_kernel(self.device.queue, k, (self.levels,), (1,))

    def dx(self, x, genc, out=None, count=None):
        """dL/dx [n, 3] (device, overwritten) of points x [n, 3] from dL/denc genc [n, L F]:
        per level the derivative of the trilinear weights times N_l, summed, times inv_ext
        (zero on an axis where the point is outside the box); the first ``count`` rows: see
        forward."""
        n = int(x.shape[0])
        if tuple(genc.shape) != (n, self.dim):
            raise ValueError(f"hash dx: dL/denc must be [{n}, {self.dim}], got {genc.shape}")
        out = out if out is not None else scratch(self.device, (n, 3))
        launch(self.device, self.program.kernel("hash_dx"), n,
               (np.int32(n), count_arg(count), x.data, self.lo4, self.inv4, self.res.data,
                self.table.data, genc.data, out.data),
               self.device.tuning.elementwise_local_size)
        return out

    def sh_encode(self, d, out=None, count=None):
        """SH basis (16) of the unit directions of d [n, 3] -> [n, 16] (the first ``count``
        rows: see forward)."""
        n = int(d.shape[0])
        out = out if out is not None else scratch(self.device, (n, SH_DIM))
        launch(self.device, self.program.kernel("hash_sh_encode"), n,
               (np.int32(n), count_arg(count), d.data, out.data),
               self.device.tuning.elementwise_local_size)
        return out
