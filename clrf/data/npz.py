"""The "tiny NeRF" layout: one .npz with ``images`` [N, H, W, 3], ``poses`` [N, 4, 4], ``focal``.

Split rule (explicit, as the layout defines none): the LAST ``n_test`` images (default 6) are the
test split and all earlier ones are train. For tiny_lego (106 images) that is images 0-99 train
and 100-105 test, matching its source_frames.txt. Images are taken as already composited on
black (the layout's convention; pass ``background`` if a file differs); intrinsics are
(focal, focal, W/2, H/2); bbox, near and far are the Blender scene's ([-1.5, 1.5]^3, 2, 6).
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

from .base import Dataset, DataError
from .io import (check_downscale, check_finite, check_poses, check_splits, downscale_image,
                 limit_split, parse_background, require_file)

DEFAULT_N_TEST = 6


def find_npz(path: Path) -> Path:
    """``path`` itself if it is a file, else the single .npz inside the folder."""
    path = Path(path)
    if path.is_file():
        return path
    files = sorted(path.glob("*.npz"))
    if len(files) != 1:
        raise DataError(f"{path}: expected exactly one .npz file in the folder, found "
                        f"{len(files)}; pass the file path itself")
    return files[0]


def load_npz(path, n_test: int = DEFAULT_N_TEST, background="black", downscale=None,
             max_images=None) -> Dataset:
    """Load a tiny-NeRF .npz (file, or a folder holding exactly one).

    n_test: the last ``n_test`` images form the test split, the rest train.
    downscale: integer box-average factor. max_images: keep the first this-many of each split.
    """
    f = require_file(find_npz(path), "tiny-NeRF .npz file")
    factor = check_downscale(downscale)
    bg = parse_background(background)
    try:
        with np.load(f, allow_pickle=False) as z:
            missing = [k for k in ("images", "poses", "focal") if k not in z.files]
            if missing:
                raise DataError(f"{f}: required field '{missing[0]}' is missing (the file has "
                                f"{sorted(z.files)}); re-save it with np.savez(images=..., "
                                f"poses=..., focal=...)")
            images, poses, focal = z["images"], z["poses"], z["focal"]
    except DataError:
        raise
    except Exception as e:  # noqa: BLE001 - zip/pickle/format errors all mean "not an npz"
        raise DataError(f"{f}: unreadable .npz ({type(e).__name__}: {e}); re-save it with "
                        f"np.savez") from None

    if images.ndim != 4 or images.shape[-1] not in (3, 4) or images.shape[0] == 0:
        raise DataError(f"{f}: field 'images' must be [N, H, W, 3], got shape {images.shape}")
    if images.dtype == np.uint8:
        images = images.astype(np.float32) / 255.0
    elif images.dtype.kind == "f":
        images = images.astype(np.float32)
    else:
        raise DataError(f"{f}: field 'images' must be float or uint8, got {images.dtype}")
    check_finite(images, f, "images")
    n = images.shape[0]
    if poses.ndim != 3 or poses.shape[0] != n or poses.shape[1:] not in ((4, 4), (3, 4)):
        raise DataError(f"{f}: field 'poses' must be [N, 4, 4] with N = {n} (one per image), "
                        f"got shape {poses.shape}")
    poses = poses.astype(np.float64)
    if poses.shape[1] == 3:
        bottom = np.broadcast_to([0.0, 0.0, 0.0, 1.0], (n, 1, 4))
        poses = np.concatenate([poses, bottom], 1)
    check_poses(poses, f, "poses[{}]")
    if np.size(focal) != 1 or not np.isfinite(focal).all() or float(np.ravel(focal)[0]) <= 0:
        raise DataError(f"{f}: field 'focal' must be one positive number (pixels), got {focal!r}")
    focal = float(np.ravel(focal)[0])

    if not 0 < n_test < n:
        raise DataError(f"{f}: split 'train' or 'test' would be empty: {n} images with "
                        f"n_test={n_test}; pass 0 < n_test < {n}")
    split = {"train": np.arange(n - n_test), "test": np.arange(n - n_test, n)}
    keep, split = limit_split(split, max_images)
    check_splits(split, f, "pass max_images >= 1")
    imgs = images[keep]
    if imgs.shape[-1] == 4:
        imgs = imgs[..., :3] * imgs[..., 3:] + np.asarray(bg, np.float32) * (1 - imgs[..., 3:])
    if factor > 1:
        imgs = np.stack([downscale_image(a, factor) for a in imgs])
    H, W = imgs.shape[1:3]
    f_px = focal / factor
    return Dataset(name=f.stem, images=np.ascontiguousarray(imgs, np.float32),
                   poses=poses[keep].astype(np.float32),
                   intrinsics=np.array([f_px, f_px, W / 2.0, H / 2.0]), split=split,
                   background=bg, bbox=np.array([[-1.5] * 3, [1.5] * 3]), near=2.0, far=6.0,
                   ndc=False, preset="tiny")
