"""Forward-facing captures as splats (clrf/data/world.py, clrf/splat, clrf/data/triangulate.py):
the splat model takes a forward-facing capture with world-space cameras (the volumetric models
keep NDC), starts from the capture's points, triangulated ones, or random ones in the views'
frusta between the depth bounds; where pycolmap is missing the run says once how to get
points; ``clrf eval --protocol llff`` evaluates such a run.

The tiny capture is the procedural scene (clrf/data/synthetic.py) in front of a textured back
wall, seen by 12 parallel cameras on a 4 x 3 grid, written in the LLFF layout
(poses_bounds.npy, images_4/ at a quarter of the size its poses_bounds.npy names, so that
``--protocol llff`` is the standard protocol on it)."""
import csv
import dataclasses
import json
import sys

import imageio.v3 as iio
import numpy as np
import pytest

from clrf.cli.main import main as cli
from clrf.data import load_dataset
from clrf.data.cameras import look_at, pixel_rays
from clrf.data.synthetic import Box, Material, ProceduralScene, _unit

H, W = 36, 48
FOCAL = 40.0
GRID_Y = (-0.45, -0.15, 0.15, 0.45)
GRID_Z = (-0.2, 0.1, 0.4)
EYE_X = 4.0
WALL = Box((-2.2, -5.0, -4.0), (-2.0, 5.0, 4.0))
WALL_MATERIAL = Material((0.60, 0.55, 0.50), 7.0, _unit((0, 1, 1)), 0.05, _unit((1, 0, 0)))


def _scene():
    s = ProceduralScene()
    return ProceduralScene(shapes=s.shapes + [WALL], materials=s.materials + [WALL_MATERIAL])


def _poses():
    """OpenGL camera-to-world [12, 4, 4]: every camera at x = EYE_X looking along -x."""
    eyes = [np.array([EYE_X, y, z]) for z in GRID_Z for y in GRID_Y]
    return np.stack([look_at(e, e - np.array([1.0, 0.0, 0.0])) for e in eyes])


def write_capture(root, supersample=2):
    """The tiny forward-facing capture in the LLFF layout at ``root``; returns (root, the
    per-view (near, far) depth bounds written, the exact depth maps [N, H, W])."""
    scene, poses = _scene(), _poses()
    k = supersample
    intr = np.array([FOCAL, FOCAL, W / 2, H / 2])
    (root / "images_4").mkdir(parents=True)
    rows, depths = [], []
    for i, c2w in enumerate(poses):
        hi = scene.render(c2w[None], intr * k, H * k, W * k)["rgb"][0]
        rgb = hi.reshape(H, k, W, k, 3).mean((1, 3))
        iio.imwrite(root / "images_4" / f"IMG_{i:02d}.png",
                    np.clip(rgb * 255 + 0.5, 0, 255).astype(np.uint8))
        o, d = pixel_rays(c2w[None], intr, H, W)                    # camera z of d is -1
        t = scene.trace(o, d)["depth"]                              # along the unit direction
        z = (t / np.linalg.norm(d, axis=1)).reshape(H, W)           # along the viewing axis
        assert np.all(np.isfinite(z)), "the wall must fill every view"
        depths.append(z)
        llff = np.stack([-c2w[:3, 1], c2w[:3, 0], c2w[:3, 2], c2w[:3, 3]], 1)   # down right back
        hwf = np.array([[4 * H], [4 * W], [4 * FOCAL]])
        rows.append(np.concatenate([np.concatenate([llff, hwf], 1).ravel(),
                                    [z.min(), z.max()]]))
    np.save(root / "poses_bounds.npy", np.stack(rows))
    bounds = np.array([r[15:] for r in rows])
    return root, bounds, np.stack(depths)


@pytest.fixture(scope="module")
def capture(tmp_path_factory):
    return write_capture(tmp_path_factory.mktemp("ff") / "capture")


