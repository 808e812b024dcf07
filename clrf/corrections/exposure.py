"""A learned colour transform per training image (``splat.exposure``, ``hash.exposure``,
``nerf.exposure``): phone captures change exposure and white balance from frame to frame,
which a static scene cannot explain. ``Exposure`` serves models that train on whole views (the
splat model), ``RayExposure`` models whose batches mix rays of many images (the hash and NeRF
models); both are colour corrections of the protocol in clrf/corrections/base.py, on the
kernels of cl/splat_exposure.cl (float64 twin: clrf/references/reference_exposure.py).

Each training image v owns a row of P [V, 12] on the device: a 3 x 3 matrix A and an offset b,
so that a pixel the loss sees is ``A (c + T bg) + b`` (c the premultiplied colour, T the
transmittance, bg the background, which in a capture without alpha stands for scene light
that the exposure changes too), or, for a masked (RGBA) capture whose background was
composited in when it was loaded, ``A c + (1 - T) b + T bg``: the transform acts on the
scene's light only, and white behind a masked object stays white whatever the exposure. Rows
start at the identity and are pulled toward it by ``reg (|A - I|^2 + |b|^2)``, which also fixes
the scale the scene's colours and the transforms could otherwise trade. ``matrix``
(``<model>.exposure_matrix``) says which entries train: "full" every one, "diagonal" A's
diagonal and b (a gain and an offset per channel), "gain" A's diagonal only (a gain per
channel: exposure and white balance). The rows' common (geometric mean) transform is taken out
of them from time to time (``reference_exposure.recentre``): the scene then takes the images'
mean exposure, and the test views' identity means it. Test views are rendered under the
identity, as published; clrf's final evaluation also reports NeRF-W's protocol (a transform
fitted on the left half of each test image, the right half scored:
``reference_exposure.half_fitted_psnr``).

Whole views (``Exposure``): the model renders view v on ``background(v, bg)`` (A^-1 (bg - b)
masked, else bg), and the transform of that render, ``A rgb + b``, is then exactly what the
loss sees; each row takes an Adam step (its own learning rate and step count, on the device:
``exposure_adam``) whenever its image is trained, or is fitted (``fit``) or held (``seed``) as
the settings say (``train_view``), and the rows are recentred after each pass over the views.

>>> exp = Exposure(dev, n_images=100, lr=5e-3, reg=1e-3)
>>> bg_v = exp.background(v, bg)                  # render view v on this
>>> out = exp.apply(rgb_d, v)                     # [H, W, 3] device arrays
>>> grad_rgb_d = exp.backward_and_step(rgb_d, T_d, bg_v, grad_out_d, v)

Ray batches (``RayExposure``): ray i comes from training image ``index[i] // pixels`` (its
place in the concatenated training images, which the trainer's ray store gives), and the loss
compares the ray's colour under that image's transform with the ray's target (T = 1 - a the
ray's transmittance, bg the step's background). The kernels (``exposure_rays``,
``exposure_rays_bg``, ``exposure_rays_grad``) take each ray's composite state, so the marcher's
backward is unchanged: run on a black background, it is given the target ``c - A^T r`` (r the
residual), whose loss gradient is the colour's through the transform, and
``exposure_rays_bg`` adds the background's share to the densities' gradient. Every row takes
one Adam step a training step (pyopencl's device arrays, cl/optim.cl's Adam); the pull toward
the identity is weighted by each row's share of the batch, and every RECENTRE_EVERY steps the
rows are recentred. A renderer whose loss has several passes over the batch (NeRF: the coarse
and the fine pass, ``nerf.exposure``; its composite gives the same state and packing,
cl/composite.cl composite_state) calls ``backward`` after each pass but the last, which keeps
that pass's gradient for the one Adam step of ``backward_and_step``.

>>> exp = RayExposure(dev, n_images=100, pixels=400 * 400, lr=1e-3, reg=1e-3)
>>> eff, sq = exp.forward(state_d, bg, target_d, index_d)    # before the marcher's backward
>>> g = packed_backward(dev, pk, sigma, rgb, (0, 0, 0), eff, loss_scale)
>>> exp.add_background(pk, sigma, loss_scale, g["sigma"])
>>> exp.backward_and_step(state_d, bg, index_d, loss_scale)
"""
from __future__ import annotations

from typing import NamedTuple

