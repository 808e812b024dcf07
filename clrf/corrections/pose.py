"""A pose correction per training camera (``splat.pose_opt``), a camera correction of the protocol
in clrf/corrections/base.py: poses from structure from motion, more so from a video, are a
little off, and a scene fitted to slightly wrong cameras blurs.

Training camera v owns a rotation vector w_v and a translation tau_v (float64, on the host: six
numbers an image) that correct its world-to-camera transform [R0 t0] about a pivot p_v = (0, 0,
d_v) on its optical axis, d_v ahead (the depth of the scene's centre in that camera):

    R = Exp(w) R0,    t = Exp(w) (t0 - p) + p + tau,

a rotation of the camera's own frame about the pivot, then a shift (Exp: Rodrigues' formula).
Turning a camera about its own centre and shifting it sideways both slide the whole image, so in
those two coordinates the loss has a long narrow valley, which a per-coordinate optimiser such as
Adam walks slowly; about a pivot in the scene, w moves the image only by parallax around the
pivot and tau slides it, two nearly independent effects (d_v = 0 is the camera's centre).

The model's renderer gives dL/dR and dL/dt of the corrected camera (the splat model: the
projection's backward with POSE_GRAD=1, cl/splat_project.cl; clrf/splat/raster.py
``camera_gradient`` sums the Gaussians' shares on the device and reads twelve numbers). A
rotation phi of the frame about the pivot moves R to Exp(phi) R and t - tau - p to Exp(phi) (t -
tau - p), so with M = dL/dR R^T + dL/dt (t - tau - p)^T:

    dL/dphi = (M[2, 1] - M[1, 2], M[0, 2] - M[2, 0], M[1, 0] - M[0, 1]),
    dL/dw = J_l(w)^T dL/dphi,    dL/dtau = dL/dt,

J_l the left Jacobian of SO(3) (Exp(w + d) = Exp(J_l(w) d) Exp(w) to first order). A pull
``reg (|w|^2 + |tau / scale|^2)`` toward the identity keeps the corrections small (scale: the
scene's extent, so that the pull does not depend on the capture's units), and each image takes
an Adam step (its own step count; clrf/runtime/optim.py ``adam_host_step``) when it is trained:
rotations at ``lr`` radians, translations at ``lr * scale``, the rate falling log-linearly to
``lr_final`` over the budget where one is given (``schedule``).

The frame stays put (``hold_frame``, on by default). Images alone cannot tell a scene and all
its cameras from the same scene and cameras moved together by one rigid motion G of the world
and scaled by one factor e^s about the world's origin, so the corrections' common part is free:
left alone it drifts, the scene follows it, and the test views, which keep their given poses,
no longer fit the scene (a common scale moves every camera along the line to the origin, as a
camera's own translation does). After each pass over the views (``after_pass``) the common
similarity of the trained images' corrections is taken out, as the exposure rows' common gain
is: to first order a world twist (omega, nu) and a scale s move camera v's world-to-camera
[R_v t_v] by the camera-frame rotation R_v omega and shift R_v nu + t_v x (R_v omega) + s t_v,
so (omega, nu, s) is the least-squares fit of those to the corrections (rotation vector w_v,
shift of the corrected transform c_v; shifts over the scene's extent), and each trained image's
corrected transform C_v V_v becomes S(-s) C_v V_v G^-1 exactly (S(s): the translation times
e^s; ``common_motion``, ``remove_common_motion``; ``hold_scale=False`` keeps the scale). The
scene, which followed the drift by no more than a pass's steps,
stays in the given poses' frame. Each image's given transform V_v is the one it was last
rendered from (``camera``). Test views keep their given
poses, as published protocols evaluate them; ``clrf eval --refine-poses N`` also scores them
after N steps of a correction of their own against their own image, the scene held still
(``refine_view_pose`` in clrf/splat/model.py).

>>> pose = PoseCorrection(n_images=100, lr=1e-3, reg=1e-4, scale=4.0, pivots=depths)
>>> cam = pose.camera(cam0, v)                  # SplatCamera with view v's corrected viewmat
>>> pose.step(v, cam.viewmat, dR, dt)           # from raster.camera_gradient
>>> pose.summary()                               # mean rotation (degrees) and translation
"""
from __future__ import annotations

