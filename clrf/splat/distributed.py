"""Gaussian splats over MPI ranks: the Gaussians split into shards, one per rank, and a batch of
views, one per rank, each rendered whole by the rank that owns it (Grendel's design).

Shards: rank r holds rows [r n / P, (r + 1) n / P) of the parameter table at the start (the
same first Gaussians on every rank, each keeps its rows), their Adam moments and the density
strategy's statistics; density control edits each shard alone, under the cap split over the
ranks. A step trains P views, view k owned by rank k:

1. forward: every rank projects its shard into every camera of the batch (splat_project), keeps
   the splats each camera sees (radius > 0) and sends camera k's records to rank k (one
   ``Alltoallv``; RECORD floats a splat: xy, conic, radius, depth, colour, opacity, the tile
   rectangle). The owner lays the records it receives in rank order, which is the order of
   the Gaussians in the whole table, so binning (a stable sort by tile and depth) gives each
   tile the same list, in the same order, as one process rendering every Gaussian: the image
   is the one-process image;
2. the owner takes the loss and its gradient on the image and runs the raster backward over
   those records: dL/d(xy, conic, opacity, colour) of each record, which goes back to the rank
   that sent it (a second ``Alltoallv``, GRAD floats a splat, 2 more with absgrad);
3. each rank scatters the gradients into its shard's rows, runs the projection backward for
   each camera, adds the density statistics of each view, and takes one Adam step of its rows
   on the mean of the batch's gradients. With batches of P views the learning rates are
   sqrt(P) times the one-view rates (Grendel's scaling; ``lr_scale``).

Renders outside training (evaluations, clrf view) are collective: every rank sends every
rank the records it sees (``Allgatherv``) and composites the whole image. Checkpoints are one
file per rank (its shard) and a manifest written last (clrf/outputs/checkpoint.py); one
process loads the shards joined in rank order, another rank count re-splits them.

>>> proj, sources = gather_records(dp, rast, params, cams)   # proj: this rank's camera's
>>> g_rows = scatter_grads(dp, g2d, sources, shard_sizes)    # each camera's, this shard's rows
"""
from __future__ import annotations

import numpy as np

from .raster import Projected
from ..runtime.dataparallel import shard_bounds
from ..runtime.programs import download, launch, upload
from .config import SplatConfig
from .model import FILTER3D_EVERY, SplatModel, camera_of
from .params import NAMES, moment_keys
from .strategies import RenderInfo, strategy_class

# the columns of a projected record: xy 2, conic 3, radius, depth, colour 3, opacity, rect 4
# (int32 bits in float32 columns)
RECORD = 15
COLUMNS = (("xy", 2), ("conic", 3), ("radius", 1), ("depth", 1), ("color", 3),
           ("opacity", 1), ("rect", 4))
GRAD_COLUMNS = (("xy", 2), ("conic", 3), ("opacity", 1), ("color", 3))


def _records(proj: Projected) -> tuple[np.ndarray, np.ndarray]:
    """(the rows a camera sees, their records [m, RECORD]) of a projection (host)."""
    radius = download(proj.radius)
    seen = np.flatnonzero(radius > 0)
    rec = np.empty((len(seen), RECORD), np.float32)
    at = 0
    for name, w in COLUMNS:
        a = download(getattr(proj, name)).reshape(proj.n, w)[seen]
        rec[:, at:at + w] = a.view(np.float32) if a.dtype == np.int32 else a
        at += w
    return seen, rec


def projected_of(device, rec: np.ndarray) -> Projected:
    """A Projected of records [m, RECORD] (on the device)."""
    q = device.queue
    cols, at = {}, 0
    for name, w in COLUMNS:
        a = np.ascontiguousarray(rec[:, at:at + w])
        if name == "rect":
            a = a.view(np.int32)
        cols[name] = upload(q, a.reshape(-1) if w == 1 else a)
        at += w
    return Projected(len(rec), **cols)


