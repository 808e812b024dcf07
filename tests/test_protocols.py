"""`clrf eval --protocol`: each protocol's held-out views and resolution on small synthetic
scenes, the refusals, and an end-to-end protocol evaluation of a tiny checkpoint."""
import json

import imageio.v3 as iio
import numpy as np
import pytest

from clrf.data import protocols
from clrf.cli.main import main as cli
from clrf.data import DataError
from clrf.data.llff import load_llff
from clrf.data.synthetic import load_procedural
from clrf.data.protocols import ProtocolError, prepare

CAPTURE = (96, 128, 100.0)      # H, W, focal of the "original" capture in poses_bounds.npy


def _write_images(folder, n, hw, seed=0):
    rng = np.random.default_rng(seed)
    folder.mkdir(parents=True, exist_ok=True)
    for i in range(n):
        iio.imwrite(folder / f"IMG_{i:03d}.png", rng.integers(0, 255, (*hw, 3), np.uint8))


def _llff_scene(root, folders, n=17, kind="forward_facing"):
    """n views in the LLFF layout; folders: {name: (H, W)} image folders to write."""
    root.mkdir(parents=True, exist_ok=True)
    pb = np.zeros((n, 17))
    for i in range(n):
        if kind == "forward_facing":
            down, right, back = [0, -1, 0], [1, 0, 0], [0, 0, 1]
            c = np.array([0.05 * i, 0.02 * (i % 3), 0.0])
        else:                                   # a circle of cameras looking at the origin
            a = 2 * np.pi * i / n
            c = 4 * np.array([np.cos(a), np.sin(a), 0.3])
            back = c / np.linalg.norm(c)
            right = np.cross([0, 0, 1], back)
            right /= np.linalg.norm(right)
            down = -np.cross(back, right)
        p = np.zeros((3, 5))
        p[:, 0], p[:, 1], p[:, 2], p[:, 3] = down, right, back, c
        p[:, 4] = CAPTURE
        pb[i, :15] = p.ravel()
        pb[i, 15:] = [2.0 + 0.1 * i, 10.0]
    np.save(root / "poses_bounds.npy", pb)
    for name, hw in folders.items():
        _write_images(root / name, n, hw)
    return root


def test_llff_protocol_takes_every_8th_view_at_a_quarter(tmp_path):
    root = _llff_scene(tmp_path / "ff", {"images_4": (24, 32), "images_8": (12, 16)})
    pd = prepare("llff", root)
    assert pd.standard and pd.hw == (24, 32) == pd.protocol_hw and pd.note == ""
    full = load_llff(root, downscale=4)
    np.testing.assert_array_equal(full.split["test"], [0, 8, 16])
    np.testing.assert_allclose(pd.dataset.poses[pd.views], full.poses[full.split["test"]])
    np.testing.assert_array_equal(pd.dataset.images[pd.views], full.images[full.split["test"]])
    np.testing.assert_allclose(pd.dataset.intrinsics, [25.0, 25.0, 16.0, 12.0])
    assert pd.dataset.ndc and pd.detail["factor"] == 4


def test_llff_protocol_downscales_full_resolution_images(tmp_path):
    root = _llff_scene(tmp_path / "ff", {"images": (96, 128)})
    pd = prepare("llff", root)
    assert pd.standard and pd.hw == (24, 32) and len(pd.views) == 3


def test_llff_protocol_refuses_smaller_images(tmp_path):
    root = _llff_scene(tmp_path / "ff", {"images_8": (12, 16)})
    with pytest.raises(ProtocolError) as e:
        prepare("llff", root)
    msg = str(e.value)
    for part in ("images_4/ at 32x24", "128x96", "images_8/ is 16x12", "--allow-downscaled"):
        assert part in msg, msg
    pd = prepare("llff", root, allow_downscaled=True)
    assert not pd.standard and pd.hw == (12, 16) and pd.protocol_hw == (24, 32)
    assert pd.note.startswith("NOT the llff protocol") and len(pd.views) == 3


def test_llff_protocol_refuses_a_360_scene_and_other_layouts(tmp_path):
    root = _llff_scene(tmp_path / "garden", {"images_4": (24, 32)}, kind="real360")
    with pytest.raises(ProtocolError, match="use --protocol mipnerf360"):
        prepare("llff", root)
    with pytest.raises(ProtocolError, match="LLFF layout"):
        prepare("llff", _blender_scene(tmp_path / "b", 8))
    with pytest.raises(ProtocolError, match="NeRF synthetic layout"):
        prepare("blender", root)


@pytest.mark.parametrize("name,factor", [("garden", 4), ("bicycle", 4), ("room", 2),
                                         ("bonsai_800", 2)])
