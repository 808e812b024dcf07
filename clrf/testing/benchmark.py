"""Forward and forward+backward throughput of the grid renderer on one standard problem.

128^3 grid (dense, all voxels allocated), SH degree 2, 4096 camera rays (a 64x64 pinhole view
of the whole grid), step 0.5 voxel, low density so every ray crosses the grid (no early
termination): samples = sum of per-ray step counts. Prints medians with min-max of 5 timed runs
after a warm-up, and writes JSON with --json. The full benchmark suite is tools/bench.py.

    clrf bench [--reso 128] [--degree 2]
    python tools/render_speed.py [--reso 128] [--degree 2] [--rays-side 64] [--json out.json]
"""
import argparse
import json
import time
from pathlib import Path

import numpy as np
import pyopencl.array as cla

from ..references import reference
from ..runtime.device import Device
from ..grid import SparseGrid
from ..grid.render import render_backward_device, render_forward_device


def camera_rays(side, dist=3.0, fov_deg=40.0, seed=0):
    """A pinhole camera at distance ``dist`` looking at the origin, slightly off-axis."""
    rng = np.random.default_rng(seed)
    eye = np.array([0.3, 0.5, dist]) + rng.normal(0, 0.01, 3)
    fwd = -eye / np.linalg.norm(eye)
    right = np.cross(fwd, [0, 1, 0]); right /= np.linalg.norm(right)
    up = np.cross(right, fwd)
    f = 0.5 * side / np.tan(np.radians(fov_deg) / 2)
    j, i = np.meshgrid(np.arange(side) + 0.5, np.arange(side) + 0.5, indexing="ij")
    d = ((i - side / 2) / f)[..., None] * right + (-(j - side / 2) / f)[..., None] * up + fwd
    d = d.reshape(-1, 3)
    return np.broadcast_to(eye, d.shape).astype(np.float32).copy(), d.astype(np.float32)


def timeit(fn, dev, repeats=5):
    fn(); dev.finish()
    ts = []
    for _ in range(repeats):
        t = time.perf_counter(); fn(); dev.finish(); ts.append(time.perf_counter() - t)
    return float(np.median(ts)), float(min(ts)), float(max(ts))


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--reso", type=int, default=128)
    ap.add_argument("--degree", type=int, default=2)
    ap.add_argument("--rays-side", type=int, default=64)
    ap.add_argument("--step", type=float, default=0.5)
    ap.add_argument("--json")
    a = ap.parse_args(argv)
    dev = Device()
    rng = np.random.default_rng(0)
    R = a.reso
    C = 3 * (a.degree + 1) ** 2
    bbox = np.array([[-1.0] * 3, [1.0] * 3])
    dens = rng.uniform(0.0, 0.05, (R, R, R)).astype(np.float32)
    sh = rng.normal(0, 0.2, (R, R, R, C)).astype(np.float32)
    grid = SparseGrid.from_dense(dev, dens, sh, bbox)
    del sh
    o, d = camera_rays(a.rays_side)
    n = o.shape[0]
    samples = int(reference.march_setup(o, d, (R, R, R), bbox, a.step)["nsteps"].sum())
    q = dev.queue
    od, dd = cla.to_device(q, o), cla.to_device(q, d)
    gi = cla.to_device(q, rng.normal(size=(n, 3)).astype(np.float32))
    gd = cla.zeros(q, grid.density.shape[0], np.float32)
    gs = cla.zeros(q, grid.sh.shape, np.float32)
    out = render_forward_device(grid, od, dd, a.step, (1, 1, 1))
    fwd = timeit(lambda: render_forward_device(grid, od, dd, a.step, (1, 1, 1), out), dev)
    bwd = timeit(lambda: render_backward_device(grid, od, dd, gi, a.step, (1, 1, 1), gd, gs), dev)
    zero = timeit(lambda: (gd.fill(0), gs.fill(0)), dev)
    res = {"device": repr(dev), "reso": R, "sh_degree": a.degree, "rays": n, "samples": samples,
           "samples_per_ray": samples / n, "forward_s": fwd, "fwd_bwd_s": bwd,
           "grad_zero_fill_s": zero}
    print(f"device: {dev}")
    print(f"grid {R}^3 SH{a.degree}, {n} camera rays, step {a.step}: {samples} samples "
          f"({samples / n:.0f}/ray)")
    for name, (med, lo, hi) in (("forward", fwd), ("forward+backward", bwd),
                                ("(dense gradient zero-fill, not included)", zero)):
        print(f"{name:42s} {med * 1e3:8.1f} ms [{lo * 1e3:.1f}-{hi * 1e3:.1f}]  "
              f"{samples / med / 1e6:7.2f} M samples/s  {n / med / 1e3:7.1f} k rays/s")
    if a.json:
        Path(a.json).write_text(json.dumps(res, indent=2))
    return 0


if __name__ == "__main__":
    main()
