"""splat.bilateral_grid in the model: the settings (one colour correction at a time, rates and
shapes checked: one clear error each), training moves the trained views' grids, the checkpoint
keeps them (keys prefixed ``bilateral_grid``) and a resumed model trains on, MPI ranks refuse
it, and a run evaluates with its summary (the kernels: tests/test_bilateral.py)."""
import json

import numpy as np
import pytest

from clrf.corrections import VIEWS, Views, build
from clrf.references.reference_bilateral import IDENTITY
from clrf.testing import tolerances as tol


def _model(device, **splat):
    from clrf import registry
    from clrf.data import load_dataset
    from clrf.training.config import build_config
    ds = load_dataset(None)
    cfg = build_config("procedural", overrides={"train": {"model": "splat"},
                                                "splat": {"preset": "tiny", "init_points": 300,
                                                          "bilateral_grid": True, **splat}})
    return registry.get("splat").create(device, cfg, ds, ds.background), ds


def _train(tmp_path, *sets):
    from clrf.cli.main import main as cli
    args = ["--quiet", "train", "--model", "splat", "--out", str(tmp_path / "run"),
            "--max-seconds", "1"]
    for s in sets:
        args += ["--set", s]
    return cli(args)


def test_exposure_and_the_bilateral_grid_together_are_one_clear_error(capsys, tmp_path):
    rc = _train(tmp_path, "splat.exposure=true", "splat.bilateral_grid=true")
    err = capsys.readouterr().err
    assert rc == 2 and err.count("clrf: error:") == 1, err
    assert "splat.exposure" in err and "splat.bilateral_grid" in err, err
    assert not (tmp_path / "run").exists()


@pytest.mark.parametrize("key,value", [("lr_bilateral_grid", 0.0), ("lr_bilateral_grid", -1e-3),
                                       ("bilateral_grid_tv", -1.0),
                                       ("bilateral_grid_shape", "[16,16]"),
                                       ("bilateral_grid_shape", "[16,0,8]")])
def test_bad_settings_are_one_clear_error(key, value, capsys, tmp_path):
    rc = _train(tmp_path, "splat.bilateral_grid=true", f"splat.{key}={value}")
    err = capsys.readouterr().err
    assert rc == 2 and err.count("clrf: error:") == 1 and f"splat.{key}" in err, err


def test_gsplats_defaults():
    from clrf.splat.config import SplatConfig
    c = SplatConfig()
    assert not c.bilateral_grid and c.bilateral_grid_shape == [16, 16, 8]
    assert c.lr_bilateral_grid == 2e-3 and c.bilateral_grid_tv == 10.0
    # two departures: the trained view's grid alone steps (a checkpoint from before the
    # setting resumes with gsplat's dense step), and no calibration unless asked
    assert c.bilateral_grid_sparse and c.bilateral_grid_calibrate == 0
    old = {k: v for k, v in c.__dict__.items() if k != "bilateral_grid_sparse"}
    assert not SplatConfig.from_dict(old).bilateral_grid_sparse


def test_mpi_ranks_refuse_it():
    from clrf.splat.distributed import check_settings
    from clrf.training.config import build_config
    cfg = build_config("procedural", overrides={"train": {"model": "splat"},
                                                "splat": {"bilateral_grid": True}})
    with pytest.raises(ValueError, match=r"splat\.bilateral_grid.*MPI ranks"):
        check_settings(cfg, 2)


def test_the_settings_make_it_with_the_captures_masking(device):
    from clrf.splat.config import SplatConfig
    s = SplatConfig(bilateral_grid=True, bilateral_grid_shape=[4, 3, 2], lr_bilateral_grid=1e-3,
                    bilateral_grid_tv=2.0)
    corr = build(device, s, Views(5, masked=True), VIEWS)
    bil = corr.get("bilateral")
    assert corr.colour is bil and bil.masked and bil.n_images == 5
    assert bil.shape == (4, 3, 2) and bil.lr == 1e-3 and bil.tv_weight == 2.0
    assert build(device, s, Views(5, masked=False), VIEWS, corr).get("bilateral") is bil
    assert not bil.masked
    with pytest.raises(ValueError, match="whole views"):
        build(device, s, Views(5, pixels=16), "rays")


def test_training_moves_the_trained_grids_and_the_checkpoint_keeps_them(device):
    from clrf.splat.model import SplatModel
    m, ds = _model(device)
    m.attach(ds)
    bil = m.corrections.get("bilateral")
    trained = {m.view_of(it) for it in range(3)}
    for it in range(3):
        assert np.isfinite(m.train_step(it))
    grids = bil.host_grids()
    moved = {v for v in range(len(grids)) if np.any(grids[v] != IDENTITY)}
    assert bil.steps == 3 and moved and moved <= trained, (moved, trained)
    state = m.state_dict()
    assert {k for k in state if k.startswith("bilateral")} == {
        "bilateral_grid", "bilateral_grid_m", "bilateral_grid_v", "bilateral_grid_steps",
        "bilateral_grid_view_steps", "bilateral_grid_hold_until", "bilateral_grid_masked"}
    back = SplatModel.from_state_dict(device, state)
    b2 = back.corrections.get("bilateral")
    np.testing.assert_array_equal(b2.host_grids(), grids)
    assert b2.steps == 3
    back.attach(ds)                                  # resumed: the checkpoint's grids kept
    assert back.corrections.get("bilateral") is b2
    assert np.isfinite(back.train_step(3)) and b2.steps == 4
    # the test views render without it
    out = back.render_image(ds.poses[ds.split["test"][0]], ds.intrinsics, ds.hw, depth=False)
    assert np.all(np.isfinite(out["rgb"]))


