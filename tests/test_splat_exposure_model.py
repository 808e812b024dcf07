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


@pytest.mark.parametrize("matrix", ["full", "gain"])
@pytest.mark.slow
def test_training_learns_each_images_gain(device, matrix):
    """Training images scaled by per-image gains: the transforms of those images move toward
    their gain (A's diagonal), and stay near the identity for the untouched ones; with
    splat.exposure_matrix=gain the other entries stay exactly as the identity has them."""
    m, ds = _model(device, init_points=2000, exposure=True, lr_exposure=0.05,
                   exposure_matrix=matrix)
    gains = {int(v): g for v, g in zip(ds.split["train"][:6], (0.6, 1.4, 0.7, 1.3, 0.8, 1.2))}
    ds.images = ds.images.copy()
    for v, g in gains.items():
        ds.images[v] = ds.images[v] * g
    m.attach(ds)
    for it in range(6 * len(ds.split["train"])):
        assert np.isfinite(m.train_step(it))
    exp = m.corrections.get("exposure")
    rows = exp.rows()
    diag = {v: rows[v][[0, 4, 8]].mean() for v in gains}
    brighter = [v for v, g in gains.items() if g > 1]
    darker = [v for v, g in gains.items() if g < 1]
    assert min(diag[v] for v in brighter) > max(diag[v] for v in darker), diag
    from clrf.references.reference_exposure import IDENTITY, TRAINED
    fixed = ~TRAINED[2]
    assert np.all(rows[:, fixed] == IDENTITY[fixed]) == (matrix == "gain")
    # the checkpoint keeps them
    state = m.state_dict()
    from clrf.splat.model import SplatModel
    back = SplatModel.from_state_dict(device, state).corrections.get("exposure")
    assert np.array_equal(back.rows(), rows)
    assert np.array_equal(back.steps, exp.steps)
    assert back.matrix == exp.matrix


def test_exposure_clip_on_by_default_but_not_for_older_checkpoints():
    """splat.exposure_clip is on by default; a checkpoint written before the setting existed
    resumes unclipped, as it was trained; one that records it keeps what it records."""
    from clrf.splat.config import SplatConfig
    assert SplatConfig().exposure_clip is True
    old = {k: v for k, v in SplatConfig(exposure=True).__dict__.items()
           if k not in ("exposure_clip", "exposure_clip_inward")}
    assert SplatConfig.from_dict(old).exposure_clip is False
    assert SplatConfig.from_dict(dict(old, exposure_clip=True)).exposure_clip is True


def test_exposure_gain_by_default_but_not_for_older_checkpoints():
    """splat.exposure_matrix is "gain" by default; a checkpoint written before the setting
    existed resumes with the full matrix it trained; one that records it keeps what it
    records."""
    from clrf.splat.config import SplatConfig
    assert SplatConfig().exposure_matrix == "gain"
    old = {k: v for k, v in SplatConfig(exposure=True).__dict__.items()
           if k != "exposure_matrix"}
    assert SplatConfig.from_dict(old).exposure_matrix == "full"
    assert SplatConfig.from_dict(dict(old, exposure_matrix="diagonal")).exposure_matrix == \
        "diagonal"


@pytest.mark.parametrize("key,value", [("lr_exposure", 0.0), ("lr_exposure", -1.0),
                                       ("exposure_reg", -0.1),
                                       ("exposure_matrix", "mixed"),
                                       ("exposure_clip_inward", "true")])
def test_bad_settings_are_one_clear_error(key, value, capsys, tmp_path):
    from clrf.cli.main import main as cli
    rc = cli(["--quiet", "train", "--model", "splat", "--out", str(tmp_path / "run"),
              "--set", "splat.exposure=true", "--set", "splat.exposure_clip=false",
              "--set", f"splat.{key}={value}", "--max-seconds", "1"])
    err = capsys.readouterr().err
    assert rc == 2 and err.count("clrf: error:") == 1 and f"splat.{key}" in err, err


def test_a_correction_on_a_model_without_it_is_one_clear_error(capsys, tmp_path):
    """Every model takes exposure and pose_opt now; the bilateral grid is the splat model's
    alone (it needs whole views): asking the grid for one is one clear error, exit 2."""
    from clrf.cli.main import main as cli
    rc = cli(["--quiet", "train", "--model", "grid", "--out", str(tmp_path / "run"),
              "--set", "grid.bilateral_grid=true", "--max-seconds", "1"])
    err = capsys.readouterr().err
    assert rc == 2 and err.count("clrf: error:") == 1 and "grid.bilateral_grid" in err, err
    assert not (tmp_path / "run").exists()


