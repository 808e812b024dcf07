"""A pose correction per training camera for models whose batches mix rays of many images
(``hash.pose_opt``, ``nerf.pose_opt``): the maths of clrf/corrections/pose.py (a rotation
vector and a translation about a pivot per image, its Adam step on the host), on rays
(cl/ray_pose.cl).

Ray i of a batch comes from training image v = index[i] // pixels; the ray store holds it as the
given camera [R0 t0] (world-to-camera, OpenCV axes) made it. Each step the rays are remade
from each image's corrected camera [R t] (``rays``: o = -R^T t, d = R^T R0 d0), the model gives
each ray's dL/do, dL/dd (cl/hash_march.cl packed_ray_grad; NeRF: cl/sample.cl
ray_points_backward), and the device sums them per image
(S_d = sum_i d_i dL/dd_i^T, S_o = sum_i dL/do_i) so that

    dL/dR = R S_d - t S_o^T,    dL/dt = -R S_o                    (``camera_gradient``)

come back as twelve numbers a touched image; PoseCorrection turns them into dL/dw, dL/dtau and
steps each image that had rays in the batch. Under NDC (forward-facing scenes) the store's rays
are not the camera's, so the correction is refused there (clrf/hash/kind.py,
clrf/nerf/kind.py). ``viewmat_of`` and ``pivot_depth`` give the models' kinds the store's
cameras and their pivots.

``refine_view_pose`` is the same correction of one test camera at evaluation time (``clrf eval
--refine-poses N``, BARF's protocol): a one-image RayPose stepped against the view's own image
from each ray's dL/d(o, d) of a model held still (the model's ``ray_loss_grad``).

>>> pose = RayPose(dev, viewmats0, pixels=400 * 400, lr=1e-3, reg=1e-4, scale=4.0,
...                pivots=depths)
>>> o_d, d_d = pose.rays(index_d, o0_d, d0_d)      # the batch from the corrected cameras
>>> pose.step_rays(index_d, d_d, ray_grad_d)       # one Adam step of each touched image
"""
from __future__ import annotations

import numpy as np

from ..runtime.programs import download, launch, scratch, upload
from ..runtime.validate import check_array
from .base import CAMERA, RAYS
from .pose import PoseCorrection

LOCAL = 64   # work-items per image of ray_pose_sums (cl/ray_pose.cl RAY_POSE_LS)
SUMS = 13    # floats per image of ray_pose_sums: S_d (9), S_o (3), the ray count


def program(device):
    """cl/ray_pose.cl on ``device`` (clrf/hash/kind.py lists it)."""
    return device.program("ray_pose.cl", {"RAY_POSE_LS": LOCAL})


def camera_gradient(viewmat, sums) -> tuple:
    """(dL/dR [3, 3], dL/dt [3]) of the camera ``viewmat`` [4, 4] that made the rays whose
    per-image sums are ``sums`` [13] (module doc)."""
    V = np.asarray(viewmat, np.float64)
    R, t = V[:3, :3], V[:3, 3]
    s = np.asarray(sums, np.float64)
    S_d, S_o = s[:9].reshape(3, 3), s[9:12]
    return R @ S_d - np.outer(t, S_o), -R @ S_o


def camera_gradients(viewmats, sums) -> tuple:
    """``camera_gradient`` of k cameras at once: (dL/dR [k, 3, 3], dL/dt [k, 3]) from
    viewmats [k, 4, 4] and sums [k, 13]."""
    V = np.asarray(viewmats, np.float64).reshape(-1, 4, 4)
    s = np.asarray(sums, np.float64).reshape(len(V), -1)
    R, t = V[:, :3, :3], V[:, :3, 3]
    S_d, S_o = s[:, :9].reshape(-1, 3, 3), s[:, 9:12]
    return (R @ S_d - t[:, :, None] * S_o[:, None, :],
            -np.einsum("kij,kj->ki", R, S_o))