import numpy as np
import pyopencl.array as cla

from ..references.reference_exposure import IDENTITY, MATRICES, ROW, fit_row, recentre
from ..runtime.optim import ADAM_BETAS, ADAM_EPS, Optimizer, expon_lr
from ..runtime.programs import download, float4, launch, scratch, upload
from .base import COLOUR, RAY_STATE, RAYS, VIEWS

CHUNK = 256              # pixels per work-item of exposure_backward (its partial sums)
LOCAL = 64               # cl/splat_exposure.cl EXPOSURE_LS (exposure_rays_grad's work-group)
RECENTRE_EVERY = 100     # RayExposure: steps between recentrings


class RayTransform(NamedTuple):
    """``RayExposure.in_backward``'s record: each ray's place in the training images (int32
    device [n]), pixels per image, the rows P [V, 12] (device), the state [n, RAY_STATE]
    and residuals [n, 3] (device) the renderer writes, and whether the loss clamps to
    [0, 1]."""
    index: cla.Array
    pixels: int
    rows: cla.Array
    state: cla.Array
    resid: cla.Array
    clip: bool


def gain_spread(rows) -> float:
    """The spread of the gains of rows P [V, 12] (A row-major, then b): the standard deviation
    over the rows of log A_cc, the largest of the three channels; rows with a non-finite or
    non-positive gain are left out (0.0 with fewer than two rows left). How a steady capture
    (one exposure throughout) is told from one whose exposure changes: the splat model's
    calibration (clrf/training/calibrate.py) and ``RayExposure``'s check."""
    P = np.asarray(rows, np.float64).reshape(-1, ROW)
    d = P[:, [0, 4, 8]]
    ok = np.all(np.isfinite(d) & (d > 0), axis=1)
    if ok.sum() < 2:
        return 0.0
    return float(np.log(d[ok]).std(axis=0).max())


def program(device):
    """cl/splat_exposure.cl on ``device`` (its one build; clrf/training/catalog.py lists it)."""
    return device.program("splat_exposure.cl")


class _Rows:
    """What both transforms share: the rows P [V, 12] on the device, the entries that train,
    the recentring, and the protocol's reporting (clrf/corrections/base.py)."""
    name = "exposure"
    changes = COLOUR

    def __init__(self, device, n_images: int, lr: float, reg: float, masked: bool,
                 matrix: str, lr_final: float | None = None):
        self.device, self.n_images = device, int(n_images)
        self.masked = bool(masked)     # an RGBA capture: the background stays (module doc)
        # the entries that train (exposure_matrix): an index of MATRICES, the kernels' argument
        self.matrix = MATRICES.index(matrix)
        self.lr, self.reg = float(lr), float(reg)
        self.lr_start = self.lr
        self.lr_final = None if lr_final is None else float(lr_final)
        self._prg = program(device)

    def schedule(self, progress: float) -> None:
        """The rate at the budget fraction ``progress``: log-linear from its first rate to
        ``lr_final`` (``<model>.lr_exposure_final``; constant without one)."""
        if self.lr_final is not None:
            self.lr = expon_lr(progress, self.lr_start, self.lr_final, 1.0)

    def slow(self, factor: float) -> None:
        """The rates (first and final) times ``factor`` (a steady capture: the splat
        model's calibration, clrf/training/calibrate.py, and ``RayExposure``'s check)."""
        if not factor > 0:
            raise ValueError(f"{type(self).__name__}.slow: factor > 0, got {factor}")
        self.lr_start *= float(factor)
        self.lr = self.lr_start
        if self.lr_final is not None:
            self.lr_final *= float(factor)

    def rows(self) -> np.ndarray:
        """P [V, 12] on the host."""
        return download(self.P).reshape(self.n_images, ROW)

    def _recentre(self, trained):
        """Takes the geometric mean transform of rows ``trained`` out of every row
        (``reference_exposure.recentre``)."""
        P = recentre(self.rows(), trained, self.matrix)
        self.P.set(np.ascontiguousarray(P.astype(np.float32)))

    def _deviation(self, rows) -> str:
        dev = np.abs(rows - IDENTITY[None]).mean()
        return f"exposure |P - I| {dev:.3f} over {len(rows)} images"

    def summary(self) -> dict:
        """Nothing of its own in eval.json: the evaluation's half-fitted and shared-gain scores
        (clrf/training/trainer.py evaluate) stand for it."""
        return {}

    def report(self, summary: dict) -> str:
        return ""