def _frustum_check(ds, pts):
    """For points [n, 3]: (inside: some training view has it on its image between its own
    depth bounds [n] bool, depth along the nearest such view's axis [n])."""
    inside = np.zeros(len(pts), bool)
    depth = np.full(len(pts), np.inf)
    fx, fy, cx, cy = ds.intrinsics
    for v in ds.split["train"]:
        c2w = np.asarray(ds.poses[v], np.float64)
        q = (pts - c2w[:3, 3]) @ c2w[:3, :3]          # camera axes (OpenGL)
        z = -q[:, 2]
        u = cx + fx * q[:, 0] / np.maximum(z, 1e-9)
        w = cy - fy * q[:, 1] / np.maximum(z, 1e-9)
        lo, hi = ds.depth_bounds[v]
        ok = (z >= lo * (1 - 1e-6)) & (z <= hi * (1 + 1e-6)) & (u >= -1e-6) \
            & (u <= ds.hw[1] + 1e-6) & (w >= -1e-6) & (w <= ds.hw[0] + 1e-6)
        inside |= ok
        depth = np.where(ok, np.minimum(depth, z), depth)
    return inside, depth


# ---- the dataset as each kind takes it --------------------------------------------------------
def test_splat_kind_gets_world_space_cameras_and_the_others_ndc(capture):
    from clrf.training.models import dataset_for, load_data
    root, bounds, _ = capture
    ds = load_dataset(root)
    assert ds.ndc and ds.preset == "forward_facing" and ds.images.shape == (12, H, W, 3)
    for kind in ("grid", "nerf", "hash"):
        assert dataset_for(kind, ds) is ds
    w = load_data(root, 1, "splat")
    assert not w.ndc and w.preset == "forward_facing"
    np.testing.assert_array_equal(w.poses, ds.poses)       # the loader's frame, unchanged
    np.testing.assert_array_equal(w.images, ds.images)
    # LLFF's rescale: the nearest bound becomes 1 / 0.75, every bound scaled alike
    sc = 1.0 / (0.75 * bounds.min())
    np.testing.assert_allclose(w.depth_bounds, bounds * sc, rtol=1e-9)
    assert w.near == pytest.approx(1 / 0.75) and w.far == pytest.approx(bounds[:, 1].max() * sc)
    # the box: every view's frustum between its bounds, tight (its faces touch corners)
    corners = []
    for v in range(len(w.poses)):
        for u, r in ((0, 0), (W, 0), (0, H), (W, H)):
            d = np.array([(u - W / 2) / FOCAL, -(r - H / 2) / FOCAL, -1.0])
            corners += [w.poses[v, :3, 3] + b * (w.poses[v, :3, :3] @ d)
                        for b in w.depth_bounds[v]]
    pts = np.stack(corners)
    np.testing.assert_allclose(w.bbox, [pts.min(0), pts.max(0)], rtol=1e-6, atol=1e-6)
    assert w.bbox[1, 2] == pytest.approx(-w.near) and w.bbox[0, 2] == pytest.approx(-w.far)
    # the background: the training images' mean colour, not the loader's white
    want = ds.images[ds.split["train"]].astype(np.float64).mean((0, 1, 2))
    np.testing.assert_allclose(w.background, want, rtol=1e-6)
    assert ds.background == (1.0, 1.0, 1.0)


