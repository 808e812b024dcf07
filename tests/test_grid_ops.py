"""Optimiser, TV/sparsity, pruning, resampling and batch kernels against float64 numpy."""
import numpy as np
import pyopencl.array as cla
import pytest

import clrf
from clrf.grid import ops as grid_ops
from clrf.references import reference as ref
from clrf.runtime.optim import Optimizer, expon_lr

from clrf.testing.tolerances import FD_ATOL, FD_RTOL, GRAD_ATOL, GRAD_RTOL, RENDER_ATOL, RENDER_RTOL

BBOX = np.array([[-1.0] * 3, [1.0] * 3])


def sparse_grid(device, rng, shape, degree=1, empty_frac=0.3):
    C = 3 * (degree + 1) ** 2
    dens = rng.uniform(0.1, 2.0, shape).astype(np.float32)
    sh = rng.normal(0, 0.3, shape + (C,)).astype(np.float32)
    alloc = rng.random(shape) >= empty_frac
    dens[~alloc] = 0
    sh[~alloc] = 0
    return clrf.SparseGrid.from_dense(device, dens, sh, BBOX, mask=alloc), dens, sh, alloc


@pytest.mark.parametrize("mode", ["rmsprop", "sgd"])
def test_update_rows_vs_reference(device, mode):
    rng = np.random.default_rng(0)
    q = device.queue
    n, D = 37, 5
    p0 = rng.normal(size=(n, D)).astype(np.float32)
    g = rng.normal(size=(n, D)).astype(np.float32)
    g[3] = 0                       # touched row with a zero gradient: no update, state stays 0
    g[4, 0] = 1e30                 # huge gradient: clamped, finite
    s0 = np.where(rng.random((n, D)) < 0.5, 0, rng.uniform(0.1, 1, (n, D))).astype(np.float32)
    touched = (rng.random(n) < 0.6).astype(np.uint8)
    touched[3] = touched[4] = 1
    param = cla.to_device(q, p0)
    opt = Optimizer(device, param, mode=mode, state=cla.to_device(q, s0))
    opt.grad.set(g)
    tch = cla.to_device(q, touched)
    opt.step(tch, lr=0.1, clear_touched=True)
    p_ref, s_ref = ref.update_rows(p0, g, s0, touched, 0.1, mode=mode)
    np.testing.assert_allclose(param.get(), p_ref, rtol=1e-6, atol=1e-6)
    if mode == "rmsprop":
        np.testing.assert_allclose(opt.state.get()[~np.isinf(s_ref)], s_ref[~np.isinf(s_ref)],
                                   rtol=1e-6, atol=1e-30)
        assert np.all(opt.state.get()[3] == s0[3])
    assert np.all(np.isfinite(param.get()))
    # consumed gradients reset to zero, untouched ones kept
    gg = opt.grad.get()
    assert np.all(gg[touched == 1] == 0) and np.all(gg[touched == 0] == g[touched == 0])
    assert np.all(tch.get() == 0)


@pytest.mark.parametrize("mode", ["rmsprop", "sgd"])
def test_update_rows_live_columns(device, mode):
    """columns=(group, live): only the columns j % group < live step (the grid's SH band 0,
    grid.sh_diffuse_until); the others keep parameter and state, their gradient consumed."""
    rng = np.random.default_rng(1)
    q = device.queue
    n, D, cols = 23, 12, (4, 1)
    p0 = rng.normal(size=(n, D)).astype(np.float32)
    g = rng.normal(size=(n, D)).astype(np.float32)
    s0 = np.where(rng.random((n, D)) < 0.5, 0, rng.uniform(0.1, 1, (n, D))).astype(np.float32)
    touched = (rng.random(n) < 0.7).astype(np.uint8)
    param = cla.to_device(q, p0)
    opt = Optimizer(device, param, mode=mode, state=cla.to_device(q, s0))
    opt.grad.set(g)
    opt.step(cla.to_device(q, touched), lr=0.1, columns=cols)
    p_ref, s_ref = ref.update_rows(p0, g, s0, touched, 0.1, mode=mode, columns=cols)
    np.testing.assert_allclose(param.get(), p_ref, rtol=1e-6, atol=1e-6)
    np.testing.assert_allclose(opt.state.get(), s_ref, rtol=1e-6, atol=1e-30)
    dead = np.arange(D) % cols[0] >= cols[1]
    got = param.get()
    assert np.all(got[:, dead] == p0[:, dead]) and np.all(opt.state.get()[:, dead] == s0[:, dead])
    assert np.all(got[touched == 1][:, ~dead] != p0[touched == 1][:, ~dead])
    gg = opt.grad.get()
    assert np.all(gg[touched == 1] == 0) and np.all(gg[touched == 0] == g[touched == 0])
    with pytest.raises(ValueError, match="columns"):
        opt.step(cla.to_device(q, touched), lr=0.1, columns=(5, 1))


