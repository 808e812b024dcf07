"""Bad input fails loudly: each case is a small crafted scene in tmp_path, and the DataError
message must name the file and the field (or the offending path)."""
import json

import imageio.v3 as iio
import numpy as np
import pytest

from clrf.data import DataError, load_dataset
from clrf.data.blender import load_blender

ANGLE = 0.69


def _pose(tx=0.0):
    m = np.eye(4)
    m[:3, 3] = [tx, 0.0, 4.0]
    return m.tolist()


def _png(path, h=4, w=4, alpha=True):
    path.parent.mkdir(parents=True, exist_ok=True)
    a = np.full((h, w, 4 if alpha else 3), 200, np.uint8)
    iio.imwrite(path, a)


def make_blender(root, n=2, splits=("train", "val", "test")):
    """A valid 4x4-pixel Blender scene with ``n`` frames per split."""
    for s in splits:
        frames = []
        for i in range(n):
            _png(root / s / f"r_{i}.png")
            frames.append({"file_path": f"./{s}/r_{i}", "transform_matrix": _pose(i)})
        (root / f"transforms_{s}.json").write_text(json.dumps({"camera_angle_x": ANGLE,
                                                               "frames": frames}))
    return root


def _edit(path, fn):
    meta = json.loads(path.read_text())
    fn(meta)
    path.write_text(json.dumps(meta))


def _raises(call, *needles):
    with pytest.raises(DataError) as e:
        call()
    msg = str(e.value)
    for n in needles:
        assert str(n) in msg, f"{n!r} not in {msg!r}"
    return msg


def test_crafted_scene_loads(tmp_path):
    d = load_dataset(make_blender(tmp_path))               # the baseline all cases break
    assert d.images.shape == (6, 4, 4, 3)


def test_missing_folder(tmp_path):
    _raises(lambda: load_blender(tmp_path / "absent"), tmp_path / "absent", "does not exist")


def test_missing_json(tmp_path):
    root = make_blender(tmp_path)
    (root / "transforms_val.json").unlink()
    _raises(lambda: load_dataset(root), "transforms_val.json", "does not exist")


def test_missing_image_file(tmp_path):
    root = make_blender(tmp_path)
    (root / "test" / "r_1.png").unlink()
    _raises(lambda: load_dataset(root), "r_1.png", "does not exist")


def test_malformed_json(tmp_path):
    root = make_blender(tmp_path)
    (root / "transforms_train.json").write_text('{"camera_angle_x": 0.69, "frames": [,]}')
    _raises(lambda: load_dataset(root), "transforms_train.json", "malformed JSON", "line 1")


def test_missing_required_fields(tmp_path):
    root = make_blender(tmp_path)
    _edit(root / "transforms_test.json", lambda m: m.pop("camera_angle_x"))
    _raises(lambda: load_dataset(root), "transforms_test.json", "'camera_angle_x'", "missing")
    root = make_blender(tmp_path / "b")
    _edit(root / "transforms_train.json", lambda m: m["frames"][1].pop("transform_matrix"))
    _raises(lambda: load_dataset(root), "transforms_train.json", "frames[1].transform_matrix")
    root = make_blender(tmp_path / "c")
    _edit(root / "transforms_val.json", lambda m: m.pop("frames"))
    _raises(lambda: load_dataset(root), "transforms_val.json", "'frames'")


def test_wrong_field_type(tmp_path):
    root = make_blender(tmp_path)
    _edit(root / "transforms_train.json", lambda m: m.update(camera_angle_x="wide"))
    _raises(lambda: load_dataset(root), "transforms_train.json", "camera_angle_x", "number")
    root = make_blender(tmp_path / "b")
    _edit(root / "transforms_train.json",
          lambda m: m["frames"][0].update(transform_matrix=[[1, 0], [0, 1]]))
    _raises(lambda: load_dataset(root), "frames[0].transform_matrix", "4x4")


def test_mixed_image_sizes(tmp_path):
    root = make_blender(tmp_path)
    _png(root / "val" / "r_1.png", h=5, w=4)
    msg = _raises(lambda: load_dataset(root), "r_1.png", "4x5", "train/r_0.png")
    assert "val" in msg


def test_unreadable_image(tmp_path):
    root = make_blender(tmp_path)
    (root / "train" / "r_1.png").write_bytes(b"this is not a png")
    _raises(lambda: load_dataset(root), "r_1.png", "unreadable")