def _alltoallv(comm, parts: list) -> list:
    """Rank r's ``parts[k]`` (float32 [m_k, w], the same w everywhere) to rank k; returns what
    each rank sent this one, in rank order."""
    from mpi4py import MPI
    w = parts[0].shape[1]
    send_counts = np.array([p.shape[0] * w for p in parts], np.int64)
    recv_counts = np.array(comm.alltoall(send_counts.tolist()), np.int64)
    sdispl = np.concatenate([[0], np.cumsum(send_counts)[:-1]])
    rdispl = np.concatenate([[0], np.cumsum(recv_counts)[:-1]])
    send = np.ascontiguousarray(np.concatenate(parts).reshape(-1), np.float32)
    recv = np.empty(int(recv_counts.sum()), np.float32)
    comm.Alltoallv([send, (send_counts, sdispl), MPI.FLOAT],
                   [recv, (recv_counts, rdispl), MPI.FLOAT])
    return [recv[a:a + c].reshape(-1, w) for a, c in zip(rdispl, recv_counts)]


def gather_records(comm, rast, params: dict, cams: list):
    """Step 1 of the module doc: this shard projected into every camera of ``cams`` (camera k
    owned by rank k; fewer cameras than ranks: the ranks past them own none), each camera's
    records sent to its owner. Returns (this rank's camera's Projected of every rank's
    records in rank order, or None where it owns none; seen: for each camera the rows of this
    shard it sees; counts: for this rank's camera the number of records from each rank;
    radii: for each camera this shard's screen radii [n] on the device, 0 where unseen)."""
    P, r = comm.Get_size(), comm.Get_rank()
    seen, parts, radii = [], [], []
    for k in range(P):
        if k < len(cams):
            shard = rast.project(params, cams[k])
            rows, rec = _records(shard)
            radii.append(shard.radius)
        else:
            rows, rec = np.zeros(0, np.int64), np.zeros((0, RECORD), np.float32)
        seen.append(rows)
        parts.append(rec)
    got = _alltoallv(comm, parts)
    counts = [len(g) for g in got]
    proj = projected_of(rast.device, np.concatenate(got)) if r < len(cams) else None
    return proj, seen, counts, radii


def return_grads(comm, g2d: dict | None, counts: list, seen: list, n: int, absgrad: bool):
    """Step 2's way back: the owner's gradients of the records (GRAD_COLUMNS, "xy_abs" with
    ``absgrad``; None where this rank owns no camera) to the ranks that sent them; returns for
    each camera this shard's gradients as device-ready numpy arrays of all n rows (zeros where
    the camera does not see a row)."""
    P = comm.Get_size()
    cols = GRAD_COLUMNS + ((("xy_abs", 2),) if absgrad else ())
    w = sum(c for _, c in cols)
    if g2d is None:
        parts = [np.zeros((0, w), np.float32) for _ in range(P)]
    else:
        flat = np.concatenate([download(g2d[name]).reshape(-1, c) for name, c in cols], 1)
        cuts = np.cumsum([0] + list(counts))
        parts = [flat[cuts[k]:cuts[k + 1]] for k in range(P)]
    got = _alltoallv(comm, parts)
    out = []
    for k, rows in enumerate(seen):
        g = got[k]
        if g.shape[0] != len(rows):
            raise RuntimeError(f"rank {k} returned {g.shape[0]} gradients for the {len(rows)} "
                               f"records this rank sent it")
        full, at = {}, 0
        for name, c in cols:
            a = np.zeros((n, c), np.float32)
            a[rows] = g[:, at:at + c]
            full[name] = a.reshape(-1) if c == 1 else a
            at += c
        out.append(full)
    return out


def allgather_records(comm, rast, params: dict, cam) -> Projected:
    """A render's records: every rank's splats of camera ``cam``, on every rank, in rank order
    (the whole table's order)."""
    from mpi4py import MPI
    _, rec = _records(rast.project(params, cam))
    counts = np.array(comm.allgather(rec.size), np.int64)
    displ = np.concatenate([[0], np.cumsum(counts)[:-1]])
    out = np.empty(int(counts.sum()), np.float32)
    comm.Allgatherv(np.ascontiguousarray(rec.reshape(-1)), [out, (counts, displ), MPI.FLOAT])
    return projected_of(rast.device, out.reshape(-1, RECORD))


# ---- the model ------------------------------------------------------------------------------
REBALANCE_AT = 0.10   # shards are evened out when the largest exceeds the smallest by this share
# the per-Gaussian arrays of a state (clrf/splat/model.py state_dict) and the axis their rows
# run along: what a checkpoint's shards join (clrf/outputs/checkpoint.py merge_shards); the
# strategy's statistics add theirs (checkpoint_layout)
ROW_KEYS = {**{f"param_{k}": 0 for k in NAMES},
            **{f"adam_{mk}": 0 for k in NAMES for mk in moment_keys(k)},
            "filter3d": 0}


