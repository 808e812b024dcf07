"""The hash model's bounded step (HashModel.bounded, the GPU default): sample buffers of a fixed
capacity whose live count stays on the device, every kernel launched over the capacity and
reading the count (cl/common.h live_rows), nothing read back inside the step. Checked: each
kernel with a count equals the same kernel on the first count rows and leaves the rows past
it alone (hash encoding forward, backward on both accumulation paths, SH encoding; the fused
MLP's forward, density, backward and weight gradient on the CPU tiles and the GPU tiling); a
bounded step's loss and gradients against the float64 chain, also when the capacity cuts the
batch's samples short; the batch-size adaptation and the trainer reading the losses late.
tests/test_oclgrind.py runs the small kernel cases under Oclgrind."""
import dataclasses
import time

import numpy as np
import pyopencl.array as cla
import pytest

from clrf.hash.encoding import HashEncoding
from clrf.hash.model import BOUND_FACTOR, HashModel
from clrf.mlp.mlp import MLP
from clrf.references import reference_hash as rh
from clrf.references import reference_nerf as rn
from clrf.runtime.pending import Pending
from clrf.testing import tolerances as tol
from test_hash_model import BOX, SMALL, _rays, _up, seeded_model
from test_mlp_gpu import SHAPES

SENTINEL = np.float32(-7.25)


def _count(dev, k):
    return cla.to_device(dev.queue, np.array([k], np.int32))


def _filled(dev, shape):
    return cla.to_device(dev.queue, np.full(shape, SENTINEL, np.float32))


@pytest.mark.parametrize("path", ["atomics", "owned"])
def test_hash_kernels_cover_the_device_count(device, path):
    """Forward and SH encoding write rows < count only; the backward adds the first count rows'
    gradient only (garbage past them is never read)."""
    dev = device.with_tuning(grad_slots=0 if path == "atomics" else 2)
    rng = np.random.default_rng(4)
    enc = HashEncoding(dev, 4, 2, 10, 2, 40, BOX, table=rng.uniform(-1, 1, (4, 1024, 2)))
    n = 37
    x = rng.uniform(-1.2, 1.2, (n, 3)).astype(np.float32)
    genc = rng.uniform(-1, 1, (n, enc.dim)).astype(np.float32)
    genc[20:] = np.nan                     # past the count: must not reach the gradient
    table = enc.table.get()
    for k in (0, 1, 20):
        out = enc.forward(_up(dev, x), out=_filled(dev, (n, enc.dim)), count=_count(dev, k))
        out = out.get()
        want = rh.hash_forward(x[:k], enc.lo, enc.inv_ext, enc.res_host, table)
        np.testing.assert_allclose(out[:k], want, rtol=0, atol=tol.HASH_ATOL)
        assert np.all(out[k:] == SENTINEL)
        sh = enc.sh_encode(_up(dev, x), out=_filled(dev, (n, 16)), count=_count(dev, k)).get()
        np.testing.assert_allclose(sh[:k], rh.sh_encode(x[:k]), rtol=0, atol=tol.HASH_ATOL)
        assert np.all(sh[k:] == SENTINEL)
        enc.grad.fill(np.float32(0))
        enc.backward(_up(dev, x), _up(dev, genc), count=_count(dev, k))
        want = rh.hash_backward(x[:k], enc.lo, enc.inv_ext, enc.res_host, genc[:k], enc.shape)
        got = enc.grad.get()
        assert np.all(np.isfinite(got))
        np.testing.assert_allclose(got, want, rtol=0, atol=tol.HASH_GRAD_ATOL
                                   + tol.HASH_GRAD_RTOL * np.abs(want).max(initial=0.0))


@pytest.mark.parametrize("tiling", ["cpu", "gpu"])
@pytest.mark.parametrize("shape,n,k", [("hash-1x64-c2", 50, 0), ("hash-1x64-c2", 50, 1),
                                       ("hash-1x64-c2", 200, 129), ("softplus-c3", 50, 33),
                                       ("softplus-c3", 7, 7)])
