"""hash.exposure in the hash model: the marcher's backward with the transform's target and the
background's share is the gradient through the transform (host-sized and bounded steps), a run
learns each image's gain and keeps the transforms in its checkpoint, reports NeRF-W's
half-fitted protocol and resumes, and bad settings are one clear error (the kernels:
tests/test_hash_exposure.py)."""
import dataclasses
import json

import numpy as np
import pytest

from clrf.references import reference_exposure as ref
from clrf.runtime.programs import upload

def _grads(m, o, d, t, index=None):
    """(loss, dL/dnetwork, dL/dtable) of one batch (the model's gradient buffers cleared)."""
    m.enc.grad.fill(0)
    loss, _ = m.loss_and_grad(0, o, d, t, jitter=False, index=index)
    return float(loss), m.net.grad.get().astype(np.float64), m.enc.grad.get().astype(np.float64)


@pytest.mark.parametrize("bounded", [False, True], ids=["host", "bounded"])
@pytest.mark.parametrize("masked", [True, False], ids=["masked", "plain"])
def test_model_gradient_through_the_transform(device, masked, bounded):
    """The marcher's backward on black with eff, plus the background's share, is the gradient
    through the transform: under the identity it is the model's plain gradient; without alpha,
    under A = g I it is g^2 times the plain gradient against target / g (L = |g x - t|^2 =
    g^2 |x - t/g|^2), the background included; with a dense field, a step's samples go opaque
    and the background matters little, so the rays here stop half-way."""
    from test_hash_model import SMALL, _rays, _up, seeded_model
    q = device.queue
    B = 64
    o, d = _rays(B, seed=5)
    t = np.random.default_rng(6).uniform(0.1, 0.9, (B, 3)).astype(np.float32)
    idx = upload(q, (np.arange(B) % 4 * 10 + np.arange(B) % 10).astype(np.int32))
    plain = seeded_model(device, SMALL, bounded=bounded)
    want = _grads(plain, _up(device, o), _up(device, d), _up(device, t))
    m = seeded_model(device, dataclasses.replace(SMALL, exposure=True), bounded=bounded)
    m.attach_corrections(4, 10, masked=masked)
    exp = m.corrections.get("exposure")
    exp.lr = 1e-30
    got = _grads(m, _up(device, o), _up(device, d), _up(device, t), idx)
    assert got[0] == pytest.approx(want[0], rel=1e-5)
    for g, w in zip(got[1:], want[1:]):
        np.testing.assert_allclose(g, w, rtol=2e-4, atol=2e-4 * np.abs(w).max())
    if masked:
        return
    gain = 1.3
    P = np.tile(ref.IDENTITY, (4, 1)).astype(np.float32)
    P[:, [0, 4, 8]] = gain
    exp.P.set(P)
    got = _grads(m, _up(device, o), _up(device, d), _up(device, t), idx)
    ref_g = _grads(plain, _up(device, o), _up(device, d), _up(device, t / gain))
    assert got[0] == pytest.approx(gain ** 2 * ref_g[0], rel=1e-5)
    for g, w in zip(got[1:], ref_g[1:]):
        np.testing.assert_allclose(g, gain ** 2 * w, rtol=2e-4,
                                   atol=2e-4 * gain ** 2 * np.abs(w).max())


def _scene(gains):
    from clrf.data import load_dataset
    ds = load_dataset(None)
    ds.images = ds.images.copy()
    train = ds.split["train"]
    for k, g in gains.items():
        ds.images[train[k]] = np.clip(ds.images[train[k]] * g, 0, 1)
    return ds


@pytest.mark.parametrize("matrix", ["full", "diagonal"])
@pytest.mark.slow
def test_training_learns_each_images_gain(device, matrix):
    """Training images scaled by per-image gains: their transforms' diagonals order as the
    gains do (with hash.exposure_matrix=diagonal the other entries of A stay 0); the
    checkpoint keeps them."""
    from clrf import registry
    from clrf.hash.model import HashModel
    from clrf.training.config import build_config
    from clrf.training.trainer import train_on_batch, training_rays
    gains = {0: 0.6, 1: 1.4, 2: 0.7, 3: 1.3}
    ds = _scene(gains)
    cfg = build_config("procedural", overrides={
        "train": {"model": "hash"},
        "hash": {"exposure": True, "lr_exposure": 0.01, "batch_samples": 0,
                 "batch_rays": 1024, "exposure_matrix": matrix}})
    m = registry.get("hash").create(device, cfg, ds, ds.background)
    exp = m.corrections.get("exposure")
    assert m.ray_index and exp.n_images == len(ds.split["train"])
    rays = training_rays(device, ds)
    for it in range(80):
        assert np.isfinite(train_on_batch(m, rays, 0, it, m.batch_size))
    rows = exp.rows()
    diag = {k: rows[k][[0, 4, 8]].mean() for k in gains}
    assert min(diag[1], diag[3]) > max(diag[0], diag[2]), diag
    assert exp.matrix == ref.MATRICES.index(matrix)
    if matrix == "diagonal":
        assert np.all(rows[:, ~ref.TRAINED_DIAGONAL] == 0)
    else:
        assert np.any(rows[:, ~ref.TRAINED_DIAGONAL] != 0)
    back = HashModel.from_state_dict(device, m.state_dict()).corrections.get("exposure")
    assert back.matrix == exp.matrix
    assert np.array_equal(back.rows(), rows) and back.steps == 80
    assert back.pixels == exp.pixels


@pytest.mark.slow
def test_a_hash_run_with_exposure_reports_the_half_fitted_protocol(tmp_path):
    from clrf.cli.main import main as cli
    out = tmp_path / "run"
    assert cli(["--quiet", "train", "--model", "hash", "--out", str(out), "--max-seconds", "3",
                "--set", "hash.exposure=true", "--set", "train.eval_every=100"]) == 0
    ev = json.loads((out / "eval.json").read_text())
    assert np.isfinite(ev["psnr_half_fitted"]) and np.isfinite(ev["psnr_right_half"])
    # the built-in scene has one exposure: the steady check (at 0.2 of the budget) found so
    found = ev["exposure_correction"]
    assert found["steady"] is True and 0 <= found["gain_spread"] < 0.05, found
    # resumed: the transforms and their Adam state carry on
    assert cli(["--quiet", "train", "--out", str(out), "--resume", "--max-seconds", "4"]) == 0
    assert cli(["--quiet", "eval", "--ckpt", str(out), "--max-views", "2", "--lpips", "none",
                "--out", str(tmp_path / "e.json")]) == 0
    assert "psnr_half_fitted" in json.loads((tmp_path / "e.json").read_text())


@pytest.mark.parametrize("key,value", [("lr_exposure", 0.0), ("lr_exposure", -1.0),
                                       ("exposure_reg", -0.1), ("exposure_matrix", "mixed"),
                                       ("exposure_steady_spread", -1.0),
                                       ("exposure_steady_rate", 0.0)])
def test_bad_settings_are_one_clear_error(key, value, capsys, tmp_path):
    from clrf.cli.main import main as cli
    rc = cli(["--quiet", "train", "--model", "hash", "--out", str(tmp_path / "run"),
              "--set", "hash.exposure=true", "--set", f"hash.{key}={value}",
              "--max-seconds", "1"])
    err = capsys.readouterr().err
    assert rc == 2 and err.count("clrf: error:") == 1 and f"hash.{key}" in err, err
