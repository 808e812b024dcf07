"""The Gaussian-splatting model (clrf/splat/model.py, `clrf train --model splat`): the 3DGS PLY
layout, the host SSIM loss against a float64 twin and central differences, the SH Adam's band
mask, densification under the cap, the configuration's checks, and a short training run
through the command line (loss falls, the checkpoint renders what was evaluated, --splats
exports it, --mesh is refused)."""
import csv
import json

import numpy as np
import pytest

from clrf.splat import model as sm
from clrf.splat.ply import property_names, read_splat_ply, write_splat_ply


# ---- PLY --------------------------------------------------------------------------------------
def _random_splats(n, degree, seed=0):
    rng = np.random.default_rng(seed)
    return {"means": rng.normal(size=(n, 3)).astype(np.float32),
            "log_scales": rng.normal(-3, 1, (n, 3)).astype(np.float32),
            "quats": rng.normal(size=(n, 4)).astype(np.float32),
            "opacity_logits": rng.normal(size=n).astype(np.float32),
            "sh": rng.normal(size=(n, (degree + 1) ** 2, 3)).astype(np.float32)}


def _parse(path):
    """(header lines, structured vertex array) read with plain numpy, independently of
    read_splat_ply."""
    data = path.read_bytes()
    end = data.index(b"end_header\n") + len(b"end_header\n")
    lines = data[:end].decode("ascii").splitlines()
    names = [ln.split()[2] for ln in lines if ln.startswith("property float ")]
    n = int(next(ln for ln in lines if ln.startswith("element vertex")).split()[2])
    v = np.frombuffer(data, np.dtype([(k, "<f4") for k in names]), n, end)
    assert len(data) == end + n * 4 * len(names)
    return lines, v


@pytest.mark.parametrize("degree", [0, 3])
def test_ply_layout_and_round_trip(tmp_path, degree):
    g = _random_splats(7, degree)
    path = tmp_path / "s.ply"
    assert write_splat_ply(path, **g) == 7
    lines, v = _parse(path)
    assert lines[:3] == ["ply", "format binary_little_endian 1.0", "element vertex 7"]
    assert lines[-1] == "end_header"
    rest = 3 * ((degree + 1) ** 2 - 1)
    want = (["x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2"]
            + [f"f_rest_{i}" for i in range(rest)]
            + ["opacity", "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3"])
    assert list(v.dtype.names) == want == property_names((degree + 1) ** 2)
    np.testing.assert_array_equal(np.stack([v["x"], v["y"], v["z"]], -1), g["means"])
    assert not np.any(v["nx"]) and not np.any(v["ny"]) and not np.any(v["nz"])
    for c in range(3):
        np.testing.assert_array_equal(v[f"f_dc_{c}"], g["sh"][:, 0, c])
    B = (degree + 1) ** 2
    for c in range(3):                      # channel-major: all of R, then G, then B
        for b in range(1, B):
            np.testing.assert_array_equal(v[f"f_rest_{c * (B - 1) + b - 1}"], g["sh"][:, b, c])
    np.testing.assert_array_equal(v["opacity"], g["opacity_logits"])
    for k in range(3):
        np.testing.assert_array_equal(v[f"scale_{k}"], g["log_scales"][:, k])
    for k in range(4):                      # w, x, y, z
        np.testing.assert_array_equal(v[f"rot_{k}"], g["quats"][:, k])
    back = read_splat_ply(path)
    for k in g:
        np.testing.assert_array_equal(back[k], g[k])
    assert [p.name for p in tmp_path.iterdir()] == ["s.ply"]   # no temporary file left


def test_ply_write_is_atomic(tmp_path):
    path = tmp_path / "s.ply"
    write_splat_ply(path, **_random_splats(3, 1))
    before = path.read_bytes()
    bad = _random_splats(3, 1)
    bad["sh"] = bad["sh"][:, :3]            # not a square number of coefficients
    with pytest.raises(ValueError, match="sh"):
        write_splat_ply(path, **bad)
    assert path.read_bytes() == before and len(list(tmp_path.iterdir())) == 1


# ---- the model --------------------------------------------------------------------------------
def _model(device, **splat):
    from clrf.data import load_dataset
    from clrf.training.config import build_config
    from clrf import registry
    ds = load_dataset(None)
    cfg = build_config("procedural", overrides={"train": {"model": "splat"},
                                                "splat": {"preset": "tiny", **splat}})
    return registry.get("splat").create(device, cfg, ds, ds.background), ds