def test_update_rows_1d_and_first_step(device):
    q = device.queue
    p = cla.to_device(q, np.array([1.0, 2.0, 3.0], np.float32))
    opt = Optimizer(device, p)
    opt.grad.set(np.array([4.0, -0.5, 0.0], np.float32))
    opt.step(cla.to_device(q, np.ones(3, np.uint8)), lr=0.5, clear_touched=False)
    # RMSProp's first step is +-lr (state = g^2): 1 - 0.5, 2 + 0.5, untouched 3
    np.testing.assert_allclose(p.get(), [0.5, 2.5, 3.0], rtol=1e-6)


@pytest.mark.parametrize("eps", [1e-8, 0.0])
def test_rmsprop_first_step_tiny_and_huge_gradients(device, eps):
    """First touch: step = lr g / (|g| + eps), also where g^2 underflows float32 (|g| < 1e-19;
    with eps = 0 this used to be g / 0 = -inf) and where |g| is clamped (1e38 -> 1e18)."""
    q = device.queue
    g = np.array([1e-30, -1e-30, 1e-20, 1e-40, 3.0, -0.1234567, 1e20, 1e38, -1e38], np.float32)
    p = cla.to_device(q, np.zeros(g.size, np.float32))
    opt = Optimizer(device, p, eps=eps)
    opt.grad.set(g)
    opt.step(cla.to_device(q, np.ones(g.size, np.uint8)), lr=0.1, clear_touched=True)
    got = p.get()
    assert np.all(np.isfinite(got))
    gd = np.clip(g.astype(np.float64), -1e18, 1e18)
    want = -np.float32(0.1) * gd / (np.abs(gd) + eps)
    np.testing.assert_allclose(got, want, rtol=2e-7, atol=0)
    if eps == 0.0:
        np.testing.assert_array_equal(np.abs(got), np.float32(0.1))   # exactly +-lr


@pytest.mark.parametrize("mode", ["rmsprop", "sgd"])
def test_nan_gradient_is_skipped(device, mode):
    """A NaN gradient entry changes nothing (like 0) and is consumed; it used to be clamped to
    -1e18 (fmax(NaN, -C) = -C): RMSProp stepped +lr and set the state to 1e36, SGD moved the
    parameter by +1e17."""
    q = device.queue
    p = cla.to_device(q, np.ones((2, 2), np.float32))
    opt = Optimizer(device, p, mode=mode)
    opt.grad.set(np.array([[np.nan, 1.0], [np.nan, np.nan]], np.float32))
    opt.step(cla.to_device(q, np.ones(2, np.uint8)), lr=0.1, clear_touched=True)
    np.testing.assert_allclose(p.get(), [[1.0, 0.9], [1.0, 1.0]], rtol=1e-6)
    assert np.all(opt.state.get() == ([[0, 1], [0, 0]] if mode == "rmsprop" else 0))
    assert np.all(opt.grad.get() == 0)
    p_ref, _ = ref.update_rows(np.ones((2, 2)), np.array([[np.nan, 1.0], [np.nan, np.nan]]),
                               np.zeros((2, 2)), [1, 1], 0.1, mode=mode)
    np.testing.assert_allclose(p.get(), p_ref, rtol=1e-6)


def test_expon_lr_schedule():
    assert expon_lr(0, 1.0, 0.01, 100) == pytest.approx(1.0)
    assert expon_lr(100, 1.0, 0.01, 100) == pytest.approx(0.01)
    assert expon_lr(50, 1.0, 0.01, 100) == pytest.approx(0.1)
    assert expon_lr(0, 1.0, 0.01, 100, delay_steps=10, delay_mult=0.01) == pytest.approx(0.01)
    assert expon_lr(1000, 1.0, 0.01, 100) == pytest.approx(0.01)