def test_a_masked_capture_trains_with_its_background_kept(device):
    """An RGBA capture (the dataset's alpha): the grids are made masked, and a step on a grid
    far from the identity gives the loss the scene's background where the render is
    transparent (the model hands ``apply`` the render's T and background)."""
    from clrf.runtime.programs import download, upload
    m, ds = _model(device)
    ds.alpha = np.ones(ds.images.shape[:3], np.float32)
    m.attach(ds)
    bil = m.corrections.get("bilateral")
    assert bil.masked
    rng = np.random.default_rng(11)
    g = bil.host_grids()
    bil.grids.set(np.ascontiguousarray((g + rng.normal(0, 0.3, g.shape)).astype(np.float32)
                                       .reshape(-1)))
    for it in range(2):
        assert np.isfinite(m.train_step(it))
    H, W = ds.hw
    q = device.queue
    rgb = np.tile(np.asarray(m.background, np.float32), (H, W, 1))
    out = m.corrections.apply(upload(q, rgb), 0, upload(q, np.ones((H, W), np.float32)),
                              m.background)
    np.testing.assert_allclose(download(out), rgb, rtol=tol.BILATERAL_RTOL,
                               atol=tol.BILATERAL_ATOL)


@pytest.mark.slow
def test_a_run_trains_evaluates_and_reports_it(tmp_path, capsys):
    from clrf.cli.main import main as cli
    out = tmp_path / "run"
    assert cli(["--quiet", "train", "--model", "splat", "--out", str(out), "--max-seconds", "3",
                "--set", "splat.bilateral_grid=true", "--set", "splat.init_points=1000",
                "--set", "train.eval_every=100"]) == 0
    ev = json.loads((out / "eval.json").read_text())
    s = ev["bilateral_correction"]
    assert s["images"] == 72 and s["shape"] == [16, 16, 8] and s["steps"] > 0
    assert s["mean_abs_deviation"] > 0 and np.isfinite(s["mean_tv"])
    assert np.isfinite(ev["psnr_color_corrected"]) and ev["psnr_color_corrected"] >= ev["psnr"]
    capsys.readouterr()
    assert cli(["eval", "--ckpt", str(out), "--max-views", "2", "--lpips", "none",
                "--out", str(tmp_path / "e.json")]) == 0
    printed = capsys.readouterr().out
    assert "bilateral grids (16 x 16 x 8 cells) of 72 training images" in printed, printed
    e = json.loads((tmp_path / "e.json").read_text())
    assert e["bilateral_correction"]["steps"] == s["steps"]
    assert np.isfinite(e["psnr_color_corrected"])


def test_the_calibration_of_a_bilateral_grid_is_an_exposure_calibration():
    """splat.bilateral_grid_calibrate: the calibration run trains exposure transforms (no
    grid) at their held first rate on its share of the budget; 0 asks for none."""
    import dataclasses

    from clrf.training import calibrate
    from clrf.training.config import build_config
    cfg = build_config("procedural", overrides={"train": {"model": "splat", "max_seconds": 100},
                                                "splat": {"bilateral_grid": True,
                                                          "bilateral_grid_calibrate": 0.1}})
    assert calibrate.wants_calibration(cfg)
    small = calibrate.calibration_config(cfg)
    s = small.splat
    assert s.exposure and not s.bilateral_grid and s.bilateral_grid_calibrate == 0
    assert s.exposure_calibrate == 0 and s.lr_exposure == s.lr_exposure_final == 0.05
    assert small.train.max_seconds == pytest.approx(10.0) and not small.train.final_eval
    cfg.set_section("splat", dataclasses.replace(cfg.splat, bilateral_grid_calibrate=0.0))
    assert not calibrate.wants_calibration(cfg)


