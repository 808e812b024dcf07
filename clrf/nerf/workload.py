"""NeRF's workload for the device choice (clrf/runtime/workload.py): the fused MLP forward +
backward of the tiny NeRF shape (4 x 64) on WORK_SAMPLES samples, in samples/s."""
from __future__ import annotations

import numpy as np

from ..runtime.workload import Workload, best_time

WORK_SAMPLES = 8192
SPEC_FIELDS = dict(width=64, depth=4, skip=-1, color_width=32, in_dim=51, dir_dim=15)  # MLPSpec


def nerf_rate(device) -> float:
    import pyopencl.array as cla

    from ..mlp.mlp import MLP, MLPSpec
    spec = MLPSpec(**SPEC_FIELDS)
    net = MLP(device, spec)
    q = device.queue
    rng = np.random.default_rng(4)
    n = WORK_SAMPLES
    x = cla.to_device(q, rng.random((n, spec.in_dim), np.float32))
    d = cla.to_device(q, rng.random((n, spec.dir_dim), np.float32))
    ds = cla.to_device(q, rng.random(n, np.float32))
    dr = cla.to_device(q, rng.random((n, 3), np.float32))

    def step():
        net.forward(x, d)
        net.backward(ds, dr)
        q.finish()
    return n / best_time(step)


WORKLOAD = Workload("nerf", nerf_rate, "samples/s")
