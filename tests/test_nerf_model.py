"""NerfModel end to end (short trainings on tiny data), Adam, checkpoints, interface checks."""
import numpy as np
import pyopencl.array as cla
import pytest

from clrf.nerf import NerfConfig, NerfModel
from clrf.runtime.optim import Optimizer
from clrf.testing import tolerances as tol

# a very small model so that each step takes milliseconds
TEST_CFG = NerfConfig.from_preset("tiny", width=32, depth=2, color_width=16, pos_freqs=4,
                             dir_freqs=1, n_coarse=16, n_fine=16, lr=1e-2, batch_rays=64,
                             dw_chunk=64)


def test_adam_matches_reference(device):
    rng = np.random.default_rng(0)
    n = 101
    p, m, v = rng.normal(size=n), rng.normal(size=n) * 0.1, rng.random(n) * 0.01
    g = rng.normal(size=n)
    g[:5] = 0.0
    m[:5] = v[:5] = 0.0
    q = device.queue
    pd, md, vd, gd = (cla.to_device(q, a.astype(np.float32)) for a in (p, m, v, g))
    opt = Optimizer(device, pd, "adam", beta=0.9, beta2=0.999, eps=1e-7, state=md, grad=gd,
                    state2=vd)
    opt.step(None, lr=1e-3, t=3)
    m2 = 0.9 * m + 0.1 * g
    v2 = 0.999 * v + 0.001 * g * g
    p2 = p - 1e-3 * (m2 / (1 - 0.9 ** 3)) / (np.sqrt(v2 / (1 - 0.999 ** 3)) + 1e-7)
    np.testing.assert_allclose(md.get(), m2, rtol=tol.ADAM_RTOL, atol=tol.ADAM_ATOL)
    np.testing.assert_allclose(vd.get(), v2, rtol=tol.ADAM_RTOL, atol=tol.ADAM_ATOL)
    np.testing.assert_allclose(pd.get(), p2, rtol=tol.ADAM_RTOL, atol=tol.ADAM_ATOL)
    assert np.all(pd.get()[:5] == p[:5].astype(np.float32))   # zero gradient, zero moments


def synthetic_scene(n_rays, seed=0):
    """Rays from a ring of cameras at radius 4 looking at the origin; the target colour is a
    function of the ray (a sphere of radius 1: red on the +x side, green elsewhere, over
    black), computed in closed form from the ray-sphere hit."""
    rng = np.random.default_rng(seed)
    ang = rng.uniform(0, 2 * np.pi, n_rays)
    o = np.stack([4 * np.cos(ang), 4 * np.sin(ang), rng.uniform(-0.5, 0.5, n_rays)], 1)
    look = -o + rng.normal(scale=0.4, size=o.shape)
    d = look / np.linalg.norm(look, axis=1, keepdims=True)
    b = np.sum(o * d, 1)
    disc = b * b - (np.sum(o * o, 1) - 1.0)
    hit = disc > 0
    x = o + (-b - np.sqrt(np.maximum(disc, 0)))[:, None] * d
    col = np.where((x[:, 0] > 0)[:, None], [0.9, 0.1, 0.1], [0.1, 0.8, 0.2]) * hit[:, None]
    return o.astype(np.float32), d.astype(np.float32), col.astype(np.float32)


def train(model, o, d, c, steps, batch, seed=0):
    q = model.device.queue
    rng = np.random.default_rng(seed)
    losses = []
    for it in range(steps):
        idx = rng.integers(0, o.shape[0], batch)
        losses.append(model.train_step(it, cla.to_device(q, o[idx]), cla.to_device(q, d[idx]),
                                       cla.to_device(q, c[idx])))
    return np.array(losses)


@pytest.mark.parametrize("shared", [False, True])
def test_training_reduces_loss_on_synthetic_scene(device, shared):
    o, d, c = synthetic_scene(2048)
    model = NerfModel(device, NerfConfig.from_preset("tiny", **{**TEST_CFG.__dict__,
                                                           "shared_net": shared}),
                      near=2.0, far=6.0, background=(0, 0, 0), seed=1)
    before = np.mean((model.render(o[:256], d[:256])["rgb"] - c[:256]) ** 2)
    losses = train(model, o, d, c, 60, 64)
    assert np.all(np.isfinite(losses))
    assert losses[-10:].mean() < 0.5 * losses[:10].mean()
    after = np.mean((model.render(o[:256], d[:256])["rgb"] - c[:256]) ** 2)
    assert after < 0.5 * before