def test_views_cycle_and_inactive_sh_bands_stay_put(device):
    m, ds = _model(device, init_points=300)
    k = len(ds.split["train"])
    assert sorted(m.view_of(i) for i in range(k)) == sorted(ds.split["train"])
    assert [m.view_of(i) for i in range(k)] != [m.view_of(i) for i in range(k, 2 * k)]
    before = m.host_params()
    assert m.active_degree == 0
    for it in range(3):
        assert np.isfinite(m.train_step(it))
    after = m.host_params()
    assert not np.any(after["sh"][:, 1:]) and np.any(after["sh"][:, 0] != before["sh"][:, 0])
    for k_ in ("means", "log_scales", "opacity_logits"):
        assert np.any(after[k_] != before[k_]), k_
    st = m.strategy.host_rows()
    accum, count = st["grad_accum"], st["grad_count"]
    assert count.max() == 3 and np.all(accum[count == 0] == 0) and accum.max() > 0
    m.active_degree = 3
    m.train_step(3)
    assert np.any(m.host_params()["sh"][:, 1:])


@pytest.mark.slow
def test_gpu_shape_steps_every_group_in_one_adam_launch(device):
    """With the GPU-shaped kernels the four parameter groups take one Adam launch (AdamSet,
    kept through a densification); from the same state and gradients it gives the parameters
    and moments of a launch a group. (Same gradients, not same steps: the rasteriser's and
    the loss's float sums vary in their last bits from run to run.)"""
    from clrf.runtime.optim import AdamSet
    from clrf.runtime.programs import upload
    gpu, _ = _model(device.with_tuning(gpu_kernels=True), init_points=300)
    assert isinstance(gpu._adam_groups, AdamSet)
    gpu.refine()
    assert isinstance(gpu._adam_groups, AdamSet) and gpu._adam_groups.optimizers[0] is \
        gpu.opts["means"]
    one, _ = _model(device, init_points=300)
    each, _ = _model(device, init_points=300)
    assert each._adam_groups is None
    one._adam_groups = AdamSet(device, [one.opts[k] for k in sm.GROUPS])
    rng = np.random.default_rng(3)
    for t in (1, 2):
        grads = {k: rng.normal(size=v.shape).astype(np.float32) * 1e-2
                 for k, v in one.host_params().items()}
        for m in (one, each):
            m._adam({k: upload(device.queue, g) for k, g in grads.items()}, t)
    a, b = one.host_params(), each.host_params()
    for k in a:
        np.testing.assert_array_equal(a[k], b[k], err_msg=k)
    ma, mb = one.host_moments(), each.host_moments()
    for k in ma:
        np.testing.assert_array_equal(ma[k], mb[k], err_msg=k)


def test_gpu_shape_defers_the_loss(device):
    """With the GPU-shaped kernels a step returns its loss as a Pending (read when the trainer
    reports): the MSE entry of the loss's stats as the host read returns it."""
    from clrf.runtime.pending import Pending
    gpu, _ = _model(device.with_tuning(gpu_kernels=True), init_points=200)
    assert gpu.defer_loss
    m, _ = _model(device, init_points=200)
    assert not m.defer_loss and isinstance(m.train_step(0), float)
    m.defer_loss = True
    loss = m.train_step(1)
    assert isinstance(loss, Pending)
    stats = m._loss_fn.read()
    assert float(loss) == stats["mse"] and stats["mse"] != stats["loss"]


def test_densify_and_prune_keep_the_cap(device):
    from clrf.interface import Budget
    m, _ = _model(device, init_points=300, max_gaussians=340, densify_grad_threshold=1e-9)
    for it in range(4):
        m.train_step(it)
    # a fifth of the Gaussians made transparent: pruned
    p = m.params["opacity_logits"].get()
    p[:60] = -10.0
    m.params["opacity_logits"].set(p)
    msg = m.refine()
    assert "60 pruned" in msg and m.n <= 340
    assert m.n == 340            # every remaining Gaussian is a candidate: filled to the cap
    for it in range(4, 6):
        assert np.isfinite(m.train_step(it))
    assert m.n <= 340
    # the budget hook densifies only inside [densify_from, densify_until) and after enough steps
    m.strategy.state.last_refine = 0
    assert m.on_iteration(10, Budget(10, 1.0, 0.01, None)) is None
    assert "densified" in m.on_iteration(30, Budget(30, 1.0, 0.05, None))
    assert m.n <= 340 and m.describe().startswith(f"{m.n} Gaussians")


