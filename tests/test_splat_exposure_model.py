"""splat.exposure in the model: a training run learns each image's gain and keeps the
transforms in its checkpoint, the final evaluation reports NeRF-W's half-fitted protocol, and a
bad setting is one clear error (the kernels: tests/test_splat_exposure.py)."""
import json

import numpy as np
import pytest


def _model(device, **splat):
    from clrf import registry
    from clrf.data import load_dataset
    from clrf.training.config import build_config
    ds = load_dataset(None)
    cfg = build_config("procedural", overrides={"train": {"model": "splat"},
                                                "splat": {"preset": "tiny", **splat}})
    return registry.get("splat").create(device, cfg, ds, ds.background), ds


def test_training_learns_each_images_gain(device):
    """Training images scaled by per-image gains: the transforms of those images move toward
    their gain (A's diagonal), and stay near the identity for the untouched ones."""
    m, ds = _model(device, init_points=2000, exposure=True, lr_exposure=0.05)
    gains = {int(v): g for v, g in zip(ds.split["train"][:6], (0.6, 1.4, 0.7, 1.3, 0.8, 1.2))}
    ds.images = ds.images.copy()
    for v, g in gains.items():
        ds.images[v] = ds.images[v] * g
    m.attach(ds)
    for it in range(6 * len(ds.split["train"])):
        assert np.isfinite(m.train_step(it))
    rows = m.exposure.rows()
    diag = {v: rows[v][[0, 4, 8]].mean() for v in gains}
    brighter = [v for v, g in gains.items() if g > 1]
    darker = [v for v, g in gains.items() if g < 1]
    assert min(diag[v] for v in brighter) > max(diag[v] for v in darker), diag
    # the checkpoint keeps them
    state = m.state_dict()
    from clrf.splat.model import SplatModel
    back = SplatModel.from_state_dict(device, state)
    assert np.array_equal(back.exposure.rows(), rows)
    assert np.array_equal(back.exposure.steps, m.exposure.steps)


@pytest.mark.parametrize("key,value", [("lr_exposure", 0.0), ("lr_exposure", -1.0),
                                       ("exposure_reg", -0.1),
                                       ("exposure_clip_inward", "true")])
def test_bad_settings_are_one_clear_error(key, value, capsys, tmp_path):
    from clrf.cli.main import main as cli
    rc = cli(["--quiet", "train", "--model", "splat", "--out", str(tmp_path / "run"),
              "--set", "splat.exposure=true",
              "--set", f"splat.{key}={value}", "--max-seconds", "1"])
    err = capsys.readouterr().err
    assert rc == 2 and err.count("clrf: error:") == 1 and f"splat.{key}" in err, err


@pytest.mark.parametrize("model", ["grid", "nerf"])
def test_exposure_on_a_model_without_it_is_one_clear_error(model, capsys, tmp_path):
    from clrf.cli.main import main as cli
    rc = cli(["--quiet", "train", "--model", model, "--out", str(tmp_path / "run"),
              "--set", f"{model}.exposure=true",
              "--max-seconds", "1"])
    err = capsys.readouterr().err
    assert rc == 2 and err.count("clrf: error:") == 1 and f"{model}.exposure" in err, err


def test_a_run_with_exposure_reports_the_half_fitted_protocol(tmp_path):
    from clrf.cli.main import main as cli
    out = tmp_path / "run"
    assert cli(["--quiet", "train", "--model", "splat", "--out", str(out), "--max-seconds", "3",
                "--set", "splat.exposure=true", "--set", "splat.init_points=1000",
                "--set", "train.eval_every=100"]) == 0
    ev = json.loads((out / "eval.json").read_text())
    assert np.isfinite(ev["psnr_half_fitted"]) and np.isfinite(ev["psnr_right_half"])
    assert all("psnr_half_fitted" in v for v in ev["views"])
    # the run resumes with its transforms and evaluates again
    assert cli(["--quiet", "eval", "--ckpt", str(out), "--max-views", "2", "--lpips", "none",
                "--out", str(tmp_path / "e.json")]) == 0
    assert "psnr_half_fitted" in json.loads((tmp_path / "e.json").read_text())
