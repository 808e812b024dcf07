"""One camera -> one image: the render path shared by ``clrf render`` and the viewer.

A :class:`ViewSpec` holds what :func:`clrf.data.cameras.view_rays` needs of a dataset (image size,
pinhole intrinsics, distortion, whether the scene is in NDC). ``clrf render`` builds it from
the checkpoint's dataset metadata (:func:`spec_from_meta`); the viewer and camera-path files
give a vertical field of view instead (:func:`spec_from_fov`). Either way :func:`render_pose`
makes the rays with ``view_rays`` and renders them with ``model.render`` (the same OpenCL
kernels as evaluation), so a frame the viewer shows and a frame ``clrf render`` writes for the
same camera come from identical rays.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Optional, Tuple

import numpy as np

from ..data.cameras import as_distortion

MAX_SIDE = 4096   # largest image side a camera may ask for (a 4096^2 frame is 16.8 M rays)


@dataclass
class ViewSpec:
    """hw = (H, W); intrinsics = (fx, fy, cx, cy) px; distortion None or a
    clrf.data.camera_models.Distortion (clrf.data.cameras.as_distortion).

    ndc_frame: for a camera other than the training camera of an NDC scene, the training
    camera's (intrinsics, H, W): the NDC map (x' = -2 fx / W * x / z, ...) is the model's
    coordinate system, fixed by the camera it was trained with, not by the viewing camera."""
    hw: Tuple[int, int]
    intrinsics: np.ndarray
    distortion: Optional[object] = None
    ndc: bool = False
    ndc_frame: Optional[tuple] = None


def spec_from_meta(meta, scale: float = 1.0) -> ViewSpec:
    """The training camera of a checkpoint's ``dataset`` metadata, at ``scale`` times its
    resolution with the same field of view (intrinsics scaled by W'/W, H'/H)."""
    H0, W0 = int(meta["H"]), int(meta["W"])
    H, W = (H0, W0) if scale == 1 else (max(1, round(H0 * scale)), max(1, round(W0 * scale)))
    sx, sy = W / W0, H / H0
    return ViewSpec((H, W), np.asarray(meta["intrinsics"], np.float64) * [sx, sy, sx, sy],
                    as_distortion(meta.get("distortion")), bool(meta["ndc"]))


def focal_from_fov(fov_y_deg: float, height: int) -> float:
    """Focal length in pixels of a pinhole camera with vertical field of view ``fov_y_deg``:
    f = (H / 2) / tan(fov / 2) (three.js's and nerfstudio's convention)."""
    return 0.5 * height / math.tan(math.radians(fov_y_deg) / 2)


def spec_from_fov(fov_y_deg: float, width: int, height: int, meta=None) -> ViewSpec:
    """An undistorted pinhole camera of W x H pixels, square pixels, principal point at the
    centre, vertical field of view ``fov_y_deg`` degrees in (0, 180). ``meta``: the checkpoint's
    dataset metadata; in an NDC scene its training camera fixes the NDC map (ndc_frame)."""
    if not (math.isfinite(fov_y_deg) and 0 < fov_y_deg < 180):
        raise ValueError(f"fov: must be a vertical field of view in (0, 180) degrees, got "
                         f"{fov_y_deg}")
    if not (1 <= int(width) <= MAX_SIDE and 1 <= int(height) <= MAX_SIDE):
        raise ValueError(f"image size {width}x{height}: each side must be in 1..{MAX_SIDE}")
    f = focal_from_fov(fov_y_deg, int(height))
    ndc = bool(meta is not None and meta.get("ndc"))
    frame = ((np.asarray(meta["intrinsics"], np.float64), int(meta["H"]), int(meta["W"]))
             if ndc else None)
    return ViewSpec((int(height), int(width)),
                    np.array([f, f, 0.5 * int(width), 0.5 * int(height)]), None, ndc, frame)


def check_pose(pose) -> np.ndarray:
    """A camera-to-world matrix as float64 [4, 4]; raises ValueError naming the problem for a
    wrong shape, non-finite values or a rotation part that is not a rotation (|R^T R - I| >
    1e-3: a scaled or sheared matrix would change the rays' lengths and so the render)."""
    p = np.asarray(pose, np.float64)
    if p.shape == (16,):
        p = p.reshape(4, 4)
    if p.shape == (3, 4):
        p = np.vstack([p, [0, 0, 0, 1]])
    if p.shape != (4, 4):
        raise ValueError(f"camera_to_world: expected 16 numbers (a 4x4 matrix, rows first), got "
                         f"shape {p.shape}")
    if not np.all(np.isfinite(p)):
        raise ValueError("camera_to_world: holds NaN or infinite values; replace it with a finite "
                         "camera-to-world matrix")
    r = p[:3, :3]
    if np.abs(r.T @ r - np.eye(3)).max() > 1e-3:
        raise ValueError("camera_to_world: the upper-left 3x3 block is not a rotation "
                         "(columns must be orthonormal)")
    return p


def frame_rays(spec: ViewSpec, pose):
    """Rays of every pixel of one camera, float32 [H*W, 3] origins and directions, rows first:
    ``view_rays`` (as evaluation), or for a viewing camera of an NDC scene the world rays of
    that camera through the training camera's NDC map (``spec.ndc_frame``)."""
    from ..data.cameras import pixel_rays, to_ndc, view_rays
    if spec.ndc and spec.ndc_frame is not None:
        H, W = spec.hw
        o, d = pixel_rays(check_pose(pose)[None], spec.intrinsics, H, W, spec.distortion)
        k, nh, nw = spec.ndc_frame
        return to_ndc(o, d, k, nh, nw)
    return view_rays(spec, check_pose(pose)[None])


def render_pose(model, spec: ViewSpec, pose, near: float = 0.0, depth: bool = True) -> dict:
    """Render one camera: rgb [H, W, 3], depth [H, W], acc [H, W] float32 numpy (a model that
    renders whole cameras leaves the depth out unless ``depth``).

    near > 0 moves every ray's origin ``near`` along its direction first (direction z = -1 in
    camera axes, so near is a distance along the viewing axis): matter closer to the camera than
    that is cut away. Ignored in NDC scenes (their rays start on the near plane already)."""
    from ..interface import render_view

    def rays():
        o, d = frame_rays(spec, pose)
        if near > 0 and not spec.ndc:
            o = (o + np.float32(near) * d).astype(np.float32)
        return o, d
    return render_view(model, np.asarray(pose, np.float64), spec.intrinsics, spec.hw, rays,
                       depth)


def to_uint8(img) -> np.ndarray:
    """[0, 1] float image -> uint8 with round-half-up (x * 255 + 0.5, clipped first)."""
    return (np.clip(img, 0, 1) * 255 + 0.5).astype(np.uint8)
