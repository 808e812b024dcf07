"""The bad-input corpus: every row is one broken dataset, config, option or checkpoint, run
through the CLI in-process. Each must exit 2 with exactly one ``clrf: error:`` message that
names the file or field (the row's needles) and the fix, print no traceback, and write nothing:
the set of files under tmp_path is the same before and after the command.

A row is (id, build, needles): ``build(tmp_path)`` writes the small synthetic inputs and returns
the CLI arguments; every needle must appear in the error message. The valid baselines the rows
break are loaded by test_data_errors.py (and the ``valid`` rows here).
"""
import json
import importlib.util
import os
import struct
import shutil
import subprocess
import sys
import zlib
from pathlib import Path

import imageio.v3 as iio
import numpy as np
import pytest
from PIL import Image

from clrf.cli.main import main as cli
from test_colmap import F, H, W, _colmap_scene, _images, _scene
from test_data_errors import _edit, _llff, _ngp, _npz, _png, make_blender

FIX_WORDS = ("pass", "add", "use", "fix", "remove", "replace", "regenerate", "re-", "restore",
             "convert", "copy", "move", "lower", "store", "resize", "check", "must", "expected")


# ---------------------------------------------------------------- builders

def blender(tmp, edit=None, split="train", **frame):
    """A valid Blender scene in tmp/scene; ``edit(meta)`` rewrites transforms_<split>.json,
    ``frame`` updates its frames[1]."""
    root = make_blender(tmp / "scene")
    if edit is not None:
        _edit(root / f"transforms_{split}.json", edit)
    if frame:
        _edit(root / f"transforms_{split}.json", lambda m: m["frames"][1].update(frame))
    return root


def train(data, *extra):
    return ["train", "--data", str(data), "--out", "OUT", "--max-seconds", "1", *extra]


def blender_json(**frame):
    return lambda t: train(blender(t, **frame))


def blender_meta(edit, split="train"):
    return lambda t: train(blender(t, edit, split))


def blender_image(write):
    """Replace train/r_1.png by ``write(path)``."""
    def build(t):
        root = blender(t)
        write(root / "train" / "r_1.png")
        return train(root)
    return build


def blender_text(split, text):
    def build(t):
        (blender(t) / f"transforms_{split}.json").write_text(text)
        return train(t / "scene")
    return build


def png_bomb(path, w=100_000, h=100_000):
    """A PNG of a few bytes whose header declares w x h RGBA pixels."""
    def chunk(kind, data):
        return (struct.pack(">I", len(data)) + kind + data
                + struct.pack(">I", zlib.crc32(kind + data) & 0xFFFFFFFF))
    ihdr = struct.pack(">IIBBBBB", w, h, 8, 6, 0, 0, 0)
    path.write_bytes(b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", ihdr)
                     + chunk(b"IDAT", zlib.compress(b"\0" * 8)) + chunk(b"IEND", b""))


