"""Camera paths in nerfstudio's ``camera_path.json`` layout: read, write, interpolate.

The file (as nerfstudio's viewer saves it and ``ns-render camera-path`` reads it)::

    {"camera_type": "perspective", "render_height": H, "render_width": W,
     "fps": 24, "seconds": 4.0, "is_cycle": false, "smoothness_value": 0.0,
     "keyframes": [{"matrix": [16], "fov": deg, "aspect": W/H}, ...],
     "camera_path": [{"camera_to_world": [16], "fov": deg, "aspect": W/H}, ...]}

``camera_to_world`` (and a keyframe's ``matrix``; clrf also writes it as ``camera_to_world``)
is the 4x4 camera-to-world matrix flattened rows first, in OpenGL camera axes (x right, y up,
looking down -z: clrf's convention too); ``fov`` is the vertical field of view in degrees, so
the focal length is (H / 2) / tan(fov / 2). Rendering needs only ``camera_path``,
``render_height`` and ``render_width``; keyframes are kept so the viewer can load and edit a
path. nerfstudio's coordinates are its own scene's: a path made by nerfstudio for another
scene frames clrf's scene only if both use the same world frame.
"""
from __future__ import annotations

import json
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import List

import numpy as np

from ..runtime.atomicfile import write_text
from .frames import MAX_SIDE, check_pose


class CameraPathError(ValueError):
    pass


@dataclass
class CameraPath:
    """poses [N, 4, 4] float64, fovs [N] degrees; keyframes: list of (pose [4, 4], fov)."""
    poses: np.ndarray
    fovs: np.ndarray
    width: int
    height: int
    fps: float = 24.0
    keyframes: List[tuple] = field(default_factory=list)

    @property
    def seconds(self) -> float:
        return len(self.poses) / self.fps


def _slerp(q0, q1, t):
    """Spherical interpolation of unit quaternions (w, x, y, z), shortest arc."""
    d = float(np.dot(q0, q1))
    if d < 0:
        q1, d = -q1, -d
    if d > 0.9995:
        q = q0 + t * (q1 - q0)
        return q / np.linalg.norm(q)
    th = math.acos(d)
    return (math.sin((1 - t) * th) * q0 + math.sin(t * th) * q1) / math.sin(th)


def _quat(r):
    """Rotation matrix [3, 3] -> unit quaternion (w, x, y, z)."""
    w = math.sqrt(max(0.0, 1 + r[0, 0] + r[1, 1] + r[2, 2])) / 2
    x = math.copysign(math.sqrt(max(0.0, 1 + r[0, 0] - r[1, 1] - r[2, 2])) / 2, r[2, 1] - r[1, 2])
    y = math.copysign(math.sqrt(max(0.0, 1 - r[0, 0] + r[1, 1] - r[2, 2])) / 2, r[0, 2] - r[2, 0])
    z = math.copysign(math.sqrt(max(0.0, 1 - r[0, 0] - r[1, 1] + r[2, 2])) / 2, r[1, 0] - r[0, 1])
    q = np.array([w, x, y, z])
    return q / np.linalg.norm(q)


def _rot(q):
    w, x, y, z = q
    return np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
                     [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
                     [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)]])


def interpolate(keyframes, n: int) -> tuple:
    """``n`` cameras evenly spaced in time through ``keyframes`` [(pose [4, 4], fov)], each
    segment taking the same time: positions and fov linearly, rotations by slerp; a camera at a
    keyframe's time is that keyframe exactly. Returns (poses [n, 4, 4], fovs [n])."""
    if not keyframes:
        raise CameraPathError("camera path: no keyframes to interpolate")
    if len(keyframes) == 1 or n == 1:
        p, f = keyframes[0]
        return np.repeat(np.asarray(p, np.float64)[None], n, 0), np.full(n, float(f))
    segs = len(keyframes) - 1
    poses, fovs = [], []
    for s in np.linspace(0, segs, n):
        i = min(int(s), segs - 1)
        t = s - i
        (p0, f0), (p1, f1) = keyframes[i], keyframes[i + 1]
        p0, p1 = np.asarray(p0, np.float64), np.asarray(p1, np.float64)
        if t == 0 or t == 1:   # a keyframe's time: its own pose, bit for bit
            poses.append((p0 if t == 0 else p1).copy())
            fovs.append(float(f0 if t == 0 else f1))
            continue
        m = np.eye(4)
        m[:3, :3] = _rot(_slerp(_quat(p0[:3, :3]), _quat(p1[:3, :3]), t))
        m[:3, 3] = (1 - t) * p0[:3, 3] + t * p1[:3, 3]
        poses.append(m)
        fovs.append((1 - t) * f0 + t * f1)
    return np.stack(poses), np.asarray(fovs)