def test_initial_gaussians_from_points_random_and_beyond_the_box():
    """init: a capture's sparse points (positions and colours kept, subsampled to init_points);
    random in the box; for unbounded scenes as many again beyond the box, out to
    UNBOUNDED_REACH half-sizes; "points" without points is refused naming the fix."""
    import dataclasses
    from clrf.data import load_dataset
    from clrf.interface import Unsupported
    from clrf.splat.config import SplatConfig
    ds = load_dataset(None)
    sc = SplatConfig.from_preset("tiny", sh_degree=1)
    rng = np.random.default_rng(0)
    pts = np.concatenate([rng.uniform(-0.5, 0.5, (50, 3)), rng.uniform(0, 1, (50, 3))], 1)
    with_pts = dataclasses.replace(ds, points=pts.astype(np.float32))
    host, where = sm.initial_host(sc, with_pts, cap=1000, seed=1)
    assert "50 of the capture's 50 sparse points" in where
    np.testing.assert_allclose(host["means"], pts[:, :3], rtol=0, atol=1e-6)
    colour = 0.5 + sm.SH_C0 * host["sh"][:, 0]
    np.testing.assert_allclose(colour, pts[:, 3:], rtol=0, atol=1e-5)
    assert not np.any(host["sh"][:, 1:]) and host["sh"].shape == (50, 4, 3)
    host, where = sm.initial_host(dataclasses.replace(sc, init_points=20), with_pts, 1000, 1)
    assert len(host["means"]) == 20 and "20 of the capture's 50" in where
    host, where = sm.initial_host(dataclasses.replace(sc, init="random", init_points=40),
                                  with_pts, 1000, 1)
    lo, hi = ds.bbox
    assert "40 random in the scene box" in where and len(host["means"]) == 40
    assert np.all((host["means"] >= lo) & (host["means"] <= hi))
    # random Gaussians start grey, as published (SH degree 0 in [0, 1/255])
    dc = host["sh"][:, 0]
    assert dc.min() >= 0 and dc.max() <= 1 / 255 + 1e-7 and dc.std() > 0
    unb = dataclasses.replace(ds, preset="real360", bbox=np.array([[-1.0] * 3, [1.0] * 3]))
    host, where = sm.initial_host(dataclasses.replace(sc, init_points=400), unb, 1000, 1)
    r = np.linalg.norm(host["means"], axis=1)
    assert len(r) == 800 and "400 beyond it" in where
    assert np.all(r[:400] <= np.sqrt(3) + 1e-6)
    assert r[400:].min() >= 1 - 1e-6 and r[400:].max() <= sm.UNBOUNDED_REACH + 1e-4
    assert np.median(r[400:]) > 1.5
    # the cap holds for both halves
    host, _ = sm.initial_host(dataclasses.replace(sc, init_points=400), unb, 300, 1)
    assert len(host["means"]) <= 300
    with pytest.raises(Unsupported, match="splat.init = 'points'.*sparse points"):
        sm.initial_host(dataclasses.replace(sc, init="points"), ds, 1000, 1)


@pytest.mark.parametrize("file_degree,degree", [(3, 1), (0, 2), (2, 2)])
def test_initial_gaussians_from_a_splat_ply(tmp_path, file_degree, degree):
    """init_ply: a splat file's Gaussians as written, its SH bands above sh_degree dropped and
    missing ones zero; more Gaussians than the cap are refused."""
    import dataclasses
    from clrf.data import load_dataset
    from clrf.splat.config import SplatConfig
    from clrf.splat.ply import SplatFileError
    g = _random_splats(9, file_degree, seed=4)
    path = tmp_path / "start.ply"
    write_splat_ply(path, **g)
    sc = dataclasses.replace(SplatConfig.from_preset("tiny", sh_degree=degree),
                             init_ply=str(path))
    host, where = sm.initial_host(sc, load_dataset(None), cap=100, seed=0)
    assert f"9 Gaussians of {path} (SH degree {file_degree})" == where
    for k in ("means", "log_scales", "quats", "opacity_logits"):
        np.testing.assert_array_equal(host[k], g[k])
    nb, fb = (degree + 1) ** 2, (file_degree + 1) ** 2
    k = min(nb, fb)
    assert host["sh"].shape == (9, nb, 3)
    np.testing.assert_array_equal(host["sh"][:, :k], g["sh"][:, :k])
    assert not np.any(host["sh"][:, k:])
    with pytest.raises(SplatFileError, match="9 Gaussians exceed the cap of 8"):
        sm.initial_host(sc, load_dataset(None), cap=8, seed=0)


def test_refuses_ndc_scenes(device):
    import dataclasses
    from clrf.data import load_dataset
    from clrf.training.config import build_config
    from clrf import registry
    ds = dataclasses.replace(load_dataset(None), ndc=True)
    cfg = build_config("procedural", overrides={"train": {"model": "splat"}})
    with pytest.raises(ValueError, match="world-space cameras"):
        registry.get("splat").create(device, cfg, ds, ds.background)


