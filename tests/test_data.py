"""Loaders on the shared real scenes (small subsets) and the procedural scene's exact pixels."""
import imageio.v3 as iio
import numpy as np
import pytest

from clrf.data import DataError, detect_layout, load_dataset
from clrf.data.synthetic import ProceduralScene, load_procedural
from clrf.data.cameras import view_rays
from clrf.testing.tolerances import PROCEDURAL_ATOL


def _rigid(poses, tol=1e-4):
    p = np.asarray(poses, np.float64)
    r = p[:, :3, :3]
    return (np.abs(np.einsum("nji,njk->nik", r, r) - np.eye(3)).max() < tol
            and np.allclose(p[:, 3], [0, 0, 0, 1]))


def _check_common(d, n, hw):
    assert d.images.shape == (n,) + tuple(hw) + (3,)
    assert d.images.dtype == np.float32 and d.poses.dtype == np.float32
    assert d.poses.shape == (n, 4, 4) and _rigid(d.poses)
    assert 0.0 <= d.images.min() and d.images.max() <= 1.0
    assert d.intrinsics.shape == (4,) and d.bbox.shape == (2, 3)
    all_idx = np.sort(np.concatenate(list(d.split.values())))
    np.testing.assert_array_equal(all_idx, np.arange(n))          # splits partition the images


# ---------------------------------------------------------------- procedural scene

def test_procedural_defaults_and_determinism():
    a = load_procedural(size=32, seed=3)
    _check_common(a, 72, (32, 32))
    assert len(a.split["train"]) == 64 and len(a.split["test"]) == 8
    assert a.background == (1.0, 1.0, 1.0) and a.preset == "procedural" and not a.ndc
    b = load_procedural(size=32, seed=3)
    np.testing.assert_array_equal(a.images, b.images)
    np.testing.assert_array_equal(a.poses, b.poses)
    c = load_procedural(size=32, seed=4)
    assert np.abs(c.poses[:64] - a.poses[:64]).max() > 1e-3       # the seed moves train cameras
    np.testing.assert_array_equal(c.poses[64:], a.poses[64:])      # test views are fixed
    # the corners see only background; something is hit in the middle
    np.testing.assert_array_equal(a.images[:, 0, 0], 1.0)
    assert np.all(a.images[:, 16, 16].max(-1) < 1.0)


def test_procedural_default_sizes():
    d = load_dataset(None)
    assert d.images.shape == (72, 64, 64, 3) and d.name == "procedural"
    assert load_dataset(None, size=8, max_images=3).images.shape == (6, 8, 8, 3)
    with pytest.raises(DataError, match="unknown options.*'downscale'"):
        load_dataset(None, downscale=2)


def _axis_camera(eye, rot):
    pose = np.eye(4)
    pose[:3, :3] = rot
    pose[:3, 3] = eye
    return pose


def test_procedural_hand_checked_pixels():
    scene = ProceduralScene()
    intr = (10.0, 10.0, 2.5, 2.5)      # 5x5 image: pixel (2, 2) is on the optical axis
    # camera on +x looking at the origin: columns x, y, z of the rotation = world y, z, x
    side = _axis_camera([4.0, 0.0, 0.0], np.array([[0, 0, 1], [1, 0, 0], [0, 1, 0]]))
    # camera above (0, 0) and above (1.1, 1.1), looking straight down (identity rotation)
    top = _axis_camera([0.0, 0.0, 4.0], np.eye(3))
    floor = _axis_camera([1.1, 1.1, 4.0], np.eye(3))
    out = scene.render(np.stack([side, top, floor]), intr, 5, 5)
    rgb, depth, obj = out["rgb"][:, 2, 2], out["depth"][:, 2, 2], out["obj"][:, 2, 2]
    # side: hits sphere 0 (r 0.6) at p = (0.6, 0, 0), t = 4 - 0.6, d = (-1, 0, 0).
    #   g.p = 0.6/sqrt(3); phase = 4 * 0.34641 = 1.385641 + (0, 2pi/3, 4pi/3)
    #   base = (0.7, 0.25, 0.2) * (0.7 + 0.3 sin(phase)) = (0.696411, 0.150099, 0.100947)
    #   view = 0.25 * (0.5 + 0.5 * d.(0,0,1)) = 0.125
    # top: p = (0, 0, 0.6), same g.p, so the same base; d.(0,0,1) = -1 -> view = 0
    # floor: hits the slab top z = -0.7 at t = 4.7, p = (1.1, 1.1, -0.7), g = (1,-1,0)/sqrt(2):
    #   g.p = 0 -> base = (0.55, 0.5, 0.45) * (0.7 + 0.3 sin(0, 2pi/3, 4pi/3))
    #        = (0.385, 0.479904, 0.198087); view = 0.1 * (0.5 + 0.5 * 0) = 0.05
    np.testing.assert_array_equal(obj, [0, 0, 3])
    np.testing.assert_allclose(depth, [3.4, 3.4, 4.7], atol=1e-12)
    np.testing.assert_allclose(rgb, [[0.821411, 0.275099, 0.225947],
                                     [0.696411, 0.150099, 0.100947],
                                     [0.435, 0.529904, 0.248087]], atol=PROCEDURAL_ATOL)
    # pixels that see nothing are the white background with infinite depth
    np.testing.assert_array_equal(out["rgb"][0, 0, 0], [1, 1, 1])
    assert np.isinf(out["depth"][0, 0, 0]) and out["obj"][0, 0, 0] == -1