def ray_rows(viewmats0, viewmats) -> np.ndarray:
    """float32 [V, 12]: per image A = R^T R0 (row-major) and the centre c = -R^T t of given
    viewmats0 [V, 4, 4] and corrected viewmats [V, 4, 4] (world-to-camera)."""
    V0, V = np.asarray(viewmats0, np.float64), np.asarray(viewmats, np.float64)
    A = np.einsum("vji,vjk->vik", V[:, :3, :3], V0[:, :3, :3])
    c = -np.einsum("vji,vj->vi", V[:, :3, :3], V[:, :3, 3])
    return np.ascontiguousarray(np.concatenate([A.reshape(-1, 9), c], axis=1), np.float32)


def apply_rays(device, index, pixels: int, rows, o0, d0):
    """(o, d) [n, 3] device: the rays o0/d0 [n, 3] (device) moved by their images' rows
    ([V, 12] device, ``ray_rows``)."""
    n = int(o0.shape[0])
    o, d = scratch(device, (max(n, 1), 3)), scratch(device, (max(n, 1), 3))
    launch(device, program(device).kernel("ray_pose_apply"), n,
           (np.int32(n), np.int32(pixels), index.data, rows.data, o0.data, d0.data, o.data,
            d.data), device.tuning.elementwise_local_size)
    return o[:n], d[:n]


def ray_sums(device, index, pixels: int, d, ray_grad, n_images: int):
    """[V, 13] device: per image S_d (row-major), S_o and its ray count over the batch's rays
    (index [n] int32, d [n, 3], ray_grad [n, 6] = dL/d(o, d); module doc)."""
    n = int(d.shape[0])
    out = scratch(device, (n_images, SUMS))
    launch(device, program(device).kernel("ray_pose_sums"), n_images * LOCAL,
           (np.int32(n), np.int32(pixels), index.data, d.data, ray_grad.data, out.data),
           local_size=LOCAL)
    return out


OPENGL_TO_OPENCV = np.diag([1.0, -1.0, -1.0, 1.0])   # the datasets' camera axes to viewmats'


def viewmat_of(c2w) -> np.ndarray:
    """World-to-camera (OpenCV axes) of a camera-to-world pose in OpenGL axes (the cameras of
    the ray store's rays)."""
    c2w = np.asarray(c2w, np.float64)
    full = np.eye(4)
    full[:c2w.shape[0]] = c2w
    return OPENGL_TO_OPENCV @ np.linalg.inv(full)


def pivot_depth(viewmat, bbox) -> float:
    """The depth of the box's centre in camera ``viewmat`` (0 where it lies behind): the point
    a pose correction turns the camera about (clrf/corrections/pose.py)."""
    centre = np.append(np.asarray(bbox, np.float64).mean(0), 1.0)
    return max(float((viewmat @ centre)[2]), 0.0)


FRAME_EVERY = 100   # steps between removals of the corrections' common motion (a ray batch
#                     mixes every image, so there is no pass; the exposure rows' recentring
#                     has the same rhythm)