def test_random_first_gaussians_fill_the_frusta_between_the_bounds(capture, device):
    """init random on a forward-facing capture: every mean inside some training view's image
    between that view's bounds, spread over the depth range (not a unit box), each at most
    splat.init_max_pixels (the forward_facing preset's 4) of its nearest view."""
    from clrf.splat import model as sm
    from clrf.training.config import build_config
    from clrf.training.models import load_data
    w = load_data(capture[0], 1, "splat")
    cfg = build_config("", None, {"train": {"model": "splat"},
                                  "splat": {"init": "random", "init_points": 3000}}, w.preset)
    assert cfg.splat.init_max_pixels == 4.0
    host, where = sm.initial_host(cfg.splat, w, 10 ** 6, 0)
    assert "frusta" in where and len(host["means"]) == 3000
    m = host["means"].astype(np.float64)
    inside, depth = _frustum_check(w, m)
    assert inside.all()
    lo, hi = w.depth_bounds.min(), w.depth_bounds.max()
    assert np.percentile(depth, 5) < lo + 0.2 * (hi - lo) and depth.max() > lo + 0.7 * (hi - lo)
    px = np.exp(host["log_scales"].max(axis=1)) * FOCAL / depth
    assert px.max() <= 4.0 + 1e-3 and np.median(px) > 0.5
    # without the limit (the published sizing) the same points come out larger
    big, _ = sm.initial_host(dataclasses.replace(cfg.splat, init_max_pixels=0.0), w, 10 ** 6, 0)
    np.testing.assert_array_equal(big["means"], host["means"])
    assert (np.exp(big["log_scales"].max(axis=1)) * FOCAL / depth).max() > 4.5
    # a model in NDC is refused (the command line never gives it one)
    with pytest.raises(sm.Unsupported, match="world-space cameras"):
        sm.check_inputs(cfg, load_dataset(capture[0]), device.caps)


def test_fern_loads_in_world_space_for_splats(scene):
    """fern: world-space cameras with LLFF's bounds (nearest 1 / 0.75 after the rescale), a
    box as wide as the frusta out to the far bounds, the scene's mean colour behind it, and
    random first Gaussians between the bounds."""
    from clrf.splat import model as sm
    from clrf.training.config import build_config
    from clrf.training.models import load_data
    w = load_data(scene("fern"), 1, "splat")
    assert not w.ndc and w.preset == "forward_facing" and w.hw == (378, 504)
    assert w.near == pytest.approx(1 / 0.75) and 5.0 < w.far < 7.0
    assert w.depth_bounds.shape == (20, 2) and np.all(w.depth_bounds[:, 1] > w.depth_bounds[:, 0])
    lo, hi = w.bbox
    assert hi[2] < -1.0 and lo[2] < -w.far * 0.9 and np.all(hi[:2] - lo[:2] > 5.0)
    assert 0.3 < sm.scene_extent(w) < 0.6      # the cameras' spread: 1.1 times ~0.42
    assert all(0.3 < c < 0.7 for c in w.background)
    cfg = build_config("", None, {"train": {"model": "splat"}, "splat": {"init": "random"}},
                       w.preset)
    host, where = sm.initial_host(cfg.splat, w, 10 ** 6, 0)
    assert len(host["means"]) == cfg.splat.init_points == 20000 and "frusta" in where
    inside, depth = _frustum_check(w, host["means"].astype(np.float64))
    assert inside.all() and depth.min() >= w.near * (1 - 1e-6) and depth.max() > 4.0


# ---- where the first Gaussians come from ------------------------------------------------------
def _surface_points(capture, n=400):
    """n points [n, 6] on the tiny capture's surfaces (from its exact depth maps, in the
    loader's normalised frame) with their pixels' colours."""
    root, bounds, depths = capture
    ds = load_dataset(root)
    sc = 1.0 / (0.75 * bounds.min())
    rng = np.random.default_rng(3)
    v = rng.integers(0, len(ds.poses), n)
    r, c = rng.integers(0, H, n), rng.integers(0, W, n)
    d = np.stack([(c + 0.5 - W / 2) / FOCAL, -(r + 0.5 - H / 2) / FOCAL, -np.ones(n)], 1)
    p = ds.poses[v, :3, 3] + np.einsum("nij,nj->ni", ds.poses[v, :3, :3], d) \
        * (depths[v, r, c] * sc)[:, None]
    return np.concatenate([p, ds.images[v, r, c]], 1).astype(np.float32)


