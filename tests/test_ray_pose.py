"""Pose corrections of ray batches (cl/ray_pose.cl, clrf/corrections/ray_pose.py): the rays
from each image's corrected camera and the per-image sums against the float64 twin, and the
camera gradient dL/dR, dL/dt against central differences of a loss of the camera's rays."""
import numpy as np
import pyopencl.array as cla
import pytest

from clrf.corrections.pose import corrected_viewmat, so3_exp
from clrf.corrections.ray_pose import apply_rays, camera_gradient, ray_rows, ray_sums
from clrf.references import reference_ray_pose as ref
from clrf.testing import tolerances as tol


def _up(dev, a, dtype=np.float32):
    return cla.to_device(dev.queue, np.ascontiguousarray(a, dtype))


def _viewmats(n, seed):
    """n world-to-camera [4, 4]: random rotations, centres ~3 from the origin."""
    rng = np.random.default_rng(seed)
    out = np.tile(np.eye(4), (n, 1, 1))
    for v in range(n):
        out[v, :3, :3] = so3_exp(rng.normal(size=3))
        out[v, :3, 3] = rng.normal(size=3) + [0, 0, 3]
    return out


def _batch(n, V, pixels, seed):
    rng = np.random.default_rng(seed)
    index = rng.integers(0, (V - 1) * pixels, n)     # the last image has no ray
    return (index.astype(np.int32), rng.normal(size=(n, 3)), rng.normal(size=(n, 3)),
            rng.normal(size=(n, 6)))


@pytest.mark.parametrize("n", [0, 1, 65, 300])
def test_rays_and_sums_match_the_twin(device, n):
    V, pixels = 5, 7
    index, o0, d0, g = _batch(n, V, pixels, n)
    vm0 = _viewmats(V, 1)
    vm = np.stack([corrected_viewmat(m, [0.01, -0.02, 0.03], [0.05, 0.0, -0.1], 2.0)
                   for m in vm0])
    r = ray_rows(vm0, vm)
    np.testing.assert_allclose(r, ref.rows(vm0, vm), rtol=0, atol=tol.RAY_POSE_ATOL)
    o, d = apply_rays(device, _up(device, index, np.int32), pixels, _up(device, r),
                      _up(device, o0), _up(device, d0))
    wo, wd = ref.apply(index, pixels, r, o0.astype(np.float32), d0.astype(np.float32))
    assert o.shape == (n, 3) and d.shape == (n, 3)
    np.testing.assert_allclose(o.get(), wo, rtol=0, atol=tol.RAY_POSE_ATOL)
    np.testing.assert_allclose(d.get(), wd, rtol=0, atol=tol.RAY_POSE_ATOL * 3)
    s = ray_sums(device, _up(device, index, np.int32), pixels, _up(device, d0), _up(device, g),
                 V).get()
    want = ref.sums(index, pixels, d0.astype(np.float32), g.astype(np.float32), V)
    assert np.all(s[-1] == 0) and s[:, 12].sum() == n
    bound = ref.sums(index, pixels, np.abs(d0), np.abs(g), V)   # the terms' magnitudes
    assert np.all(np.abs(s - want) <= tol.RAY_POSE_SUM_RTOL * bound)


def test_camera_gradient_vs_central_differences():
    """L of the rays a camera [R t] makes (o = -R^T t, d = R^T d_cam, a smooth nonlinear loss):
    dL/dR, dL/dt from the per-ray gradients' sums (host and twin) against central differences
    in each entry of R and t."""
    rng = np.random.default_rng(4)
    n = 40
    d_cam = np.concatenate([rng.uniform(-0.5, 0.5, (n, 2)), np.ones((n, 1))], 1)
    a, b = rng.normal(size=(n, 3)), rng.normal(size=(n, 3))
    vm = _viewmats(1, 5)[0]

    def rays(V):
        R, t = V[:3, :3], V[:3, 3]
        return np.tile(-R.T @ t, (n, 1)), d_cam @ R

    def loss(V):
        o, d = rays(V)
        return np.sum(np.sin(np.sum(o * a, 1))) + np.sum(np.sum(d * b, 1) ** 2)

    o, d = rays(vm)
    g = np.concatenate([np.cos(np.sum(o * a, 1))[:, None] * a,
                        2 * np.sum(d * b, 1)[:, None] * b], 1)
    s = ref.sums(np.zeros(n, int), 1, d, g, 1)[0]
    dR, dt = camera_gradient(vm, s)
    wR, wt = ref.camera_gradient(vm, s)
    np.testing.assert_allclose(dR, wR, rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(dt, wt, rtol=1e-12, atol=1e-12)
    h = 1e-6
    for k in range(12):
        e = np.zeros((4, 4))
        e[k // 4, k % 4] = h        # rows 0-2: [R t]'s entries
        fd = (loss(vm + e) - loss(vm - e)) / (2 * h)
        got = dR[k // 4, k % 4] if k % 4 < 3 else dt[k // 4]
        assert abs(fd - got) <= tol.RAY_POSE_FD_RTOL * max(1.0, abs(got)), (k, fd, got)
