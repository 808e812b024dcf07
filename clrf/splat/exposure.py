"""A learned colour transform per training image (``splat.exposure``): phone captures change
exposure and white balance from frame to frame, which a static scene cannot explain.

Each training image v owns a row of P [V, 12] on the device: a 3 x 3 matrix A and an offset b,
so that a pixel the loss sees is ``A (c + T bg) + b`` (c the premultiplied colour, T the
transmittance, bg the background, which in a capture without alpha stands for scene light
that the exposure changes too), or, for a masked (RGBA) capture whose background was
composited in when it was loaded, ``A c + (1 - T) b + T bg``: the transform acts on the
scene's light only, and white behind a masked object stays white whatever the exposure. The
model renders on ``background(v, bg)`` (A^-1 (bg - b) masked, else bg), and the transform of
that render, ``A rgb + b``, is then exactly what the loss sees (cl/splat_exposure.cl; float64
twin: clrf/references/reference_exposure.py). Rows start at the identity and are pulled toward it by
``reg (|A - I|^2 + |b|^2)``, which also fixes the scale the scene's colours and the transforms
could otherwise trade; each row takes an Adam step (its own learning rate and step count)
whenever its image is trained. ``matrix`` (``splat.exposure_matrix``) says which entries train:
"full" every one, "diagonal" A's diagonal and b (a gain and an offset per channel), "gain" A's
diagonal only (a gain per channel: exposure and white balance). Test views are rendered under the
identity, as published; clrf's final evaluation also reports NeRF-W's protocol (a transform
fitted on the left half of each test image, the right half scored:
``reference_exposure.half_fitted_psnr``).

>>> exp = Exposure(dev, n_images=100, lr=5e-3, reg=1e-3)
>>> bg_v = exp.background(v, bg)                  # render view v on this
>>> out = exp.apply(rgb_d, v)                     # [H, W, 3] device arrays
>>> grad_rgb_d = exp.backward_and_step(rgb_d, T_d, bg_v, grad_out_d, v)
"""
from __future__ import annotations

import numpy as np

from ..references.reference_exposure import IDENTITY, MATRICES, ROW, fit_row, recentre
from ..runtime.programs import download, float4, launch, scratch, upload

CHUNK = 256              # pixels per work-item of exposure_backward (its partial sums)
ADAM_BETAS = (0.9, 0.999)
ADAM_EPS = 1e-15


def program(device):
    """cl/splat_exposure.cl on ``device`` (its one build; clrf/training/catalog.py lists it)."""
    return device.program("splat_exposure.cl")


