"""The hash-grid model: occupancy grid and compaction vs references, one whole training step's
gradients vs the chain of float64 references, stiff cases, checkpoints, a short training."""
import dataclasses
from pathlib import Path

import numpy as np
import pyopencl.array as cla
import pytest

from clrf.training.config import ConfigError, build_config
from clrf.hash.config import HashConfig
from clrf.hash.model import HashModel
from clrf.hash.occupancy import OccupancyGrid
from clrf.references import reference_hash as rh
from clrf.references import reference_nerf as rn
from clrf.testing import tolerances as tol

BOX = np.array([[-1.0, -1.0, -1.0], [1.0, 1.0, 1.0]])
# a very small model so that each step takes milliseconds
SMALL = HashConfig.from_preset("tiny", levels=3, features=2, log2_table=8, min_res=2,
                               max_res=16, width=16, color_width=16, samples=12, occ_res=4,
                               occ_points=32, batch_rays=32, occ_warmup=0, occ_every=1)


def _rays(n, seed=0, radius=3.0):
    """Rays from a sphere of the given radius towards random points near the origin."""
    rng = np.random.default_rng(seed)
    o = rng.normal(size=(n, 3))
    o *= radius / np.linalg.norm(o, axis=1, keepdims=True)
    d = rng.uniform(-0.5, 0.5, (n, 3)) - o
    return o.astype(np.float32), d.astype(np.float32)


def _up(dev, a):
    return cla.to_device(dev.queue, np.ascontiguousarray(a, np.float32))


def test_presets_and_validation():
    assert HashConfig().log2_table == 19 and HashConfig().levels == 16
    assert HashConfig.from_preset("tiny").log2_table == 16
    assert build_config("tiny").hash.preset == "tiny"
    assert build_config("synthetic").hash.preset == "full"
    # object-centric synthetic scenes hold the full learning rate longer; the rest keep 0.5
    assert build_config("synthetic").hash.lr_hold == 0.65
    for other in ("tiny", "forward_facing", "real360", "procedural"):
        assert build_config(other).hash.lr_hold == HashConfig().lr_hold == 0.5, other
    assert build_config("synthetic", overrides={"hash": {"lr_hold": 0.4}}).hash.lr_hold == 0.4
    cfg = build_config("tiny", overrides={"hash": {"preset": "full", "levels": 8},
                                          "train": {"model": "hash"}})
    assert cfg.hash.log2_table == 19 and cfg.hash.levels == 8
    with pytest.raises(ConfigError, match="hash.features"):
        build_config(overrides={"hash": {"features": 3}})
    with pytest.raises(ConfigError, match="hash.levls"):
        build_config(overrides={"hash": {"levls": 3}})
    with pytest.raises(ConfigError, match="hash.preset"):
        build_config(overrides={"hash": {"preset": "huge"}})


def test_density_pass_matches_forward_and_reference(device):
    """MLP.density (trunk and head only) gives the forward's sigma, and the float64 one; a
    backward after it (its activations overwritten) is refused."""
    model = HashModel(device, SMALL, near=1.5, far=4.5, bbox=BOX, background=(1, 1, 1), seed=4)
    rng = np.random.default_rng(9)
    model.enc.table.set(rng.uniform(-1, 1, model.enc.shape).astype(np.float32))
    xyz = rng.uniform(-1, 1, (77, 3))
    vdir = rng.normal(size=(77, 3))
    xe = model.enc.forward(_up(device, xyz))
    de = model.enc.sh_encode(_up(device, vdir))
    net = model.net
    sigma, _ = net.forward(xe, de)
    dens = net.density(xe).get()
    np.testing.assert_allclose(dens, sigma.get(), rtol=1e-6, atol=0)
    want, _ = rn.mlp_forward(net.params.get(), net.spec, net.layout, xe.get(), de.get())
    np.testing.assert_allclose(dens, want, rtol=tol.MLP_RTOL, atol=tol.MLP_ATOL)
    assert dens.std() > 0
    with pytest.raises(RuntimeError, match="density"):
        net.backward(sigma, _up(device, np.zeros((77, 3))))
    net.forward(xe, de)
    net.backward(sigma, _up(device, np.zeros((77, 3))))