import dataclasses

import numpy as np

from ..runtime.optim import adam_host_step, expon_lr
from .base import CAMERA, VIEWS


FRAME_ITERATIONS = 3   # fits of the common motion a removal takes (each removes the last's
#                        second-order rest: 0.5 degrees leave 1e-5 of it, then 1e-10)


def hat(w) -> np.ndarray:
    """[w]x: the cross-product matrix, hat(w) @ x = w x x."""
    x, y, z = (float(c) for c in w)
    return np.array([[0.0, -z, y], [z, 0.0, -x], [-y, x, 0.0]])


def so3_exp(w) -> np.ndarray:
    """Exp(w): the rotation by |w| radians about w / |w| (Rodrigues; a series near 0)."""
    w = np.asarray(w, np.float64)
    th2 = float(w @ w)
    K = hat(w)
    if th2 < 1e-12:
        a, b = 1.0 - th2 / 6.0, 0.5 - th2 / 24.0
    else:
        th = np.sqrt(th2)
        a, b = np.sin(th) / th, (1.0 - np.cos(th)) / th2
    return np.eye(3) + a * K + b * (K @ K)


def left_jacobian(w) -> np.ndarray:
    """J_l(w) = I + (1 - cos th) / th^2 [w]x + (th - sin th) / th^3 [w]x^2, th = |w|."""
    w = np.asarray(w, np.float64)
    th2 = float(w @ w)
    K = hat(w)
    if th2 < 1e-12:
        a, b = 0.5 - th2 / 24.0, 1.0 / 6.0 - th2 / 120.0
    else:
        th = np.sqrt(th2)
        a, b = (1.0 - np.cos(th)) / th2, (th - np.sin(th)) / (th2 * th)
    return np.eye(3) + a * K + b * (K @ K)


def rotation_angle(R) -> float:
    """The angle of rotation matrix R, in radians (robust near 0 and pi)."""
    R = np.asarray(R, np.float64)
    s = 0.5 * np.linalg.norm([R[2, 1] - R[1, 2], R[0, 2] - R[2, 0], R[1, 0] - R[0, 1]])
    c = 0.5 * (np.trace(R) - 1.0)
    return float(np.arctan2(s, c))


def so3_log(R) -> np.ndarray:
    """w with Exp(w) = R (|w| <= pi), the inverse of ``so3_exp``."""
    R = np.asarray(R, np.float64)
    v = 0.5 * np.array([R[2, 1] - R[1, 2], R[0, 2] - R[2, 0], R[1, 0] - R[0, 1]])
    th = rotation_angle(R)
    s = np.sin(th)
    if th < 1e-6:
        return v * (1.0 + th * th / 6.0)
    if np.pi - th > 1e-4:
        return v * (th / s)
    # near a half turn: the axis from the symmetric part, R + R^T = 2 (cos th I + (1 - cos th)
    # a a^T), its sign from v
    B = 0.5 * (R + R.T) - np.cos(th) * np.eye(3)
    a = B[np.argmax(np.diag(B))]
    a = a / np.linalg.norm(a)
    return th * (a if a @ v >= 0 else -a)


def common_motion(viewmats, corrected, scale: float) -> tuple:
    """(omega, nu, s): the world similarity whose camera-frame motions best fit the corrections
    of given world-to-camera ``viewmats`` [n, 4, 4] to ``corrected`` [n, 4, 4] (module doc;
    shifts weighed over ``scale``), by linear least squares; s the log of its scale."""
    rows, rhs = [], []
    for V, Vc in zip(np.asarray(viewmats, np.float64), np.asarray(corrected, np.float64)):
        R, t = V[:3, :3], V[:3, 3]
        C = Vc @ np.linalg.inv(V)                # the correction, in the camera's frame
        rows.append(np.hstack([R, np.zeros((3, 4))]))
        rhs.append(so3_log(C[:3, :3]))
        rows.append(np.hstack([hat(t) @ R, R, t[:, None]]) / scale)
        rhs.append(C[:3, 3] / scale)
    x = np.linalg.lstsq(np.vstack(rows), np.concatenate(rhs), rcond=None)[0]
    return x[:3], x[3:6], float(x[6])


