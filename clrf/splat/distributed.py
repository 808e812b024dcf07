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
   sqrt(P) times the one-view rates (Grendel's scaling; ``BATCH_LR``).

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
from ..runtime.programs import download, upload

# the columns of a projected record: xy 2, conic 3, radius, depth, colour 3, opacity, rect 4
# (int32 bits in float32 columns)
RECORD = 15
COLUMNS = (("xy", 2), ("conic", 3), ("radius", 1), ("depth", 1), ("color", 3),
           ("opacity", 1), ("rect", 4))
GRAD_COLUMNS = (("xy", 2), ("conic", 3), ("opacity", 1), ("color", 3))
BATCH_LR = "sqrt"   # the learning rates of a batch of P views: sqrt(P) times the one-view rate


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
    shard it sees; counts: for this rank's camera the number of records from each rank)."""
    P, r = comm.Get_size(), comm.Get_rank()
    seen, parts = [], []
    for k in range(P):
        if k < len(cams):
            rows, rec = _records(rast.project(params, cams[k]))
        else:
            rows, rec = np.zeros(0, np.int64), np.zeros((0, RECORD), np.float32)
        seen.append(rows)
        parts.append(rec)
    got = _alltoallv(comm, parts)
    counts = [len(g) for g in got]
    proj = projected_of(rast.device, np.concatenate(got)) if r < len(cams) else None
    return proj, seen, counts


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
