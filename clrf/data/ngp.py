"""instant-ngp's ``transforms.json`` (a user's own capture, e.g. from colmap2nerf.py).

Fields: fl_x, fl_y (or camera_angle_x / camera_angle_y), cx, cy (default: image centre), w, h
(default: the images' size), camera_model with its distortion fields (below; kept in
``Dataset.distortion``, None without distortion), aabb_scale (default 1), optional scale (default
0.33) and offset (default [0.5, 0.5, 0.5]) of instant-ngp's world -> unit-cube map, and
``frames`` with file_path (relative to the JSON's folder) and a 4x4 camera-to-world
transform_matrix in OpenGL axes (instant-ngp's "NeRF" convention, used as is).

Frames whose image file is missing are skipped with one warning (fox lists 67 frames, 50
exist). No split is stored in the file, so every ``holdout``-th kept frame (0, 8, ...) is test.
bbox: instant-ngp's scene box -- the cube of side aabb_scale centred at 0.5 in its unit-cube
space, mapped back to world: x_world = (x_ngp - offset) / scale (ngp permutes axes x,y,z <-
y,z,x, which only matters for a non-uniform offset).

camera_model (COLMAP's names, as nerfstudio writes them; the equations are in
``clrf.data.camera_models``) and the distortion fields each reads (missing fields are 0):
PINHOLE and SIMPLE_PINHOLE none; SIMPLE_RADIAL k1; RADIAL k1, k2; OPENCV k1, k2, p1, p2 and
k3 (OpenCV's r^6 term); OPENCV_FISHEYE k1, k2, k3, k4. Without camera_model it is OPENCV, or
OPENCV_FISHEYE when instant-ngp's ``is_fisheye`` is true. Any other model, or a non-zero
distortion field the model does not read, is an error rather than a guess.
"""
from __future__ import annotations

import numpy as np

from .camera_models import FAMILIES, Distortion, as_distortion, check_camera
from .base import Dataset, DataError
from .io import (as_matrix, as_number, check_downscale, check_poses, check_splits, get_field,
                 holdout_split, inside, limit_split, load_images, parse_background, read_json,
                 require_dir, warn)

NGP_SCALE = 0.33          # instant-ngp's default world -> unit cube scale
NGP_OFFSET = 0.5          # ... and offset (the unit cube's centre)
NEAR = 0.1                # world units; instant-ngp's default near distance is of this order
ASPECT_TOL = 0.02
MAX_LISTED = 5            # missing file names shown in the warning
# camera_model -> (distortion family, the fields it reads in that family's argument names)
NGP_MODELS = {"PINHOLE": ("radtan", ()), "SIMPLE_PINHOLE": ("radtan", ()),
              "SIMPLE_RADIAL": ("radtan", ("k1",)), "RADIAL": ("radtan", ("k1", "k2")),
              "OPENCV": ("radtan", ("k1", "k2", "p1", "p2", "k3")),
              "OPENCV_FISHEYE": ("fisheye", ("k1", "k2", "k3", "k4"))}
DIST_FIELDS = ("k1", "k2", "k3", "k4", "p1", "p2")


def _num(meta, key, path, default=None):
    if key not in meta:
        return default
    return as_number(meta[key], path, key)


def _fov_focal(angle, size, path, name) -> float:
    """Focal length in pixels of a field of view ``angle`` (radians) over ``size`` pixels."""
    if not 0.0 < angle < np.pi:
        raise DataError(f"{path}: field '{name}' must be in (0, pi) radians, got {angle}; fix it "
                        f"(or give the focal length in pixels)")
    return 0.5 * size / np.tan(0.5 * angle)


def _lens(meta, path):
    """The Distortion (or None) of camera_model / is_fisheye and the k*, p* fields."""
    fisheye = meta.get("is_fisheye", False)
    if not isinstance(fisheye, bool):
        raise DataError(f"{path}: field 'is_fisheye' must be true or false, got {fisheye!r}")
    model = meta.get("camera_model", "OPENCV_FISHEYE" if fisheye else "OPENCV")
    if not isinstance(model, str) or model not in NGP_MODELS:
        raise DataError(f"{path}: field 'camera_model' is {model!r}, which clrf does not "
                        f"support (supported: {', '.join(NGP_MODELS)}); undistort the images "
                        f"to PINHOLE (e.g. `colmap image_undistorter`) and use camera_model "
                        f"PINHOLE")
    if fisheye and model != "OPENCV_FISHEYE":
        raise DataError(f"{path}: fields 'is_fisheye' (true) and 'camera_model' ({model}) "
                        f"disagree; remove one of them")
    family, reads = NGP_MODELS[model]
    k = {f: _num(meta, f, path, 0.0) for f in DIST_FIELDS}
    stray = [f"{f} = {v:g}" for f, v in k.items() if v != 0 and f not in reads]
    if stray:
        raise DataError(f"{path}: field(s) {', '.join(stray)} are not part of camera_model "
                        f"{model} (it reads {', '.join(reads) or 'no distortion fields'}); "
                        f"remove them or set the camera_model they belong to")
    if model in ("SIMPLE_PINHOLE", "SIMPLE_RADIAL", "RADIAL"):
        fx, fy = _num(meta, "fl_x", path), _num(meta, "fl_y", path)
        if fx is not None and fy is not None and fx != fy:
            raise DataError(f"{path}: camera_model {model} has one focal length but 'fl_x' "
                            f"({fx:g}) and 'fl_y' ({fy:g}) differ; use PINHOLE/OPENCV or make "
                            f"them equal")
    return as_distortion(Distortion(family, tuple(k[f] if f in reads else 0.0
                                                  for f in FAMILIES[family])))


