"""NeRF's Blender synthetic layout: ``transforms_{train,val,test}.json`` + RGBA PNGs.

Each JSON holds ``camera_angle_x`` (horizontal field of view, radians) and ``frames``, each with
``file_path`` (relative to the folder, ".png" appended when it has no extension) and a 4x4
camera-to-world ``transform_matrix`` in OpenGL axes. Focal = 0.5 W / tan(0.5 camera_angle_x),
principal point at the image centre. RGBA is composited on white by default
(rgb * alpha + bg * (1 - alpha)). The scene fits in [-1.5, 1.5]^3; near 2, far 6.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

from .base import Dataset, DataError
from .io import (as_matrix, as_number, check_downscale, check_poses, check_splits, get_field,
                 inside, load_images, parse_background, read_json, require_dir)

SPLITS = ("train", "val", "test")


def load_blender(path, splits=SPLITS, background="white", downscale=None,
                 max_images=None) -> Dataset:
    """Load a Blender-layout scene folder.

    splits: which transforms_<split>.json to read (all must exist).
    background: "white", "black" or an RGB triple. downscale: integer box-average factor
    (applied to RGBA before compositing, as nerf-pytorch's half_res). max_images: keep the first
    this-many frames of each split (None: all).
    """
    root = require_dir(path, "Blender scene", "pass the folder holding transforms_train.json")
    factor = check_downscale(downscale)
    bg = parse_background(background)
    files, poses, split, angle, angle_src = [], [], {}, None, None
    for s in splits:
        jpath = root / f"transforms_{s}.json"
        meta = read_json(jpath)
        a = as_number(get_field(meta, "camera_angle_x", jpath), jpath, "camera_angle_x")
        if not 0.0 < a < np.pi:
            raise DataError(f"{jpath}: field 'camera_angle_x' must be in (0, pi) radians, got {a}")
        if angle is None:
            angle, angle_src = a, jpath
        elif abs(a - angle) > 1e-9 * max(1.0, abs(angle)):
            raise DataError(f"{jpath}: field 'camera_angle_x' = {a} differs from {angle} in "
                            f"{angle_src}; one scene must share one camera")
        frames = get_field(meta, "frames", jpath, kind=list)
        if max_images is not None:
            frames = frames[:max_images]
        start = len(files)
        for i, fr in enumerate(frames):
            where = f"frames[{i}]"
            fp = get_field(fr, "file_path", jpath, where, kind=str)
            m = as_matrix(get_field(fr, "transform_matrix", jpath, where), jpath,
                          f"{where}.transform_matrix")
            p = inside(root, fp if Path(fp).suffix else fp + ".png", jpath, f"{where}.file_path")
            files.append(p)
            poses.append(m)
        if len(frames):
            check_poses(np.stack(poses[start:]), jpath, "frames[{}].transform_matrix")
        split[s] = np.arange(start, len(files))
        check_splits({s: split[s]}, jpath, "add frames to it (or pass max_images >= 1)")

    images, alpha, (H0, W0) = load_images(files, downscale=factor, background=bg)
    focal = 0.5 * W0 / np.tan(0.5 * angle) / factor
    return Dataset(name=root.name, images=images, poses=np.stack(poses).astype(np.float32),
                   intrinsics=np.array([focal, focal, W0 / 2.0 / factor, H0 / 2.0 / factor]),
                   split=split,
                   background=bg, bbox=np.array([[-1.5] * 3, [1.5] * 3]), near=2.0, far=6.0,
                   ndc=False, preset="synthetic", alpha=alpha)
