"""clrf/outputs/frames.py: the cameras of the shared render path (clrf render and the viewer)."""
import math

import numpy as np
import pytest

from clrf.data.cameras import look_at
from clrf.outputs.frames import check_pose, frame_rays, spec_from_fov, spec_from_meta
from clrf.testing.tolerances import CAMERA_ATOL, NDC_LINE_ATOL

# a forward-facing (NDC) scene's training camera: 80x60, f = 50, principal point at the centre
META = {"H": 60, "W": 80, "intrinsics": [50.0, 50.0, 40.0, 30.0], "ndc": True}
FOV = math.degrees(2 * math.atan(0.5 * 60 / 50.0))       # the same camera as a field of view


def test_fov_camera_equal_to_the_training_camera_gives_its_rays():
    pose = look_at([0.1, -0.2, 0.3], [0.0, 0.0, -4.0], up=(0, 1, 0))
    for ndc in (False, True):
        meta = dict(META, ndc=ndc)
        o1, d1 = frame_rays(spec_from_fov(FOV, 80, 60, meta), pose)
        o2, d2 = frame_rays(spec_from_meta(meta), pose)
        np.testing.assert_allclose(o1, o2, atol=CAMERA_ATOL)
        np.testing.assert_allclose(d1, d2, atol=CAMERA_ATOL)


def ndc_point(p):
    """The training camera's NDC map of world points [n, 3] (near = 1):
    (-2 fx / W * x / z, -2 fy / H * y / z, 1 + 2 / z)."""
    fx, fy = META["intrinsics"][:2]
    x, y, z = p.T
    return np.stack([-2 * fx / META["W"] * x / z, -2 * fy / META["H"] * y / z, 1 + 2 / z], -1)


def test_viewing_camera_of_an_ndc_scene_uses_the_training_ndc_map():
    # another field of view and aspect than the training camera: its own fx / W differs
    pose = look_at([0.2, 0.1, 0.0], [0.5, -0.3, -5.0], up=(0, 1, 0))
    spec = spec_from_fov(25.0, 50, 20, META)
    o, d = frame_rays(spec, pose)
    world = spec_from_fov(25.0, 50, 20)                 # the same camera without NDC
    ow, dw = frame_rays(world, pose)
    for i in (0, 517, 999):                              # a few pixels
        pts = ndc_point(np.stack([ow[i] + t * dw[i] for t in (2.0, 6.0)]).astype(np.float64))
        for q in pts:   # each NDC point of the world ray lies on the NDC ray
            s = np.dot(q - o[i], d[i]) / np.dot(d[i], d[i])
            np.testing.assert_allclose(o[i] + s * d[i], q, atol=NDC_LINE_ATOL)


@pytest.mark.parametrize("pose, words", [
    (np.full(16, np.nan), "NaN"), (np.eye(3), "16 numbers"), (2 * np.eye(4), "rotation"),
])
def test_check_pose_names_the_problem(pose, words):
    with pytest.raises(ValueError, match=words):
        check_pose(pose)


@pytest.mark.parametrize("fov, w, h, words", [
    (0.0, 8, 8, "fov"), (180.0, 8, 8, "fov"), (float("nan"), 8, 8, "fov"),
    (50.0, 0, 8, "image size"), (50.0, 8, 5000, "image size"),
])
def test_spec_from_fov_rejects(fov, w, h, words):
    with pytest.raises(ValueError, match=words):
        spec_from_fov(fov, w, h)


def test_viewer_without_websockets_says_how_to_install(monkeypatch):
    import sys

    from clrf.viewer.core import ViewerError
    from clrf.viewer.server import need_websockets
    monkeypatch.setitem(sys.modules, "websockets", None)
    monkeypatch.setitem(sys.modules, "websockets.sync.server", None)
    with pytest.raises(ViewerError, match=r"pip install websockets.*clrf\[view\]"):
        need_websockets()