class RayPose:
    """The pose corrections of ``n_images`` training cameras (given world-to-camera
    ``viewmats0`` [V, 4, 4], OpenCV axes) of ``pixels`` pixels each, for a model whose batches
    mix rays of many images (module doc): a PoseCorrection (the corrections, their Adam and
    pull, on the host) and the rows [V, 12] of the corrected cameras on the device."""
    name = "pose"
    changes = CAMERA
    batches = RAYS

    def __init__(self, device, viewmats0, pixels: int, lr: float, reg: float, scale: float,
                 pivots=None, lr_final: float | None = None, state: dict | None = None,
                 hold_frame: bool = True, start: float = 0.0, every: int = 1,
                 min_rays: int = 0):
        if state is not None:
            viewmats0 = state["pose_viewmats"]
            pixels = int(state["pose_pixels"])
        self.viewmats0 = np.asarray(viewmats0, np.float64).reshape(-1, 4, 4).copy()
        if pixels < 1 or not np.all(np.isfinite(self.viewmats0)):
            raise ValueError(f"RayPose needs finite viewmats and pixels >= 1, got {pixels}")
        self.device = device
        self.pixels = int(pixels)
        self.pose = PoseCorrection(len(self.viewmats0), lr, reg, scale, state=state,
                                   pivots=pivots, lr_final=lr_final, hold_frame=hold_frame,
                                   start=start)
        self.pose.given = dict(enumerate(self.viewmats0))   # every image's given camera
        self.steps = 0
        self.every = int(every)    # training steps a camera step (pose_opt_every)
        self.calls = 0             # training steps seen (gradient_due)
        # rays an image gathers before its step (pose_opt_rays; 0: a step every batch it is
        # in): its sums add up over the batches, at a pose that holds still meanwhile
        self.min_rays = int(min_rays)
        n = len(self.viewmats0)
        self.gathered = np.zeros((n, SUMS))
        if state is not None and state.get("pose_gathered") is not None:
            self.gathered = np.asarray(state["pose_gathered"], np.float64).reshape(
                n, SUMS).copy()
        self.n_images = self.pose.n_images
        self.rows = upload(device.queue, ray_rows(self.viewmats0, self.viewmats()))

    def viewmats(self) -> np.ndarray:
        """[V, 4, 4] every image's corrected world-to-camera."""
        return self.pose.viewmats(self.viewmats0, np.arange(self.n_images))

    def rays(self, index, origins, dirs):
        """(origins, dirs) [n, 3] device: the batch as the corrected cameras make it."""
        return apply_rays(self.device, index, self.pixels, self.rows, origins, dirs)

    @property
    def trains(self) -> bool:
        """False before the budget fraction ``start`` (the corrections are all zero then)."""
        return self.pose.trains

    def gradient_due(self) -> bool:
        """Whether this training step forms the cameras' gradient and steps them: one step in
        ``every`` (``pose_opt_every``: the rest use the corrected cameras without their
        gradient's pass). Counts the step."""
        due = self.calls % self.every == 0
        self.calls += 1
        return due

    def step_rays(self, index, dirs, ray_grad) -> None:
        """One Adam step of each image with rays in the batch (PoseCorrection.step), from the
        rays' corrected directions and dL/d(o, d); the rows are then remade. With
        ``min_rays``, an image's sums are gathered over batches and it steps once they hold
        that many rays: a gradient of that many rays, not of the one or two that a batch of
        a capture with hundreds of images gives it."""
        sums = download(ray_sums(self.device, index, self.pixels, dirs, ray_grad,
                                 self.n_images))
        if self.min_rays > 0:
            self.gathered += sums
            sums = self.gathered
        touched = np.flatnonzero(sums[:, SUMS - 1] >= max(self.min_rays, 1))
        if len(touched):   # every touched image's step at once (hundreds a batch)
            vm = self.pose.viewmats(self.viewmats0[touched], touched)
            dR, dt = camera_gradients(vm, sums[touched])
            self.pose.step_many(touched, vm, dR, dt)
            if self.min_rays > 0:
                self.gathered[touched] = 0.0
        self.steps += 1
        held = self.pose.hold_frame and self.steps % FRAME_EVERY == 0
        if held:
            self.pose.remove_common_motion()     # the frame held (clrf/corrections/pose.py)
        if len(touched) or held:
            self.rows.set(ray_rows(self.viewmats0, self.viewmats()))

    def schedule(self, progress: float) -> None:
        self.pose.schedule(progress)

    def after_pass(self) -> None:
        """Nothing: there is no pass; the frame is held every FRAME_EVERY steps instead
        (``step_rays``)."""

    def state_dict(self) -> dict:
        return {**self.pose.state_dict(), "pose_viewmats": self.viewmats0.copy(),
                "pose_pixels": self.pixels, "pose_gathered": self.gathered.copy()}

    def summary(self, trained=None) -> dict:
        return self.pose.summary(trained)

    def report(self, summary: dict) -> str:
        return self.pose.report(summary)

    def describe(self) -> str:
        return self.pose.describe()


