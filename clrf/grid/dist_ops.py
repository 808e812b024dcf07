"""Structure changes of a distributed grid (clrf/grid/dist_model.py): pruning and coarse-to-fine
resampling across bricks, with the single grid's rules (clrf/grid/ops.py, cl/grid_ops.cl).

1. Pruning weights: every rank renders the pruning rays' partials, composes them, and marches
   its brick again with T_b in front (render_max_weight, BRICK): the single grid's max weight
   of each row from its own samples; the overlap replicas take the max over their holders.
2. keep = allocated and (max weight >= threshold), dilated by one voxel (26-neighbourhood): each
   rank dilates its own voxels with its neighbours' flags one voxel around its box
   (``gather_box``).
3. The new grid is split again (bricks.split at the new resolution, weighted by the rows each
   block of cells is expected to hold: the kept old voxels, each worth (new / old)^3 new ones,
   summed over the ranks; so pruning does not leave some ranks with most of the rows and
   others idle); each rank evaluates its new
   voxels (own and halo) by trilinear interpolation of the kept old rows at their centres, in
   float32 with the operation order of resample_corners / resample_fill, from the old voxels
   around them (``gather_box`` from their owners). A new voxel is allocated iff a kept old row
   has weight > 0 there. Optimiser state starts at zero, as for the single grid.

Only the voxels on the faces of the old bricks cross the network; each rank holds dense host
copies of its own old box during the change (density, SH, flags).
"""
from __future__ import annotations

import numpy as np

from . import bricks as B
from .ops import prune_keep
from .grid import SparseGrid
from ..runtime.programs import device_zeros, upload


def _inter(alo, ahi, blo, bhi):
    lo = np.maximum(alo, blo)
    hi = np.minimum(ahi, bhi)
    return (lo, hi) if np.all(hi > lo) else None


def gather_box(comm, bricks, own, lo, hi):
    """Dense values of the voxels [lo, hi) (global indices, clamped to the grid) assembled from
    every rank's ``own`` array (the values of its own voxels [b.lo, b.hi), trailing dimensions
    allowed). Collective: every rank calls it with its own box."""
    from mpi4py import MPI
    me = comm.Get_rank()
    reso = np.array(bricks[0].reso)
    lo = np.clip(np.asarray(lo), 0, reso)
    hi = np.clip(np.asarray(hi), 0, reso)
    boxes = comm.allgather((lo.tolist(), hi.tolist()))
    mb = bricks[me]
    mlo, mhi = np.array(mb.lo), np.array(mb.hi)
    out = np.zeros(tuple(np.maximum(hi - lo, 0)) + own.shape[3:], own.dtype)
    reqs, recv = [], []
    for r, (rlo, rhi) in enumerate(boxes):
        x = _inter(mlo, mhi, np.array(rlo), np.array(rhi))
        if x is None:
            continue
        src = own[tuple(slice(a, b) for a, b in zip(x[0] - mlo, x[1] - mlo))]
        if r == me:
            out[tuple(slice(a, b) for a, b in zip(x[0] - lo, x[1] - lo))] = src
        else:
            reqs.append(comm.Isend(np.ascontiguousarray(src), dest=r, tag=23))
    for b in bricks:
        if b.index == me:
            continue
        x = _inter(np.array(b.lo), np.array(b.hi), lo, hi)
        if x is None:
            continue
        buf = np.empty(tuple(x[1] - x[0]) + own.shape[3:], own.dtype)
        recv.append((x, buf))
        reqs.append(comm.Irecv(buf, source=b.index, tag=23))
    MPI.Request.Waitall(reqs)
    for x, buf in recv:
        out[tuple(slice(a, b) for a, b in zip(x[0] - lo, x[1] - lo))] = buf
    return out


def max_weight(model, origins, dirs, chunk=1 << 16):
    """Per-row max rendering weight of this rank's rows over the rays (numpy [n, 3]; the same
    on every rank), the overlap rows' replicas maxed over their holders."""
    g = model.grid
    q = model.device.queue
    dist = model.dist
    maxw = device_zeros(q, g.density.shape[0], np.float32)
    for s in range(0, origins.shape[0], chunk):
        e = min(origins.shape[0], s + chunk)
        od = upload(q, np.ascontiguousarray(origins[s:e], np.float32))
        dd = upload(q, np.ascontiguousarray(dirs[s:e], np.float32))
        comp, _ = dist.forward(od, dd, model.cfg.step, model.background)
        tb = upload(q, comp["T_before"][dist.rank].astype(np.float32))
        B.max_weight_partial_device(g, od, dd, tb, model.cfg.step, maxw)
    dist.max_halo(maxw)
    return maxw


def _own_dense(bgrid, rows):
    """Dense values of a per-row array over the brick's own voxels (zeros where empty)."""
    links = bgrid.links.get()[bgrid.brick.own_slices]
    out = np.zeros(links.shape + rows.shape[1:], rows.dtype)
    m = links >= 0
    out[m] = rows[links[m]]
    return out


def _lerp_axis(p, r):
    """lerp_axis of cl/march.h in float32: lower index, upper index, fraction."""
    u = np.clip(p - np.float32(0.5), np.float32(0), np.float32(r - 1)).astype(np.float32)
    i = np.minimum(u.astype(np.int64), max(r - 2, 0))
    return i, np.minimum(i + 1, r - 1), (u - i.astype(np.float32)).astype(np.float32)