def load_ngp(path, downscale=None, holdout=8, max_images=None, background="white") -> Dataset:
    """Load an instant-ngp scene folder (transforms.json + images).

    downscale: integer box-average factor (intrinsics scale with it). holdout: every
    holdout-th present frame is test. max_images: first this-many frames of each split.
    background: used to composite RGBA images.
    """
    root = require_dir(path, "instant-ngp scene", "pass the folder holding transforms.json")
    jpath = root / "transforms.json"
    meta = read_json(jpath)
    factor = check_downscale(downscale)
    bg = parse_background(background)
    frames = get_field(meta, "frames", jpath, kind=list)
    dist = _lens(meta, jpath)

    files, poses, missing = [], [], []
    for i, fr in enumerate(frames):
        where = f"frames[{i}]"
        fp = get_field(fr, "file_path", jpath, where, kind=str)
        m = as_matrix(get_field(fr, "transform_matrix", jpath, where), jpath,
                      f"{where}.transform_matrix")
        check_poses(m[None], jpath, f"{where}.transform_matrix")
        for key in ("fl_x", "fl_y", "cx", "cy", "camera_model", "is_fisheye") + DIST_FIELDS:
            if key in fr and fr[key] != meta.get(key):
                raise DataError(f"{jpath}: {where}.{key} is set per frame (and differs from the "
                                f"top-level '{key}'); clrf supports one camera per scene: put "
                                f"'{key}' at the top level only")
        f = inside(root, fp, jpath, f"{where}.file_path")
        if not f.is_file():
            missing.append(fp)
            continue
        files.append(f)
        poses.append(m)
    if missing:
        shown = ", ".join(missing[:MAX_LISTED]) + (", ..." if len(missing) > MAX_LISTED else "")
        warn(f"{jpath}: skipping {len(missing)} of {len(frames)} frames whose image is missing "
             f"({shown})")
    if not files:
        raise DataError(f"{jpath}: none of the {len(frames)} frames has an existing image file; "
                        f"check the file_path entries and the images folder")

    split = holdout_split(len(files), holdout)
    check_splits(split, jpath, f"use a holdout between 2 and {len(files)} (there are "
                               f"{len(files)} usable frames)")
    keep, split = limit_split(split, max_images)
    check_splits(split, jpath, "pass max_images >= 1")
    images, alpha, (H0, W0) = load_images([files[i] for i in keep], downscale=factor,
                                          background=bg)

    w = _num(meta, "w", jpath, float(W0))
    h = _num(meta, "h", jpath, float(H0))
    if abs((H0 / W0) / (h / w) - 1.0) > ASPECT_TOL:
        raise DataError(f"{jpath}: fields 'w', 'h' = {w:.0f}x{h:.0f} but the images are "
                        f"{W0}x{H0}; fix w/h or use the images the camera was calibrated on")
    fl_x = _num(meta, "fl_x", jpath)
    if fl_x is None:
        angle = _num(meta, "camera_angle_x", jpath)
        if angle is None:
            raise DataError(f"{jpath}: required field 'fl_x' (or 'camera_angle_x') is missing; "
                            f"add the focal length in pixels")
        fl_x = _fov_focal(angle, w, jpath, "camera_angle_x")
    fl_y = _num(meta, "fl_y", jpath)
    if fl_y is None:
        angle_y = _num(meta, "camera_angle_y", jpath)
        fl_y = fl_x if angle_y is None else _fov_focal(angle_y, h, jpath, "camera_angle_y")
    cx, cy = _num(meta, "cx", jpath, w / 2.0), _num(meta, "cy", jpath, h / 2.0)
    if not all(np.isfinite(v) and v > 0 for v in (w, h, fl_x, fl_y)):
        raise DataError(f"{jpath}: focal lengths and image size must be positive (fl_x {fl_x:g}, "
                        f"fl_y {fl_y:g}, w {w:g}, h {h:g}); fix the calibration fields")
    s = W0 / w / factor                                        # file intrinsics -> loaded pixels
    intr = np.array([fl_x * s, fl_y * s, cx * s, cy * s])
    bad = check_camera(dist, intr, *images.shape[1:3])
    if bad:
        raise DataError(f"{jpath}: the distortion fields of camera_model "
                        f"{meta.get('camera_model', 'OPENCV')} are not a usable lens: {bad}; "
                        f"check k1..k4, p1, p2 or undistort the images")

    aabb = _num(meta, "aabb_scale", jpath, 1.0)
    scale = _num(meta, "scale", jpath, NGP_SCALE)
    off = np.asarray(meta.get("offset", [NGP_OFFSET] * 3), np.float64).reshape(-1)
    if off.shape != (3,) or not np.all(np.isfinite(off)) or aabb <= 0 or scale <= 0:
        raise DataError(f"{jpath}: fields 'aabb_scale', 'scale' must be positive and 'offset' "
                        f"three finite numbers")
    off_world = off[[2, 0, 1]]                                 # ngp axes are world (y, z, x)
    bbox = np.stack([(NGP_OFFSET - aabb / 2 - off_world) / scale,
                     (NGP_OFFSET + aabb / 2 - off_world) / scale])
    return Dataset(name=root.name, images=images, poses=np.stack(poses)[keep].astype(np.float32),
                   intrinsics=intr, split=split, background=bg, bbox=bbox, near=NEAR,
                   far=float(np.linalg.norm(bbox[1] - bbox[0])), ndc=False,
                   distortion=dist, preset="real360_box", alpha=alpha)
