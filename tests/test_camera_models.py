"""Camera models: every pixel's ray, as clrf undistorts it, must point back at the 3D points
that COLMAP's published forward projection (clrf.references.reference_cameras, float64) sends to
that pixel; through the model functions, the COLMAP loader and the transforms.json loader.
Models clrf does not implement are refused by name."""
import struct

import numpy as np
import pytest

from clrf.data.camera_models import (
    MODELS, Distortion, as_distortion, check_camera, distort, from_colmap, undistort)
from clrf.data.cameras import _pixel_dirs
from clrf.data import DataError, load_dataset
from clrf.references.reference_cameras import project
from clrf.testing.tolerances import CAMERA_MODEL_ANGLE, CAMERA_MODEL_PX

from test_colmap import H as CH, W as CW, _colmap_scene, _scene
from test_data_errors import _edit, _ngp

W, H = 64, 48
CX, CY = 32.3, 23.7
# (model, COLMAP parameters) of a 64 x 48 image: realistic coefficients, fields of view up to
# ~100 degrees (radial-tangential) and ~145 degrees (fisheye) across the diagonal
CAMERAS = [
    ("SIMPLE_PINHOLE", [40.0, CX, CY]),
    ("PINHOLE", [40.0, 42.0, CX, CY]),
    ("SIMPLE_RADIAL", [40.0, CX, CY, -0.12]),
    ("RADIAL", [40.0, CX, CY, -0.15, 0.03]),
    ("OPENCV", [40.0, 42.0, CX, CY, -0.25, 0.07, 0.001, -0.0015]),
    ("FULL_OPENCV", [40.0, 42.0, CX, CY, -0.2, 0.05, 0.001, -0.0015, 0.01, 0.1, 0.01, 0.001]),
    ("OPENCV_FISHEYE", [30.0, 31.0, CX, CY, 0.05, -0.01, 0.002, -0.0005]),
    ("SIMPLE_RADIAL_FISHEYE", [30.0, CX, CY, 0.04]),
    ("RADIAL_FISHEYE", [30.0, CX, CY, 0.04, -0.008]),
]
IDS = [m for m, _ in CAMERAS]


def _angle(a, b):
    """Angle (radians) between direction arrays [..., 3], accurate near 0."""
    return np.arctan2(np.linalg.norm(np.cross(a, b), axis=-1), np.einsum("...i,...i", a, b))


def _gl(x_cv):
    """OpenCV camera axes (y down, z forward) -> OpenGL (y up, looking down -z)."""
    return x_cv * [1.0, -1.0, -1.0]


def _points_in_view(model, params, w, h, seed=0, n=4000):
    """Camera-space points (OpenCV axes) spread over the whole field of view, and their
    reference pixels; only those that land inside the w x h image."""
    rng = np.random.default_rng(seed)
    max_theta = np.deg2rad(85.0 if "FISHEYE" in model else 60.0)
    theta = np.arccos(rng.uniform(np.cos(max_theta), 1.0, n))
    phi = rng.uniform(0.0, 2.0 * np.pi, n)
    d = np.stack([np.sin(theta) * np.cos(phi), np.sin(theta) * np.sin(phi), np.cos(theta)], -1)
    pts = d * rng.uniform(0.5, 20.0, (n, 1))
    uv = project(model, params, pts)
    inside = (uv[:, 0] >= 0) & (uv[:, 0] <= w) & (uv[:, 1] >= 0) & (uv[:, 1] <= h)
    return pts[inside], uv[inside]


def _border_pixels(w, h):
    u = np.concatenate([np.linspace(0, w, 33), np.zeros(25), np.linspace(0, w, 33), np.full(25, w)])
    v = np.concatenate([np.zeros(33), np.linspace(0, h, 25), np.full(33, h), np.linspace(0, h, 25)])
    return u, v


def _check_rays(intr, dist, model, params, w, h):
    pts, uv = _points_in_view(model, params, w, h)
    assert len(pts) > 200                       # the whole image is covered
    d = _pixel_dirs(uv[:, 0], uv[:, 1], intr, dist)
    assert _angle(d, _gl(pts)).max() < CAMERA_MODEL_ANGLE


# ---------------------------------------------------------------- the models themselves

@pytest.mark.parametrize("model,params", CAMERAS, ids=IDS)
def test_rays_point_at_reference_projections(model, params):
    intr, dist = from_colmap(model, params)
    assert check_camera(dist, intr, H, W) is None
    _check_rays(intr, dist, model, params, W, H)


@pytest.mark.parametrize("model,params", CAMERAS, ids=IDS)
def test_border_round_trip(model, params):
    # pixel on the image border -> clrf ray -> reference projection -> the same pixel
    intr, dist = from_colmap(model, params)
    u, v = _border_pixels(W, H)
    d = _pixel_dirs(u, v, intr, dist)
    uv = project(model, params, _gl(d))
    np.testing.assert_allclose(uv, np.stack([u, v], -1), atol=CAMERA_MODEL_PX, rtol=0)


