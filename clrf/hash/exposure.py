"""A learned colour transform per training image for the hash model (``hash.exposure``): the
splat model's ``splat.exposure`` (clrf/splat/exposure.py) for ray batches.

A batch holds rays of many images: ray i comes from training image ``index[i] // pixels``
(its place in the concatenated training images, which the trainer's ray store gives), and the
loss compares the ray's colour under that image's transform with the ray's target: ``A (c +
T bg) + b`` (c premultiplied, T = 1 - a the ray's transmittance, bg the step's background), or
for a masked (RGBA) capture ``A c + a b + T bg``, the background left alone (as the splat
model's, clrf/splat/exposure.py). The kernels (cl/splat_exposure.cl ``exposure_rays``,
``exposure_rays_bg``, ``exposure_rays_grad``; float64 twin:
clrf/references/reference_exposure.py) take each ray's composite state, so the marcher's
backward is unchanged: run on a black background, it is given the target ``c - A^T r`` (r the
residual), whose loss gradient is the colour's through the transform, and
``exposure_rays_bg`` adds the background's share to the densities' gradient. Every row takes
one Adam step a training step (pyopencl's device arrays, cl/optim.cl's Adam); the pull toward
the identity is weighted by each row's share of the batch, and every RECENTRE_EVERY steps the
rows' common mean is taken out of them. Test views are scored under the
identity, as published, and NeRF-W's half-fitted protocol beside it.

>>> exp = RayExposure(dev, n_images=100, pixels=400 * 400, lr=1e-3, reg=1e-3)
>>> eff, sq = exp.forward(state_d, bg, target_d, index_d)    # before the marcher's backward
>>> g = packed_backward(dev, pk, sigma, rgb, (0, 0, 0), eff, loss_scale)
>>> exp.add_background(pk, sigma, loss_scale, g["sigma"])
>>> exp.backward_and_step(state_d, bg, index_d, loss_scale)
"""
from __future__ import annotations

import numpy as np
import pyopencl.array as cla

from ..references.reference_exposure import IDENTITY, MATRICES, ROW, recentre
from ..runtime.optim import Optimizer
from ..runtime.programs import download, float4, launch, scratch, upload
from ..splat.exposure import program

LOCAL = 64       # cl/splat_exposure.cl EXPOSURE_LS
RECENTRE_EVERY = 100   # steps between taking the rows' mean transform out (recentre)


class RayExposure:
    """The transforms of ``n_images`` training images of ``pixels`` pixels each (module doc)."""

    def __init__(self, device, n_images: int, pixels: int, lr: float, reg: float,
                 beta=(0.9, 0.999), eps: float = 1e-15, state: dict | None = None,
                 masked: bool = False, matrix: str = "full"):
        if n_images < 1 or pixels < 1:
            raise ValueError(f"RayExposure needs images and pixels, got {n_images}, {pixels}")
        self.device, self.n_images, self.pixels = device, int(n_images), int(pixels)
        self.masked = bool(masked)     # an RGBA capture: the background stays (module doc)
        # the entries that train (exposure_matrix): an index of MATRICES, the kernel's argument
        self.matrix = MATRICES.index(matrix)
        self.lr, self.reg = float(lr), float(reg)
        q = device.queue
        rows = np.tile(IDENTITY.astype(np.float32), (self.n_images, 1))
        m = v = np.zeros_like(rows)
        self.steps = 0
        if state is not None:
            rows = np.asarray(state["exposure"], np.float32).reshape(self.n_images, ROW)
            m = np.asarray(state["exposure_m"], np.float32).reshape(self.n_images, ROW)
            v = np.asarray(state["exposure_v"], np.float32).reshape(self.n_images, ROW)
            self.steps = int(np.asarray(state["exposure_steps"]).reshape(-1)[0])
        self.P = upload(q, np.ascontiguousarray(rows))
        self.grad = cla.zeros_like(self.P)
        self.opt = Optimizer(device, self.P, "adam", beta=beta[0], beta2=beta[1], eps=eps,
                             grad=self.grad, state=upload(q, np.ascontiguousarray(m)),
                             state2=upload(q, np.ascontiguousarray(v)))
        self._prg = program(device)
        self._resid = self._bgt = None

    @staticmethod
    def _bg(background):
        r, g, b = (float(c) for c in background)
        return float4(r, g, b, 0.0)

    def forward(self, state, background, target, index):
        """(eff, sq) device arrays of a batch of n rays: the target [n, 3] to give the marcher's
        backward and each ray's squared transformed residual [n] (the loss's terms). Keeps the
        residuals for ``backward_and_step``."""
        n = int(target.shape[0])
        self._resid = scratch(self.device, (n, 3))
        self._bgt = scratch(self.device, n)
        eff = scratch(self.device, (n, 3))
        sq = scratch(self.device, n)
        launch(self.device, self._prg.kernel("exposure_rays"), n,
               (np.int32(n), np.int32(self.pixels), index.data, state.data,
                np.int32(self.masked), self._bg(background), target.data, self.P.data,
                self._resid.data, eff.data, sq.data, self._bgt.data))
        return eff, sq

    def add_background(self, pk, sigma, loss_scale: float, dsigma):
        """Adds the background's share of dL/dsigma (the last ``forward``'s rays, packed as
        ``pk``; the marcher's backward ran on a black background) to ``dsigma``, in place."""
        if pk.m:
            launch(self.device, self._prg.kernel("exposure_rays_bg"), pk.n,
                   (np.int32(pk.n), pk.offsets.data, pk.dt.data, sigma.data, self._bgt.data,
                    np.float32(loss_scale), dsigma.data))

    def backward_and_step(self, state, background, index, loss_scale: float):
        """dL/dP of L = loss_scale sum |r|^2 over the last ``forward``'s rays (on
        ``background``), the pull added, and one Adam step of every row."""
        n = int(self._resid.shape[0])
        launch(self.device, self._prg.kernel("exposure_rays_grad"), self.n_images * LOCAL,
               (np.int32(n), np.int32(self.pixels), index.data, state.data,
                np.int32(self.masked), self._bg(background), self._resid.data, self.P.data,
                np.float32(loss_scale), np.float32(self.reg), np.int32(self.matrix),
                self.grad.data), local_size=LOCAL)
        self.steps += 1
        self.opt.step(None, self.lr, t=self.steps)
        self._resid = self._bgt = None
        if self.steps % RECENTRE_EVERY == 0:
            self.recentre()

    def recentre(self):
        """Takes the rows' geometric mean transform out of them
        (``reference_exposure.recentre``); ``backward_and_step`` calls it every
        RECENTRE_EVERY steps."""
        P = recentre(self.rows(), np.arange(self.n_images), self.matrix)
        self.P.set(np.ascontiguousarray(P.astype(np.float32)))

    def rows(self) -> np.ndarray:
        """P [V, 12] on the host."""
        return download(self.P).reshape(self.n_images, ROW)

    def state_dict(self) -> dict:
        return {"exposure": self.rows(), "exposure_m": download(self.opt.state),
                "exposure_v": download(self.opt.state2),
                "exposure_steps": np.array([self.steps], np.int64),
                "exposure_pixels": self.pixels, "exposure_masked": self.masked}

    def describe(self) -> str:
        """'exposure |P - I| 0.031 over 100 images' for progress lines."""
        if not self.steps:
            return "exposure: no step yet"
        dev = np.abs(self.rows() - IDENTITY[None]).mean()
        return f"exposure |P - I| {dev:.3f} over {self.n_images} images"