@pytest.mark.parametrize("bad, what", [
    (lambda m: np.diag([2.0, 1.0, 1.0, 1.0]) @ m, "not orthonormal"),       # scaled rotation
    (lambda m: m + np.array([[0, 0, 0, 0]] * 3 + [[0, 0, 0.5, 0]]), "bottom row"),
])
def test_non_rigid_pose(tmp_path, bad, what):
    root = make_blender(tmp_path)
    _edit(root / "transforms_val.json",
          lambda m: m["frames"][1].update(transform_matrix=bad(np.array(_pose(1))).tolist()))
    _raises(lambda: load_dataset(root), "transforms_val.json", "frames[1].transform_matrix",
            "not a rigid transform", what)


def test_slightly_off_rotation_accepted(tmp_path):
    # within the 1e-3 orthonormality tolerance (float32 exports): loads
    root = make_blender(tmp_path)
    _edit(root / "transforms_val.json", lambda m: m["frames"][1].update(
        transform_matrix=(np.diag([1.0002, 1.0, 1.0, 1.0]) @ np.array(_pose(1))).tolist()))
    assert load_dataset(root).images.shape[0] == 6


def test_empty_split(tmp_path):
    root = make_blender(tmp_path)
    _edit(root / "transforms_val.json", lambda m: m.update(frames=[]))
    _raises(lambda: load_dataset(root), "transforms_val.json", "split 'val' is empty")
    _raises(lambda: load_dataset(make_blender(tmp_path / "b"), max_images=0), "is empty")


def test_inconsistent_camera(tmp_path):
    root = make_blender(tmp_path)
    _edit(root / "transforms_test.json", lambda m: m.update(camera_angle_x=0.9))
    _raises(lambda: load_dataset(root), "transforms_test.json", "camera_angle_x", "differs")


# ---------------------------------------------------------------- npz

def _npz(path, n=8, **override):
    arrays = {"images": np.full((n, 4, 4, 3), 0.5, np.float32),
              "poses": np.stack([np.array(_pose(i)) for i in range(n)]).astype(np.float32),
              "focal": np.float64(5.0)}
    arrays.update(override)
    arrays = {k: v for k, v in arrays.items() if v is not None}
    np.savez(path, **arrays)
    return path


def test_npz_ok_and_split_rule(tmp_path):
    d = load_dataset(_npz(tmp_path / "s.npz"), n_test=3)
    np.testing.assert_array_equal(d.split["train"], np.arange(5))
    np.testing.assert_array_equal(d.split["test"], [5, 6, 7])


def test_npz_nan_images(tmp_path):
    imgs = np.full((8, 4, 4, 3), 0.5, np.float32)
    imgs[3, 1, 2, 0] = np.nan
    imgs[4, 0, 0, 1] = np.inf
    _raises(lambda: load_dataset(_npz(tmp_path / "s.npz", images=imgs)), "s.npz", "'images'",
            "2 NaN/Inf")


def test_npz_missing_field(tmp_path):
    _raises(lambda: load_dataset(_npz(tmp_path / "s.npz", focal=None)), "s.npz", "'focal'",
            "missing")


def test_npz_bad_poses(tmp_path):
    poses = np.stack([np.array(_pose(i)) for i in range(8)])
    poses[2, :3, :3] *= 1.1
    _raises(lambda: load_dataset(_npz(tmp_path / "s.npz", poses=poses)), "s.npz", "poses[2]",
            "not a rigid transform")
    _raises(lambda: load_dataset(_npz(tmp_path / "t.npz", poses=poses[:5])), "t.npz", "'poses'")


def test_npz_empty_split(tmp_path):
    _raises(lambda: load_dataset(_npz(tmp_path / "s.npz"), n_test=0), "s.npz", "n_test")
    _raises(lambda: load_dataset(_npz(tmp_path / "t.npz", n=3), n_test=3), "t.npz", "empty")


def test_npz_unreadable(tmp_path):
    (tmp_path / "s.npz").write_bytes(b"garbage")
    _raises(lambda: load_dataset(tmp_path / "s.npz"), "s.npz", "unreadable")


# ---------------------------------------------------------------- LLFF