def test_fisheye_read_as_radial_tangential_is_caught():
    # the old misreading of OPENCV_FISHEYE (its k1..k4 taken as OpenCV k1, k2, p1, p2): the
    # check above must fail for it, by far more than its tolerance
    model, params = CAMERAS[IDS.index("OPENCV_FISHEYE")]
    pts, uv = _points_in_view(model, params, W, H)
    wrong = _pixel_dirs(uv[:, 0], uv[:, 1], params[:4], Distortion.radtan(*params[4:]))
    assert _angle(wrong, _gl(pts)).max() > 1e-2


def test_every_model_is_tested():
    assert set(IDS) == set(MODELS)


def test_toy_values():
    # fisheye, k = 0: theta_d = theta, so x = 1 (45 degrees) lands at pi/4
    np.testing.assert_allclose(distort([[1.0, 0.0]], Distortion.fisheye()), [[np.pi / 4, 0.0]],
                               atol=1e-15)
    np.testing.assert_allclose(undistort([[np.pi / 4, 0.0]], Distortion.fisheye()), [[1.0, 0.0]],
                               atol=1e-14)
    # rational radial: r2 = 0.01, radial = (1 + 0.1 r2) / (1 + 0.1 r2) = 1
    np.testing.assert_allclose(distort([[0.1, 0.0]], Distortion.radtan(k1=0.1, k4=0.1)),
                               [[0.1, 0.0]], atol=1e-15)
    # the centre stays put
    np.testing.assert_allclose(undistort([[0.0, 0.0]], Distortion.fisheye(0.1, 0.1)),
                               [[0.0, 0.0]], atol=0)


def test_distortion_serialises():
    d = Distortion.fisheye(0.1, -0.02, 0.003, -0.0004)
    assert as_distortion(d.to_json()) == d
    assert as_distortion([0.1, 0.0, 0.0, 0.0]) == Distortion.radtan(k1=0.1)   # older checkpoints
    assert as_distortion(None) is None and as_distortion([0, 0, 0, 0]) is None
    # a zero fisheye is still a fisheye (the equidistant projection), not a pinhole
    assert as_distortion(Distortion.fisheye()) is not None


def test_unusable_lenses_are_refused():
    intr = [40.0, 40.0, CX, CY]
    for d in (Distortion.radtan(k1=-0.9), Distortion.radtan(k1=-0.9, k2=0.3)):
        assert "fold" in check_camera(d, intr, H, W)         # barrel past its turning point
    assert "degrees off the optical axis" in check_camera(Distortion.fisheye(),
                                                          [10.0, 10.0, CX, CY], H, W)


# ---------------------------------------------------------------- the COLMAP loader

def _colmap_params(model, params):
    """The same lens for the loader's 16 x 12 test images (focal and centre scaled by 1/4)."""
    n_intr = 3 if MODELS[model][1][0] == "f" else 4
    p = list(np.asarray(params[:n_intr]) * CW / W) + list(params[n_intr:])
    return p


@pytest.mark.parametrize("fmt", ["txt", "bin"])
@pytest.mark.parametrize("model,params", CAMERAS, ids=IDS)
def test_colmap_loads_each_model(tmp_path, model, params, fmt):
    poses, points = _scene("real360")
    p = _colmap_params(model, params)
    root = _colmap_scene(tmp_path / "s", poses, points, fmt, cams={1: (model, CW, CH, p)})
    ds = load_dataset(root)
    assert ds.hw == (CH, CW)
    assert (ds.distortion is None) == (model in ("SIMPLE_PINHOLE", "PINHOLE"))
    _check_rays(ds.intrinsics, ds.distortion, model, p, CW, CH)


def _raises(fn, *parts):
    with pytest.raises(DataError) as e:
        fn()
    for part in parts:
        assert part in str(e.value), (part, str(e.value))


@pytest.mark.parametrize("model,n", [("FOV", 5), ("THIN_PRISM_FISHEYE", 12), ("BOGUS", 4)])
def test_colmap_refuses_unsupported_models(tmp_path, model, n):
    poses, points = _scene("real360")
    root = _colmap_scene(tmp_path / "s", poses, points, "txt",
                         cams={1: (model, CW, CH, [10.0] * n)})
    _raises(lambda: load_dataset(root), "cameras.txt", model, "not supported", "OPENCV_FISHEYE",
            "image_undistorter")


def test_colmap_bin_refuses_model_id(tmp_path):
    poses, points = _scene("real360")
    root = _colmap_scene(tmp_path / "s", poses, points, "bin")
    f = root / "sparse" / "0" / "cameras.bin"
    b = bytearray(f.read_bytes())
    struct.pack_into("<i", b, 12, 10)           # count (8 bytes), camera id (4), model id
    f.write_bytes(bytes(b))
    _raises(lambda: load_dataset(root), "cameras.bin", "model id 10 (THIN_PRISM_FISHEYE)",
            "not supported")