def test_train_step_loss_is_fine_mse(device):
    """The returned loss equals the MSE of a render with the same samples (no jitter)."""
    o, d, c = synthetic_scene(64, seed=3)
    cfg = NerfConfig.from_preset("tiny", **{**TEST_CFG.__dict__, "perturb": False, "lr": 0.0})
    model = NerfModel(device, cfg, near=2.0, far=6.0, background=(1, 1, 1), seed=2)
    q = device.queue
    loss = model.train_step(0, cla.to_device(q, o), cla.to_device(q, d), cla.to_device(q, c))
    out = model.render(o, d)
    assert loss == pytest.approx(np.mean((out["rgb"] - c) ** 2), rel=tol.MODEL_LOSS_RTOL)
    assert out["rgb"].shape == (64, 3) and out["depth"].shape == (64,) and out["acc"].shape == (64,)
    assert np.all((out["acc"] >= 0) & (out["acc"] <= 1 + tol.TOY_ATOL))


def test_state_dict_round_trip(device):
    o, d, c = synthetic_scene(256, seed=4)
    model = NerfModel(device, TEST_CFG, near=2.0, far=6.0, background=(0, 0, 0), seed=3)
    train(model, o, d, c, 3, 32)
    st = model.state_dict()
    assert st["step"] == 3 and st["config"]["width"] == TEST_CFG.width
    m2 = NerfModel.from_state_dict(device, st)
    a, b = model.render(o[:50], d[:50]), m2.render(o[:50], d[:50])
    np.testing.assert_array_equal(a["rgb"], b["rgb"])
    # training continues identically from the checkpoint (same moments, step and keys)
    l1 = train(model, o, d, c, 2, 32, seed=9)
    l2 = train(m2, o, d, c, 2, 32, seed=9)
    np.testing.assert_allclose(l1, l2, rtol=tol.CHECKPOINT_RTOL)


def test_bad_inputs_fail_loudly(device):
    model = NerfModel(device, TEST_CFG, near=2.0, far=6.0)
    q = device.queue
    good = cla.zeros(q, (4, 3), np.float32)
    with pytest.raises(TypeError, match="origins"):
        model.train_step(0, np.zeros((4, 3), np.float32), good, good)
    with pytest.raises(ValueError, match="same B"):
        model.train_step(0, good, cla.zeros(q, (5, 3), np.float32), good)
    with pytest.raises(ValueError, match="near/far"):
        NerfModel(device, TEST_CFG, near=3.0, far=2.0)
    with pytest.raises(ValueError, match="preset"):
        NerfConfig.from_preset("huge")


def test_near_equals_far_renders_background(device):
    model = NerfModel(device, TEST_CFG, near=3.0, far=3.0, background=(0.2, 0.4, 0.6))
    o, d, _ = synthetic_scene(10)
    out = model.render(o, d)
    np.testing.assert_allclose(out["rgb"], np.tile([0.2, 0.4, 0.6], (10, 1)), atol=tol.TOY_ATOL)
    assert np.all(out["acc"] == 0)


def test_short_training_on_tiny_lego(device, scene):
    """A few steps on real data: the loss goes down (tiny_lego, 100 x 100, black background)."""
    import sys
    from pathlib import Path
    sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tools"))
    from train_nerf_tiny import camera_rays
    f = next(scene("tiny_lego").glob("*.npz"))
    z = np.load(f)
    imgs, poses, focal = z["images"][:10], z["poses"][:10], float(z["focal"])
    o, d = camera_rays(poses, 100, 100, focal)
    c = imgs.reshape(-1, 3)
    model = NerfModel(device, NerfConfig.from_preset("tiny", **{**TEST_CFG.__dict__, "lr": 5e-3,
                                                           "batch_rays": 256}),
                      near=2.0, far=6.0, background=(0, 0, 0))
    losses = train(model, o, d, c, 40, 256)
    assert losses[-10:].mean() < 0.7 * losses[:10].mean()


@pytest.mark.slow
def test_gpu_shape_defers_the_loss_and_steps_both_networks_in_one_launch(device):
    """With the GPU-shaped kernels the step's loss stays on the device (a Pending, summed
    there) and the coarse and fine networks take one Adam launch: the same networks as a
    launch each, the loss as the host's float64 sum within float32 rounding."""
    from clrf.runtime.optim import AdamSet
    from clrf.runtime.pending import Pending
    dev = device.with_tuning(gpu_kernels=True)
    cfg = TEST_CFG
    one, each = (NerfModel(dev, cfg, near=2.0, far=6.0) for _ in range(2))
    assert one.defer_loss and isinstance(one._adam_all, AdamSet) and not cfg.shared_net
    each.defer_loss, each._adam_all = False, None
    o, d, c = synthetic_scene(64, seed=3)
    q = dev.queue
    for it in range(3):
        batch = [cla.to_device(q, a) for a in (o, d, c)]
        got, want = one.train_step(it, *batch), each.train_step(it, *batch)
        assert isinstance(got, Pending) and isinstance(want, float)
        assert abs(float(got) - want) <= 1e-6 * want
    for a, b in zip(one._nets(), each._nets()):
        np.testing.assert_array_equal(a.params.get(), b.params.get())
    assert NerfModel(device, cfg, near=2.0, far=6.0).defer_loss is False
