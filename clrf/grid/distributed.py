"""Sort-last distributed Plenoxels over MPI: one brick of the grid per process.

``world()`` returns the MPI communicator when the process was started by an MPI launcher
(`mpirun -n N`, N > 1) and mpi4py is installed, else None; mpi4py is imported only then, so a
single process never pays for it. Every rank holds its brick (clrf/grid/bricks.py) on its own
OpenCL device (CLRF_DEVICE per rank) and the whole batch of rays (all ranks draw the same
batches). Per batch:

1. forward: each rank renders its partials of every ray and ``Allgather`` s them
   (PARTIAL_FLOATS = 7 floats per ray and rank); every rank composes all rays identically;
2. backward: each rank takes its own (T_b g, R_b) from the composed result (no exchange) and
   runs the BRICK backward over its own rows;
3. halo: rows in the one-voxel overlaps are held by up to 8 ranks; ``sum_halo`` exchanges the
   gradients of those rows with the neighbours holding them (Isend/Irecv) and every holder
   sums the contributions in rank order, so all replicas get bit-identical gradients and,
   after the same optimiser step, stay bit-identical. No dense gradient crosses the network:
   per step, the partials (28 bytes per ray and rank) and the overlap rows' gradients.
"""
from __future__ import annotations

import numpy as np
import pyopencl.array as cla

from ..runtime.mpi import LAUNCHER_SIZE_VARS, launched_size, world  # noqa: F401 - re-exported
from ..runtime.programs import upload

def _box_intersection(a_lo, a_hi, b_lo, b_hi):
    lo = np.maximum(a_lo, b_lo)
    hi = np.minimum(a_hi, b_hi)
    return (lo, hi) if np.all(hi > lo) else None


class Halo:
    """Which local rows this rank shares with each other rank (the overlaps of the bricks' held
    voxel boxes), in C order of the shared box; rebuilt whenever the links change."""

    def __init__(self, bricks, rank: int, links_host: np.ndarray):
        me = bricks[rank]
        my_lo, my_hi = np.array(me.lo), np.array(me.local_hi)
        self.rows = {}
        for b in bricks:
            if b.index == rank:
                continue
            box = _box_intersection(my_lo, my_hi, np.array(b.lo), np.array(b.local_hi))
            if box is None:
                continue
            lo, hi = box - my_lo
            sub = links_host[lo[0]:hi[0], lo[1]:hi[1], lo[2]:hi[2]].reshape(-1)
            self.rows[b.index] = sub[sub >= 0].astype(np.int64)
        allr = [r for r in self.rows.values()]
        self.union = np.unique(np.concatenate(allr)) if allr else np.zeros(0, np.int64)
        self.pos = {r: np.searchsorted(self.union, v) for r, v in self.rows.items()}

    def n_rows(self) -> int:
        return int(self.union.size)


