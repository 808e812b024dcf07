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


def test_pose_opt_rays_gathers_an_images_batches_into_one_step(device):
    """pose_opt_rays R: an image steps once its batches hold R rays, on the sum of their
    sums (the same step as one batch of all of them), and what it gathered is then cleared;
    an image short of R does not move; the gathered sums go through the checkpoint."""
    from clrf.corrections.ray_pose import RayPose
    V, pixels, R = 4, 50, 30
    vm0 = _viewmats(V, 2)
    rng = np.random.default_rng(3)
    # image 0: 20 + 20 rays, image 1: 10 + 10, image 2: 40 in the first batch, image 3: none
    counts = [(20, 20), (10, 10), (40, 0), (0, 0)]
    batches = []
    for k in range(2):
        index = np.concatenate([v * pixels + rng.integers(0, pixels, c[k])
                                for v, c in enumerate(counts)]).astype(np.int32)
        batches.append((index, rng.normal(size=(len(index), 3)),
                        rng.normal(size=(len(index), 6)) * 1e-2))
    gather = RayPose(device, vm0, pixels, 1e-3, 0.0, 3.0, hold_frame=False, min_rays=R)
    once = RayPose(device, vm0, pixels, 1e-3, 0.0, 3.0, hold_frame=False)
    index, d, g = batches[0]
    gather.step_rays(_up(device, index, np.int32), _up(device, d), _up(device, g))
    assert gather.pose.steps.tolist() == [0, 0, 1, 0]      # image 2 had 40 rays at once
    state = gather.state_dict()
    assert state["pose_gathered"][0, 12] == 20 and state["pose_gathered"][2, 12] == 0
    back = RayPose(device, None, 0, 1e-3, 0.0, 3.0, hold_frame=False, min_rays=R,
                   state=state)
    np.testing.assert_array_equal(back.gathered, gather.gathered)
    index, d, g = batches[1]
    gather.step_rays(_up(device, index, np.int32), _up(device, d), _up(device, g))
    assert gather.pose.steps.tolist() == [1, 0, 1, 0]      # image 0: 40 rays; image 1: 20
    assert gather.gathered[0].sum() == 0 and gather.gathered[1, 12] == 20
    assert not gather.pose.params[1].any() and not gather.pose.params[3].any()
    both = [np.concatenate([batches[0][i][batches[0][0] // pixels == 0],
                            batches[1][i][batches[1][0] // pixels == 0]]) for i in range(3)]
    once.step_rays(_up(device, both[0], np.int32), _up(device, both[1]), _up(device, both[2]))
    np.testing.assert_allclose(gather.pose.params[0], once.pose.params[0], rtol=1e-5,
                               atol=1e-9)
    assert np.abs(gather.pose.params[0]).max() > 1e-4


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


# ---- hash.pose_opt on a tiny scene --------------------------------------------------------
def _pose_model(device, bounded=False, **cfg):
    """A tiny hash model with hash.pose_opt (unless ``cfg`` turns it off) whose field is smooth
    (only its two coarse levels non-zero), occupied everywhere, in a box that holds every
    sample of the test's cameras (no sample enters or leaves the box as a camera moves),
    rendering the bins it trains on; ``bounded``: the GPU-shaped step."""
    import dataclasses
    import sys
    from pathlib import Path
    sys.path.insert(0, str(Path(__file__).resolve().parent))
    from test_hash_model import SMALL
    from clrf.hash.model import HashModel
    c = dataclasses.replace(SMALL, **{"pose_opt": True, "train_t_stop": 0.0,
                                      "render_oversample": 1, "pose_opt_every": 1,
                                      "pose_opt_rays": 0, **cfg})   # a camera step a step
    model = HashModel(device, c, 1.5, 4.5, [[-8.0] * 3, [8.0] * 3], (0.2, 0.5, 1.0),
                      bounded=bounded)
    t = np.random.default_rng(3).uniform(-1, 1, model.enc.shape).astype(np.float32)
    t[2:] = 0.0
    model.enc.table.set(t)
    model.occ.ema.fill(np.float32(1.0))
    model.occ._threshold(0.5)
    return model


def _view(c2w, hw=(16, 16), focal=14.0):
    from clrf.data.cameras import _posed, camera_dirs
    d_cam = camera_dirs([focal, focal, hw[1] / 2, hw[0] / 2], *hw).reshape(-1, 3)
    return _posed(np.asarray(c2w, np.float64)[None], d_cam)


def _given_pose(c2w_true, w, tau, pivot):
    """The camera-to-world whose correction (w, tau) about ``pivot`` is the true camera."""
    from clrf.hash.kind import OPENGL_TO_OPENCV, viewmat_of
    V = viewmat_of(c2w_true)
    E = so3_exp(-np.asarray(w))
    p = np.array([0.0, 0.0, pivot])
    V0 = np.eye(4)
    V0[:3, :3] = E @ V[:3, :3]
    V0[:3, 3] = E @ (V[:3, 3] - p - tau) + p
    return np.linalg.inv(OPENGL_TO_OPENCV @ V0), V0


def _scene(device, **cfg):
    """(model, true camera-to-worlds, (w*, tau*), the batch's device arrays (o0, d0, target,
    index), pixels): two 16 x 16 views rendered by the model from their true cameras, the
    first one's rays made by a given camera off by a known correction (w*, tau*)."""
    from clrf.data.cameras import look_at
    from clrf.hash.kind import pivot_depth, viewmat_of
    model = _pose_model(device, **cfg)
    c2w = [look_at([0.3, -3.0, 0.8], [0.0, 0.0, 0.0]), look_at([2.8, 1.0, -0.5], [0, 0, 0])]
    star = (np.array([0.02, -0.015, 0.01]), np.array([-0.03, 0.04, 0.01]))
    pivots = [pivot_depth(viewmat_of(p), model.bbox) for p in c2w]
    given, vm0 = _given_pose(c2w[0], *star, pivots[0])
    rays = [_view(given), _view(c2w[1])]
    targets = [model.render(*_view(p))["rgb"] for p in c2w]
    pixels = len(targets[0])
    model.attach_corrections(2, pixels, False, viewmats=lambda: np.stack(
        [vm0, viewmat_of(c2w[1])]), pivots=lambda: pivots)
    batch = (_up(device, np.concatenate([r[0] for r in rays])),
             _up(device, np.concatenate([r[1] for r in rays])),
             _up(device, np.concatenate(targets)), _up(device, np.arange(2 * pixels), np.int32))
    return model, c2w, star, batch, pixels


def test_pose_gradient_matches_differences_of_the_step_loss(device):
    """dL/d(w, tau) of image 0 as a step forms it (each ray's gradient, the per-image sums,
    camera_gradient, the correction's chain rule) against central differences of the float32
    step loss in (w, tau), at the given pose and half-way to the true one."""
    from clrf.corrections import Corrections
    model, _, star, (o0, d0, target, index), pixels = _scene(device, pose_reg=0.0)
    pose = model.corrections.get("pose")
    model.corrections = Corrections()        # the loss alone; the correction is driven here

    def loss_grad(p):
        pose.pose.params[0] = p
        pose.rows.set(ray_rows(pose.viewmats0, pose.viewmats()))
        o, d = pose.rays(index, o0, d0)
        rg = _up(device, np.zeros((2 * pixels, 6)))
        loss, _ = model.loss_and_grad(0, o, d, target, jitter=False, ray_grad=rg)
        s = ray_sums(device, index, pixels, d, rg, 2).get()
        vm = pose.pose.viewmat(pose.viewmats0[0], 0)
        return loss, pose.pose.gradient(0, vm, *camera_gradient(vm, s[0]))

    h = 1e-3
    for p in (np.zeros(6), 0.5 * np.concatenate(star)):
        _, g = loss_grad(p.copy())
        fd = np.array([(loss_grad(p + h * e)[0] - loss_grad(p - h * e)[0]) / (2 * h)
                       for e in np.eye(6)])
        assert np.abs(g).max() > 0
        np.testing.assert_allclose(g, fd, rtol=0,
                                   atol=tol.HASH_POSE_FD_REL_TO_MAX * np.abs(g).max())


def test_pose_refinement_moves_a_perturbed_camera_toward_its_true_pose(device):
    """Targets rendered by the model from two true cameras; image 0's rays come from a given
    camera off by a known correction (w*, tau*) (0.03 rad, 0.05). Steps of hash.pose_opt (the
    scene held still) bring its correction toward (w*, tau*): the error falls fourfold, and
    its first Adam step (lr times the gradient's sign) moves each coordinate of (w*, tau*)
    larger than 0.015 that way; image 1, at its true pose, stays within one step of it (seen:
    the error 0.027 -> 0.0023 in 40 steps; image 1 within a tenth of a step)."""
    model, _, star, (o0, d0, target, index), pixels = _scene(
        device, lr_pose=3e-3, lr_pose_final=3e-3, pose_reg=0.0, pose_opt_after=0.0)
    pose = model.corrections.get("pose")
    w_star, tau_star = star
    star = np.concatenate([w_star, tau_star / model.extent])

    def error():
        p = pose.pose.params[0]
        return np.linalg.norm(np.concatenate([p[:3], p[3:] / model.extent]) - star)

    before = error()
    for it in range(40):
        model.loss_and_grad(it, o0, d0, target, jitter=False, index=index)
        if it == 0:
            first = pose.pose.params[0].copy()
            big = np.abs(np.concatenate([w_star, tau_star])) > 0.015
            assert np.all(np.sign(first[big]) == np.sign(np.concatenate(
                [w_star, tau_star])[big])), (first, w_star, tau_star)
    assert error() < 0.25 * before, (before, error(), pose.pose.params[0], star)
    p1 = pose.pose.params[1]          # within one Adam step (lr, lr * extent) of where it was
    assert np.all(np.abs(p1[:3]) < 3e-3) and np.all(np.abs(p1[3:]) < 3e-3 * model.extent), p1
    assert pose.pose.steps.tolist() == [40, 40]


def test_no_camera_gradient_before_the_start(device, monkeypatch):
    """Before hash.pose_opt_after of the budget the correction does not train: the model sees
    no camera correction (Corrections.ray_camera is None), renders the stored rays and
    computes no spatial derivative (HashEncoding.dx is not called); from the start on it does,
    and the poses move."""
    from clrf.hash.encoding import HashEncoding
    model, _, _, (o0, d0, target, index), _ = _scene(
        device, lr_pose=3e-3, lr_pose_final=3e-3, pose_reg=0.0, pose_opt_after=0.5)
    pose = model.corrections.get("pose")
    calls = []
    real_dx = HashEncoding.dx
    monkeypatch.setattr(HashEncoding, "dx", lambda self, *a, **k: calls.append(1) or
                        real_dx(self, *a, **k))
    model.corrections.schedule(0.4)
    assert not pose.trains and model.corrections.ray_camera is None
    model.loss_and_grad(0, o0, d0, target, jitter=False, index=index)
    assert calls == [] and not pose.pose.params.any() and pose.pose.steps.tolist() == [0, 0]
    model.corrections.schedule(0.5)
    assert pose.trains and model.corrections.ray_camera is pose
    model.loss_and_grad(1, o0, d0, target, jitter=False, index=index)
    assert calls == [1] and pose.pose.params[0].any() and pose.pose.steps.tolist() == [1, 1]


def test_pose_opt_every_forms_the_camera_gradient_on_one_step_in_k(device, monkeypatch):
    """hash.pose_opt_every 3: of six steps, the first and the fourth form the spatial
    derivative and step the cameras; the others render the corrected cameras' rays (a moved
    camera's rays differ from the stored ones) with no derivative and no camera step."""
    from clrf.hash.encoding import HashEncoding
    model, _, _, (o0, d0, target, index), _ = _scene(
        device, lr_pose=3e-3, lr_pose_final=3e-3, pose_reg=0.0, pose_opt_after=0.0,
        pose_opt_every=3)
    pose = model.corrections.get("pose")
    calls, seen = [], []
    real_dx, real_rays = HashEncoding.dx, type(pose).rays
    monkeypatch.setattr(HashEncoding, "dx", lambda self, *a, **k: calls.append(1) or
                        real_dx(self, *a, **k))
    monkeypatch.setattr(type(pose), "rays", lambda self, *a: seen.append(1) or
                        real_rays(self, *a))
    for it in range(6):
        model.loss_and_grad(it, o0, d0, target, jitter=False, index=index)
        assert pose.pose.steps.tolist() == [1 + it // 3] * 2 and len(calls) == 1 + it // 3
    assert len(seen) == 6 and pose.pose.params[0].any()


def test_checkpoint_keeps_the_corrections_and_resumes_alike(device):
    """A model with hash.pose_opt after a few steps, through state_dict and from_state_dict:
    the same corrections, Adam moments, cameras and rows, and the next step the same."""
    from clrf.hash.model import HashModel
    model, _, _, (o0, d0, target, index), _ = _scene(device)
    for it in range(3):
        model.loss_and_grad(it, o0, d0, target, jitter=False, index=index)
    back = HashModel.from_state_dict(device, model.state_dict())
    a, b = model.corrections.get("pose"), back.corrections.get("pose")
    for k in ("params", "m", "v", "steps", "pivots"):
        np.testing.assert_array_equal(getattr(a.pose, k), getattr(b.pose, k))
    np.testing.assert_array_equal(a.viewmats0, b.viewmats0)
    assert (a.pixels, a.pose.scale, a.pose.lr) == (b.pixels, b.pose.scale, b.pose.lr)
    np.testing.assert_array_equal(a.rows.get(), b.rows.get())
    for m in (model, back):
        m.loss_and_grad(3, o0, d0, target, jitter=False, index=index)
    np.testing.assert_array_equal(a.pose.params, b.pose.params)


def test_pose_opt_is_refused_on_ndc_scenes_and_over_ranks():
    """NDC rays are not a camera's, and the corrections are not summed over MPI ranks: one
    error naming hash.pose_opt each."""
    from types import SimpleNamespace
    from clrf.hash.config import HashConfig
    from clrf.hash.kind import Distributed, create
    cfg = SimpleNamespace(hash=HashConfig(pose_opt=True))
    with pytest.raises(ValueError, match="hash.pose_opt.*NDC"):
        create(None, cfg, SimpleNamespace(name="fern", ndc=True), (0, 0, 0))
    with pytest.raises(ValueError, match="hash.pose_opt.*MPI ranks"):
        Distributed(SimpleNamespace(Get_size=lambda: 2)).check(cfg)


def test_the_frame_is_held_every_frame_every_steps(device, monkeypatch):
    """RayPose knows every image's given camera, so the corrections' common motion is taken
    out every FRAME_EVERY steps (clrf/corrections/pose.py): a common rigid motion of all the
    cameras is gone, and the device rows follow; with the frame free it stays."""
    from clrf.corrections import ray_pose as rp
    from clrf.corrections.pose import twist_matrix
    from clrf.references.reference_splat import look_at
    monkeypatch.setattr(rp, "FRAME_EVERY", 2)
    rng = np.random.default_rng(4)
    given = np.stack([look_at(rng.normal(size=3) * 3 + 0.1, (0, 0, 0)) for _ in range(5)])
    G = twist_matrix(np.radians(0.5) * np.array([0.0, 0.6, 0.8]), [0.02, 0.0, -0.03])
    q = device.queue
    empty = (cla.zeros(q, 0, np.int32), cla.zeros(q, (0, 3), np.float32),
             cla.zeros(q, (0, 6), np.float32))
    for hold in (True, False):
        r = rp.RayPose(device, given, 16, 1e-3, 0.0, 3.0, hold_frame=hold)
        for v, V in enumerate(given):
            r.pose.set_viewmat(v, V, V @ G)
        r.pose.steps[:] = 1
        r.rows.set(ray_rows(given, r.viewmats()))
        moved = r.pose.params.copy()
        assert np.abs(r.rows.get() - ray_rows(given, given)).max() > 1e-3
        r.step_rays(*empty)                  # step 1: no removal yet
        np.testing.assert_array_equal(r.pose.params, moved)
        r.step_rays(*empty)                  # step 2
        if hold:
            assert np.abs(r.pose.params).max() < 1e-9
            np.testing.assert_allclose(r.rows.get(), ray_rows(given, given), atol=1e-6)
        else:
            np.testing.assert_array_equal(r.pose.params, moved)


def test_the_batched_camera_gradients_are_the_single_ones():
    from clrf.corrections.ray_pose import camera_gradient, camera_gradients
    from clrf.references.reference_splat import look_at
    rng = np.random.default_rng(5)
    V = np.stack([look_at(rng.normal(size=3) * 3, (0, 0, 0)) for _ in range(4)])
    sums = rng.normal(size=(4, 13))
    dR, dt = camera_gradients(V, sums)
    for k in range(4):
        a, b = camera_gradient(V[k], sums[k])
        np.testing.assert_allclose(dR[k], a, atol=1e-14)
        np.testing.assert_allclose(dt[k], b, atol=1e-14)