def twist_matrix(omega, nu) -> np.ndarray:
    """G = [Exp(omega) nu; 0 1], the rigid motion of the world a twist (omega, nu) stands for."""
    G = np.eye(4)
    G[:3, :3], G[:3, 3] = so3_exp(omega), np.asarray(nu, np.float64)
    return G


def similar_viewmat(viewmat, omega, nu, s: float) -> np.ndarray:
    """S(s) V G: world-to-camera ``viewmat`` V [4, 4] after the world moved by G =
    twist_matrix(omega, nu), its translation then scaled by e^s (S(s)): the camera that sees
    the world moved by G^-1, then scaled by e^s about its origin, as V saw it."""
    out = np.asarray(viewmat, np.float64) @ twist_matrix(omega, nu)
    out[:3, 3] *= np.exp(s)
    return out


def remove_similarity(corrected, omega, nu, s: float) -> np.ndarray:
    """The world-to-camera ``corrected`` [4, 4] with the similarity of ``similar_viewmat``
    taken out: S(-s) Vc G^-1 (its inverse, exact)."""
    out = np.asarray(corrected, np.float64).copy()
    out[:3, 3] *= np.exp(-s)
    return out @ np.linalg.inv(twist_matrix(omega, nu))


def pivot_point(pivot: float) -> np.ndarray:
    """p = (0, 0, pivot): the point on the optical axis a correction turns the camera about."""
    return np.array([0.0, 0.0, float(pivot)])


def corrected_viewmat(viewmat, w, tau, pivot: float = 0.0) -> np.ndarray:
    """[Exp(w) R0, Exp(w) (t0 - p) + p + tau] of world-to-camera ``viewmat`` [4, 4], p = (0, 0,
    pivot)."""
    V = np.asarray(viewmat, np.float64)
    E = so3_exp(w)
    p = pivot_point(pivot)
    out = np.eye(4)
    out[:3, :3] = E @ V[:3, :3]
    out[:3, 3] = E @ (V[:3, 3] - p) + p + np.asarray(tau, np.float64)
    return out


def pose_gradient(viewmat, w, tau, dR, dt, pivot: float = 0.0) -> tuple:
    """(dL/dw, dL/dtau) from dL/dR, dL/dt of the corrected camera ``viewmat`` (module doc)."""
    V = np.asarray(viewmat, np.float64)
    R, t = V[:3, :3], V[:3, 3]
    arm = t - np.asarray(tau, np.float64) - pivot_point(pivot)
    M = np.asarray(dR, np.float64) @ R.T + np.outer(dt, arm)
    g_phi = np.array([M[2, 1] - M[1, 2], M[0, 2] - M[2, 0], M[1, 0] - M[0, 1]])
    return left_jacobian(w).T @ g_phi, np.asarray(dt, np.float64).copy()


def hats(w) -> np.ndarray:
    """[k, 3, 3]: ``hat`` of each row of w [k, 3]."""
    w = np.asarray(w, np.float64)
    K = np.zeros(w.shape[:-1] + (3, 3))
    K[..., 0, 1], K[..., 0, 2], K[..., 1, 2] = -w[..., 2], w[..., 1], -w[..., 0]
    K[..., 1, 0], K[..., 2, 0], K[..., 2, 1] = w[..., 2], -w[..., 1], w[..., 0]
    return K


