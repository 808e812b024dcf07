"""Training cases: reductions, optimisers (cl/optim.cl), regularisers and structure changes
(cl/grid_ops.cl, cl/batch.cl)."""
from __future__ import annotations

import math

import numpy as np
import clrf
import clrf.training.metrics
import pyopencl.array as cla
from clrf.references import reference as ref

from .framework import (EXACT, GRAD, OPT, OPT_LONG, OPT_REL, REL, RENDER, UNIT, make_grid,
                        random_grid, random_rays, tol)


# ---- reductions --------------------------------------------------------------------------------
def reduce_case(run, fp64: bool, kind: str):
    """sum of squares / MSE / PSNR of n values near 0.5 with tiny differences (or O(1) ones),
    float32 inputs, against float64 numpy. The note gives a float32 running sum's error."""
    if fp64 and not run.device.caps.fp64:
        run.finite("skipped: device has no fp64", [0.0])
        return
    n = run.size(4 << 20, 16 << 20)
    a = (0.5 + 0.01 * run.rng.standard_normal(n)).astype(np.float32)
    if kind == "tiny":
        b = (a + 1e-4 * run.rng.standard_normal(n)).astype(np.float32)
    else:
        b = run.rng.random(n).astype(np.float32)
    q = run.device.queue
    A, B = cla.to_device(q, a), cla.to_device(q, b)
    diff = a.astype(np.float64) - b.astype(np.float64)
    want = float(np.dot(diff, diff))
    got = clrf.training.metrics.sum_squares(run.device, A, B, fp64=fp64)
    naive = float(np.cumsum(((a - b) ** 2).astype(np.float32), dtype=np.float32)[-1])
    rt = tol("STAB_ZERO_ATOL", "STAB_REDUCE_FP64_RTOL" if fp64 else "STAB_REDUCE_F32C_RTOL")
    run.compare(f"sum_squares n={n}", [got], [want], rt,
                note=f"float32 running sum rel. error {abs(naive - want) / want:.1e}")
    run.compare("mse", [clrf.training.metrics.mse(run.device, A, B, fp64=fp64)], [want / n], rt)
    run.compare("psnr (dB)", [clrf.training.metrics.psnr(run.device, A, B, fp64=fp64)],
                [10 * math.log10(n / want)], tol("STAB_PSNR_ATOL"))
    run.compare("identical -> 0", [clrf.training.metrics.sum_squares(run.device, A, A, fp64=fp64)], [0.0],
                EXACT)


# ---- optimiser (cl/optim.cl) -------------------------------------------------------------------
LR = 0.1    # learning rate of the optimiser cases (STAB_OPT_ATOL is written for it)
F32_BETA = float(np.float32(0.95))   # the kernel's float32 beta, given to the float64 twin too
FLT_MAX = float(np.finfo(np.float32).max)


def _opt(run, mode, p0, s0=None, eps=1e-8):
    from clrf.runtime.optim import Optimizer
    q = run.device.queue
    p = cla.to_device(q, np.ascontiguousarray(p0, np.float32))
    st = None if s0 is None else cla.to_device(q, np.ascontiguousarray(s0, np.float32))
    return Optimizer(run.device, p, mode=mode, beta=0.95, eps=eps, state=st)


def _opt_step(run, opt, g, touched, lr=LR):
    q = run.device.queue
    opt.grad.set(np.ascontiguousarray(g, np.float32))
    t = cla.to_device(q, np.ascontiguousarray(touched, np.uint8))
    opt.step(t, lr, clear_touched=True)
    return t.get()


def _twin(p, g, s, touched, lr=LR, mode="rmsprop", eps=1e-8):
    return ref.update_rows(p, np.asarray(g, np.float32), s, touched, float(np.float32(lr)),
                           beta=F32_BETA, eps=float(np.float32(eps)), mode=mode)


