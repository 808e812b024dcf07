"""COLMAP scene folders: a model written here from a known scene (text and binary) must load to
the same rays as the same scene's poses_bounds.npy / transforms.json form; bad models fail
with a DataError naming the file."""
import json
import struct
import subprocess
import sys

import imageio.v3 as iio
import numpy as np
import pytest

from clrf.data.cameras import camera_dirs, pixel_rays
from clrf.data import DataError, detect_layout, load_dataset
from clrf.data.colmap import CAMERA_MODELS
from clrf.data.cameras import view_rays
from clrf.testing.tolerances import CAMERA_ATOL, RESAMPLE_ATOL

H, W, F = 12, 16, 14.0
MODEL_IDS = {name: mid for mid, (name, _) in CAMERA_MODELS.items()}


# ---------------------------------------------------------------- a COLMAP writer (tests only)

def _quat(r):
    """Unit quaternion (w, x, y, z) of a rotation matrix: the eigenvector of the largest
    eigenvalue of the symmetric 4x4 matrix whose quadratic form is trace(R^T R(q)) (Bar-Itzhack)."""
    k = np.array([[r[0, 0] - r[1, 1] - r[2, 2], r[1, 0] + r[0, 1], r[2, 0] + r[0, 2],
                   r[2, 1] - r[1, 2]],
                  [r[1, 0] + r[0, 1], r[1, 1] - r[0, 0] - r[2, 2], r[2, 1] + r[1, 2],
                   r[0, 2] - r[2, 0]],
                  [r[2, 0] + r[0, 2], r[2, 1] + r[1, 2], r[2, 2] - r[0, 0] - r[1, 1],
                   r[1, 0] - r[0, 1]],
                  [r[2, 1] - r[1, 2], r[0, 2] - r[2, 0], r[1, 0] - r[0, 1],
                   r[0, 0] + r[1, 1] + r[2, 2]]]) / 3.0
    x, y, z, w = np.linalg.eigh(k)[1][:, -1]
    return np.array([w, x, y, z]) * (1 if w >= 0 else -1)


def _w2c_colmap(c2w_gl):
    c2w = np.array(c2w_gl, np.float64)
    c2w[:3, 1:3] *= -1.0                                   # OpenGL -> OpenCV camera axes
    w2c = np.linalg.inv(c2w)
    return _quat(w2c[:3, :3]), w2c[:3, 3]


def write_colmap(model, cams, views, points, fmt):
    """cams: {id: (model, w, h, params)}; views: [(name, cam id, OpenGL c2w)]; points: [P, 3],
    every point seen by every view. fmt 'txt' or 'bin'."""
    model.mkdir(parents=True, exist_ok=True)
    obs = [(i, j) for i in range(len(views)) for j in range(len(points))]
    if fmt == "txt":
        (model / "cameras.txt").write_text("# Camera list\n" + "".join(
            f"{cid} {m} {w} {h} " + " ".join(repr(float(p)) for p in par) + "\n"
            for cid, (m, w, h, par) in cams.items()))
        lines = ["# Image list", "#   POINTS2D[] as (X, Y, POINT3D_ID)"]
        for i, (name, cid, pose) in enumerate(views):
            q, t = _w2c_colmap(pose)
            lines.append(" ".join(map(repr, [i + 1, *map(float, q), *map(float, t), cid])) +
                         f" {name}")
            lines.append(" ".join(f"1.5 2.5 {j + 1}" for j in range(len(points))) + " 3.0 4.0 -1")
        (model / "images.txt").write_text("\n".join(lines) + "\n")
        (model / "points3D.txt").write_text("".join(
            f"{j + 1} {x!r} {y!r} {z!r} 10 20 30 0.5 " +
            " ".join(f"{i + 1} {j}" for i in range(len(views))) + "\n"
            for j, (x, y, z) in enumerate(points.tolist())))
        return
    b = struct.pack("<Q", len(cams))
    for cid, (m, w, h, par) in cams.items():
        b += struct.pack("<iiQQ", cid, MODEL_IDS.get(m, 7), w, h)
        b += struct.pack(f"<{len(par)}d", *par)
    (model / "cameras.bin").write_bytes(b)
    b = struct.pack("<Q", len(views))
    for i, (name, cid, pose) in enumerate(views):
        q, t = _w2c_colmap(pose)
        b += struct.pack("<I7dI", i + 1, *q, *t, cid) + name.encode() + b"\0"
        b += struct.pack("<Q", len(points) + 1)
        b += b"".join(struct.pack("<ddq", 1.5, 2.5, j + 1) for j in range(len(points)))
        b += struct.pack("<ddq", 3.0, 4.0, -1)
    (model / "images.bin").write_bytes(b)
    b = struct.pack("<Q", len(points))
    for j, p in enumerate(points):
        b += struct.pack("<Q3d3BdQ", j + 1, *p, 10, 20, 30, 0.5, len(views))
        b += b"".join(struct.pack("<II", i + 1, j) for i, _ in obs if _ == j)
    (model / "points3D.bin").write_bytes(b)


