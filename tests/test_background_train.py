"""Background model in Plenoxels training: the grid renderer's per-ray background (BG_PER_RAY)
against the float64 reference and finite differences, GridModel with an MSI background against
a float64 composition of the references, checkpoints, background off, and a real-scene smoke."""
import numpy as np
import pytest

import clrf
import pyopencl.array as cla
from clrf.grid.render import ray_exit_device
from clrf.references import reference as ref
from clrf.testing.tolerances import (FD_ATOL, FD_RTOL, GRAD_ATOL, GRAD_RTOL, RENDER_ATOL,
                                     RENDER_RTOL)

from test_render import BBOX, assert_forward_matches, random_grid, random_rays


@pytest.mark.parametrize("shape,degree", [((1, 1, 1), 0), ((6, 5, 4), 2)])
def test_per_ray_forward_vs_reference(device, shape, degree):
    rng = np.random.default_rng(40 + degree)
    dens, sh = random_grid(rng, shape, degree, empty_frac=0.25 if np.prod(shape) > 8 else 0.0)
    grid = clrf.SparseGrid.from_dense(device, dens, sh, BBOX)
    o, d = random_rays(rng, 150)
    bg = rng.uniform(0, 1, (150, 3)).astype(np.float32)
    out = clrf.render_rays(grid, o, d, step=0.37, background=bg)
    r = ref.render_forward(dens, sh, BBOX, o, d, 0.37, bg)
    assert_forward_matches(out, r)
    # rays that miss the box show their own background exactly
    miss = out["acc"] == 0
    assert miss.any() and np.array_equal(out["rgb"][miss], bg[miss])
    # a per-ray background equal to a constant one gives the constant path's bytes
    c = (0.2, 0.5, 0.9)
    same = clrf.render_rays(grid, o, d, step=0.37, background=np.tile(np.float32(c), (150, 1)))
    const = clrf.render_rays(grid, o, d, step=0.37, background=c)
    for k in const:
        assert np.array_equal(same[k], const[k]), k


def test_ray_exit_vs_reference(device):
    rng = np.random.default_rng(44)
    dens, sh = random_grid(rng, (3, 4, 5), 0)
    grid = clrf.SparseGrid.from_dense(device, dens, sh, BBOX)
    o, d = random_rays(rng, 100)
    o[:10] = BBOX.mean(0)                      # origins inside the box: exit from inside
    q = device.queue
    t = ray_exit_device(grid, cla.to_device(q, o), cla.to_device(q, d), 0.5).get()[:100]
    r = ref.ray_exit(o, d, dens.shape, BBOX, 0.5)
    np.testing.assert_allclose(t, r, atol=RENDER_ATOL, rtol=RENDER_RTOL)
    assert np.all(t[:10] > 0) and np.any(t[10:] == 0)


@pytest.mark.parametrize("degree", [0, 2])
def test_per_ray_backward_vs_reference_and_fd(render_device, degree):
    """dL/d density, sh and the per-ray background (T_end g) on both backward code paths."""
    rng = np.random.default_rng(50 + degree)
    shape = (2, 3, 2)
    dens, sh = random_grid(rng, shape, degree, dens_hi=2.0)
    grid = clrf.SparseGrid.from_dense(render_device, dens, sh, BBOX)
    n = 24
    o, d = random_rays(rng, n, spread=2.0)
    g = rng.normal(size=(n, 3)).astype(np.float32)
    bg = rng.uniform(0, 1, (n, 3)).astype(np.float32)
    kern = clrf.render_rays_backward(grid, o, d, g, step=0.3, background=bg)
    ana = ref.render_backward(dens, sh, BBOX, o, d, g, 0.3, bg)
    for k in ("density", "sh", "background"):
        np.testing.assert_allclose(kern[k], ana[k], atol=GRAD_ATOL, rtol=GRAD_RTOL, err_msg=k)
    for which, arr in (("density", dens), ("sh", sh), ("background", bg)):
        for flat in rng.choice(arr.size, 5, replace=False):
            idx = np.unravel_index(flat, arr.shape)
            fd = ref.finite_difference(dens, sh, BBOX, o, d, g, which, idx, step=0.3,
                                       background=bg)
            assert abs(fd - ana[which][idx]) <= FD_ATOL + FD_RTOL * abs(fd), (which, idx, fd)
    assert np.abs(ana["density"]).max() > 1e-3
    assert np.ptp(kern["background"] / np.where(g == 0, 1, g)) > 0.1   # T_end varies by ray