def opt_zero_grad(run, mode):
    """Touched rows with zero (and NaN, skipped the same way) gradients: parameters and state
    unchanged bit for bit (state 0 stays 0: no 0/(sqrt(0) + eps) update), gradients reset to 0,
    touched flags cleared."""
    n, D = 64, 4
    p0 = run.rng.normal(size=(n, D)).astype(np.float32)
    s0 = np.where(run.rng.random((n, D)) < 0.5, 0.0, run.rng.uniform(0.1, 2, (n, D)))
    opt = _opt(run, mode, p0, s0)
    for k in range(3):
        g = np.where(run.rng.random((n, D)) < 0.5, np.nan, 0.0) if k == 2 else np.zeros((n, D))
        t = _opt_step(run, opt, g, np.ones(n))
    run.compare("params unchanged", opt.param.get(), p0, EXACT)
    run.compare("state unchanged (zeros stay 0)", opt.state.get(), s0.astype(np.float32), EXACT)
    run.compare("grad buffer 0, touched cleared", np.concatenate([opt.grad.get().ravel(), t]),
                0.0, EXACT)


def opt_huge_grad(run, mode):
    """Gradients 1e20, 1e38, -1e38, +-FLT_MAX, +-inf (clamped to +-1e18 = GRAD_CLAMP; plus 1 and
    -3e-3): params and state finite; RMSProp's first and second steps are -lr sign(g) for the
    huge ones (state 1e36); SGD moves by lr * 1e18. Against the float64 twin (same clamp)."""
    g = np.array([1e18, 1e20, 1e38, -1e38, FLT_MAX, -FLT_MAX, np.inf, -np.inf, 1.0, -3e-3],
                 np.float32)[:, None]
    n = len(g)
    p0 = run.rng.normal(size=(n, 1)).astype(np.float32)
    opt = _opt(run, mode, p0)
    p, s = p0.astype(np.float64), np.zeros((n, 1))
    for k in range(2):
        _opt_step(run, opt, g, np.ones(n))
        p, s = _twin(p, g, s, np.ones(n), mode=mode)
        run.compare(f"step {k + 1} params vs twin", opt.param.get(), p,
                    OPT if mode == "rmsprop" else tol("STAB_ZERO_ATOL", "STAB_OPT_RTOL"))
        run.finite(f"step {k + 1} params, state finite", opt.param.get(), opt.state.get())
    if mode == "rmsprop":
        gc = np.clip(g.astype(np.float64), -1e18, 1e18)
        run.compare("two steps = -2 lr g / (|g| + eps) (= -2 lr sign(g) for huge g)",
                    opt.param.get(), p0 - 2 * float(np.float32(LR)) * gc / (np.abs(gc) + 1e-8),
                    OPT)
        run.compare("state = 1e36 (clamped g^2)", opt.state.get()[:8], 1e36,
                    tol("STAB_ZERO_ATOL", "STAB_OPT_RTOL"))


def opt_tiny_grad(run):
    """Gradients 1e-20 .. 1e-45 (g^2 subnormal or 0 in float32) on a first touch, eps 1e-8 and
    0: the step is lr g / (|g| + eps) as in the float64 twin (+-lr exactly for eps = 0, no
    g / 0). A state that underflowed to 0 makes the next touch a first touch again (the twin
    keeps s = g^2 ~ 1e-60 there and would step 4.5 lr = lr / sqrt(1 - beta) for g = 1): that
    rule, not the twin, is checked for the second step."""
    g = np.array([1e-20, -1e-20, 1e-25, 1e-30, -1e-30, 1e-38, 1e-40, -1e-45, 1.0, -0.25],
                 np.float32)[:, None]
    n = len(g)
    for eps in (1e-8, 0.0):
        p0 = np.zeros((n, 1), np.float32)
        opt = _opt(run, "rmsprop", p0, eps=eps)
        _opt_step(run, opt, g, np.ones(n))
        p, s = _twin(p0, g, np.zeros((n, 1)), np.ones(n), eps=eps)
        run.compare(f"eps {eps:g}: first step vs twin", opt.param.get(), p, OPT_REL)
        g2 = np.ones((n, 1), np.float32)
        before = opt.param.get().astype(np.float64)
        s1 = opt.state.get().astype(np.float64)    # g^2 in float32 (0 where it underflowed)
        _opt_step(run, opt, g2, np.ones(n))
        s_new = np.where(s1 == 0, 1.0, F32_BETA * s1 + (1 - F32_BETA))
        run.compare(f"eps {eps:g}: second step (g = 1) vs the rule on the float32 state",
                    opt.param.get(), before - np.float32(LR) / (np.sqrt(s_new) + eps), OPT,
                    note=f"{int(np.sum(s1 == 0))} of {n} states underflowed to 0")
        run.finite(f"eps {eps:g}: params, state finite", opt.param.get(), opt.state.get())


