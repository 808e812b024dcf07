"""The benchmark factories: device peaks (cl/bench.cl), the grid renderer, peers on identical
inputs, the training kernels, the hash encoding and the Gaussian-splatting rasteriser (each
beside its Taichi peer)."""
from __future__ import annotations

import numpy as np
import pyopencl as cl
import pyopencl.array as cla
import clrf
from clrf.references import reference, reference_splat
from clrf.testing import tolerances as tol
from clrf.grid.render import (render_backward_device, render_forward_device,
                              render_rays)
import bench_scenes as scenes

from .framework import Case, Skip, Spec, _compare, _grid_work, _rays, factory


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
    if dev.caps.type != "cpu":   # as the device probe: a GPU needs ~2048 items per unit in flight
        n = max(n, dev.caps.compute_units * 2048)
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


# Peer-vs-clrf agreement: both are float32 (rgb: same error budget as clrf/testing/tolerances.py
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
            return f"clrf.references.reference (numpy {np.__version__}, float64)"
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


# ---- training kernels (main: clrf.grid.ops, clrf.runtime.optim, clrf.grid.model) ----------------------
def _touched_all(dev, n):
    t = cla.empty(dev.queue, n, np.uint8)
    t.fill(1)
    return t


@factory("train.tv")
def _train_tv(ctx, p):
    """tv_grad over every cell of the grid (density and SH), as one training step does over a
    window: cells/s. Adds into zeroed-once gradient buffers (not reset per repetition)."""
    from clrf.grid import ops as grid_ops
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
    """Optimizer.step (RMSProp) over every row of density and SH (all touched): rows/s."""
    from clrf.runtime.optim import Optimizer
    dev = ctx.dev
    links, dens, sh, grid = ctx.grid(p["reso"], p["degree"], p["occupancy"])
    od = Optimizer(dev, grid.density.copy(), "rmsprop")
    osh = Optimizer(dev, grid.sh.copy(), "rmsprop")
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
    from clrf.grid import ops as grid_ops
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
    from clrf.grid import ops as grid_ops
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
    from clrf.grid.config import GridConfig
    from clrf.grid.model import GridModel
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
    need_ops = (("clrf.grid.ops", "tv_grad"),)
    return [
        Spec("train/tv/128/sh2/dense", "train.tv", dict(base), "cells/s", dict(quick), need_ops),
        Spec("train/optim/128/sh2/dense", "train.optim", dict(base), "rows/s", dict(quick),
             (("clrf.runtime.optim", "Optimizer"),)),
        Spec("train/upsample/64to128/sh2/dense", "train.upsample", dict(base, reso=64),
             "cells/s", dict(quick, reso=8), (("clrf.grid.ops", "resample"),)),
        Spec("train/prune/128/sh2/dense", "train.prune",
             dict(base, rays="camera", n_rays=65536), "cells/s", dict(quick),
             (("clrf.grid.ops", "prune"),)),
        Spec("train/step/128/sh2/dense/random", "train.step",
             dict(base, rays="random", n_rays=5000), "rays/s", dict(quick),
             (("clrf.grid.model", "GridModel"),)),
        Spec("train/step/128/sh2/pruned5/random", "train.step",
             dict(base, occupancy=0.05, rays="random", n_rays=5000), "rays/s", dict(quick),
             (("clrf.grid.model", "GridModel"),)),
    ]


# ---- hash encoding (cl/hash.cl) and its Taichi peer --------------------------------------------
def _hash_inputs(ctx, p):
    """The encoding and identical inputs for clrf and the peer: n points uniform in the box, a
    table uniform in +-1, dL/denc uniform in +-1."""
    from clrf.hash.encoding import HashEncoding
    rng = np.random.default_rng(4)
    L, F, lt = p["levels"], p["features"], p["log2_t"]
    box = ((-1.5,) * 3, (1.5,) * 3)
    table = rng.uniform(-1, 1, (L, 1 << lt, F)).astype(np.float32)
    enc = HashEncoding(ctx.dev, L, F, lt, p["n_min"], p["n_max"], box, table=table)
    x = rng.uniform(-1.5, 1.5, (p["n_points"], 3)).astype(np.float32)
    genc = rng.uniform(-1, 1, (p["n_points"], L * F)).astype(np.float32)
    return enc, table, x, genc


