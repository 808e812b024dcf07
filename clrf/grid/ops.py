"""Host side of cl/grid_ops.cl: TV and sparsity gradients, pruning masks, resampling."""
from __future__ import annotations

import numpy as np
import pyopencl.array as cla
from pyopencl.scan import GenericScanKernel

from .grid import SparseGrid
from ..runtime.programs import device_empty, device_zeros, int4, launch, upload
from ..runtime.scan import run_scan
from .render import render_max_weight_device

TV_EPS = 1e-9


def program(device, sh_degree: int, brick: bool = False):
    """cl/grid_ops.cl for SH degree ``sh_degree`` on ``device``; brick: the BRICK variant
    (clrf/grid/bricks.py)."""
    d = {"SH_DEGREE": sh_degree, "TV_EPS": TV_EPS}
    if brick:
        d["BRICK"] = 1
    return device.program("grid_ops.cl", d)


def _prg(grid):
    return program(grid.device, grid.sh_degree)


def tv_grad(grid, param, grad, touched, start: int, n_cells: int, scale: float,
            empty_is_zero: bool, lambda_sparsity: float = 0.0):
    """Add TV (and optional Cauchy sparsity) gradients of `param` rows over a cell window."""
    D = 1 if param.ndim == 1 else param.shape[1]
    total = int(np.prod(grid.reso))
    n_cells = int(min(n_cells, total))
    launch(grid.device, _prg(grid).kernel("tv_grad"), n_cells,
           (np.int32(n_cells), np.int32(start % total), grid.geometry_args()[0],
            grid.links.data, param.data, np.int32(D), grad.data, touched.data,
            np.float32(scale), np.int32(bool(empty_is_zero)), np.float32(lambda_sparsity)))


def max_weight(grid, origins, dirs, step, chunk=1 << 18):
    """Per-row max rendering weight over the given rays (numpy [n, 3], uploaded in chunks)."""
    q = grid.device.queue
    mw = device_zeros(q, grid.density.shape[0], np.float32)
    n = origins.shape[0]
    for s in range(0, n, chunk):
        e = min(n, s + chunk)
        render_max_weight_device(grid, upload(q, np.ascontiguousarray(origins[s:e], np.float32)),
                                 upload(q, np.ascontiguousarray(dirs[s:e], np.float32)),
                                 step, mw)
    return mw


def prune_keep(grid, maxw, weight_thresh: float, density_thresh: float = np.inf,
               dilate: bool = True):
    """uint8 [N] device mask of rows to keep: max weight >= weight_thresh or density >=
    density_thresh, then dilated by one voxel (26-neighbourhood) so surfaces keep neighbours."""
    dev = grid.device
    prg = _prg(grid)
    n = grid.density.shape[0]
    keep = device_zeros(dev.queue, n, np.uint8)
    launch(dev, prg.kernel("threshold_keep"), n,
           (np.int32(n), maxw.data, grid.density.data, np.float32(weight_thresh),
            np.float32(min(density_thresh, 3e38)), keep.data))
    if grid.n_rows < n:   # the padding row of an empty grid
        keep[grid.n_rows:] = 0
    if not dilate:
        return keep
    out = device_zeros(dev.queue, n, np.uint8)
    total = int(np.prod(grid.reso))
    launch(dev, prg.kernel("dilate_keep"), total,
           (grid.geometry_args()[0], grid.links.data, keep.data, out.data))
    return out


_scan_cache = {}


def _links_from_flags(dev, flags):
    """Exclusive prefix sum of 0/1 flags -> links (row index or -1) and the row count."""
    key = dev.context
    if key not in _scan_cache:
        _scan_cache[key] = GenericScanKernel(
            dev.context, np.int32,
            arguments="__global const int *flags, __global int *links, __global int *count, int n",
            input_expr="flags[i]", scan_expr="a+b", neutral="0",
            output_statement="links[i] = flags[i] ? prev_item : -1; "
                             "if (i == n - 1) count[0] = item;")
    links = cla.empty_like(flags)
    count = device_zeros(dev.queue, 1, np.int32)
    run_scan(dev.queue, _scan_cache[key], flags, links, count, np.int32(flags.size))
    return links, int(count.get()[0])


def resample(grid, new_reso, keep=None) -> SparseGrid:
    """A new grid over the same box at resolution new_reso from the kept rows (all if None)."""
    dev = grid.device
    q = dev.queue
    new_reso = tuple(int(r) for r in new_reso)
    if min(new_reso) < 1:
        raise ValueError(f"resample: resolution must be >= 1 per axis, got {new_reso}")
    prg = _prg(grid)
    if keep is None:
        keep = device_empty(q, grid.density.shape[0], np.uint8)
        keep.fill(1)
    total = int(np.prod(new_reso))
    nr = _reso4(new_reso)
    orr = grid.geometry_args()[0]
    flags = device_empty(q, new_reso, np.int32)
    launch(dev, prg.kernel("resample_flags"), total,
           (nr, orr, grid.links.data, keep.data, flags.data))
    links, n = _links_from_flags(dev, flags.reshape(-1))
    links = links.reshape(new_reso)
    D = grid.sh_dim
    nd = device_zeros(q, max(n, 1), np.float32)
    ns = device_zeros(q, (max(n, 1), D), np.float32)
    launch(dev, prg.kernel("resample_fill"), total,
           (nr, orr, grid.links.data, keep.data, links.data, np.int32(D), grid.density.data,
            grid.sh.data, nd.data, ns.data))
    return SparseGrid(dev, links, nd, ns, grid.bbox, grid.sh_degree, n_rows=n)


def _reso4(r):
    return int4(r[0], r[1], r[2], 0)


def prune(grid, maxw, weight_thresh, density_thresh=np.inf, dilate=True) -> SparseGrid:
    """The grid without rows whose max weight (and density) fall under the thresholds."""
    return resample(grid, grid.reso, prune_keep(grid, maxw, weight_thresh, density_thresh, dilate))