def opt_eps_state0(run):
    """eps in {0, 1e-8, 1e-3, 1} with state 0 and |g| log-uniform in 1e-6..1e6: first step
    lr g / (|g| + eps), second step the RMS rule; against the float64 twin."""
    n = 256
    g = (run.rng.choice([-1, 1], (n, 1)) * 10.0 ** run.rng.uniform(-6, 6, (n, 1))).astype(
        np.float32)
    for eps in (0.0, 1e-8, 1e-3, 1.0):
        p0 = run.rng.normal(size=(n, 1)).astype(np.float32)
        opt = _opt(run, "rmsprop", p0, eps=eps)
        p, s = p0.astype(np.float64), np.zeros((n, 1))
        for k in range(2):
            gk = g if k == 0 else (g * run.rng.uniform(0.1, 10, (n, 1))).astype(np.float32)
            _opt_step(run, opt, gk, np.ones(n))
            p, s = _twin(p, gk, s, np.ones(n), eps=eps)
            run.compare(f"eps {eps:g} step {k + 1} params", opt.param.get(), p, OPT)
            run.compare(f"eps {eps:g} step {k + 1} state", opt.state.get(), s,
                        tol("STAB_ZERO_ATOL", "STAB_OPT_RTOL"))


def opt_long_sparse(run, mode):
    """Long run of sparse updates: each step touches a random 1% of 2000 rows (D = 4) with
    gradients of random sign and magnitude 1e-3..1e3 (10% exact zeros), lr from expon_lr
    (1e-1 -> 1e-3); the kernel and the float64 twin run in lockstep from the same inputs."""
    from clrf.runtime.optim import expon_lr
    n, D = 2000, 4
    steps = run.size(300, 2000)
    p0 = run.rng.normal(size=(n, D)).astype(np.float32)
    opt = _opt(run, mode, p0)
    p, s = p0.astype(np.float64), np.zeros((n, D))
    worst = 0.0
    ever = np.zeros((n, D), bool)
    touches = np.zeros((n, D), int)
    for k in range(steps):
        touched = run.rng.random(n) < 0.01
        g = np.zeros((n, D), np.float32)
        m = int(touched.sum())
        gt = run.rng.choice([-1, 1], (m, D)) * 10.0 ** run.rng.uniform(-3, 3, (m, D))
        gt[run.rng.random((m, D)) < 0.1] = 0.0
        g[touched] = gt
        ever |= touched[:, None] & (g != 0)
        touches += touched[:, None] & (g != 0)
        lr = expon_lr(k, 1e-1, 1e-3, steps)
        _opt_step(run, opt, g, touched, lr)
        p, s = _twin(p, g, s, touched, lr, mode=mode)
        if k % 100 == 99:
            worst = max(worst, float(np.abs(opt.param.get() - p).max() / np.abs(p).max()))
    got = opt.param.get()
    pmax = float(np.abs(p).max())
    run.compare(f"{steps} steps params vs twin (normwise)", got, p, OPT_LONG, scale=pmax,
                note=f"max |param| {pmax:.2g}; up to {touches.max()} updates per entry; worst "
                     f"normwise error at any 100th step {worst:.1e}")
    run.compare("never-touched entries unchanged", got[~ever], p0[~ever], EXACT)
    if mode == "rmsprop":
        run.compare(f"{steps} steps state vs twin", opt.state.get(), s,
                    tol("STAB_ZERO_ATOL", "STAB_OPT_LONG_STATE_RTOL"))
        run.compare("state 0 where never touched with g != 0", opt.state.get()[~ever], 0.0,
                    EXACT)
    run.finite("params, state, grad finite", got, opt.state.get(), opt.grad.get())
    run.compare("grad buffer all 0 after the run", opt.grad.get(), 0.0, EXACT)