@pytest.mark.slow
def test_a_calibrated_grid_starts_from_the_calibrations_transforms(tmp_path, monkeypatch):
    """`clrf train` with splat.bilateral_grid_calibrate (and the sparse step): the calibration
    runs first (its metrics kept, eval.json's exposure_calibration), every grid starts from
    its image's calibrated transform, held for splat.exposure_calibrate_hold, then trains."""
    from clrf.cli.main import main as cli
    from clrf.corrections import bilateral as B
    seen = {}
    real_seed = B.BilateralGrid.seed

    def seed_spy(self, rows, hold_until=0.0):
        seen["seed"] = (np.array(rows), hold_until, self.sparse)
        return real_seed(self, rows, hold_until)
    monkeypatch.setattr(B.BilateralGrid, "seed", seed_spy)
    out = tmp_path / "run"
    assert cli(["--quiet", "train", "--model", "splat", "--out", str(out), "--max-seconds", "600",
                "--set", "train.max_iters=150", "--set", "splat.bilateral_grid=true",
                "--set", "splat.bilateral_grid_sparse=true",
                "--set", "splat.bilateral_grid_calibrate=0.25", "--set", "splat.init_points=1000",
                "--set", "train.eval_every=1000", "--set", "splat.exposure_steady_spread=0"]) == 0
    rows, hold, sparse = seen["seed"]
    assert rows.shape == (72, 12) and np.all(np.isfinite(rows)) and sparse
    assert hold == pytest.approx(0.1) and np.abs(rows[:, [0, 4, 8]] - 1).max() > 0
    assert (out / "calibration" / "metrics.csv").exists()
    assert not (out / "calibration" / "ckpt.npz").exists()
    ev = json.loads((out / "eval.json").read_text())
    assert ev["exposure_calibration"]["iterations"] > 0
    assert ev["bilateral_correction"]["steps"] > 0


def _capture(root, rng):
    """A Blender-layout capture of 12 training and 2 test RGBA images, 9 x 14."""
    import imageio.v3 as iio
    for split, n in (("train", 12), ("test", 2)):
        (root / split).mkdir(parents=True)
        frames = []
        for i in range(n):
            iio.imwrite(root / split / f"r_{i}.png", rng.integers(0, 256, (9, 14, 4),
                                                                   dtype=np.uint8))
            frames.append({"file_path": f"./{split}/r_{i}",
                           "transform_matrix": np.eye(4).tolist()})
        (root / f"transforms_{split}.json").write_text(json.dumps(
            {"camera_angle_x": 0.7, "frames": frames}))


def test_perturb_capture_vignettes_as_recorded(tmp_path):
    """tools/perturb_capture.py --vignette S: every training image is its source times
    clip(1 - s r^2, 0, 1) about the recorded centre (r over half the diagonal), s in [S/2, S],
    the centre within 10 % of the image's; rounded to 8 bits; alpha and the test images
    untouched; the same seed gives the same capture, and the exposure draws of a seed stay
    what they were without it; a strength outside (0, 1] is refused (exit 2)."""
    import subprocess
    import sys
    from pathlib import Path

    import imageio.v3 as iio
    src = tmp_path / "src"
    _capture(src, np.random.default_rng(5))
    tool = Path(__file__).resolve().parents[1] / "tools" / "perturb_capture.py"
    sys.path.insert(0, str(tool.parent))
    from perturb_capture import vignette

    def run(out, *flags):
        return subprocess.run([sys.executable, str(tool), str(src), str(tmp_path / out),
                               *flags], capture_output=True, text=True)
    assert run("a", "--vignette", "0.4").returncode == 0
    rec = json.loads((tmp_path / "a" / "perturbation.json").read_text())
    assert rec["vignette"] == 0.4 and len(rec["frames"]) == 12
    strengths = []
    for i, f in enumerate(rec["frames"]):
        a = iio.imread(src / "train" / f"r_{i}.png").astype(np.float64)
        b = iio.imread(tmp_path / "a" / "train" / f"r_{i}.png").astype(np.float64)
        s, (cx, cy) = f["vignette"]["strength"], f["vignette"]["centre"]
        strengths.append(s)
        assert 0.2 <= s <= 0.4 and abs(cx - 7) <= 1.4 + 1e-12 and abs(cy - 4.5) <= 0.9 + 1e-12
        want = a[..., :3] * vignette(9, 14, s, (cx, cy))[..., None]
        np.testing.assert_allclose(b[..., :3], want, atol=0.5 + 1e-9)
        assert np.array_equal(a[..., 3], b[..., 3])
        corner = vignette(9, 14, s, (cx, cy))[[0, 0, -1, -1], [0, -1, 0, -1]]
        assert np.all(corner < 1 - s * 0.5) and np.all(corner > 0)
    assert len(set(strengths)) == 12                  # a strength per image
    for i in range(2):
        assert np.array_equal(iio.imread(src / "test" / f"r_{i}.png"),
                              iio.imread(tmp_path / "a" / "test" / f"r_{i}.png"))
    assert run("b", "--vignette", "0.4").returncode == 0
    for i in range(12):
        assert np.array_equal(iio.imread(tmp_path / "a" / "train" / f"r_{i}.png"),
                              iio.imread(tmp_path / "b" / "train" / f"r_{i}.png"))
    assert run("c", "--exposure").returncode == 0
    assert run("d", "--exposure", "--vignette", "0.4").returncode == 0
    plain = json.loads((tmp_path / "c" / "perturbation.json").read_text())["frames"]
    both = json.loads((tmp_path / "d" / "perturbation.json").read_text())["frames"]
    assert [f["gain"] for f in plain] == [f["gain"] for f in both]
    assert [f["vignette"] for f in both] == [f["vignette"] for f in rec["frames"]]
    for bad in ("0", "1.5", "-0.2"):
        p = run(f"bad{bad}", "--vignette", bad)
        assert p.returncode == 2 and "--vignette" in p.stderr, p.stderr