# ---------------------------------------------------------------- known scenes

def _look_at(eye, target):
    back = np.asarray(eye, np.float64) - target
    back /= np.linalg.norm(back)
    right = np.cross([0.0, 1.0, 0.0], back)
    right /= np.linalg.norm(right)
    m = np.eye(4)
    m[:3, :3] = np.stack([right, np.cross(back, right), back], 1)
    m[:3, 3] = eye
    return m


def _scene(kind, n=10, seed=0):
    """OpenGL camera-to-world poses and 3D points of a forward-facing or 360 capture."""
    rng = np.random.default_rng(seed)
    if kind == "forward_facing":
        eyes = np.c_[rng.uniform(-0.5, 0.5, (n, 2)), np.full(n, 3.0)]
        poses = [_look_at(e, np.array([0.0, 0.0, -2.0]) + rng.normal(0, 0.05, 3)) for e in eyes]
    else:
        a = np.linspace(0, 2 * np.pi, n, endpoint=False)
        poses = [_look_at([4 * np.cos(t), 0.5 * np.sin(3 * t), 4 * np.sin(t)], np.zeros(3))
                 for t in a]
    points = rng.uniform(-1.0, 1.0, (40, 3))
    return np.stack(poses), points


def _images(root, names, seed=0, h=H, w=W):
    rng = np.random.default_rng(seed)
    for name in names:
        (root / name).parent.mkdir(parents=True, exist_ok=True)
        iio.imwrite(root / name, rng.integers(0, 255, (h, w, 3), dtype=np.uint8))


def _depth_bounds(poses, points):
    """LLFF's per-view bounds: percentiles of the depths along each camera's viewing axis."""
    depth = -np.einsum("nk,npk->np", poses[:, :3, 2], points[None] - poses[:, None, :3, 3])
    return np.percentile(depth, [0.1, 99.9], axis=1).T


def _colmap_scene(root, poses, points, fmt, cams=None, cam_of=None):
    names = [f"IMG_{i:03d}.png" for i in range(len(poses))]
    cams = cams or {1: ("PINHOLE", W, H, [F, F, W / 2, H / 2])}
    cam_of = cam_of or [1] * len(poses)
    write_colmap(root / "sparse" / "0", cams, list(zip(names, cam_of, poses)), points, fmt)
    _images(root / "images", names)
    return root


def _llff_scene(root, poses, points):
    gl = np.asarray(poses)
    llff = np.concatenate([-gl[:, :3, 1:2], gl[:, :3, 0:1], gl[:, :3, 2:4],
                           np.broadcast_to(np.array([H, W, F])[:, None], (len(gl), 3, 1))], 2)
    pb = np.concatenate([llff.reshape(len(gl), 15), _depth_bounds(gl, points)], 1)
    root.mkdir(parents=True)
    np.save(root / "poses_bounds.npy", pb)
    _images(root / "images", [f"IMG_{i:03d}.png" for i in range(len(gl))])
    return root


def _same_rays(a, b):
    assert a.ndc == b.ndc and a.preset == b.preset and a.hw == b.hw
    np.testing.assert_allclose(a.bbox, b.bbox, atol=CAMERA_ATOL)
    np.testing.assert_allclose(a.intrinsics, b.intrinsics, atol=CAMERA_ATOL)
    for k in ("train", "test"):
        np.testing.assert_array_equal(a.split[k], b.split[k])
    np.testing.assert_array_equal(a.images, b.images)
    for x, y in zip(view_rays(a, a.poses), view_rays(b, b.poses)):
        np.testing.assert_allclose(x, y, atol=CAMERA_ATOL)


# ---------------------------------------------------------------- round trips

@pytest.mark.parametrize("kind", ["forward_facing", "real360"])
@pytest.mark.parametrize("fmt", ["txt", "bin"])
def test_colmap_matches_poses_bounds(tmp_path, kind, fmt):
    poses, points = _scene(kind)
    c = _colmap_scene(tmp_path / "c", poses, points, fmt)
    assert detect_layout(c) == "colmap"
    dc = load_dataset(c)
    dl = load_dataset(_llff_scene(tmp_path / "l", poses, points))
    assert dc.preset == kind and dc.distortion is None
    _same_rays(dc, dl)