# ---- regularisers (cl/grid_ops.cl tv_grad) -----------------------------------------------------
def _tv(run, data, alloc, scale, empty_is_zero, lam=0.0, start=0, n_cells=None):
    """Kernel and twin TV (+ sparsity) gradients of density ([X,Y,Z]) or SH ([X,Y,Z,C]) data,
    both dense [X,Y,Z,D]; the kernel's touched flags as a dense bool mask."""
    from clrf.grid import ops as grid_ops
    data = np.asarray(data, np.float32)
    shape = alloc.shape
    dens = data if data.ndim == 3 else np.zeros(shape, np.float32)
    sh = data if data.ndim == 4 else np.zeros(shape + (3,), np.float32)
    g = clrf.SparseGrid.from_dense(run.device, dens * alloc, sh * alloc[..., None], UNIT,
                                   mask=alloc)
    param = g.density if data.ndim == 3 else g.sh
    grad = cla.zeros_like(param)
    touched = cla.zeros(run.device.queue, param.shape[0], np.uint8)
    n_cells = alloc.size if n_cells is None else n_cells
    grid_ops.tv_grad(g, param, grad, touched, start, n_cells, scale, empty_is_zero, lam)
    want = ref.tv_grad(alloc, (data * (alloc if data.ndim == 3 else alloc[..., None])), start,
                       n_cells, scale, empty_is_zero, lam)
    gr = grad.get()
    links = g.links.get()
    got = np.zeros(want.shape, np.float32)
    got[alloc] = gr.reshape(gr.shape[0], -1)[links[alloc]]
    tch = np.zeros(shape, bool)
    tch[alloc] = touched.get()[links[alloc]] == 1
    return got, want, tch


TV_BOUND = 3 + math.sqrt(3)   # |grad| per cell <= scale (sqrt 3 own term + 3 neighbour terms)


def tv_flat(run):
    """Flat regions (all allocated neighbours equal; outside / unallocated count as the cell
    itself) at values 0, 1e-30, 1, 1e30, -1e30: gradient exactly 0, not d / sqrt(eps) noise."""
    shape = (4, 5, 6)
    for v in (0.0, 1e-30, 1.0, 1e30, -1e30):
        alloc = run.rng.random(shape) < 0.7
        data = np.full(shape, v, np.float32)
        got, _, _ = _tv(run, data, alloc, 1.0, False)
        run.compare(f"density {v:g}, holes (empty = self): grad == 0", got, 0.0, EXACT)
        got, _, _ = _tv(run, np.full(shape + (12,), v, np.float32), alloc, 1.0, False)
        run.compare(f"SH {v:g}, holes: grad == 0", got, 0.0, EXACT)
        got, _, _ = _tv(run, data, np.ones(shape, bool), 1.0, True)
        run.compare(f"density {v:g}, dense, empty_is_zero: grad == 0", got, 0.0, EXACT)


def tv_step_edge(run):
    """A step edge of height h in {1e-6, 1, 1e10} across x: gradient vs the float64 twin
    (normwise, in units of scale), non-zero only next to the edge, |grad| <= scale (3+sqrt 3)."""
    shape = (6, 4, 5)
    scale = 0.5
    for h in (1e-6, 1.0, 1e10):
        data = np.zeros(shape, np.float32)
        data[3:] = h
        alloc = np.ones(shape, bool)
        got, want, _ = _tv(run, data, alloc, scale, False)
        run.compare(f"h {h:g} vs twin", got, want, GRAD, scale=scale)
        run.compare(f"h {h:g}: 0 away from the edge", np.concatenate(
            [got[:2].ravel(), got[4:].ravel()]), 0.0, EXACT)
        run.compare(f"h {h:g}: within bound scale (3 + sqrt 3)",
                    [max(float(np.abs(got).max()) - scale * TV_BOUND, 0.0)], [0.0], EXACT)


