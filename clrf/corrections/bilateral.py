"""The bilateral grid per training image (``splat.bilateral_grid``): Wang et al. 2024,
"Bilateral Guided Radiance Field Processing", as gsplat trains it (``use_bilateral_grid``):
a small grid of affine colour transforms per image, sliced by pixel position and the render's
luminance, that can absorb what a camera's processing does to one photo and not the next
(exposure, white balance, tone curves, vignetting). A colour correction of whole views
(clrf/corrections/base.py ``ViewColourCorrection``) on the kernels of cl/bilateral.cl (float64
twin: clrf/references/reference_bilateral.py); the formulas are in the kernel file's header.

gsplat's figures, kept: a grid of 16 x 16 x 8 cells per image (``splat.bilateral_grid_shape``,
x and y bins over the image, luminance bins), 12 channels (a 3 x 4 affine transform) a cell,
every cell at the identity at the start; the slice trilinear at the pixel's centre and its
render's BT.601 grey (0.299, 0.587, 0.114), clamped at the border; the prior 10 times the
total variation of the grids (``splat.bilateral_grid_tv``) summed over the images and divided
by their number; Adam at 2e-3 (``splat.lr_bilateral_grid``, eps 1e-15, betas 0.9 and 0.999)
with every grid stepped every training step (a view's grid by its data gradient and the prior,
the others by the prior and their moments); the rate warmed up linearly from 1 % over the
first 1,000 of 30,000 steps (a budget fraction WARMUP) and decayed exponentially to 1 % at
the end (FINAL).

Two departures, each a setting: ``sparse`` (``splat.bilateral_grid_sparse``) steps the trained
view's grid alone (its data and prior gradients; Adam's bias correction by that grid's own
step count), so that a step costs one grid's update, not all of them (the splat model holds a
grid per image of the capture, 400 on lego_400; with gsplat's dense update a CPU run there
made 37 % fewer steps than with the exposure transforms); ``seed`` starts every cell of each image's grid from that image's
affine transform found by an exposure calibration (``splat.bilateral_grid_calibrate``,
clrf/training/calibrate.py) and holds the grids until a budget fraction while the scene forms
under them: on a CPU budget each grid is trained a few dozen times, far too few for gsplat's
rate to reach an exposure change from the identity.

Test views are rendered without it (the identity), as gsplat scores them;
gsplat reports them after a colour correction fitted to each test image as well, as clrf's
``psnr_color_corrected`` does (docs/evaluation.md).

A masked (RGBA) capture keeps its background: the scene's light rgb - T bg is transformed,
(1 - T) b added, and T bg kept (``masked``). The render's transmittance T is then an input of
the transform beside rgb; the gradient the model's rasteriser receives is dL/drgb at fixed T
(its backward takes one background colour, not a gradient per pixel), so the share
g . (bg - A bg - b) dT, nil at the identity, does not reach the Gaussians' opacities.

>>> bil = BilateralGrid(dev, n_images=100, lr=2e-3, tv=10.0)
>>> out = bil.apply(rgb_d, v, T_d)                       # [H, W, 3] device arrays
>>> grad_rgb_d = bil.backward_and_step(rgb_d, T_d, bg, grad_out_d, v)
"""
from __future__ import annotations

import numpy as np
import pyopencl.array as cla

from ..references.reference_bilateral import CHANNELS, IDENTITY, lr_factor, tv
from ..runtime.optim import ADAM_BETAS, ADAM_EPS, Optimizer
from ..runtime.programs import download, float4, launch, scratch, upload
from .base import COLOUR, VIEWS

SHAPE = (16, 16, 8)    # gsplat's grid: x bins, y bins, luminance bins
LR = 2e-3              # gsplat's Adam rate of the grids
TV_WEIGHT = 10.0       # gsplat's weight of the grids' total variation
WARMUP = 1000 / 30000  # the linear warm-up: gsplat's first 1,000 of 30,000 steps
FINAL = 0.01           # the rate's factor at the end of the budget (gsplat's decay to 1 %)