def _series(w, small, large):
    """(a, b) [k, 1, 1] of the rows of w [k, 3]: ``small(th2)`` below th^2 = 1e-12, else
    ``large(th, th2)`` (the scalar functions' branches, row by row)."""
    th2 = np.einsum("ki,ki->k", w, w)
    near = th2 < 1e-12
    th = np.sqrt(np.where(near, 1.0, th2))
    a0, b0 = small(th2)
    a1, b1 = large(th, np.where(near, 1.0, th2))
    return (np.where(near, a0, a1)[:, None, None], np.where(near, b0, b1)[:, None, None])


def so3_exps(w) -> np.ndarray:
    """[k, 3, 3]: ``so3_exp`` of each row of w [k, 3]."""
    w = np.asarray(w, np.float64).reshape(-1, 3)
    K = hats(w)
    a, b = _series(w, lambda t2: (1.0 - t2 / 6.0, 0.5 - t2 / 24.0),
                   lambda th, t2: (np.sin(th) / th, (1.0 - np.cos(th)) / t2))
    return np.eye(3) + a * K + b * (K @ K)


def left_jacobians(w) -> np.ndarray:
    """[k, 3, 3]: ``left_jacobian`` of each row of w [k, 3]."""
    w = np.asarray(w, np.float64).reshape(-1, 3)
    K = hats(w)
    a, b = _series(w, lambda t2: (0.5 - t2 / 24.0, 1.0 / 6.0 - t2 / 120.0),
                   lambda th, t2: ((1.0 - np.cos(th)) / t2, (th - np.sin(th)) / (t2 * th)))
    return np.eye(3) + a * K + b * (K @ K)


def corrected_viewmats(viewmats, w, tau, pivots) -> np.ndarray:
    """[k, 4, 4]: ``corrected_viewmat`` of each of viewmats [k, 4, 4] with its row of w, tau
    [k, 3] and pivots [k]."""
    V = np.asarray(viewmats, np.float64).reshape(-1, 4, 4)
    E = so3_exps(w)
    p = np.zeros((len(V), 3))
    p[:, 2] = np.asarray(pivots, np.float64).reshape(-1)
    out = np.broadcast_to(np.eye(4), V.shape).copy()
    out[:, :3, :3] = E @ V[:, :3, :3]
    out[:, :3, 3] = np.einsum("kij,kj->ki", E, V[:, :3, 3] - p) + p + np.asarray(tau)
    return out


def pose_gradients(viewmats, w, tau, dR, dt, pivots) -> tuple:
    """(dL/dw, dL/dtau) [k, 3] each: ``pose_gradient`` of each corrected camera of viewmats
    [k, 4, 4] with its rows of w, tau, dR [k, 3, 3], dt [k, 3] and pivots [k]."""
    V = np.asarray(viewmats, np.float64).reshape(-1, 4, 4)
    dt = np.asarray(dt, np.float64).reshape(-1, 3)
    arm = V[:, :3, 3] - np.asarray(tau, np.float64)
    arm[:, 2] -= np.asarray(pivots, np.float64).reshape(-1)
    M = np.asarray(dR, np.float64) @ np.transpose(V[:, :3, :3], (0, 2, 1)) \
        + dt[:, :, None] * arm[:, None, :]
    g_phi = np.stack([M[:, 2, 1] - M[:, 1, 2], M[:, 0, 2] - M[:, 2, 0],
                      M[:, 1, 0] - M[:, 0, 1]], axis=1)
    return np.einsum("kji,kj->ki", left_jacobians(w), g_phi), dt.copy()


def _frame_report(summary: dict) -> str:
    """'; a common motion of 0.41 deg, 0.2 % of the extent and a scale of +0.1 % taken out
    (the frame held)'."""
    if not summary.get("frame_held"):
        return ""
    return (f"; a common motion of {summary['frame_rotation_deg']:.3f} deg, "
            f"{100 * summary['frame_translation_rel']:.2f} % of the extent and a scale of "
            f"{100 * summary.get('frame_scale_rel', 0.0):+.2f} % taken out (the frame held)")


