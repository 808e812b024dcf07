"""camera_path.json (nerfstudio's layout): round trip, a hand-written nerfstudio-style file,
bad files named by field, interpolation, and `clrf render --camera-path` to PNGs and MP4."""
import importlib.util
import json
import math

import imageio.v3 as iio
import numpy as np
import pytest

from clrf.outputs import camera_path as cp
from clrf.data.cameras import look_at
from clrf.cli.main import main as cli
from clrf.outputs.frames import render_pose, spec_from_fov, spec_from_meta, to_uint8
from clrf.training.models import load_model
from clrf.testing.tolerances import CAMERA_ATOL
from viewer_util import train_tiny

# Written by hand in the layout nerfstudio's viewer saves (keyframe "matrix" as a flat list,
# rows first; render_height/width; camera_path entries with camera_to_world, fov, aspect).
NERFSTUDIO_FILE = {
    "camera_type": "perspective", "render_height": 24, "render_width": 32,
    "keyframes": [{"matrix": [1, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1, 4, 0, 0, 0, 1], "fov": 50,
                   "aspect": 1.3333, "override_transition_enabled": False,
                   "override_transition_sec": None}],
    "camera_path": [
        {"camera_to_world": [1, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1, 4, 0, 0, 0, 1], "fov": 50,
         "aspect": 1.3333},
        {"camera_to_world": [0, 0, 1, 4, 1, 0, 0, 0, 0, 1, 0, 0, 0, 0, 0, 1], "fov": 40,
         "aspect": 1.3333}],
    "fps": 24, "seconds": 2, "smoothness_value": 0.5, "is_cycle": False, "crop": None,
}


def test_nerfstudio_file_reads(tmp_path):
    f = tmp_path / "camera_path.json"
    f.write_text(json.dumps(NERFSTUDIO_FILE))
    p = cp.load(f)
    assert (p.width, p.height, p.fps) == (32, 24, 24.0) and p.poses.shape == (2, 4, 4)
    np.testing.assert_array_equal(p.poses[1][:3, 3], [4, 0, 0])   # rows first
    np.testing.assert_array_equal(p.poses[1][:3, 0], [0, 1, 0])
    assert list(p.fovs) == [50.0, 40.0] and len(p.keyframes) == 1


def test_first_viewer_keyframe_matrix_string_is_columns_first():
    d = dict(NERFSTUDIO_FILE)
    m = np.eye(4)
    m[:3, 3] = [1, 2, 3]
    d["keyframes"] = [{"matrix": json.dumps(m.T.reshape(-1).tolist()), "fov": 50,
                       "aspect": 1}]
    p = cp.from_dict(d)
    np.testing.assert_array_equal(p.keyframes[0][0], m)


def test_round_trip(tmp_path):
    keys = [(look_at([3.0, 0, 1], [0, 0, 0]), 45.0), (look_at([0, 3.0, 1], [0, 0, 0]), 30.0),
            (look_at([-3.0, 0, 2], [0, 0, 0]), 60.0)]
    poses, fovs = cp.interpolate(keys, 9)
    path = cp.CameraPath(poses, fovs, 40, 30, 12.0, keys)
    f = tmp_path / "p.json"
    cp.save(f, path)
    back = cp.load(f)
    np.testing.assert_array_equal(back.poses, poses)
    np.testing.assert_array_equal(back.fovs, fovs)
    assert (back.width, back.height, back.fps) == (40, 30, 12.0)
    for (p0, f0), (p1, f1) in zip(keys, back.keyframes):
        np.testing.assert_array_equal(p0, p1)
        assert f0 == f1
    d = json.loads(f.read_text())
    assert d["seconds"] == pytest.approx(9 / 12) and d["render_width"] == 40
    assert {"camera_to_world", "fov", "aspect"} <= set(d["camera_path"][0])
    assert {"matrix", "camera_to_world", "fov", "aspect"} <= set(d["keyframes"][0])


def test_interpolation_hits_the_keyframes_and_stays_rotations():
    keys = [(look_at([3.0, 0, 1], [0, 0, 0]), 45.0), (look_at([0, 3.0, 1], [0, 0, 0]), 30.0),
            (look_at([-3.0, 0, 2], [0, 0, 0]), 60.0)]
    poses, fovs = cp.interpolate(keys, 5)          # keyframes at 0, 2, 4
    for i, (p, f) in zip((0, 2, 4), keys):
        np.testing.assert_array_equal(poses[i], p)
        assert fovs[i] == pytest.approx(f)
    for p in poses:
        np.testing.assert_allclose(p[:3, :3].T @ p[:3, :3], np.eye(3), atol=CAMERA_ATOL)
    assert fovs[1] == pytest.approx(37.5)