def test_procedural_dataset_matches_tracer():
    d = load_procedural(n_train=3, n_test=1, size=16, seed=1, supersample=1)
    again = ProceduralScene().render(d.poses.astype(np.float64), d.intrinsics, 16, 16)["rgb"]
    np.testing.assert_allclose(d.images, again, atol=PROCEDURAL_ATOL)
    assert d.images.shape == (4, 16, 16, 3)


def test_procedural_pixels_average_supersampled_rays():
    """By default a pixel is the mean of 4 x 4 rays over it: the tracer's image at 4x the size
    (intrinsics x 4) averaged over 4 x 4 blocks; interiors keep their colour, silhouettes
    blend object and background."""
    d = load_procedural(n_train=2, n_test=1, size=16, seed=1)
    hi = ProceduralScene().render(d.poses.astype(np.float64), d.intrinsics * 4, 64, 64)["rgb"]
    want = hi.reshape(3, 16, 4, 16, 4, 3).mean((2, 4))
    np.testing.assert_allclose(d.images, want, atol=PROCEDURAL_ATOL)
    centre = load_procedural(n_train=2, n_test=1, size=16, seed=1, supersample=1).images
    edge = np.abs(d.images - centre).max(-1) > 0.05
    assert 0 < edge.mean() < 0.3   # only pixels on a silhouette or a colour edge differ
    with pytest.raises(DataError, match="supersample must be >= 1"):
        load_procedural(supersample=0)


# ---------------------------------------------------------------- tiny npz

def test_npz_tiny_lego(scene):
    d = load_dataset(scene("tiny_lego"))
    _check_common(d, 106, (100, 100))
    np.testing.assert_array_equal(d.split["train"], np.arange(100))
    np.testing.assert_array_equal(d.split["test"], np.arange(100, 106))
    np.testing.assert_allclose(d.intrinsics, [138.88887889922103, 138.88887889922103, 50, 50])
    assert d.background == (0.0, 0.0, 0.0)
    assert d.images[:, 0, 0].max() < 0.01                           # black background corners
    f = next(scene("tiny_lego").glob("*.npz"))
    assert detect_layout(f) == "npz"
    small = load_dataset(f, max_images=2, downscale=2)
    assert small.images.shape == (4, 50, 50, 3)
    np.testing.assert_allclose(small.intrinsics, np.array([138.88887889922103] * 2 + [50, 50]) / 2)


# ---------------------------------------------------------------- Blender

def test_blender_lego(scene):
    root = scene("lego_400")
    d = load_dataset(root, max_images=2)
    _check_common(d, 6, (400, 400))
    assert {k: len(v) for k, v in d.split.items()} == {"train": 2, "val": 2, "test": 2}
    f = 0.5 * 400 / np.tan(0.5 * 0.6911112070083618)                   # 555.555...
    np.testing.assert_allclose(d.intrinsics, [f, f, 200, 200])
    assert (d.near, d.far, d.ndc, d.preset) == (2.0, 6.0, False, "synthetic")
    # compositing, checked at one alpha-0 and one partial-alpha pixel of train/r_0
    raw = iio.imread(root / "train" / "r_0.png").astype(np.float64) / 255.0
    alpha = raw[..., 3]
    z = np.argwhere(alpha == 0)[0]
    np.testing.assert_array_equal(d.images[0][tuple(z)], [1.0, 1.0, 1.0])
    part = np.argwhere((alpha > 0.2) & (alpha < 0.8))[0]
    a = alpha[tuple(part)]
    expect = raw[tuple(part)][:3] * a + (1 - a)
    np.testing.assert_allclose(d.images[0][tuple(part)], expect, atol=1e-6)
    black = load_dataset(root, max_images=1, splits=("train",), background="black")
    np.testing.assert_array_equal(black.images[0][tuple(z)], [0.0, 0.0, 0.0])
    np.testing.assert_allclose(black.images[0][tuple(part)], raw[tuple(part)][:3] * a, atol=1e-6)
    np.testing.assert_array_equal(black.poses[0], d.poses[0])
    # the coverage is kept for training on random backgrounds: the same alpha, [N, H, W]
    assert d.alpha.shape == (6, 400, 400) and d.alpha.dtype == np.float32
    np.testing.assert_allclose(d.alpha[0], alpha, atol=1e-7)


