"""Hash-grid model cases (cl/hash.cl, cl/hash_occ.cl, clrf/hash/): tiny tables, levels finer
than any image, saturated densities, rays that leave every occupied cell, an empty occupancy
grid, 1e-8 gradients in fp32 tables, contracted rays a million box sizes long. Outputs and losses must stay finite; where a float64 twin
exists the kernels are held to it."""
from __future__ import annotations

import numpy as np
import pyopencl.array as cla

from .framework import EXACT, OPT, RENDER, tol

HASH = tol("HASH_ATOL")
HASH_GRAD = tol("HASH_GRAD_ATOL", "HASH_GRAD_RTOL")
BOX = np.array([[-1.0, -1.0, -1.0], [1.0, 1.0, 1.0]])
BG = np.float32([0.2, 0.6, 0.9])     # the models' background, as the kernels hold it


def _up(run, a):
    return cla.to_device(run.device.queue, np.ascontiguousarray(a, np.float32))


def _encoding_vs_reference(run, levels, log2_t, n_min, n_max, genc_scale=1.0, label=""):
    from clrf.hash.encoding import HashEncoding
    from clrf.references import reference_hash as rh
    table = run.rng.uniform(-1, 1, (levels, 1 << log2_t, 2)).astype(np.float32)
    for slots in (0, 2):                # the atomic (GPU) and level-owned (CPU) backward
        dev = run.device.with_tuning(grad_slots=slots)
        enc = HashEncoding(dev, levels, 2, log2_t, n_min, n_max, BOX, table=table)
        n = run.size(65, 2000)
        x = run.rng.uniform(-1.2, 1.2, (n, 3)).astype(np.float32)
        got = enc.forward(_up(run, x)).get()
        run.compare(f"{label} forward vs float64 (slots {slots})", got,
                    rh.hash_forward(x, enc.lo, enc.inv_ext, enc.res_host, table), HASH)
        genc = (run.rng.uniform(-1, 1, (n, enc.dim)) * genc_scale).astype(np.float32)
        enc.backward(_up(run, x), _up(run, genc))
        want = rh.hash_backward(x, enc.lo, enc.inv_ext, enc.res_host, genc, enc.shape)
        run.compare(f"{label} backward vs float64 (slots {slots})", enc.grad.get(), want,
                    HASH_GRAD, scale=genc_scale)
        run.finite(f"{label} finite (slots {slots})", got, enc.grad.get())


def hash_tiny_tables(run):
    """T = 2 and T = 16: every level collides everywhere; forward and backward vs float64."""
    for log2_t in (1, 4):
        _encoding_vs_reference(run, 6, log2_t, 4, 256, label=f"T=2^{log2_t}")


def hash_levels_finer_than_images(run):
    """N_max = 65536 (a 100-pixel image resolves ~100 cells): fine levels hashed into 2^10 rows;
    forward and backward still the reference, finite."""
    _encoding_vs_reference(run, 8, 10, 16, 65536, label="N_max 65536")


def hash_tiny_table_gradients(run):
    """dL/denc of 1e-8 (and 1e-30): table gradients vs float64 relative to their size, and Adam
    with eps 1e-15 moves an fp32 table entry by ~lr from a 1e-8 gradient (float64 twin)."""
    _encoding_vs_reference(run, 4, 8, 4, 64, genc_scale=1e-8, label="|g| 1e-8")
    from clrf.runtime.optim import Optimizer
    n = 64
    p = run.rng.uniform(-1e-4, 1e-4, n)
    g = run.rng.choice([-1.0, 1.0], n) * 10.0 ** run.rng.uniform(-9, -7, n)
    pd, gd = _up(run, p), _up(run, g)
    opt = Optimizer(run.device, pd, "adam", beta=0.9, beta2=0.99, eps=1e-15, grad=gd)
    opt.step(None, 1e-2, t=1)
    g32 = g.astype(np.float32).astype(np.float64)
    m, v = 0.1 * g32, 0.01 * g32 * g32
    want = p.astype(np.float32) - 1e-2 * (m / 0.1) / (np.sqrt(v / 0.01) + 1e-15)
    run.compare("Adam step from |g| 1e-9..1e-7 vs float64", pd.get(), want, OPT)
    run.finite("Adam state finite", opt.state.get(), opt.state2.get())


def _model(run, **over):
    from clrf.hash.config import HashConfig
    from clrf.hash.model import HashModel
    cfg = HashConfig.from_preset("tiny", levels=4, log2_table=10, min_res=4, max_res=64,
                                 width=16, color_width=16, samples=32, occ_res=8,
                                 occ_points=256, batch_rays=64, occ_warmup=10 ** 6, **over)
    return HashModel(run.device, cfg, near=1.0, far=5.0, bbox=BOX,
                     background=tuple(float(b) for b in BG))


def _rays(run, n, aim=0.5):
    o = run.rng.normal(size=(n, 3))
    o *= 3.0 / np.linalg.norm(o, axis=1, keepdims=True)
    d = run.rng.uniform(-aim, aim, (n, 3)) - o
    return o.astype(np.float32), d.astype(np.float32)