def truncated_png(path):
    _png(path)
    data = path.read_bytes()
    path.write_bytes(data[:len(data) // 2])


def palette_png(path):
    Image.fromarray(np.full((4, 4, 3), 90, np.uint8)).convert("P").save(path)


def symlink_out(path):
    outside = path.parents[2] / "outside.png"
    _png(outside)
    path.unlink()
    os.symlink(outside, path)


def npz(**override):
    def build(t):
        (t / "scene").mkdir()
        return train(_npz(t / "scene" / "s.npz", **override))
    return build


def npz_bytes(data):
    def build(t):
        (t / "s.npz").write_bytes(data)
        return train(t / "s.npz")
    return build


def _poses(n=8, fn=None):
    p = np.tile(np.eye(4), (n, 1, 1))
    p[:, 2, 3] = 4.0
    if fn is not None:
        fn(p)
    return p


def llff(edit_rows=None, edit_root=None, **kw):
    """A valid 9-view LLFF scene, then ``edit_rows(poses_bounds)`` / ``edit_root(root)``."""
    def build(t):
        root = _llff(t / "scene", **kw)
        if edit_rows is not None:
            pb = np.load(root / "poses_bounds.npy")
            edit_rows(pb)
            np.save(root / "poses_bounds.npy", pb)
        if edit_root is not None:
            edit_root(root)
        return train(root)
    return build


def mip360(t, n=9):
    """A valid Mip-NeRF 360 layout: n cameras on a circle looking at the origin."""
    root = t / "scene"
    rows = np.zeros((n, 17))
    for i in range(n):
        a = 2 * np.pi * i / n
        back = np.array([np.cos(a), np.sin(a), 0.0])        # camera +z (OpenGL back) axis
        up = np.array([0.0, 0.0, 1.0])
        right = np.cross(up, back)
        p = np.zeros((3, 5))
        p[:, 0], p[:, 1], p[:, 2] = -up, right, back            # LLFF (down, right, back)
        p[:, 3] = 4.0 * back
        p[:, 4] = [48, 64, 50]
        rows[i, :15] = p.ravel()
        rows[i, 15:] = [0.01, 0.01]                             # placeholder bounds (as bonsai)
    root.mkdir(parents=True)
    np.save(root / "poses_bounds.npy", rows)
    for i in range(n):
        _png(root / "images_4" / f"IMG_{i:02d}.png", h=6, w=8, alpha=False)
    return root


def mip(edit):
    def build(t):
        root = mip360(t)
        edit(root)
        return train(root)
    return build


def mip_rows(fn):
    def edit(root):
        pb = np.load(root / "poses_bounds.npy")
        fn(pb)
        np.save(root / "poses_bounds.npy", pb)
    return mip(edit)


def ngp(edit=None, present=None):
    def build(t):
        root = _ngp(t / "scene", n=4, present=present)
        if edit is not None:
            _edit(root / "transforms.json", edit)
        return train(root)
    return build


def ngp_frame(**frame):
    return ngp(lambda m: m["frames"][1].update(frame))


def empty_folder(t):
    (t / "empty").mkdir()
    return train(t / "empty")


def small_npz(t):
    """A valid 8-view .npz scene (fast to load) for the option and config rows."""
    return _npz(t / "s.npz")


def opts(*extra):
    return lambda t: train(small_npz(t), *extra)


def splat_ply(edit=None, n=4, *extra):
    """Train a splat model from s.ply (n Gaussians written by clrf, then edited)."""
    def build(t):
        from clrf.splat.ply import write_splat_ply
        rng = np.random.default_rng(0)
        path = t / "s.ply"
        write_splat_ply(path, rng.normal(size=(n, 3)), np.full((n, 3), -3.0),
                        np.tile([1.0, 0, 0, 0], (n, 1)), np.zeros(n),
                        rng.normal(size=(n, 16, 3)))
        if edit:
            edit(path)
        return train(small_npz(t), "--model", "splat", "--set", f"splat.init_ply={path}",
                     *extra)
    return build


def _drop_property(name):
    def edit(path):
        data = path.read_bytes()
        end = data.index(b"end_header\n") + len(b"end_header\n")
        head = data[:end].decode().replace(f"property float {name}\n", "")
        path.write_bytes(head.encode() + data[end:])
    return edit


def _splat_nan(path):
    data = bytearray(path.read_bytes())
    end = data.index(b"end_header\n") + len(b"end_header\n")
    data[end + 4:end + 8] = np.float32(np.nan).tobytes()      # vertex 0's y
    path.write_bytes(bytes(data))


def config(obj):
    def build(t):
        f = t / "c.json"
        f.write_text(obj if isinstance(obj, str) else json.dumps(obj))
        return train(small_npz(t), "--config", str(f))
    return build


def existing_file_out(t):
    (t / "taken").write_text("not a folder")
    return ["train", "--data", str(small_npz(t)), "--out", str(t / "taken")]


def run_dir(t, ckpt=None):
    d = t / "run"
    d.mkdir()
    if ckpt is not None:
        (d / "ckpt.npz").write_bytes(ckpt)
    return d


def resume(ckpt):
    return lambda t: ["train", "--out", str(run_dir(t, ckpt)), "--resume", "--max-seconds", "1"]


def on_ckpt(cmd, ckpt, *extra):
    def build(t):
        d = run_dir(t, ckpt)
        args = [cmd, "--ckpt", str(d), *extra]
        return args + (["--out", str(t / "frames")] if cmd == "render" else [])
    return build


def plain_train_over_run(t):
    d = run_dir(t, b"x")
    return ["train", "--data", str(small_npz(t)), "--out", str(d), "--max-seconds", "1"]


def nan_row(i):
    def fn(pb):
        pb[i, 3] = np.nan
    return fn


def _set(pb, idx, v):
    pb[idx] = v


def colmap(edit=None, fmt="txt", **kw):
    """A valid forward-facing COLMAP folder (images/ + sparse/0/, text or binary model), then
    ``edit(root)``."""
    def build(t):
        poses, points = _scene("forward_facing")
        root = _colmap_scene(t / "scene", poses, points, fmt, **kw)
        if edit is not None:
            edit(root)
        return train(root)
    return build


def colmap_text(name, fn):
    """Rewrite sparse/0/NAME with ``fn(text)``."""
    def edit(root):
        p = root / "sparse" / "0" / name
        p.write_text(fn(p.read_text()))
    return colmap(edit)


def colmap_image_field(i, k, value):
    """images.txt: field k of image i's record line set to ``value``."""
    def fn(text):
        lines = text.splitlines()
        rec = [n for n, line in enumerate(lines) if line and not line.startswith("#")][2 * i]
        parts = lines[rec].split()
        parts[k] = value
        lines[rec] = " ".join(parts)
        return "\n".join(lines) + "\n"
    return colmap_text("images.txt", fn)


def colmap_bytes(name, cut):
    def edit(root):
        p = root / "sparse" / "0" / name
        p.write_bytes(p.read_bytes()[:cut])
    return colmap(edit, fmt="bin")


def pinhole(*params):
    return {1: ("PINHOLE", W, H, list(params))}


_TRAINED = {}


def trained(t):
    """t/run: a copy of a real checkpoint of the built-in scene (trained once per session, a
    few seconds) for the rows that need one: camera paths, export, the viewer, protocols."""
    if "dir" not in _TRAINED:
        import tempfile
        src = Path(tempfile.mkdtemp(prefix="clrf_bad_inputs_")) / "run"
        assert cli(["--quiet", "train", "--out", str(src), "--max-seconds", "1", "--set",
                    "grid.reso=[[16,16,16]]", "--set", "grid.upsample_at=[]", "--set",
                    "train.eval_views=1", "--set", "train.final_eval=false"]) == 0
        _TRAINED["dir"] = src
    d = t / "run"
    d.mkdir()
    for name in ("ckpt.npz", "config.json"):
        shutil.copy(_TRAINED["dir"] / name, d / name)
    return d


def view(*extra):
    """`clrf view` of a real checkpoint with the flags ``extra``."""
    return lambda t: ["view", "--ckpt", str(trained(t)), "--port", "0", "--exit-after", "0.1",
                      *extra]


def camera_path_file(text=None, **fields):
    """`clrf render --camera-path` of a file holding ``text``, or a one-camera path with
    ``fields`` changed (its camera's fields: c2w, fov)."""
    def build(t):
        ck = trained(t)
        f = t / "path.json"
        if text is not None:
            f.write_text(text)
        else:
            cam = {"camera_to_world": fields.pop("c2w", np.eye(4).reshape(-1).tolist()),
                   "fov": fields.pop("fov", 50.0), "aspect": 1.0}
            meta = {"render_width": 16, "render_height": 16, "fps": 24, "seconds": 1,
                    "camera_path": [cam]}
            meta.update(fields)
            f.write_text(json.dumps(meta))
        return ["render", "--ckpt", str(ck), "--camera-path", str(f), "--out", str(t / "frames")]
    return build


def process(make):
    """`clrf process INPUT --out scene`, INPUT = ``make(t)``."""
    return lambda t: ["process", str(make(t)), "--out", str(t / "scene")]


def text_as_mp4(t):
    (t / "clip.mp4").write_text("this is a text file, not a video\n")
    return t / "clip.mp4"


def photos(n):
    def make(t):
        d = t / "photos"
        d.mkdir()
        rng = np.random.default_rng(0)
        for i in range(n):
            iio.imwrite(d / f"p{i}.png", rng.integers(0, 255, (16, 16, 3), dtype=np.uint8))
        return d
    return make


# ---------------------------------------------------------------- the corpus

NAN_POSE = [[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, float("nan")], [0, 0, 0, 1]]
SCALED_POSE = [[2, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 4], [0, 0, 0, 1]]

CASES = [
    # ---- Blender (transforms_{train,val,test}.json + PNGs)
    ("blender-truncated-png", blender_image(truncated_png), ["r_1.png", "unreadable"]),
    ("blender-empty-png", blender_image(lambda p: p.write_bytes(b"")), ["r_1.png", "unreadable"]),
    ("blender-text-as-png", blender_image(lambda p: p.write_bytes(b"this is not a png")),
     ["r_1.png", "unreadable"]),
    ("blender-decompression-bomb", blender_image(png_bomb),
     ["r_1.png", "100000x100000", "resize"]),
    ("blender-grayscale-among-rgba", blender_image(lambda p: iio.imwrite(p, np.zeros((4, 4),
                                                                              np.uint8))),
     ["r_1.png", "RGBA", "channel layout"]),
    ("blender-palette-among-rgba", blender_image(palette_png), ["r_1.png", "channel layout"]),
    ("blender-mixed-sizes", blender_image(lambda p: _png(p, h=5, w=4)),
     ["r_1.png", "4x5", "one size"]),
    ("blender-missing-image", blender_image(lambda p: p.unlink()), ["r_1.png", "does not exist"]),
    ("blender-symlink-escape", blender_image(symlink_out),
     ["frames[1].file_path", "outside the dataset folder"]),
    ("blender-dotdot-escape", blender_json(file_path="../../elsewhere/r_1"),
     ["frames[1].file_path", "outside the dataset folder"]),
    ("blender-absolute-path", blender_json(file_path="/tmp/r_1.png"),
     ["frames[1].file_path", "absolute path"]),
    ("blender-file-path-not-string", blender_json(file_path=7), ["frames[1].file_path", "str"]),
    ("blender-matrix-2x2", blender_json(transform_matrix=[[1, 0], [0, 1]]),
     ["frames[1].transform_matrix", "4x4"]),
    ("blender-matrix-strings", blender_json(transform_matrix="identity"),
     ["frames[1].transform_matrix", "4x4"]),
    ("blender-nan-pose", blender_json(transform_matrix=NAN_POSE),
     ["frames[1].transform_matrix", "NaN"]),
    ("blender-non-rigid-pose", blender_json(transform_matrix=SCALED_POSE),
     ["frames[1].transform_matrix", "not a rigid transform"]),
    ("blender-empty-frames", blender_meta(lambda m: m.update(frames=[]), "val"),
     ["transforms_val.json", "'val' is empty"]),
    ("blender-frames-not-list", blender_meta(lambda m: m.update(frames={"a": 1})),
     ["transforms_train.json", "'frames'", "list"]),
    ("blender-fov-zero", blender_meta(lambda m: m.update(camera_angle_x=0.0)),
     ["camera_angle_x", "(0, pi)"]),
    ("blender-fov-negative", blender_meta(lambda m: m.update(camera_angle_x=-0.5)),
     ["camera_angle_x", "(0, pi)"]),
    ("blender-fov-nan", blender_meta(lambda m: m.update(camera_angle_x=float("nan"))),
     ["camera_angle_x", "finite"]),
    ("blender-fov-string", blender_meta(lambda m: m.update(camera_angle_x="wide")),
     ["camera_angle_x", "number"]),
    ("blender-fov-missing", blender_meta(lambda m: m.pop("camera_angle_x")),
     ["transforms_train.json", "'camera_angle_x'", "missing"]),
    ("blender-fov-differs", blender_meta(lambda m: m.update(camera_angle_x=0.9), "test"),
     ["transforms_test.json", "differs"]),
    ("blender-json-array", blender_text("val", "[]"), ["transforms_val.json", "JSON object"]),
    ("blender-malformed-json", blender_text("train", '{"frames": [,]}'),
     ["transforms_train.json", "line 1"]),
    # ---- tiny NeRF .npz
    ("npz-nan-images", npz(images=np.where(np.arange(384).reshape(8, 4, 4, 3) == 7, np.nan,
                                           0.5).astype(np.float32)), ["s.npz", "'images'", "NaN"]),
    ("npz-inf-pose", npz(poses=_poses(fn=lambda p: p.__setitem__((3, 0, 3), np.inf))),
     ["s.npz", "poses[3]", "NaN or Inf"]),
    ("npz-non-rigid-pose", npz(poses=_poses(fn=lambda p: p.__setitem__((2, 0, 0), 2.0))),
     ["s.npz", "poses[2]", "not a rigid transform"]),
    ("npz-count-mismatch", npz(poses=_poses(5)), ["s.npz", "'poses'", "N = 8"]),
    ("npz-poses-3x3", npz(poses=np.tile(np.eye(3), (8, 1, 1))), ["s.npz", "'poses'"]),
    ("npz-focal-zero", npz(focal=np.float64(0.0)), ["s.npz", "'focal'", "positive"]),
    ("npz-focal-negative", npz(focal=np.float64(-5.0)), ["s.npz", "'focal'", "positive"]),
    ("npz-focal-nan", npz(focal=np.float64(np.nan)), ["s.npz", "'focal'"]),
    ("npz-missing-focal", npz(focal=None), ["s.npz", "'focal'", "missing"]),
    ("npz-images-2d", npz(images=np.zeros((8, 16), np.float32)), ["s.npz", "'images'"]),
    ("npz-garbage", npz_bytes(b"garbage"), ["s.npz", "unreadable"]),
    ("npz-empty-file", npz_bytes(b""), ["s.npz", "unreadable"]),
    # ---- LLFF (forward-facing)
    ("llff-wrong-shape", llff(rows=np.zeros((9, 15))), ["poses_bounds.npy", "(N, 17)"]),
    ("llff-count-mismatch", llff(edit_root=lambda r: (r / "images_8" / "IMG_03.png").unlink()),
     ["images_8", "8 images", "9 rows"]),
    ("llff-nan-pose", llff(nan_row(2)), ["poses_bounds.npy", "NaN or Inf"]),
    ("llff-inf-bounds", llff(lambda pb: _set(pb, (4, 16), np.inf)),
     ["poses_bounds.npy", "NaN or Inf"]),
    ("llff-negative-bounds", llff(lambda pb: _set(pb, (4, 15), -1.0)),
     ["poses_bounds.npy", "bounds", "positive"]),
    ("llff-zero-focal", llff(lambda pb: _set(pb, (0, 14), 0.0)),
     ["poses_bounds.npy", "focal", "positive"]),
    ("llff-non-rigid-pose", llff(lambda pb: _set(pb, (4, 0), 3.0)),
     ["poses_bounds.npy", "row 4", "not a rigid transform"]),
    ("llff-truncated-image", llff(edit_root=lambda r: truncated_png(r / "images_8" / "IMG_05.png")),
     ["IMG_05.png", "unreadable"]),
    ("llff-symlink-escape", llff(edit_root=lambda r: symlink_out(r / "images_8" / "IMG_05.png")),
     ["IMG_05.png", "outside the dataset folder"]),
    ("llff-aspect-mismatch", llff(size=(8, 8)), ["images_8", "aspect"]),
    ("llff-garbage-npy", llff(edit_root=lambda r: (r / "poses_bounds.npy").write_bytes(b"xx")),
     ["poses_bounds.npy", "unreadable"]),
    # ---- Mip-NeRF 360 (LLFF layout, cameras all around)
    ("mip360-inf-pose", mip_rows(lambda pb: _set(pb, (6, 3), np.inf)),
     ["poses_bounds.npy", "NaN or Inf"]),
    ("mip360-grayscale-among-rgb", mip(lambda r: _png(r / "images_4" / "IMG_03.png", h=6, w=8,
                                                       alpha=True)),
     ["IMG_03.png", "channel layout"]),
    ("mip360-no-images", mip(lambda r: (r / "images_4").rename(r / "pictures")),
     ["no images/", "add the images"]),
    # ---- instant-ngp transforms.json
    ("ngp-focal-negative", ngp(lambda m: m.update(fl_x=-5.0)), ["transforms.json", "positive"]),
    ("ngp-focal-zero", ngp(lambda m: m.update(fl_y=0)), ["transforms.json", "positive"]),
    ("ngp-fov-zero", ngp(lambda m: (m.pop("fl_x"), m.update(camera_angle_x=0.0))),
     ["transforms.json", "camera_angle_x", "(0, pi)"]),
    ("ngp-focal-nan", ngp(lambda m: m.update(fl_x=float("nan"))), ["transforms.json", "fl_x"]),
    ("ngp-focal-string", ngp(lambda m: m.update(fl_x="5")), ["transforms.json", "fl_x"]),
    ("ngp-dotdot-escape", ngp_frame(file_path="../elsewhere/0001.png"),
     ["frames[1].file_path", "outside the dataset folder"]),
    ("ngp-absolute-path", ngp_frame(file_path="/etc/hostname"),
     ["frames[1].file_path", "absolute path"]),
    ("ngp-matrix-3x3", ngp_frame(transform_matrix=np.eye(3).tolist()),
     ["frames[1].transform_matrix", "4x4"]),
    ("ngp-no-images", ngp(present=set()), ["transforms.json", "none of the 4 frames"]),
    ("ngp-size-mismatch", ngp(lambda m: m.update(w=8)), ["transforms.json", "'w', 'h'"]),
    ("ngp-frames-not-list", ngp(lambda m: m.update(frames="all")), ["'frames'", "list"]),
    ("ngp-camera-model-unknown", ngp(lambda m: m.update(camera_model="FOV")),
     ["transforms.json", "'camera_model'", "'FOV'", "OPENCV_FISHEYE"]),
    ("ngp-fisheye-field-in-opencv", ngp(lambda m: m.update(camera_model="OPENCV", k4=0.01)),
     ["transforms.json", "k4", "not part of camera_model OPENCV"]),
    # ---- COLMAP (images/ + sparse/0/ cameras, images, points3D as .txt or .bin)
    ("colmap-fov-camera", colmap(cams={1: ("FOV", W, H, [F, F, W / 2, H / 2, 0.1])}),
     ["cameras.txt", "FOV", "image_undistorter"]),
    ("colmap-focal-negative", colmap(cams=pinhole(-F, F, W / 2, H / 2)),
     ["cameras.txt", "camera 1", "positive"]),
    ("colmap-focal-nan", colmap(cams=pinhole(float("nan"), F, W / 2, H / 2)),
     ["cameras.txt", "camera 1", "finite"]),
    ("colmap-camera-params-missing", colmap(cams=pinhole(F, F)),
     ["cameras.txt", "PINHOLE needs 4 parameters"]),
    ("colmap-camera-non-numeric", colmap_text("cameras.txt",
                                              lambda s: s.replace(f"PINHOLE {W}", "PINHOLE wide")),
     ["cameras.txt", "non-numeric"]),
    ("colmap-quaternion-nan", colmap_image_field(1, 1, "nan"), ["images.txt", "quaternion"]),
    ("colmap-quaternion-not-unit", colmap_image_field(1, 1, "3.0"),
     ["images.txt", "quaternion", "unit length"]),
    ("colmap-unknown-camera", colmap_image_field(1, 8, "7"),
     ["images.txt", "camera 7", "does not define"]),
    ("colmap-dotdot-escape", colmap_image_field(1, 9, "../x.png"),
     ["images.txt", "'NAME'", "outside the dataset folder"]),
    ("colmap-absolute-path", colmap_image_field(1, 9, "/etc/hostname"),
     ["images.txt", "'NAME'", "absolute path"]),
    ("colmap-no-registered-images", colmap_text("images.txt", lambda s: "# empty\n"),
     ["images.txt", "no registered images"]),
    ("colmap-point-nan", colmap_text("points3D.txt", lambda s: s.replace(s.split()[1], "nan", 1)),
     ["points3D.txt", "non-finite"]),
    ("colmap-points-missing", colmap(lambda r: (r / "sparse" / "0" / "points3D.txt").unlink()),
     ["points3D.bin / points3D.txt", "missing"]),
    ("colmap-images-bin-truncated", colmap_bytes("images.bin", 100), ["images.bin", "truncated"]),
    ("colmap-cameras-bin-empty", colmap_bytes("cameras.bin", 0), ["cameras.bin", "truncated"]),
    ("colmap-image-missing", colmap(lambda r: (r / "images" / "IMG_004.png").unlink()),
     ["IMG_004.png", "does not exist"]),
    ("colmap-image-not-an-image",
     colmap(lambda r: (r / "images" / "IMG_004.png").write_bytes(b"not a png")),
     ["IMG_004.png", "unreadable image"]),
    ("colmap-image-other-aspect",
     colmap(lambda r: _images(r / "images", ["IMG_004.png"], h=8, w=8)),
     ["IMG_004.png", "camera 1 is 16x12"]),
    # ---- dataset path
    ("data-missing", lambda t: train(t / "nowhere"), ["nowhere", "does not exist"]),
    ("data-no-layout", empty_folder,
     ["empty", "not a dataset layout", "accepted layouts"]),
    # ---- options and config files
    ("set-wrong-type", opts("--set", "grid.batch_size=many"), ["grid.batch_size", "integer"]),
    ("set-bool-type", opts("--set", "grid.sphere_bound=3"), ["grid.sphere_bound", "true or false"]),
    ("set-negative-step", opts("--set", "grid.step=-1"), ["grid.step", "(0, 4]"]),
    ("set-sh-degree-7", opts("--set", "grid.sh_degree=7"), ["grid.sh_degree", "0, 1, 2 or 3"]),
    ("set-upsample-order", opts("--set", "grid.upsample_at=[5,1]"), ["grid.upsample_at"]),
    ("set-reso-too-fine", opts("--set", "grid.reso=[[2048,8,8]]", "--set", "grid.upsample_at=[]"),
     ["grid.reso", "1..1024"]),
    ("set-background-range", opts("--set", "train.background=[2,0,0]"), ["train.background"]),
    ("set-downscale-zero", opts("--set", "train.downscale=0"), ["train.downscale", ">= 1"]),
    ("set-unknown-option", opts("--set", "grid.no_such_option=1"),
     ["unknown option 'grid.no_such_option'"]),
    ("set-no-section", opts("--set", "bogus"), ["SECTION.KEY=VALUE"]),
    ("max-seconds-zero", opts("--max-seconds", "0"), ["train.max_seconds", "> 0"]),
    ("preset-unknown", opts("--preset", "nope"), ["train.preset", "must be one of"]),
    ("config-missing", opts("--config", "/nonexistent.json"), ["config file", "not found"]),
    ("config-malformed", config('{"grid": {"step": }'), ["c.json", "invalid JSON", "line 1"]),
    ("config-top-level-list", config([1, 2]), ["c.json", "JSON object"]),
    ("config-unknown-section", config({"gird": {}}), ["c.json", "unknown section 'gird'"]),
    ("config-reso-string", config({"grid": {"reso": "big"}}), ["c.json", "grid.reso", "list"]),
    ("config-float-for-int", config({"grid": {"batch_size": 10.5}}),
     ["c.json", "grid.batch_size", "integer"]),
    ("memory-too-large", opts("--set", "grid.reso=[[1024,1024,1024]]", "--set",
                              "grid.upsample_at=[]", "--set", "grid.sh_degree=3"),
     ["grid stage 0 (1024x1024x1024, SH degree 3)", "lower grid.reso"]),
    ("splat-ply-missing-rotation", splat_ply(_drop_property("rot_0")),
     ["s.ply", "rot_0", "missing"]),
    ("splat-ply-missing-sh-band", splat_ply(_drop_property("f_rest_7")),
     ["s.ply", "44 f_rest_* properties"]),
    ("splat-ply-truncated", splat_ply(lambda p: p.write_bytes(p.read_bytes()[:-10])),
     ["s.ply", "truncated"]),
    ("splat-ply-not-a-ply", splat_ply(lambda p: p.write_text("x y z\n1 2 3\n")),
     ["s.ply", "not a PLY file"]),
    ("splat-ply-ascii", splat_ply(lambda p: p.write_bytes(
        p.read_bytes().replace(b"binary_little_endian", b"ascii               "))),
     ["s.ply", "format ascii", "binary_little_endian"]),
    ("splat-ply-nan", splat_ply(_splat_nan), ["s.ply", "property y of vertex 0", "finite"]),
    ("splat-ply-past-the-cap", splat_ply(None, 40, "--set", "splat.max_gaussians=30"),
     ["s.ply", "40 Gaussians exceed the cap of 30", "splat.max_gaussians"]),
    ("splat-ply-missing-file", lambda t: train(small_npz(t), "--model", "splat", "--set",
                                               f"splat.init_ply={t / 'none.ply'}"),
     ["none.ply", "cannot read"]),
    ("splat-init-points-without-points", opts("--model", "splat", "--set", "splat.init=points"),
     ["splat.init = 'points'", "no sparse points"]),
    ("train-points-unknown", opts("--set", "train.points=always"),
     ["train.points", "triangulate"]),
    ("splat-init-unknown", opts("--model", "splat", "--set", "splat.init=mesh"),
     ["splat.init", "auto"]),
    ("nerf-width-not-a-number", opts("--model", "nerf", "--set", "nerf.width=abc"),
     ["nerf.width", "integer"]),
    ("nerf-width-not-16s", opts("--model", "nerf", "--set", "nerf.width=17"),
     ["nerf.width = 17", "multiple of 16"]),
    ("nerf-samples-negative", opts("--model", "nerf", "--set", "nerf.n_coarse=-3"),
     ["nerf.n_coarse = -3", "1..1024"]),
    ("nerf-lr-zero", opts("--model", "nerf", "--set", "nerf.lr=0"), ["nerf.lr = 0.0", "(0, 1]"]),
    ("nerf-activation-unknown", opts("--model", "nerf", "--set", "nerf.hidden_act=tanh"),
     ["nerf.hidden_act = 'tanh'", "'relu' or 'softplus'"]),
    ("nerf-skip-past-depth", opts("--model", "nerf", "--set", "nerf.skip=3"),
     ["nerf.skip = 3", "depth-2"]),
    ("nerf-preset-unknown", opts("--model", "nerf", "--set", "nerf.preset=huge"),
     ["nerf.preset = 'huge'", "original", "tiny"]),
    ("nerf-tile-rows", opts("--model", "nerf", "--set", "nerf.mlp_rows=7"),
     ["nerf.mlp_rows = 7", "one of 1, 2"]),
    ("nerf-unknown-option", opts("--model", "nerf", "--set", "nerf.widht=64"),
     ["unknown option 'nerf.widht'", "width"]),
    ("memory-nerf-too-large", opts("--model", "nerf", "--set", "nerf.batch_rays=4194304"),
     ["NeRF training (4194304 rays", "lower nerf.batch_rays"]),
    # ---- output folder and checkpoints
    ("out-is-a-file", existing_file_out, ["taken", "existing file"]),
    ("out-holds-a-run", plain_train_over_run, ["already holds a run", "--resume"]),
    ("resume-no-checkpoint", resume(None), ["no checkpoint", "ckpt.npz"]),
    ("resume-corrupt-checkpoint", resume(b"PK\x03\x04 truncated"), ["ckpt.npz", "unreadable"]),
    ("eval-no-checkpoint", on_ckpt("eval", None), ["no checkpoint"]),
    ("eval-corrupt-checkpoint", on_ckpt("eval", b"garbage"), ["ckpt.npz", "unreadable"]),
    ("render-no-checkpoint", on_ckpt("render", None), ["no checkpoint"]),
    ("render-corrupt-checkpoint", on_ckpt("render", b""), ["ckpt.npz", "unreadable"]),
    # ---- camera paths (clrf render --camera-path)
    ("camera-path-not-json", camera_path_file("not json {"), ["path.json", "not valid JSON"]),
    ("camera-path-nan", camera_path_file(c2w=[float("nan")] * 16),
     ["path.json", "camera_path[0]", "NaN"]),
    ("camera-path-12-numbers", camera_path_file(c2w=[1.0] * 12),
     ["path.json", "camera_path[0]", "16 numbers"]),
    ("camera-path-huge-frames", camera_path_file(render_width=200_000),
     ["path.json", "'render_width' = 200000", "1..4096"]),
    # ---- export
    ("export-mesh-100000-cubed", lambda t: ["export", "--ckpt", str(trained(t)), "--mesh",
                                            str(t / "m.ply"), "--reso", "100000"],
     ["--reso 100000", "2..2048"]),
    # ---- protocols (clrf eval --protocol)
    ("protocol-without-the-scene", lambda t: ["eval", "--ckpt", str(trained(t)), "--protocol",
                                              "blender"],
     ["blender protocol", "--data"]),
    # ---- clrf process
    ("process-text-as-mp4", process(text_as_mp4), ["clip.mp4", "cannot read the video"]),
    ("process-empty-folder", process(photos(0)), ["photos", "holds 0 images", "at least 3"]),
    ("process-two-photos", process(photos(2)), ["photos", "holds 2 images", "at least 3"]),
    # ---- hash settings
    ("hash-levels-1000", opts("--model", "hash", "--set", "hash.levels=1000"),
     ["hash.levels = 1000", "1..64"]),
    ("hash-table-2-to-the-64", opts("--model", "hash", "--set", "hash.log2_table=64"),
     ["hash.log2_table = 64", "1..24"]),
    ("hash-samples-zero", opts("--model", "hash", "--set", "hash.samples=0"),
     ["hash.samples = 0", "1..4096"]),
    ("hash-resolution-inverted", opts("--model", "hash", "--set", "hash.min_res=512", "--set",
                                      "hash.max_res=16"), ["hash.min_res"]),
    # ---- the viewer's flags (clrf view, clrf train --view)
    ("view-port-70000", view("--port", "70000"), ["--port 70000", "0..65535"]),
    ("view-port-negative", view("--port", "-1"), ["--port -1", "0..65535"]),
    ("view-host-empty", view("--host", ""), ["--host ''", "address"]),
    ("view-host-url", view("--host", "http://example.org"), ["--host 'http://example.org'"]),
    ("view-host-unresolvable", view("--host", "no-such-host.invalid"),
     ["cannot listen on no-such-host.invalid", "--host"]),
    ("view-no-token-off-loopback", view("--host", "0.0.0.0", "--no-token"),
     ["--no-token", "loopback"]),
    ("view-token-short", view("--token", "abc"), ["--token", "at least 22 characters"]),
    ("view-token-bad-characters", view("--token", "a" * 30 + "!"), ["--token", "A-Z"]),
    ("view-token-and-no-token", view("--token", "a" * 30, "--no-token"),
     ["--no-token and --token"]),
    ("view-max-clients-zero", view("--max-clients", "0"), ["--max-clients 0", "1..64"]),
    ("view-max-fps-nan", view("--max-fps", "nan"), ["--max-fps nan", "(0, 240]"]),
    ("view-exit-after-negative", view("--exit-after", "-5"), ["--exit-after -5.0", ">= 0"]),
    ("view-allow-host-path", view("--allow-host", "a/b"), ["--allow-host 'a/b'"]),
    ("train-view-port-70000", opts("--view", "--port", "70000"), ["--port 70000", "0..65535"]),
    ("train-view-share-zero", opts("--view", "--view-share", "0"),
     ["--view-share 0.0", "(0, 1]"]),
    ("train-view-no-token-off-loopback", opts("--view", "--host", "::", "--no-token"),
     ["--no-token", "loopback"]),
]


def _files(root: Path) -> set:
    return {p.relative_to(root) for p in root.rglob("*")}


@pytest.mark.parametrize("build,needles", [c[1:] for c in CASES], ids=[c[0] for c in CASES])
def test_bad_input(tmp_path, capsys, build, needles):
    args = [str(tmp_path / "out") if a == "OUT" else a for a in build(tmp_path)]
    if args[0] == "process" and importlib.util.find_spec("pycolmap") is None:
        pytest.skip("clrf process needs pycolmap (the 'process' extra: `bash tools/setup.sh "
                    "process`), which is not installed here")
    before = _files(tmp_path)
    capsys.readouterr()
    rc = cli(args)
    cap = capsys.readouterr()
    err = cap.err
    assert rc == 2, err
    assert err.count("clrf: error:") == 1 and err.startswith("clrf: error:"), err
    assert "Traceback" not in err + cap.out, err
    for n in needles:
        assert n in err, f"{n!r} not in {err!r}"
    assert any(w in err.lower() for w in FIX_WORDS), f"no fix in {err!r}"
    assert _files(tmp_path) == before, "a command that failed must not write anything"


def test_corpus_is_large_and_unique():
    ids = [c[0] for c in CASES]
    assert len(ids) >= 40 and len(set(ids)) == len(ids)


def test_unknown_flag_exits_2(capsys):
    with pytest.raises(SystemExit) as e:           # argparse: usage and exit 2
        cli(["train", "--no-such-flag"])
    assert e.value.code == 2
    assert "unrecognized arguments: --no-such-flag" in capsys.readouterr().err


@pytest.mark.parametrize("name", ["blender-decompression-bomb", "memory-too-large",
                                  "resume-corrupt-checkpoint", "view-port-70000"])
def test_bad_input_in_a_real_process(tmp_path, name):
    """A few rows again as `python -m clrf.cli`: the exit status and stderr of a real process."""
    build, needles = next(c[1:] for c in CASES if c[0] == name)
    args = [str(tmp_path / "out") if a == "OUT" else a for a in build(tmp_path)]
    before = _files(tmp_path)
    env = dict(os.environ)   # the installed clrf (tests/conftest.py)
    p = subprocess.run([sys.executable, "-m", "clrf.cli", *args], env=env, capture_output=True,
                       text=True, timeout=120)
    assert p.returncode == 2, p.stderr
    assert p.stderr.count("clrf: error:") == 1 and "Traceback" not in p.stderr, p.stderr
    assert all(n in p.stderr for n in needles), p.stderr
    assert _files(tmp_path) == before