@pytest.mark.slow
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
    e = json.loads((tmp_path / "e.json").read_text())
    assert "psnr_half_fitted" in e
    assert np.isfinite(ev["psnr_shared_gain"]) and len(ev["shared_gain"]) == 3
    # `clrf eval` renders a view a call; its one gain pools them as one call over both does
    from clrf.runtime.device import Device
    from clrf.training.models import checkpoint_dataset, load_model
    from clrf.training.trainer import evaluate
    model, state, _ = load_model(Device(None), str(out / "ckpt.npz"))
    ds = checkpoint_dataset(state, None)
    both = evaluate(model, ds, [v["view"] for v in e["views"]], half_fitted=True)
    np.testing.assert_allclose(e["shared_gain"], both["shared_gain"], rtol=1e-6)
    np.testing.assert_allclose(e["psnr_shared_gain"], both["psnr_shared_gain"], rtol=1e-6)


@pytest.mark.parametrize("no_clip", [False, True], ids=["clipped", "no-clip"])
def test_perturb_capture_changes_exposure_as_recorded(tmp_path, no_clip):
    """tools/perturb_capture.py --exposure: every training image is its source times the
    recorded gain and channel factors, rounded to 8 bits and clipped as a camera would (alpha
    and the test images untouched); --no-clip divides every gain by 1.65, so that nothing
    clips; --no-clip without --exposure is refused."""
    import subprocess
    import sys
    from pathlib import Path

    import imageio.v3 as iio
    src = tmp_path / "src"
    rng = np.random.default_rng(5)
    for split, n in (("train", 12), ("test", 2)):
        (src / split).mkdir(parents=True)
        frames = []
        for i in range(n):
            img = rng.integers(0, 256, (6, 5, 4), dtype=np.uint8)
            img[0, 0, :3] = 255                     # a white pixel: clips at any gain > 1
            iio.imwrite(src / split / f"r_{i}.png", img)
            frames.append({"file_path": f"./{split}/r_{i}",
                           "transform_matrix": np.eye(4).tolist()})
        (src / f"transforms_{split}.json").write_text(json.dumps(
            {"camera_angle_x": 0.7, "frames": frames}))
    tool = Path(__file__).resolve().parents[1] / "tools" / "perturb_capture.py"
    out = tmp_path / "out"
    args = [sys.executable, str(tool), str(src), str(out), "--exposure"]
    subprocess.run(args + (["--no-clip"] if no_clip else []), check=True, capture_output=True)
    rec = json.loads((out / "perturbation.json").read_text())
    assert rec["no_clip"] is no_clip and len(rec["frames"]) == 12
    clipped = 0
    for i, f in enumerate(rec["frames"]):
        a = iio.imread(src / "train" / f"r_{i}.png").astype(np.float64)
        b = iio.imread(out / "train" / f"r_{i}.png").astype(np.float64)
        k = f["gain"] * np.asarray(f["channel"])
        want = a[..., :3] * k
        clipped += int((want > 255.0 + 1e-9).any())
        np.testing.assert_allclose(b[..., :3], np.clip(want, 0, 255), atol=0.5 + 1e-9)
        assert np.array_equal(a[..., 3], b[..., 3])
        lo, hi = (0.6 * 0.9, 1.5 * 1.1)
        if no_clip:
            lo, hi = lo / 1.65, hi / 1.65
        assert np.all((k >= lo) & (k <= hi + 1e-12))
    assert (clipped == 0) if no_clip else (clipped > 0)
    for i in range(2):
        assert np.array_equal(iio.imread(src / "test" / f"r_{i}.png"),
                              iio.imread(out / "test" / f"r_{i}.png"))
    p = subprocess.run([sys.executable, str(tool), str(src), str(tmp_path / "x"), "--no-clip"],
                       capture_output=True, text=True)
    assert p.returncode == 2 and "--no-clip goes with --exposure" in p.stderr