def test_mlp_passes_cover_the_device_count(device, tiling, shape, n, k):
    """Forward, density and backward over a buffer of n rows with count k: the outputs of
    rows < k and the parameter gradient are those of the same passes over the first k rows
    (the CPU tiles exactly; the GPU tiling up to its chunked sum's order), rows past k keep
    what they held, and NaN inputs past k reach nothing."""
    dev = device.with_tuning(gpu_kernels=tiling == "gpu")
    spec = SHAPES[shape]
    net = MLP(dev, spec, seed=3)
    rng = np.random.default_rng(n + k)
    x = rng.normal(size=(n, spec.in_dim)).astype(np.float32)
    d = rng.normal(size=(n, spec.dir_dim)).astype(np.float32)
    ds = rng.normal(size=n).astype(np.float32)
    dr = rng.normal(size=(n, 3)).astype(np.float32)
    for a in (x, d, ds, dr):
        a[k:] = np.nan
    q, cnt = dev.queue, _count(dev, k)
    sig_d = net.density(_up(dev, x), sigma=_filled(dev, n), count=cnt).get()
    sig, rgb = net.forward(_up(dev, x), _up(dev, d), sigma=_filled(dev, n),
                           rgb=_filled(dev, (n, 3)), count=cnt)
    sig, rgb = sig.get(), rgb.get()
    dx, dd = (a.get() for a in net.backward(_up(dev, ds), _up(dev, dr), want_input=True))
    grad = net.grad.get()
    assert np.all(sig[k:] == SENTINEL) and np.all(rgb[k:] == SENTINEL) \
        and np.all(sig_d[k:] == SENTINEL)
    assert np.all(np.isfinite(grad))
    if k:     # the same passes over exactly k rows
        s1, c1 = net.forward(_up(dev, x[:k]), _up(dev, d[:k]))
        np.testing.assert_array_equal(sig[:k], s1.get())
        np.testing.assert_array_equal(rgb[:k], c1.get())
        np.testing.assert_array_equal(sig_d[:k], s1.get())
        dx1, dd1 = (a.get() for a in net.backward(_up(dev, ds[:k]), _up(dev, dr[:k]),
                                                  want_input=True))
        np.testing.assert_array_equal(dx[:k], dx1)
        np.testing.assert_array_equal(dd[:k], dd1)
        g1 = net.grad.get()
        if tiling == "cpu":
            np.testing.assert_array_equal(grad, g1)
        else:
            np.testing.assert_allclose(grad, g1, rtol=0,
                                       atol=tol.MLP_GRAD_REL_TO_MAX * np.abs(g1).max())
        r = rn.mlp_backward(net.params.get(), spec, net.layout, x[:k], d[:k], ds[:k], dr[:k])
        np.testing.assert_allclose(grad, r["params"], rtol=0,
                                   atol=tol.MLP_GRAD_REL_TO_MAX * np.abs(r["params"]).max())
    else:
        assert np.all(grad == 0)