def _hash_work(p):
    return {"samples": p["n_points"], "bytes": p["n_points"] * p["levels"] * 8 * p["features"] * 4}


@factory("hash.encode")
def _hash_encode(ctx, p):
    """params: levels, features, log2_t, n_min, n_max, n_points, mode ('fwd' | 'fwdbwd': the
    encoding forward, then the gradient table zeroed and the backward scattered into it, as a
    training step runs them). samples/s = points per second."""
    enc, table, x, genc = _hash_inputs(ctx, p)
    q = ctx.dev.queue
    xd, gd = cla.to_device(q, x), cla.to_device(q, genc)
    out = cla.empty(q, (x.shape[0], enc.dim), np.float32)
    mode = p.get("mode", "fwd")

    def run():
        enc.forward(xd, out)
        if mode != "fwd":
            enc.grad.fill(np.float32(0))
            enc.backward(xd, gd)
        ctx.dev.finish()
    info = {"table_mb": enc.n_params * 4 / 2 ** 20, "grad_owned": enc.owned}
    return Case(run, _hash_work(p), info)


# Peer-vs-clrf agreement on the hash encoding: both float32 sums of 8 products (forward) and of
# the same scatters in another order (backward): tolerances of clrf/testing/tolerances.py
# HASH_ATOL and HASH_GRAD_* relative to the largest gradient.
PEER_HASH_ATOL = 3e-6
PEER_HASH_GRAD_REL = 1e-5


@factory("peer.taichi_hash")
def _peer_taichi_hash(ctx, p):
    try:
        from peers import taichi_hash
    except ImportError as e:
        raise Skip(f"taichi peer unavailable: {e}") from None
    enc, table, x, genc = _hash_inputs(ctx, p)
    peer = taichi_hash.TaichiHash(x, table, enc.res_host, enc.lo, enc.inv_ext, genc)
    q = ctx.dev.queue
    xd = cla.to_device(q, x)
    ref_out = enc.forward(xd).get()
    check = {"enc": _compare(peer.forward(), ref_out, PEER_HASH_ATOL, 0.0)}
    mode = p.get("mode", "fwd")
    if mode != "fwd":
        enc.grad.fill(np.float32(0))
        enc.backward(xd, cla.to_device(q, genc))
        g = enc.grad.get()
        scale = max(1e-30, float(np.abs(g).max()))
        check["grad"] = _compare(peer.forward_backward(), g, PEER_HASH_GRAD_REL * scale + 3e-6,
                                 0.0)
    check["ok"] = all(v["ok"] for v in check.values() if isinstance(v, dict))
    if not check["ok"]:
        raise Skip(f"peer disagrees with clrf, not timed: {check}")
    run = peer.forward if mode == "fwd" else peer.forward_backward
    return Case(run, _hash_work(p), {"peer": peer.describe()}, check)


# ---- Gaussian-splatting rasteriser (cl/splat_raster.cl) and its Taichi peer -------------------
# Model flop per (pixel, Gaussian) pair, counted from cl/splat_raster.cl (exp and fmin count as
# one each, an atomic add as one add): evaluating alpha (offset 2, power 9, exp, o G, clamp) =
# 14; compositing an entry in the forward (new T 2, colour 7) = 9; its backward (T recovered 2,
# colour behind 3 + 10, dL/dalpha 6, colour gradient 1 + 6, opacity 2, dL/dpower 1, xy 10, conic
# 11) = 52. The forward evaluates alpha up to and including the entry that stops the pixel (or
# to the end of the list), the backward for the pixel's n_contrib entries.
SPLAT_FLOP_ALPHA = 14
SPLAT_FLOP_BLEND = 9
SPLAT_FLOP_GRAD = 52
# Peer-vs-clrf agreement on the rasteriser, both float32 on identical splats and lists: the
# image and final transmittance within clrf/testing/tolerances.py SPLAT_LONG_ATOL (hundreds of
# entries per pixel), the gradients within 1e-4 of each array's largest entry (sums over up to
# thousands of pixels by float atomics in other orders; Taichi's default fast math may also
# contract a * b + c, which the kernels do not). Where the two exp's differ in the last bit, an
# entry can sit on the skip threshold (alpha = 1/255) or on the stopping rule in one and not in
# the other: up to PEER_SPLAT_FLIP_FRACTION of the pixels may differ in n_contrib (by one entry,
# alpha <= 1/255 x colour in rgb); rgb and T are compared on the others, and the gradients of
# both for dL/drgb zeroed on those pixels (every backward term is proportional to dL/drgb of
# its pixel, so the differing pixels then add nothing to either). Seen on the 20k /
# 400 x 400 case (PoCL CPU, Taichi 1.7.4): no n_contrib difference, rgb 3.6e-7, T 2.4e-7,
# gradients <= 2.2e-6 of the largest; a wrong sign, factor or skipped entry is >= 1e-3.
PEER_SPLAT_ATOL = 2e-5
PEER_SPLAT_GRAD_REL = 1e-4
PEER_SPLAT_FLIP_FRACTION = 1e-4
SPLAT_BACKGROUND = (1.0, 1.0, 1.0)