def test_seeded_rows_hold_until_their_budget_fraction_then_learn(device):
    """Exposure.seed puts rows in place of the identity; while the model's budget fraction is
    below the hold, training leaves them (and their step counts) as seeded, and the scene
    still trains; from the hold on they learn; the checkpoint keeps the hold."""
    from clrf.references.reference_exposure import IDENTITY
    m, ds = _model(device, init_points=1000, exposure=True)
    m.attach(ds)
    seeded = np.tile(IDENTITY, (len(ds.images), 1))
    seeded[:, [0, 4, 8]] = np.random.default_rng(2).uniform(0.8, 1.2, (len(ds.images), 3))
    exp = m.corrections.get("exposure")
    exp.seed(seeded, hold_until=0.5)
    m.progress = 0.2
    before = {k: np.array(v) for k, v in m.host_params().items()}
    n = len(ds.split["train"])
    for it in range(n + 3):    # a whole pass: recentring leaves held rows alone
        assert np.isfinite(m.train_step(it))
    np.testing.assert_array_equal(exp.rows(), seeded.astype(np.float32))
    assert not exp.steps.any()
    after = m.host_params()
    assert any(not np.array_equal(after[k], before[k]) for k in before)   # the scene trained
    from clrf.splat.model import SplatModel
    back = SplatModel.from_state_dict(device, m.state_dict())
    assert back.corrections.get("exposure").hold_until == 0.5
    m.progress = 0.5
    for it in range(n + 3, n + 9):
        m.train_step(it)
    assert exp.steps.sum() == 6
    assert not np.array_equal(exp.rows(), seeded.astype(np.float32))
    with pytest.raises(ValueError, match="finite rows"):
        exp.seed(seeded[:-1])


@pytest.mark.parametrize("key,value", [("exposure_calibrate", 0.6),
                                       ("exposure_calibrate", -0.1),
                                       ("exposure_calibrate_downscale", 0),
                                       ("exposure_calibrate_hold", 1.5)])
def test_bad_calibration_settings_are_one_clear_error(key, value, capsys, tmp_path):
    from clrf.cli.main import main as cli
    rc = cli(["--quiet", "train", "--model", "splat", "--out", str(tmp_path / "run"),
              "--set", "splat.exposure=true", "--set", f"splat.{key}={value}",
              "--max-seconds", "1"])
    err = capsys.readouterr().err
    assert rc == 2 and err.count("clrf: error:") == 1 and f"splat.{key}" in err, err
    assert not (tmp_path / "run").exists()


@pytest.mark.slow
def test_calibration_by_default_only_with_the_transforms(tmp_path):
    """splat.exposure_calibrate is on by default and acts only with splat.exposure: a run
    without the transforms neither calibrates nor shortens its budget; a checkpoint from
    before the setting resumes without one; the calibration's resolution keeps 32 pixels a
    side."""
    from clrf.cli.main import main as cli
    from clrf.splat.config import SplatConfig
    from clrf.training.calibrate import calibration_factor
    from clrf.training.config import build_config
    assert SplatConfig().exposure_calibrate > 0
    old = {k: v for k, v in SplatConfig().__dict__.items() if k != "exposure_calibrate"}
    assert SplatConfig.from_dict(old).exposure_calibrate == 0
    cfg = build_config("procedural", overrides={"train": {"model": "splat"}})
    assert [calibration_factor(cfg, hw) for hw in ((400, 600), (64, 64), (31, 500))] == [8, 2, 1]
    out = tmp_path / "run"
    assert cli(["--quiet", "train", "--model", "splat", "--out", str(out), "--max-seconds", "2",
                "--set", "splat.init_points=500", "--set", "train.final_eval=false"]) == 0
    assert not (out / "calibration").exists()
    assert json.loads((out / "config.json").read_text())["train"]["max_seconds"] == 2


