"""SparseGrid: a voxel grid of density and SH coefficients stored as int32 links into compact rows.

Layout (device buffers, pyopencl arrays):

- ``links``   int32 ``[X, Y, Z]``: row index k >= 0 of an allocated voxel, or -1 if empty;
- ``density`` float32 ``[N]``: raw density per row (ReLU is applied after interpolation);
- ``sh``      float32 ``[N, 3*(d+1)^2]``: SH coefficients, channel-major (R block, G, B).

The grid fills the world box ``bbox = [[x0, y0, z0], [x1, y1, z1]]``; voxel (i, j, k) has its
value at its centre. Rows are in C order of the voxels they belong to (the order that keeps
neighbouring voxels of a ray near each other in memory along z).
"""
from __future__ import annotations

import numpy as np

from ..runtime.validate import as_bbox, check_array
from ..runtime.programs import float4, int4, upload

SH_DIMS = {3 * (d + 1) ** 2: d for d in range(4)}


def sh_dim(degree: int) -> int:
    return 3 * (degree + 1) ** 2


class SparseGrid:
    """Sparse SH voxel grid on a device. Build with ``from_dense`` or ``from_arrays``."""

    def __init__(self, device, links, density, sh, bbox, sh_degree: int,
                 n_rows: int | None = None):
        self.device = device
        self.links = links
        self.density = density
        self.sh = sh
        self.bbox = as_bbox(bbox)
        self.sh_degree = int(sh_degree)
        self.reso = tuple(int(r) for r in links.shape)
        # allocated rows (the buffers keep >= 1 row, so a fully pruned grid has n_rows 0)
        self._n_rows = int(density.shape[0]) if n_rows is None else int(n_rows)
        # device buffers the render wrappers (render.py) keep between calls: block occupancy,
        # gradient slots, sample records; keyed so a changed links buffer or size rebuilds them
        self.scratch = {}

    # ---- construction -------------------------------------------------------------------
    @classmethod
    def from_dense(cls, device, density, sh, bbox, mask=None):
        """Grid from dense arrays: density ``[X,Y,Z]``, sh ``[X,Y,Z,3*(d+1)^2]``.

        Voxels are allocated where ``mask`` is true; by default where any value is non-zero,
        which renders exactly like the dense grid (empty voxels count as zeros).

        >>> g = SparseGrid.from_dense(dev, np.ones((2,2,2)), np.zeros((2,2,2,3)), [[0,0,0],[1,1,1]])
        >>> g.n_rows, g.sh_degree
        (8, 0)
        """
        density = check_array("density", density, ndim=3)
        X, Y, Z = density.shape
        sh = check_array("sh", sh, ndim=4)
        if sh.shape[:3] != density.shape:
            raise ValueError(f"sh has shape {sh.shape}, expected {density.shape + (sh.shape[-1],)} "
                             f"to match density {density.shape}")
        if sh.shape[3] not in SH_DIMS:
            raise ValueError(f"sh has {sh.shape[3]} coefficients per voxel; expected 3*(d+1)^2 "
                             f"for SH degree d in 0..3, i.e. one of {sorted(SH_DIMS)}")
        if mask is None:
            mask = (density != 0) | np.any(sh != 0, axis=-1)
        else:
            mask = np.asarray(mask, bool)
            if mask.shape != density.shape:
                raise ValueError(f"mask has shape {mask.shape}, expected {density.shape}")
        links = np.full(density.shape, -1, np.int32)
        n = int(mask.sum())
        links[mask] = np.arange(n, dtype=np.int32)
        return cls.from_arrays(device, links, density[mask], sh[mask], bbox)

    @classmethod
    def from_arrays(cls, device, links, density_rows, sh_rows, bbox):
        """Grid from host arrays in the compact layout (links, density [N], sh [N, C])."""
        links = np.ascontiguousarray(links, np.int32)
        if links.ndim != 3 or min(links.shape) < 1:
            raise ValueError(f"links must be a non-empty [X,Y,Z] array, got shape {links.shape}")
        density_rows = np.ascontiguousarray(density_rows, np.float32).reshape(-1)
        sh_rows = np.ascontiguousarray(sh_rows, np.float32)
        n = density_rows.shape[0]
        if sh_rows.ndim != 2 or sh_rows.shape[0] != n:
            raise ValueError(f"sh rows must be [N, C] with N = {n} density rows, got {sh_rows.shape}")
        if sh_rows.shape[1] not in SH_DIMS:
            raise ValueError(f"sh rows have {sh_rows.shape[1]} coefficients; expected one of "
                             f"{sorted(SH_DIMS)}")
        if links.max(initial=-1) >= n:
            raise ValueError(f"links point at row {links.max()} but only {n} rows were given")
        q = device.queue
        # Keep at least one row so buffers are never zero-sized (a fully pruned grid is legal).
        pad = 1 if n == 0 else 0
        dens = np.concatenate([density_rows, np.zeros(pad, np.float32)])
        shr = np.concatenate([sh_rows, np.zeros((pad, sh_rows.shape[1]), np.float32)])
        return cls(device, upload(q, links), upload(q, dens), upload(q, shr),
                   bbox, SH_DIMS[sh_rows.shape[1]], n_rows=n)

    # ---- properties ---------------------------------------------------------------------
    @property
    def n_rows(self) -> int:
        return self._n_rows

    @property
    def sh_dim(self) -> int:
        return sh_dim(self.sh_degree)

    @property
    def voxel_size(self) -> np.ndarray:
        return (self.bbox[1] - self.bbox[0]) / np.array(self.reso, np.float64)

    def geometry_args(self):
        """(reso int4, bmin float4, scale float4) kernel arguments."""
        r = self.reso
        b0 = self.bbox[0]
        sc = np.array(r, np.float64) / (self.bbox[1] - self.bbox[0])
        return (int4(r[0], r[1], r[2], 0),
                float4(b0[0], b0[1], b0[2], 0.0),
                float4(sc[0], sc[1], sc[2], 0.0))

    # ---- host views ---------------------------------------------------------------------
    def to_dense(self):
        """(density [X,Y,Z], sh [X,Y,Z,C]) as numpy, zeros where no voxel is allocated."""
        links = self.links.get()
        rows_d = self.density.get()
        rows_s = self.sh.get()
        return scatter_dense(links, rows_d, rows_s)

    def rows_to_dense(self, rows_density, rows_sh):
        """Dense views of per-row arrays (e.g. gradients) using this grid's links."""
        return scatter_dense(self.links.get(), rows_density, rows_sh)

    def __repr__(self):
        return (f"SparseGrid(reso={self.reso}, rows={self.n_rows}, sh_degree={self.sh_degree}, "
                f"bbox={self.bbox.tolist()})")


def scatter_dense(links, rows_density, rows_sh):
    mask = links >= 0
    dens = np.zeros(links.shape, np.float32)
    sh = np.zeros(links.shape + (rows_sh.shape[-1],), np.float32)
    dens[mask] = rows_density[links[mask]]
    sh[mask] = rows_sh[links[mask]]
    return dens, sh
