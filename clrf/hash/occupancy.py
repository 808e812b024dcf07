"""Host side of cl/hash_occ.cl: the occupancy grid of the hash model (math in the kernel
file's header; the sampler that reads it is clrf/hash/march.py).

>>> occ = OccupancyGrid(dev, res=128, box=((-1.5,) * 3, (1.5,) * 3))
>>> occ.update(density_fn, key, n_points, decay=0.95, threshold=0.05, start=0)
"""
from __future__ import annotations

import math

import numpy as np

from ..runtime.programs import device_empty, download, float4, launch, upload
from .encoding import box_args

POINTS_PER_LAUNCH = 1 << 18   # cells measured per density evaluation (bounds the MLP scratch)


def sweep_stride(n_cells: int) -> int:
    """The stride of the measuring sweep (cl/hash_occ.cl): the odd number nearest 0.618 of
    n_cells that is coprime with it (1 for n_cells <= 2), so that p -> p * stride mod n_cells
    is a permutation that scatters neighbouring positions over the grid."""
    if n_cells <= 2:
        return 1
    s = int(0.6180339887 * n_cells) | 1
    while math.gcd(s, n_cells) != 1:
        s += 2
    return s


class OccupancyGrid:
    """R^3 cells over the box: ``ema`` float [R^3] (-1: never measured) and ``occ`` uchar
    [R^3] (1: the sampler keeps samples there). Starts fully occupied."""

    def __init__(self, device, res: int, box, ema=None):
        self.device = device
        self.res = int(res)
        if not 1 <= self.res <= 256:
            raise ValueError(f"occupancy grid resolution: must be in 1..256, got {res}")
        self.lo4, self.inv4, lo, inv = box_args(box)
        ext = 1.0 / inv.astype(np.float64)
        self.ext4 = float4(*ext, 0.0)
        self.prg = device.program("hash_occ.cl", {})
        n = self.res ** 3
        q = device.queue
        if ema is None:
            ema = np.full(n, -1.0, np.float32)
        ema = np.asarray(ema, np.float32)
        if ema.shape != (n,):
            raise ValueError(f"occupancy ema: expected shape ({n},), got {ema.shape}")
        self.ema = upload(q, ema)
        self.occ = device_empty(q, n, np.uint8)
        self.stride = sweep_stride(n)
        self.threshold = 0.0
        self._threshold(0.0)

    @property
    def n_cells(self) -> int:
        return self.res ** 3

    def _k(self, name):
        return self.prg.kernel(name)

    def _threshold(self, thr: float):
        self.threshold = float(thr)
        self._fraction = None
        launch(self.device, self._k("occ_threshold"), self.n_cells,
               (np.int32(self.n_cells), np.float32(thr), self.ema.data, self.occ.data),
               self.device.tuning.elementwise_local_size)

    def occupied_fraction(self) -> float:
        """The fraction of occupied cells (a download, cached until the next threshold: the
        live viewer asks after every step)."""
        if self._fraction is None:
            self._fraction = float(np.count_nonzero(download(self.occ))) / self.n_cells
        return self._fraction

    def update(self, density_fn, key: int, n_points: int, decay: float, threshold: float,
               start: int = 0):
        """Decay the measured cells, measure density_fn (device xyz [m, 3] -> device sigma [m])
        at a random point of each cell at sweep positions start .. start + n_points - 1 (in
        launches of at most POINTS_PER_LAUNCH), and re-threshold."""
        dev, q = self.device, self.device.queue
        ls = dev.tuning.elementwise_local_size
        launch(dev, self._k("occ_decay"), self.n_cells,
               (np.int32(self.n_cells), np.float32(decay), self.ema.data), ls)
        for j0 in range(0, int(n_points), POINTS_PER_LAUNCH):
            m = min(POINTS_PER_LAUNCH, int(n_points) - j0)
            cells = device_empty(q, m, np.int32)
            xyz = device_empty(q, (m, 3), np.float32)
            # launch j0's jitter key: the first launch's own key, later ones shifted past it
            launch(dev, self._k("occ_points"), m,
                   (np.int32(m), np.uint32((key + j0 * 4) & 0xFFFFFFFF),
                    np.uint32((start + j0) % self.n_cells), np.uint32(self.stride),
                    np.int32(self.res), self.lo4, self.ext4, cells.data, xyz.data), ls)
            sigma = density_fn(xyz)
            launch(dev, self._k("occ_max"), m, (np.int32(m), cells.data, sigma.data,
                                                 self.ema.data), ls)
        self._threshold(threshold)