class DistGrid:
    """One rank's brick of a distributed grid plus the collective operations on it."""

    def __init__(self, comm, bgrid, bricks):
        self.comm = comm
        self.rank = comm.Get_rank()
        self.size = comm.Get_size()
        if len(bricks) != self.size:
            raise ValueError(f"{len(bricks)} bricks for {self.size} ranks")
        self.bricks = bricks
        self.set_grid(bgrid)
        self.bytes_sent = 0      # counters for tools/mpi_bench.py
        self.bytes_received = 0

    def set_grid(self, bgrid):
        self.grid = bgrid
        self.halo = Halo(self.bricks, self.rank, bgrid.links.get())
        q = bgrid.device.queue
        u = self.halo.union
        self._union_d = upload(q, u.astype(np.int32)) if u.size else None
        C = bgrid.sh_dim
        self._union_sh_d = (upload(q, (u[:, None] * C + np.arange(C)).reshape(-1)
                                          .astype(np.int64)) if u.size else None)

    # ---- forward / backward -------------------------------------------------------------
    def allgather(self, local: np.ndarray) -> np.ndarray:
        """[P, ...] stack of every rank's ``local`` (same shape on every rank)."""
        local = np.ascontiguousarray(local)
        out = np.empty((self.size,) + local.shape, local.dtype)
        self.comm.Allgather(local, out)
        self.bytes_sent += local.nbytes * (self.size - 1)
        self.bytes_received += local.nbytes * (self.size - 1)
        return out

    def forward(self, origins_d, dirs_d, step, background):
        """Composed render of every ray: (comp, packed) with comp as bricks.compose (float64
        rgb, depth, acc, T_end, T_before, order) and packed the partials [P, n, 7]."""
        from . import bricks
        part = bricks.render_partial_device(self.grid, origins_d, dirs_d, step)
        packed = self.allgather(bricks.pack_partials(part))
        return bricks.compose(packed, background), packed

    def backward(self, origins_d, dirs_d, step, background, packed, comp, grad_rgb,
                 grad_density, grad_sh, touched=None, grad_T=None):
        """Add this brick's gradients of sum(grad_rgb * rgb) (+ grad_T * T_end) into its rows;
        call sum_halo afterwards to complete the overlap rows."""
        from . import bricks
        inp = bricks.backward_inputs(packed, comp, grad_rgb, background, grad_T)[self.rank]
        q = self.grid.device.queue
        bricks.render_backward_partial_device(self.grid, origins_d, dirs_d,
                                              upload(q, np.ascontiguousarray(inp)),
                                              step, grad_density, grad_sh, touched)

    # ---- halo ---------------------------------------------------------------------------
    def _exchange(self, mine):
        """Send this rank's values of the shared rows (mine [len(union), W]) to each neighbour
        holding them; returns {rank: its values of the rows shared with it}."""
        if not self.halo.pos:
            return {}
        from mpi4py import MPI
        reqs, recv = [], {}
        for r, pos in sorted(self.halo.pos.items()):
            send = np.ascontiguousarray(mine[pos])
            recv[r] = np.empty_like(send)
            reqs.append(self.comm.Irecv(recv[r], source=r, tag=7))
            reqs.append(self.comm.Isend(send, dest=r, tag=7))
            self.bytes_sent += send.nbytes
            self.bytes_received += send.nbytes
        MPI.Request.Waitall(reqs)
        return recv

    def sum_halo(self, grad_density, grad_sh, touched=None):
        """Sum the overlap rows' gradients over every rank holding them (rank order, so all
        replicas agree bit for bit) and OR their touched flags."""
        h = self.halo
        C = self.grid.sh_dim
        u = h.union
        mine = np.zeros((u.size, C + 2), np.float32)
        if u.size:
            mine[:, 0] = cla.take(grad_density, self._union_d).get()
            mine[:, 1:C + 1] = cla.take(grad_sh.reshape(-1), self._union_sh_d).get().reshape(-1, C)
            if touched is not None:
                mine[:, C + 1] = cla.take(touched, self._union_d).get()
        recv = self._exchange(mine)
        if not u.size:
            return
        total = np.zeros_like(mine)
        for r in sorted(list(h.pos) + [self.rank]):
            if r == self.rank:
                total += mine
            else:
                total[h.pos[r]] += recv[r]
        q = self.grid.device.queue
        grad_density.setitem(self._union_d, upload(q, np.ascontiguousarray(total[:, 0])))
        grad_sh.reshape(-1).setitem(self._union_sh_d, upload(
            q, np.ascontiguousarray(total[:, 1:C + 1]).reshape(-1)))
        if touched is not None:
            touched.setitem(self._union_d, upload(
                q, (total[:, C + 1] > 0).astype(np.uint8)))

    def max_halo(self, values):
        """values[k] = max over the holders of row k, for the overlap rows (pruning weights)."""
        u = self.halo.union
        mine = np.zeros((u.size, 1), np.float32)
        if u.size:
            mine[:, 0] = cla.take(values, self._union_d).get()
        recv = self._exchange(mine)
        if not u.size:
            return
        m = mine.copy()
        for r, pos in self.halo.pos.items():
            m[pos] = np.maximum(m[pos], recv[r])
        values.setitem(self._union_d, upload(self.grid.device.queue,
                                                    np.ascontiguousarray(m[:, 0])))
