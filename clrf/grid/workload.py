"""The grid's workload for the device choice (clrf/runtime/workload.py): forward + backward
(float32 gradients, the device's own tuning) of WORK_RAYS random rays through a dense
WORK_RESO^3 SH-degree-2 grid, in rays/s."""
from __future__ import annotations

import numpy as np

from ..runtime.workload import Workload, best_time

WORK_RESO = 48
WORK_RAYS = 4096


def grid_rate(device) -> float:
    import pyopencl.array as cla

    from ..runtime.programs import upload
    from .grid import SparseGrid
    from .render import render_backward_device, render_forward_device
    rng = np.random.default_rng(3)
    r = WORK_RESO
    dens = rng.uniform(0.0, 0.3, (r, r, r)).astype(np.float32)
    sh = rng.normal(0.0, 0.3, (r, r, r, 27)).astype(np.float32)
    grid = SparseGrid.from_dense(device, dens, sh, np.array([[-1.0] * 3, [1.0] * 3]))
    o = rng.uniform(-0.5, 0.5, (WORK_RAYS, 3)) + np.array([0.0, 0.0, -3.0])
    d = rng.uniform(-0.4, 0.4, (WORK_RAYS, 3)) + np.array([0.0, 0.0, 1.0])   # towards the box
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    q = device.queue
    od, dd = upload(q, o.astype(np.float32)), upload(q, d.astype(np.float32))
    g = upload(q, rng.normal(size=(WORK_RAYS, 3)).astype(np.float32))
    gd = cla.zeros(q, grid.density.shape[0], np.float32)
    gs = cla.zeros(q, grid.sh.shape, np.float32)

    def step():
        render_forward_device(grid, od, dd, 0.5, (1.0, 1.0, 1.0))
        render_backward_device(grid, od, dd, g, 0.5, (1.0, 1.0, 1.0), gd, gs)
        q.finish()
    return WORK_RAYS / best_time(step)


WORKLOAD = Workload("grid", grid_rate, "rays/s")