def test_auto_points_triangulate_only_captures_for_models_that_start_from_points(
        capture, monkeypatch):
    from clrf.data import triangulate as tri
    from clrf.training.models import load_data
    calls = []
    fake = _surface_points(capture)
    monkeypatch.setattr(tri, "triangulate", lambda ds: calls.append(ds.name) or fake)
    monkeypatch.setattr(tri, "have_pycolmap", lambda: True)
    w = load_data(capture[0], 1, "splat")
    got, note = tri.points_for_run(w, "auto", wanted=True)
    assert note == "" and calls == ["capture"]
    np.testing.assert_array_equal(got.points, fake)
    for ds, mode, wanted in ((w, "auto", False),                      # a model without points
                             (w, "none", True),                       # told not to
                             (load_dataset(capture[0]), "auto", True),   # NDC: not the world's
                             (load_dataset(None, size=8, n_train=4, n_test=1), "auto", True)):
        out, note = tri.points_for_run(ds, mode, wanted)
        assert out.points is None and note == "" and len(calls) == 1, (ds.name, mode, wanted)
    # an explicit request triangulates whatever the model
    assert tri.points_for_run(w, "triangulate", False)[0].points is fake and len(calls) == 2
    # a capture with points keeps them
    assert tri.points_for_run(got, "auto", True)[0] is got and len(calls) == 2
    # nothing triangulates: the run goes on from random points and says why
    monkeypatch.setattr(tri, "triangulate", lambda ds: (_ for _ in ()).throw(
        tri.DataError("dataset capture: no matched feature triangulates; use x")))
    out, note = tri.points_for_run(w, "auto", True)
    assert out.points is None and "no matched feature triangulates" in note and "use x" not in note


@pytest.fixture(scope="module")
def trained(capture, tmp_path_factory):
    """A splat run on the tiny capture with the defaults of `clrf train --model splat`: points
    triangulated (here: the surface points, the COLMAP step replaced) and the forward_facing
    preset; 6 s."""
    from clrf.data import triangulate as tri
    out = tmp_path_factory.mktemp("ff_run") / "run"
    mp = pytest.MonkeyPatch()
    mp.setattr(tri, "triangulate", lambda ds: _surface_points(capture))
    mp.setattr(tri, "have_pycolmap", lambda: True)
    try:
        rc = cli(["--quiet", "train", "--model", "splat", "--data", str(capture[0]), "--out",
                  str(out), "--max-seconds", "6", "--set", "train.eval_downscale=1"])
    finally:
        mp.undo()
    assert rc == 0
    return out


@pytest.mark.slow
def test_a_forward_facing_capture_trains_as_a_splat(trained):
    from clrf.outputs import checkpoint
    state = checkpoint.load(trained)
    meta = state["dataset"]
    assert state["kind"] == "splat" and meta["ndc"] is False and meta["preset"] == "forward_facing"
    assert meta["near"] == pytest.approx(1 / 0.75)
    rows = [r for r in csv.DictReader(open(trained / "metrics.csv")) if r["eval_psnr"]]
    assert "of the capture's 400 sparse points" in rows[0]["model"]
    final = json.loads((trained / "eval.json").read_text())
    first = float(rows[0]["eval_psnr"])           # the untrained model, full size
    assert final["psnr"] > first + 3.0 and final["n_views"] == 2, (first, final["psnr"])


