"""A forward-facing capture with world-space cameras, for the models that need them.

Forward-facing captures (LLFF ``poses_bounds.npy``, COLMAP folders whose cameras all look one
way) load for the volumetric models with rays in NDC (clrf/data/llff.py: ``ndc`` True, a box
in NDC, near 0 and far 1 along the NDC rays). A model that projects points through the
cameras (Kind.world_cameras: the splat model) takes the same capture without NDC:

- poses, intrinsics and images unchanged (the recentred, rescaled frame of the loader; the
  NDC map is a change of the rays only, so nothing else moves);
- near, far: the smallest near and the largest far of the per-view depth bounds
  (``Dataset.depth_bounds``: LLFF's, in the poses' units; on fern at 1/8: 1.33 and 6.3);
- bbox: the box holding every view's frustum between its own bounds (``frustum_box``);
- background: the mean colour of the training images. The view is filled by the scene, so
  there is no backdrop to match; what no Gaussian covers (a frustum's edge the training views
  never saw) then shows the scene's average colour, not white or black.

The splat model draws its random first Gaussians in those frusta between the bounds
(clrf/splat/model.py ``frustum_means``).
"""
from __future__ import annotations

import dataclasses

import numpy as np

from .base import DataError
from .cameras import _pixel_dirs


def _bounds(ds) -> np.ndarray:
    b = getattr(ds, "depth_bounds", None)
    if b is None:
        raise DataError(f"dataset {ds.name}: a forward-facing scene without per-view depth bounds "
                        f"(poses_bounds.npy's last two columns, or the COLMAP points each image "
                        f"sees) has no world-space extent; regenerate poses_bounds.npy with "
                        f"LLFF's imgs2poses.py or pose the photos with `clrf process`")
    b = np.asarray(b, np.float64).reshape(-1, 2)
    if len(b) != len(ds.poses) or not np.all(np.isfinite(b)) or not np.all(b > 0) \
            or not np.all(b[:, 1] > b[:, 0]):
        raise DataError(f"dataset {ds.name}: its depth bounds must be finite, positive and near "
                        f"< far, one pair per view; regenerate poses_bounds.npy (LLFF's "
                        f"imgs2poses.py)")
    return b


def frustum_box(poses, intrinsics, hw, bounds) -> np.ndarray:
    """[2, 3] box holding every view's frustum between its (near, far) ``bounds`` [N, 2]
    (depths along the viewing axis): the image corners at both depths, per view.
    poses [N, 4, 4] camera-to-world (OpenGL axes), intrinsics (fx, fy, cx, cy), hw (H, W)."""
    H, W = (float(v) for v in hw)
    u = np.array([0.0, W, 0.0, W])
    v = np.array([0.0, 0.0, H, H])
    d_cam = _pixel_dirs(u, v, intrinsics)                              # [4, 3], z = -1
    p = np.asarray(poses, np.float64)
    d = np.einsum("nij,cj->nci", p[:, :3, :3], d_cam)                  # [N, 4, 3]
    b = np.asarray(bounds, np.float64)
    pts = p[:, None, None, :3, 3] + b[:, :, None, None] * d[:, None]   # [N, 2, 4, 3]
    pts = pts.reshape(-1, 3)
    return np.stack([pts.min(0), pts.max(0)])


def world_space(ds):
    """``ds`` with world-space cameras (see the module docstring); a dataset that is not in
    NDC comes back unchanged. DataError naming the fix when its depth bounds are missing or
    unusable."""
    if not ds.ndc:
        return ds
    b = _bounds(ds)
    train = np.asarray(ds.split.get("train", np.arange(len(ds.images))))
    background = ds.background
    if ds.alpha is None and len(train):   # RGBA captures keep what they were composited on
        means = [np.asarray(ds.images[v], np.float64).mean(axis=(0, 1)) for v in train]
        background = tuple(float(c) for c in np.mean(means, axis=0))   # one image at a time
    return dataclasses.replace(ds, ndc=False, near=float(b[:, 0].min()),
                               far=float(b[:, 1].max()),
                               bbox=frustum_box(ds.poses, ds.intrinsics, ds.hw, b),
                               background=background)


__all__ = ["world_space", "frustum_box"]