@pytest.mark.parametrize("empty_is_zero,which", [(True, "density"), (False, "sh")])
@pytest.mark.parametrize("start,frac", [(0, 1.0), (37, 0.3), (200, 0.5)])
def test_tv_grad_vs_reference(device, empty_is_zero, which, start, frac):
    rng = np.random.default_rng(start)
    shape = (5, 6, 7)
    grid, dens, sh, alloc = sparse_grid(device, rng, shape)
    dens[2:4, 2:4, 2:4] = np.where(alloc[2:4, 2:4, 2:4], 0.7, 0)  # a flat patch
    grid = clrf.SparseGrid.from_dense(device, dens, sh, BBOX, mask=alloc)
    q = device.queue
    param = grid.density if which == "density" else grid.sh
    grad = cla.zeros_like(param)
    touched = cla.zeros(q, param.shape[0], np.uint8)
    n_cells = int(frac * dens.size)
    lam = 0.01 if which == "density" else 0.0
    grid_ops.tv_grad(grid, param, grad, touched, start, n_cells, 0.5, empty_is_zero, lam)
    data = dens if which == "density" else sh
    r = ref.tv_grad(alloc, data, start, n_cells, 0.5, empty_is_zero, lam)
    D = 1 if which == "density" else sh.shape[-1]
    gk = grid.rows_to_dense(grad.get().reshape(-1), np.zeros((grad.shape[0], 3), np.float32))[0] \
        if D == 1 else grid.rows_to_dense(np.zeros(grad.shape[0], np.float32), grad.get())[1]
    np.testing.assert_allclose(gk.reshape(r.shape), r, atol=GRAD_ATOL, rtol=GRAD_RTOL)
    assert np.abs(r).max() > 0.01
    assert np.all(np.isfinite(gk))
    # every row that got a gradient is marked touched
    links = grid.links.get()
    t = touched.get()
    nz = np.any(r.reshape(shape + (-1,)) != 0, axis=-1) & alloc
    assert np.all(t[links[nz]] == 1)


def test_tv_flat_region_has_zero_gradient(device):
    shape = (4, 4, 4)
    dens = np.full(shape, 2.0, np.float32)
    sh = np.full(shape + (3,), 0.3, np.float32)
    grid = clrf.SparseGrid.from_dense(device, dens, sh, BBOX)
    grad = cla.zeros_like(grid.sh)
    touched = cla.zeros(device.queue, grid.n_rows, np.uint8)
    grid_ops.tv_grad(grid, grid.sh, grad, touched, 0, dens.size, 1.0, False)
    assert np.all(grad.get() == 0)


@pytest.mark.parametrize("big", [1e10, 1e19, 1e20, 1e30, 1e38, 3e38])
def test_tv_grad_huge_differences(device, big):
    """Neighbour differences whose squares overflow float32 (|d| > 1.8e19) keep the gradient
    scale * d / |d| (it used to vanish: r = inf). At 3e38 next to -3e38 the difference itself
    overflows float32; it is clamped to +-FLT_MAX: finite, bounded, direction approximate."""
    rng = np.random.default_rng(5)
    shape = (3, 4, 5)
    dens = (rng.choice([-1.0, 0.0, 0.5, 1.0], shape) * big).astype(np.float32)
    dens[0, 0, 0], dens[1, 0, 0] = big, -big
    alloc = rng.random(shape) < 0.8
    alloc[:2, 0, 0] = True
    grid = clrf.SparseGrid.from_dense(device, dens * alloc, np.zeros(shape + (3,), np.float32),
                                      BBOX, mask=alloc)
    grad = cla.zeros_like(grid.density)
    touched = cla.zeros(device.queue, grad.shape[0], np.uint8)
    grid_ops.tv_grad(grid, grid.density, grad, touched, 0, dens.size, 0.5, True)
    r = ref.tv_grad(alloc, dens * alloc, 0, dens.size, 0.5, True)[..., 0]
    gk = grid.rows_to_dense(grad.get(), np.zeros((grad.shape[0], 3), np.float32))[0]
    assert np.all(np.isfinite(gk))
    assert np.abs(gk).max() <= 0.5 * (3 + np.sqrt(3)) * (1 + 1e-6)   # <= scale per term
    if big < 1.7e38:
        np.testing.assert_allclose(gk, r, atol=GRAD_ATOL, rtol=GRAD_RTOL)
    assert np.abs(r).max() > 0.4