def test_blender_downscale(scene):
    d = load_dataset(scene("lego_400"), max_images=1, splits=("train",), downscale=4)
    _check_common(d, 1, (100, 100))
    # the coverage is box-averaged like the colours (before compositing)
    raw = iio.imread(scene("lego_400") / "train" / "r_0.png").astype(np.float64) / 255.0
    want = raw[..., 3].reshape(100, 4, 100, 4).mean(axis=(1, 3))
    np.testing.assert_allclose(d.alpha[0], want, atol=1e-6)
    f = 0.5 * 400 / np.tan(0.5 * 0.6911112070083618) / 4
    np.testing.assert_allclose(d.intrinsics, [f, f, 50, 50])


# ---------------------------------------------------------------- LLFF

def test_llff_fern(scene):
    d = load_dataset(scene("fern"))
    _check_common(d, 20, (378, 504))
    np.testing.assert_array_equal(d.split["test"], [0, 8, 16])            # every 8th held out
    assert len(d.split["train"]) == 17
    assert d.ndc and d.preset == "forward_facing" and (d.near, d.far) == (0.0, 1.0)
    raw = np.load(scene("fern") / "poses_bounds.npy")
    f = raw[0, 14] * 504 / raw[0, 9]                                      # focal * 504 / 4032
    np.testing.assert_allclose(d.intrinsics, [f, f, 252, 189])
    # recentred: the mean position is the origin, cameras look down -z (forward-facing)
    np.testing.assert_allclose(d.poses[:, :3, 3].mean(0), 0.0, atol=1e-5)
    assert np.all(d.poses[:, 2, 2] > 0.95)
    # bounds rescale: the nearest scene depth is 1/0.75 -> translations are O(0.1..1)
    assert 0.05 < np.abs(d.poses[:, :3, 3]).max() < 2.0
    # the NDC box holds every view's rays from the near plane to infinity: wider than the cube
    # in x, y (the cube cut ~15 % of fern's training rays short), and no wider than needed
    o, dd = view_rays(d, d.poses)
    ends = np.abs(np.concatenate([o, o + dd]))
    assert np.all(ends <= d.bbox[1] + 1e-6) and np.all(d.bbox[0] == -d.bbox[1])
    assert d.bbox[1, 2] == 1.0 and np.all(d.bbox[1, :2] > 1.2)
    assert np.all(d.bbox[1, :2] < ends.max(0)[:2] * 1.02)


def test_llff_bonsai_real360(scene):
    d = load_dataset(scene("bonsai_800"), max_images=1)
    _check_common(d, 2, (533, 800))
    np.testing.assert_allclose(d.intrinsics, [826.86, 826.86, 400.0, 266.5], atol=0.01)
    assert not d.ndc and d.preset == "real360"
    pos = d.poses[:, :3, 3]
    assert np.all(np.linalg.norm(pos, axis=-1) <= 1.0 + 1e-5)
    assert np.all(pos >= d.bbox[0] - 1e-6) and np.all(pos <= d.bbox[1] + 1e-6)
    # every camera looks roughly at the origin (the focus point)
    fwd = -d.poses[:, :3, 2]
    assert np.all(np.einsum("ij,ij->i", fwd, -pos / np.linalg.norm(pos, axis=-1)[:, None]) > 0.9)


# ---------------------------------------------------------------- instant-ngp

def test_ngp_fox_skips_missing(scene):
    with pytest.warns(UserWarning, match=r"skipping 17 of 67 frames.*images/0005\.jpg"):
        d = load_dataset(scene("fox"), max_images=10, downscale=8)
    # 50 present frames: test = 0, 8, ..., 48 (7 frames); train capped at 10
    assert len(d.split["test"]) == 7 and len(d.split["train"]) == 10
    _check_common(d, 17, (240, 135))
    np.testing.assert_allclose(d.intrinsics, np.array([1375.52, 1374.49, 554.558, 965.268]) / 8)
    assert d.distortion.family == "radtan"        # no camera_model: OPENCV (k1, k2, p1, p2)
    np.testing.assert_allclose(d.distortion.coeffs[:4], [0.0578421, -0.0805099, -0.000980296,
                                                         0.00015575])
    # the aabb_scale cube holds the scene: real360 without the MSI background
    assert d.preset == "real360_box" and not d.ndc
    np.testing.assert_allclose(d.bbox, [[-2 / 0.33] * 3, [2 / 0.33] * 3])  # aabb_scale 4


# ---------------------------------------------------------------- dispatch

def test_detect_layout(scene):
    assert detect_layout(scene("lego_400")) == "blender"
    assert detect_layout(scene("fox")) == "ngp"
    assert detect_layout(scene("fern")) == "llff"
    assert detect_layout(scene("tiny_lego")) == "npz"
    assert detect_layout(None) == "procedural"


def test_unknown_layout(tmp_path):
    (tmp_path / "notes.txt").write_text("hello")
    with pytest.raises(DataError) as e:
        load_dataset(tmp_path)
    msg = str(e.value)
    assert str(tmp_path) in msg and "transforms_train.json" in msg and "poses_bounds.npy" in msg
    with pytest.raises(DataError, match="does not exist"):
        load_dataset(tmp_path / "nowhere")