REFINE_BATCH = 4096   # rays a step of a test view's refinement by default (the models pass
#                       their training batch: HashModel / GridModel.refine_view_pose)


def refine_view_pose(device, ray_loss_grad, c2w, rays, image, steps: int, lr: float, bbox,
                     scale: float, batch: int = REFINE_BATCH, seed: int = 0):
    """Test-time pose refinement of one camera for a model whose batches are rays (BARF's
    protocol for runs that refine their poses; ``clrf eval --refine-poses``): ``steps`` Adam
    steps of a correction of this one camera (clrf/corrections/pose.py: turned about the depth
    of the centre of the box ``bbox`` [2, 3], translations relative to ``scale``, no pull toward
    the given pose, the frame free) against ``image`` [H, W, 3], the rate falling log-linearly
    from ``lr`` to a tenth of it over the steps, as the splat model's ``refine_view_pose``.

    ``c2w``: the given camera-to-world [4, 4] or [3, 4] (OpenGL axes); ``rays``: a callable
    returning (origins, dirs) [H W, 3] of every pixel of that camera, row by row, as the
    trainer's ray store makes them (clrf/data/cameras.py view_rays; not NDC rays).

    Each step draws ``batch`` of the pixels (with replacement, from a generator seeded with
    ``seed``: a call's draws are the same every time; every pixel once a step where the view
    has no more than ``batch``), remakes their rays from the corrected camera
    (``RayPose.rays``), takes each ray's dL/d(origin, direction) [B, 6] (device float32) of the
    model's training loss from ``ray_loss_grad(origins, dirs, target)`` (device [B, 3] each;
    the model held still) and steps (``RayPose.step_rays``).

    Returns (the corrected camera-to-world [4, 4], OpenGL axes; the correction's summary,
    PoseCorrection.summary of the one image: ``rotation_deg``, ``translation_rel``, ...)."""
    if steps < 1 or not lr > 0 or batch < 1:
        raise ValueError(f"refine_view_pose: steps >= 1, lr > 0 and batch >= 1, got {steps}, "
                         f"{lr}, {batch}")
    if not callable(rays):
        raise ValueError("refine_view_pose: rays must be a callable returning the camera's "
                         "origins, dirs [H W, 3]")
    target = check_array("image", image, ndim=3, shape_tail=(3,)).reshape(-1, 3)
    n = len(target)
    o0, d0 = rays()
    o0 = check_array("origins", o0, ndim=2, shape_tail=(3,))
    d0 = check_array("dirs", d0, ndim=2, shape_tail=(3,))
    if len(o0) != n or len(d0) != n or n == 0:
        raise ValueError(f"refine_view_pose: a ray per pixel of the image, got {len(o0)} "
                         f"origins and {len(d0)} directions for {n} pixels")
    vm0 = viewmat_of(c2w)
    pose = RayPose(device, vm0[None], n, lr, 0.0, scale, pivots=[pivot_depth(vm0, bbox)],
                   lr_final=0.1 * lr, hold_frame=False)
    q = device.queue
    rng = np.random.default_rng(seed)
    every = n <= batch
    if every:
        index, o_b, d_b, t_b = (upload(q, a) for a in (np.arange(n, dtype=np.int32), o0, d0,
                                                        target))
    for k in range(int(steps)):
        pose.schedule(k / max(int(steps) - 1, 1))
        if not every:
            pixels = rng.integers(0, n, int(batch))
            index, o_b, d_b, t_b = (upload(q, a) for a in (pixels.astype(np.int32), o0[pixels],
                                                            d0[pixels], target[pixels]))
        o, d = pose.rays(index, o_b, d_b)
        pose.step_rays(index, d, ray_loss_grad(o, d, t_b))
    V = pose.viewmats()[0]
    return np.linalg.inv(OPENGL_TO_OPENCV @ V), pose.summary([0])