def tv_missing_neighbours(run):
    """Half the voxels unallocated (empty_is_zero true and false), windows that wrap, grids
    whose neighbours are mostly outside (1x1x1, 1xNxN, Nx1x1): vs the float64 twin; every cell
    that got a gradient is touched; a 1x1x1 grid has no TV gradient at all."""
    for shape in ((6, 5, 4), (1, 6, 6), (7, 1, 1), (1, 1, 1)):
        alloc = run.rng.random(shape) < (0.5 if min(shape) > 1 else 0.8)
        alloc.flat[0] = True
        for eiz in (True, False):
            data = run.rng.uniform(0.1, 2.0, shape + (3,)).astype(np.float32)
            start = int(run.rng.integers(0, alloc.size))
            got, want, tch = _tv(run, data, alloc, 0.7, eiz, start=start,
                                 n_cells=max(1, alloc.size // 2))
            tag = f"{'x'.join(map(str, shape))} empty_is_zero={eiz}"
            run.compare(f"{tag} vs twin", got, want, GRAD)
            nz = np.any(want != 0, axis=-1)
            run.compare(f"{tag}: cells with gradient touched", [float(np.sum(nz & ~tch))], [0.0],
                        EXACT)
            if shape == (1, 1, 1):
                run.compare(f"{tag}: no neighbours -> 0", got, 0.0, EXACT)


def tv_huge_values(run, big):
    """Density / SH values +-big (and 0, big/2): differences |d| up to 2 big; d^2 overflows
    float32 above 1.8e19. Against the float64 twin (normwise, units of scale), finite, bounded;
    for big = 3e38 the difference itself overflows (clamped to +-FLT_MAX): finite and bounded
    only, the direction is approximate."""
    shape = (5, 4, 6)
    scale = 0.5
    for which in ("density", "sh"):
        tail = () if which == "density" else (3,)
        data = (run.rng.choice([-1.0, -0.5, 0.0, 0.5, 1.0], shape + tail) * big).astype(
            np.float32)
        alloc = run.rng.random(shape) < 0.8
        for eiz in (True, False):
            got, want, _ = _tv(run, data, alloc, scale, eiz)
            tag = f"{which} empty_is_zero={eiz}"
            if big < FLT_MAX / 2:
                run.compare(f"{tag} vs twin", got, want, GRAD, scale=scale)
            run.finite(f"{tag} finite", got)
            run.compare(f"{tag} within bound scale (3 + sqrt 3)",
                        [max(float(np.abs(got).max()) - scale * TV_BOUND * (1 + 1e-6), 0.0)],
                        [0.0], EXACT)


def sparsity(run):
    """Cauchy sparsity gradient lambda 4 sigma / (1 + 2 sigma^2) at sigma in {0, +-1e-30, 1,
    1e19, 1.5e19 (2 sigma^2 overflows), 1e30, -1e30, 3e38, -3e38}, lambda 1e-10 and 1 (TV scale
    0 so only the prior acts): finite, against the float64 twin (the exact value is <= 2 lambda /
    sigma there, so a 0 from the overflow is within GRAD_ATOL)."""
    sig = np.array([0.0, 1e-30, -1e-30, 1.0, -1.0, 0.7071, 1e19, 1.5e19, 1e30, -1e30, 3e38,
                    -3e38], np.float32)
    shape = (len(sig), 1, 1)
    alloc = np.ones(shape, bool)
    for lam in (1e-10, 1.0):
        got, want, _ = _tv(run, sig.reshape(shape), alloc, 0.0, True, lam=lam)
        run.compare(f"lambda {lam:g} vs twin (units of lambda)", got, want, GRAD, scale=lam)
        run.finite(f"lambda {lam:g} finite", got)


def beta_prior(run):
    """The beta prior beta_scale [log(T + 1e-3) + log(1 - T + 1e-3)] fused into training's
    backward (GRAD_MODE 1), on rays ending at T = 1 (zero density), T ~ 1 - 1e-7, T ~ 0.5 and
    T below T_STOP (density 1e30): gradients finite and equal to the float64 reference."""
    from clrf.grid.render import render_backward_device
    q = run.device.queue
    o = np.array([[0.5, 0.5, -1.0]] * 3, np.float32)
    d = np.array([[0, 0, 1.0], [0.1, 0.05, 1.0], [-0.1, 0.1, 1.0]], np.float32)
    for sigma in (0.0, 1e-7, 0.7, 1e4, 1e30):
        dens = np.full((2, 2, 2), sigma, np.float32)
        sh = np.full((2, 2, 2, 3), 0.1, np.float32)
        g = make_grid(run, dens, sh, UNIT, mask=np.ones((2, 2, 2), bool))
        target = np.full((3, 3), 0.3, np.float32)
        gd, gs = cla.zeros_like(g.density), cla.zeros_like(g.sh)
        for lam in (1e-3, 1.0):
            gd.fill(0)
            gs.fill(0)
            render_backward_device(g, cla.to_device(q, o), cla.to_device(q, d),
                                   cla.to_device(q, target), 0.5, (1, 1, 1), gd, gs,
                                   grad_mode=1, loss_scale=0.0, beta_scale=lam)
            f = ref.render_forward(dens, sh, UNIT, o, d, 0.5, (1, 1, 1))
            r = ref.render_backward(dens, sh, UNIT, o, d, np.zeros((3, 3)), 0.5, (1, 1, 1),
                                    mask=np.ones((2, 2, 2), bool),
                                    grad_T=ref.beta_grad_T(1 - f["acc"], lam))
            kd, _ = g.rows_to_dense(gd.get(), gs.get())
            run.finite(f"sigma {sigma:g} lambda {lam:g} finite", kd)
            scale = max(1.0, float(np.abs(r["density"]).max()))
            run.compare(f"sigma {sigma:g} lambda {lam:g} density grad vs ref", kd, r["density"],
                        GRAD, scale=scale)


# ---- structure changes (cl/grid_ops.cl resample / prune, cl/batch.cl) --------------------------
def _resample_check(run, label, dens, sh, keep, new_reso, scale=1.0):
    from clrf.grid import ops as grid_ops
    alloc = (dens != 0) | np.any(sh != 0, axis=-1) | keep
    g = make_grid(run, dens, sh, UNIT, mask=alloc)
    links = g.links.get()
    kr = np.zeros(g.density.shape[0], np.uint8)
    kr[links[keep & alloc]] = 1
    g2 = grid_ops.resample(g, new_reso, cla.to_device(run.device.queue, kr))
    d_ref, s_ref, a_ref = ref.resample(dens * alloc, sh * alloc[..., None], keep & alloc,
                                       new_reso)
    d2, s2 = g2.to_dense()
    run.compare(f"{label} allocation == twin", (g2.links.get() >= 0).astype(float),
                a_ref.astype(float), EXACT)
    run.compare(f"{label} density vs twin", d2, d_ref, RENDER, scale=scale)
    run.compare(f"{label} sh vs twin", s2, s_ref, RENDER, scale=scale)
    run.finite(f"{label} finite", d2, s2)
    return g2


def prune_to_nothing(run):
    """Pruning every row: a grid with 0 rows (one padding row), then resampled to other
    resolutions (still 0 rows), TV and an optimiser step on it (no-ops), rendered (background)."""
    from clrf.grid import ops as grid_ops
    from clrf.runtime.optim import Optimizer
    R = run.size(6, 16)
    dens, sh = random_grid(run.rng, (R, R, R), degree=1, dens=2.0)
    g = make_grid(run, dens, sh)
    q = run.device.queue
    empty = grid_ops.prune(g, cla.zeros(q, g.density.shape[0], np.float32), 1e30)
    up = grid_ops.resample(empty, (2 * R, R + 1, 3))
    down = grid_ops.resample(empty, (1, 1, 1))
    run.compare("rows after prune / upsample / downsample",
                [empty.n_rows, up.n_rows, down.n_rows], [0, 0, 0], EXACT)
    run.compare("links all -1", np.concatenate([x.links.get().ravel() for x in (empty, up, down)]),
                -1.0, EXACT)
    grad = cla.zeros_like(empty.density)
    touched = cla.zeros(q, empty.density.shape[0], np.uint8)
    grid_ops.tv_grad(empty, empty.density, grad, touched, 0, R ** 3, 1.0, True, 1.0)
    opt = Optimizer(run.device, empty.density)
    opt.grad.set(np.full(opt.grad.shape, 5.0, np.float32))
    opt.step(touched, 0.1, True)
    run.compare("TV + optimiser on the empty grid: no touch, no change",
                np.concatenate([touched.get().astype(float), empty.density.get()]), 0.0, EXACT)
    o, d = random_rays(run.rng, 16)
    out = clrf.render_rays(up, o, d, 0.5, (0.3, 0.5, 0.7))
    run.compare("render == background", out["rgb"], np.broadcast_to(
        np.float32([0.3, 0.5, 0.7]), out["rgb"].shape), EXACT)


def single_voxel_upsample(run):
    """A 1x1x1 grid upsampled to 64^3 (quick: 32^3): every new voxel takes the one value
    (clamped interpolation), allocation and values as the twin; and back down to 1^3."""
    from clrf.grid import ops as grid_ops
    R = run.size(32, 64)
    dens = np.full((1, 1, 1), 2.5, np.float32)
    sh = run.rng.normal(size=(1, 1, 1, 12)).astype(np.float32)
    g2 = _resample_check(run, f"1 -> {R}^3", dens, sh, np.ones((1, 1, 1), bool), (R, R, R))
    d2, s2 = g2.to_dense()
    run.compare(f"{R}^3 all equal to the voxel", d2, 2.5, REL)
    g3 = grid_ops.resample(g2, (1, 1, 1))
    run.compare(f"{R}^3 -> 1 back to the voxel", g3.to_dense()[0], 2.5, REL)


def resample_huge(run):
    """Densities and SH of +-1e30 (and one-signed 3e38, next to FLT_MAX) interpolated up and
    down: finite, against the twin normwise (units of the value size)."""
    shape = (4, 5, 3)
    for big, signs in ((1e30, (-1.0, 0.3, 1.0)), (3e38, (0.5, 1.0))):
        dens = (run.rng.choice(signs, shape) * big).astype(np.float32)
        sh = (run.rng.choice(signs, shape + (3,)) * big).astype(np.float32)
        keep = run.rng.random(shape) < 0.8
        for nr in ((8, 10, 6), (2, 3, 2), (5, 7, 9)):
            _resample_check(run, f"{big:g} -> {nr}", dens, sh, keep, nr, scale=big)


def flat_grid_upsample(run):
    """Degenerate 1xNxN (and Nx1xN) grids upsampled (x2, and 1 -> 4 along the flat axis) and
    downsampled: against the twin, finite."""
    N = run.size(6, 24)
    for shape in ((1, N, N), (N, 1, N)):
        dens, sh = random_grid(run.rng, shape, degree=1, dens=2.0)
        keep = run.rng.random(shape) < 0.9
        up = tuple(2 * s for s in shape)
        thick = tuple(4 if s == 1 else s for s in shape)
        down = tuple(max(1, s // 3) for s in shape)
        for nr in (up, thick, down):
            _resample_check(run, f"{shape} -> {nr}", dens, sh, keep, nr)


def batch_extremes(run):
    """Batch indices for 1, 2, 3 and 2^18 + 3 source rays, seeds 0, 2^32 - 1 and a large odd
    one: exactly the twin's, all in range; a 1-ray source gives only index 0."""
    from clrf.training.trainer import RayStore
    for n_src in (1, 2, 3, (1 << 18) + 3):
        src = run.rng.random((n_src, 3)).astype(np.float32)
        store = RayStore(run.device, src, src, src)
        for seed in (0, 0xFFFFFFFF, 0x9E3779B9):
            n = run.size(4099, 65537)
            _, _, _, idx = store.batch(seed=seed, n=n)
            idx = idx.get()
            run.compare(f"n_src {n_src} seed {seed:#x} == twin", idx,
                        ref.batch_indices(seed, n, n_src), EXACT)
            run.compare(f"n_src {n_src} seed {seed:#x} in range",
                        [float(np.sum((idx < 0) | (idx >= n_src)))], [0.0], EXACT)