def test_occupancy_starts_full_and_updates_like_reference(device):
    R = 6
    occ = OccupancyGrid(device, R, BOX)
    assert occ.occupied_fraction() == 1.0
    ema0 = np.full(R ** 3, -1.0)
    ema0[:50] = np.linspace(0, 2, 50)
    occ.ema.set(ema0.astype(np.float32))
    seen = {}

    def density(xyz):
        p = xyz.get().astype(np.float64)
        s = np.abs(p[:, 0]) * 3.0
        s[::7] = np.nan
        seen["xyz"] = p
        return _up(device, s)

    occ.update(density, key=1234, n_points=300, decay=0.9, threshold=0.8, start=100)
    cells, pts = rh.occ_points(300, 1234, R, BOX[0], BOX[1] - BOX[0], 100, occ.stride)
    np.testing.assert_allclose(seen["xyz"], pts, rtol=0, atol=1e-6)
    sig = np.abs(seen["xyz"][:, 0]) * 3.0
    sig[::7] = np.nan
    e, o = rh.occ_update(ema0, cells, sig, 0.9, 0.8)
    np.testing.assert_allclose(occ.ema.get(), e, rtol=tol.HASH_OCC_RTOL, atol=0)
    np.testing.assert_array_equal(occ.occ.get(), o)
    assert 0 < occ.occupied_fraction() < 1