def program(device, luma_bins: int = SHAPE[2]):
    """cl/bilateral.cl for grids of ``luma_bins`` luminance bins (its one build per shape;
    clrf/training/catalog.py lists it through the splat kind's programs)."""
    return device.program("bilateral.cl", {"BILATERAL_L": int(luma_bins)})


class BilateralGrid:
    """The grids of ``n_images`` training images on ``device`` (module doc): ``shape`` (x, y,
    luminance bins), Adam at ``lr`` on gsplat's schedule, the prior's weight ``tv``; ``state``
    a checkpoint's entries (``state_dict``)."""
    name = "bilateral"
    changes = COLOUR
    batches = VIEWS

    def __init__(self, device, n_images: int, lr: float = LR, tv: float = TV_WEIGHT,
                 shape=SHAPE, state: dict | None = None, masked: bool = False,
                 sparse: bool = False):
        if n_images < 1:
            raise ValueError(f"BilateralGrid needs at least one image, got {n_images}")
        self.device, self.n_images = device, int(n_images)
        self.masked = bool(masked)
        self.lr_start = self.lr = float(lr)
        self.tv_weight = float(tv)
        self.sparse = bool(sparse)
        self.hold_until = 0.0
        steps = 0
        if state is None:
            gx, gy, gl = (int(s) for s in shape)
            grids = np.tile(IDENTITY.astype(np.float32), (self.n_images, gl, gy, gx, 1))
            m = v = np.zeros_like(grids)
        else:
            grids = np.asarray(state["bilateral_grid"], np.float32)
            m = np.asarray(state["bilateral_grid_m"], np.float32).reshape(grids.shape)
            v = np.asarray(state["bilateral_grid_v"], np.float32).reshape(grids.shape)
            steps = int(np.asarray(state["bilateral_grid_steps"]))
            self.hold_until = float(state.get("bilateral_grid_hold_until", 0.0))
            self.masked = bool(state.get("bilateral_grid_masked", masked))
            if grids.ndim != 5 or grids.shape[-1] != CHANNELS:
                raise ValueError(f"bilateral_grid: [V, L, GY, GX, {CHANNELS}] expected, got "
                                 f"{grids.shape}")
            self.n_images = grids.shape[0]
        self.shape = (grids.shape[3], grids.shape[2], grids.shape[1])   # (x, y, luminance)
        self.steps = steps
        # each grid's own Adam step count (sparse steps); a dense step counts in all of them
        self.view_steps = np.full(self.n_images, steps, np.int64)
        if state is not None and "bilateral_grid_view_steps" in state:
            self.view_steps = np.asarray(state["bilateral_grid_view_steps"], np.int64).copy()
        q = device.queue
        self.grids = upload(q, np.ascontiguousarray(grids).reshape(-1))   # flat [V L GY GX 12]
        self.cells = int(grids[0].size)                  # floats of one grid
        self._data = cla.zeros(q, self.cells, np.float32)   # view v's data gradient
        self._opt = Optimizer(device, self.grids, "adam", beta=ADAM_BETAS[0],
                              beta2=ADAM_BETAS[1], eps=ADAM_EPS,
                              grad=cla.zeros(q, self.grids.size, np.float32),
                              state=upload(q, np.ascontiguousarray(m).reshape(-1)),
                              state2=upload(q, np.ascontiguousarray(v).reshape(-1)))
        self._none = cla.zeros(q, 1, np.float32)        # T where a capture has no alpha
        self._prg = program(device, self.shape[2])

    # ---- the kernels ---------------------------------------------------------------------
    def _common(self, rgb, T, background, v: int):
        """(H, W, the kernels' leading arguments) of a render, checked: rgb float32 [H, W, 3],
        T float32 [H, W] (a masked capture's), both contiguous, v a row."""
        if rgb.dtype != np.float32 or rgb.ndim != 3 or rgb.shape[2] != 3 or \
                not rgb.flags.c_contiguous:
            raise ValueError(f"BilateralGrid: rgb must be a contiguous float32 [H, W, 3], got "
                             f"{rgb.dtype} {rgb.shape}")
        if not 0 <= v < self.n_images:
            raise ValueError(f"BilateralGrid: view {v} is not one of its {self.n_images}")
        H, W = (int(s) for s in rgb.shape[:2])
        gx, gy, _ = self.shape
        masked = self.masked and T is not None
        if masked and (T.dtype != np.float32 or T.size != H * W or not T.flags.c_contiguous):
            raise ValueError(f"BilateralGrid: T must be a contiguous float32 [{H}, {W}], got "
                             f"{T.dtype} {T.shape}")
        if masked and background is None:
            raise ValueError("BilateralGrid: a masked capture's render needs its background")
        bg = float4(*(float(c) for c in background[:3]), 0.0) if masked else \
            float4(0.0, 0.0, 0.0, 0.0)
        return H, W, (np.int32(H), np.int32(W), np.int32(gx), np.int32(gy), rgb.data,
                      np.int32(masked), (T if masked else self._none).data, bg)

    def apply(self, rgb, v: int, T=None, background=None):
        """View v's grid applied to its render ``rgb`` [H, W, 3] (a masked capture: its
        transmittance ``T`` [H, W] on ``background`` given), a new device array."""
        H, W, head = self._common(rgb, T, background, v)
        out = scratch(self.device, rgb.shape)
        launch(self.device, self._prg.kernel("bilateral_apply"), H * W,
               head + (self.grids.data, np.int32(v), out.data))
        return out

    def backward(self, rgb, T, background, grad_out, v: int, grid: bool = True):
        """(dL/drgb [H, W, 3], dL/dG of view v's grid [cells]) from dL/dout: new and the
        correction's own device arrays (the second is overwritten by the next call; not
        formed with ``grid`` False: held grids take no step)."""
        H, W, head = self._common(rgb, T, background, v)
        if grad_out.shape != rgb.shape or grad_out.dtype != np.float32:
            raise ValueError(f"BilateralGrid: grad_out must be float32 {rgb.shape}, got "
                             f"{grad_out.dtype} {grad_out.shape}")
        grad_rgb = scratch(self.device, rgb.shape)
        launch(self.device, self._prg.kernel("bilateral_backward_rgb"), H * W,
               head + (grad_out.data, self.grids.data, np.int32(v), grad_rgb.data))
        if grid:
            launch(self.device, self._prg.kernel("bilateral_backward_grid"),
                   self.shape[0] * self.shape[1], head + (grad_out.data, self._data.data))
        return grad_rgb, self._data

    def gradient(self, v: int):
        """The gradient of a step of view v into the optimiser's gradient: the data gradient
        of the last ``backward`` (v < 0: none) plus the prior's, tv / V times each grid's
        total-variation gradient (gsplat's loss); every grid's, or with ``sparse`` grid v's
        alone (the others' entries left as they are)."""
        gx, gy, _ = self.shape
        first, count = (v, 1) if self.sparse and v >= 0 else (0, self.n_images)
        launch(self.device, self._prg.kernel("bilateral_tv_grad"), count * self.cells,
               (np.int32(first), np.int32(count), np.int32(gx), np.int32(gy),
                self.grids.data, np.int32(v), self._data.data,
                np.float32(self.tv_weight / self.n_images), self._opt.grad.data))
        return self._opt.grad

    def step(self, v: int):
        """One Adam step from view v's data gradient and the prior's: of every grid, or with
        ``sparse`` of grid v alone (bias-corrected by its own step count)."""
        self.gradient(v)
        self.steps += 1
        if self.sparse and v >= 0:
            self.view_steps[v] += 1
            self._opt.step(None, self.lr, t=int(self.view_steps[v]),
                           spans=[(v * self.cells, (v + 1) * self.cells)])
            return
        self.view_steps += 1
        self._opt.step(None, self.lr, t=self.steps)

    # ---- the protocol (clrf/corrections/base.py) ----------------------------------------
    def background(self, v: int, background) -> tuple:
        """The scene's background: the grid transforms the render on it (masked captures keep
        it through ``apply``'s T)."""
        return tuple(float(c) for c in background[:3])

    def backward_and_step(self, rgb, T, background, grad_out, v: int):
        """dL/drgb (a new device array) from dL/dout, and an Adam step of the grids."""
        grad, _ = self.backward(rgb, T, background, grad_out, v)
        self.step(v)
        return grad

    def train_view(self, v: int, rgb, T, background, grad_out, progress: float, images,
                   scene_background):
        """``backward_and_step`` (gsplat trains the grids every step from the first); seeded
        grids (``seed``) are held, dL/drgb through them alone, before ``hold_until``."""
        if progress < self.hold_until:
            return self.backward(rgb, T, background, grad_out, v, grid=False)[0]
        return self.backward_and_step(rgb, T, background, grad_out, v)

    def seed(self, rows, hold_until: float = 0.0):
        """Every cell of image v's grid set to row v of ``rows`` P [V, 12] (an affine
        transform: A row-major, then b; an exposure calibration's, clrf/training/calibrate.py)
        in place of the identity, the grids held until the budget fraction ``hold_until``."""
        rows = np.asarray(rows, np.float64).reshape(-1, 12)
        if len(rows) != self.n_images or not np.all(np.isfinite(rows)):
            raise ValueError(f"BilateralGrid.seed: {self.n_images} finite rows of 12 expected, "
                             f"got {rows.shape}")
        cell = np.concatenate([rows[:, :9].reshape(-1, 3, 3), rows[:, 9:, None]], axis=2)
        gx, gy, gl = self.shape
        grids = np.broadcast_to(cell.reshape(-1, 1, 1, 1, CHANNELS),
                                (self.n_images, gl, gy, gx, CHANNELS))
        self.grids.set(np.ascontiguousarray(grids, np.float32).reshape(-1))
        self.hold_until = float(hold_until)

    def schedule(self, progress: float) -> None:
        """gsplat's rate at the budget fraction ``progress``: warm-up, then the decay."""
        self.lr = self.lr_start * lr_factor(progress, WARMUP, FINAL)

    def after_pass(self) -> None:
        """Nothing: the prior and the identity start hold the grids (gsplat recentres none)."""

    def host_grids(self) -> np.ndarray:
        """The grids [V, L, GY, GX, 12] on the host."""
        gx, gy, gl = self.shape
        return download(self.grids).reshape(self.n_images, gl, gy, gx, CHANNELS)

    def state_dict(self) -> dict:
        grids = self.host_grids()
        shape = grids.shape
        return {"bilateral_grid": grids,
                "bilateral_grid_m": download(self._opt.state).reshape(shape),
                "bilateral_grid_v": download(self._opt.state2).reshape(shape),
                "bilateral_grid_steps": np.array(self.steps, np.int64),
                "bilateral_grid_view_steps": self.view_steps.copy(),
                "bilateral_grid_hold_until": self.hold_until,
                "bilateral_grid_masked": self.masked}

    def summary(self) -> dict:
        """eval.json's ``bilateral_correction``: the shape, the images, the grids' mean
        distance from the identity and their mean total variation."""
        g = self.host_grids().astype(np.float64)
        return {"images": self.n_images, "shape": list(self.shape), "steps": self.steps,
                "mean_abs_deviation": float(np.abs(g - IDENTITY).mean()),
                "mean_tv": float(np.mean([tv(x) for x in g]))}

    def report(self, summary: dict) -> str:
        gx, gy, gl = summary["shape"]
        return (f"bilateral grids ({gx} x {gy} x {gl} cells) of {summary['images']} training "
                f"images after {summary['steps']} steps: mean |G - I| "
                f"{summary['mean_abs_deviation']:.4f}, mean total variation "
                f"{summary['mean_tv']:.3g}; the test views are scored without them")

    def describe(self) -> str:
        """'bilateral |G - I| 0.0123 over 100 images' for progress lines."""
        g = download(self.grids).astype(np.float64).reshape(-1, CHANNELS)
        return f"bilateral |G - I| {np.abs(g - IDENTITY).mean():.4f} over {self.n_images} images"
