"""Rays from posed pinhole cameras, NDC for forward-facing scenes, and render paths.

Conventions (the same as :class:`clrf.data.Dataset`): poses are camera-to-world 4x4 matrices in
OpenGL/Blender camera axes (x right, y up, the camera looks down -z); ``intrinsics`` is
(fx, fy, cx, cy) in pixels with the image origin at the top-left corner of the top-left pixel,
so the centre of pixel (row v, column u) is at (u + 0.5, v + 0.5). Lens distortion is a
:class:`clrf.data.camera_models.Distortion` (radial-tangential or fisheye; a plain (k1, k2, p1, p2)
is OpenCV's radial-tangential), applied in OpenCV normalised coordinates (y down).

Everything is vectorised numpy; nothing loops over pixels in Python.
"""
from __future__ import annotations

import numpy as np

from .camera_models import Distortion, as_distortion, distort, undistort  # noqa: F401

PIXEL_CENTER = 0.5        # offset from a pixel's corner to its centre, in pixels


def _as_intrinsics(intrinsics) -> np.ndarray:
    k = np.asarray(intrinsics, np.float64).reshape(-1)
    if k.shape != (4,):
        raise ValueError(f"intrinsics: expected (fx, fy, cx, cy), got shape {np.shape(intrinsics)}")
    if not (k[0] > 0 and k[1] > 0):
        raise ValueError(f"intrinsics: focal lengths must be positive, got fx={k[0]}, fy={k[1]}")
    return k


def _as_poses(poses) -> np.ndarray:
    p = np.asarray(poses, np.float64)
    if p.ndim == 2:
        p = p[None]
    if p.ndim != 3 or p.shape[1:] not in ((4, 4), (3, 4)):
        raise ValueError(f"poses: expected [N, 4, 4] or [N, 3, 4], got shape {np.shape(poses)}")
    return p


def camera_dirs(intrinsics, H: int, W: int, distortion=None) -> np.ndarray:
    """Per-pixel ray directions in camera (OpenGL) axes, [H, W, 3], with z = -1 (not unit length).

    Pixel (v, u) centre -> ((u + 0.5 - cx) / fx, -(v + 0.5 - cy) / fy, -1), after undistorting the
    normalised coordinates when ``distortion`` is given.
    """
    u = np.arange(W, dtype=np.float64) + PIXEL_CENTER
    v = np.arange(H, dtype=np.float64) + PIXEL_CENTER
    uu, vv = np.meshgrid(u, v, indexing="xy")                     # [H, W]
    return _pixel_dirs(uu, vv, intrinsics, distortion)


def _pixel_dirs(u, v, intrinsics, distortion=None) -> np.ndarray:
    """Camera-axes directions (z = -1) through image points (u, v) (pixels, any shape)."""
    fx, fy, cx, cy = _as_intrinsics(intrinsics)
    xy = np.stack([(u - cx) / fx, (v - cy) / fy], axis=-1)        # OpenCV normalised, y down
    xy = undistort(xy, distortion)                                # a copy when None
    return np.stack([xy[..., 0], -xy[..., 1], -np.ones_like(u)], axis=-1)


def pixel_rays(poses, intrinsics, H: int, W: int, distortion=None, normalize: bool = False):
    """Rays through every pixel centre of every camera.

    poses: [N, 4, 4] (or [N, 3, 4], or one [4, 4]) camera-to-world, OpenGL axes.
    intrinsics: (fx, fy, cx, cy). distortion: None, a Distortion or OpenCV (k1, k2, p1, p2).
    Returns origins, dirs: float32 [N*H*W, 3], ordered image, row, column. Directions have
    camera-space z = -1 (the NeRF convention, which :func:`to_ndc` expects) unless ``normalize``.

    Example: pose = identity, intrinsics (1, 1, 0.5, 0.5), H = W = 1 -> dirs [[0, 0, -1]].
    """
    p = _as_poses(poses)
    return _posed(p, camera_dirs(intrinsics, H, W, distortion).reshape(-1, 3), normalize)


def _posed(p, d_cam, normalize: bool = False):
    """(origins, dirs) float32 of camera-space directions d_cam [P, 3] under poses p [N, 3|4,
    4] (float64)."""
    dirs = np.einsum("nij,pj->npi", p[:, :3, :3], d_cam).reshape(-1, 3)      # R @ d per camera
    if normalize:
        dirs /= np.linalg.norm(dirs, axis=-1, keepdims=True)
    origins = np.repeat(p[:, :3, 3], len(d_cam), axis=0)
    return origins.astype(np.float32), dirs.astype(np.float32)