def _bounded_reference(model, o, d, target, cap):
    """Loss and gradients (float64) of a bounded step: the marched samples cut at ``cap`` rows
    (offsets capped), training-time termination always applied; and the uncut sample count."""
    c, enc, net = model.config, model.enc, model.net
    off, t, dt, xyz, vdir = rh.march_samples(o, d, c.samples, model.near, model.far,
                                             model.occ.occ.get(), enc.lo, enc.inv_ext, c.occ_res)
    marched = len(t)
    off = np.minimum(off, cap)
    t, dt, xyz, vdir = t[:cap], dt[:cap], xyz[:cap], vdir[:cap]
    params = net.params.get()
    x_enc = rh.hash_forward(xyz, enc.lo, enc.inv_ext, enc.res_host, enc.table.get())
    d_enc = rh.sh_encode(vdir)
    sigma, rgb = rn.mlp_forward(params, net.spec, net.layout, x_enc, d_enc)
    if c.train_t_stop > 0:
        keep, _ = rh.packed_keep(off, dt, sigma, c.train_t_stop)
        sel = np.concatenate([off[i] + np.arange(k) for i, k in enumerate(keep)]).astype(int)
        off = np.concatenate([[0], np.cumsum(keep)])
        t, dt, xyz, x_enc, d_enc = t[sel], dt[sel], xyz[sel], x_enc[sel], d_enc[sel]
        sigma, rgb = sigma[sel], rgb[sel]
    scale = 1.0 / (3 * o.shape[0])
    g = rh.packed_backward(off, t, dt, sigma, rgb, model.background, target, scale)
    mb = rn.mlp_backward(params, net.spec, net.layout, x_enc, d_enc, g["sigma"], g["rgb"])
    gt = rh.hash_backward(xyz, enc.lo, enc.inv_ext, enc.res_host, mb["x_enc"], enc.shape)
    return scale * np.sum(g["sq_err"]), mb["params"], gt, marched


@pytest.mark.parametrize("tiling,dense,cut", [("cpu", False, False), ("cpu", True, True),
                                              ("gpu", False, True), ("gpu", True, False)])
def test_bounded_step_matches_reference_chain(device, tiling, dense, cut):
    """One bounded step's loss (read late) and gradients against the float64 chain; cut: a
    capacity (BOUND_FACTOR x batch_samples) below the batch's live samples, so the last rays
    keep what fits."""
    dev = device.with_tuning(gpu_kernels=tiling == "gpu")
    model = seeded_model(dev, dataclasses.replace(SMALL, batch_samples=40 if cut else 0),
                         dense=dense, bounded=True)
    o, d = _rays(24, seed=4)
    target = np.random.default_rng(5).uniform(0, 1, (24, 3))
    cap = model.sample_capacity(24)
    assert cap == (BOUND_FACTOR * 40 if cut else 24 * SMALL.samples)
    loss, live = model.loss_and_grad(0, _up(dev, o), _up(dev, d), _up(dev, target),
                                     jitter=False)
    assert isinstance(loss, Pending) and live == cap
    rloss, gp, gt, marched = _bounded_reference(model, o, d, target, cap)
    assert (marched > cap) == cut
    assert abs(float(loss) - rloss) <= tol.HASH_STEP_LOSS_RTOL * rloss
    for got, want in ((model.net.grad.get(), gp), (model.enc.grad.get(), gt)):
        assert np.abs(want).max() > 0
        np.testing.assert_allclose(got, want, rtol=0,
                                   atol=tol.HASH_STEP_GRAD_REL_TO_MAX * np.abs(want).max())
    assert int(model._marched[1]) == marched      # the next batch's size comes from this


def test_bounded_steps_equal_host_sized_steps(device):
    """On the CPU tiles a bounded run is the host-sized run: the same losses, tables,
    network and adapted batch sizes over a few steps (no termination: the host-sized step
    compacts only when that drops 15 % of the samples). The CPU shapes and the table gradient
    owned per level on every device: float atomics would add in another order each run."""
    device = device.with_tuning(gpu_kernels=False, grad_slots=2)
    cfg = dataclasses.replace(SMALL, batch_samples=4000, train_t_stop=0.0)
    runs = []
    for bounded in (False, True):
        m = HashModel(device, cfg, near=1.5, far=4.5, bbox=BOX, background=(1, 1, 1),
                      bounded=bounded)
        losses, sizes = [], [m.batch_size]
        for it in range(4):
            o, d = _rays(m.batch_size, seed=it)
            t = np.random.default_rng(it).uniform(0, 1, (m.batch_size, 3))
            loss = m.train_step(it, _up(device, o), _up(device, d), _up(device, t))
            assert isinstance(loss, Pending) == bounded
            losses.append(float(loss))
            sizes.append(m.batch_size)
        runs.append((losses, sizes, m.enc.table.get(), m.net.params.get()))
    (l0, s0, t0, p0), (l1, s1, t1, p1) = runs
    assert l0 == l1 and s0 == s1 and len(set(s0)) > 1
    np.testing.assert_array_equal(t0, t1)
    np.testing.assert_array_equal(p0, p1)