def test_colmap_refuses_bad_parameters(tmp_path):
    poses, points = _scene("real360")
    root = _colmap_scene(tmp_path / "a", poses, points, "txt",
                         cams={1: ("OPENCV_FISHEYE", CW, CH, [8.0, 8.0, 8.0, 6.0, 0.1, 0.0, 0.0])})
    _raises(lambda: load_dataset(root), "cameras.txt", "OPENCV_FISHEYE needs 8 parameters")
    root = _colmap_scene(tmp_path / "b", poses, points, "txt",
                         cams={1: ("RADIAL", CW, CH, [8.0, 8.0, 6.0, -0.9, 0.0])})
    _raises(lambda: load_dataset(root), "cameras.txt", "RADIAL", "not a usable lens", "fold")


# ---------------------------------------------------------------- the transforms.json loader

# camera_model -> its transforms.json distortion fields, and the COLMAP model and parameters
# of the same lens (the _ngp scene: 4 x 4 images, fl_x = fl_y = 5, centre (2, 2)); OPENCV's k3
# is OpenCV's r^6 term, which COLMAP has only in FULL_OPENCV
NGP = {
    "PINHOLE": ({}, "PINHOLE", [5.0, 5.0, 2.0, 2.0]),
    "SIMPLE_PINHOLE": ({}, "SIMPLE_PINHOLE", [5.0, 2.0, 2.0]),
    "SIMPLE_RADIAL": ({"k1": -0.1}, "SIMPLE_RADIAL", [5.0, 2.0, 2.0, -0.1]),
    "RADIAL": ({"k1": -0.1, "k2": 0.02}, "RADIAL", [5.0, 2.0, 2.0, -0.1, 0.02]),
    "OPENCV": ({"k1": -0.2, "k2": 0.05, "p1": 0.002, "p2": -0.001, "k3": 0.01}, "FULL_OPENCV",
               [5.0, 5.0, 2.0, 2.0, -0.2, 0.05, 0.002, -0.001, 0.01, 0.0, 0.0, 0.0]),
    "OPENCV_FISHEYE": ({"k1": 0.05, "k2": -0.01, "k3": 0.002, "k4": -0.0005}, "OPENCV_FISHEYE",
                       [5.0, 5.0, 2.0, 2.0, 0.05, -0.01, 0.002, -0.0005]),
}


def _ngp_model(root, fields):
    root = _ngp(root)
    _edit(root / "transforms.json", lambda m: m.update(fields))
    return root


@pytest.mark.parametrize("name", list(NGP))
def test_transforms_json_camera_model(tmp_path, name):
    fields, model, params = NGP[name]
    ds = load_dataset(_ngp_model(tmp_path / "s", dict(fields, camera_model=name)))
    _check_rays(ds.intrinsics, ds.distortion, model, params, 4, 4)


def test_transforms_json_is_fisheye(tmp_path):
    # instant-ngp's colmap2nerf marks a fisheye with is_fisheye instead of camera_model
    fields = dict(NGP["OPENCV_FISHEYE"][0], is_fisheye=True)
    ds = load_dataset(_ngp_model(tmp_path / "s", fields))
    assert ds.distortion == Distortion.fisheye(0.05, -0.01, 0.002, -0.0005)


@pytest.mark.parametrize("fields,parts", [
    ({"camera_model": "FOV"}, ["'camera_model'", "'FOV'", "not support", "OPENCV_FISHEYE"]),
    ({"camera_model": "EQUIRECTANGULAR"}, ["'camera_model'", "'EQUIRECTANGULAR'", "PINHOLE"]),
    ({"camera_model": 3}, ["'camera_model'", "3", "not support"]),
    ({"camera_model": "OPENCV", "k4": 0.01}, ["k4 = 0.01", "not part of camera_model OPENCV"]),
    ({"camera_model": "PINHOLE", "k1": 0.1}, ["k1 = 0.1", "PINHOLE", "no distortion fields"]),
    ({"k3": 0.1, "k4": 0.01}, ["k4 = 0.01", "OPENCV"]),        # no camera_model: OPENCV
    ({"camera_model": "OPENCV", "is_fisheye": True}, ["'is_fisheye'", "disagree"]),
    ({"camera_model": "SIMPLE_RADIAL", "fl_y": 6.0}, ["SIMPLE_RADIAL", "'fl_y'", "differ"]),
    ({"camera_model": "OPENCV_FISHEYE", "fl_x": 1.0, "fl_y": 1.0},
     ["OPENCV_FISHEYE", "degrees off the optical axis"]),
    ({"camera_model": "RADIAL", "k1": -3.0}, ["RADIAL", "not a usable lens"]),
])
def test_transforms_json_refusals(tmp_path, fields, parts):
    _raises(lambda: load_dataset(_ngp_model(tmp_path / "s", fields)), "transforms.json", *parts)