def test_per_ray_fused_mse_backward(render_device):
    """GRAD_MODE 1 (target colours in, MSE + beta prior) with a per-ray background: grid
    gradients and dL/d background = T_end g, g = 2 (pixel - target) loss_scale."""
    from clrf.grid.render import render_backward_device
    rng = np.random.default_rng(60)
    dens, sh = random_grid(rng, (5, 4, 6), 1, empty_frac=0.3, dens_hi=1.5)
    grid = clrf.SparseGrid.from_dense(render_device, dens, sh, BBOX)
    n = 200
    o, d = random_rays(rng, n)
    bg = rng.uniform(0, 1, (n, 3)).astype(np.float32)
    target = rng.uniform(0, 1, (n, 3)).astype(np.float32)
    ls, bs = 1.0 / (3 * n), 1e-2 / n
    q = render_device.queue
    gd = cla.zeros(q, grid.density.shape[0], np.float32)
    gs = cla.zeros(q, grid.sh.shape, np.float32)
    sq = cla.empty(q, n, np.float32)
    gbg = render_backward_device(grid, cla.to_device(q, o), cla.to_device(q, d),
                                 cla.to_device(q, target), 0.5, cla.to_device(q, bg), gd, gs,
                                 grad_mode=1, loss_scale=ls, ray_out=sq, beta_scale=bs)
    f = ref.render_forward(dens, sh, BBOX, o, d, 0.5, bg, record=True)
    g = 2 * ls * (f["rgb"] - target)
    ana = ref.render_backward(dens, sh, BBOX, o, d, g, 0.5, bg,
                              grad_T=ref.beta_grad_T(f["T_end"], bs))
    kd, ks = grid.rows_to_dense(gd.get(), gs.get())
    np.testing.assert_allclose(sq.get(), np.sum((f["rgb"] - target) ** 2, 1), atol=RENDER_ATOL,
                               rtol=RENDER_RTOL)
    np.testing.assert_allclose(kd, ana["density"], atol=GRAD_ATOL, rtol=GRAD_RTOL)
    np.testing.assert_allclose(ks, ana["sh"], atol=GRAD_ATOL, rtol=GRAD_RTOL)
    np.testing.assert_allclose(gbg.get(), ana["background"], atol=GRAD_ATOL, rtol=GRAD_RTOL)



@pytest.mark.parametrize("scale", [0.0, 1e-30, 1e-10, 1.0, 1e10, 1e30])
def test_per_ray_density_scale_sweep_finite(render_device, scale):
    """Densities from 0 to 1e30 with a per-ray background: finite pixels and gradients, and
    dL/d background = T_end g never exceeds g (0 <= T_end <= 1)."""
    rng = np.random.default_rng(65)
    dens, sh = random_grid(rng, (4, 3, 5), 1)
    grid = clrf.SparseGrid.from_dense(render_device, dens * np.float32(scale), sh, BBOX)
    o, d = random_rays(rng, 50)
    bg = rng.uniform(0, 1, (50, 3)).astype(np.float32)
    g = rng.normal(size=(50, 3)).astype(np.float32)
    out = clrf.render_rays(grid, o, d, step=0.5, background=bg)
    kern = clrf.render_rays_backward(grid, o, d, g, step=0.5, background=bg)
    for k, v in list(out.items()) + list(kern.items()):
        assert np.all(np.isfinite(v)), k
    assert np.all(np.abs(kern["background"]) <= np.abs(g))
    if scale == 0.0:
        assert np.array_equal(out["rgb"], bg) and np.array_equal(kern["background"], g)

# ---- GridModel with an MSI background ---------------------------------------------------
from clrf.outputs import checkpoint  # noqa: E402
from clrf.grid.config import GridConfig  # noqa: E402
from clrf.grid.background import GridBackground, msi_geometry  # noqa: E402
from clrf.grid.model import GridModel  # noqa: E402
from clrf.references import reference_background as ref_bg  # noqa: E402
from clrf.testing.tolerances import (BG_ATOL, BG_GRAD_ATOL, BG_GRAD_RTOL, BG_RTOL,  # noqa: E402
                                     MODEL_LOSS_RTOL)

CUBE = np.array([[-1.0] * 3, [1.0] * 3])
BG_CONST = (0.9, 0.8, 0.7)