def to_ndc(origins, dirs, intrinsics, H: int, W: int, near: float = 1.0):
    """The NeRF normalised-device-coordinate transform for forward-facing scenes.

    Origins are first moved onto the plane z = -near; then, with ax = -2 fx / W, ay = -2 fy / H::

        o' = (ax ox / oz, ay oy / oz, 1 + 2 near / oz)
        d' = (ax (dx / dz - ox / oz), ay (dy / dz - oy / oz), -2 near / oz)

    so the camera frustum maps to [-1, 1]^3, the near plane to z' = -1 and infinity to z' = 1,
    and a ray is o' + t d' with t in [0, 1]. Like NeRF this assumes the principal point at the
    image centre (cx, cy are not used). Returns float32 arrays of the input shapes.
    """
    fx, fy, _, _ = _as_intrinsics(intrinsics)
    o = np.asarray(origins, np.float64)
    d = np.asarray(dirs, np.float64)
    t = -(near + o[..., 2]) / d[..., 2]
    o = o + t[..., None] * d
    ax, ay = -2.0 * fx / W, -2.0 * fy / H
    oz = o[..., 2]
    o_ndc = np.stack([ax * o[..., 0] / oz, ay * o[..., 1] / oz, 1.0 + 2.0 * near / oz], -1)
    d_ndc = np.stack([ax * (d[..., 0] / d[..., 2] - o[..., 0] / oz),
                      ay * (d[..., 1] / d[..., 2] - o[..., 1] / oz),
                      -2.0 * near / oz], -1)
    return o_ndc.astype(np.float32), d_ndc.astype(np.float32)


def ndc_extent(poses, intrinsics, H: int, W: int, distortion=None, near: float = 1.0):
    """(max |x|, max |y|) of every view's rays in NDC, from the near plane (t = 0) to infinity
    (t = 1): the half-widths of the NDC box that holds each camera's whole frustum.

    The NDC cube [-1, 1]^3 holds only the frustum of the reference (average) camera; a camera
    turned or moved from it sees beyond x, y = +-1 (on fern ~15 % of the training rays start
    outside the cube). NDC maps lines to lines, so the extremes lie on the image border:
    only rays through the border pixels' outer edges are traced.
    """
    u = np.concatenate([np.arange(W + 1.0), np.zeros(H + 1), np.arange(W + 1.0),
                        np.full(H + 1, float(W))])
    v = np.concatenate([np.zeros(W + 1), np.arange(H + 1.0), np.full(W + 1, float(H)),
                        np.arange(H + 1.0)])
    d_cam = _pixel_dirs(u, v, intrinsics, distortion)
    p = _as_poses(poses)
    dirs = np.einsum("nij,pj->npi", p[:, :3, :3], d_cam).reshape(-1, 3)
    origins = np.repeat(p[:, :3, 3], len(u), axis=0)
    o, d = to_ndc(origins, dirs, intrinsics, H, W, near)
    ends = np.concatenate([o, o + d]).astype(np.float64)
    return float(np.abs(ends[:, 0]).max()), float(np.abs(ends[:, 1]).max())


def _normalize(v):
    return v / np.linalg.norm(v, axis=-1, keepdims=True)


def look_at(eye, target, up=(0.0, 0.0, 1.0)) -> np.ndarray:
    """Camera-to-world [..., 4, 4] for cameras at ``eye`` looking at ``target`` (OpenGL axes).

    The camera's -z points at the target, its y is as close to ``up`` as possible.
    """
    eye = np.asarray(eye, np.float64)
    target = np.broadcast_to(np.asarray(target, np.float64), eye.shape)
    up = np.broadcast_to(np.asarray(up, np.float64), eye.shape)
    z = _normalize(eye - target)                    # camera looks down -z
    x = _normalize(np.cross(up, z))
    y = np.cross(z, x)
    m = np.zeros(eye.shape[:-1] + (4, 4))
    m[..., :3, 0], m[..., :3, 1], m[..., :3, 2], m[..., :3, 3] = x, y, z, eye
    m[..., 3, 3] = 1.0
    return m


def orbit_poses(n: int, radius: float = 4.0, elevation_deg: float = 30.0, center=(0.0, 0.0, 0.0),
                start_deg: float = 0.0) -> np.ndarray:
    """``n`` cameras evenly spaced in azimuth on a circle around ``center`` (world z up).

    Camera i sits at azimuth start_deg + 360 i / n, ``elevation_deg`` above the xy-plane through
    the centre, ``radius`` from it, looking at the centre. Returns float64 [n, 4, 4].
    """
    az = np.deg2rad(start_deg + 360.0 * np.arange(n) / n)
    el = np.deg2rad(elevation_deg)
    c = np.asarray(center, np.float64)
    eye = c + radius * np.stack([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az),
                                 np.full_like(az, np.sin(el))], -1)
    return look_at(eye, c)


