"""The built-in procedural scene: analytic opaque objects rendered exactly by a numpy ray tracer.

It is the default scene of ``clrf train`` with no data, and a scene with exact ground truth for
tests: each ray gets the colour of the first surface it hits (or the white background),
computed in closed form, so tests can check pixels by hand. A dataset pixel is the mean of
``supersample`` x ``supersample`` rays spread evenly over it (4 x 4 by default, as a camera
integrates over its pixel; 1: the centre ray alone). With centre rays only, the silhouettes
are aliased: a pixel on an edge is all object or all background depending on where its
centre falls, which no smooth volume reproduces from other views, and the default run stalled
near 30 dB with two thirds of its test error on those edges (34.6 dB at 900 steps with 4 x 4).

The scene (world z up, everything inside [-1.5, 1.5]^3):

====  ========  =========================================  ==========================
id    kind      geometry                                   albedo a (RGB)
====  ========  =========================================  ==========================
0     sphere    centre (0, 0, 0), radius 0.6               (0.70, 0.25, 0.20)
1     sphere    centre (0.85, -0.65, -0.35), radius 0.35   (0.20, 0.45, 0.70)
2     box       [-1.0, -0.4] x [0.2, 0.8] x [-0.7, -0.1]   (0.25, 0.65, 0.30)
3     box       [-1.2, 1.2] x [-1.2, 1.2] x [-0.9, -0.7]   (0.55, 0.50, 0.45)   (a floor slab)
====  ========  =========================================  ==========================

Colour of object k at surface point p seen along the unit ray direction d (per channel c)::

    rgb_c = a_kc * (0.7 + 0.3 * sin(w_k * (g_k . p) + phi_c)) + s_k * (0.5 + 0.5 * (d . v_k))

a smooth function of position plus a view-dependent term linear in d (so SH degree 1 can
represent it exactly). With a <= 0.7 and s <= 0.25 every value lies in [0, 1) without clipping.
The random ``seed`` only jitters the camera orbit, never the scene.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from .cameras import look_at, pixel_rays
from .base import Dataset

BLENDER_CAMERA_ANGLE_X = 0.6911112070083618   # the Blender scenes' horizontal field of view
ORBIT_RADIUS = 4.0
PHASES = np.array([0.0, 2.0 * np.pi / 3.0, 4.0 * np.pi / 3.0])   # phi_c: one phase per channel
BASE, SWING = 0.7, 0.3                        # base colour factor = BASE + SWING * sin(...)
VIEW_MID, VIEW_SWING = 0.5, 0.5               # view factor = VIEW_MID + VIEW_SWING * (d . v)


@dataclass
class Sphere:
    center: tuple
    radius: float


@dataclass
class Box:
    lo: tuple
    hi: tuple


@dataclass
class Material:
    albedo: tuple        # a_k, RGB
    freq: float          # w_k
    grad: tuple          # g_k (unit vector)
    spec: float          # s_k
    view: tuple          # v_k (unit vector)


def _unit(v):
    v = np.asarray(v, np.float64)
    return tuple(v / np.linalg.norm(v))


@dataclass
class ProceduralScene:
    """Analytic objects with materials; :meth:`trace` is the exact renderer."""

    shapes: list = field(default_factory=lambda: [
        Sphere((0.0, 0.0, 0.0), 0.6),
        Sphere((0.85, -0.65, -0.35), 0.35),
        Box((-1.0, 0.2, -0.7), (-0.4, 0.8, -0.1)),
        Box((-1.2, -1.2, -0.9), (1.2, 1.2, -0.7)),
    ])
    materials: list = field(default_factory=lambda: [
        Material((0.70, 0.25, 0.20), 4.0, _unit((1, 1, 1)), 0.25, _unit((0, 0, 1))),
        Material((0.20, 0.45, 0.70), 6.0, _unit((0, 1, 0)), 0.20, _unit((1, 0, 1))),
        Material((0.25, 0.65, 0.30), 5.0, _unit((1, 0, 0)), 0.15, _unit((0, 1, 1))),
        Material((0.55, 0.50, 0.45), 3.0, _unit((1, -1, 0)), 0.10, _unit((1, 0, 0))),
    ])
    background: tuple = (1.0, 1.0, 1.0)

    def color(self, k: int, points, dirs) -> np.ndarray:
        """rgb [n, 3] of object ``k`` at surface ``points`` [n, 3] seen along unit ``dirs``."""
        m = self.materials[k]
        p = np.asarray(points, np.float64)
        d = np.asarray(dirs, np.float64)
        phase = m.freq * (p @ np.asarray(m.grad))[:, None] + PHASES        # [n, 3]
        base = np.asarray(m.albedo) * (BASE + SWING * np.sin(phase))
        view = m.spec * (VIEW_MID + VIEW_SWING * (d @ np.asarray(m.view)))
        return base + view[:, None]

    @staticmethod
    def _hit_sphere(s: Sphere, o, d):
        oc = o - np.asarray(s.center)
        b = np.einsum("ij,ij->i", d, oc)
        c = np.einsum("ij,ij->i", oc, oc) - s.radius ** 2
        disc = b * b - c
        root = np.sqrt(np.maximum(disc, 0.0))
        t_near, t_far = -b - root, -b + root
        t = np.where(t_near > 0.0, t_near, t_far)
        return np.where((disc >= 0.0) & (t > 0.0), t, np.inf)

    @staticmethod
    def _hit_box(bx: Box, o, d):
        safe = np.where(d == 0.0, 1e-300, d)                 # axis-parallel rays: +-huge slabs
        t0 = (np.asarray(bx.lo) - o) / safe
        t1 = (np.asarray(bx.hi) - o) / safe
        t_in = np.minimum(t0, t1).max(-1)
        t_out = np.maximum(t0, t1).min(-1)
        t = np.where(t_in > 0.0, t_in, t_out)
        return np.where((t_out >= t_in) & (t > 0.0), t, np.inf)

    def trace(self, origins, dirs) -> dict:
        """Exact render of rays. origins, dirs [n, 3] (dirs any length; normalised here).

        Returns rgb [n, 3] (background where nothing is hit), depth [n] (distance along the
        unit direction; inf on a miss), obj [n] (object id, -1 on a miss).
        """
        o = np.asarray(origins, np.float64).reshape(-1, 3)
        d = np.asarray(dirs, np.float64).reshape(-1, 3)
        d = d / np.linalg.norm(d, axis=-1, keepdims=True)
        ts = np.stack([self._hit_sphere(s, o, d) if isinstance(s, Sphere) else
                       self._hit_box(s, o, d) for s in self.shapes], -1)   # [n, K]
        obj = np.argmin(ts, -1)
        depth = ts[np.arange(len(o)), obj]
        hit = np.isfinite(depth)
        obj = np.where(hit, obj, -1)
        rgb = np.broadcast_to(np.asarray(self.background, np.float64), o.shape).copy()
        for k in range(len(self.shapes)):
            sel = obj == k
            if np.any(sel):
                rgb[sel] = self.color(k, o[sel] + depth[sel, None] * d[sel], d[sel])
        return {"rgb": rgb, "depth": depth, "obj": obj}

    def render(self, poses, intrinsics, H: int, W: int) -> dict:
        """Exact images: rgb float32 [N, H, W, 3], depth [N, H, W], obj [N, H, W]."""
        o, d = pixel_rays(poses, intrinsics, H, W)
        out = self.trace(o.astype(np.float64), d.astype(np.float64))
        n = len(np.asarray(poses).reshape(-1, 4, 4))
        return {"rgb": out["rgb"].reshape(n, H, W, 3).astype(np.float32),
                "depth": out["depth"].reshape(n, H, W), "obj": out["obj"].reshape(n, H, W)}


def procedural_cameras(n_train: int, n_test: int, seed: int = 0, radius: float = ORBIT_RADIUS):
    """Camera-to-world poses [n_train + n_test, 4, 4] looking at the origin.

    Train views: azimuth 360 i / n_train plus a seeded jitter of up to half a step, elevation
    cycling through 10..60 degrees (golden-ratio sequence, seeded offset). Test views: azimuth
    360 (j + 0.5) / n_test, elevation 30 degrees (not seeded).
    """
    rng = np.random.default_rng(seed)
    i = np.arange(n_train)
    az_tr = 360.0 * i / max(n_train, 1) + rng.uniform(-0.5, 0.5, n_train) * 360.0 / max(n_train, 1)
    el_tr = 10.0 + 50.0 * np.mod(rng.uniform() + i * 0.6180339887498949, 1.0)
    az_te = 360.0 * (np.arange(n_test) + 0.5) / max(n_test, 1)
    el_te = np.full(n_test, 30.0)
    az = np.deg2rad(np.concatenate([az_tr, az_te]))
    el = np.deg2rad(np.concatenate([el_tr, el_te]))
    eye = radius * np.stack([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)], -1)
    return look_at(eye, np.zeros(3))


def load_procedural(n_train: int = 64, n_test: int = 8, size: int = 64, seed: int = 0,
                    scene: ProceduralScene | None = None, max_images: int | None = None,
                    supersample: int = 4, **unused) -> Dataset:
    """The procedural scene as a Dataset: ``n_train`` + ``n_test`` views of ``size`` x ``size``
    pixels on an orbit of radius 4, white background, Blender field of view, deterministic in
    ``seed``; ``max_images`` caps both counts (as for the file loaders); each pixel the mean
    of ``supersample``^2 rays over it (see the module docstring).
    Example: load_procedural(size=32).images.shape -> (72, 32, 32, 3)."""
    from .base import DataError

    if unused:
        raise DataError(f"procedural scene: unknown options {sorted(unused)}; accepted: n_train, "
                        f"n_test, size, seed, scene, max_images, supersample")
    if max_images is not None:
        n_train, n_test = min(n_train, max_images), min(n_test, max_images)
    if n_train < 1 or n_test < 1 or size < 1 or supersample < 1:
        raise DataError(f"procedural scene: n_train, n_test, size and supersample must be >= 1, "
                        f"got {n_train}, {n_test}, {size}, {supersample}")
    scene = scene or ProceduralScene()
    focal = 0.5 * size / np.tan(0.5 * BLENDER_CAMERA_ANGLE_X)
    intr = np.array([focal, focal, size / 2.0, size / 2.0])
    poses = procedural_cameras(n_train, n_test, seed)
    k = int(supersample)
    images = np.empty((len(poses), size, size, 3), np.float32)
    for i in range(len(poses)):   # one view at a time: (k size)^2 rays of float64 temporaries
        hi = scene.render(poses[i:i + 1], intr * k, size * k, size * k)["rgb"][0]
        images[i] = hi.reshape(size, k, size, k, 3).mean((1, 3), dtype=np.float64)
    return Dataset(name="procedural", images=images, poses=poses.astype(np.float32),
                   intrinsics=intr,
                   split={"train": np.arange(n_train), "test": np.arange(n_train, n_train + n_test)},
                   background=tuple(scene.background), bbox=np.array([[-1.5] * 3, [1.5] * 3]),
                   near=2.0, far=6.0, ndc=False, preset="procedural")