def test_mipnerf360_factor_by_scene(tmp_path, name, factor):
    hw = (CAPTURE[0] // factor, CAPTURE[1] // factor)
    root = _llff_scene(tmp_path / name, {f"images_{factor}": hw}, kind="real360")
    pd = prepare("mipnerf360", root)
    assert pd.standard and pd.hw == hw and not pd.dataset.ndc
    np.testing.assert_array_equal(pd.views, [0, 1, 2])
    full = load_llff(root, downscale=factor)
    np.testing.assert_allclose(pd.dataset.poses, full.poses[[0, 8, 16]])
    assert pd.detail == {"scene_type": "indoor" if factor == 2 else "outdoor", "factor": factor}


def test_mipnerf360_unknown_scene_needs_scene_type(tmp_path):
    root = _llff_scene(tmp_path / "myscene", {"images_2": (48, 64)}, kind="real360")
    with pytest.raises(ProtocolError, match="--scene-type indoor or outdoor"):
        prepare("mipnerf360", root)
    assert prepare("mipnerf360", root, scene_type="indoor").hw == (48, 64)
    # outdoor wants 1/4, which this scene lacks: refused, naming what it has
    with pytest.raises(ProtocolError, match="images_4/ at 32x24"):
        prepare("mipnerf360", root, scene_type="outdoor")
    with pytest.raises(ProtocolError, match="use --protocol llff"):
        prepare("mipnerf360", _llff_scene(tmp_path / "room", {"images_2": (48, 64)}))
    # the kind is checked first: a forward-facing capture of any name is sent to llff
    with pytest.raises(ProtocolError, match="use --protocol llff"):
        prepare("mipnerf360", _llff_scene(tmp_path / "other", {"images_8": (12, 16)}))


def test_protocol_on_a_malformed_poses_file(tmp_path):
    root = _llff_scene(tmp_path / "ff", {"images_4": (24, 32)})
    np.save(root / "poses_bounds.npy", np.zeros((17, 15)))
    with pytest.raises(DataError, match="poses_bounds.npy: expected shape"):
        prepare("llff", root)


def _blender_scene(root, size, n=(6, 1, 3)):
    """A Blender-layout scene from the procedural scene's views at ``size`` pixels (opaque
    RGBA, so compositing on white changes nothing)."""
    ds = load_procedural(n_train=n[0], n_test=n[1] + n[2], size=size)
    angle = 2 * np.arctan(0.5 * size / ds.intrinsics[0])
    idx = {"train": ds.split["train"], "val": ds.split["test"][:n[1]],
           "test": ds.split["test"][n[1]:]}
    for s, views in idx.items():
        frames = []
        for v in views:
            rgba = np.concatenate([ds.images[v], np.ones((size, size, 1), np.float32)], -1)
            (root / s).mkdir(parents=True, exist_ok=True)
            iio.imwrite(root / s / f"r_{v}.png", (rgba * 255 + 0.5).astype(np.uint8))
            frames.append({"file_path": f"./{s}/r_{v}", "transform_matrix": ds.poses[v].tolist()})
        (root / f"transforms_{s}.json").write_text(json.dumps({"camera_angle_x": angle,
                                                                "frames": frames}))
    return root


def test_blender_protocol_refuses_downscaled_copies(tmp_path):
    root = _blender_scene(tmp_path / "lego_small", 16)
    with pytest.raises(ProtocolError) as e:
        prepare("blender", root)
    assert "16x16" in str(e.value) and "800x800" in str(e.value)
    pd = prepare("blender", root, allow_downscaled=True)
    assert not pd.standard and pd.background == (1.0, 1.0, 1.0) and len(pd.views) == 3
    assert "NOT the blender protocol" in pd.note


FAST = ["--set", "grid.reso=[[16,16,16],[24,24,24]]", "--set", "grid.upsample_at=[6]",
        "--set", "grid.batch_size=1024", "--set", "train.eval_every=100",
        "--set", "train.eval_views=1"]


@pytest.fixture(scope="module")
def blender_run(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("bl")
    data = _blender_scene(tmp / "scene", 32)
    out = tmp / "run"
    # trained at half resolution: the protocol must render at the data's full 32x32
    assert cli(["train", "--data", str(data), "--out", str(out), "--max-seconds", "2",
                "--set", "train.downscale=2", *FAST]) == 0
    return data, out


def test_eval_protocol_end_to_end(blender_run, tmp_path, monkeypatch, capsys):
    data, out = blender_run
    monkeypatch.setenv("CLRF_LPIPS_WEIGHTS", str(tmp_path / "no_weights"))
    monkeypatch.setenv("TORCH_HOME", str(tmp_path / "no_torch_home"))
    # the real protocol: 800x800 test views, which this scene lacks
    assert cli(["eval", "--ckpt", str(out), "--protocol", "blender"]) == 2
    err = capsys.readouterr().err
    assert "800x800" in err and "--allow-downscaled" in err
    assert not (out / "eval_blender.json").exists()
    # with 32x32 as the protocol's resolution, this is the protocol
    monkeypatch.setattr(protocols, "BLENDER_HW", (32, 32))
    assert cli(["eval", "--ckpt", str(out), "--protocol", "blender"]) == 0
    text = capsys.readouterr().out
    ev = json.loads((out / "eval_blender.json").read_text())
    assert ev["protocol"] == "blender" and ev["standard"] and ev["resolution"] == [32, 32]
    assert ev["protocol_resolution"] == [32, 32] and ev["n_views"] == 3
    assert [m["view"] for m in ev["views"]] == [0, 1, 2] and ev["ssim_window"] == "gaussian11"
    assert np.isfinite(ev["psnr"]) and 0 < ev["ssim"] <= 1
    assert ev["lpips"] is None and "LPIPS unavailable" in ev["lpips_unavailable"]
    assert "LPIPS unavailable" in text and "blender protocol, mean over 3 views at 32x32" in text
    # the run's own evaluation was at its training resolution (16x16): a different figure
    own = json.loads((out / "eval.json").read_text())
    assert own["psnr"] != ev["psnr"]
    # --max-views: not the whole protocol, and said so
    assert cli(["eval", "--ckpt", str(out), "--protocol", "blender", "--max-views", "1",
                "--lpips", "none", "--out", str(tmp_path / "one.json")]) == 0
    one = json.loads((tmp_path / "one.json").read_text())
    assert not one["standard"] and "--max-views" in one["note"] and one["lpips"] is None
