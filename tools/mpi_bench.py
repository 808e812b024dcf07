"""Distributed Plenoxels throughput (clrf/grid/distributed.py): rays/s of the composed forward render
and of a training step, rows and device memory per rank, bytes exchanged per ray and per step.

    mpirun --bind-to core -n 2 python tools/mpi_bench.py --reso 128 --out tools/results/mpi_bench_2.json
    python tools/mpi_bench.py --reso 128          # one process: the bricks path on one brick

The scene is synthetic: a sphere shell of allocated voxels (a surface-like occupancy, about 10%
of the box) with random density and SH degree 2, rays from an orbit of cameras through the box.
Each figure is the best of --repeat timings after a warm-up; rank 0 prints one JSON record.
"""
from __future__ import annotations

import argparse
import json
import os
import platform
import sys
import time
from pathlib import Path

import numpy as np

sys.path.append(str(Path(__file__).resolve().parent.parent))   # the checkout's clrf only where none is installed

import pyopencl.array as cla  # noqa: E402

import clrf  # noqa: E402
from clrf.grid.config import GridConfig  # noqa: E402
from clrf.grid import bricks as B  # noqa: E402
from clrf.grid.dist_model import DistGridModel  # noqa: E402


def shell_scene(reso, degree, seed=0):
    """Dense density / SH of a spherical shell (radius 0.6-0.8 of the half box)."""
    rng = np.random.default_rng(seed)
    c = [(np.arange(r) + 0.5) / r * 2 - 1 for r in reso]
    x, y, z = np.meshgrid(*c, indexing="ij")
    rad = np.sqrt(x * x + y * y + z * z)
    mask = (rad > 0.6) & (rad < 0.8)
    dens = np.where(mask, rng.uniform(0, 20, reso), 0).astype(np.float32)
    sh = np.where(mask[..., None], rng.normal(0, 0.3, tuple(reso) + (3 * (degree + 1) ** 2,)),
                  0).astype(np.float32)
    return dens, sh, mask


def orbit_rays(n, seed=1):
    rng = np.random.default_rng(seed)
    th = rng.uniform(0, 2 * np.pi, n)
    o = np.stack([2.5 * np.cos(th), 2.5 * np.sin(th), rng.uniform(-0.5, 0.5, n)], 1)
    target = rng.uniform(-0.7, 0.7, (n, 3))
    return o.astype(np.float32), (target - o).astype(np.float32)


class _Solo:
    """COMM_WORLD stand-in for one process without mpi4py (the bricks path on one brick)."""

    def Get_rank(self):
        return 0

    def Get_size(self):
        return 1

    def Allgather(self, a, b):
        b[0] = a

    def allreduce(self, x, op=None):
        return x

    def Barrier(self):
        pass


def phases(model, od, dd, target, repeat):
    """Seconds of each part of one training step (best of repeat), as DistGridModel.train_step
    runs them, with the queue drained between parts."""
    c = model.cfg
    q = model.device.queue
    dist = model.dist
    n = od.shape[0]
    t = {}

    def tick(name, t0):
        q.finish()
        t[name] = min(t.get(name, 1e9), time.perf_counter() - t0)
        return time.perf_counter()

    for _ in range(repeat + 1):
        t0 = time.perf_counter()
        part = B.render_partial_device(model.grid, od, dd, c.step)
        t0 = tick("forward kernel", t0)
        local = B.pack_partials(part)
        t0 = tick("partials to host", t0)
        packed = dist.allgather(local)
        t0 = tick("Allgather", t0)
        comp = B.compose(packed, model.background)
        diff = comp["rgb"] - target.get().astype(np.float64)
        inp = B.backward_inputs(packed, comp, (2.0 / (3 * n)) * diff, model.background)[dist.rank]
        inp_d = cla.to_device(q, np.ascontiguousarray(inp))
        t0 = tick("compose + loss + inputs (host)", t0)
        B.render_backward_partial_device(model.grid, od, dd, inp_d, c.step,
                                         model.opt_density.grad, model.opt_sh.grad, model.touched)
        t0 = tick("backward kernel", t0)
        dist.sum_halo(model.opt_density.grad, model.opt_sh.grad, model.touched)
        t0 = tick("halo gradient sum", t0)
        model.opt_density.step(model.touched, 0.0, clear_touched=False)
        model.opt_sh.step(model.touched, 0.0, clear_touched=True)
        tick("optimiser", t0)
    return t