def _llff(root, n=9, rows=None, folder="images_8", size=(6, 8)):
    root.mkdir(parents=True, exist_ok=True)
    pb = np.zeros((n, 17))
    for i in range(n):
        p = np.zeros((3, 5))
        p[:, :3] = [[0, 1, 0], [1, 0, 0], [0, 0, -1]]        # LLFF (down, right, back) columns
        p[:, 3] = [0.1 * i, 0.0, 0.0]
        p[:, 4] = [48, 64, 50]                               # H, W, focal of the originals
        pb[i, :15] = p.ravel()
        pb[i, 15:] = [2.0 + 0.1 * i, 10.0]
    np.save(root / "poses_bounds.npy", pb if rows is None else rows)
    for i in range(n):
        _png(root / folder / f"IMG_{i:02d}.png", h=size[0], w=size[1], alpha=False)
    return root


def test_llff_crafted_ok(tmp_path):
    d = load_dataset(_llff(tmp_path / "s"))
    assert d.ndc and d.images.shape == (9, 6, 8, 3)
    np.testing.assert_array_equal(d.split["test"], [0, 8])
    np.testing.assert_allclose(d.intrinsics, [50 / 8, 50 / 8, 4, 3])
    # LLFF column 1 (right) is world x and the cameras step 0.1 along it: after the axis
    # conversion, the 1 / (0.75 * min bound) = 1 / 1.5 rescale and recentring on the average
    # camera, they sit on the camera x axis at (0.1 i - 0.4) / 1.5, with identity rotations
    np.testing.assert_allclose(d.poses[:, :3, :3], np.broadcast_to(np.eye(3), (9, 3, 3)),
                               atol=1e-6)
    expect = np.zeros((9, 3))
    expect[:, 0] = (0.1 * np.arange(9) - 0.4) / 1.5
    np.testing.assert_allclose(d.poses[:, :3, 3], expect, atol=1e-6)


def test_llff_errors(tmp_path):
    _raises(lambda: load_dataset(_llff(tmp_path / "a", rows=np.zeros((9, 15)))),
            "poses_bounds.npy", "(N, 17)")
    root = _llff(tmp_path / "b")
    (root / "images_8" / "IMG_03.png").unlink()
    _raises(lambda: load_dataset(root), "images_8", "8 images", "9 rows")
    _raises(lambda: load_dataset(_llff(tmp_path / "c", size=(8, 8))), "images_8", "aspect")
    root = _llff(tmp_path / "d")
    pb = np.load(root / "poses_bounds.npy")
    pb[4, 0] = 3.0                                           # breaks orthonormality of row 4
    np.save(root / "poses_bounds.npy", pb)
    _raises(lambda: load_dataset(root), "poses_bounds.npy", "row 4", "not a rigid transform")
    _raises(lambda: load_dataset(_llff(tmp_path / "e", n=1)), "poses_bounds.npy", "'train'",
            "empty")
    _raises(lambda: load_dataset(_llff(tmp_path / "f"), kind="real360"), "poses_bounds.npy",
            "parallel")


# ---------------------------------------------------------------- instant-ngp

def _ngp(root, n=4, present=None):
    frames = []
    for i in range(n):
        if present is None or i in present:
            _png(root / "images" / f"{i:04d}.png", alpha=False)
        frames.append({"file_path": f"images/{i:04d}.png", "transform_matrix": _pose(i)})
    root.mkdir(parents=True, exist_ok=True)
    (root / "transforms.json").write_text(json.dumps(
        {"fl_x": 5.0, "fl_y": 5.0, "cx": 2.0, "cy": 2.0, "w": 4, "h": 4, "frames": frames}))
    return root


def test_ngp_errors(tmp_path):
    with pytest.warns(UserWarning, match="skipping 1 of 4"):
        d = load_dataset(_ngp(tmp_path / "a", present={0, 1, 3}))
    assert d.images.shape == (3, 4, 4, 3) and d.distortion is None
    root = _ngp(tmp_path / "b", present=set())
    with pytest.warns(UserWarning):
        _raises(lambda: load_dataset(root), "transforms.json", "none of the 4 frames")
    root = _ngp(tmp_path / "c")
    _edit(root / "transforms.json", lambda m: m.pop("fl_x"))
    _raises(lambda: load_dataset(root), "transforms.json", "'fl_x'")
    root = _ngp(tmp_path / "d", n=1)
    _raises(lambda: load_dataset(root), "transforms.json", "'train' is empty")
    root = _ngp(tmp_path / "e")
    _edit(root / "transforms.json", lambda m: m.update(w=8))
    _raises(lambda: load_dataset(root), "transforms.json", "'w', 'h'")
