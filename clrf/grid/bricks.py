"""Bricks of a sparse grid for sort-last distributed rendering (no MPI here: clrf/grid/distributed.py
moves the partials between processes).

The grid's cells are split into boxes, one per process, by recursive bisection along the
longest axis (``split``). Brick b owns the voxels ``[lo, hi)`` per axis (``hi`` = reso on the
high faces of the grid) and the cells whose lower corner lies there, i.e. every sample whose
trilinear cell starts in the brick (cl/march.h, BRICK). It holds the voxels
``[lo, min(hi + 1, reso))``: its own plus a one-voxel halo on its high sides, every corner its
cells touch. Halo rows are replicas of the neighbour's rows; distributed.py keeps them equal
(their gradients are summed over every holder before the optimiser step).

Each brick renders every ray over its own samples only (``render_partial_device``), giving a
partial per ray: premultiplied colour, log transmittance, opacity and depth moment, and the
first segment it evaluated (its order along the ray). ``compose`` combines the partials front
to back with the over operator into the single-grid render; ``backward_inputs`` gives each
brick what its remaining-radiance backward needs: T_b g and the radiance behind it. With early
termination off (T_STOP 0, the bricks cannot know T in front of them), the composed render and
gradients equal the single-grid ones up to float32 rounding (tests/test_bricks.py,
tests/test_mpi.py). Float64 twin: clrf/references/reference_bricks.py.

>>> bricks = split((64, 64, 32), 2)
>>> [(b.lo, b.hi) for b in bricks]
[((0, 0, 0), (32, 64, 32)), ((32, 0, 0), (64, 64, 32))]
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..runtime.programs import device_empty, float4, int4, launch
from .grid import SparseGrid
from .ops import program as ops_program
from .render import block_occupancy, grad_slots, grid_program, launch_backward

# Per-ray floats a brick contributes to the exchange: rgb (3), logT, depth, acc, key.
PARTIAL_FLOATS = 7


@dataclass(frozen=True)
class Brick:
    """Brick ``index`` of a grid of resolution ``reso``: owns voxels [lo, hi) per axis."""
    index: int
    lo: tuple
    hi: tuple
    reso: tuple

    @property
    def local_hi(self) -> tuple:
        """End (exclusive) of the voxels the brick holds: hi plus the one-voxel halo."""
        return tuple(min(h + 1, r) for h, r in zip(self.hi, self.reso))

    @property
    def local_reso(self) -> tuple:
        return tuple(h - l for l, h in zip(self.lo, self.local_hi))

    @property
    def local_slices(self) -> tuple:
        return tuple(slice(l, h) for l, h in zip(self.lo, self.local_hi))

    @property
    def own_slices(self) -> tuple:
        """The owned voxels within the local array."""
        return tuple(slice(0, h - l) for l, h in zip(self.lo, self.hi))

    def kernel_args(self):
        """(blo, bhi, lreso) int4 kernel arguments (BRICK_ARGS of cl/grid_render.cl)."""
        return (int4(*self.lo, 0), int4(*self.hi, 0), int4(*self.local_reso, 0))


def split(reso, n: int, weight=None, block: int = 1) -> list:
    """``n`` bricks covering a grid of resolution ``reso``: recursive bisection of the cells
    (lower corners 0 .. reso - 2) along the longest axis. Without ``weight`` each side gets
    cells in proportion to its ranks; with ``weight`` (per block of ``block``^3 cells, shape
    ceil(cells / block) per axis, e.g. expected rows) the cut, at a block boundary, splits the
    weight in that proportion instead (rebalancing after pruning), keeping at least one cell
    per rank on each side. Raises ValueError when an axis has too few cells for its share."""
    reso = tuple(int(r) for r in reso)
    n = int(n)
    if n < 1:
        raise ValueError(f"bricks: need at least one, got {n}")
    ncell = [max(r - 1, 1) for r in reso]
    W = None if weight is None else np.asarray(weight, np.float64)
    out = []

    def weighted_cut(lo, hi, a, k1, k):
        """Block-aligned cut along axis a splitting the box's weight k1 : k - k1, or None."""
        if W is None:
            return None
        blo = [l // block for l in lo]
        bhi = [-(-min(h, c) // block) for h, c in zip(hi, ncell)]
        sub = W[blo[0]:bhi[0], blo[1]:bhi[1], blo[2]:bhi[2]]
        marg = sub.sum(axis=tuple(i for i in range(3) if i != a))
        total = marg.sum()
        if not total > 0:
            return None
        cum = np.cumsum(marg)[:-1]                  # weight below each inner block boundary
        cuts = (np.arange(blo[a] + 1, bhi[a]) * block)
        end = min(hi[a], ncell[a])
        ok = (cuts - lo[a] >= k1) & (end - cuts >= k - k1)
        if not ok.any():
            return None
        j = np.argmin(np.where(ok, np.abs(cum - total * k1 / k), np.inf))
        return int(cuts[j])

    def rec(lo, hi, k):
        if k == 1:
            out.append((tuple(lo), tuple(hi)))
            return
        # cells along each axis in [lo, hi): lower corners up to reso - 2
        cells = [min(h, c) - l for l, h, c in zip(lo, hi, ncell)]
        a = int(np.argmax(cells))
        if cells[a] < k:
            raise ValueError(f"bricks: a {reso} grid cannot be split into {n} bricks (a brick "
                             f"of {cells[a]} cells along its longest axis for {k} ranks); "
                             f"use fewer ranks or a finer grid")
        k1 = k // 2
        cut = weighted_cut(lo, hi, a, k1, k)
        if cut is None:
            cut = lo[a] + int(round(cells[a] * k1 / k))
        hi1, lo2 = list(hi), list(lo)
        hi1[a] = cut
        lo2[a] = cut
        rec(lo, hi1, k1)
        rec(lo2, hi, k - k1)

    rec([0, 0, 0], list(reso), n)
    return [Brick(i, lo, hi, reso) for i, (lo, hi) in enumerate(out)]


def from_boxes(boxes, reso) -> list:
    """Bricks from saved [[lo, hi], ...] (a distributed checkpoint's manifest)."""
    return [Brick(i, tuple(int(v) for v in lo), tuple(int(v) for v in hi),
                  tuple(int(r) for r in reso)) for i, (lo, hi) in enumerate(boxes)]


def owner_of(bricks, voxels) -> np.ndarray:
    """Index of the brick that owns each voxel (int [n, 3] global indices)."""
    v = np.asarray(voxels).reshape(-1, 3)
    own = np.full(v.shape[0], -1, np.int64)
    for b in bricks:
        inside = np.all((v >= np.array(b.lo)) & (v < np.array(b.hi)), axis=1)
        own[inside] = b.index
    return own


class BrickGrid(SparseGrid):
    """The SparseGrid of one brick: ``links`` over the brick's local voxels (``reso`` is that
    shape), rendered with the whole grid's geometry (``march_reso``, ``bbox``)."""

    def __init__(self, device, links, density, sh, bbox, sh_degree, brick: Brick, n_rows=None):
        super().__init__(device, links, density, sh, bbox, sh_degree, n_rows)
        if tuple(self.reso) != brick.local_reso:
            raise ValueError(f"brick links have shape {self.reso}, expected {brick.local_reso}")
        self.brick = brick
        self.march_reso = brick.reso

    @classmethod
    def from_grid(cls, grid: SparseGrid, brick: Brick):
        """Wrap a SparseGrid holding the brick's local voxels (same buffers)."""
        return cls(grid.device, grid.links, grid.density, grid.sh, grid.bbox, grid.sh_degree,
                   brick, grid.n_rows)

    @classmethod
    def from_dense(cls, device, density, sh, bbox, brick: Brick, mask=None):
        """The brick of dense whole-grid arrays (allocation as SparseGrid.from_dense)."""
        density = np.asarray(density)
        sh = np.asarray(sh)
        if mask is None:
            mask = (density != 0) | np.any(sh != 0, axis=-1)
        s = brick.local_slices
        g = SparseGrid.from_dense(device, density[s], sh[s], bbox, mask=np.asarray(mask)[s])
        return cls.from_grid(g, brick)

    @property
    def voxel_size(self) -> np.ndarray:
        return (self.bbox[1] - self.bbox[0]) / np.array(self.march_reso, np.float64)

    def geometry_args(self):
        """(reso int4, bmin float4, scale float4) of the whole grid: the march's geometry."""
        r = self.march_reso
        b0 = self.bbox[0]
        sc = np.array(r, np.float64) / (self.bbox[1] - self.bbox[0])
        return (int4(r[0], r[1], r[2], 0),
                float4(b0[0], b0[1], b0[2], 0.0),
                float4(sc[0], sc[1], sc[2], 0.0))

    def __repr__(self):
        return (f"BrickGrid(brick={self.brick.index}, lo={self.brick.lo}, hi={self.brick.hi}, "
                f"local reso={self.reso}, rows={self.n_rows})")


def _program(bgrid, step, **kw):
    return grid_program(bgrid, t_stop=0.0, step=step, brick=True, **kw)


def render_partial_device(bgrid: BrickGrid, origins_d, dirs_d, step):
    """The brick's partial of every ray (device arrays): rgb [n,3] (premultiplied, no
    background), logT [n], depth [n] (sum of w' t), acc [n], key [n] int32 (first segment
    evaluated; -1: the partial is the identity)."""
    dev = bgrid.device
    q = dev.queue
    n = origins_d.shape[0]
    m = max(n, 1)
    out = {"rgb": device_empty(q, (m, 3)), "logT": device_empty(q, m),
           "depth": device_empty(q, m), "acc": device_empty(q, m),
           "key": device_empty(q, m, np.int32)}
    if n:
        occ, oreso = block_occupancy(bgrid)
        bg = float4(0, 0, 0, 0)   # unused: a partial has no background
        launch(dev, _program(bgrid, step).kernel("render_forward"), n,
               (np.int32(n), origins_d.data, dirs_d.data, bgrid.links.data,
                bgrid.density.data, bgrid.sh.data, *bgrid.geometry_args(), np.float32(step),
                bg, out["rgb"].data, out["depth"].data, out["acc"].data, out["logT"].data,
                out["key"].data, occ.data, oreso, *bgrid.brick.kernel_args()),
               dev.tuning.grid_local_size)
    return {k: v[:n] for k, v in out.items()}


def pack_partials(part) -> np.ndarray:
    """float32 [n, PARTIAL_FLOATS] host array of a partial (the key as a float: exact below
    2^24 segments per ray, far above MAX_SAMPLES_PER_RAY's practical range)."""
    n = part["logT"].shape[0]
    out = np.empty((n, PARTIAL_FLOATS), np.float32)
    out[:, 0:3] = part["rgb"].get()
    out[:, 3] = part["logT"].get()
    out[:, 4] = part["depth"].get()
    out[:, 5] = part["acc"].get()
    out[:, 6] = part["key"].get()
    return out


def compose(packed, background):
    """Compose the partials of every brick, float [P, n, PARTIAL_FLOATS], front to back.

    Returns float64 ``rgb`` [n,3], ``depth``, ``acc``, ``T_end`` [n], ``T_before`` [P, n]
    (transmittance in front of each brick), ``order`` [P, n] (bricks sorted along each ray).
    Over operator: rgb = sum_b T_b rgb_b + T_end bg with T_b = exp(sum_{b' before b} logT_b').
    """
    p = np.asarray(packed, np.float64)
    P, n = p.shape[:2]
    key = np.where(p[:, :, 6] < 0, np.inf, p[:, :, 6])
    order = np.argsort(key, axis=0, kind="stable")          # [P, n]: sorted position -> brick
    logT = np.take_along_axis(p[:, :, 3], order, axis=0)
    before_sorted = np.cumsum(logT, axis=0) - logT            # exclusive prefix
    T_before = np.empty((P, n))
    np.put_along_axis(T_before, order, np.exp(before_sorted), axis=0)
    T_end = np.exp(np.sum(p[:, :, 3], axis=0))
    bg = np.broadcast_to(np.asarray(background, np.float64), (3,))
    rgb = np.einsum("pn,pnc->nc", T_before, p[:, :, 0:3]) + T_end[:, None] * bg
    depth = np.einsum("pn,pn->n", T_before, p[:, :, 4])
    acc = np.einsum("pn,pn->n", T_before, p[:, :, 5])
    return {"rgb": rgb, "depth": depth, "acc": acc, "T_end": T_end, "T_before": T_before,
            "order": order}


def backward_inputs(packed, comp, grad_rgb, background, grad_T=None, dtype=np.float32):
    """[P, n, 4] (float32 for the kernel; float64 for the reference): per brick and ray
    (T_b g, R_b), R_b = g.(everything behind brick b, background included) + T_end dL/dT_end,
    the ray_in of the BRICK backward."""
    p = np.asarray(packed, np.float64)
    g = np.asarray(grad_rgb, np.float64)
    bg = np.broadcast_to(np.asarray(background, np.float64), (3,))
    Tb = comp["T_before"]
    contrib = Tb * np.einsum("nc,pnc->pn", g, p[:, :, 0:3])           # T_b g.rgb_b
    order = comp["order"]
    c_sorted = np.take_along_axis(contrib, order, axis=0)
    behind_sorted = np.cumsum(c_sorted[::-1], axis=0)[::-1] - c_sorted  # sum over later bricks
    behind = np.empty_like(contrib)
    np.put_along_axis(behind, order, behind_sorted, axis=0)
    tail = comp["T_end"] * (g @ bg + (0.0 if grad_T is None else np.asarray(grad_T, np.float64)))
    out = np.empty(contrib.shape + (4,), dtype)
    out[..., 0:3] = Tb[..., None] * g[None]
    out[..., 3] = behind + tail[None]
    return out


def render_backward_partial_device(bgrid: BrickGrid, origins_d, dirs_d, ray_in4_d, step,
                                   grad_density, grad_sh, touched=None):
    """Add the brick's gradients for one batch into grad_density [N] / grad_sh [N, C]; ray_in4_d
    float32 [n, 4] from ``backward_inputs`` (this brick's slice)."""
    dev = bgrid.device
    n = origins_d.shape[0]
    if n == 0:
        return
    slots = grad_slots(bgrid)
    record = slots > 0 and dev.tuning.sample_record
    prg = _program(bgrid, step, track_touched=touched is not None, slots=slots, record=record)
    bg = float4(0, 0, 0, 0)   # unused: R_b carries the background
    args = [np.int32(n), origins_d.data, dirs_d.data, bgrid.links.data, bgrid.density.data,
            bgrid.sh.data, *bgrid.geometry_args(), np.float32(step), bg, ray_in4_d.data,
            grad_density.data, grad_sh.data]
    launch_backward(bgrid, prg, n, args, grad_density, grad_sh, touched, slots, record,
                    bgrid.march_reso, step, bgrid.brick.kernel_args())


def max_weight_partial_device(bgrid: BrickGrid, origins_d, dirs_d, ray_T_d, step, maxw):
    """maxw[k] = max(maxw[k], T_b w' w_corner) over the brick's samples (pruning weights equal
    to the single grid's, T_b from ``compose``)."""
    dev = bgrid.device
    n = origins_d.shape[0]
    if n == 0:
        return
    occ, oreso = block_occupancy(bgrid)
    launch(dev, _program(bgrid, step).kernel("render_max_weight"), n,
           (np.int32(n), origins_d.data, dirs_d.data, bgrid.links.data, bgrid.density.data,
            *bgrid.geometry_args(), np.float32(step), maxw.data, occ.data, oreso,
            ray_T_d.data, *bgrid.brick.kernel_args()),
           dev.tuning.grid_local_size)


def tv_grad_brick(bgrid: BrickGrid, param, grad, touched, start: int, n_cells: int, scale: float,
                  empty_is_zero: bool, lambda_sparsity: float = 0.0):
    """ops.tv_grad for one brick: the same window of the whole grid's cells (start, n_cells in
    its C order), over the brick's own voxels (cl/grid_ops.cl, BRICK)."""
    dev = bgrid.device
    D = 1 if param.ndim == 1 else param.shape[1]
    b = bgrid.brick
    total = int(np.prod(b.reso))
    n_cells = int(min(n_cells, total))
    own = tuple(h - l for l, h in zip(b.lo, b.hi))
    prg = ops_program(dev, bgrid.sh_degree, brick=True)
    r = bgrid.reso
    launch(dev, prg.kernel("tv_grad"), int(np.prod(own)),
           (np.int32(n_cells), np.int32(start % total), int4(r[0], r[1], r[2], 0),
            bgrid.links.data, param.data, np.int32(D), grad.data, touched.data,
            np.float32(scale), np.int32(bool(empty_is_zero)), np.float32(lambda_sparsity),
            int4(*b.reso, 0), int4(*b.lo, 0), int4(*own, 0)))