def tiny_cfg(**kw):
    base = dict(reso=[[3, 4, 3]], upsample_at=[], sh_degree=1, step=0.4, batch_size=64,
                lambda_tv=0.0, lambda_tv_sh=0.0, lambda_sparsity=0.0, lambda_beta=1e-2,
                background_layers=4, background_height=3)
    base.update(kw)
    return GridConfig(**base)


def bg_model(dev, cfg, rng):
    """A GridModel on a random dense 3x4x3 grid in CUBE with a random MSI behind it."""
    dens, sh = random_grid(rng, tuple(cfg.reso[0]), cfg.sh_degree, dens_hi=1.0)
    grid = clrf.SparseGrid.from_dense(dev, dens, sh, CUBE)
    bgm = GridBackground.create(dev, cfg, CUBE, BG_CONST)
    L, H, W = bgm.msi.shape
    bgm.msi.set_params(rng.uniform(0.0, 0.2, (L, H, W)), rng.normal(0, 0.3, (L, H, W, 3)))
    return GridModel(dev, cfg, grid, BG_CONST, bg_model=bgm), dens, sh


def camera_rays(rng, n):
    """Origins inside the box's circumscribed sphere (cameras of a 360 capture), random
    directions: every ray leaves the box and crosses every MSI sphere."""
    o = rng.uniform(-0.9, 0.9, (n, 3))
    d = rng.normal(size=(n, 3))
    return o.astype(np.float32), d.astype(np.float32)


def capture_grads(opt, into, name):
    """Record the gradient an optimiser step consumes (the step zeroes it)."""
    step = opt.step

    def wrapped(*a, **kw):
        into[name] = opt.grad.get().copy()
        return step(*a, **kw)
    opt.step = wrapped


def test_train_step_matches_float64_composition(render_device):
    """One GridModel step with a background == the float64 pieces chained by hand:
    t_start = ray_exit, bg = MSI forward, pixel = C_fg + T_fg bg, MSE + beta prior; gradients of
    the grid and of the MSI (dL/d bg = T_fg g into the MSI backward)."""
    rng = np.random.default_rng(70)
    cfg = tiny_cfg()
    model, dens, sh = bg_model(render_device, cfg, rng)
    msi = model.bg_model.msi
    bg_d, bg_c = msi.density.get().astype(np.float64), msi.color.get().astype(np.float64)
    B = cfg.batch_size
    o, d = camera_rays(rng, B)
    target = rng.uniform(0, 1, (B, 3)).astype(np.float32)
    grads = {}
    capture_grads(model.opt_density, grads, "density")
    capture_grads(model.opt_sh, grads, "sh")
    capture_grads(model.bg_model.opt_density, grads, "bg_density")
    capture_grads(model.bg_model.opt_color, grads, "bg_color")
    q = render_device.queue
    # float(): the GPU shape's step returns its loss as a Pending (read back when asked)
    mse = float(model.train_step(0, cla.to_device(q, o), cla.to_device(q, d),
                                 cla.to_device(q, target)))

    center, r_inner = msi_geometry(CUBE)
    t_start = ref.ray_exit(o, d, dens.shape, CUBE, cfg.step)
    assert np.all(t_start > 0)
    bg_rgb, _ = ref_bg.forward(bg_d, bg_c, msi.r_inner, o, d, t_start, center, BG_CONST)
    f = ref.render_forward(dens, sh, CUBE, o, d, cfg.step, bg_rgb, record=True)
    g = 2.0 / (3 * B) * (f["rgb"] - target)
    ana = ref.render_backward(dens, sh, CUBE, o, d, g, cfg.step, bg_rgb,
                              grad_T=ref.beta_grad_T(f["T_end"], cfg.lambda_beta / B))
    ana_bd, ana_bc = ref_bg.backward(bg_d, bg_c, msi.r_inner, o, d, t_start, ana["background"],
                                     center, BG_CONST)
    np.testing.assert_allclose(mse, np.mean((f["rgb"] - target) ** 2), rtol=MODEL_LOSS_RTOL)
    kd, ks = model.grid.rows_to_dense(grads["density"], grads["sh"])
    np.testing.assert_allclose(kd, ana["density"], atol=GRAD_ATOL, rtol=GRAD_RTOL)
    np.testing.assert_allclose(ks, ana["sh"], atol=GRAD_ATOL, rtol=GRAD_RTOL)
    np.testing.assert_allclose(grads["bg_density"].reshape(msi.shape), ana_bd,
                               atol=BG_GRAD_ATOL, rtol=BG_GRAD_RTOL)
    np.testing.assert_allclose(grads["bg_color"].reshape(msi.shape + (3,)), ana_bc,
                               atol=BG_GRAD_ATOL, rtol=BG_GRAD_RTOL)
    assert np.abs(ana_bd).max() > 1e-4 and np.abs(ana_bc).max() > 1e-4
    # the step: RMSProp (float64 twin of update_rows) on the texels with a gradient
    lr_d, lr_c = model.bg_model.learning_rates(0)
    for name, before, arr, lr in (("bg_density", bg_d, msi.density, lr_d),
                                  ("bg_color", bg_c, msi.color, lr_c)):
        gr = grads[name].reshape(before.shape[0] * before.shape[1] * before.shape[2], -1)
        want, _ = ref.update_rows(before.reshape(gr.shape), gr, np.zeros(gr.shape),
                                  np.ones(gr.shape[0], bool), lr, cfg.rms_beta)
        np.testing.assert_allclose(arr.get().reshape(gr.shape), want, atol=RENDER_ATOL,
                                   err_msg=name)
    # the model's render shows the float64 composition of its updated parameters
    n = model.grid.n_rows
    dens1, sh1 = model.grid.rows_to_dense(model.grid.density.get()[:n], model.grid.sh.get()[:n])
    bg1, _ = ref_bg.forward(msi.density.get(), msi.color.get(), msi.r_inner, o, d, t_start,
                            center, BG_CONST)
    out = model.render(o, d)
    want = ref.render_forward(dens1, sh1, CUBE, o, d, cfg.step, bg1)
    np.testing.assert_allclose(out["rgb"], want["rgb"], atol=BG_ATOL, rtol=BG_RTOL)