def _splat_scene(p):
    """n random 3D Gaussians (SH degree ``degree``) about the origin, screen standard deviations
    ~0.1-0.8 % of the width, and a width x height pinhole camera 3 units away looking at them
    (f = width px, ~53 degrees across): (float32 parameters, SplatCamera)."""
    from clrf.splat import SplatCamera
    rng = np.random.default_rng(p.get("seed", 5))
    n, deg = p["n"], p["degree"]
    g = {"means": rng.normal(0, 0.6, (n, 3)).astype(np.float32),
         "log_scales": rng.uniform(-4.5, -2.5, (n, 3)).astype(np.float32),
         "quats": rng.normal(size=(n, 4)).astype(np.float32),
         "opacity_logits": rng.uniform(-2, 2, n).astype(np.float32),
         "sh": rng.normal(0, 0.3, (n, (deg + 1) ** 2, 3)).astype(np.float32)}
    W, H = p["width"], p["height"]
    cam = SplatCamera(reference_splat.look_at((0.3, -0.2, -3.0), (0, 0, 0)).astype(np.float32),
                      float(W), float(W), W / 2, H / 2, W, H, 0.1)
    return g, cam


def _splat_pair_counts(sp, ids, ranges, n_contrib, width, height, tile):
    """(pixel, Gaussian) pairs of the rasteriser on these inputs, dict(forward: evaluated by
    the forward, composited, backward: evaluated by the backward = sum of n_contrib) and the
    pixels that stopped early, from the forward's n_contrib and alpha recomputed per tile in
    float32 (the entry that stops a pixel is the first non-skipped one after its last
    composited one)."""
    ntx = -(-width // tile)
    a_max, a_min = np.float32(reference_splat.ALPHA_MAX), np.float32(reference_splat.ALPHA_MIN)
    fwd = comp = stopped = 0
    for t in np.flatnonzero(ranges[:, 1] > ranges[:, 0]):
        ty, tx = divmod(int(t), ntx)
        py, px = np.meshgrid(np.arange(ty * tile, min((ty + 1) * tile, height)),
                             np.arange(tx * tile, min((tx + 1) * tile, width)), indexing="ij")
        px, py = px.ravel(), py.ravel()
        g = ids[ranges[t, 0]:ranges[t, 1]]
        centre = np.stack([px + 0.5, py + 0.5], 1).astype(np.float32)
        dx = sp["xy"][g, 0][None] - centre[:, :1]
        dy = sp["xy"][g, 1][None] - centre[:, 1:]
        A, B, C = (sp["conic"][g, k][None] for k in range(3))
        power = np.float32(-0.5) * (A * dx * dx + C * dy * dy) - B * dx * dy
        alpha = np.minimum(a_max, sp["opacity"][g][None] * np.exp(power))
        live = (power <= 0) & (alpha >= a_min)
        before = np.arange(g.size)[None] < n_contrib[py, px][:, None]
        comp += int(np.count_nonzero(live & before))
        after = live & ~before
        stops = after.any(1)
        stopped += int(np.count_nonzero(stops))
        fwd += int(np.where(stops, after.argmax(1) + 1, g.size).sum())
    return {"forward": fwd, "composited": comp, "backward": int(n_contrib.sum()),
            "stopped_pixels": stopped}


# (context, key, inputs) of the last set-up: the clrf cases and the peer's share one
_SPLAT_LAST: list = [None, None, None]


def _splat_inputs(ctx, p):
    """dict: the rasteriser, camera, clrf's projection and binning (device), dL/drgb (host and
    device), clrf's forward and backward outputs (numpy: the peer's reference), the splats and
    lists as numpy, and the work of one forward + backward. Built once per parameter set."""
    from clrf.splat import SplatRasterizer
    key = (id(ctx), p["n"], p["width"], p["height"], p["degree"], p.get("seed", 5))
    if _SPLAT_LAST[0] is ctx and _SPLAT_LAST[1] == key:
        return _SPLAT_LAST[2]
    _SPLAT_LAST[:] = [None, None, None]
    dev, q = ctx.dev, ctx.dev.queue
    g, cam = _splat_scene(p)
    r = SplatRasterizer(dev, p["degree"])
    proj = r.project(r.upload(g), cam)
    bins = r.bin(proj, cam)
    grad = np.random.default_rng(6).normal(0, 1, (cam.height, cam.width, 3)).astype(np.float32)
    grad_d = cla.to_device(q, grad)
    ras = r.rasterize(proj, bins, cam, SPLAT_BACKGROUND)
    g2d = r.rasterize_backward(proj, bins, ras, cam, grad_d, SPLAT_BACKGROUND)
    sp = {k: getattr(proj, k).get() for k in ("xy", "conic", "opacity", "color", "rect",
                                              "depth")}
    ids = bins.ids.get() if bins.n_pairs else np.zeros(0, np.int32)
    ranges = bins.ranges.get()
    out = {"r": r, "cam": cam, "proj": proj, "bins": bins, "grad": grad, "grad_d": grad_d,
           "sp": sp, "ids": ids, "ranges": ranges,
           "fwd": {"rgb": ras.rgb.get(), "T": ras.T.get(), "n_contrib": ras.n_contrib.get()},
           "bwd": {k: v.get() for k, v in g2d.items()}}
    out["pairs"] = _splat_pair_counts(sp, ids, ranges, out["fwd"]["n_contrib"], cam.width,
                                      cam.height, r.tile)
    _SPLAT_LAST[:] = [ctx, key, out]
    return out


def _splat_work(s, mode):
    """samples = the (pixel, Gaussian) pairs the forward evaluates; flop by the model above."""
    pr = s["pairs"]
    flop = pr["forward"] * SPLAT_FLOP_ALPHA + pr["composited"] * SPLAT_FLOP_BLEND
    if mode != "fwd":
        flop += pr["backward"] * SPLAT_FLOP_ALPHA + pr["composited"] * SPLAT_FLOP_GRAD
    return {"samples": pr["forward"], "flop": flop}


def _splat_info(s):
    H, W = s["cam"].height, s["cam"].width
    nc = s["fwd"]["n_contrib"]
    return {"gaussians": s["proj"].n,
            "visible": int(np.count_nonzero(s["proj"].radius.get() > 0)),
            "pixels": H * W, "tile_pairs": s["bins"].n_pairs, "pairs": s["pairs"],
            "mean_n_contrib": float(nc.mean()),
            "note": "samples = (pixel, Gaussian) pairs the forward evaluates; flop: model "
                    "(cases.py SPLAT_FLOP_*)"}


@factory("splat.raster")
def _splat_raster(ctx, p):
    """params: n Gaussians, width x height camera, SH degree, mode ('fwd' | 'fwdbwd': rasterize
    then rasterize_backward given a fixed dL/drgb, the gradient buffers allocated zeroed at
    every call as rasterize_backward does). Projection and binning are set-up, not timed.
    samples/s = (pixel, Gaussian) pairs the forward evaluates per second. At small sizes
    (<= 64 x 64 pixels) clrf is first checked against the float64 twin."""
    s = _splat_inputs(ctx, p)
    r, cam, proj, bins = s["r"], s["cam"], s["proj"], s["bins"]
    dev, mode = ctx.dev, p.get("mode", "fwd")
    check = None
    if cam.width * cam.height <= 64 * 64:
        ntx, nty = cam.tiles(r.tile)
        sp64 = {k: np.asarray(v, np.float64) for k, v in s["sp"].items()}
        lists = reference_splat.bin_gaussians(s["sp"]["rect"], s["sp"]["depth"], ntx, nty)
        want = reference_splat.rasterize(sp64, lists, cam.width, cam.height, SPLAT_BACKGROUND)
        check = {"rgb": _compare(s["fwd"]["rgb"], want["rgb"], tol.SPLAT_RASTER_ATOL, 0.0),
                 "T": _compare(s["fwd"]["T"], want["T"], tol.SPLAT_RASTER_ATOL, 0.0),
                 "n_contrib": {"ok": bool(np.array_equal(s["fwd"]["n_contrib"],
                                                         want["n_contrib"]))}}
        check["ok"] = all(v["ok"] for v in check.values())

    if mode == "fwd":
        def run():
            r.rasterize(proj, bins, cam, SPLAT_BACKGROUND)
            dev.finish()
    else:
        def run():
            ras = r.rasterize(proj, bins, cam, SPLAT_BACKGROUND)
            r.rasterize_backward(proj, bins, ras, cam, s["grad_d"], SPLAT_BACKGROUND)
            dev.finish()
    return Case(run, _splat_work(s, mode), _splat_info(s), check)


def _peer_splat_check(s, peer, mode):
    """The peer's forward (and backward) against clrf's on the set-up ``s`` (PEER_SPLAT_*)."""
    got, want = peer.forward(), s["fwd"]
    same = got["n_contrib"] == want["n_contrib"]
    flips = float(np.mean(~same))
    check = {"n_contrib": {"mismatch_fraction": flips, "ok": flips <= PEER_SPLAT_FLIP_FRACTION},
             "rgb": _compare(got["rgb"][same], want["rgb"][same], PEER_SPLAT_ATOL, 0.0),
             "T": _compare(got["T"][same], want["T"][same], PEER_SPLAT_ATOL, 0.0)}
    if mode == "fwd":
        return check
    ref = s["bwd"]
    if not same.all():   # dL/drgb zeroed on the pixels that differ, for clrf and the peer
        r, cam, bg = s["r"], s["cam"], SPLAT_BACKGROUND
        masked = np.where(same[..., None], s["grad"], np.float32(0.0))
        ras = r.rasterize(s["proj"], s["bins"], cam, bg)
        ref = {k: v.get() for k, v in r.rasterize_backward(
            s["proj"], s["bins"], ras, cam, cla.to_device(r.device.queue, masked), bg).items()}
        peer.grad_rgb = masked
    try:
        g = peer.backward()
    finally:
        peer.grad_rgb = s["grad"]
    for name, v in ref.items():
        scale = max(1e-30, float(np.abs(v).max(initial=0.0)))
        check[f"grad_{name}"] = _compare(g[name], v, PEER_SPLAT_GRAD_REL * scale, 0.0)
    return check


@factory("peer.taichi_splat")
def _peer_taichi_splat(ctx, p):
    """tools/peers/taichi_splat.py on clrf's projection and binning (identical inputs to
    ``splat.raster``), checked against clrf's outputs before it is timed; the same work."""
    try:
        from peers import taichi_splat
    except ImportError as e:
        raise Skip(f"taichi peer unavailable: {e}") from None
    s = _splat_inputs(ctx, p)
    sp, cam = s["sp"], s["cam"]
    peer = taichi_splat.TaichiSplat(sp["xy"], sp["conic"], sp["opacity"], sp["color"], s["ids"],
                                    s["ranges"], cam.width, cam.height, s["r"].tile,
                                    SPLAT_BACKGROUND, s["grad"])
    mode = p.get("mode", "fwd")
    check = _peer_splat_check(s, peer, mode)
    check["ok"] = all(v["ok"] for v in check.values() if isinstance(v, dict))
    if not check["ok"]:
        raise Skip(f"peer disagrees with clrf, not timed: {check}")
    run = peer.forward if mode == "fwd" else peer.forward_backward
    info = dict(_splat_info(s), peer=peer.describe())
    return Case(run, _splat_work(s, mode), info, check)
