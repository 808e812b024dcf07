"""Camera rays, undistortion, NDC and render paths, on hand-checkable toy cases."""
import numpy as np
import pytest

from clrf.data.cameras import (
    camera_orbit_poses, distort, look_at, ndc_extent, orbit_poses, pixel_rays, spiral_poses,
    to_ndc, undistort)
from clrf.testing.tolerances import CAMERA_ATOL, UNDISTORT_ATOL

# The fox capture's OpenCV coefficients (instant-ngp data/nerf/fox/transforms.json).
FOX_DISTORTION = (0.0578421, -0.0805099, -0.000980296, 0.00015575)


def _rigid(poses):
    r = poses[:, :3, :3]
    return (np.abs(np.einsum("nji,njk->nik", r, r) - np.eye(3)).max() < 1e-9
            and np.allclose(poses[:, 3], [0, 0, 0, 1]))


def test_centre_pixel_looks_down_minus_z():
    pose = look_at(np.array([1.0, -2.0, 3.0]), np.array([0.2, 0.1, -0.3]))
    H = W = 5                                    # odd: pixel (2, 2) centre is (2.5, 2.5) = (cx, cy)
    o, d = pixel_rays(pose[None], (7.0, 9.0, 2.5, 2.5), H, W)
    assert o.shape == d.shape == (H * W, 3)
    centre = d.reshape(H, W, 3)[2, 2]
    np.testing.assert_allclose(centre, -pose[:3, 2], atol=CAMERA_ATOL)       # camera -z
    np.testing.assert_allclose(o, np.broadcast_to(pose[:3, 3], o.shape), atol=CAMERA_ATOL)
    # and it points at the look-at target
    to_target = np.array([0.2, 0.1, -0.3]) - pose[:3, 3]
    np.testing.assert_allclose(centre / np.linalg.norm(centre), to_target / np.linalg.norm(to_target),
                               atol=CAMERA_ATOL)


def test_pixel_axes_opengl():
    # identity pose: right column -> +x, top row -> +y, all rays z = -1
    H, W = 3, 4
    _, d = pixel_rays(np.eye(4), (2.0, 2.0, W / 2, H / 2), H, W)
    d = d.reshape(H, W, 3)
    np.testing.assert_allclose(d[..., 2], -1.0)
    # pixel (row 0, col 3) centre at (3.5, 0.5): x = (3.5 - 2) / 2 = 0.75, y = -(0.5 - 1.5) / 2 = 0.5
    np.testing.assert_allclose(d[0, 3], [0.75, 0.5, -1.0], atol=CAMERA_ATOL)
    _, dn = pixel_rays(np.eye(4), (2.0, 2.0, W / 2, H / 2), H, W, normalize=True)
    np.testing.assert_allclose(np.linalg.norm(dn, axis=-1), 1.0, atol=CAMERA_ATOL)


def test_pixel_rays_batch_order():
    poses = orbit_poses(3, radius=2.0, elevation_deg=20.0)
    o, d = pixel_rays(poses, (3.0, 3.0, 1.0, 1.5), 3, 2)
    assert o.shape == (3 * 3 * 2, 3)
    for i in range(3):
        np.testing.assert_allclose(o[i * 6:(i + 1) * 6], np.broadcast_to(poses[i, :3, 3], (6, 3)),
                                   atol=CAMERA_ATOL)


def test_undistort_inverts_distort():
    # normalised coordinates of a whole 1080x1920 fox frame (fx 1375, cx 555, cy 965)
    u, v = np.meshgrid(np.linspace(0, 1080, 41), np.linspace(0, 1920, 61))
    xy = np.stack([(u - 554.558) / 1375.52, (v - 965.268) / 1374.49], -1)
    xd = distort(xy, FOX_DISTORTION)
    assert np.abs(xd - xy).max() > 1e-3           # the distortion is not a no-op
    np.testing.assert_allclose(undistort(xd, FOX_DISTORTION), xy, atol=UNDISTORT_ATOL, rtol=0)


