"""The grid's workload for the device choice (clrf/runtime/workload.py): one training step's
render, the fused forward + backward against target colours (GRAD_MODE 1 with the per-sample
record where the device's tuning keeps one, float32 gradients), of WORK_RAYS rays through a
dense WORK_RESO^3 SH-degree-2 grid, in rays/s.

The rays are a training batch's: each from its own camera on a sphere around the box, towards
a random point inside it (sorted by the device's ray order, as in training). Until 2026-11-25
the workload ran the forward and then the backward given dL/drgb (GRAD_MODE 0) on rays from
one side: on a Zen 4 it put Intel's CPU runtime 1.6x ahead of PoCL, where tools/bench.py's
fused forward + backward measured PoCL 1.2x ahead. This one measured Intel at 0.80-0.89x PoCL
in three runs (0.76-0.83x at 64^3), in line with bench.py's 0.81-0.86x.
"""
from __future__ import annotations

import numpy as np

from ..runtime.workload import Workload, best_time

WORK_RESO = 48
WORK_RAYS = 4096
CAMERA_RADIUS = 2.5     # cameras on this sphere around the box [-1, 1]^3
TARGET_HALF = 0.8       # rays aim at uniform points of [-TARGET_HALF, TARGET_HALF]^3


def batch_rays(n: int, rng) -> tuple:
    """(origins, unit directions), float32 [n, 3]: a training batch's incoherent rays."""
    o = rng.normal(size=(n, 3))
    o *= CAMERA_RADIUS / np.linalg.norm(o, axis=1, keepdims=True)
    d = rng.uniform(-TARGET_HALF, TARGET_HALF, (n, 3)) - o
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    return o.astype(np.float32), d.astype(np.float32)


def grid_rate(device) -> float:
    import pyopencl.array as cla

    from ..runtime.programs import upload
    from .grid import SparseGrid
    from .render import render_backward_device
    rng = np.random.default_rng(3)
    r = WORK_RESO
    dens = rng.uniform(0.0, 0.3, (r, r, r)).astype(np.float32)
    sh = rng.normal(0.0, 0.3, (r, r, r, 27)).astype(np.float32)
    grid = SparseGrid.from_dense(device, dens, sh, np.array([[-1.0] * 3, [1.0] * 3]))
    o, d = batch_rays(WORK_RAYS, rng)
    q = device.queue
    od, dd = upload(q, o), upload(q, d)
    target = upload(q, rng.uniform(0.0, 1.0, (WORK_RAYS, 3)).astype(np.float32))
    sqerr = cla.empty(q, WORK_RAYS, np.float32)
    gd = cla.zeros(q, grid.density.shape[0], np.float32)
    gs = cla.zeros(q, grid.sh.shape, np.float32)
    bg = (1.0, 1.0, 1.0)

    def step():
        render_backward_device(grid, od, dd, target, 0.5, bg, gd, gs, grad_mode=1,
                               loss_scale=1.0 / (3 * WORK_RAYS), ray_out=sqerr)
        q.finish()
    return WORK_RAYS / best_time(step)


WORKLOAD = Workload("grid", grid_rate, "rays/s")