def _step(run, model, o, d, target, label):
    loss = model.train_step(0, _up(run, o), _up(run, d), _up(run, target))
    run.finite(f"{label}: loss finite", np.array([loss]))
    run.finite(f"{label}: tables, MLP and their gradients finite", model.enc.table.get(),
               model.net.params.get(), model.enc.grad.get(), model.net.grad.get())
    return loss


def hash_density_saturation(run):
    """The density head's bias at 88.8 (exp overflows float32 past it), 1e4 and 1e30: softplus
    keeps sigma finite, the composite saturates (acc = 1 on rays through the box), and a
    training step keeps loss, parameters and gradients finite."""
    for bias in (88.8, 1e4, 1e30):
        model = _model(run)
        net = model.net
        p = net.params.get()
        p[net.layout.layers[net.spec.depth]["b_off"]] = bias     # sigma's bias (head row 0)
        net.set_params(p)
        o, d = _rays(run, run.size(32, 256), aim=0.2)
        out = model.render(o, d)
        run.finite(f"bias {bias:g}: render finite", out["rgb"], out["acc"], out["depth"])
        run.compare(f"bias {bias:g}: acc == 1", out["acc"], 1.0, RENDER)
        _step(run, model, o, d, np.full((len(o), 3), 0.5), f"bias {bias:g}")


def hash_rays_leave_occupied_cells(run):
    """One occupied cell in a corner, rays through the centre that miss it: every sample is
    dropped, the render is the background exactly, the loss finite, nothing updated."""
    model = _model(run)
    R = model.config.occ_res
    ema = np.zeros(R ** 3, np.float32)
    ema[0] = 1e3                                   # cell (0, 0, 0) only
    model.occ.ema.set(ema)
    model.occ._threshold(model.occupancy_threshold())
    o = np.tile(np.float32([[0.0, 0.0, 3.0]]), (16, 1))
    d = np.concatenate([run.rng.uniform(0.0, 0.1, (16, 2)), -np.ones((16, 1))], 1)
    out = model.render(o, d.astype(np.float32))
    run.compare("rgb == background", out["rgb"], np.tile(BG, (16, 1)), EXACT)
    before = model.enc.table.get()
    _step(run, model, o, d, np.full((16, 3), 0.5), "step")
    run.compare("table unchanged", model.enc.table.get(), before, EXACT)


def hash_empty_occupancy(run):
    """An occupancy grid emptied by an update (all densities below the threshold) renders the
    background, trains without NaN, and a fresh model (never measured) starts fully occupied."""
    model = _model(run, occ_tau=1e30)            # every measured cell is below the threshold
    run.compare("fresh grid fully occupied", model.occ.occupied_fraction(), 1.0, EXACT)
    model.update_occupancy(key=5)
    model.occ.ema.set(np.maximum(model.occ.ema.get(), 0.0))   # every cell measured
    model.occ._threshold(model.occupancy_threshold())
    run.compare("emptied grid occupied fraction", model.occ.occupied_fraction(), 0.0, EXACT)
    o, d = _rays(run, 24)
    out = model.render(o, d)
    run.compare("rgb == background", out["rgb"], np.tile(BG, (24, 1)), EXACT)
    _step(run, model, o, d, np.full((24, 3), 0.5), "step")


def hash_contracted_long_rays(run):
    """Unbounded scenes: rays from inside the box (axis-parallel ones included) out to 1e6 box
    half-sizes, bins even in log t from 1e-4: the encoding's points stay inside [-2, 2]^3
    against the float64 contraction, each bin's segment is its length (they tile
    [near, far]), and the render and a training step stay finite."""
    from clrf.hash.march import Contraction, march
    from clrf.references import reference_hash as rh
    model = _model(run, contract="on")
    model.near, model.far = 1e-4, 1e6
    n = run.size(16, 128)
    o = run.rng.uniform(-0.5, 0.5, (n, 3)).astype(np.float32)
    d = run.rng.normal(size=(n, 3)).astype(np.float32)
    d[:3] = np.eye(3, dtype=np.float32)                  # axis-parallel
    S = model.config.samples
    pk = march(run.device, model.occ, _up(run, o), _up(run, d), S, model.near, model.far,
               contract=model.contraction)
    xyz = pk.xyz.get()
    run.compare("every bin live (grid fresh)", np.array([pk.m]), np.array([n * S]), EXACT)
    run.finite("contracted points finite", xyz, pk.dt.get())
    run.compare("points inside [-2, 2]^3", np.array([np.abs(xyz).max() < 2.0]),
                np.array([True]), EXACT)
    _, t, dt, want, _ = rh.march_samples(o, d, S, model.near, model.far,
                                         np.ones(model.occ.n_cells, np.uint8),
                                         Contraction.BOX[0], np.full(3, 0.25),
                                         model.config.occ_res, centre=np.zeros(3),
                                         half=np.ones(3))
    run.compare("contracted points vs float64", xyz, want, tol("HASH_CONTRACT_RTOL"),
                scale=float(np.abs(want).max()))
    run.compare("segments tile [near, far]", np.array([pk.dt.get()[:S].sum(dtype=np.float64)]),
                np.array([model.far - model.near]), tol("HASH_CONTRACT_RTOL"),
                scale=model.far)
    out = model.render(o, d)
    run.finite("render finite", out["rgb"], out["acc"], out["depth"])
    _step(run, model, o, d, np.full((n, 3), 0.5), "step")
