"""Loader-level checks through the Python API (load_dataset / load_blender), and the small valid
scenes (make_blender, _npz, _llff, _ngp) that the CLI bad-input corpus (test_bad_inputs.py)
breaks one way per row. Cases the corpus covers are not repeated here."""
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


def test_missing_required_fields(tmp_path):
    root = make_blender(tmp_path / "b")
    _edit(root / "transforms_train.json", lambda m: m["frames"][1].pop("transform_matrix"))
    _raises(lambda: load_dataset(root), "transforms_train.json", "frames[1].transform_matrix")
    root = make_blender(tmp_path / "c")
    _edit(root / "transforms_val.json", lambda m: m.pop("frames"))
    _raises(lambda: load_dataset(root), "transforms_val.json", "'frames'")


@pytest.mark.parametrize("bad, what", [
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
    _raises(lambda: load_dataset(make_blender(tmp_path / "b"), max_images=0), "is empty")


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


def test_npz_empty_split(tmp_path):
    _raises(lambda: load_dataset(_npz(tmp_path / "s.npz"), n_test=0), "s.npz", "n_test")
    _raises(lambda: load_dataset(_npz(tmp_path / "t.npz", n=3), n_test=3), "t.npz", "empty")


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
    root = _ngp(tmp_path / "c")
    _edit(root / "transforms.json", lambda m: m.pop("fl_x"))
    _raises(lambda: load_dataset(root), "transforms.json", "'fl_x'")
    root = _ngp(tmp_path / "d", n=1)
    _raises(lambda: load_dataset(root), "transforms.json", "'train' is empty")