@pytest.mark.parametrize("key,value,needle", [
    ("sh_degree", 4, "splat.sh_degree"), ("lambda_dssim", 1.5, "splat.lambda_dssim"),
    ("densify_every", 0.0, "splat.densify_every"), ("max_gaussians", 0, "splat.max_gaussians"),
    ("lr_position_final", 1.0, "splat.lr_position_final"), ("preset", "huge", "splat.preset"),
])
def test_config_checks(key, value, needle):
    from clrf.training.config import ConfigError, Config, build_config
    assert all(ok for ok, _, _ in Config().splat.checks())
    with pytest.raises((ConfigError, ValueError), match=needle.replace(".", r"\.")
                       if key != "preset" else "splat"):
        build_config("procedural", overrides={"splat": {key: value}}).validate()


def test_memory_estimate_names_the_cap(device):
    from clrf.splat import budget
    from clrf.training.config import Config
    cfg = Config()
    stages, fix = budget.memory(cfg, 100 * 100, device.caps)
    assert "splat.max_gaussians" in fix and stages[0].total > 0
    assert budget.bytes_per_gaussian(3) > budget.bytes_per_gaussian(0) > 0
    # the CPU backward's gradient copies (ABSGRAD's 11 floats each) are counted
    assert budget.bytes_per_gaussian(3, 4) - budget.bytes_per_gaussian(3) == 4 * 4 * 11
    want = budget.backward_copies(device.caps) if device.caps.type == "cpu" else 0
    assert budget.copies_on(device.caps) == want


def test_memory_estimate_counts_the_images_the_device_holds():
    """splat.images_on_device: every training pixel's target where the images are resident
    (and where the device is not known, for "auto"), one view's where they are streamed."""
    import dataclasses
    from clrf.splat import budget
    from clrf.training.config import Config
    cfg = Config()
    view, train = 1 << 22, 1 << 25        # a view's pixels are bounded at 2048 x 2048
    totals = {}
    for setting in ("auto", "true", "false"):
        cfg.set_section("splat", dataclasses.replace(cfg.splat, images_on_device=setting))
        totals[setting] = budget.memory(cfg, train, None)[0][0].total
    assert totals["auto"] == totals["true"]
    assert totals["true"] - totals["false"] == budget.TARGET_BYTES * (train - view)


# ---- through the command line -----------------------------------------------------------------
@pytest.fixture(scope="module")
def trained(tmp_path_factory):
    from clrf.cli.main import main as cli
    out = tmp_path_factory.mktemp("splat_run")
    rc = cli(["--quiet", "train", "--model", "splat", "--out", str(out), "--max-seconds", "8",
              "--set", "train.eval_every=3", "--set", "splat.init_points=2000"])
    assert rc == 0
    return out


@pytest.mark.slow
def test_training_lowers_the_error(trained):
    rows = [r for r in csv.DictReader(open(trained / "metrics.csv")) if r["eval_psnr"]]
    first, last = float(rows[0]["eval_psnr"]), float(rows[-1]["eval_psnr"])
    assert last > first + 2.0, (first, last)
    losses = [float(r["train_loss"]) for r in rows if r["train_loss"]]
    assert losses[-1] < losses[0]


def test_checkpoint_renders_what_was_evaluated(trained, device):
    from clrf.training.models import load_model
    from clrf.data import load_dataset
    from clrf.training.metrics import image_metrics
    model, state, _ = load_model(device, trained)
    assert state["kind"] == "splat" and model.kind == "splat"
    ds = load_dataset(None)
    ev = json.loads((trained / "eval.json").read_text())
    v = ev["views"][0]
    out = model.render_image(ds.poses[v["view"]], ds.intrinsics, ds.hw)
    assert image_metrics(out["rgb"], ds.images[v["view"]])["psnr"] == pytest.approx(
        v["psnr"], abs=1e-3)
    again = load_model(device, trained)[0].render_image(ds.poses[v["view"]], ds.intrinsics,
                                                        ds.hw)
    np.testing.assert_array_equal(again["rgb"], out["rgb"])
    assert np.all((out["acc"] >= 0) & (out["acc"] <= 1)) and np.all(out["depth"] >= 0)
    seen = out["acc"] > 0.5
    assert seen.any() and np.all(out["depth"][seen] > 0.5)   # the scene lies 2..6 away