@pytest.mark.parametrize("new_reso", [(5, 6, 7), (10, 12, 14), (3, 3, 3), (1, 1, 1), (8, 5, 9)])
def test_resample_vs_reference(device, new_reso):
    rng = np.random.default_rng(sum(new_reso))
    grid, dens, sh, alloc = sparse_grid(device, rng, (5, 6, 7))
    keep = alloc & (rng.random(alloc.shape) < 0.7)
    links = grid.links.get()
    keep_rows = np.zeros(grid.density.shape[0], np.uint8)
    keep_rows[links[keep]] = 1
    g2 = grid_ops.resample(grid, new_reso, cla.to_device(device.queue, keep_rows))
    d_ref, s_ref, a_ref = ref.resample(dens, sh, keep, new_reso)
    assert g2.reso == tuple(new_reso)
    np.testing.assert_array_equal(g2.links.get() >= 0, a_ref)
    d2, s2 = g2.to_dense()
    np.testing.assert_allclose(d2, d_ref, atol=RENDER_ATOL, rtol=RENDER_RTOL)
    np.testing.assert_allclose(s2, s_ref, atol=RENDER_ATOL, rtol=RENDER_RTOL)


def test_resample_same_reso_keep_all_is_identity(device):
    rng = np.random.default_rng(1)
    grid, dens, sh, alloc = sparse_grid(device, rng, (4, 5, 6))
    g2 = grid_ops.resample(grid, grid.reso)
    d2, s2 = g2.to_dense()
    np.testing.assert_array_equal(g2.links.get() >= 0, alloc)
    np.testing.assert_allclose(d2, dens, rtol=1e-6)
    np.testing.assert_allclose(s2, sh, rtol=1e-6, atol=1e-7)


def test_prune_vs_reference_and_to_nothing(device):
    rng = np.random.default_rng(2)
    grid, dens, sh, alloc = sparse_grid(device, rng, (6, 6, 6), degree=0)
    o = (rng.normal(0, 2.5, (200, 3))).astype(np.float32)
    d = (rng.uniform(-0.5, 0.5, (200, 3)) - o).astype(np.float32)
    mw = grid_ops.max_weight(grid, o, d, 0.5)
    mw_dense = grid.rows_to_dense(mw.get(), np.zeros((mw.shape[0], 3), np.float32))[0]
    thr = float(np.quantile(mw_dense[alloc], 0.8))
    keep = grid_ops.prune_keep(grid, mw, thr)
    keep_dense = np.zeros(alloc.shape, bool)
    links = grid.links.get()
    keep_dense[alloc] = keep.get()[links[alloc]] == 1
    r = ref.prune_keep(alloc, mw_dense, dens, thr)
    np.testing.assert_array_equal(keep_dense, r)
    assert 0 < r.sum() < alloc.sum()
    pruned = grid_ops.prune(grid, mw, thr)
    assert pruned.n_rows == r.sum()
    # pruned to nothing: a legal, empty grid that renders the background
    empty = grid_ops.prune(grid, mw, 1e9)
    assert empty.n_rows == 0 and np.all(empty.links.get() == -1)
    out = clrf.render_rays(empty, o, d, background=(0.3, 0.3, 0.3))
    assert np.all(out["acc"] == 0) and np.allclose(out["rgb"], 0.3)


def test_pruned_grid_renders_like_its_dense_equivalent(device):
    """Empty-space skipping over pruned cells leaves the render unchanged (float32 rounding)."""
    rng = np.random.default_rng(4)
    shape = (16, 16, 16)
    dens = np.zeros(shape, np.float32)
    dens[5:11, 4:9, 6:12] = rng.uniform(0.5, 4, (6, 5, 6))
    sh = rng.normal(0, 0.3, shape + (3,)).astype(np.float32) * (dens > 0)[..., None]
    grid = clrf.SparseGrid.from_dense(device, dens, sh, BBOX)   # rows only where non-zero
    assert grid.n_rows < dens.size / 5
    o = rng.normal(0, 3, (500, 3)).astype(np.float32)
    d = (rng.uniform(-0.4, 0.4, (500, 3)) - o).astype(np.float32)
    out = clrf.render_rays(grid, o, d, step=0.5)
    r = ref.render_forward(dens, sh, BBOX, o, d, 0.5)         # dense, no skipping
    np.testing.assert_allclose(out["rgb"], r["rgb"], atol=RENDER_ATOL, rtol=RENDER_RTOL)
    assert np.sum(out["acc"] > 0.5) > 20