def test_the_run_renders_and_evaluates_under_the_llff_protocol(trained, capture, tmp_path,
                                                               capsys):
    # test views through `clrf render`: the images the run's final evaluation scored
    from clrf.training.metrics import image_metrics
    out = tmp_path / "test"
    assert cli(["--quiet", "render", "--ckpt", str(trained), "--views", "test", "--out",
                str(out)]) == 0
    ds = load_dataset(capture[0])
    final = json.loads((trained / "eval.json").read_text())
    for i, v in enumerate(final["views"]):
        img = iio.imread(out / f"test_{i:03d}.png").astype(np.float64) / 255
        assert image_metrics(img, ds.images[v["view"]])["psnr"] == pytest.approx(v["psnr"],
                                                                                 abs=0.3)
    # the default path of a forward-facing scene is the spiral around its cameras (an orbit
    # around the box would look at the wall from behind)
    spiral = tmp_path / "spiral"
    assert cli(["--quiet", "render", "--ckpt", str(trained), "--frames", "2", "--out",
                str(spiral)]) == 0
    frame = iio.imread(spiral / "orbit_000.png").astype(np.float64) / 255
    # the scene in view, not the flat background of an empty one
    assert frame.std((0, 1)).mean() > 0.5 * ds.images.std((1, 2)).mean()
    # the published protocol: views 0 and 8 at a quarter of the capture, which images_4 is
    capsys.readouterr()
    assert cli(["eval", "--ckpt", str(trained), "--protocol", "llff", "--lpips", "none",
                "--out", str(tmp_path / "llff.json")]) == 0
    res = json.loads((tmp_path / "llff.json").read_text())
    assert res["standard"] is True and res["protocol"] == "llff" and res["n_views"] == 2
    assert [m["view"] for m in res["views"]] == [0, 1]    # indices into the test-only load
    assert res["psnr"] == pytest.approx(final["psnr"], abs=1e-3)


# ---- without pycolmap -------------------------------------------------------------------------
def _no_pycolmap(monkeypatch):
    monkeypatch.setitem(sys.modules, "pycolmap", None)   # `import pycolmap` raises ImportError
    from clrf.data import triangulate as tri
    assert not tri.have_pycolmap()


@pytest.mark.slow
def test_without_pycolmap_the_run_says_once_how_to_get_points(capture, tmp_path, monkeypatch,
                                                             capsys):
    _no_pycolmap(monkeypatch)
    out = tmp_path / "run"
    capsys.readouterr()
    rc = cli(["--quiet", "train", "--model", "splat", "--data", str(capture[0]), "--out",
              str(out), "--max-seconds", "1", "--set", "train.eval_views=1", "--set",
              "train.final_eval=false"])
    err = capsys.readouterr().err
    assert rc == 0, err
    assert err.count("bash tools/setup.sh process") == 1 and "pycolmap is not installed" in err
    rows = list(csv.DictReader(open(out / "metrics.csv")))
    assert "random in the training views' frusta" in rows[0]["model"]
    # told not to use points, or a model that does not start from them: no word of it
    for extra in (["--model", "splat", "--set", "train.points=none"], ["--model", "splat",
                  "--set", "splat.init=random"], ["--model", "grid", "--set",
                                                  "grid.reso=[[8,8,8]]", "--set",
                                                  "grid.upsample_at=[]"]):
        capsys.readouterr()
        assert cli(["--quiet", "train", "--data", str(capture[0]), "--out",
                    str(tmp_path / "r2"), "--force", "--max-seconds", "1", "--set",
                    "train.eval_views=1", "--set", "train.final_eval=false", *extra]) == 0
        assert "pycolmap is not installed" not in capsys.readouterr().err, extra


def test_points_required_without_points_or_pycolmap_is_one_clear_error(capture, tmp_path,
                                                                       monkeypatch, capsys):
    _no_pycolmap(monkeypatch)
    before = set(tmp_path.rglob("*"))
    capsys.readouterr()
    rc = cli(["train", "--model", "splat", "--data", str(capture[0]), "--out",
              str(tmp_path / "run"), "--max-seconds", "1", "--set", "splat.init=points"])
    cap = capsys.readouterr()
    assert rc == 2
    assert cap.err.startswith("clrf: error:") and cap.err.count("clrf: error:") == 1, cap.err
    assert "Traceback" not in cap.err + cap.out
    for needle in ("dataset capture", "splat.init = 'points'", "no sparse points",
                   "bash tools/setup.sh process", "splat.init = 'random'"):
        assert needle in cap.err, (needle, cap.err)
    assert set(tmp_path.rglob("*")) == before
