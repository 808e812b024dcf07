"""clrf benchmark runner: benchmarks declared as data, device peaks measured in the same run.

    python tools/bench.py                       # everything; JSON to bench-results/bench-<time>.json
    python tools/bench.py --only 'grid.*128*'   # fnmatch pattern(s) on the benchmark names
    python tools/bench.py --quick               # smoke mode: tiny sizes, one repeat, checks only
    python tools/bench.py --list                # names and parameters, nothing run
    python tools/report.py bench-results/bench-*.json   # Markdown table + plots

Every benchmark is a ``Spec`` (name, kind, parameters, metric) in ``SPECS``; ``kind`` names a
factory in ``FACTORIES`` that builds the inputs and returns a ``Case``: a callable doing one
repetition (device work finished when it returns), the work it does (samples, rays, bytes,
flop) and an optional check against a reference. The runner warms each case up once (JIT),
then repeats until the timing is stable (relative inter-quartile range below ``--tol`` after
``--min-repeats``) or a cap (``--max-repeats``, ``--max-seconds``), and records the median and
the min-max. The device peaks (copy and triad bandwidth, FMA throughput at the device's native
float vector width, cl/bench.cl) are measured at the start and at the end of the run; every
throughput is also given as a ratio to them, because this class of machine sometimes halves
everything at once (docs/perf-notes.md 1.2).

Adding benchmarks: append Specs (and, for a new kind, a factory registered with
``@factory("kind")``). Kernels that have not landed are left out by name: a Spec whose
``requires`` names a missing module attribute is reported as skipped, with the reason.
Other suites plug in through ``EXTERNAL_SUITES``: a module there (e.g. tools/nerf_bench.py)
that defines ``bench_suite(api)`` returning Specs (``api`` is this module, for ``Spec``,
``Case`` and ``factory``) has them run and reported with the rest.

Peers (optional dependencies, skipped with the reason when not importable) run on identical
inputs after their outputs were checked against clrf's: the float64 numpy reference
(clrf.reference, small sizes), tools/peers/torch_grid.py (PyTorch CPU, autograd backward)
and tools/peers/taichi_grid.py (Taichi CPU).
"""
from __future__ import annotations

import argparse
import datetime as _dt
import fnmatch
import importlib
import json
import os
import platform
import socket
import sys
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Callable

# A dense 256^3 SH-2 grid is 1.9 GB: raise PoCL's default 4.3 GB / 2.15 GB-per-buffer limits.
# Must be set before the OpenCL platform is loaded.
os.environ.setdefault("POCL_MEMORY_LIMIT", "16")

import numpy as np  # noqa: E402
import pyopencl as cl  # noqa: E402
import pyopencl.array as cla  # noqa: E402

TOOLS = Path(__file__).resolve().parent
ROOT = TOOLS.parent
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(TOOLS))
import clrf  # noqa: E402
from clrf import reference  # noqa: E402
from clrf.render import (render_backward_device, render_forward_device,  # noqa: E402
                         render_rays)
import bench_scenes as scenes  # noqa: E402

EXTERNAL_SUITES = ["nerf_bench"]   # modules in tools/ that may define bench_suite(api)


class Skip(Exception):
    """A case that cannot run here (missing peer, memory, kernel not landed): the reason."""


@dataclass
class Spec:
    name: str                 # unique; used by --only
    kind: str                 # factory key in FACTORIES
    params: dict              # passed to the factory
    metric: str = "samples/s" # headline metric for tables
    quick: dict = field(default_factory=dict)      # parameter overrides in --quick mode
    requires: tuple = ()      # ("module", "attribute") pairs that must exist, else skipped
    min_repeats: int | None = None  # overrides --min-repeats (slow peers: at least 3)


@dataclass
class Case:
    run: Callable[[], None]   # one repetition; returns when the device work is finished
    work: dict                # per repetition: samples, rays, segments, bytes, flop (any subset)
    info: dict = field(default_factory=dict)       # recorded as is (sizes, notes)
    check: dict | None = None # result of the correctness check made before timing


FACTORIES: dict[str, Callable] = {}


def factory(kind: str):
    def deco(fn):
        FACTORIES[kind] = fn
        return fn
    return deco