@pytest.mark.slow
def test_trainer_reads_pending_losses(device, tmp_path):
    """Through the trainer: a bounded hash model's losses arrive late, fill metrics.csv, and a
    NaN among them stops the run with the last checkpoint kept."""
    from clrf import registry
    from clrf.data import load_dataset
    from clrf.training.config import build_config
    from clrf.training.trainer import Trainer
    kind = registry.get("hash")

    def create(dev, cfg, ds, bg):
        model = kind.create(dev, cfg, ds, bg)
        model.bounded = True
        step = model.train_step

        def paced_step(*args, **kw):
            # 10 ms a step or more on any device, so a row falls due mid-run (an H200 ran
            # the 40 steps in 0.2 s: only the last row held a loss)
            time.sleep(0.01)
            return step(*args, **kw)

        model.train_step = paced_step
        return model

    bounded = dataclasses.replace(kind, create=create)
    cfg = build_config("procedural", overrides={
        "train": {"model": "hash", "max_seconds": 300.0, "max_iters": 40, "eval_every": 0.2,
                  "eval_views": 1, "final_eval": False},
        "hash": {"preset": "tiny", "batch_rays": 64, "batch_samples": 0, "samples": 16}})
    tr = Trainer(device, load_dataset(None), cfg, tmp_path / "run", model_factory=bounded,
                 log=lambda *a: None)
    tr.run()
    import csv
    rows = list(csv.DictReader(open(tmp_path / "run" / "metrics.csv")))
    losses = [float(r["train_loss"]) for r in rows if r["train_loss"]]
    assert len(losses) >= 2 and all(np.isfinite(losses))
    assert tr.iteration == 40

    model = tr.model
    step = model.train_step

    def nan_step(it, *args, **kw):
        step(it, *args, **kw)
        return Pending(device.queue, cla.to_device(device.queue, np.float32([np.nan])))

    model.train_step = nan_step
    saved = (tmp_path / "run" / "ckpt.npz").stat().st_mtime_ns
    cfg.train.max_iters = 80
    with pytest.raises(FloatingPointError, match="became nan at iteration"):
        tr.run()
    assert (tmp_path / "run" / "ckpt.npz").stat().st_mtime_ns == saved


def test_gpu_shape_steps_tables_and_network_in_one_adam_launch(device):
    """With the GPU-shaped kernels the tables' spans and the network take one Adam launch
    (AdamSet): the same model as with a launch for each (the table gradient owned per level:
    float atomics would add in another order each run)."""
    from clrf.runtime.optim import AdamSet
    dev = device.with_tuning(gpu_kernels=True, grad_slots=2)
    one = seeded_model(dev, SMALL, bounded=True)
    each = seeded_model(dev, SMALL, bounded=True)
    assert isinstance(one._adam_all, AdamSet)
    each._adam_all = None
    for it in range(3):
        o, d = _rays(32, seed=it)
        t = np.random.default_rng(it).uniform(0, 1, (32, 3))
        assert float(one.train_step(it, _up(dev, o), _up(dev, d), _up(dev, t))) == \
            float(each.train_step(it, _up(dev, o), _up(dev, d), _up(dev, t)))
    np.testing.assert_array_equal(one.enc.table.get(), each.enc.table.get())
    np.testing.assert_array_equal(one.net.params.get(), each.net.params.get())
    np.testing.assert_array_equal(one._adam_table.state2.get(), each._adam_table.state2.get())