def test_downscaled_dataset_scales_images_coverage_and_intrinsics():
    from clrf.data import load_dataset
    from clrf.training.calibrate import downscaled
    ds = load_dataset(None)
    ds.alpha = np.random.default_rng(0).uniform(0, 1, ds.images.shape[:3]).astype(np.float32)
    small = downscaled(ds, 4)
    H, W = ds.hw
    assert small.hw == (H // 4, W // 4) and small.alpha.shape == (len(ds.images), H // 4, W // 4)
    np.testing.assert_allclose(small.intrinsics, np.asarray(ds.intrinsics) / 4)
    np.testing.assert_allclose(small.images[3, 1, 2],
                               np.asarray(ds.images[3])[4:8, 8:12].mean((0, 1)), rtol=1e-6)
    np.testing.assert_allclose(small.alpha[5, 2, 0], ds.alpha[5, 8:12, 0:4].mean(), rtol=1e-6)
    assert small.poses is ds.poses and downscaled(ds, 1) is ds


@pytest.mark.slow
def test_a_calibrated_run_starts_from_the_calibrations_rows(tmp_path, monkeypatch):
    """splat.exposure_calibrate: the calibration runs first at a fraction of the resolution
    with the transforms' rate held, its share taken from the budget; the run starts from its
    rows, held for splat.exposure_calibrate_hold; eval.json says what it did and reports the
    shared-gain score; the calibration's metrics stay, its checkpoint does not."""
    from clrf.cli.main import main as cli
    from clrf.corrections import exposure as E
    from clrf.training import calibrate
    seen = {}
    real_calibrate, real_seed = calibrate.calibrate_exposure, E.Exposure.seed

    def calibrate_spy(device, ds, cfg, out, *a, **k):
        small = calibrate.calibration_config(cfg)
        seen["cfg"] = (small.train.max_seconds, small.splat.lr_exposure_final,
                       small.splat.exposure_calibrate, small.train.final_eval)
        rows, info = real_calibrate(device, ds, cfg, out, *a, **k)
        seen["rows"] = rows
        return rows, info

    def seed_spy(self, rows, hold_until=0.0):
        seen["seed"] = (np.array(rows), hold_until)
        return real_seed(self, rows, hold_until)
    monkeypatch.setattr(calibrate, "calibrate_exposure", calibrate_spy)
    monkeypatch.setattr(E.Exposure, "seed", seed_spy)
    out = tmp_path / "run"
    # Steps, not seconds, end both runs (train.max_iters, which the calibration keeps): one
    # pass over the 64 views gives every row one Adam step of the same size (lr times the
    # gradient's sign), which the recentring after the pass can take out exactly, so the rows
    # show their training from the second pass on; a 1.5 s calibration made one pass with the
    # other test worker busy, and one step where PoCL first compiled the kernels for their
    # work-group sizes (at their first launch, inside the step)
    assert cli(["--quiet", "train", "--model", "splat", "--out", str(out), "--max-seconds", "600",
                "--set", "train.max_iters=150", "--set", "splat.exposure=true",
                "--set", "splat.exposure_calibrate=0.25", "--set", "splat.init_points=1000",
                "--set", "train.eval_every=1000",
                # the procedural scene is of one exposure: kept from the steady start
                "--set", "splat.exposure_steady_spread=0"]) == 0
    assert seen["cfg"] == (150.0, 0.05, 0.0, False)
    np.testing.assert_array_equal(seen["seed"][0], seen["rows"])
    assert seen["seed"][1] == 0.1
    ev = json.loads((out / "eval.json").read_text())
    cal = ev["exposure_calibration"]
    assert cal["iterations"] == 150 and cal["images_trained"] == 64
    assert (seen["rows"][:, [0, 4, 8]] != 1).any()     # the calibration trained its rows
    # the procedural scene's 64 pixels keep 32 a side: a half, not an eighth
    assert cal["seconds_budget"] == 150.0 and cal["downscale"] == 2
    assert json.loads((out / "config.json").read_text())["train"]["max_seconds"] == 450.0
    assert (out / "calibration" / "metrics.csv").exists()
    assert not (out / "calibration" / "ckpt.npz").exists()
    assert np.isfinite(ev["psnr_shared_gain"]) and len(ev["shared_gain"]) == 3
    assert cal["steady"] is False and cal["gain_spread"] > 0


def test_a_steady_calibration_starts_the_run_from_the_identity(tmp_path, monkeypatch):
    """A calibration that found a steady capture (its gains' spread under
    splat.exposure_steady_spread): the run's rows start at the identity, unheld, and its
    exposure rates are times splat.exposure_steady_rate."""
    from clrf import corrections
    from clrf.cli.main import main as cli
    from clrf.references.reference_exposure import IDENTITY
    from clrf.training import calibrate
    from clrf.training import trainer as T
    rows = np.tile(IDENTITY, (64, 1)) * 1.03
    info = {"seconds_budget": 1.0, "seconds": 1.0, "iterations": 5, "downscale": 2,
            "images_trained": 64, "folder": "x", "gain_spread": 0.01, "steady": True}
    monkeypatch.setattr(calibrate, "calibrate_exposure", lambda *a, **k: (rows, info))
    seen = {}

    def run(self):
        exp = corrections.of(self.model).get("exposure")
        seen.update(P=exp.rows(), lr=(exp.lr, exp.lr_final), hold=exp.hold_until)
        return {"iteration": 0, "seconds": 0.0, "interrupted": True}
    monkeypatch.setattr(T.Trainer, "run", run)
    cli(["--quiet", "train", "--model", "splat", "--out", str(tmp_path / "run"),
         "--max-seconds", "40", "--set", "splat.exposure=true",
         "--set", "splat.init_points=1000", "--set", "splat.exposure_steady_rate=0.1"])
    np.testing.assert_array_equal(seen["P"], np.tile(IDENTITY.astype(np.float32),
                                                     (len(seen["P"]), 1)))
    assert seen["lr"] == pytest.approx((0.005, 0.00005)) and seen["hold"] == 0.0


def test_an_interrupted_calibration_leaves_nothing_trained(tmp_path, monkeypatch, capsys):
    from clrf.cli.main import main as cli
    from clrf.training import trainer as T

    def interrupted(self):
        return {"iteration": 0, "seconds": 0.0, "interrupted": True}
    monkeypatch.setattr(T.Trainer, "run", interrupted)
    out = tmp_path / "run"
    rc = cli(["--quiet", "train", "--model", "splat", "--out", str(out), "--max-seconds", "4",
              "--set", "splat.exposure=true", "--set", "splat.exposure_calibrate=0.25",
              "--set", "splat.init_points=1000"])
    assert rc == 130 and "exposure calibration" in capsys.readouterr().err
    assert not (out / "ckpt.npz").exists() and not (out / "calibration" / "ckpt.npz").exists()


def test_the_calibration_has_a_rate_of_its_own():
    """splat.lr_exposure_calibrate: the calibration's held rate, so that the run's own
    lr_exposure can be small; 0 (the default) holds lr_exposure as before."""
    import dataclasses
    from clrf.training import calibrate
    from clrf.training.config import Config
    cfg = Config()
    cfg.train.model = "splat"
    cfg.train.max_seconds = 100.0
    low = dataclasses.replace(cfg.splat, lr_exposure=0.005, lr_exposure_final=0.0005)
    cfg.set_section("splat", low)
    small = calibrate.calibration_config(cfg)
    assert (small.splat.lr_exposure, small.splat.lr_exposure_final) == (0.005, 0.005)
    cfg.set_section("splat", dataclasses.replace(low, lr_exposure_calibrate=0.05))
    small = calibrate.calibration_config(cfg)
    assert (small.splat.lr_exposure, small.splat.lr_exposure_final) == (0.05, 0.05)
    assert small.train.max_seconds == 100.0 * cfg.splat.exposure_calibrate
    assert cfg.splat.lr_exposure == 0.005       # the run's own rate is left as it was
    # splat.exposure_calibrate_fit (0.3 by default): the calibration's last part fits the rows
    assert (small.splat.exposure_fit, small.splat.exposure_fit_after) == (1.0, 0.7)
    cfg.set_section("splat", dataclasses.replace(low, exposure_calibrate_fit=0.0))
    small = calibrate.calibration_config(cfg)   # 0: Adam throughout, as the run's own
    assert small.splat.exposure_fit == cfg.splat.exposure_fit == 0.0


def test_a_steady_capture_is_told_by_the_calibrated_gains_spread():
    """splat.exposure_steady_spread: the spread is the largest channel's standard deviation of
    the log gains (rows with a bad gain left out); below the limit the capture is steady, and
    a limit of 0 never finds one; Exposure.slow scales both rates."""
    from clrf.references.reference_exposure import IDENTITY
    from clrf.splat.config import SplatConfig
    from clrf.training import calibrate
    rng = np.random.default_rng(0)
    rows = np.tile(IDENTITY, (50, 1))
    gains = np.exp(rng.normal(0, [0.02, 0.05, 0.3], (50, 3)))
    rows[:, [0, 4, 8]] = gains
    rows[3, 0] = np.nan                                  # left out
    rows[7, 4] = -1.0                                    # left out
    keep = np.ones(50, bool)
    keep[[3, 7]] = False
    want = np.log(gains[keep]).std(axis=0).max()
    assert calibrate.gain_spread(rows) == pytest.approx(want, rel=1e-12)
    assert calibrate.gain_spread(rows[:1]) == 0.0
    c = SplatConfig()
    assert not calibrate.steady({"gain_spread": 0.25}, c)          # lego_400, changed
    assert calibrate.steady({"gain_spread": 0.06}, c)              # bonsai, one exposure
    assert not calibrate.steady({"gain_spread": 0.06}, SplatConfig(exposure_steady_spread=0))


def test_slow_scales_both_rates(device):
    from clrf.corrections.exposure import Exposure
    exp = Exposure(device, 4, lr=0.05, reg=0.0, lr_final=0.0005)
    exp.slow(0.01)
    assert (exp.lr, exp.lr_start, exp.lr_final) == pytest.approx((5e-4, 5e-4, 5e-6))
    exp.schedule(1.0)
    assert exp.lr == pytest.approx(5e-6)
    with pytest.raises(ValueError):
        exp.slow(0.0)