class PoseCorrection:
    """The corrections of ``n_images`` training cameras (module doc)."""
    name = "pose"
    changes = CAMERA
    batches = VIEWS

    def __init__(self, n_images: int, lr: float, reg: float, scale: float,
                 state: dict | None = None, pivots=None, lr_final: float | None = None,
                 hold_frame: bool = True, start: float = 0.0, hold_scale: bool = True):
        if n_images < 1:
            raise ValueError(f"PoseCorrection needs at least one image, got {n_images}")
        if not (lr > 0 and reg >= 0 and scale > 0):
            raise ValueError(f"PoseCorrection: lr > 0, reg >= 0 and scale > 0, got {lr}, "
                             f"{reg}, {scale}")
        self.n_images = int(n_images)
        self.lr, self.reg, self.scale = float(lr), float(reg), float(scale)
        self.lr_start = self.lr
        self.lr_final = None if lr_final is None else float(lr_final)
        self.params = np.zeros((self.n_images, 6))     # (w, tau) of each image
        self.m = np.zeros((self.n_images, 6))
        self.v = np.zeros((self.n_images, 6))
        self.steps = np.zeros(self.n_images, np.int64)
        self.hold_frame = bool(hold_frame)
        if not 0.0 <= start < 1.0:
            raise ValueError(f"PoseCorrection: start must be in [0, 1), got {start}")
        self.start, self.progress = float(start), 0.0    # no step before the fraction start
        self.given = {}                     # image -> its given world-to-camera (``camera``)
        self.frame = np.zeros(6)            # the common motion taken out so far (omega, nu)
        self.hold_scale = bool(hold_scale)  # the common scale too (module doc)
        self.frame_scale = 0.0              # the log of the common scale taken out so far
        # each image's pivot depth d_v (module doc); a checkpoint's own wins over ``pivots``,
        # and one written before pivots existed turned its cameras about their centres (0)
        self.pivots = np.zeros(self.n_images)
        if pivots is not None:
            self.pivots = np.asarray(pivots, np.float64).reshape(self.n_images).copy()
        if not np.all(np.isfinite(self.pivots)) or (self.pivots < 0).any():
            raise ValueError("PoseCorrection: the pivot depths must be finite and >= 0")
        if state is not None:
            for key, attr, shape in (("pose", "params", (self.n_images, 6)),
                                     ("pose_m", "m", (self.n_images, 6)),
                                     ("pose_v", "v", (self.n_images, 6))):
                setattr(self, attr, np.asarray(state[key], np.float64).reshape(shape).copy())
            self.steps = np.asarray(state["pose_steps"], np.int64).reshape(self.n_images).copy()
            self.pivots = (np.asarray(state["pose_pivot"], np.float64).reshape(self.n_images)
                           .copy() if "pose_pivot" in state else np.zeros(self.n_images))
            if "pose_frame" in state:
                self.frame = np.asarray(state["pose_frame"], np.float64).reshape(6).copy()
            if "pose_frame_scale" in state:
                self.frame_scale = float(np.asarray(state["pose_frame_scale"]).reshape(-1)[0])

    def viewmat(self, viewmat, v: int) -> np.ndarray:
        """Image v's corrected world-to-camera [4, 4]."""
        p = self.params[int(v)]
        return corrected_viewmat(viewmat, p[:3], p[3:], self.pivots[int(v)])

    def camera(self, cam, v: int):
        """``cam`` (a SplatCamera with image v's given pose) with the corrected pose."""
        self.given[int(v)] = np.asarray(cam.viewmat, np.float64)
        return dataclasses.replace(cam, viewmat=self.viewmat(cam.viewmat, v))

    def set_viewmat(self, v: int, viewmat, corrected) -> None:
        """Image v's correction set to the one that takes its given ``viewmat`` to
        ``corrected`` (both world-to-camera [4, 4]): w = Log(C_R), tau = C_t + C_R p - p for
        C = corrected viewmat^-1."""
        C = np.asarray(corrected, np.float64) @ np.linalg.inv(np.asarray(viewmat, np.float64))
        p = pivot_point(self.pivots[int(v)])
        self.params[int(v)] = np.concatenate([so3_log(C[:3, :3]),
                                              C[:3, 3] + C[:3, :3] @ p - p])

    def remove_common_motion(self) -> np.ndarray:
        """Takes the trained images' common motion and scale out of their corrections (module
        doc); returns the rigid part (omega, nu) (the scale's log is added to ``frame_scale``)."""
        idx = [v for v in sorted(self.given) if self.steps[v] > 0]
        if not idx:
            return np.zeros(6)
        given = [self.given[v] for v in idx]
        # what the fits take out in all, Vc -> S(-log_scale)(Vc) K^-1: S(a)(X H) = S(a)(X) H'
        # with H's translation times e^a, so each fit scales the K^-1 before it
        k_inv, log_scale = np.eye(4), 0.0
        for _ in range(FRAME_ITERATIONS):    # the fit is linear: a second pass is exact to
            corrected = [self.viewmat(V, v) for V, v in zip(given, idx)]   # float64 rounding
            omega, nu, s = common_motion(given, corrected, self.scale)
            if not self.hold_scale:
                s = 0.0
            for V, Vc, v in zip(given, corrected, idx):
                self.set_viewmat(v, V, remove_similarity(Vc, omega, nu, s))
            k_inv[:3, 3] *= np.exp(-s)
            k_inv = k_inv @ np.linalg.inv(twist_matrix(omega, nu))
            log_scale += s
        total = np.linalg.inv(k_inv)
        out = np.concatenate([so3_log(total[:3, :3]), total[:3, 3]])
        self.frame += out
        self.frame_scale += log_scale
        return out

    def gradient(self, v: int, viewmat, dR, dt) -> np.ndarray:
        """dL/d(w, tau) of image v, the pull toward the identity included, from dL/dR, dL/dt of
        its corrected camera ``viewmat``."""
        p = self.params[int(v)]
        gw, gtau = pose_gradient(viewmat, p[:3], p[3:], dR, dt, self.pivots[int(v)])
        gw = gw + 2.0 * self.reg * p[:3]
        gtau = gtau + 2.0 * self.reg * p[3:] / self.scale ** 2
        return np.concatenate([gw, gtau])

    def step(self, v: int, viewmat, dR, dt):
        """One Adam step of image v's correction (rotations at lr radians, translations at
        lr * scale)."""
        v = int(v)
        if self.progress < self.start:
            return   # the scene forms first (``start``)
        g = self.gradient(v, viewmat, dR, dt)
        if not np.all(np.isfinite(g)):
            return   # a non-finite gradient leaves the pose as it was (the loss reports it)
        self.steps[v] += 1
        lr = np.array([self.lr] * 3 + [self.lr * self.scale] * 3)
        adam_host_step(self.params[v], self.m[v], self.v[v], g, int(self.steps[v]), lr)

    def viewmats(self, viewmats, vs) -> np.ndarray:
        """[k, 4, 4]: the corrected world-to-camera of images vs [k] from their given
        ``viewmats`` [k, 4, 4] (``viewmat``, all at once)."""
        vs = np.asarray(vs, np.int64).reshape(-1)
        p = self.params[vs]
        return corrected_viewmats(viewmats, p[:, :3], p[:, 3:], self.pivots[vs])

    def step_many(self, vs, viewmats, dR, dt) -> None:
        """``step`` of each image of vs [k] (distinct) at once, from its corrected camera
        ``viewmats`` [k, 4, 4] and dL/dR [k, 3, 3], dL/dt [k, 3]: the same Adam steps (the
        models whose batches touch hundreds of images a step)."""
        if self.progress < self.start:
            return
        vs = np.asarray(vs, np.int64).reshape(-1)
        p = self.params[vs]
        gw, gtau = pose_gradients(viewmats, p[:, :3], p[:, 3:], dR, dt, self.pivots[vs])
        g = np.concatenate([gw + 2.0 * self.reg * p[:, :3],
                            gtau + 2.0 * self.reg * p[:, 3:] / self.scale ** 2], axis=1)
        ok = np.all(np.isfinite(g), axis=1)  # a non-finite gradient leaves its pose as it was
        vs, g = vs[ok], g[ok]
        if not len(vs):
            return
        self.steps[vs] += 1
        lr = np.array([self.lr] * 3 + [self.lr * self.scale] * 3)
        param, m, v = self.params[vs], self.m[vs], self.v[vs]
        adam_host_step(param, m, v, g, self.steps[vs][:, None].astype(np.float64), lr)
        self.params[vs], self.m[vs], self.v[vs] = param, m, v

    @property
    def trains(self) -> bool:
        """Whether ``step`` moves a pose now: from the budget fraction ``start`` on."""
        return self.progress >= self.start

    def schedule(self, progress: float) -> None:
        """The rate at the budget fraction ``progress``: log-linear from its first rate to
        ``lr_final`` (unchanged without one); before the fraction ``start`` no step."""
        self.progress = float(progress)
        if self.lr_final is not None:
            self.lr = expon_lr(progress, self.lr_start, self.lr_final, 1.0)

    def after_pass(self) -> None:
        """With ``hold_frame``: the common motion taken out (``remove_common_motion``)."""
        if self.hold_frame:
            self.remove_common_motion()

    def state_dict(self) -> dict:
        return {"pose": self.params.copy(), "pose_m": self.m.copy(), "pose_v": self.v.copy(),
                "pose_steps": self.steps.copy(), "pose_pivot": self.pivots.copy(),
                "pose_frame": self.frame.copy(),
                "pose_frame_scale": np.array([self.frame_scale])}

    def centre_shift(self, v: int) -> float:
        """How far image v's correction moved its camera's centre: in the given camera's frame
        the corrected centre is p - Exp(w)^T (p + tau)."""
        w, tau = self.params[int(v), :3], self.params[int(v), 3:]
        p = pivot_point(self.pivots[int(v)])
        return float(np.linalg.norm(p - so3_exp(w).T @ (p + tau)))

    def summary(self, trained=None) -> dict:
        """The mean correction over the trained images (those that took a step, or the indices
        ``trained``): rotation in degrees, translation (how far the camera centre moved) in
        scene units and relative to the scene's extent."""
        idx = np.flatnonzero(self.steps > 0) if trained is None else np.asarray(trained)
        if len(idx) == 0:
            return {"images": 0, "rotation_deg": 0.0, "translation": 0.0,
                    "translation_rel": 0.0}
        rot = [np.degrees(np.linalg.norm(self.params[i, :3])) for i in idx]
        tr = [self.centre_shift(i) for i in idx]
        return {"images": int(len(idx)), "rotation_deg": float(np.mean(rot)),
                "translation": float(np.mean(tr)),
                "translation_rel": float(np.mean(tr) / self.scale),
                "frame_held": self.hold_frame,
                "frame_rotation_deg": float(np.degrees(np.linalg.norm(self.frame[:3]))),
                "frame_translation_rel": float(np.linalg.norm(self.frame[3:]) / self.scale),
                "frame_scale_rel": float(np.expm1(self.frame_scale))}

    def report(self, summary: dict) -> str:
        """The sentence ``clrf eval`` prints of ``summary``."""
        return (f"training poses corrected by {summary['rotation_deg']:.3f} deg and "
                f"{summary['translation']:.4g} ({100 * summary['translation_rel']:.2f} % of "
                f"the scene's extent) on average over {summary['images']} images (the test "
                f"views keep theirs)" + _frame_report(summary))

    def describe(self) -> str:
        """'poses corrected by 0.42 deg, 0.3 % of the scene' for progress lines."""
        s = self.summary()
        return (f"poses corrected by {s['rotation_deg']:.2f} deg, "
                f"{100 * s['translation_rel']:.2f} % of the scene")