def test_gather_batch_vs_reference(device):
    from clrf.training.trainer import RayStore
    rng = np.random.default_rng(0)
    n_src = 1001
    o = rng.normal(size=(n_src, 3)).astype(np.float32)
    d = rng.normal(size=(n_src, 3)).astype(np.float32)
    c = rng.uniform(size=(n_src, 3)).astype(np.float32)
    store = RayStore(device, o, d, c)
    bo, bd, bc, idx = store.batch(seed=1234, n=257)
    r = ref.batch_indices(1234, 257, n_src)
    np.testing.assert_array_equal(idx.get(), r)
    np.testing.assert_array_equal(bo.get(), o[r])
    np.testing.assert_array_equal(bc.get(), c[r])
    counts = np.bincount(ref.batch_indices(7, 200000, 10), minlength=10)
    assert counts.min() > 19000  # uniform over the sources


def test_strided_rays_read_back_from_the_device(device):
    """RayStore.strided: rows 0, s, 2 s, ... of the origins and directions, read from the
    device (the store keeps no host copy), equal to numpy's slicing of what was stored."""
    from clrf.training.trainer import RayStore
    rng = np.random.default_rng(2)
    n_src = 1001
    o = rng.normal(size=(n_src, 3)).astype(np.float32)
    d = rng.normal(size=(n_src, 3)).astype(np.float32)
    store = RayStore(device, o, d, np.zeros((n_src, 3), np.float32))
    assert not hasattr(store, "host")
    for n in (1, 7, 100, 1001, 5000):
        so, sd = store.strided(n)
        stride = max(1, n_src // n)
        assert so.dtype == np.float32 and so.shape == o[::stride].shape
        np.testing.assert_array_equal(so, o[::stride])
        np.testing.assert_array_equal(sd, d[::stride])
    empty = RayStore(device, o[:0], d[:0], o[:0])
    assert [a.shape for a in empty.strided(10)] == [(0, 3), (0, 3)]


@pytest.mark.parametrize("alpha", [False, True])
def test_training_rays_filled_part_by_part(device, monkeypatch, alpha):
    """training_rays fills the device store a few views at a time (RAY_PART rays): the store
    holds what one build of every view gives (view_rays, the images, their alpha), in order."""
    import dataclasses
    from clrf.data.synthetic import load_procedural
    from clrf.data.cameras import view_rays
    from clrf.training import trainer
    ds = load_procedural(n_train=5, n_test=1, size=16)
    if alpha:
        cover = np.random.default_rng(3).uniform(size=ds.images.shape[:3]).astype(np.float32)
        ds = dataclasses.replace(ds, alpha=cover)
    monkeypatch.setattr(trainer, "RAY_PART", 2 * 16 * 16 + 7)      # two views a part
    store = trainer.training_rays(device, ds, alpha=True)
    idx = ds.split["train"]
    o, d = view_rays(ds, ds.poses[idx])
    assert store.n == len(o) == 5 * 256
    np.testing.assert_array_equal(store.o.get(), o)
    np.testing.assert_array_equal(store.d.get(), d)
    np.testing.assert_array_equal(store.c.get(), ds.images[idx].reshape(-1, 3))
    if alpha:
        np.testing.assert_array_equal(store.alpha.get(), ds.alpha[idx].reshape(-1))
    else:
        assert store.alpha is None
    with pytest.raises(ValueError, match="RayStore.put"):
        store.put(store.n - 1, o[:2], d[:2], o[:2])


def test_batch_recomposited_on_another_background(device):
    """RGBA rays: a batch's colours moved from the background they were composited on to
    another one (random-background training) match the float64 reference; without alpha the
    store refuses."""
    from clrf.training.trainer import RayStore
    rng = np.random.default_rng(1)
    n_src, old, new = 999, (1.0, 1.0, 1.0), (0.25, 0.8, 0.0)
    rgb = rng.uniform(size=(n_src, 3))
    alpha = rng.uniform(size=n_src)
    alpha[:100], alpha[100:200] = 0.0, 1.0           # fully clear and fully covered rays
    c = (rgb * alpha[:, None] + np.asarray(old) * (1 - alpha[:, None])).astype(np.float32)
    o = rng.normal(size=(n_src, 3)).astype(np.float32)
    store = RayStore(device, o, o, c, alpha.astype(np.float32), old)
    _, _, bc, idx = store.batch(seed=5, n=300, background=new)
    r = ref.batch_indices(5, 300, n_src)
    np.testing.assert_array_equal(idx.get(), r)
    want = ref.recomposite(c[r], alpha[r].astype(np.float32), old, new)
    np.testing.assert_allclose(bc.get(), want, rtol=0, atol=2e-7)
    # what it stands for: the same rgb over the new background
    np.testing.assert_allclose(bc.get(), rgb[r] * alpha[r, None] + np.asarray(new)
                               * (1 - alpha[r, None]), rtol=0, atol=1e-6)
    _, _, plain, _ = store.batch(seed=5, n=300)           # no background: the colours as stored
    np.testing.assert_array_equal(plain.get(), c[r])
    with pytest.raises(ValueError, match="alpha"):
        RayStore(device, o, o, c).batch(seed=5, n=8, background=new)


@pytest.mark.parametrize("path", ["device", "per_sample"])
@pytest.mark.parametrize("lambda_beta", [0.0, 0.05])
def test_fused_mse_and_beta_prior_vs_reference(device, lambda_beta, path):
    """Training's fused backward (GRAD_MODE 1): MSE against targets plus the beta prior on each
    ray's transmittance, against the float64 reference (analytic) and finite differences; on
    the device's own path and on the GPU shape adding each sample's gradients (GRAD_MERGE 0,
    Intel GPUs' default)."""
    from clrf.grid.render import render_backward_device
    if path == "per_sample":
        device = device.with_tuning(grad_slots=0, sample_record=False, grad_locks=0,
                                    gpu_kernels=True, grad_merge=False)
    rng = np.random.default_rng(11)
    grid, dens, sh, alloc = sparse_grid(device, rng, (4, 5, 3), degree=1, empty_frac=0.2)
    n = 64
    o = rng.normal(0, 2.5, (n, 3)).astype(np.float32)
    d = (rng.uniform(-0.6, 0.6, (n, 3)) - o).astype(np.float32)
    target = rng.uniform(0, 1, (n, 3)).astype(np.float32)
    bg = (1.0, 1.0, 1.0)
    q = device.queue
    gd = cla.zeros_like(grid.density)
    gs = cla.zeros_like(grid.sh)
    sq = cla.empty(q, n, np.float32)
    loss_scale = 1.0 / (3 * n)
    render_backward_device(grid, cla.to_device(q, o), cla.to_device(q, d), cla.to_device(q, target),
                           0.5, bg, gd, gs, grad_mode=1, loss_scale=loss_scale, ray_out=sq,
                           beta_scale=lambda_beta / n)
    f = ref.render_forward(dens, sh, BBOX, o, d, 0.5, bg)
    np.testing.assert_allclose(sq.get(), np.sum((f["rgb"] - target) ** 2, 1), atol=RENDER_ATOL,
                               rtol=RENDER_RTOL)
    g = 2 * loss_scale * (f["rgb"] - target)
    T = 1 - f["acc"]
    r = ref.render_backward(dens, sh, BBOX, o, d, g, 0.5, bg, mask=alloc,
                            grad_T=ref.beta_grad_T(T, lambda_beta / n))
    kd, ks = grid.rows_to_dense(gd.get(), gs.get())
    if lambda_beta:   # the prior must matter in this problem, or the test has no teeth
        r0 = ref.render_backward(dens, sh, BBOX, o, d, g, 0.5, bg, mask=alloc)
        assert np.abs(r0["density"] - r["density"]).max() > 100 * GRAD_ATOL
    np.testing.assert_allclose(kd, r["density"], atol=GRAD_ATOL, rtol=GRAD_RTOL)
    np.testing.assert_allclose(ks, r["sh"], atol=GRAD_ATOL, rtol=GRAD_RTOL)

    def loss(dd):
        ff = ref.render_forward(dd, sh, BBOX, o, d, 0.5, bg)
        return (loss_scale * np.sum((ff["rgb"] - target) ** 2)
                + ref.beta_loss(1 - ff["acc"], lambda_beta / n))
    for idx in [tuple(np.argwhere(alloc)[k]) for k in (0, 7, 19)]:
        e = np.zeros_like(dens, dtype=np.float64)
        e[idx] = 1e-4
        fd = (loss(dens + e) - loss(dens - e)) / 2e-4
        assert abs(fd - r["density"][idx]) <= FD_ATOL + FD_RTOL * abs(fd), (idx, fd, r["density"][idx])