def best(fn, repeat):
    """(wall seconds, CPU seconds of this process, all its threads), each the best of repeat
    after a warm-up. On a shared machine the CPU time is the steadier measure of the work."""
    fn()
    ts, cs = [], []
    for _ in range(repeat):
        t0, c0 = time.perf_counter(), time.process_time()
        fn()
        ts.append(time.perf_counter() - t0)
        cs.append(time.process_time() - c0)
    return min(ts), min(cs)


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--reso", type=int, default=128)
    ap.add_argument("--degree", type=int, default=2)
    ap.add_argument("--rays", type=int, default=8192)
    ap.add_argument("--repeat", type=int, default=5)
    ap.add_argument("--out", default="")
    a = ap.parse_args()
    try:
        from clrf.grid.distributed import world
        comm = world()
    except RuntimeError:
        comm = None
    comm = comm or _Solo()
    rank, P = comm.Get_rank(), comm.Get_size()
    dev = clrf.Device()
    reso = (a.reso,) * 3
    dens, sh, _ = shell_scene(reso, a.degree)
    bl = B.split(reso, P)
    bg = B.BrickGrid.from_dense(dev, dens, sh, [[-1, -1, -1], [1, 1, 1]], bl[rank])
    cfg = GridConfig(reso=[list(reso)], upsample_at=[], sh_degree=a.degree, batch_size=a.rays,
                     lambda_tv=0.0, lambda_tv_sh=0.0)
    model = DistGridModel(dev, cfg, comm, bg, bl, (1.0, 1.0, 1.0))
    q = dev.queue
    o, d = orbit_rays(a.rays)
    od, dd = cla.to_device(q, o), cla.to_device(q, d)
    target = cla.to_device(q, np.full((a.rays, 3), 0.5, np.float32))

    def fwd():
        model.dist.forward(od, dd, cfg.step, model.background)

    def step():
        model.train_step(1000, od, dd, target)
        q.finish()

    # bytes this rank sends per call (the counters of DistGrid)
    d0 = model.dist.bytes_sent
    fwd()
    fwd_bytes = model.dist.bytes_sent - d0
    d0 = model.dist.bytes_sent
    step()
    step_bytes = model.dist.bytes_sent - d0
    t_fwd, c_fwd = best(fwd, a.repeat)
    t_step, c_step = best(step, a.repeat)
    t_phases = phases(model, od, dd, target, a.repeat)
    g = model.grid
    C = g.sh_dim
    rows = g.n_rows
    # device bytes: links + rows (density, SH) x (value, gradient, RMSProp state) + touched
    mem = 4 * int(np.prod(g.reso)) + rows * (1 + C) * 4 * 3 + rows
    rec = {"rank": rank, "ranks": P, "brick_lo": list(bl[rank].lo), "brick_hi": list(bl[rank].hi),
           "rows": int(rows), "halo_rows": int(model.dist.halo.n_rows()),
           "device_bytes": int(mem), "fwd_s": t_fwd, "step_s": t_step,
           "fwd_cpu_s": c_fwd, "step_cpu_s": c_step,
           "fwd_bytes_sent": int(fwd_bytes), "step_bytes_sent": int(step_bytes),
           "step_phases_s": t_phases}
    if P == 1:   # the single-device path (prefetch, early termination) for comparison
        from clrf.grid.grid import SparseGrid
        from clrf.grid.model import GridModel
        sg = SparseGrid.from_dense(dev, dens, sh, [[-1, -1, -1], [1, 1, 1]])
        gm = GridModel(dev, cfg, sg, (1.0, 1.0, 1.0))
        from clrf.grid.render import render_forward_device

        def sfwd():
            render_forward_device(sg, od, dd, cfg.step, gm.background)
            q.finish()

        def sstep():
            gm.train_step(1000, od, dd, target)
            q.finish()
        rec["single_device_fwd_s"], rec["single_device_fwd_cpu_s"] = best(sfwd, a.repeat)
        rec["single_device_step_s"], rec["single_device_step_cpu_s"] = best(sstep, a.repeat)
    allrec = comm.allgather(rec) if P > 1 else [rec]
    if rank == 0:
        t_f = max(r["fwd_s"] for r in allrec)
        t_s = max(r["step_s"] for r in allrec)
        out = {
            "device": str(dev.caps.name), "driver": dev.caps.platform_version,
            "cpu": platform.processor() or platform.machine(),
            "bind": os.environ.get("OMPI_MCA_hwloc_base_binding_policy", ""),
            "reso": a.reso, "sh_degree": a.degree, "rays": a.rays, "ranks": P,
            "fwd_rays_per_s": a.rays / t_f, "step_rays_per_s": a.rays / t_s,
            "fwd_cpu_s_per_rank": [r["fwd_cpu_s"] for r in allrec],
            "step_cpu_s_per_rank": [r["step_cpu_s"] for r in allrec],
            "load_average": os.getloadavg()[0],
            "fwd_bytes_per_ray_per_rank": max(r["fwd_bytes_sent"] for r in allrec) / a.rays,
            "step_bytes_per_rank": max(r["step_bytes_sent"] for r in allrec),
            "per_rank": allrec,
            **({"single_device_fwd_rays_per_s": a.rays / rec["single_device_fwd_s"],
                "single_device_step_rays_per_s": a.rays / rec["single_device_step_s"]}
               if P == 1 else {}),
        }
        print(json.dumps(out, indent=1))
        if a.out:
            Path(a.out).parent.mkdir(parents=True, exist_ok=True)
            Path(a.out).write_text(json.dumps(out, indent=1) + "\n")


if __name__ == "__main__":
    main()