def test_checkpoint_round_trip(device, tmp_path):
    rng = np.random.default_rng(80)
    cfg = tiny_cfg(sh_degree=0)
    model = GridModel.create(device, cfg, CUBE, BG_CONST)
    q = device.queue
    o, d = camera_rays(rng, cfg.batch_size)
    batch = [cla.to_device(q, a) for a in (o, d, rng.uniform(0, 1, o.shape).astype(np.float32))]
    for it in range(3):
        model.train_step(it, *batch)
    st = model.state_dict()
    for k in ("bg_density", "bg_color", "opt_bg_density", "opt_bg_color"):
        assert k in st and np.any(st[k] != 0), k
    checkpoint.save(tmp_path / "ckpt.npz", {**st, "run_config": {}})
    loaded = checkpoint.load(tmp_path)
    m2 = GridModel.from_state_dict(device, loaded, cfg)
    st2 = m2.state_dict()
    for k, v in st.items():
        assert np.array_equal(np.asarray(v), np.asarray(st2[k])), k
    r1, r2 = model.render(o, d), m2.render(o, d)
    for k in r1:
        assert np.array_equal(r1[k], r2[k]), k
    assert model.train_step(3, *batch) == m2.train_step(3, *batch)   # same pixels, same loss
    with pytest.raises(ValueError, match="background_layers"):
        GridModel.from_state_dict(device, loaded, tiny_cfg(sh_degree=0, background_layers=0))
    with pytest.raises(ValueError, match="background_layers"):
        GridModel.from_state_dict(device, loaded, tiny_cfg(sh_degree=0, background_layers=5))