# ---- context shared by the cases of one run ----------------------------------------------
class Context:
    def __init__(self, dev, quick: bool):
        self.dev = dev
        self.quick = quick
        self._grid_key = None
        self._grid = None

    def grid(self, reso, degree, occupancy):
        """(links, density_rows, sh_rows, SparseGrid): the last one is kept for the next case."""
        key = (reso, degree, occupancy)
        if key != self._grid_key:
            self._grid = None
            C = 3 * (degree + 1) ** 2
            n_est = reso ** 3 * (1.0 if occupancy >= 1 else occupancy)
            need = n_est * (C + 1) * 4
            caps = self.dev.caps
            if n_est * C * 4 > caps.max_alloc_size:
                raise Skip(f"sh rows {n_est * C * 4 / 1e9:.2f} GB exceed the device's max "
                           f"allocation {caps.max_alloc_size / 1e9:.2f} GB")
            if need > 0.45 * caps.global_mem_size:
                raise Skip(f"grid {need / 1e9:.2f} GB leaves no room for gradients in "
                           f"{caps.global_mem_size / 1e9:.2f} GB of device memory")
            links, dens, sh = scenes.make_grid_rows(reso, degree, occupancy)
            g = clrf.SparseGrid.from_arrays(self.dev, links, dens, sh, scenes.BBOX)
            self._grid_key = key
            self._grid = (links, dens, sh, g)
        return self._grid


def _rays(p):
    return scenes.make_rays(p["rays"], p["n_rays"])


grid_bytes_per_sample = scenes.grid_bytes_per_sample
grid_flop_per_sample = scenes.grid_flop_per_sample


def _grid_work(p, links, o, d):
    seg, smp = scenes.count_samples(links, o, d, scenes.BBOX, p["step"])
    bwd = p.get("mode", "fwd") != "fwd"
    return {"rays": o.shape[0], "segments": seg, "samples": smp,
            "bytes": smp * grid_bytes_per_sample(p["degree"], bwd),
            "flop": smp * grid_flop_per_sample(p["degree"], bwd)}


def _compare(a, b, atol, rtol):
    a = np.asarray(a, np.float64)
    b = np.asarray(b, np.float64)
    err = np.abs(a - b)
    ok = bool(np.all(err <= atol + rtol * np.abs(b)))
    return {"max_abs_err": float(err.max(initial=0.0)), "ok": ok}