def test_export_splats_and_refuse_mesh(trained, tmp_path, capsys):
    from clrf.cli.main import main as cli
    from clrf.outputs import checkpoint
    ply = tmp_path / "x.ply"
    assert cli(["export", "--ckpt", str(trained), "--splats", str(ply)]) == 0
    g = read_splat_ply(ply)
    state = checkpoint.load(trained)
    np.testing.assert_array_equal(g["means"], state["param_means"])
    np.testing.assert_array_equal(g["sh"], state["param_sh"])
    # a splat model has no density field: --mesh is bad input (exit 2, one line naming
    # --splats), and nothing is written
    capsys.readouterr()
    assert cli(["export", "--ckpt", str(trained), "--mesh", str(tmp_path / "m.ply")]) == 2
    err = capsys.readouterr().err
    assert err.count("clrf: error:") == 1 and "--splats" in err and "Traceback" not in err
    assert not (tmp_path / "m.ply").exists()
    # and the other way: --splats on a checkpoint of another kind names the kind it needs
    from viewer_util import train_tiny
    grid = train_tiny(tmp_path / "grid", 1.0)
    capsys.readouterr()
    assert cli(["export", "--ckpt", str(grid), "--splats", str(tmp_path / "g.ply")]) == 2
    err = capsys.readouterr().err
    assert "--model splat" in err and "grid" in err and not (tmp_path / "g.ply").exists()


@pytest.mark.slow
def test_resume_continues_a_splat_run(trained, tmp_path):
    """--resume: the checkpoint's Gaussians and Adam state, the dataset attached again, the
    iteration count going on."""
    import shutil
    from clrf.cli.main import main as cli
    from clrf.outputs import checkpoint
    run = tmp_path / "run"
    shutil.copytree(trained, run)
    before = checkpoint.load(run)
    assert cli(["--quiet", "train", "--out", str(run), "--resume", "--max-seconds",
                str(float(before["seconds"]) + 3.0)]) == 0
    after = checkpoint.load(run)
    assert after["kind"] == "splat" and after["iteration"] > before["iteration"]
    assert after["seconds"] > before["seconds"]


def test_a_third_party_reader_opens_the_export(trained, tmp_path):
    """plyfile (the PLY library of the original 3DGS code's tools) reads the file: the 62
    properties in the 3DGS order, one vertex per Gaussian, the checkpoint's values."""
    plyfile = pytest.importorskip("plyfile", reason="plyfile is in the test extra")
    from clrf.cli.main import main as cli
    from clrf.outputs import checkpoint
    ply = tmp_path / "s.ply"
    assert cli(["export", "--ckpt", str(trained), "--splats", str(ply)]) == 0
    v = plyfile.PlyData.read(str(ply))["vertex"]
    names = [p.name for p in v.properties]
    assert names == (["x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2"]
                     + [f"f_rest_{i}" for i in range(45)] + ["opacity", "scale_0", "scale_1",
                                                            "scale_2", "rot_0", "rot_1",
                                                            "rot_2", "rot_3"])
    state = checkpoint.load(trained)
    assert v.count == len(state["param_means"])
    np.testing.assert_array_equal(np.stack([v["x"], v["y"], v["z"]], 1), state["param_means"])
    np.testing.assert_array_equal(v["opacity"], state["param_opacity_logits"].reshape(-1))


def test_render_image_depth_in_the_same_pass_where_asked(device):
    """render_image's depth (RENDER_DEPTH, composited in the colour's own raster pass) is the
    twin's opacity-weighted mean camera depth; without depth=True no depth is made and the
    colour is the same."""
    from clrf.references import reference_splat as rs
    m, ds = _model(device, init_points=400, sh_degree=0)
    c2w, K, hw = ds.poses[0], ds.intrinsics, ds.hw
    with_d = m.render_image(c2w, K, hw)
    without = m.render_image(c2w, K, hw, depth=False)
    assert set(without) == {"rgb", "acc"} and set(with_d) == {"rgb", "acc", "depth"}
    np.testing.assert_array_equal(with_d["rgb"], without["rgb"])
    cam = sm.camera_of(c2w, K, hw)
    rcam = {"viewmat": cam.viewmat, "fx": cam.fx, "fy": cam.fy, "cx": cam.cx, "cy": cam.cy,
            "width": cam.width, "height": cam.height, "near": cam.near}
    p = {k: v.astype(np.float64) for k, v in m.host_params().items()}
    _, _, ref = rs.render(p, rcam, m.background, tile=m.rast.tile)
    acc = 1 - ref["T"]
    want = np.where(acc > 1e-6, ref["depth"] / np.maximum(acc, 1e-6), 0.0)
    seen = acc > 0.05
    assert seen.mean() > 0.05
    np.testing.assert_allclose(with_d["depth"][seen], want[seen], rtol=1e-3)
    assert np.all(with_d["depth"][acc < 1e-7] == 0)