def test_background_off_builds_and_launches_nothing_new(device, monkeypatch):
    """background_layers = 0: the grid program is built with exactly the defines it had before
    per-ray backgrounds existed (no BG_PER_RAY key), background.cl is never built, and a step
    and a render launch only the constant-background kernels. (Byte-identical training was
    checked against the previous commit with one PoCL thread, where the gradient order is
    deterministic: same checkpoint bytes after 25 iterations and an upsample.)"""
    import clrf.grid.render as grid_render
    rng = np.random.default_rng(90)
    cfg = tiny_cfg(background_layers=0)
    built, launched = [], []
    program, launch = device.program, grid_render.launch
    monkeypatch.setattr(device, "program",
                        lambda src, defines=None: built.append((src, dict(defines or {})))
                        or program(src, defines))
    monkeypatch.setattr(grid_render, "launch",
                        lambda dev, k, *a: launched.append(k.function_name) or launch(dev, k, *a))
    model = GridModel.create(device, cfg, CUBE, BG_CONST)
    assert model.bg_model is None and "MSI" not in model.describe()
    q = device.queue
    o, d = camera_rays(rng, cfg.batch_size)
    model.train_step(0, *[cla.to_device(q, a) for a in (o, d, np.zeros_like(o))])
    out = model.render(o, d)
    assert {src for src, _ in built} <= {"grid_render.cl", "grid_ops.cl", "optim.cl"}, built
    assert not any("BG_PER_RAY" in df for _, df in built)
    assert set(launched) <= {"render_backward", "grad_slots_reduce", "render_forward",
                             "block_occupancy"}, launched
    assert not any(k.startswith(("bg_", "opt_bg_")) for k in model.state_dict())
    want = ref.render_forward(*model.grid.rows_to_dense(model.grid.density.get()[:model.grid.n_rows],
                                                        model.grid.sh.get()[:model.grid.n_rows]),
                              CUBE, o, d, cfg.step, BG_CONST)
    assert_forward_matches(out, want)


@pytest.mark.slow
def test_bonsai_smoke_with_background(scene, tmp_path):
    """`clrf train` on the real 360 scene (real360 preset: background on) for 30 iterations
    (a count, not a time, so a busy host logs the same) writes every output and lowers the loss; `clrf eval` and `clrf render` read its
    checkpoint."""
    import csv
    import json
    from clrf.cli.main import main as cli
    out = tmp_path / "run"
    rc = cli(["train", "--data", str(scene("bonsai_800")), "--out", str(out),
              "--max-seconds", "300", "--set", "train.max_iters=30", "--set", "train.downscale=8",
              "--set", "grid.reso=[[32,32,32]]", "--set", "grid.upsample_at=[]",
              "--set", "grid.batch_size=2000", "--set", "grid.background_height=32",
              "--set", "train.eval_every=0.5", "--set", "train.eval_views=1",
              "--set", "train.max_train_images=40"])
    assert rc == 0
    for name in ("config.json", "metrics.csv", "error_vs_time.png", "ckpt.npz", "eval.json"):
        assert (out / name).is_file(), name
    cfg = json.loads((out / "config.json").read_text())
    assert cfg["train"]["preset"] == "real360" and cfg["grid"]["background_layers"] > 0
    rows = list(csv.DictReader(open(out / "metrics.csv")))
    assert "MSI background" in rows[-1]["model"]
    losses = [float(r["train_loss"]) for r in rows if r["train_loss"]]
    assert len(losses) >= 2 and losses[-1] < losses[0], losses
    st = checkpoint.load(out)
    assert st["bg_density"].shape == (cfg["grid"]["background_layers"], 32, 64)
    assert cli(["eval", "--ckpt", str(out), "--max-views", "1"]) == 0
    assert np.isfinite(json.loads((out / "eval_cli.json").read_text())["psnr"])
    assert cli(["render", "--ckpt", str(out), "--max-views", "1", "--scale", "0.5",
                "--out", str(tmp_path / "png")]) == 0
    assert (tmp_path / "png" / "orbit_000.png").is_file()


def test_loss_stays_on_the_device_where_the_gpu_kernels_run(device):
    """Where a device runs the GPU-shaped kernels the grid step returns its loss as a Pending
    (read when the trainer reports), with the value the host-read step returns (equal on a
    CPU; on a GPU the float atomics of the first step's gradients add in any order)."""
    from clrf.runtime.pending import Pending
    rng = np.random.default_rng(81)
    cfg = tiny_cfg(sh_degree=0)
    q = device.queue
    o, d = camera_rays(rng, cfg.batch_size)
    batch = [cla.to_device(q, a) for a in (o, d, rng.uniform(0, 1, o.shape).astype(np.float32))]
    host = GridModel.create(device, cfg, CUBE, BG_CONST)
    lazy = GridModel.create(device.with_tuning(gpu_kernels=True), cfg, CUBE, BG_CONST)
    assert not host.defer_loss and lazy.defer_loss
    for it in range(2):
        want = host.train_step(it, *batch)
        got = lazy.train_step(it, *batch)
        assert isinstance(want, float) and isinstance(got, Pending)
        assert float(got) == want if device.is_cpu else abs(float(got) - want) <= 1e-6 * want