def test_distort_toy_value():
    # x = 0.1, k1 = 0.1: radial = 1 + 0.1 * 0.01 = 1.001 -> x_d = 0.1001
    np.testing.assert_allclose(distort([[0.1, 0.0]], (0.1, 0, 0, 0)), [[0.1001, 0.0]], atol=1e-15)
    # tangential p1 only, point (0.1, 0.2): x_d = x + 2 p1 x y = 0.1 + 2*0.01*0.02 = 0.1004
    #                                        y_d = y + p1 (r2 + 2 y^2) = 0.2 + 0.01*(0.05+0.08)
    np.testing.assert_allclose(distort([[0.1, 0.2]], (0, 0, 0.01, 0)), [[0.1004, 0.2013]],
                               atol=1e-15)


def test_distorted_rays_reproject_to_pixel_centres():
    intr = (50.0, 52.0, 15.3, 11.7)
    H, W = 24, 32
    _, d = pixel_rays(np.eye(4), intr, H, W, distortion=FOX_DISTORTION)
    xy = np.stack([d[:, 0] / -d[:, 2], -d[:, 1] / -d[:, 2]], -1)       # OpenCV normalised
    uv = distort(xy, FOX_DISTORTION) * [intr[0], intr[1]] + [intr[2], intr[3]]
    uu, vv = np.meshgrid(np.arange(W) + 0.5, np.arange(H) + 0.5)
    np.testing.assert_allclose(uv, np.stack([uu.ravel(), vv.ravel()], -1), atol=1e-6)
    # and distortion changes the rays (so the test above can fail)
    _, d0 = pixel_rays(np.eye(4), intr, H, W)
    assert np.abs(d0 - d).max() > 1e-3


def test_ndc_near_plane_and_infinity():
    H, W, f = 30, 40, 35.0
    intr = (f, f, W / 2, H / 2)
    rng = np.random.default_rng(0)
    o = rng.uniform(-0.3, 0.3, (50, 3))
    o[:, 2] = rng.uniform(-0.5, 0.5, 50)
    d = np.concatenate([rng.uniform(-0.3, 0.3, (50, 2)), -np.ones((50, 1))], 1)
    near = 1.0
    on, dn = to_ndc(o, d, intr, H, W, near=near)
    np.testing.assert_allclose(on[:, 2], -1.0, atol=CAMERA_ATOL)           # near plane -> z = -1
    np.testing.assert_allclose(on[:, 2] + dn[:, 2], 1.0, atol=CAMERA_ATOL)  # t = 1 -> infinity
    # a world point on the near plane maps to (ax x / z, ay y / z, -1): here o' = o moved to z=-1
    t = -(near + o[:, 2]) / d[:, 2]
    p = o + t[:, None] * d
    np.testing.assert_allclose(on[:, 0], -2 * f / W * p[:, 0] / p[:, 2], atol=CAMERA_ATOL)


def test_ndc_image_edge_maps_to_one():
    # the ray through the right image edge (u = W) maps to NDC x = 1 at every depth
    H, W, f = 30, 40, 35.0
    o = np.zeros((1, 3))
    d = np.array([[W / 2 / f, 0.0, -1.0]])
    on, dn = to_ndc(o, d, (f, f, W / 2, H / 2), H, W, near=1.0)
    np.testing.assert_allclose(on[0, 0], 1.0, atol=CAMERA_ATOL)
    np.testing.assert_allclose(dn[0, 0], 0.0, atol=CAMERA_ATOL)


def test_ndc_extent_of_the_reference_camera_is_the_cube():
    # the camera at the NDC reference pose sees exactly x, y in [-1, 1] (pixel edges 0 and W)
    H, W, f = 30, 40, 35.0
    ex, ey = ndc_extent(np.eye(4)[None], (f, f, W / 2, H / 2), H, W)
    np.testing.assert_allclose([ex, ey], [1.0, 1.0], atol=CAMERA_ATOL)