def upsample(model, origins, dirs, new_reso):
    """Prune (weight_thresh / new z-resolution, dilated when prune_dilate) and resample to
    new_reso; returns (new bricks, new BrickGrid of this rank, rows before, rows kept)."""
    c = model.cfg
    comm = model.comm
    g = model.grid
    br = g.brick
    old = np.array(br.reso)
    new = np.array(new_reso)
    maxw = max_weight(model, origins, dirs)
    # keep flags of the own voxels (threshold, then dilation with the neighbours' flags)
    keep0 = prune_keep(g, maxw, c.weight_thresh / new_reso[2], dilate=False).get()
    links = g.links.get()
    own_links = links[br.own_slices]
    alloc_own = own_links >= 0
    keep0_own = _own_dense(g, keep0.astype(np.uint8)).astype(bool) & alloc_own
    if c.prune_dilate:
        lo, hi = np.array(br.lo) - 1, np.array(br.hi) + 1
        ext = gather_box(comm, model.bricks, keep0_own.astype(np.uint8), lo, hi).astype(bool)
        elo = np.clip(lo, 0, old)
        pad = np.pad(ext, [(int(a - b), 0) for a, b in zip(elo, lo)])   # index 0 = br.lo - 1
        pad = np.pad(pad, [(0, int(s + 2 - p)) for s, p in zip(alloc_own.shape, pad.shape)])
        X, Y, Z = alloc_own.shape
        dil = np.zeros_like(alloc_own)
        for dx in (0, 1, 2):
            for dy in (0, 1, 2):
                for dz in (0, 1, 2):
                    dil |= pad[dx:dx + X, dy:dy + Y, dz:dz + Z]
        keep_own = dil & alloc_own
    else:
        keep_own = keep0_own
    before = comm.allreduce(int(alloc_own.sum()))
    kept = comm.allreduce(int(keep_own.sum()))
    # the new bricks, balanced by expected rows, and the old voxels their centres interpolate
    nb = B.split(new_reso, comm.Get_size(), *expected_rows(comm, br, keep_own, new))
    me = nb[comm.Get_rank()]
    ax = []
    for a in range(3):
        i = np.arange(me.lo[a], me.local_hi[a])
        p = ((i.astype(np.float32) + np.float32(0.5)) * np.float32(old[a])
             / np.float32(new[a])).astype(np.float32)
        ax.append(_lerp_axis(p, int(old[a])))
    blo = np.array([a[0].min() for a in ax])
    bhi = np.array([a[1].max() for a in ax]) + 1
    dens = gather_box(comm, model.bricks, _own_dense(g, g.density.get()) * keep_own, blo, bhi)
    sh = gather_box(comm, model.bricks, _own_dense(g, g.sh.get()) * keep_own[..., None], blo, bhi)
    kp = gather_box(comm, model.bricks, keep_own.astype(np.uint8), blo, bhi).astype(bool)
    # trilinear interpolation, float32, corners c = (cx << 2) | (cy << 1) | cz in order
    (x0, x1, fx), (y0, y1, fy), (z0, z1, fz) = ax
    one = np.float32(1)
    wx = (one - fx, fx)
    wy = (one - fy, fy)
    wz = (one - fz, fz)
    xs, ys, zs = (x0 - blo[0], x1 - blo[0]), (y0 - blo[1], y1 - blo[1]), (z0 - blo[2], z1 - blo[2])
    shape = me.local_reso
    nd = np.zeros(shape, np.float32)
    ns = np.zeros(shape + (g.sh_dim,), np.float32)
    alloc = np.zeros(shape, bool)
    for cidx in range(8):
        cx, cy, cz = cidx >> 2, (cidx >> 1) & 1, cidx & 1
        w = (wx[cx][:, None, None] * wy[cy][None, :, None]).astype(np.float32)
        w = (w * wz[cz][None, None, :]).astype(np.float32)
        sel = np.ix_(xs[cx], ys[cy], zs[cz])
        k = kp[sel]
        use = k & (w != 0)
        alloc |= k & (w > 0)
        wk = np.where(use, w, np.float32(0))
        nd += wk * dens[sel]
        ns += wk[..., None] * sh[sel]
    sg = SparseGrid.from_dense(model.device, nd, ns, g.bbox, mask=alloc)
    return nb, B.BrickGrid.from_grid(sg, me), before, kept


# Blocks per axis of the weights the new split balances (bricks.split ``weight``): fine enough to
# place cuts within 1/64 of an axis, small enough to allreduce (64^3 float64 = 2 MB).
BALANCE_BLOCKS = 64


def expected_rows(comm, brick, keep_own, new):
    """(weight, block) for bricks.split at resolution ``new``: per block of new cells, the
    number of new voxels the kept old voxels (``keep_own``, this rank's own) will give, summed
    over the ranks (Allreduce)."""
    from mpi4py import MPI
    old = np.array(brick.reso)
    ncell = np.maximum(new - 1, 1)
    block = max(1, int(-(-ncell.max() // BALANCE_BLOCKS)))
    shape = tuple(int(-(-c // block)) for c in ncell)
    w = np.zeros(shape, np.float64)
    pos = np.argwhere(keep_own) + np.array(brick.lo)           # kept old voxels, global
    if pos.size:
        cell = np.minimum(((pos + 0.5) * new / old).astype(np.int64), ncell - 1)
        np.add.at(w, tuple((cell // block).T), float(np.prod(new / old)))
    comm.Allreduce(MPI.IN_PLACE, w, op=MPI.SUM)
    return w, block