# ---- peaks (cl/bench.cl) --------------------------------------------------------------------
@factory("peak.bandwidth")
def _peak_bandwidth(ctx, p):
    dev = ctx.dev
    n = (int(p["mbytes"] * 2 ** 20) // 4) // 16 * 16
    prg = dev.program("bench.cl")
    q = dev.queue
    a = cla.empty(q, n, np.float32)
    b = cla.zeros(q, n, np.float32) + 1.0
    c = cla.zeros(q, n, np.float32) + 2.0
    if p["op"] == "copy":
        k = prg.kernel("bench_copy")
        args, nbytes = (a.data, b.data), 2 * 4 * n
    else:
        k = prg.kernel("bench_triad")
        args, nbytes = (a.data, b.data, c.data, np.float32(3.0)), 3 * 4 * n
    k.set_args(*args)
    keep = (a, b, c)   # the kernel holds raw buffers: keep the arrays alive with the case

    def run():
        cl.enqueue_nd_range_kernel(q, k, (n // 16,), None, wait_for=None)
        q.finish()
        return keep
    return Case(run, {"bytes": nbytes}, {"mbytes_per_array": n * 4 / 2 ** 20})


@factory("peak.fma")
def _peak_fma(ctx, p):
    dev = ctx.dev
    iters, chains, vec = p["iters"], 8, p.get("vec") or dev.caps.vector_width
    prg = dev.program("bench.cl", {"FMA_ITERS": iters, "FMA_CHAINS": chains, "FMA_VEC": vec})
    q = dev.queue
    n = p["items"]
    out = cla.empty(q, n, np.float32)
    k = prg.kernel("bench_fma")
    k.set_args(out.data, np.float32(0.999), np.float32(1e-3))

    def run():
        cl.enqueue_nd_range_kernel(q, k, (n,), None)
        q.finish()
        return out
    return Case(run, {"flop": 2 * vec * chains * iters * n}, {"items": n, "vector_width": vec})


# ---- clrf grid renderer ---------------------------------------------------------------------
@factory("grid.render")
def _grid_render(ctx, p):
    """params: reso, degree, occupancy, rays ('camera'/'random'), n_rays, step,
    mode ('fwd', 'fwdbwd' = fused MSE backward (GRAD_MODE 1, what training runs),
    'fwdbwd_g' = backward given dL/drgb (GRAD_MODE 0)). The gradient buffers are zeroed once
    at set-up, never per repetition (training keeps them zero except for touched rows)."""
    dev = ctx.dev
    links, dens, sh, grid = ctx.grid(p["reso"], p["degree"], p["occupancy"])
    o, d = _rays(p)
    q = dev.queue
    od, dd = cla.to_device(q, o), cla.to_device(q, d)
    step, bg = p["step"], (1.0, 1.0, 1.0)
    work = _grid_work(p, links, o, d)
    mode = p.get("mode", "fwd")
    check = None
    if p["reso"] <= 32:   # small: check the kernel against the float64 reference first
        dn, shd = scenes.dense_from_rows(links, dens, sh)
        ref = reference.render_forward(dn, shd, scenes.BBOX, o, d, step, bg)
        got = render_rays(grid, o, d, step, bg)
        check = _compare(got["rgb"], ref["rgb"], 2e-5, 1e-5)
    if mode == "fwd":
        out = render_forward_device(grid, od, dd, step, bg)

        def run():
            render_forward_device(grid, od, dd, step, bg, out)
            dev.finish()
    else:
        rng = np.random.default_rng(2)
        ray_in = cla.to_device(q, rng.uniform(0, 1, (o.shape[0], 3)).astype(np.float32))
        ray_out = cla.empty(q, o.shape[0], np.float32)
        gd = cla.zeros(q, grid.density.shape[0], np.float32)
        gs = cla.zeros(q, grid.sh.shape, np.float32)
        gm = 1 if mode == "fwdbwd" else 0
        scale = 1.0 / o.shape[0]

        def run():
            render_backward_device(grid, od, dd, ray_in, step, bg, gd, gs, grad_mode=gm,
                                   loss_scale=scale, ray_out=ray_out)
            dev.finish()
    info = {"rows": grid.n_rows, "grid_mb": grid.n_rows * (1 + grid.sh_dim) * 4 / 2 ** 20,
            "samples_per_ray": work["samples"] / max(1, work["rays"])}
    return Case(run, work, info, check)


# ---- peers ------------------------------------------------------------------------------------
def _peer_inputs(ctx, p):
    links, dens, sh, grid = ctx.grid(p["reso"], p["degree"], p["occupancy"])
    o, d = _rays(p)
    return links, dens, sh, grid, o, d


def _clrf_reference_outputs(grid, o, d, p, target):
    """clrf's rgb and (fused MSE) row gradients on the peer's inputs, as numpy."""
    q = grid.device.queue
    fwd = render_rays(grid, o, d, p["step"], (1, 1, 1))
    gd = cla.zeros(q, grid.density.shape[0], np.float32)
    gs = cla.zeros(q, grid.sh.shape, np.float32)
    render_backward_device(grid, cla.to_device(q, o), cla.to_device(q, d),
                           cla.to_device(q, target), p["step"], (1, 1, 1), gd, gs,
                           grad_mode=1, loss_scale=1.0 / o.shape[0])
    n = grid.n_rows
    return fwd["rgb"], gd.get()[:n], gs.get()[:n]


# Peer-vs-clrf agreement: both are float32 (rgb: same error budget as tests/tolerances.py
# RENDER_*; gradients: GRAD_*, relative to the largest gradient since sums run in other orders).
PEER_RGB_ATOL = 2e-5
PEER_GRAD_ATOL_REL = 1e-4


def _peer_case(ctx, p, make_peer):
    links, dens, sh, grid, o, d = _peer_inputs(ctx, p)
    rng = np.random.default_rng(2)
    target = rng.uniform(0, 1, (o.shape[0], 3)).astype(np.float32)
    peer = make_peer(links, dens, sh, o, d, p, target)
    mode = p.get("mode", "fwd")
    rgb_c, gd_c, gs_c = _clrf_reference_outputs(grid, o, d, p, target)
    res = peer.forward()
    check = {"rgb": _compare(res, rgb_c, PEER_RGB_ATOL, 1e-5)}
    if mode != "fwd":
        gd_p, gs_p = peer.forward_backward()
        scale_d = max(1e-30, float(np.abs(gd_c).max()))
        scale_s = max(1e-30, float(np.abs(gs_c).max()))
        check["grad_density"] = _compare(gd_p, gd_c, PEER_GRAD_ATOL_REL * scale_d, 1e-3)
        check["grad_sh"] = _compare(gs_p, gs_c, PEER_GRAD_ATOL_REL * scale_s, 1e-3)
    check["ok"] = all(v["ok"] for v in check.values() if isinstance(v, dict))
    if not check["ok"]:
        raise Skip(f"peer disagrees with clrf, not timed: {check}")
    run = peer.forward if mode == "fwd" else peer.forward_backward
    work = _grid_work(p, links, o, d)
    return Case(run, work, {"peer": peer.describe()}, check)


@factory("peer.numpy_ref")
def _peer_numpy(ctx, p):
    class Ref:
        def __init__(self, links, dens, sh, o, d, p, target):
            self.dn, self.sh = scenes.dense_from_rows(links, dens, sh)
            self.o, self.d, self.p = o, d, p

        def forward(self):
            return reference.render_forward(self.dn, self.sh, scenes.BBOX, self.o, self.d,
                                            self.p["step"], (1, 1, 1))["rgb"]

        def describe(self):
            return f"clrf.reference (numpy {np.__version__}, float64)"
    if p.get("mode", "fwd") != "fwd":
        raise Skip("the numpy reference backward is not a fused MSE step; forward only")
    return _peer_case(ctx, p, Ref)


@factory("peer.torch")
def _peer_torch(ctx, p):
    try:
        from peers import torch_grid
    except ImportError as e:
        raise Skip(f"torch peer unavailable: {e}") from None
    return _peer_case(ctx, p, torch_grid.TorchGrid)


@factory("peer.taichi")
def _peer_taichi(ctx, p):
    try:
        from peers import taichi_grid
    except ImportError as e:
        raise Skip(f"taichi peer unavailable: {e}") from None
    return _peer_case(ctx, p, taichi_grid.TaichiGrid)


# ---- training kernels (main: clrf.grid_ops, clrf.optim, clrf.model_grid) ----------------------
def _touched_all(dev, n):
    t = cla.empty(dev.queue, n, np.uint8)
    t.fill(1)
    return t


@factory("train.tv")
def _train_tv(ctx, p):
    """tv_grad over every cell of the grid (density and SH), as one training step does over a
    window: cells/s. Adds into zeroed-once gradient buffers (not reset per repetition)."""
    from clrf import grid_ops
    dev = ctx.dev
    links, dens, sh, grid = ctx.grid(p["reso"], p["degree"], p["occupancy"])
    q = dev.queue
    gd = cla.zeros(q, grid.density.shape[0], np.float32)
    gs = cla.zeros(q, grid.sh.shape, np.float32)
    touched = cla.zeros(q, grid.density.shape[0], np.uint8)
    total = int(np.prod(grid.reso))

    def run():
        grid_ops.tv_grad(grid, grid.density, gd, touched, 0, total, 1e-5 / total, True)
        grid_ops.tv_grad(grid, grid.sh, gs, touched, 0, total, 1e-3 / total, False)
        dev.finish()
    # per cell: links of the cell and 3 neighbours, their rows (density + SH) read, grad RMW
    row = 4 * (1 + grid.sh_dim)
    return Case(run, {"cells": total, "bytes": total * (16 + 4 * row + 2 * row)},
                {"rows": grid.n_rows})


@factory("train.optim")
def _train_optim(ctx, p):
    """RowOptimizer.step (RMSProp) over every row of density and SH (all touched): rows/s."""
    from clrf.optim import RowOptimizer
    dev = ctx.dev
    links, dens, sh, grid = ctx.grid(p["reso"], p["degree"], p["occupancy"])
    od = RowOptimizer(dev, grid.density.copy(), "rmsprop")
    osh = RowOptimizer(dev, grid.sh.copy(), "rmsprop")
    touched = _touched_all(dev, grid.density.shape[0])

    def run():
        od.step(touched, 1e-3, clear_touched=False)
        osh.step(touched, 1e-3, clear_touched=False)
        dev.finish()
    n = grid.density.shape[0]
    # per row: param, grad, state read and written, touched read
    return Case(run, {"rows": n, "bytes": n * (6 * 4 * (1 + grid.sh_dim) + 1)},
                {"rows": grid.n_rows})


@factory("train.upsample")
def _train_upsample(ctx, p):
    """grid_ops.resample to twice the resolution (all rows kept): output cells/s."""
    from clrf import grid_ops
    dev = ctx.dev
    links, dens, sh, grid = ctx.grid(p["reso"], p["degree"], p["occupancy"])
    new = tuple(2 * r for r in grid.reso)

    def run():
        grid_ops.resample(grid, new)
        dev.finish()
    total = int(np.prod(new))
    return Case(run, {"cells": total}, {"rows_in": grid.n_rows, "new_reso": new})


@factory("train.prune")
def _train_prune(ctx, p):
    """Pruning: max rendering weight over n_rays camera rays, threshold + dilation, rebuild
    (grid_ops.max_weight + grid_ops.prune): cells/s of the grid."""
    from clrf import grid_ops
    dev = ctx.dev
    links, dens, sh, grid = ctx.grid(p["reso"], p["degree"], p["occupancy"])
    o, d = _rays(p)

    def run():
        mw = grid_ops.max_weight(grid, o, d, p["step"])
        grid_ops.prune(grid, mw, 0.256 / grid.reso[2])
        dev.finish()
    return Case(run, {"cells": int(np.prod(grid.reso)), "rays": o.shape[0]},
                {"rows": grid.n_rows})


@factory("train.step")
def _train_step(ctx, p):
    """One full Plenoxels training step (GridModel.train_step: fused render backward, TV,
    RMSProp on density and SH, per-batch MSE read back) on a batch of random rays: rays/s."""
    from clrf.config import GridConfig
    from clrf.model_grid import GridModel
    dev = ctx.dev
    links, dens, sh, grid = ctx.grid(p["reso"], p["degree"], p["occupancy"])
    q = dev.queue
    # a private copy: the step updates the grid
    g = clrf.SparseGrid.from_arrays(dev, links, dens, sh, scenes.BBOX)
    cfg = GridConfig(reso=[list(g.reso)], sh_degree=p["degree"], step=p["step"],
                     batch_size=p["n_rays"], tv_early_only=False)
    model = GridModel(dev, cfg, g, (1.0, 1.0, 1.0))
    o, d = _rays(p)
    rng = np.random.default_rng(3)
    target = rng.uniform(0, 1, (o.shape[0], 3)).astype(np.float32)
    od, dd, td = cla.to_device(q, o), cla.to_device(q, d), cla.to_device(q, target)
    it = [0]

    def run():
        it[0] += 1
        model.train_step(it[0], od, dd, td)
        dev.finish()
    work = _grid_work(dict(p, mode="fwdbwd"), links, o, d)
    work.pop("bytes")
    return Case(run, work, {"rows": g.n_rows, "batch": o.shape[0]})


def _train_specs():
    base = {"reso": 128, "degree": 2, "occupancy": 1.0, "step": 0.5}
    quick = {"reso": 16, "n_rays": 64}
    need_ops = (("clrf.grid_ops", "tv_grad"),)
    return [
        Spec("train/tv/128/sh2/dense", "train.tv", dict(base), "cells/s", dict(quick), need_ops),
        Spec("train/optim/128/sh2/dense", "train.optim", dict(base), "rows/s", dict(quick),
             (("clrf.optim", "RowOptimizer"),)),
        Spec("train/upsample/64to128/sh2/dense", "train.upsample", dict(base, reso=64),
             "cells/s", dict(quick, reso=8), (("clrf.grid_ops", "resample"),)),
        Spec("train/prune/128/sh2/dense", "train.prune",
             dict(base, rays="camera", n_rays=65536), "cells/s", dict(quick),
             (("clrf.grid_ops", "prune"),)),
        Spec("train/step/128/sh2/dense/random", "train.step",
             dict(base, rays="random", n_rays=5000), "rays/s", dict(quick),
             (("clrf.model_grid", "GridModel"),)),
        Spec("train/step/128/sh2/pruned5/random", "train.step",
             dict(base, occupancy=0.05, rays="random", n_rays=5000), "rays/s", dict(quick),
             (("clrf.model_grid", "GridModel"),)),
    ]


# ---- the benchmark list ---------------------------------------------------------------------
def _grid_specs():
    base = {"step": 0.5, "n_rays": 4096}
    quick = {"reso": 16, "n_rays": 64}
    out = []

    def add(kind, prefix, min_repeats=None, **kw):
        p = dict(base, **kw)
        occ = "dense" if p["occupancy"] >= 1 else f"pruned{int(round(p['occupancy'] * 100))}"
        name = (f"{prefix}/{p.get('mode', 'fwd')}/{p['reso']}/sh{p['degree']}/{occ}/"
                f"{p['rays']}")
        out.append(Spec(name, kind, p, "samples/s", dict(quick), min_repeats=min_repeats))

    # 128^3: every SH degree, dense and pruned (5 %), coherent camera rays, fwd / fused fwd+bwd
    for deg in (0, 2, 3):
        for occ in (1.0, 0.05):
            for mode in ("fwd", "fwdbwd"):
                add("grid.render", "grid", reso=128, degree=deg, occupancy=occ, rays="camera",
                    mode=mode)
    add("grid.render", "grid", reso=128, degree=2, occupancy=1.0, rays="camera", mode="fwdbwd_g")
    for occ in (1.0, 0.05):   # incoherent rays
        for mode in ("fwd", "fwdbwd"):
            add("grid.render", "grid", reso=128, degree=2, occupancy=occ, rays="random",
                mode=mode)
    # 256^3: SH2 dense is 1.9 GB (forward only: grid + gradients + scratch would not fit in
    # device memory); fwd+bwd on SH0 dense and on a 5 % pruned SH2 grid.
    add("grid.render", "grid", reso=256, degree=2, occupancy=1.0, rays="camera", mode="fwd")
    for mode in ("fwd", "fwdbwd"):
        add("grid.render", "grid", reso=256, degree=0, occupancy=1.0, rays="camera", mode=mode)
        add("grid.render", "grid", reso=256, degree=2, occupancy=0.05, rays="camera", mode=mode)
    add("grid.render", "grid", reso=256, degree=2, occupancy=0.05, rays="random", mode="fwd")

    # peers on the bar configuration (128^3 SH2 dense camera); taichi also on a pruned grid
    # (torch takes tens of seconds per repetition here: dense only, 3 repetitions)
    for occ in (1.0, 0.05):
        for mode in ("fwd", "fwdbwd"):
            add("peer.taichi", "peer.taichi", reso=128, degree=2, occupancy=occ, rays="camera",
                mode=mode)
    for mode in ("fwd", "fwdbwd"):
        add("peer.torch", "peer.torch", min_repeats=3, reso=128, degree=2, occupancy=1.0,
            rays="camera", mode=mode)
    # the float64 reference is slow: a small problem, with clrf on the same one
    small = dict(reso=32, degree=2, occupancy=1.0, rays="camera", n_rays=1024, mode="fwd")
    add("peer.numpy_ref", "peer.numpy_ref", **small)
    add("grid.render", "grid", **small)
    return out


def _peak_specs():
    return [
        Spec("peak/copy", "peak.bandwidth", {"op": "copy", "mbytes": 256}, "GB/s",
             {"mbytes": 4}),
        Spec("peak/triad", "peak.bandwidth", {"op": "triad", "mbytes": 256}, "GB/s",
             {"mbytes": 4}),
        Spec("peak/fma", "peak.fma", {"iters": 4096, "items": 4096}, "GFLOP/s",
             {"iters": 64, "items": 64}),
    ]


# Training kernels (TV, optimiser step, upsample, prune, full Plenoxels step); a spec whose
# module is missing on a branch is reported as skipped (Spec.requires).
TRAINING_SPECS: list = _train_specs()

SPECS = _grid_specs() + TRAINING_SPECS


def external_specs():
    out = []
    for modname in EXTERNAL_SUITES:
        if not (TOOLS / f"{modname}.py").is_file():
            continue
        mod = importlib.import_module(modname)
        if hasattr(mod, "bench_suite"):
            out += list(mod.bench_suite(sys.modules[__name__]))
    return out


# ---- runner ---------------------------------------------------------------------------------
def _requires_ok(spec):
    for modname, attr in spec.requires:
        try:
            mod = importlib.import_module(modname)
        except ModuleNotFoundError as e:
            if e.name and modname.startswith(e.name):
                return f"{modname} does not exist (not landed on this branch)"
            return f"{modname} not importable: {e}"
        except ImportError as e:
            return f"{modname} not importable: {e}"
        if not hasattr(mod, attr):
            return f"{modname}.{attr} does not exist (not landed on this branch)"
    return None


def time_case(case: Case, min_repeats, max_repeats, max_seconds, tol, warmup=1):
    for _ in range(warmup):
        case.run()
    ts, cpu = [], []
    t_start = time.perf_counter()
    while True:
        t = time.perf_counter()
        c = time.process_time()
        case.run()
        ts.append(time.perf_counter() - t)
        cpu.append(time.process_time() - c)
        n = len(ts)
        if n >= max_repeats:
            break
        if n >= min_repeats:
            q1, med, q3 = np.percentile(ts, [25, 50, 75])
            if (q3 - q1) / med < tol or time.perf_counter() - t_start > max_seconds:
                break
    return ts, cpu


def metrics(work, median_s):
    m = {}
    for key, unit in (("samples", "samples/s"), ("rays", "rays/s"), ("segments", "segments/s"),
                      ("cells", "cells/s"), ("rows", "rows/s")):
        if key in work:
            m[unit] = work[key] / median_s
    if "bytes" in work:
        m["GB/s"] = work["bytes"] / median_s / 1e9
    if "flop" in work:
        m["GFLOP/s"] = work["flop"] / median_s / 1e9
    return m


def device_info(dev):
    c = dev.caps
    return {"name": c.name, "platform": c.platform, "platform_version": c.platform_version,
            "driver_version": c.driver_version, "type": c.type, "compute_units": c.compute_units,
            "global_mem_gb": c.global_mem_size / 1e9, "max_alloc_gb": c.max_alloc_size / 1e9,
            "repr": repr(dev)}


def host_info():
    try:
        load = os.getloadavg()
    except OSError:
        load = None
    cpu = platform.processor()
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                cpu = line.split(":", 1)[1].strip()
                break
    except OSError:
        pass
    return {"host": socket.gethostname(), "cpu": cpu, "cpus": os.cpu_count(), "loadavg": load,
            "python": platform.python_version(), "numpy": np.__version__,
            "pyopencl": cl.VERSION_TEXT}


def run_spec(ctx, spec, args):
    params = dict(spec.params)
    if ctx.quick:
        params.update(spec.quick)
    rec = {"name": spec.name, "kind": spec.kind, "params": params, "metric": spec.metric}
    why = _requires_ok(spec)
    if why:
        rec["skipped"] = why
        return rec
    try:
        t0 = time.perf_counter()
        case = FACTORIES[spec.kind](ctx, params)
        rec["setup_s"] = time.perf_counter() - t0
    except Skip as e:
        rec["skipped"] = str(e)
        return rec
    rec.update(work=case.work, info=case.info, check=case.check)
    if case.check is not None and not case.check.get("ok", True):
        rec["failed"] = "check against the reference failed"
        return rec
    if ctx.quick:
        case.run()
        return rec
    ts, cpu = time_case(case, spec.min_repeats or args.min_repeats, args.max_repeats,
                        args.max_seconds, args.tol)
    med = float(np.median(ts))
    rec["time_s"] = {"median": med, "min": float(min(ts)), "max": float(max(ts)),
                     "repeats": len(ts)}
    # CPU time of this process (all threads) per repetition: on a shared host, work / (CPU time
    # / compute units) estimates what the case would reach with the cores to itself.
    cus = ctx.dev.caps.compute_units if ctx.dev.is_cpu else 0
    rec["cpu_s"] = {"median": float(np.median(cpu))}
    if cus:
        rec["metrics_cpu_normalised"] = metrics(case.work, float(np.median(cpu)) / cus)
    rec["metrics"] = metrics(case.work, med)
    rec["metrics_min_max"] = {k: [metrics(case.work, max(ts))[k], metrics(case.work, min(ts))[k]]
                              for k in rec["metrics"]}
    return rec


def summarise_peaks(results):
    """Median of the start and end measurements of each peak."""
    peaks = {}
    for r in results:
        if r["name"].startswith("peak/") and "metrics" in r:
            key = r["name"].split("/", 1)[1].split("@")[0]
            unit = r["metric"]
            peaks.setdefault(key, []).append(r["metrics"][unit])
    return {k: float(np.mean(v)) for k, v in peaks.items()}


def add_ratios(results, peaks):
    bw = peaks.get("triad")
    fl = peaks.get("fma")
    for r in results:
        m = r.get("metrics")
        if not m:
            continue
        ratios = {}
        if bw and "GB/s" in m:
            ratios["GB/s / triad"] = m["GB/s"] / bw
        if fl and "GFLOP/s" in m:
            ratios["GFLOP/s / fma"] = m["GFLOP/s"] / fl
        r["ratios"] = ratios


def main(argv=None):
    ap = argparse.ArgumentParser(description="clrf benchmarks (see the module docstring)")
    ap.add_argument("--only", action="append", default=[],
                    help="fnmatch pattern on benchmark names; repeatable (peaks always run)")
    ap.add_argument("--quick", action="store_true", help="smoke mode: tiny sizes, no timing")
    ap.add_argument("--list", action="store_true", help="print the benchmarks and exit")
    ap.add_argument("--out", help="JSON output path (default bench-results/bench-<time>.json)")
    ap.add_argument("--device", help="CLRF_DEVICE-style spec ('cpu', 'gpu', 'P:D')")
    ap.add_argument("--min-repeats", type=int, default=5)
    ap.add_argument("--max-repeats", type=int, default=25)
    ap.add_argument("--max-seconds", type=float, default=20.0,
                    help="stop repeating a case after this long even if not stable")
    ap.add_argument("--tol", type=float, default=0.05,
                    help="stable when (q3 - q1) / median < tol")
    args = ap.parse_args(argv)

    specs = SPECS + external_specs()
    if args.only:
        specs = [s for s in specs if any(fnmatch.fnmatch(s.name, pat) for pat in args.only)]
    if args.list:
        for s in _peak_specs() + specs:
            print(f"{s.name:50s} {s.kind:16s} {json.dumps(s.params)}")
        return 0

    dev = clrf.Device(args.device)
    ctx = Context(dev, args.quick)
    started = _dt.datetime.now().isoformat(timespec="seconds")
    host0 = host_info()
    results = []

    def run_peaks(tag):
        for s in _peak_specs():
            s = Spec(f"{s.name}@{tag}", s.kind, s.params, s.metric, s.quick)
            results.append(run_spec(ctx, s, args))
            _print(results[-1])

    run_peaks("start")
    for s in specs:
        results.append(run_spec(ctx, s, args))
        _print(results[-1])
    run_peaks("end")
    peaks = summarise_peaks(results)
    add_ratios(results, peaks)
    doc = {"started": started, "finished": _dt.datetime.now().isoformat(timespec="seconds"),
           "quick": args.quick, "device": device_info(dev), "host_start": host0,
           "host_end": host_info(), "peaks": peaks, "argv": sys.argv[1:], "results": results}
    out = Path(args.out) if args.out else (
        ROOT / "bench-results" / f"bench-{started.replace(':', '')}.json")
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(doc, indent=1, default=_jsonable))
    print(f"peaks: {json.dumps(peaks)}")
    print(f"wrote {out}")
    bad = [r["name"] for r in results if "failed" in r]
    if bad:
        print(f"FAILED checks: {bad}", file=sys.stderr)
        return 1
    return 0


def _jsonable(o):
    if isinstance(o, (np.integer,)):
        return int(o)
    if isinstance(o, (np.floating,)):
        return float(o)
    if isinstance(o, np.ndarray):
        return o.tolist()
    return str(o)


def _print(r):
    if "skipped" in r:
        print(f"{r['name']:50s} skipped: {r['skipped']}", flush=True)
    elif "failed" in r:
        print(f"{r['name']:50s} FAILED: {r['failed']} {r.get('check')}", flush=True)
    elif "metrics" in r:
        t = r["time_s"]
        m = r["metrics"]
        head = m.get(r["metric"], float("nan"))
        scale, unit = (1e-6, "M " + r["metric"]) if r["metric"].endswith("/s") and \
            r["metric"] not in ("GB/s", "GFLOP/s") else (1.0, r["metric"])
        extra = f"  {m['GB/s']:.2f} GB/s" if "GB/s" in m and r["metric"] != "GB/s" else ""
        print(f"{r['name']:50s} {head * scale:9.3f} {unit}  {t['median'] * 1e3:9.2f} ms "
              f"[{t['min'] * 1e3:.2f}-{t['max'] * 1e3:.2f}] x{t['repeats']}{extra}", flush=True)
    else:
        print(f"{r['name']:50s} ok (smoke) {r.get('check') or ''}", flush=True)


if __name__ == "__main__":
    sys.exit(main())