@pytest.mark.parametrize("kind", ["forward_facing", "real360"])
@pytest.mark.parametrize("fmt", ["txt", "bin"])
def test_colmap_points_follow_the_normalised_poses(tmp_path, kind, fmt):
    """The sparse points come with the dataset, moved by the same similarity as the poses: each
    point sits at the same depth-scaled place in every camera's frame before and after (so it
    projects to the same pixel), and carries its colour (10, 20, 30) / 255."""
    poses, points = _scene(kind)
    ds = load_dataset(_colmap_scene(tmp_path / "c", poses, points, fmt))
    assert ds.points.shape == (len(points), 6) and ds.points.dtype == np.float32
    np.testing.assert_allclose(ds.points[:, 3:], np.tile([10 / 255, 20 / 255, 30 / 255],
                                                         (len(points), 1)), rtol=1e-6)
    for before, after in zip(poses, ds.poses):
        cam0 = (points - before[:3, 3]) @ before[:3, :3]
        cam1 = (ds.points[:, :3].astype(np.float64) - after[:3, 3]) @ after[:3, :3]
        # the same point in each camera's frame, up to the world's scale
        np.testing.assert_allclose(cam0[:, :2] / cam0[:, 2:], cam1[:, :2] / cam1[:, 2:],
                                   rtol=0, atol=1e-4)


def test_similarity_recovers_a_known_transform():
    from clrf.data.colmap import similarity
    poses, _ = _scene("real360")
    a = 0.7
    R = np.array([[np.cos(a), -np.sin(a), 0], [np.sin(a), np.cos(a), 0], [0, 0, 1]])
    moved = poses.copy()
    moved[:, :3, :3] = R @ poses[:, :3, :3]
    moved[:, :3, 3] = 0.3 * poses[:, :3, 3] @ R.T + [1.0, -2.0, 0.5]
    s, R2, t = similarity(poses, moved)
    assert s == pytest.approx(0.3)
    np.testing.assert_allclose(R2, R, atol=1e-12)
    np.testing.assert_allclose(t, [1.0, -2.0, 0.5], atol=1e-12)


@pytest.mark.parametrize("model,params,dist", [
    ("SIMPLE_PINHOLE", [F, 7.5, 6.5], [0, 0, 0, 0]),
    ("SIMPLE_RADIAL", [F, 7.5, 6.5, 0.05], [0.05, 0, 0, 0]),
    ("RADIAL", [F, 7.5, 6.5, 0.05, -0.01], [0.05, -0.01, 0, 0]),
    ("OPENCV", [F, F * 1.01, 7.5, 6.5, 0.05, -0.01, 0.002, -0.001],
     [0.05, -0.01, 0.002, -0.001])])
def test_colmap_camera_models_match_transforms_json(tmp_path, model, params, dist):
    poses, points = _scene("real360")
    ds = load_dataset(_colmap_scene(tmp_path / "c", poses, points, "bin",
                                    cams={1: (model, W, H, params)}))
    fx, fy, cx, cy = (params[0], params[0], *params[1:3]) if model != "OPENCV" else params[:4]
    frames = [{"file_path": f"images/IMG_{i:03d}.png", "transform_matrix": p.tolist()}
              for i, p in enumerate(poses)]
    ngp = tmp_path / "n"
    ngp.mkdir()
    (ngp / "transforms.json").write_text(json.dumps(dict(
        fl_x=fx, fl_y=fy, cx=cx, cy=cy, k1=dist[0], k2=dist[1], p1=dist[2], p2=dist[3],
        frames=frames)))
    _images(ngp / "images", [f"IMG_{i:03d}.png" for i in range(len(poses))])
    dn = load_dataset(ngp)
    np.testing.assert_allclose(ds.intrinsics, dn.intrinsics, atol=CAMERA_ATOL)
    assert (ds.distortion is None) == (dn.distortion is None)
    np.testing.assert_array_equal(ds.images, dn.images)
    # the COLMAP loader recentres and rescales the world (rigidly): camera-space rays agree
    eye = np.eye(4)[None]
    for x, y in zip(pixel_rays(eye, ds.intrinsics, H, W, ds.distortion),
                    pixel_rays(eye, dn.intrinsics, H, W, dn.distortion)):
        np.testing.assert_allclose(x, y, atol=CAMERA_ATOL)
    rel = np.linalg.inv(ds.poses[0].astype(np.float64)) @ ds.poses[1]
    rel_n = np.linalg.inv(dn.poses[0].astype(np.float64)) @ dn.poses[1]
    np.testing.assert_allclose(rel[:3, :3], rel_n[:3, :3], atol=CAMERA_ATOL)