class Exposure:
    """The transforms of ``n_images`` training images on ``device`` (module doc)."""

    def __init__(self, device, n_images: int, lr: float, reg: float, state: dict | None = None,
                 masked: bool = False, clip: bool = False, matrix: str = "full"):
        if n_images < 1:
            raise ValueError(f"Exposure needs at least one image, got {n_images}")
        self.device, self.n_images = device, int(n_images)
        self.masked = bool(masked)     # an RGBA capture: the background stays (module doc)
        # clamped to [0, 1] as a camera clips (exposure_clip): 0 no, 1 clipped channels pass
        # no gradient, 2 only one that points back inside (exposure_clip_inward)
        self.clip = int(clip)
        # the entries that train (exposure_matrix): an index of MATRICES, the kernels' argument
        self.matrix = MATRICES.index(matrix)
        self.lr, self.reg = float(lr), float(reg)
        q = device.queue
        rows = np.tile(IDENTITY.astype(np.float32), (self.n_images, 1))
        zeros = np.zeros_like(rows)
        steps = np.zeros(self.n_images, np.int64)
        if state is not None:
            self.masked = bool(state.get("exposure_masked", masked))
            rows = np.asarray(state["exposure"], np.float32).reshape(self.n_images, ROW)
            zeros = np.asarray(state["exposure_m"], np.float32).reshape(self.n_images, ROW)
            steps = np.asarray(state["exposure_steps"], np.int64).reshape(self.n_images)
            second = np.asarray(state["exposure_v"], np.float32).reshape(self.n_images, ROW)
        else:
            second = zeros
        self.P = upload(q, np.ascontiguousarray(rows))
        self.m = upload(q, np.ascontiguousarray(zeros))
        self.v = upload(q, np.ascontiguousarray(second))
        self.steps = steps.copy()       # Adam steps of each row (host: no read-back)
        # the budget fraction before which no row steps (calibrated rows held while the scene
        # forms under them: ``seed``)
        self.hold_until = float(state.get("exposure_hold_until", 0.0)) if state else 0.0
        self._prg = program(device)

    def apply(self, rgb, v: int):
        """A_v rgb + b_v (clamped to [0, 1] with ``clip``), a new device array shaped like
        ``rgb``."""
        out = scratch(self.device, rgb.shape)
        n = int(rgb.size) // 3
        launch(self.device, self._prg.kernel("exposure_apply"), n,
               (np.int32(n), rgb.data, self.P.data, np.int32(v), np.int32(self.clip), out.data))
        return out

    def background(self, v: int, background) -> tuple:
        """The background to render image v on: A^-1 (bg - b) for a masked capture (module
        doc; reads row v, twelve numbers), else bg. A singular A (never near the identity it is
        pulled to) renders on bg."""
        if not self.masked:
            return tuple(float(c) for c in background[:3])
        row = download(self.P[v:v + 1]).reshape(ROW).astype(np.float64)
        A, b = row[:9].reshape(3, 3), row[9:]
        bg = np.asarray(background, np.float64)[:3]
        try:
            out = np.linalg.solve(A, bg - b)
        except np.linalg.LinAlgError:
            return tuple(float(c) for c in bg)
        return tuple(float(c) for c in out) if np.all(np.isfinite(out)) else \
            tuple(float(c) for c in bg)

    def backward(self, rgb, T, background, grad_out, v: int):
        """(dL/drgb, the partial sums of dL/dP_v [items, 12]) from dL/dout of the render rgb
        and its transmittance T [H, W] on ``background`` (``self.background(v, bg)``): new device
        arrays (the partials summed over items are dL/dP_v; ``step`` sums them on the
        device)."""
        n = int(rgb.size) // 3
        items = (n + CHUNK - 1) // CHUNK
        grad_rgb = scratch(self.device, rgb.shape)
        partials = scratch(self.device, (max(items, 1), ROW))
        bg = float4(*(float(c) for c in background[:3]), 0.0)
        launch(self.device, self._prg.kernel("exposure_backward"), items,
               (np.int32(n), np.int32(CHUNK), rgb.data, np.int32(self.masked), T.data, bg,
                grad_out.data, self.P.data, np.int32(v), np.int32(self.clip), grad_rgb.data,
                partials.data))
        return grad_rgb, partials

    def backward_and_step(self, rgb, T, background, grad_out, v: int):
        """dL/drgb (a new device array) from dL/dout, and an Adam step of row v."""
        grad_rgb, partials = self.backward(rgb, T, background, grad_out, v)
        self.step(partials, (int(rgb.size) // 3 + CHUNK - 1) // CHUNK, v)
        return grad_rgb

    def step(self, partials, items: int, v: int):
        """An Adam step of row v from its gradient's partial sums (``backward``)."""
        self.steps[v] += 1
        t = int(self.steps[v])
        b1, b2 = ADAM_BETAS
        launch(self.device, self._prg.kernel("exposure_adam"), ROW,
               (np.int32(items), partials.data, self.P.data, self.m.data, self.v.data,
                np.int32(v), np.float32(self.lr), np.float32(self.reg), np.float32(b1),
                np.float32(b2), np.float32(ADAM_EPS), np.float32(1 - b1 ** t),
                np.float32(1 - b2 ** t), np.int32(self.matrix)), local_size=ROW)

    def fit(self, v: int, rgb, T, render_bg, background, target, eta: float):
        """Row v moved by ``eta`` toward the least-squares transform of this render (
        ``reference_exposure.fit_row``, in float64 on the host: the render and its T come
        back, the target is the host's image): a few visits reach a transform that dozens of
        Adam steps would not. The row's Adam step count goes on, its moments stay."""
        row = download(self.P[v:v + 1]).reshape(ROW)
        new = fit_row(download(rgb), download(T), render_bg, background, target, row,
                      self.reg, eta, self.masked, self.clip, self.matrix)
        if np.all(np.isfinite(new)):
            self.P[v:v + 1].set(np.ascontiguousarray(new.astype(np.float32)[None]))
        self.steps[v] += 1

    def seed(self, rows, hold_until: float = 0.0):
        """Rows P [V, 12] from elsewhere (an exposure calibration: clrf/training/calibrate.py)
        in place of the identity, held (no step, and so left out of ``recentre``) until the
        budget fraction ``hold_until``."""
        rows = np.asarray(rows, np.float64).reshape(-1, ROW)
        if len(rows) != self.n_images or not np.all(np.isfinite(rows)):
            raise ValueError(f"Exposure.seed: {self.n_images} finite rows of {ROW} expected, got "
                             f"{rows.shape}")
        self.P.set(np.ascontiguousarray(rows.astype(np.float32)))
        self.hold_until = float(hold_until)

    def recentre(self):
        """Takes the trained rows' geometric mean transform out of them
        (``reference_exposure.recentre``: the scene then takes the images' mean exposure, and
        the test views' identity means it); the model calls it after each pass over its
        views."""
        trained = np.flatnonzero(self.steps > 0)
        P = recentre(self.rows(), trained, self.matrix)
        self.P.set(np.ascontiguousarray(P.astype(np.float32)))

    def rows(self) -> np.ndarray:
        """P [V, 12] on the host."""
        return download(self.P).reshape(self.n_images, ROW)

    def state_dict(self) -> dict:
        return {"exposure": self.rows(), "exposure_m": download(self.m),
                "exposure_v": download(self.v), "exposure_steps": self.steps.copy(),
                "exposure_masked": self.masked, "exposure_hold_until": self.hold_until}

    def describe(self) -> str:
        """'exposure |A - I| 0.031' (mean over trained rows) for progress lines."""
        rows = self.rows()[self.steps > 0]
        if not len(rows):
            return "exposure: no image trained yet"
        dev = np.abs(rows - IDENTITY[None]).mean()
        return f"exposure |P - I| {dev:.3f} over {len(rows)} images"