def grad_sum(device, total, g, scale: float) -> None:
    """total = (total + g) * scale in float32 (cl/splat_train.cl splat_grad_sum; device arrays
    of one size): one pass, where pyopencl's array arithmetic makes two slower ones on PoCL."""
    n = int(total.size)
    if g.size != n:
        raise ValueError(f"grad_sum: {g.size} entries added to {n}")
    launch(device, device.program("splat_train.cl").kernel("splat_grad_sum"), n,
           (np.int32(n), total.data, g.data, np.float32(scale)))


def _split_cap(cap: int, ranks: int, rank: int) -> int:
    lo, hi = shard_bounds(cap, ranks)[rank]
    return max(1, hi - lo)


def _rows(d: dict, a: int, b: int) -> dict:
    """Rows [a, b) of every per-row array of ``d``."""
    return {k: v[a:b] for k, v in d.items()}


def _join(parts: list) -> dict:
    return {k: np.concatenate([p[k] for p in parts]) for k in parts[0]}


class DistSplatModel(SplatModel):
    """One rank's shard of the Gaussians and its view of the batch (module doc). Its renders
    are collective: every rank must call them together."""

    comm = None

    def _join_ranks(self, comm, cap: int):
        """Become rank comm.Get_rank()'s shard of this (whole or own) model; ``cap`` the
        whole run's cap on the Gaussians."""
        self.comm = comm
        self.P, self.rank = comm.Get_size(), comm.Get_rank()
        self.cap_total = int(cap)
        self.max_count = _split_cap(cap, self.P, self.rank)
        self.lr_scale = float(np.sqrt(self.P))    # a batch of P views (module doc)
        self.n_total = self._total(self.n)        # (take_shard counts again)
        return self

    def _total(self, x: int) -> int:
        from mpi4py import MPI
        return int(self.comm.allreduce(int(x), op=MPI.SUM))

    def take_shard(self):
        """Keep this rank's rows of a model every rank holds whole (the same Gaussians
        everywhere: a new run, or a checkpoint joined from another rank count)."""
        lo, hi = shard_bounds(self.n, self.P)[self.rank]
        host, mom, stats = self.host_params(), self.host_moments(), self.strategy.host_rows()
        f2 = download(self.filter3d) if self.filter3d is not None else None
        self._release()
        self._set_host(_rows(host, lo, hi), _rows(mom, lo, hi), _rows(stats, lo, hi))
        if f2 is not None:
            self.filter3d = upload(self.device.queue, np.ascontiguousarray(f2[lo:hi]))
        self.n_total = self._total(self.n)
        return self

    # ---- training ----------------------------------------------------------------
    @property
    def batch_size(self) -> int:
        """Pixels of a step: one training view per rank."""
        return self.P * super().batch_size

    def train_step(self, it, origins=None, dirs=None, target=None, background=None):
        """One Adam step of this shard on the P views of step ``it`` (views it P ..
        it P + P - 1 of the one-process order), view k rendered by rank k; returns the
        batch's mean squared error (the mean over its views, the same on every rank)."""
        from mpi4py import MPI
        ds = self._dataset()
        views = [self.view_of(it * self.P + k) for k in range(self.P)]
        cams = [camera_of(ds.poses[v], ds.intrinsics, ds.hw) for v in views]
        bg = self.background
        if self.rast.antialiased and self.step - self.filter_step >= FILTER3D_EVERY:
            self.filter3d = None
        params = self._rparams()
        proj, seen, counts, radii = gather_records(self.comm, self.rast, params, cams)
        cam, v = cams[self.rank], views[self.rank]
        bins = self.rast.bin(proj, cam)
        ras = self.rast.rasterize(proj, bins, cam, bg)
        grad, stats = self._loss().loss_and_grad(ras.rgb, self._target(v))
        absgrad = self.strategy.absgrad
        g2d = self.rast.rasterize_backward(proj, bins, ras, cam, grad, bg, absgrad=absgrad)
        mse = self._loss_fn.read(stats)["mse"]
        back = return_grads(self.comm, g2d, counts, seen, self.n, absgrad)
        q = self.device.queue
        total = None
        for k, g in enumerate(back):
            g = {name: upload(q, np.ascontiguousarray(a)) for name, a in g.items()}
            grads = self.rast.project_backward(params, cams[k], g)
            self.strategy.step_post_backward(
                self.params, grads, self.moments, self.step,
                RenderInfo(radii[k], g["xy_abs" if absgrad else "xy"], int(cams[k].width),
                           int(cams[k].height)))
            if total is None:
                total = grads
            else:                   # the batch's mean gradient: summed, the last sum scaled
                scale = 1.0 / self.P if k == len(back) - 1 else 1.0
                for name in total:
                    grad_sum(self.device, total[name], grads[name], scale)
        self.step += 1
        self._adam(total, self.step)
        self.strategy.step_post_update(self.params, self.moments, self.step, self.lr_means)
        return float(self.comm.allreduce(float(mse), op=MPI.SUM)) / self.P

    def on_iteration(self, it, budget):
        """The one-process schedules on this shard; after density control the counts of
        every rank, and the shards evened out where they differ by more than
        REBALANCE_AT."""
        msg = super().on_iteration(it, budget)   # the schedule is the same on every rank
        if not msg:
            return msg
        counts = self.comm.allgather(int(self.n))
        before, self.n_total = self.n_total, int(sum(counts))
        msg = (f"{msg} (rank {self.rank}'s shard); {before} -> {self.n_total} Gaussians over "
               f"{self.P} ranks")
        if max(counts) > (1 + REBALANCE_AT) * max(min(counts), 1):
            self.rebalance(counts)
            msg += f", shards evened out (they held {' + '.join(map(str, counts))})"
        return msg

    def rebalance(self, counts):
        """Rows move to the ranks whose even share of the table they fall in: the table's
        order is kept, so each rank sends only the rows that change owner (pickled by
        mpi4py's alltoall)."""
        old = np.concatenate([[0], np.cumsum(counts)])
        new = shard_bounds(int(old[-1]), self.P)
        lo, hi = int(old[self.rank]), int(old[self.rank + 1])
        parts = self.host_params(), self.host_moments(), self.strategy.host_rows()
        send = []
        for a, b in new:
            s, e = max(lo, a), min(hi, b)
            send.append(tuple(_rows(d, s - lo, e - lo) for d in parts) if e > s else None)
        got = [g for g in self.comm.alltoall(send) if g is not None]
        self._release()
        self.device.pool.free_held()
        self._set_host(*(_join([g[i] for g in got]) for i in range(3)))

    # ---- renders (collective) ------------------------------------------------------
    def _render_raster(self, cam, depth: bool):
        """render_image's Raster: every rank's splats composited on every rank
        (collective)."""
        proj = allgather_records(self.comm, self.rast, self._rparams(), cam)
        bins = self.rast.bin(proj, cam)
        return self.rast.rasterize(proj, bins, cam, self.background, depth=depth)

    def describe(self) -> str:
        return super().describe().replace(f"{self.n} Gaussians",
                                          f"{self.n_total} Gaussians over {self.P} ranks",
                                          1)

    # ---- checkpoints -----------------------------------------------------------------
    def state_dict(self) -> dict:
        st = super().state_dict()
        st["max_count"] = self.cap_total          # the whole run's (a joined checkpoint)
        st["shard"] = {"rank": self.rank, "ranks": self.P}
        return st

    def checkpoint_layout(self) -> dict:
        """The per-Gaussian arrays the checkpoint's shards join (save_distributed)."""
        return {"rows": {**ROW_KEYS, **{k: 0 for k in self.strategy.row_keys()}}}


def check_settings(cfg, ranks: int):
    """ValueError naming the setting that splats over ``ranks`` MPI ranks do not take."""
    c = cfg.splat
    unsharded = strategy_class(c.strategy).UNSHARDED
    for key, on, why in (
            ("splat.exposure", c.exposure, "the colour transforms per image"),
            ("splat.bilateral_grid", c.bilateral_grid, "the bilateral grids per image"),
            ("splat.pose_opt", c.pose_opt, "the pose corrections"),
            ("splat.strategy", bool(unsharded), unsharded)):
        if on:
            off = SplatConfig.strategy if key.endswith("strategy") else "false"
            raise ValueError(f"{key}: {why} are not split over MPI ranks yet ({ranks} ranks); "
                             f"turn it off (--set {key}={off}) or run as one process")
