"""A learned colour transform per training image (``splat.exposure``): phone captures change
exposure and white balance from frame to frame, which a static scene cannot explain.

Each training image v owns a row of P [V, 12] on the device: a 3 x 3 matrix A and an offset b,
so that the render the loss sees is ``A rgb + b`` (cl/splat_exposure.cl; float64 twin:
clrf/references/reference_exposure.py). Rows start at the identity and are pulled toward it by
``reg (|A - I|^2 + |b|^2)``, which also fixes the scale the scene's colours and the transforms
could otherwise trade; each row takes an Adam step (its own learning rate and step count)
whenever its image is trained. Test views are rendered under the identity, as published;
clrf's final evaluation also reports NeRF-W's protocol (a transform fitted on the left half of
each test image, the right half scored: ``reference_exposure.half_fitted_psnr``).

>>> exp = Exposure(dev, n_images=100, lr=5e-3, reg=1e-3)
>>> out = exp.apply(rgb_d, v)                     # [H, W, 3] device arrays
>>> grad_rgb_d = exp.backward_and_step(rgb_d, grad_out_d, v)
"""
from __future__ import annotations

import numpy as np

from ..references.reference_exposure import IDENTITY, ROW
from ..runtime.programs import download, launch, scratch, upload

CHUNK = 256              # pixels per work-item of exposure_backward (its partial sums)
ADAM_BETAS = (0.9, 0.999)
ADAM_EPS = 1e-15


def program(device):
    """cl/splat_exposure.cl on ``device`` (its one build; clrf/training/catalog.py lists it)."""
    return device.program("splat_exposure.cl")


class Exposure:
    """The transforms of ``n_images`` training images on ``device`` (module doc)."""

    def __init__(self, device, n_images: int, lr: float, reg: float, state: dict | None = None):
        if n_images < 1:
            raise ValueError(f"Exposure needs at least one image, got {n_images}")
        self.device, self.n_images = device, int(n_images)
        self.lr, self.reg = float(lr), float(reg)
        q = device.queue
        rows = np.tile(IDENTITY.astype(np.float32), (self.n_images, 1))
        zeros = np.zeros_like(rows)
        steps = np.zeros(self.n_images, np.int64)
        if state is not None:
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
        self._prg = program(device)

    def apply(self, rgb, v: int):
        """A_v rgb + b_v, a new device array shaped like ``rgb``."""
        out = scratch(self.device, rgb.shape)
        n = int(rgb.size) // 3
        launch(self.device, self._prg.kernel("exposure_apply"), n,
               (np.int32(n), rgb.data, self.P.data, np.int32(v), out.data))
        return out

    def backward(self, rgb, grad_out, v: int):
        """(dL/drgb, the partial sums of dL/dP_v [items, 12]) from dL/dout: new device arrays
        (the partials summed over items are dL/dP_v; ``step`` sums them on the device)."""
        n = int(rgb.size) // 3
        items = (n + CHUNK - 1) // CHUNK
        grad_rgb = scratch(self.device, rgb.shape)
        partials = scratch(self.device, (max(items, 1), ROW))
        launch(self.device, self._prg.kernel("exposure_backward"), items,
               (np.int32(n), np.int32(CHUNK), rgb.data, grad_out.data, self.P.data,
                np.int32(v), grad_rgb.data, partials.data))
        return grad_rgb, partials

    def backward_and_step(self, rgb, grad_out, v: int):
        """dL/drgb (a new device array) from dL/dout, and an Adam step of row v."""
        grad_rgb, partials = self.backward(rgb, grad_out, v)
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
                np.float32(1 - b2 ** t)), local_size=ROW)

    def rows(self) -> np.ndarray:
        """P [V, 12] on the host."""
        return download(self.P).reshape(self.n_images, ROW)

    def state_dict(self) -> dict:
        return {"exposure": self.rows(), "exposure_m": download(self.m),
                "exposure_v": download(self.v), "exposure_steps": self.steps.copy()}

    def describe(self) -> str:
        """'exposure |A - I| 0.031' (mean over trained rows) for progress lines."""
        rows = self.rows()[self.steps > 0]
        if not len(rows):
            return "exposure: no image trained yet"
        dev = np.abs(rows - IDENTITY[None]).mean()
        return f"exposure |P - I| {dev:.3f} over {len(rows)} images"
