"""The hash grid's data-parallel step over MPI ranks (clrf/runtime/dataparallel.py): the wall
time of a training step, the part of it spent summing the gradients over the ranks, and the
bytes each rank sends per step, for a preset's table on random rays through the box.

    python tools/mpi_hash_bench.py --preset tiny                       # one process
    mpirun --bind-to core -n 2 python tools/mpi_hash_bench.py --preset tiny

Each figure is the median of --steps timed steps after --warmup; rank 0 prints one JSON
record (the CPU, the device and the OpenCL platform with it).
"""
from __future__ import annotations

import argparse
import json
import platform
import sys
import time
from pathlib import Path

import numpy as np

# the checkout's clrf only where none is installed
sys.path.append(str(Path(__file__).resolve().parent.parent))

import pyopencl.array as cla  # noqa: E402

import clrf  # noqa: E402
from clrf.hash.config import HashConfig  # noqa: E402
from clrf.hash.model import HashModel  # noqa: E402
from clrf.runtime.dataparallel import DataParallel  # noqa: E402
from clrf.runtime.mpi import world  # noqa: E402


def cpu_name() -> str:
    for line in Path("/proc/cpuinfo").read_text().splitlines():
        if line.startswith("model name"):
            return line.split(":", 1)[1].strip()
    return platform.processor()


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--preset", default="tiny", choices=["tiny", "full"])
    ap.add_argument("--rays", type=int, default=4096, help="rays per step (the whole batch)")
    ap.add_argument("--warmup", type=int, default=5)
    ap.add_argument("--steps", type=int, default=20)
    a = ap.parse_args()
    comm = world()
    dev = clrf.Device()
    cfg = HashConfig.from_preset(a.preset, batch_samples=0, occ_warmup=1 << 30)
    model = HashModel(dev, cfg, 2.0, 6.0, [[-1.5] * 3, [1.5] * 3], seed=1)
    if comm is not None:
        model.ranks = DataParallel(comm)
    rng = np.random.default_rng(0)
    o = rng.normal(size=(a.rays, 3))
    o *= 4.0 / np.linalg.norm(o, axis=1, keepdims=True)
    d = rng.uniform(-1, 1, (a.rays, 3)) - o
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    q = dev.queue
    args = [cla.to_device(q, x.astype(np.float32)) for x in (o, d, rng.random((a.rays, 3)))]
    sync_time = [0.0]
    if model.ranks is not None:   # time the gradient sum inside the step
        inner = model.ranks.sum_gradients

        def timed(parts):
            q.finish()       # the backward's kernels still queued are not the sum's,
            comm.Barrier()   # nor the wait for the slower rank's share
            t0 = time.perf_counter()
            inner(parts)
            sync_time[0] += time.perf_counter() - t0
        model.ranks.sum_gradients = timed
    steps, syncs = [], []
    for it in range(a.warmup + a.steps):
        if comm is not None:
            comm.Barrier()
        sync_time[0] = 0.0
        t0 = time.perf_counter()
        float(model.train_step(it, *args))
        q.finish()
        if it >= a.warmup:
            steps.append(time.perf_counter() - t0)
            syncs.append(sync_time[0])
    sent = model.ranks.bytes_sent / (a.warmup + a.steps) if model.ranks is not None else 0
    rec = {"preset": a.preset, "rays": a.rays, "ranks": 1 if comm is None else comm.Get_size(),
           "step_s": float(np.median(steps)), "sum_gradients_s": float(np.median(syncs)),
           "bytes_sent_per_step": int(sent),
           "table_entries_stepped": int(sum(b - a for a, b in model._table_spans)),
           "network_entries": int(model.net.grad.size),
           "cpu": cpu_name(), "device": dev.caps.name, "platform": dev.caps.platform_version}
    if comm is not None:
        from mpi4py import MPI
        rec["step_s"] = comm.allreduce(rec["step_s"], op=MPI.MAX)
        if comm.Get_rank() != 0:
            return
    print(json.dumps(rec))


if __name__ == "__main__":
    main()