class Exposure(_Rows):
    """The transforms of ``n_images`` training images on ``device``, for a model that trains
    on whole views (module doc). ``lr_final``: the rate falls log-linearly from ``lr`` to it
    over the budget (``schedule``; None: a constant rate); ``fit`` > 0: from the budget
    fraction ``fit_after`` on, a trained view's row is moved by ``fit`` toward its
    least-squares transform instead of an Adam step (``train_view``)."""
    batches = VIEWS

    def __init__(self, device, n_images: int, lr: float, reg: float, state: dict | None = None,
                 masked: bool = False, clip: bool = False, matrix: str = "full",
                 lr_final: float | None = None, fit: float = 0.0, fit_after: float = 0.0):
        if n_images < 1:
            raise ValueError(f"Exposure needs at least one image, got {n_images}")
        super().__init__(device, n_images, lr, reg, masked, matrix, lr_final)
        # clamped to [0, 1] as a camera clips (exposure_clip): 0 no, 1 clipped channels pass
        # no gradient, 2 only one that points back inside (exposure_clip_inward)
        self.clip = int(clip)
        self.fit_eta, self.fit_after = float(fit), float(fit_after)
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

    def apply(self, rgb, v: int, T=None, background=None):
        """A_v rgb + b_v (clamped to [0, 1] with ``clip``), a new device array shaped like
        ``rgb`` (``T`` and ``background`` unused: a masked capture is rendered on
        ``self.background(v, bg)`` instead)."""
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

    def train_view(self, v: int, rgb, T, background, grad_out, progress: float, images,
                   scene_background):
        """dL/drgb from dL/dout of view v's render on ``background``, row v trained as the
        settings say at the budget fraction ``progress``: held before ``hold_until`` (calibrated
        rows: ``seed``), fitted toward ``images[v]`` on ``scene_background`` from
        ``fit_after`` on where ``fit`` > 0, else an Adam step."""
        if progress < self.hold_until:
            grad, _ = self.backward(rgb, T, background, grad_out, v)
        elif self.fit_eta > 0 and progress >= self.fit_after:
            grad, _ = self.backward(rgb, T, background, grad_out, v)
            self.fit(v, rgb, T, background, scene_background, images[v], self.fit_eta)
        else:
            grad = self.backward_and_step(rgb, T, background, grad_out, v)
        return grad

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
        """Takes the trained rows' geometric mean transform out of them (module doc)."""
        self._recentre(np.flatnonzero(self.steps > 0))

    def after_pass(self) -> None:
        """The model calls it after each pass over its views: ``recentre``."""
        self.recentre()

    def state_dict(self) -> dict:
        return {"exposure": self.rows(), "exposure_m": download(self.m),
                "exposure_v": download(self.v), "exposure_steps": self.steps.copy(),
                "exposure_masked": self.masked, "exposure_hold_until": self.hold_until}

    def describe(self) -> str:
        """'exposure |P - I| 0.031 over 12 images' (mean over trained rows) for progress
        lines."""
        rows = self.rows()[self.steps > 0]
        if not len(rows):
            return "exposure: no image trained yet"
        return self._deviation(rows)