@pytest.mark.parametrize("R", [1, 2, 6, 64, 100])
def test_occupancy_sweep_measures_every_cell_once_per_round(device, R):
    """The update's cells follow a permutation of the grid: consecutive updates of m cells
    measure all R^3 once in R^3 / m of them (random cells would miss about 1/e), and the
    host's stride is coprime with R^3 (else the order would repeat early)."""
    import math
    occ = OccupancyGrid(device, R, BOX)
    n = R ** 3
    assert math.gcd(occ.stride, n) == 1
    m = max(1, n // 4 + 1)                  # rounds of m cells; the last one wraps around
    rounds = -(-n // m)
    got = []

    def density(xyz):
        got.append(xyz.get())
        return _up(device, np.zeros(xyz.shape[0]))

    assert occ.occupied_fraction() == 1.0
    for k in range(rounds):
        occ.update(density, key=7 + k, n_points=m, decay=1.0, threshold=0.5, start=k * m)
    cells = []
    for k, p in enumerate(got):
        c, pts = rh.occ_points(m, 7 + k, R, BOX[0], BOX[1] - BOX[0], k * m, occ.stride)
        np.testing.assert_allclose(p, pts, rtol=0, atol=1e-6)
        cells.append(c)
    np.testing.assert_array_equal(np.sort(np.concatenate(cells)[:n]), np.arange(n))
    assert (occ.ema.get() == 0).all()            # every cell measured (density 0)
    assert occ.occupied_fraction() == 0.0


def test_first_occupancy_update_measures_every_cell(device):
    """At occ_warmup the model measures the whole grid (later updates occ_points cells), so a
    fresh run prunes every empty cell at once."""
    cfg = dataclasses.replace(SMALL, occ_warmup=3, occ_every=2, occ_points=5)
    model = HashModel(device, cfg, near=1.5, far=4.5, bbox=BOX, background=(1, 1, 1))
    assert not model.maybe_update_occupancy(2)
    assert (model.occ.ema.get() < 0).all()
    assert model.maybe_update_occupancy(3)
    assert (model.occ.ema.get() >= 0).all()
    assert not model.maybe_update_occupancy(4) and model.maybe_update_occupancy(5)


def _reference_step(model, o, d, target, background=None):
    """Loss and gradients of one step (no jitter) through the float64 references."""
    c = model.config
    enc, net = model.enc, model.net
    con = model.contraction
    off, t, dt, xyz, vdir = rh.march_samples(
        o, d, c.samples, model.near, model.far, model.occ.occ.get(), enc.lo, enc.inv_ext,
        c.occ_res, centre=con.centre if con else None, half=con.half if con else None)
    table = enc.table.get()
    params = net.params.get()
    x_enc = rh.hash_forward(xyz, enc.lo, enc.inv_ext, enc.res_host, table)
    d_enc = rh.sh_encode(vdir)
    sigma, rgb = rn.mlp_forward(params, net.spec, net.layout, x_enc, d_enc)
    if c.train_t_stop > 0:                   # training-time termination, as the model does
        from clrf.hash.model import KEEP_BELOW
        keep, _ = rh.packed_keep(off, dt, sigma, c.train_t_stop)
        if keep.sum() <= KEEP_BELOW * len(t):
            sel = np.concatenate([off[i] + np.arange(k) for i, k in enumerate(keep)]).astype(int)
            off = np.concatenate([[0], np.cumsum(keep)])
            t, dt, xyz, x_enc, d_enc = t[sel], dt[sel], xyz[sel], x_enc[sel], d_enc[sel]
            sigma, rgb = sigma[sel], rgb[sel]
    scale = 1.0 / (3 * o.shape[0])
    bg = model.background if background is None else background
    g = rh.packed_backward(off, t, dt, sigma, rgb, bg, target, scale)
    loss = scale * np.sum(g["sq_err"])
    mb = rn.mlp_backward(params, net.spec, net.layout, x_enc, d_enc, g["sigma"], g["rgb"])
    gt = rh.hash_backward(xyz, enc.lo, enc.inv_ext, enc.res_host, mb["x_enc"], enc.shape)
    return loss, mb["params"], gt, len(t)


def seeded_model(dev, cfg, near=1.5, far=4.5, dense=False, **kw):
    """A model of cfg with random tables, 60 % of the occupancy cells occupied and (dense)
    sigma ~ e^4, so that rays go opaque within a few bins; kw: more HashModel arguments."""
    model = HashModel(dev, cfg, near=near, far=far, bbox=BOX, background=(0.2, 0.5, 1.0), **kw)
    rng = np.random.default_rng(3)
    model.enc.table.set(rng.uniform(-1, 1, model.enc.shape).astype(np.float32))
    if dense:
        p = model.net.params.get()
        p[model.net.layout.layers[model.spec.depth]["b_off"]] = 4.0
        model.net.set_params(p)
    occ = rng.random(cfg.occ_res ** 3) < 0.6
    model.occ.ema.set(np.where(occ, 1.0, 0.0).astype(np.float32))
    model.occ._threshold(0.5)
    return model


@pytest.mark.parametrize("path,contract,dense", [("atomics", "off", False),
                                                 ("owned", "off", False), ("owned", "on", False),
                                                 ("owned", "off", True), ("atomics", "on", True)])
def test_step_gradients_match_reference_chain(device, path, contract, dense):
    """One step's loss and gradients against the float64 chain; dense: opaque rays, so the
    step keeps only the samples in front of transmittance train_t_stop (the chain too)."""
    dev = device.with_tuning(grad_slots=0 if path == "atomics" else 2)
    near, far = (1.5, 4.5) if contract == "off" else (0.05, 60.0)
    model = seeded_model(dev, dataclasses.replace(SMALL, contract=contract), near, far, dense)
    assert (model.contraction is not None) == (contract == "on")
    o, d = _rays(24, seed=4)
    target = np.random.default_rng(5).uniform(0, 1, (24, 3))
    loss, live = model.loss_and_grad(0, _up(dev, o), _up(dev, d), _up(dev, target),
                                     jitter=False)
    rloss, gp, gt, rlive = _reference_step(model, o, d, target)
    assert live == rlive and 0 < live < 24 * SMALL.samples
    if dense:                                 # the termination did drop samples
        from clrf.hash.march import march
        marched = march(dev, model.occ, _up(dev, o), _up(dev, d), SMALL.samples, near, far,
                        contract=model.contraction).m
        assert live < 0.7 * marched, (live, marched)
    assert abs(loss - rloss) <= tol.HASH_STEP_LOSS_RTOL * rloss
    for got, want in ((model.net.grad.get(), gp), (model.enc.grad.get(), gt)):
        assert np.abs(want).max() > 0
        np.testing.assert_allclose(got, want, rtol=0,
                                   atol=tol.HASH_STEP_GRAD_REL_TO_MAX * np.abs(want).max())


@pytest.mark.parametrize("oversample", [1, 2])
def test_render_matches_reference_chain(device, oversample):
    """A render (windows of bins, early termination at T < 1e-4) against the float64 chain at
    samples x render_oversample bin centres: the finer render marches the finer bins."""
    cfg = dataclasses.replace(SMALL, render_oversample=oversample, samples=40)
    model = HashModel(device, cfg, near=1.5, far=4.5, bbox=BOX, background=(0.2, 0.5, 1.0))
    rng = np.random.default_rng(12)
    model.enc.table.set(rng.uniform(-1, 1, model.enc.shape).astype(np.float32))
    model.occ.ema.set(np.where(rng.random(cfg.occ_res ** 3) < 0.7, 1.0, 0.0).astype(np.float32))
    model.occ._threshold(0.5)
    assert model.render_samples == 40 * oversample
    o, d = _rays(32, seed=13)
    out = model.render(o, d)
    enc, net = model.enc, model.net
    off, t, dt, xyz, vdir = rh.march_samples(o, d, model.render_samples, model.near, model.far,
                                             model.occ.occ.get(), enc.lo, enc.inv_ext,
                                             cfg.occ_res)
    assert np.all(np.abs(dt - 3.0 / model.render_samples) < 1e-6) and len(t) > 32
    x_enc = rh.hash_forward(xyz, enc.lo, enc.inv_ext, enc.res_host, enc.table.get())
    sigma, rgb = rn.mlp_forward(net.params.get(), net.spec, net.layout, x_enc, rh.sh_encode(vdir))
    want = rh.packed_forward(off, t, dt, sigma, rgb, model.background)
    # early termination drops at most T_STOP = 1e-4 of a ray's colour
    np.testing.assert_allclose(out["rgb"], want["rgb"], rtol=tol.RENDER_RTOL,
                               atol=tol.RENDER_ATOL + 1e-4)
    np.testing.assert_allclose(out["acc"], want["acc"], rtol=tol.RENDER_RTOL,
                               atol=tol.RENDER_ATOL + 1e-4)


def test_render_chunks_do_not_change_the_image(device, monkeypatch):
    """A render's rays go in chunks sized by RENDER_ROUND_SAMPLES (CPU shapes, GPU shapes) or
    by the caller: the chunking changes how many rays a round marches, never the pixels."""
    import clrf.hash.model as hm
    cfg = dataclasses.replace(SMALL, samples=40)
    model = HashModel(device, cfg, near=1.5, far=4.5, bbox=BOX, background=(0.2, 0.5, 1.0))
    rng = np.random.default_rng(5)
    model.enc.table.set(rng.uniform(-1, 1, model.enc.shape).astype(np.float32))
    o, d = _rays(300, seed=6)
    whole = model.render(o, d)
    for chunk in (1, 37, 128):
        part = model.render(o, d, chunk=chunk)
        for k in ("rgb", "depth", "acc"):
            np.testing.assert_allclose(part[k], whole[k], rtol=1e-6, atol=1e-6, err_msg=k)
    # the default chunk: a round of RENDER_WINDOW bins holds the device's share of samples
    seen = []
    real = model._render_chunk
    monkeypatch.setattr(model, "_render_chunk", lambda od, dd: seen.append(od.shape[0])
                        or real(od, dd))
    window = hm.RENDER_WINDOW
    monkeypatch.setattr(hm, "RENDER_ROUND_SAMPLES", (64 * window, 256 * window))
    gpu = bool(device.tuning.gpu_kernels)
    model.render(o, d)
    assert seen == ([256, 44] if gpu else [64] * 4 + [44])
    for k, v in model.render(o, d).items():
        np.testing.assert_allclose(v, whole[k], rtol=1e-6, atol=1e-6, err_msg=k)


def test_step_on_another_background_matches_reference_chain(device):
    """Random-background training: a step told another background composites on it (loss and
    gradients as the float64 chain with that background), and step_background draws a colour
    per step only when config.random_background is set."""
    model = HashModel(device, SMALL, near=1.5, far=4.5, bbox=BOX, background=(1.0, 1.0, 1.0))
    rng = np.random.default_rng(8)
    model.enc.table.set(rng.uniform(-1, 1, model.enc.shape).astype(np.float32))
    model.occ.ema.set(np.where(rng.random(SMALL.occ_res ** 3) < 0.6, 1.0, 0.0).astype(np.float32))
    model.occ._threshold(0.5)
    o, d = _rays(24, seed=9)
    target = rng.uniform(0, 1, (24, 3))
    bg = model.step_background(3)
    assert bg == model.step_background(3) != model.step_background(4)
    assert len(bg) == 3 and all(0 <= x < 1 for x in bg)
    loss, live = model.loss_and_grad(0, _up(device, o), _up(device, d), _up(device, target),
                                     jitter=False, background=bg)
    rloss, gp, gt, rlive = _reference_step(model, o, d, target, bg)
    white, _, _, _ = _reference_step(model, o, d, target)
    assert live == rlive and abs(rloss - white) > 10 * tol.HASH_STEP_LOSS_RTOL * rloss
    assert abs(loss - rloss) <= tol.HASH_STEP_LOSS_RTOL * rloss
    for got, want in ((model.net.grad.get(), gp), (model.enc.grad.get(), gt)):
        np.testing.assert_allclose(got, want, rtol=0,
                                   atol=tol.HASH_STEP_GRAD_REL_TO_MAX * np.abs(want).max())
    off = HashModel(device, dataclasses.replace(SMALL, random_background=False), near=1.5,
                    far=4.5, bbox=BOX, background=(1.0, 1.0, 1.0))
    assert off.step_background(3) is None


def test_empty_grid_and_rays_missing_the_box(device):
    """An empty occupancy grid (or rays that miss the box) gives the background, a finite loss
    and no update: nothing stalls or divides by zero."""
    cfg = dataclasses.replace(SMALL, occ_warmup=10 ** 6)     # no update refills the grid
    model = HashModel(device, cfg, near=1.5, far=4.5, bbox=BOX, background=(0.3, 0.3, 0.3))
    o, d = _rays(16, seed=5)
    out = model.render(o, -d)               # pointing away from the box
    np.testing.assert_allclose(out["rgb"], 0.3, rtol=0, atol=tol.RENDER_ATOL)
    model.occ.ema.set(np.zeros(SMALL.occ_res ** 3, np.float32))
    model.occ._threshold(1.0)
    before = model.enc.table.get()
    loss = model.train_step(0, _up(device, o), _up(device, d), _up(device, np.ones((16, 3))))
    assert np.isfinite(loss) and abs(loss - 0.49) < 1e-5
    np.testing.assert_array_equal(model.enc.table.get(), before)


def test_checkpoint_round_trip_renders_the_same(device):
    model = HashModel(device, SMALL, near=1.5, far=4.5, bbox=BOX, background=(1, 1, 1), seed=2)
    o, d = _rays(32, seed=6)
    for it in range(3):
        model.train_step(it, _up(device, o), _up(device, d), _up(device, np.full((32, 3), 0.2)))
    st = model.state_dict()
    back = HashModel.from_state_dict(device, st)
    a, b = model.render(o, d), back.render(o, d)
    np.testing.assert_array_equal(a["rgb"], b["rgb"])
    assert back.step == model.step == 3
    bad = dict(st, table=st["table"][:, :5])
    with pytest.raises(ValueError, match="table"):
        HashModel.from_state_dict(device, bad)


@pytest.mark.slow
def test_short_training_improves_on_procedural_scene(device):
    """60 steps on the built-in scene: the loss falls and the test PSNR rises by a real margin
    (iteration-based, not tied to machine speed)."""
    from clrf.data import load_dataset
    from clrf.training.trainer import evaluate, training_rays
    ds = load_dataset(None)
    cfg = HashConfig.from_preset("tiny", batch_rays=256, samples=64, occ_warmup=20,
                                 occ_every=8, occ_points=8192)
    model = HashModel(device, cfg, ds.near, ds.far, ds.bbox, ds.background)
    rays = training_rays(device, ds)
    views = np.asarray(ds.split["test"])[:2]
    p0 = evaluate(model, ds, views)["psnr"]
    losses = []
    for it in range(60):
        bo, bd, bc, _ = rays.batch(it, cfg.batch_rays)
        losses.append(model.train_step(it, bo, bd, bc))
    p1 = evaluate(model, ds, views)["psnr"]
    assert np.all(np.isfinite(losses))
    assert np.mean(losses[-10:]) < 0.5 * np.mean(losses[:5])
    assert p1 > p0 + 5.0, (p0, p1)
    assert model.occ.occupied_fraction() < 1.0     # the occupancy grid did prune


@pytest.mark.slow
def test_hash_through_the_cli(tmp_path, capsys):
    """clrf train --model hash, resume, eval, render and export on the built-in scene, with an
    iteration budget (not a time budget)."""
    import json

    from clrf.outputs import checkpoint
    from clrf.cli.main import main as cli
    out = tmp_path / "h"
    small = ["--set", "hash.batch_rays=256", "--set", "hash.samples=64",
             "--set", "hash.occ_points=8192", "--set", "hash.occ_warmup=20",
             "--set", "train.max_iters=50", "--set", "train.eval_every=1000",
             "--set", "train.eval_views=2"]
    assert cli(["train", "--model", "hash", "--out", str(out), "--max-seconds", "600",
                *small]) == 0
    rows = list(__import__("csv").DictReader(open(out / "metrics.csv")))
    assert rows[-1]["model"].startswith("hash L16 F2 T2^16")
    assert float(rows[-1]["eval_psnr"]) > float(rows[0]["eval_psnr"]) + 3.0
    st = checkpoint.load(out)
    assert st["kind"] == "hash" and st["iteration"] == 50
    assert cli(["train", "--out", str(out), "--resume", "--set", "train.max_iters=60"]) == 0
    assert checkpoint.load(out)["iteration"] == 60
    assert cli(["eval", "--ckpt", str(out), "--max-views", "2",
                "--out", str(tmp_path / "ev.json")]) == 0
    assert len(json.loads((tmp_path / "ev.json").read_text())["views"]) == 2
    assert cli(["render", "--ckpt", str(out), "--views", "orbit", "--frames", "2",
                "--out", str(tmp_path / "f")]) == 0
    assert len(list((tmp_path / "f").glob("orbit_*.png"))) == 2
    assert cli(["export", "--ckpt", str(out), "--points", str(tmp_path / "p.ply"),
                "--n", "2000"]) == 0
    assert (tmp_path / "p.ply").is_file()
    # tools/render_bins.py: the same checkpoint at 1x and 2x render bins
    import sys
    sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tools"))
    from render_bins import main as render_bins
    render_bins(["--ckpt", str(out), "--every", "4", "--oversample", "1,2",
                 "--json", str(tmp_path / "bins.json")])
    rows = json.loads((tmp_path / "bins.json").read_text())["rows"]
    assert [r["bins"] for r in rows] == [64, 128] and all(r["psnr"] > 10 for r in rows)
    capsys.readouterr()
    rc = cli(["train", "--model", "hash", "--out", str(tmp_path / "bad"),
              "--set", "hash.log2_tabel=3"])
    assert rc == 2 and "log2_tabel" in capsys.readouterr().err


def test_ray_range_cuts_far_to_the_box():
    """Unbounded scenes (far 1e10) sample up to the farthest box corner seen from a camera;
    bounded ones keep their far; NDC scenes keep theirs; an impossible range is an error."""
    from types import SimpleNamespace

    from clrf.hash.model import ray_range
    poses = np.tile(np.eye(4, dtype=np.float32), (2, 1, 1))
    poses[0, :3, 3] = (0, 0, 4)
    poses[1, :3, 3] = (3, 0, 0)
    ds = SimpleNamespace(name="s", near=0.1, far=1e10, ndc=False, poses=poses, bbox=BOX)
    near, far = ray_range(ds)
    assert near == 0.1 and abs(far - np.linalg.norm([1, 1, 5])) < 1e-9
    assert ray_range(SimpleNamespace(**{**vars(ds), "far": 3.0})) == (0.1, 3.0)
    # NDC: the sampler walks unit directions; these NDC rays have |d| = 2 (identity poses)
    ndc = SimpleNamespace(**{**vars(ds), "ndc": True, "far": 1.0, "hw": (8, 10),
                             "intrinsics": (10.0, 10.0, 5.0, 4.0), "distortion": None})
    ndc.poses = np.tile(np.eye(4, dtype=np.float32), (2, 1, 1))
    from clrf.data.cameras import ndc_reach
    assert ray_range(ndc) == (0.1, 1.0)
    near, far = ray_range(ndc, ndc_far=ndc_reach(ndc))
    assert near == 0.1 and abs(far - 2.0 * 1.005) < 1e-6
    with pytest.raises(ValueError, match="near"):
        ray_range(SimpleNamespace(**{**vars(ds), "near": 50.0}))


def test_contraction_is_chosen_for_unbounded_scenes():
    """hash.contract auto: on for real360 captures, off for the rest; contracted scenes sample
    out to CONTRACT_FAR box half-sizes past the farthest camera; on is refused for NDC."""
    from types import SimpleNamespace

    from clrf.hash.model import CONTRACT_FAR, ray_range, resolve_contract
    poses = np.tile(np.eye(4, dtype=np.float32), (2, 1, 1))
    poses[1, :3, 3] = (0.6, 0, 0.8)
    ds = SimpleNamespace(name="s", near=0.02, far=3.46, ndc=False, poses=poses, bbox=BOX,
                         preset="real360")
    assert resolve_contract(SMALL, ds).contract == "on"
    assert resolve_contract(SMALL, SimpleNamespace(**{**vars(ds), "preset": "synthetic"})
                            ).contract == "off"
    assert resolve_contract(dataclasses.replace(SMALL, contract="off"), ds).contract == "off"
    with pytest.raises(ValueError, match="hash.contract=on does not apply to NDC"):
        resolve_contract(dataclasses.replace(SMALL, contract="on"),
                         SimpleNamespace(**{**vars(ds), "ndc": True}))
    near, far = ray_range(ds, contract=True)
    assert near == 0.02 and abs(far - (1.0 + CONTRACT_FAR)) < 1e-6   # float32 poses
    with pytest.raises(ConfigError, match="hash.contract"):
        build_config(overrides={"hash": {"contract": "yes"}})


def test_finest_level_follows_the_image_width():
    """hash.max_res 0 (auto, the full preset's): object-centric (synthetic) scenes get the
    published 2048 cells at 800 pixels wide, in proportion below (never above 2048 nor below
    min_res); contracted, NDC and other scenes 2048; a set value stays; a model built without a
    dataset gets 2048."""
    from types import SimpleNamespace

    from clrf.hash.model import resolve_max_res
    full = HashConfig()
    assert full.max_res == 0 and not [f for ok, f, _ in full.checks() if not ok]

    def scene(width, preset="synthetic", ndc=False):
        return SimpleNamespace(hw=(width * 3 // 4, width), preset=preset, ndc=ndc)

    for width, want in ((800, 2048), (400, 1024), (1600, 2048), (100, 256), (4, 16)):
        assert resolve_max_res(full, scene(width)).max_res == want, width
    assert resolve_max_res(full, scene(400, "real360")).max_res == 2048
    assert resolve_max_res(full, scene(400, ndc=True)).max_res == 2048
    assert resolve_max_res(dataclasses.replace(full, contract="on"), scene(400)).max_res == 2048
    assert resolve_max_res(dataclasses.replace(full, max_res=300), scene(400)).max_res == 300
    with pytest.raises(ConfigError, match="hash.min_res"):
        build_config(overrides={"hash": {"min_res": 64, "max_res": 32}})


def test_auto_finest_level_without_a_dataset(device):
    model = HashModel(device, dataclasses.replace(SMALL, max_res=0, min_res=2), near=1.5,
                      far=4.5, bbox=BOX)
    assert model.config.max_res == 2048 and model.enc.res_host[-1] == 2048


def test_memory_guard_names_the_hash_stage(device):
    """The memory guard estimates a hash run (tables + Adam, MLP activations) and names the
    fix; the tiny preset fits a normal device."""
    from dataclasses import replace as dreplace

    from clrf.training.budget import MemoryBudgetError, check_training_fits
    cfg = build_config("tiny", overrides={"train": {"model": "hash"}})
    plan = check_training_fits(device.caps, device.is_cpu, cfg, 100 * 100 * 100,
                               device.tuning)
    st = next(s for s in plan.stages if s.name.startswith("hash training"))
    assert st.total > 4 * 4 * 16 * (1 << 16) * 2     # at least the tables and their Adam state
    big = build_config(overrides={"train": {"model": "hash"}, "hash": {"log2_table": 24}})
    small = dreplace(device.caps, global_mem_size=1 << 30, max_alloc_size=1 << 30)
    with pytest.raises(MemoryBudgetError, match="hash training.*hash.log2_table"):
        check_training_fits(small, False, big, 1000)


@pytest.mark.slow
def test_bonsai_contracted_through_the_cli(scene, tmp_path):
    """`clrf train --model hash` on the real 360 scene contracts it (hash.contract auto), the
    loss falls over 40 steps, and eval and a checkpoint round trip work."""
    import csv
    import json

    from clrf.cli.main import main as cli
    from clrf.outputs import checkpoint
    out = tmp_path / "run"
    rc = cli(["train", "--model", "hash", "--data", str(scene("bonsai_800")), "--out",
              str(out), "--max-seconds", "600", "--set", "train.max_iters=40",
              "--set", "train.downscale=8", "--set", "hash.preset=tiny",
              "--set", "hash.log2_table=12", "--set", "hash.samples=64",
              "--set", "hash.batch_rays=512", "--set", "train.eval_every=0.5",
              "--set", "train.eval_views=1", "--set", "train.max_train_images=20"])
    assert rc == 0
    st = checkpoint.load(out)
    assert st["config"]["contract"] == "on" and st["far"] > 500
    rows = list(csv.DictReader(open(out / "metrics.csv")))
    assert "contracted scene" in rows[-1]["model"]
    losses = [float(r["train_loss"]) for r in rows if r["train_loss"]]
    assert len(losses) >= 2 and losses[-1] < losses[0], losses
    assert cli(["eval", "--ckpt", str(out), "--max-views", "1"]) == 0
    assert np.isfinite(json.loads((out / "eval_cli.json").read_text())["psnr"])


def test_batch_adapts_to_live_samples(device):
    """hash.batch_samples: the first step takes batch_samples / samples rays (every bin live),
    the next ones batch_samples over the live samples per ray of the last step; the count
    survives a checkpoint; batch_samples 0 keeps batch_rays."""
    from clrf.hash.model import BATCH_RAYS_RANGE
    cfg = dataclasses.replace(SMALL, batch_samples=12 * 1024, occ_warmup=10 ** 6)
    model = HashModel(device, cfg, near=1.5, far=4.5, bbox=BOX)
    assert model.batch_size == 1024
    o, d = _rays(model.batch_size, seed=7)
    rng = np.random.default_rng(7)
    model.occ.ema.set(np.where(rng.random(cfg.occ_res ** 3) < 0.3, 1.0, 0.0).astype(np.float32))
    model.occ._threshold(0.5)
    _, live = model.loss_and_grad(0, _up(device, o), _up(device, d),
                                  _up(device, rng.uniform(0, 1, (len(o), 3))))
    per_ray = live / len(o)
    assert 0 < per_ray < 6
    want = min(BATCH_RAYS_RANGE[1], round(cfg.batch_samples / per_ray / 256) * 256)
    assert model.batch_size == want > 1024
    again = HashModel.from_state_dict(device, model.state_dict())
    assert again.batch_size == want
    fixed = HashModel(device, SMALL, near=1.5, far=4.5, bbox=BOX)
    fixed.loss_and_grad(0, _up(device, o), _up(device, d), _up(device, np.ones((len(o), 3))))
    assert fixed.batch_size == SMALL.batch_rays


def test_ndc_rays_reach_infinity(scene):
    """fern (NDC): every training ray, walked along its unit direction to the models' far,
    reaches z' = 1 (infinity); with the dataset's far (1) it stopped near z' = 0, so the NeRF
    and hash models never sampled the far half of NDC space."""
    from clrf.data import load_dataset
    from clrf.data.cameras import ndc_reach, view_rays
    ds = load_dataset(scene("fern"))
    far = ndc_reach(ds)
    o, d = view_rays(ds, ds.poses, 2)
    u = d / np.linalg.norm(d, axis=1, keepdims=True)
    z_end = o[:, 2] + far * u[:, 2]
    # rays with a shorter |d| run past z' = 1: those bins leave the box and are dropped (on
    # fern |d| spans 2.00-2.14, so up to ~7 % of a ray's bins)
    assert z_end.min() >= 1.0 and z_end.max() < 1.2, (z_end.min(), z_end.max())
    assert (o[:, 2] + ds.far * u[:, 2]).max() < 0.1      # the old far: half the depth range


def test_older_checkpoint_config_keeps_how_it_trained():
    """A checkpoint's hash config from before batch_samples and contract existed resumes with
    a fixed batch and no contraction, not today's adaptive / auto defaults."""
    old = dataclasses.asdict(HashConfig.from_preset("tiny"))
    del old["batch_samples"], old["contract"], old["lr_schedule"], old["train_t_stop"]
    c = HashConfig.from_dict(old)
    assert c.batch_samples == 0 and c.contract == "off" and c.lr_schedule == "steps"
    assert c.train_t_stop == 0.0
    full = HashConfig.from_dict(dataclasses.asdict(HashConfig()))
    assert full.batch_samples == HashConfig().batch_samples and full.train_t_stop == 1e-4


def test_budget_learning_rate_follows_the_run(device):
    """lr_schedule "budget": the full lr until lr_hold of the budget (seconds or iterations,
    whichever is further along) is spent, then exponentially down to lr * lr_final at its
    end; "steps" keeps the fall over lr_decay_steps; a bad schedule name is refused."""
    from types import SimpleNamespace

    from clrf.hash.model import budget_lr
    from clrf.training.config import TrainConfig
    from clrf.training.trainer import Trainer
    assert budget_lr(1e-2, 0.03, 0.5, 0.0) == budget_lr(1e-2, 0.03, 0.5, 0.5) == 1e-2
    assert budget_lr(1e-2, 0.03, 0.5, 0.75) == pytest.approx(1e-2 * 0.03 ** 0.5, rel=1e-12)
    assert budget_lr(1e-2, 0.03, 0.5, 1.0) == pytest.approx(3e-4, rel=1e-12)
    assert budget_lr(1e-2, 0.03, 0.5, 2.0) == pytest.approx(3e-4, rel=1e-12)
    model = HashModel(device, SMALL, near=1.5, far=4.5, bbox=BOX)
    assert SMALL.lr_schedule == "budget" and model.lr_at(0) == SMALL.lr   # outside a trainer
    train = TrainConfig(max_seconds=100.0, max_iters=1000)
    for seconds, it, progress in ((10.0, 100, 0.1), (80.0, 100, 0.8), (10.0, 900, 0.9),
                                  (150.0, 0, 1.0)):
        # the trainer's budget hook: the larger of seconds and iterations over their limits
        run = SimpleNamespace(cfg=SimpleNamespace(train=train), seconds=seconds, iteration=it,
                              rays=None)
        model.on_iteration(it, Trainer.budget(run))
        assert model.progress == pytest.approx(progress)
        assert model.lr_at(it) == pytest.approx(
            budget_lr(SMALL.lr, SMALL.lr_final, SMALL.lr_hold, progress))
    steps = HashModel(device, dataclasses.replace(SMALL, lr_schedule="steps",
                                                  lr_decay_steps=100), near=1.5, far=4.5,
                      bbox=BOX)
    steps.progress = 1.0
    assert steps.lr_at(100) == pytest.approx(SMALL.lr * 0.1)
    with pytest.raises(ConfigError, match="hash.lr_schedule"):
        build_config(overrides={"hash": {"lr_schedule": "cosine"}})
    with pytest.raises(ConfigError, match="hash.lr_hold"):
        build_config(overrides={"hash": {"lr_hold": 1.0}})


def test_per_step_arrays_come_from_the_device_pool(device):
    """The packed samples, encodings and MLP outputs of a step are pool allocations (their
    buffers reused from step to step, not fresh heap blocks of a new size each step), and a
    render hands what the pool holds back. No jitter and no occupancy update: both steps pack
    the same samples, so the same sizes are asked of the pool."""
    cfg = dataclasses.replace(SMALL, perturb=False, occ_warmup=10 ** 6)
    model = HashModel(device, cfg, near=1.5, far=4.5, bbox=BOX)
    o, d = _rays(64, seed=3)
    model.train_step(0, _up(device, o), _up(device, d), _up(device, np.ones((64, 3))))
    assert device.pool.held_blocks > 0          # a step's buffers, freed back into the pool
    blocks = device.pool.held_blocks + device.pool.active_blocks
    model.train_step(1, _up(device, o), _up(device, d), _up(device, np.ones((64, 3))))
    assert device.pool.held_blocks + device.pool.active_blocks == blocks   # reused, not grown
    model.render(o, d)
    assert device.pool.held_blocks == 0