@pytest.mark.parametrize("change, words", [
    ({"camera_path": None}, ["'camera_path'"]),
    ({"camera_path": []}, ["'camera_path' is empty"]),
    ({"render_height": "24"}, ["'render_height'", "int"]),
    ({"render_width": 0}, ["'render_width'"]),
    ({"camera_type": "fisheye"}, ["'camera_type'", "perspective"]),
    ({"fps": -1}, ["'fps'"]),
    ({"camera_path": [{"fov": 50}]}, ["camera_path[0]", "'camera_to_world'"]),
    ({"camera_path": [{"camera_to_world": [1, 0, 0], "fov": 50}]},
     ["camera_path[0]", "'camera_to_world'", "16 numbers"]),
    ({"camera_path": [{"camera_to_world": [float("nan")] * 16, "fov": 50}]},
     ["camera_path[0]", "NaN"]),
    ({"camera_path": [{"camera_to_world": np.eye(4).reshape(-1).tolist(), "fov": 0}]},
     ["camera_path[0]", "'fov'"]),
    ({"keyframes": [{"matrix": "nope", "fov": 50}]}, ["keyframes[0]", "'matrix'"]),
])
def test_bad_files_name_the_field(tmp_path, change, words):
    d = dict(NERFSTUDIO_FILE)
    for k, v in change.items():
        if v is None:
            del d[k]
        else:
            d[k] = v
    f = tmp_path / "bad.json"
    f.write_text(json.dumps(d))
    with pytest.raises(cp.CameraPathError) as e:
        cp.load(f)
    for w in words + [str(f)]:
        assert w in str(e.value), (w, str(e.value))


def test_not_json_and_missing_file(tmp_path):
    f = tmp_path / "x.json"
    f.write_text("{nope")
    with pytest.raises(cp.CameraPathError, match="not valid JSON"):
        cp.load(f)
    with pytest.raises(cp.CameraPathError, match="no such file"):
        cp.load(tmp_path / "missing.json")


@pytest.fixture(scope="module")
def ckpt(tmp_path_factory):
    return train_tiny(tmp_path_factory.mktemp("cp") / "run")


@pytest.mark.slow
def test_render_camera_path(ckpt, tmp_path, device, capsys):
    f = tmp_path / "camera_path.json"
    f.write_text(json.dumps(NERFSTUDIO_FILE))
    video = importlib.util.find_spec("imageio_ffmpeg") is not None
    out = tmp_path / "frames"
    assert cli(["--quiet", "render", "--ckpt", str(ckpt), "--camera-path", str(f), "--out",
                str(out)] + (["--video"] if video else [])) == 0
    imgs = [iio.imread(out / f"path_{i:03d}.png") for i in range(2)]
    assert all(im.shape == (24, 32, 3) for im in imgs)
    model, state, _ = load_model(device, ckpt)
    p = cp.load(f)
    for im, pose, fov in zip(imgs, p.poses, p.fovs):
        ref = to_uint8(render_pose(model, spec_from_fov(fov, 32, 24), pose)["rgb"])
        np.testing.assert_array_equal(im, ref)
    if video:
        assert (out / "path.mp4").stat().st_size > 0 and "24 fps" in capsys.readouterr().out
    # a bad file is a usage error naming the field, nothing rendered
    bad = tmp_path / "bad.json"
    bad.write_text(json.dumps({**NERFSTUDIO_FILE, "render_width": -3}))
    assert cli(["render", "--ckpt", str(ckpt), "--camera-path", str(bad), "--out",
                str(tmp_path / "none")]) == 2
    assert "'render_width'" in capsys.readouterr().err
    assert not (tmp_path / "none").exists()


def test_spec_from_meta_scales_like_before():
    meta = {"H": 60, "W": 80, "intrinsics": [100.0, 100.0, 40.0, 30.0], "ndc": False}
    s = spec_from_meta(meta, 0.5)
    assert s.hw == (30, 40)
    np.testing.assert_allclose(s.intrinsics, [50, 50, 20, 15])
    f = spec_from_fov(2 * math.degrees(math.atan(0.5)), 80, 60)   # tan(fov/2) = 0.5
    np.testing.assert_allclose(f.intrinsics, [60, 60, 40, 30])