class RayExposure(_Rows):
    """The transforms of ``n_images`` training images of ``pixels`` pixels each, for a model
    whose batches mix rays of many images (module doc); Adam with ``beta`` (beta1, beta2) and
    ``eps`` at a constant rate."""
    batches = RAYS

    def __init__(self, device, n_images: int, pixels: int, lr: float, reg: float,
                 beta=ADAM_BETAS, eps: float = ADAM_EPS, state: dict | None = None,
                 masked: bool = False, matrix: str = "full", clip: bool = False,
                 lr_final: float | None = None, steady_spread: float = 0.0,
                 steady_rate: float = 0.01, steady_after: float = 0.2):
        if n_images < 1 or pixels < 1:
            raise ValueError(f"RayExposure needs images and pixels, got {n_images}, {pixels}")
        super().__init__(device, n_images, lr, reg, masked, matrix, lr_final)
        self.pixels = int(pixels)
        self.clip = bool(clip)   # the loss sees out clamped to [0, 1] (<model>.exposure_clip)
        # the steady check (``schedule``): at the budget fraction steady_after, rows whose gains
        # spread less than steady_spread (0: never) go back to the identity and the rates are
        # scaled by steady_rate; self.steady None until then, after it whether it found so
        self.steady_spread, self.steady_rate = float(steady_spread), float(steady_rate)
        self.steady_after = float(steady_after)
        self.steady, self.spread_seen = None, None
        q = device.queue
        rows = np.tile(IDENTITY.astype(np.float32), (self.n_images, 1))
        m = v = np.zeros_like(rows)
        self.steps = 0
        if state is not None:
            rows = np.asarray(state["exposure"], np.float32).reshape(self.n_images, ROW)
            m = np.asarray(state["exposure_m"], np.float32).reshape(self.n_images, ROW)
            v = np.asarray(state["exposure_v"], np.float32).reshape(self.n_images, ROW)
            self.steps = int(np.asarray(state["exposure_steps"]).reshape(-1)[0])
            if "exposure_steady" in state:   # a checkpoint from before the check: unchecked
                seen = float(np.asarray(state["exposure_spread_seen"]).reshape(-1)[0])
                self._checked(bool(np.asarray(state["exposure_steady"]).reshape(-1)[0]), seen)
        self.P = upload(q, np.ascontiguousarray(rows))
        self.grad = cla.zeros_like(self.P)
        self.opt = Optimizer(device, self.P, "adam", beta=beta[0], beta2=beta[1], eps=eps,
                             grad=self.grad, state=upload(q, np.ascontiguousarray(m)),
                             state2=upload(q, np.ascontiguousarray(v)))
        self._resid = self._bgt = None
        self._pending = False   # grad holds a pass's gradient (``backward``) not yet stepped

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
                np.int32(self.masked), np.int32(self.clip), self._bg(background),
                target.data, self.P.data, self._resid.data, eff.data, sq.data,
                self._bgt.data))
        return eff, sq

    def in_backward(self, index):
        """What a renderer that applies the transform inside its own backward needs (the grid:
        cl/grid_render.cl RAY_EXPOSURE, one march where ``forward`` needs a rendered pixel
        first), for a batch of whole pixels (opacity 1, the background in them): a
        ``RayTransform`` whose ``state`` [n, 8] and ``resid`` [n, 3] the renderer writes, as
        ``forward`` would have from the same pixels; ``backward_and_step`` then reads them."""
        n = int(index.shape[0])
        self._resid = scratch(self.device, (n, 3))
        self._bgt = None
        state = scratch(self.device, (n, RAY_STATE))
        return RayTransform(index, self.pixels, self.P, state, self._resid, self.clip)

    def behind(self, background, index):
        """[n, 3] device: each ray's background A_v^-1 (bg - b_v) (cl/splat_exposure.cl
        exposure_rays_behind), for a masked capture on a renderer that composites the
        background itself and hands ``forward`` whole pixels (the grid): its render on these
        is what the transform maps to the masked pixel."""
        n = int(index.shape[0])
        out = scratch(self.device, (max(n, 1), 3))
        launch(self.device, self._prg.kernel("exposure_rays_behind"), n,
               (np.int32(n), np.int32(self.pixels), index.data, self._bg(background),
                self.P.data, out.data))
        return out[:n]

    def add_background(self, pk, sigma, loss_scale: float, dsigma):
        """Adds the background's share of dL/dsigma (the last ``forward``'s rays, packed as
        ``pk``: n rays, m samples, offsets [n + 1] and dt [m] on the device; the renderer's
        backward ran on a black background) to ``dsigma``, in place."""
        if pk.m:
            launch(self.device, self._prg.kernel("exposure_rays_bg"), pk.n,
                   (np.int32(pk.n), pk.offsets.data, pk.dt.data, sigma.data, self._bgt.data,
                    np.float32(loss_scale), dsigma.data))

    def _grad(self, state, background, index, loss_scale: float, reg: float):
        """dL/dP of the last ``forward``'s rays (and the pull ``reg``) into ``grad``: written,
        or added to what ``backward`` left there."""
        n = int(self._resid.shape[0])
        launch(self.device, self._prg.kernel("exposure_rays_grad"), self.n_images * LOCAL,
               (np.int32(n), np.int32(self.pixels), index.data, state.data,
                np.int32(self.masked), self._bg(background), self._resid.data, self.P.data,
                np.float32(loss_scale), np.float32(reg), np.int32(self.matrix),
                np.int32(self._pending), self.grad.data), local_size=LOCAL)
        self._resid = self._bgt = None

    def backward(self, state, background, index, loss_scale: float):
        """dL/dP of L = loss_scale sum |r|^2 over the last ``forward``'s rays (on
        ``background``), kept for the next ``backward_and_step`` (a renderer whose loss has
        several passes over the batch: NeRF's coarse pass; the pull is added once, there)."""
        self._grad(state, background, index, loss_scale, 0.0)
        self._pending = True

    def backward_and_step(self, state, background, index, loss_scale: float):
        """dL/dP of L = loss_scale sum |r|^2 over the last ``forward``'s rays (on
        ``background``), plus what ``backward`` kept since the last step, the pull added, and
        one Adam step of every row; every RECENTRE_EVERY steps the rows are recentred."""
        self._grad(state, background, index, loss_scale, self.reg)
        self._pending = False
        self.steps += 1
        self.opt.step(None, self.lr, t=self.steps)
        if self.steps % RECENTRE_EVERY == 0:
            self.recentre()

    def schedule(self, progress: float) -> None:
        """The rate at the budget fraction ``progress`` (``_Rows.schedule``), after the steady
        check: the first call at or past ``steady_after`` measures the rows' ``gain_spread``;
        below ``steady_spread`` the capture is taken as one of a single exposure, what the rows
        learned as their own noise (the scene would keep it, and the test views, rendered
        under the identity, would not match it), so they go back to the identity, their Adam
        moments to 0, and the rates are scaled by ``steady_rate`` (as the splat model's
        calibration does: clrf/training/calibrate.py)."""
        if (self.steady is None and self.steady_spread > 0 and progress >= self.steady_after
                and self.steps > 0):
            spread = gain_spread(self.rows())
            if spread < self.steady_spread:
                rows = np.tile(IDENTITY.astype(np.float32), (self.n_images, 1))
                self.P.set(np.ascontiguousarray(rows))
                self.opt.state.fill(0.0)
                self.opt.state2.fill(0.0)
            self._checked(spread < self.steady_spread, spread)
        super().schedule(progress)

    def _checked(self, steady: bool, spread: float) -> None:
        """Records the steady check's finding; a steady capture's rates scaled by steady_rate."""
        self.steady, self.spread_seen = bool(steady), float(spread)
        if self.steady:
            self.slow(self.steady_rate)

    def summary(self) -> dict:
        """The steady check's finding (eval.json ``exposure_correction``), once it was made."""
        if self.steady is None:
            return {}
        return {"images": self.n_images, "steady": self.steady,
                "gain_spread": round(self.spread_seen, 5)}

    def report(self, summary: dict) -> str:
        if "steady" not in summary:
            return ""
        if summary["steady"]:
            return (f"exposure: the transforms' gains spread by {summary['gain_spread']:.3f} "
                    "(steady: one exposure), so they went back to the identity")
        return f"exposure: the transforms' gains spread by {summary['gain_spread']:.3f}"

    def recentre(self):
        """Takes the rows' geometric mean transform out of them (module doc);
        ``backward_and_step`` calls it every RECENTRE_EVERY steps."""
        self._recentre(np.arange(self.n_images))

    def after_pass(self) -> None:
        """Nothing: a ray batch mixes every image, so there is no pass; the rows are
        recentred every RECENTRE_EVERY steps instead (``backward_and_step``)."""

    def state_dict(self) -> dict:
        return {"exposure": self.rows(), "exposure_m": download(self.opt.state),
                "exposure_v": download(self.opt.state2),
                "exposure_steps": np.array([self.steps], np.int64),
                "exposure_pixels": self.pixels, "exposure_masked": self.masked,
                **({} if self.steady is None else {
                    "exposure_steady": self.steady, "exposure_spread_seen": self.spread_seen})}

    def describe(self) -> str:
        """'exposure |P - I| 0.031 over 100 images' for progress lines (', steady: from the
        identity' once the steady check found a single exposure)."""
        if not self.steps:
            return "exposure: no step yet"
        return self._deviation(self.rows()) + (
            f" (steady, gains spread {self.spread_seen:.3f}: from the identity at "
            f"{self.steady_rate:g} of the rate)" if self.steady else "")