def test_colmap_several_cameras_resampled(tmp_path):
    """A second camera with a wider view is resampled onto the first: a linear image in the
    normalised coordinates of camera 2 reads back as the same linear function of camera 1's."""
    poses, points = _scene("forward_facing", n=4)
    f2 = F * 0.8
    cams = {1: ("PINHOLE", W, H, [F, F, W / 2, H / 2]),
            2: ("SIMPLE_PINHOLE", 2 * W, 2 * H, [2 * f2, W, H])}
    root = _colmap_scene(tmp_path / "c", poses, points, "txt", cams, cam_of=[1, 2, 1, 2])

    def lin(x, y):                       # grey (16-bit RGB PNG is not writable here)
        return 0.5 + 0.3 * x - 0.25 * y

    d2 = camera_dirs([2 * f2, 2 * f2, W, H], 2 * H, 2 * W)
    img = np.round(lin(d2[..., 0], -d2[..., 1]) * 65535).astype(np.uint16)
    for name in ("IMG_001.png", "IMG_003.png"):
        iio.imwrite(root / "images" / name, img)
    with pytest.warns(UserWarning, match="2 cameras"):
        ds = load_dataset(root)
    assert ds.hw == (H, W)
    d1 = camera_dirs(ds.intrinsics, H, W)
    np.testing.assert_allclose(ds.images[[1, 3]], np.broadcast_to(
        lin(d1[..., 0], -d1[..., 1])[..., None], (2, H, W, 3)), atol=RESAMPLE_ATOL)


def test_colmap_unregistered_images_skipped(tmp_path):
    poses, points = _scene("forward_facing")
    root = _colmap_scene(tmp_path / "c", poses, points, "bin")
    _images(root / "images", ["extra_1.png", "extra_2.jpg"])
    with pytest.warns(UserWarning, match="skipping 2 images.*extra_1.png"):
        ds = load_dataset(root)
    assert len(ds.images) == len(poses)


def test_colmap_downscale_uses_images_n(tmp_path):
    poses, points = _scene("forward_facing")
    root = _colmap_scene(tmp_path / "c", poses, points, "txt")
    _images(root / "images_2", [f"IMG_{i:03d}.jpg" for i in range(len(poses))], h=H // 2,
            w=W // 2)                    # LLFF-style copies may change the extension
    ds = load_dataset(root, downscale=2)
    assert ds.hw == (H // 2, W // 2)
    np.testing.assert_allclose(ds.intrinsics, [F / 2, F / 2, W / 4, H / 4], atol=CAMERA_ATOL)


# ---------------------------------------------------------------- bad input

def _raises(fn, *parts):
    with pytest.raises(DataError) as e:
        fn()
    for p in parts:
        assert p in str(e.value), (p, str(e.value))


def test_colmap_errors(tmp_path):
    poses, points = _scene("forward_facing")
    root = _colmap_scene(tmp_path / "a", poses, points, "txt",
                         cams={1: ("FOV", W, H, [F, F, W / 2, H / 2, 0.1])})
    _raises(lambda: load_dataset(root), "cameras.txt", "FOV", "image_undistorter")
    root = _colmap_scene(tmp_path / "b", poses, points, "bin",
                         cams={1: ("FOV", W, H, [F, F, W / 2, H / 2, 0.1])})
    _raises(lambda: load_dataset(root), "cameras.bin", "model id 7")
    root = _colmap_scene(tmp_path / "c", poses, points, "bin")
    (root / "images" / "IMG_004.png").unlink()
    _raises(lambda: load_dataset(root), "IMG_004.png", "does not exist")
    root = _colmap_scene(tmp_path / "d", poses, points, "bin")
    b = (root / "sparse" / "0" / "images.bin").read_bytes()
    (root / "sparse" / "0" / "images.bin").write_bytes(b[:len(b) // 2])
    _raises(lambda: load_dataset(root), "images.bin", "truncated")
    root = _colmap_scene(tmp_path / "e", poses, points, "txt")
    (root / "sparse" / "0" / "points3D.txt").unlink()
    _raises(lambda: load_dataset(root), "points3D.bin / points3D.txt", "missing")
    from clrf.data.colmap import load_colmap
    _images(tmp_path / "f" / "images", ["IMG_000.png"])
    _raises(lambda: load_colmap(tmp_path / "f"), "sparse/0/cameras", "mapper")


def test_colmap_error_exits_2_through_cli(tmp_path):
    poses, points = _scene("forward_facing")
    root = _colmap_scene(tmp_path / "a", poses, points, "bin")
    (root / "sparse" / "0" / "cameras.bin").write_bytes(b"\x01\0\0")
    r = subprocess.run([sys.executable, "-m", "clrf.cli", "train", "--data", str(root),
                        "--out", str(tmp_path / "run")], capture_output=True, text=True)
    assert r.returncode == 2 and "Traceback" not in r.stderr
    assert "clrf: error:" in r.stderr and "cameras.bin" in r.stderr