@pytest.mark.parametrize("distortion", [None, FOX_DISTORTION])
def test_ndc_extent_holds_every_pixel_ray(distortion):
    # turned and shifted forward-facing cameras: every pixel-centre ray of every view lies inside
    # the extent from the near plane to infinity, and the extent is reached within a pixel
    H, W, f = 30, 40, 35.0
    intr = (f, f, W / 2, H / 2)
    rng = np.random.default_rng(3)
    poses = np.stack([look_at(rng.uniform(-0.3, 0.3, 3) * [1, 1, 0.2],
                              np.array([*rng.uniform(-0.4, 0.4, 2), -4.0]), up=(0, 1, 0))
                      for _ in range(6)])
    ex, ey = ndc_extent(poses, intr, H, W, distortion)
    assert ex > 1.05 and ey > 1.05                       # the cube would cut these views
    o, d = to_ndc(*pixel_rays(poses, intr, H, W, distortion), intr, H, W)
    ends = np.concatenate([o, o + d])
    mx, my = np.abs(ends[:, 0]).max(), np.abs(ends[:, 1]).max()
    assert mx <= ex and my <= ey
    assert ex - mx < 3.0 / W and ey - my < 3.0 / H      # half a pixel, in NDC units, plus warp


def test_orbit_poses():
    poses = orbit_poses(8, radius=3.0, elevation_deg=30.0, center=(0.5, 0.0, -0.2))
    assert poses.shape == (8, 4, 4) and _rigid(poses)
    c = np.array([0.5, 0.0, -0.2])
    np.testing.assert_allclose(np.linalg.norm(poses[:, :3, 3] - c, axis=-1), 3.0)
    np.testing.assert_allclose(poses[:, 2, 3] - c[2], 3.0 * np.sin(np.deg2rad(30.0)))
    look = (c - poses[:, :3, 3]) / 3.0
    np.testing.assert_allclose(-poses[:, :3, 2], look, atol=1e-12)          # -z at the centre
    assert np.all(poses[:, 2, 1] > 0)                                       # camera up is up


def test_camera_orbit_follows_a_tilted_capture():
    """A capture walked around a point on a circle of radius 2 at height 0.5 above it, about an
    up axis tilted away from z: the render orbit lies on that circle, looks at the centre and
    keeps the capture's up."""
    up = np.array([0.3, -0.2, 1.0])
    up /= np.linalg.norm(up)
    e1 = np.cross(up, [1.0, 0.0, 0.0])
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(up, e1)
    c = np.array([0.1, 0.2, -0.3])
    a = np.linspace(0, 2 * np.pi, 12, endpoint=False) + 0.1
    eyes = c + 0.5 * up + 2.0 * (np.cos(a)[:, None] * e1 + np.sin(a)[:, None] * e2)
    capture = look_at(eyes, c, up)
    path = camera_orbit_poses(capture, 7, c)
    assert path.shape == (7, 4, 4) and _rigid(path)
    rel = path[:, :3, 3] - c
    np.testing.assert_allclose(rel @ up, 0.5, atol=1e-12)
    np.testing.assert_allclose(np.linalg.norm(rel - np.outer(rel @ up, up), axis=-1), 2.0,
                               atol=1e-12)
    to_c = -rel / np.linalg.norm(rel, axis=-1, keepdims=True)
    np.testing.assert_allclose(-path[:, :3, 2], to_c, atol=1e-12)
    assert np.all(path[:, :3, 1] @ up > 0.9)


def test_spiral_poses():
    base = np.tile(np.eye(4), (5, 1, 1))
    base[:, 0, 3] = np.linspace(-0.2, 0.2, 5)
    base[:, 1, 3] = np.linspace(0.1, -0.1, 5)
    path = spiral_poses(base, n=30, focus_depth=4.0, rots=2, zrate=0.5)
    assert path.shape == (30, 4, 4) and _rigid(path) and np.all(np.isfinite(path))
    target = np.array([0.0, 0.0, -4.0])
    to_t = target - path[:, :3, 3]
    to_t /= np.linalg.norm(to_t, axis=-1, keepdims=True)
    np.testing.assert_allclose(-path[:, :3, 2], to_t, atol=1e-12)
    assert np.ptp(path[:, 0, 3]) > 0.1                                      # it moves


def test_bad_intrinsics_rejected():
    with pytest.raises(ValueError, match="intrinsics"):
        pixel_rays(np.eye(4), (1.0, 2.0, 3.0), 2, 2)
    with pytest.raises(ValueError, match="focal"):
        pixel_rays(np.eye(4), (0.0, 2.0, 1.0, 1.0), 2, 2)