def to_dict(path: CameraPath) -> dict:
    def cam(p, f):
        return {"camera_to_world": [float(v) for v in np.asarray(p).reshape(-1)],
                "fov": float(f), "aspect": path.width / path.height}
    return {"camera_type": "perspective", "render_height": int(path.height),
            "render_width": int(path.width), "fps": float(path.fps), "seconds": path.seconds,
            "is_cycle": False, "smoothness_value": 0.0,
            "keyframes": [dict(cam(p, f), matrix=[float(v) for v in np.asarray(p).reshape(-1)])
                          for p, f in path.keyframes],
            "camera_path": [cam(p, f) for p, f in zip(path.poses, path.fovs)]}


def save(file, path: CameraPath):
    write_text(file, json.dumps(to_dict(path), indent=1))


def _need(d, key, where, kinds):
    if not isinstance(d, dict) or key not in d:
        raise CameraPathError(f"{where}: missing field '{key}'")
    v = d[key]
    if not isinstance(v, kinds) or isinstance(v, bool):
        raise CameraPathError(f"{where}: field '{key}' must be {kinds[0].__name__}, got "
                              f"{type(v).__name__}")
    return v


def _camera(c, where):
    m = _need(c, "camera_to_world", where, (list,))
    try:
        pose = check_pose(np.asarray(m, np.float64))
    except (ValueError, TypeError) as e:
        raise CameraPathError(f"{where}: field 'camera_to_world': {e}") from None
    fov = float(_need(c, "fov", where, (float, int)))
    if not (math.isfinite(fov) and 0 < fov < 180):
        raise CameraPathError(f"{where}: field 'fov' = {fov}: must be a vertical field of view "
                              f"in (0, 180) degrees")
    return pose, fov


def from_dict(d, name="camera path") -> CameraPath:
    """Parse the layout above; errors name the file, the entry and the field."""
    if not isinstance(d, dict):
        raise CameraPathError(f"{name}: expected a JSON object with 'camera_path', "
                              f"'render_height' and 'render_width'")
    ctype = d.get("camera_type", "perspective")
    if ctype != "perspective":
        raise CameraPathError(f"{name}: field 'camera_type' = {ctype!r}: clrf renders "
                              f"'perspective' cameras only")
    H = _need(d, "render_height", name, (int,))
    W = _need(d, "render_width", name, (int,))
    for k, v in (("render_height", H), ("render_width", W)):
        if not 1 <= v <= MAX_SIDE:
            raise CameraPathError(f"{name}: field '{k}' = {v}: must be in 1..{MAX_SIDE}")
    cams = _need(d, "camera_path", name, (list,))
    if not cams:
        raise CameraPathError(f"{name}: field 'camera_path' is empty: it must list the cameras "
                              f"to render")
    poses, fovs = zip(*[_camera(c, f"{name}: camera_path[{i}]") for i, c in enumerate(cams)])
    fps = d.get("fps", 24.0)
    if isinstance(fps, bool) or not isinstance(fps, (int, float)) or not 0 < fps <= 1000:
        raise CameraPathError(f"{name}: field 'fps' = {fps!r}: must be a number in (0, 1000]")
    keys = []
    for i, k in enumerate(d.get("keyframes") or []):
        where = f"{name}: keyframes[{i}]"
        if isinstance(k, dict) and "camera_to_world" not in k and "matrix" in k:
            m = k["matrix"]
            if isinstance(m, str):   # nerfstudio's first viewer: three.js elements, columns first
                try:
                    m = np.asarray(json.loads(m), np.float64).reshape(4, 4).T.reshape(-1).tolist()
                except (ValueError, TypeError):
                    raise CameraPathError(f"{where}: field 'matrix' is not 16 numbers") from None
            k = dict(k, camera_to_world=m)
        keys.append(_camera(k, where))
    return CameraPath(np.stack(poses), np.asarray(fovs, np.float64), W, H, float(fps), keys)


def load(file) -> CameraPath:
    file = Path(file)
    if not file.is_file():
        raise CameraPathError(f"camera path {file}: no such file; pass a camera_path.json saved "
                              f"by the viewer (or by nerfstudio)")
    try:
        d = json.loads(file.read_text())
    except (json.JSONDecodeError, UnicodeDecodeError) as e:
        raise CameraPathError(f"camera path {file}: not valid JSON ({e}); fix the file, or "
                              f"save the path again from `clrf view`") from None
    return from_dict(d, f"camera path {file}")