def camera_orbit_poses(poses, n: int, center) -> np.ndarray:
    """``n`` cameras on the circle the capture's own cameras lie near, looking at ``center``: the
    up axis is the cameras' mean y axis, the circle sits at their median height along it and
    their median distance from that axis (a 360 capture walked around a scene at eye level).
    Returns float64 [n, 4, 4]."""
    p = _as_poses(poses)
    c = np.asarray(center, np.float64)
    up = _normalize(p[:, :3, 1].sum(0))
    rel = p[:, :3, 3] - c
    h = rel @ up
    radius = float(np.median(np.linalg.norm(rel - h[:, None] * up, axis=-1)))
    e1 = _normalize(np.cross(up, [1.0, 0.0, 0.0] if abs(up[0]) < 0.9 else [0.0, 1.0, 0.0]))
    e2 = np.cross(up, e1)
    az = 2.0 * np.pi * np.arange(n) / n
    eye = c + np.median(h) * up + radius * (np.cos(az)[:, None] * e1 + np.sin(az)[:, None] * e2)
    return look_at(eye, c, up)


def average_pose(poses) -> np.ndarray:
    """The LLFF "average" camera: mean position, summed viewing axis and up vector, [4, 4]."""
    p = _as_poses(poses)
    center = p[:, :3, 3].mean(0)
    z = _normalize(p[:, :3, 2].sum(0))
    up = p[:, :3, 1].sum(0)
    x = _normalize(np.cross(up, z))
    y = np.cross(z, x)
    m = np.eye(4)
    m[:3, 0], m[:3, 1], m[:3, 2], m[:3, 3] = x, y, z, center
    return m


def spiral_poses(poses, n: int = 120, focus_depth: float = 5.0, rots: float = 2.0,
                 zrate: float = 0.5, radius_scale: float = 1.0, radii=None) -> np.ndarray:
    """A forward-facing spiral render path (as in NeRF's LLFF renders).

    The path circles the average camera of ``poses`` with radii (x, y, z) = the 90th percentile
    of the cameras' absolute offsets in the average camera's frame (or ``radii``), times
    ``radius_scale``; it makes ``rots`` turns, moving in depth at ``zrate`` times the angular
    rate, and every camera looks at the point ``focus_depth`` in front of the average camera.
    Returns float64 [n, 4, 4].
    """
    p = _as_poses(poses)
    c2w = average_pose(p)
    if radii is None:
        local = (p[:, :3, 3] - c2w[:3, 3]) @ c2w[:3, :3]             # offsets in the avg frame
        radii = np.percentile(np.abs(local), 90, axis=0)
    radii = np.asarray(radii, np.float64) * radius_scale
    theta = np.linspace(0.0, 2.0 * np.pi * rots, n, endpoint=False)
    local_eye = np.stack([np.cos(theta), -np.sin(theta), -np.sin(theta * zrate)], -1) * radii
    eye = local_eye @ c2w[:3, :3].T + c2w[:3, 3]
    target = c2w[:3, 3] - focus_depth * c2w[:3, 2]
    return look_at(eye, target, up=c2w[:3, 1])


NDC_REACH_RAYS = 1 << 20   # rays looked at by ndc_reach (whole views, downscaled to fit)


def ndc_reach(ds) -> float:
    """How far along a UNIT direction an NDC ray of dataset ``ds`` runs while its parameter
    goes over [ds.near, ds.far] (0 to 1: near plane to infinity): ds.far times the largest
    |d| of its rays (about 2; every view's, at most NDC_REACH_RAYS of them, plus 0.5 %, since
    the views are downscaled to fit). The ray samplers of the NeRF and hash models step along
    unit directions, so this is their far; a sample past z = 1 leaves the box and is dropped.
    Non-NDC datasets: ds.far."""
    if not ds.ndc or not len(ds.poses):
        return float(ds.far)
    H, W = ds.hw
    f = max(1, int(np.ceil(np.sqrt(len(ds.poses) * H * W / NDC_REACH_RAYS))))
    _, d = view_rays(ds, ds.poses, f)
    return float(ds.far) * float(np.linalg.norm(d.astype(np.float64), axis=1).max()) * 1.005


def view_rays(ds, poses, downscale=1):
    """Rays of whole views: numpy origins, dirs [len(poses)*h*w, 3] (NDC when the scene uses it).

    downscale f: the views at (H // f, W // f) with intrinsics / f, i.e. one ray per f x f block
    of pixels (the pixels ``downscale_image`` averages). Built one view at a time into the
    float32 arrays, so the float64 intermediates are one view's (not 48 bytes a ray of every
    view); the values are those of one call over all views."""
    H, W = ds.hw[0] // downscale, ds.hw[1] // downscale
    intr = np.asarray(ds.intrinsics, np.float64) / downscale
    p = _as_poses(poses)
    d_cam = camera_dirs(intr, H, W, ds.distortion).reshape(-1, 3)
    per = H * W
    o_all = np.empty((len(p) * per, 3), np.float32)
    d_all = np.empty((len(p) * per, 3), np.float32)
    for i in range(len(p)):
        o, d = _posed(p[i:i + 1], d_cam)
        if ds.ndc:
            o, d = to_ndc(o, d, intr, H, W)
        o_all[i * per:(i + 1) * per], d_all[i * per:(i + 1) * per] = o, d
    return o_all, d_all
