"""SplatModel: 3D Gaussian splatting (Kerbl et al. 2023) trained on whole views, on the device
rasteriser of clrf/splat/raster.py.

A step renders one training view (a seeded permutation of the training views, cycled), takes
the loss (1 - lambda) L1 + lambda (1 - SSIM) against the image, and runs the rasteriser's and
the projection's backward and one Adam update per parameter group (means, log scales,
quaternions, opacity logits: clrf/runtime/optim.py; SH coefficients: cl/splat_train.cl, which
gives degree 0 and the higher bands their own rates and leaves the inactive bands alone).

The loss and dL/drgb are computed on the device (clrf/splat/loss.py, cl/splat_loss.cl: an
11 x 11 Gaussian window, sigma 1.5, zero padding); the training images are uploaded once (as
uint8 where that is exact, else float16: clrf/splat/targets.py), so a step moves no image
between host and device and reads back the one pair count of the binning; where the device's
memory is the host's they are streamed instead, a step copying its one image
(splat.images_on_device).
The loss statistics are read when the trainer asks for the step's error.

The model holds the per-view corrections its section turns on (``corrections``: a colour
transform per image, a pose correction per camera; clrf/corrections/) and calls their list's
hooks: the corrected camera and the background of a view, what the loss sees of its render,
the colour's backward and step, the camera's step from the projection's camera gradient, the
schedules and the recentring after each pass over the views.

Between steps (on_iteration) the budget fraction drives the means' learning-rate decay, the
SH degree's increase and the density strategy (splat.strategy, clrf/splat/strategies/: the
published clone / split / prune with opacity resets, or MCMC's relocation under a fixed cap).
The strategy owns its running statistics and takes the step's parameters, gradients, moments
and render record through its hooks (strategies/base.py). A refinement runs on the host
where it changes the count: it downloads the parameters and moments, the strategy edits them
with numpy (clrf/splat/params.py edit_rows) and they are uploaded again. The parameters, their
moments and learning rates follow one table (clrf/splat/params.py TABLE).
"""
from __future__ import annotations

from dataclasses import asdict

import numpy as np
import pyopencl.array as cla

from ..corrections import VIEWS, Corrections, Views, build, from_state
from ..interface import Budget, StateError, Unsupported
from ..runtime.hostmem import release_free_heap
from ..runtime.optim import ADAM_BETAS, AdamSet, Optimizer, expon_lr
from ..runtime.pending import Pending
from ..runtime.programs import device_zeros, download, launch, scratch, upload
from .config import SplatConfig
from .loss import STATS, DeviceLoss
from .params import NAMES, learning_rates, moment_keys
from .raster import PARAM_NAMES, SplatCamera, SplatRasterizer, camera_gradient, default_tile
from .strategies import RenderInfo, logit, make_strategy, strategy_class
from .targets import DeviceImages, ViewImages, resident

assert NAMES == PARAM_NAMES, "clrf/splat/params.py TABLE and the rasteriser's PARAM_NAMES"

SH_C0 = 0.28209479177387814     # degree-0 SH basis value (colour = 0.5 + SH_C0 dc)
OPENGL_TO_OPENCV = np.diag([1.0, -1.0, -1.0, 1.0])
CAMERA_NEAR = 0.01
FILTER3D_EVERY = 100            # steps between recomputations of the 3D filter (Mip-Splatting)


class NotExportable(Unsupported, NotImplementedError):
    """What a splat model cannot export (a density field for --mesh / --points)."""


def viewmat_of(c2w) -> np.ndarray:
    """World-to-camera (OpenCV axes) of a camera-to-world pose in OpenGL axes."""
    return OPENGL_TO_OPENCV @ np.linalg.inv(np.asarray(c2w, np.float64))


def camera_of(c2w, intrinsics, hw) -> SplatCamera:
    fx, fy, cx, cy = (float(v) for v in intrinsics)
    return SplatCamera(viewmat_of(c2w), fx, fy, cx, cy, int(hw[1]), int(hw[0]), CAMERA_NEAR)


# ---- the model ------------------------------------------------------------------------------
GROUPS = ("means", "log_scales", "quats", "opacity_logits")   # Adam from clrf/runtime/optim.py
#                                     (the SH coefficients: cl/splat_train.cl splat_adam_sh)


class SplatModel:
    kind = "splat"
    view_dependent = True

    def __init__(self, device, config: SplatConfig, host: dict, background, extent: float,
                 bbox, seed: int = 0, max_count: int | None = None):
        self.device = device
        self.config = config
        self.background = tuple(float(b) for b in background)
        self.extent = float(extent)
        self.bbox = np.asarray(bbox, np.float64).reshape(2, 3)
        self.seed = int(seed)
        self.max_count = int(max_count if max_count is not None else config.max_gaussians)
        self.rast = SplatRasterizer(device, config.sh_degree, default_tile(device),
                                    antialiased=config.antialiased,
                                    filter2d=config.aa_filter2d)
        self.n_basis = self.rast.n_basis
        self.step = 0                  # Adam updates so far
        # the step's loss stays on the device until read (GPU shapes; train_step)
        self.defer_loss = bool(getattr(device.tuning, "gpu_kernels", False))
        self.active_degree = 0
        self.lr_means = config.lr_position * self.extent
        # density control (splat.strategy): its settings, schedule and statistics
        self.strategy = make_strategy(config, device, self.seed)
        self.progress = 0.0
        self._ds = None                # the training views (create, or loaded on demand)
        self._loss_fn = None           # DeviceLoss for the views' size
        self.corrections = Corrections()   # per-view corrections (clrf/corrections; attach)
        self.filter3d = None           # f2 [n] of the 3D filter (splat.antialiased; None: stale)
        self.filter_step = -1          # the step it was computed at
        self._targets = None           # DeviceImages: the training images on the device
        self.train_views = None
        self.hw = None
        self._set_host(host)

    # ---- parameters on the device ---------------------------------------------------------
    def _set_host(self, host: dict, moments: dict | None = None, stats: dict | None = None):
        """Upload parameters (and Adam moments, zeros where absent) and the strategy's
        statistics (``stats``: its ``host_rows``; None: zeros)."""
        q = self.device.queue
        n = int(host["means"].shape[0])
        self.params = {k: upload(q, np.ascontiguousarray(host[k], np.float32)) for k in NAMES}
        moments = moments or {}

        def mom(key, like):
            a = moments.get(key)
            return upload(q, np.ascontiguousarray(a if a is not None else np.zeros_like(like),
                                                  np.float32))
        # Adam's two moments of every table entry
        self.moments = {k: tuple(mom(mk, host[k]) for mk in moment_keys(k)) for k in NAMES}
        b1, b2 = ADAM_BETAS
        self.opts = {k: Optimizer(self.device, self.params[k], "adam", beta=b1, beta2=b2,
                                  eps=self.config.adam_eps, state=self.moments[k][0],
                                  state2=self.moments[k][1])
                     for k in GROUPS}
        # GPU shapes: every group in one launch (the SH coefficients have their own kernel)
        self._adam_groups = (AdamSet(self.device, [self.opts[k] for k in GROUPS])
                             if getattr(self.device.tuning, "gpu_kernels", False) else None)
        self.strategy.allocate(n, stats)
        self.n = n
        self.filter3d = None   # the Gaussians changed: the 3D filter is recomputed when needed

    # ---- anti-aliasing ----------------------------------------------------------------------
    def training_cameras(self) -> list:
        """The SplatCameras of the training views (as the corrections render them)."""
        ds = self._dataset()
        return [self.corrections.camera(camera_of(ds.poses[v], ds.intrinsics, ds.hw), v)
                for v in self.train_views]

    def update_filter(self):
        """Recompute each Gaussian's 3D filter from the training cameras (splat.antialiased:
        after the Gaussians change, and every FILTER3D_EVERY steps as they move)."""
        self.filter3d = self.rast.filter3d(self.params["means"], self.training_cameras())
        self.filter_step = self.step

    def _rparams(self) -> dict:
        """The rasteriser's inputs: the parameters, and the 3D filter when anti-aliased (a
        model without training views and without a stored filter renders with f2 = 0)."""
        if not self.rast.antialiased:
            return self.params
        if self.filter3d is None:
            if self._ds is not None:
                self.update_filter()
            else:
                self.filter3d = scratch(self.device, (self.n,))
                self.filter3d.fill(0.0)
        return dict(self.params, filter3d=self.filter3d)

    def host_params(self) -> dict:
        return {k: download(v) for k, v in self.params.items()}

    def host_moments(self) -> dict:
        return {mk: download(a) for k in NAMES for mk, a in zip(moment_keys(k), self.moments[k])}

    # ---- the dataset ----------------------------------------------------------------------
    def attach(self, ds, max_images: int = 0):
        """Train on ``ds``'s training views (the first max_images; 0: all)."""
        views = np.asarray(ds.split["train"])
        if max_images:
            views = views[:max_images]
        if len(views) == 0:
            raise ValueError(f"dataset {ds.name}: no training views")
        self._ds, self.train_views, self.hw = ds, views, tuple(int(v) for v in ds.hw)
        self._loss_fn = self._targets = None
        # a row per image of the dataset (a checkpoint's corrections kept where they fit)
        views = Views(len(ds.images), ds.alpha is not None, scale=self.extent,
                      pivots=lambda: [self.pivot_depth(c2w) for c2w in ds.poses])
        self.corrections = build(self.device, self.config, views, VIEWS, self.corrections)

    def pivot_depth(self, c2w) -> float:
        """The depth of the scene box's centre in camera ``c2w`` (0 where it lies behind): the
        point a camera correction turns the camera about (clrf/corrections/pose.py)."""
        centre = np.append(self.bbox.mean(0), 1.0)
        return max(float((viewmat_of(c2w) @ centre)[2]), 0.0)

    def _dataset(self):
        if self._ds is None:
            # a model from a checkpoint has none until the trainer attaches the dataset
            raise RuntimeError("the splat model has no training views: call attach(dataset) "
                               "first (the trainer does, after create and on resume)")
        return self._ds

    def view_of(self, it: int) -> int:
        """The training view of step ``it``: a seeded permutation per pass over the views."""
        self._dataset()
        k = len(self.train_views)
        epoch, j = divmod(int(it), k)
        perm = np.random.default_rng((self.seed, epoch)).permutation(k)
        return int(self.train_views[perm[j]])

    # ---- Model protocol -------------------------------------------------------------------
    @property
    def batch_size(self) -> int:
        """Pixels of a training view (1 without training views)."""
        return 1 if self.hw is None else self.hw[0] * self.hw[1]

    @property
    def sample_length(self) -> float:
        return 1.0   # no ray marching; export's density level does not apply (export_fields)

    def train_step(self, it, origins=None, dirs=None, target=None, background=None):
        """One Adam step on the whole training view of step ``it`` (the rays' arguments are
        unused: Kind.batches "views"); returns the view's mean squared error: a float, or with
        ``defer_loss`` (the GPU shapes) a Pending the trainer reads when it reports."""
        ds = self._dataset()
        v = self.view_of(it)
        corr = self.corrections
        cam = corr.camera(camera_of(ds.poses[v], ds.intrinsics, ds.hw), v)
        bg = corr.background(v, self.background)   # what a colour correction takes to it
        if self.rast.antialiased and self.step - self.filter_step >= FILTER3D_EVERY:
            self.filter3d = None
        params = self._rparams()
        proj, bins, ras = self.rast.forward(params, cam, bg)
        # the loss sees the render as the colour correction shows it (the render without one)
        grad, stats = self._loss().loss_and_grad(corr.apply(ras.rgb, v, ras.T, bg),
                                                  self._target(v))
        grad = corr.colour_backward(v, ras.rgb, ras.T, bg, grad, self.progress, ds.images,
                                    self.background)
        absgrad = self.strategy.absgrad
        g2d = self.rast.rasterize_backward(proj, bins, ras, cam, grad, bg, absgrad=absgrad)
        moved = corr.moves_cameras
        grads = self.rast.project_backward(params, cam, g2d, camera_grad=moved)
        if moved:   # reads twelve numbers: the camera's gradient
            corr.camera_step(v, cam.viewmat, *camera_gradient(grads["camera"]))
        self.strategy.step_post_backward(
            self.params, grads, self.moments, self.step,
            RenderInfo(proj.radius, g2d["xy_abs" if absgrad else "xy"], int(cam.width),
                       int(cam.height)))
        self.step += 1
        self._adam(grads, self.step)
        self.strategy.step_post_update(self.params, self.moments, self.step, self.lr_means)
        if self.step % len(self.train_views) == 0:
            corr.after_pass()           # after each pass over the views
        if self.defer_loss:
            return Pending(self.device.queue, stats[STATS.index("mse"):][:1])
        return self._loss_fn.read(stats)["mse"]

    def _adam(self, grads, t: int):
        """Adam step t of every parameter from grads (device arrays by PARAM_NAMES): the four
        groups in one launch (GPU shapes) or a launch each, then the SH coefficients."""
        c = self.config
        prg = self.device.program("splat_train.cl")
        lrs = learning_rates(c, self.lr_means)
        if self.lr_scale != 1.0:   # a batch of views (clrf/splat/distributed.py)
            lrs = {k: (tuple(self.lr_scale * x for x in v) if isinstance(v, tuple)
                       else self.lr_scale * v) for k, v in lrs.items()}
        for k in GROUPS:
            self.opts[k].grad = grads[k]
        if self._adam_groups is not None:
            self._adam_groups.step([lrs[k] for k in GROUPS], t)
        else:
            for k in GROUPS:
                self.opts[k].step(None, lrs[k], t=t)
        b1, b2 = ADAM_BETAS
        nsh = int(self.params["sh"].size)
        sh_m, sh_v = self.moments["sh"]
        lr_dc, lr_rest = lrs["sh"]
        launch(self.device, prg.kernel("splat_adam_sh"), nsh,
               (np.int32(nsh), self.params["sh"].data, grads["sh"].data, sh_m.data,
                sh_v.data, np.float32(lr_dc), np.float32(lr_rest),
                np.float32(b1), np.float32(b2), np.float32(c.adam_eps),
                np.float32(1 - b1 ** t), np.float32(1 - b2 ** t), np.int32(self.n_basis),
                np.int32((self.active_degree + 1) ** 2)))

    def _loss(self) -> DeviceLoss:
        """The device loss for the training views' size (built on first use)."""
        if self._loss_fn is None:
            self._loss_fn = DeviceLoss(self.device, self.hw[0], self.hw[1],
                                       self.config.lambda_dssim)
        return self._loss_fn

    def _target(self, v: int):
        """Training image v on the device as float32 (all of them uploaded at the first step,
        stored as uint8 or float16, or streamed from the host a step at a time:
        splat.images_on_device, clrf/splat/targets.py)."""
        if self._targets is None:
            ds = self._dataset()
            self._targets = DeviceImages(
                self.device, ViewImages(ds.images, self.train_views),
                resident(self.config.images_on_device, self.device.caps))
        return self._targets.get(v)

    def on_iteration(self, it: int, budget: Budget):
        """Schedules from the budget fraction: the means' and the corrections' rates, the SH
        degree and the density strategy's (refinement, opacity resets). Returns a log line when
        the Gaussians changed."""
        c = self.config
        f = float(budget.fraction)
        self.progress = f
        self.lr_means = expon_lr(f, c.lr_position * self.extent,
                                 c.lr_position_final * self.extent, 1.0)
        self.active_degree = min(c.sh_degree, int(f / c.sh_increase_every))
        self.corrections.schedule(f)
        msgs = [self.refine()] if self.strategy.refine_due(it, f, self.step) else []
        msgs += self.strategy.step_schedule(self.params, self.moments, f, self.step)
        return "; ".join(msgs) or None

    def refine(self) -> str:
        """One refinement of the density strategy now; the count stays at or below the cap.
        In place on the device where the strategy can (``refine_in_place``); else host side:
        the parameters and moments down, the device's copies released (so that the edit's
        peak holds two host copies, not those and two device copies), the strategy's edit, up
        again. Returns a log line."""
        rng = np.random.default_rng((self.seed, 7, self.step))
        msg = self.strategy.refine_in_place(self, self.max_count, rng)
        if msg is not None:
            return msg
        mo, stats = self.host_moments(), self.strategy.host_rows()
        host = self.host_params()
        self._release()
        # the pool's per-step buffers are sized by the count, which this edit changes: return
        # them, or every size the count has passed through stays held (clrf/runtime/device.py)
        self.device.pool.free_held()
        host, moments, msg = self.strategy.refine(host, mo, stats, extent=self.extent,
                                                  cap=self.max_count, rng=rng)
        del mo, stats
        self._set_host(host, moments)
        del host, moments
        release_free_heap()   # the host copies' pages (hostmem.release_free_heap)
        return msg

    def _release(self):
        """Drops the device's parameters, moments, optimisers and statistics (``_set_host``
        makes new ones)."""
        self.params = self.moments = self.opts = self._adam_groups = None
        self.strategy.release()
        self.filter3d = None

    def get_rows(self, name: str, idx=None) -> np.ndarray:
        """Parameter ``name`` from the device as numpy: every row, or rows ``idx`` only
        (gathered on the device, pyopencl's take)."""
        a = self.params[name]
        if idx is None:
            return download(a)
        idx = np.asarray(idx, np.int64)
        if idx.size == 0:
            return np.zeros((0,) + a.shape[1:], np.float32)
        got = cla.take(a.reshape(-1), self._flat_rows(a, idx))
        return got.get().reshape((len(idx),) + a.shape[1:])

    def _flat_rows(self, a, idx):
        """The flat indices (a device array) of rows ``idx`` of device array ``a``."""
        w = int(np.prod(a.shape[1:], dtype=np.int64))
        return cla.to_device(self.device.queue, (idx[:, None] * w + np.arange(w)).reshape(-1))

    def put_rows(self, idx, rows: dict):
        """In place on the device, as ``params.edit_rows(assign=(idx, rows))`` on the host:
        rows ``idx`` of each named parameter set to ``rows[name]``, and the Adam moments (of
        every parameter) and the strategy's statistics of those rows zeroed. A row listed
        twice must be given the same values twice."""
        idx = np.asarray(idx, np.int64)
        if idx.size == 0:
            return
        if idx.min() < 0 or idx.max() >= self.n:
            raise IndexError(f"put_rows: rows must be in 0..{self.n - 1}")
        q = self.device.queue
        zero = device_zeros(q, 1, np.float32)
        for k in NAMES:
            a = self.params[k]
            flat = self._flat_rows(a, idx)
            if k in rows:
                v = np.ascontiguousarray(rows[k], np.float32).reshape(-1)
                if v.size != flat.size:
                    raise ValueError(f"put_rows: {k} needs {flat.size // len(idx)} floats a row")
                cla.multi_put([cla.to_device(q, v)], flat, out=[a.reshape(-1)])
            cla.multi_put([zero, zero], flat, out=[m.reshape(-1) for m in self.moments[k]])
        self.strategy.zero_rows(idx)
        self.filter3d = None   # the Gaussians changed: the 3D filter is recomputed when needed

    def render(self, origins, dirs) -> dict:
        raise Unsupported("the splat model renders whole cameras, not single rays (so --points "
                          "does not apply: export its Gaussians with --splats FILE.ply)")

    def render_image(self, c2w, intrinsics, hw, depth: bool = True) -> dict:
        """rgb [H, W, 3], acc [H, W] (1 - the final transmittance) and, with ``depth``, depth
        [H, W] (the opacity-weighted mean camera depth of the splats, 0 where nothing is
        seen; composited in the same raster pass, RENDER_DEPTH) of one camera."""
        ras = self._render_raster(camera_of(c2w, intrinsics, hw), depth)
        out = {"rgb": download(ras.rgb), "acc": (1.0 - download(ras.T)).astype(np.float32)}
        if depth:
            zs, acc = download(ras.depth), out["acc"]
            out["depth"] = np.where(acc > 1e-6, zs / np.maximum(acc, 1e-6), 0.0).astype(
                np.float32)
        return out

    def _render_raster(self, cam, depth: bool):
        """The Raster of camera ``cam`` over the model's background (render_image's)."""
        return self.rast.forward(self._rparams(), cam, self.background, depth=depth)[2]

    def export_fields(self, points, dirs):
        raise NotExportable("a splat model has no density field to mesh or sample: --mesh and "
                            "--points do not apply; export the Gaussians with --splats FILE.ply")

    def refine_view_pose(self, c2w, intrinsics, hw, image, steps: int, lr: float, rays=None):
        """Test-time pose refinement (BARF's protocol for runs that refine their poses): ``steps``
        Adam steps of a correction of this one camera (clrf/corrections/pose.py, turned about the
        scene's centre, no pull toward the given pose) against ``image`` [H, W, 3] under the
        training loss, the Gaussians held still, the rate falling log-linearly from ``lr`` to a
        tenth of it. ``rays`` (the ray models' camera rays) is not used: the model renders the
        whole camera. Returns (the corrected camera-to-world pose, the correction's summary)."""
        from ..corrections.pose import PoseCorrection
        if steps < 1 or not lr > 0:
            raise ValueError(f"refine_view_pose: steps >= 1 and lr > 0, got {steps}, {lr}")
        H, W = (int(x) for x in hw)
        cam0 = camera_of(c2w, intrinsics, (H, W))
        pc = PoseCorrection(1, lr, 0.0, self.extent, pivots=[self.pivot_depth(c2w)])
        loss = (self._loss() if self.hw is not None and tuple(self.hw) == (H, W)
                else DeviceLoss(self.device, H, W, self.config.lambda_dssim))
        target = upload(self.device.queue, np.ascontiguousarray(image, np.float32))
        params = self._rparams()
        for k in range(int(steps)):
            pc.lr = expon_lr(k, lr, 0.1 * lr, int(steps) - 1)
            cam = pc.camera(cam0, 0)
            proj, bins, ras = self.rast.forward(params, cam, self.background)
            grad, _ = loss.loss_and_grad(ras.rgb, target)
            g2d = self.rast.rasterize_backward(proj, bins, ras, cam, grad, self.background)
            out = self.rast.project_backward(params, cam, g2d, camera_grad=True)
            pc.step(0, cam.viewmat, *camera_gradient(out["camera"]))
        V = pc.viewmat(cam0.viewmat, 0)
        return np.linalg.inv(OPENGL_TO_OPENCV @ V), pc.summary([0])

    def export_block(self, block: int) -> int:
        return max(1, min(int(block), 1 << 20))

    def native_reso(self, bbox):
        raise NotExportable("a splat model has no density field to mesh: --mesh does not "
                            "apply; export the Gaussians with --splats FILE.ply")

    initialised_from = ""   # create_model: where the first Gaussians came from
    lr_scale = 1.0          # the learning rates' factor (a batch of views: distributed.py)

    def describe(self) -> str:
        start = f" (from {self.initialised_from})" if self.step == 0 and \
            self.initialised_from else ""
        corr = f", {self.corrections.describe()}" if self.corrections and self.step else ""
        return f"{self.n} Gaussians, SH degree {self.active_degree}{start}{corr}"

    # ---- checkpoints ----------------------------------------------------------------------
    def state_dict(self) -> dict:
        st = {"kind": self.kind, "config": asdict(self.config),
              "background": list(self.background), "extent": self.extent,
              "bbox": self.bbox.tolist(), "seed": self.seed, "max_count": self.max_count,
              "step": self.step, "active_degree": self.active_degree,
              "progress": self.progress, "lr_means": self.lr_means}
        st.update(self.strategy.state_dict())
        for k, v in self.host_params().items():
            st[f"param_{k}"] = v
        for k, v in self.host_moments().items():
            st[f"adam_{k}"] = v
        st.update(self.corrections.state_dict())
        if self.rast.antialiased:
            st["filter3d"] = download(self._rparams()["filter3d"])
        return st

    @classmethod
    def from_state_dict(cls, device, state: dict) -> "SplatModel":
        if state.get("kind") != cls.kind:
            raise StateError(f"state_dict: kind is {state.get('kind')!r}, expected 'splat'")
        try:
            config = SplatConfig.from_dict(dict(state["config"]))
            host = {k: np.asarray(state[f"param_{k}"], np.float32) for k in PARAM_NAMES}
            moments = {k[5:]: np.asarray(v, np.float32) for k, v in state.items()
                       if k.startswith("adam_")}
        except (KeyError, ValueError, TypeError) as e:
            raise StateError(f"not a splat model's state ({e})") from None
        n, nb = host["means"].shape[0], (config.sh_degree + 1) ** 2
        want = {"means": (n, 3), "log_scales": (n, 3), "quats": (n, 4),
                "opacity_logits": (n,), "sh": (n, nb, 3)}
        for k, shape in want.items():
            if host[k].shape != shape:
                raise StateError(f"state_dict['param_{k}']: shape {host[k].shape}, expected "
                                 f"{shape}")
        m = cls(device, config, host, tuple(state["background"]), float(state["extent"]),
                state["bbox"], int(state["seed"]), int(state["max_count"]))
        m._set_host(host, moments)
        if config.antialiased and "filter3d" in state:
            f2 = np.ascontiguousarray(state["filter3d"], np.float32)
            if f2.shape != (n,):
                raise StateError(f"state_dict['filter3d']: shape {f2.shape}, expected ({n},)")
            m.filter3d = upload(device.queue, f2)
        m.corrections = from_state(device, config, state, Views(scale=m.extent), VIEWS)
        m.step = int(state["step"])
        m.active_degree = int(state["active_degree"])
        try:
            m.strategy.load_state_dict(state, n)
        except ValueError as e:
            raise StateError(f"state_dict: the strategy's {e}") from None
        m.progress = float(state["progress"])
        m.lr_means = float(state["lr_means"])
        return m


def scene_extent(ds) -> float:
    """1.1 times the largest distance of a training camera from their mean centre (the scale
    the published learning rates and size thresholds are relative to)."""
    c = np.asarray(ds.poses)[np.asarray(ds.split["train"]), :3, 3].astype(np.float64)
    r = float(np.linalg.norm(c - c.mean(0), axis=1).max()) if len(c) else 0.0
    return 1.1 * r if r > 0 else float(np.linalg.norm(np.subtract(*ds.bbox)))


def _gaussians_at(config: SplatConfig, means, rgb, rng) -> dict:
    """Gaussians at ``means`` [n, 3] with colours ``rgb`` [n, 3] in [0, 1] (degree 0 only):
    isotropic scales from the mean squared distance to the 3 nearest neighbours (times the
    strategy's first size factor), its first opacity, no rotation (Strategy.first: the
    published initialisation 1 and 0.1; MCMC's 0.1 and 0.5)."""
    from scipy.spatial import cKDTree
    means = np.asarray(means, np.float64)
    n = len(means)
    k = min(4, n)
    if k > 1:
        d, _ = cKDTree(means).query(means, k=k)
        d2 = np.mean(d[:, 1:] ** 2, axis=1)
    else:
        d2 = np.full(n, 1e-2)
    opacity, size = strategy_class(config.strategy).first(config)
    log_s = np.log(np.sqrt(np.maximum(d2, 1e-14)) * size)
    nb = (config.sh_degree + 1) ** 2
    sh = np.zeros((n, nb, 3), np.float32)
    sh[:, 0, :] = (np.asarray(rgb, np.float64) - 0.5) / SH_C0
    quats = np.zeros((n, 4), np.float32)
    quats[:, 0] = 1
    return {"means": means.astype(np.float32),
            "log_scales": np.repeat(log_s[:, None], 3, 1).astype(np.float32),
            "quats": quats, "opacity_logits": np.full(n, logit(opacity), np.float32),
            "sh": sh}


def frustum_means(ds, n: int, rng) -> np.ndarray:
    """n random points [n, 3] in the training views' frusta of a world-space forward-facing
    dataset ``ds`` (clrf/data/world.py): a training view uniformly, a point uniform over its
    image (pinhole, as the rasteriser), a depth along its axis uniform in 1 / depth between
    the view's bounds (``ds.depth_bounds``), as NDC spaces the volumetric models' samples."""
    b = np.asarray(ds.depth_bounds, np.float64)
    views = np.asarray(ds.split["train"])
    pick = views[rng.integers(0, len(views), n)]
    H, W = ds.hw
    fx, fy, cx, cy = (float(v) for v in ds.intrinsics)
    u = rng.uniform(0.0, W, n)
    v = rng.uniform(0.0, H, n)
    d_cam = np.stack([(u - cx) / fx, -(v - cy) / fy, -np.ones(n)], 1)   # OpenGL axes, z = -1
    p = np.asarray(ds.poses, np.float64)[pick]
    inv = rng.uniform(1.0 / b[pick, 1], 1.0 / b[pick, 0])
    return p[:, :3, 3] + np.einsum("nij,nj->ni", p[:, :3, :3], d_cam) / inv[:, None]


def initial_gaussians(config: SplatConfig, n: int, bbox, seed: int, outer: float = 0.0,
                      frusta=None) -> dict:
    """n Gaussians uniform in ``bbox`` [2, 3], grey (colour 0.5 plus at most 1/255 of SH
    degree 0, as the published code starts random points: a random colour per Gaussian costs
    hundreds of steps at the published SH rate to undo); with ``outer`` > 1 (an
    unbounded scene whose cameras sit in the box), as many again beyond the box, out to
    ``outer`` times its half-size from its centre: directions uniform and distances uniform in
    1 / r, so that each shell the cameras see at a similar angular size holds a similar
    number (what the far background needs). ``frusta``: a world-space forward-facing dataset,
    whose training views' frusta between their depth bounds take the n instead of the box
    (``frustum_means``)."""
    rng = np.random.default_rng((seed, 1))
    lo, hi = np.asarray(bbox, np.float64)
    if frusta is not None:
        means = frustum_means(frusta, n, rng)
    else:
        means = rng.uniform(lo, hi, (n, 3))
    if outer > 1.0:
        centre, half = 0.5 * (lo + hi), 0.5 * (hi - lo)
        d = rng.normal(size=(n, 3))
        d /= np.maximum(np.linalg.norm(d, axis=1, keepdims=True), 1e-12)
        r = 1.0 / rng.uniform(1.0 / outer, 1.0, n)
        means = np.concatenate([means, centre + d * (r[:, None] * half.max())])
    rgb = 0.5 + SH_C0 * rng.uniform(0.0, 1.0 / 255.0, (len(means), 3))
    return _gaussians_at(config, means, rgb, rng)


def gaussians_from_points(config: SplatConfig, points, n: int, seed: int) -> dict:
    """Gaussians at a capture's sparse points [P, 6] (xyz, RGB in [0, 1]), a seeded random
    subset of n when there are more."""
    rng = np.random.default_rng((seed, 2))
    pts = np.asarray(points, np.float64)
    if len(pts) > n:
        pts = pts[np.sort(rng.choice(len(pts), n, replace=False))]
    return _gaussians_at(config, pts[:, :3], np.clip(pts[:, 3:6], 0, 1), rng)


def gaussians_from_ply(sc: SplatConfig, path, cap: int) -> tuple[dict, str]:
    """(the Gaussians of splat file ``path`` (any ending files.py reads) at sh_degree,
    where they came from); more than ``cap`` of them is refused (SplatFileError, a bad input)
    with the fix."""
    from .files import read_splat_file
    from .ply import SplatFileError
    g = read_splat_file(path)
    n = len(g["means"])
    if n == 0:
        raise SplatFileError(f"{path}: holds no Gaussians; pass a splat file with some, or "
                             f"leave splat.init_ply empty")
    if n > cap:
        raise SplatFileError(f"{path}: {n} Gaussians exceed the cap of {cap} (splat."
                             f"max_gaussians and what fits this device's memory); raise "
                             f"splat.max_gaussians if it is lower, or train on a device with "
                             f"more memory, or thin the file")
    nb = (sc.sh_degree + 1) ** 2
    sh = np.zeros((n, nb, 3), np.float32)
    k = min(nb, g["sh"].shape[1])
    sh[:, :k] = g["sh"][:, :k]
    degree = int(round(g["sh"].shape[1] ** 0.5)) - 1
    host = {"means": g["means"], "log_scales": g["log_scales"], "quats": g["quats"],
            "opacity_logits": g["opacity_logits"], "sh": sh}
    return ({k_: np.ascontiguousarray(v, np.float32) for k_, v in host.items()},
            f"{n} Gaussians of {path} (SH degree {degree})")


UNBOUNDED_REACH = 16.0   # random init of unbounded scenes: out to 16 box half-sizes


def limit_scales(host: dict, ds, max_px: float) -> dict:
    """``host`` with every Gaussian's scales at most ``max_px`` pixels of the nearest training
    view of ``ds`` that has it in front (depth z: max_px z / fx); Gaussians no training view
    has in front stay as they are."""
    views = np.asarray(ds.split["train"])
    p = np.asarray(ds.poses, np.float64)[views]
    m = np.asarray(host["means"], np.float64)
    z = np.full(len(m), np.inf)
    for c2w in p:   # the depth along each view's axis (OpenGL: the camera looks down -z)
        d = (m - c2w[:3, 3]) @ -c2w[:3, 2]
        z = np.minimum(z, np.where(d > CAMERA_NEAR, d, np.inf))
    cap = np.log(max_px * np.where(np.isfinite(z), z, 1.0) / float(ds.intrinsics[0]))
    cap = np.where(np.isfinite(z), cap, np.inf)[:, None]
    return dict(host, log_scales=np.minimum(host["log_scales"], cap).astype(np.float32))


def initial_host(sc: SplatConfig, ds, cap: int, seed: int) -> tuple[dict, str]:
    """(the first Gaussians of a run on dataset ``ds`` under the cap, where they came from);
    their scales limited to splat.init_max_pixels where it is set (a splat PLY is taken as
    it is)."""
    if sc.init_ply:
        return gaussians_from_ply(sc, sc.init_ply, cap)
    host, where = _initial_host(sc, ds, cap, seed)
    if sc.init_max_pixels > 0:
        host = limit_scales(host, ds, sc.init_max_pixels)
    return host, where


def _initial_host(sc: SplatConfig, ds, cap: int, seed: int) -> tuple[dict, str]:
    points = getattr(ds, "points", None)
    has_points = points is not None and len(points) > 0
    if sc.init == "points" and not has_points:
        raise Unsupported(no_points_message(ds))
    if sc.init != "random" and has_points:
        n = max(1, min(len(points), sc.init_points, cap))
        return (gaussians_from_points(sc, points, n, seed),
                f"{n} of the capture's {len(points)} sparse points")
    if forward_facing(ds):
        n = max(1, min(sc.init_points, cap))
        return (initial_gaussians(sc, n, ds.bbox, seed, frusta=ds),
                f"{n} random in the training views' frusta between their depth bounds")
    unbounded = getattr(ds, "preset", "") == "real360"
    n = max(1, min(sc.init_points, cap // 2 if unbounded else cap))
    host = initial_gaussians(sc, n, ds.bbox, seed, UNBOUNDED_REACH if unbounded else 0.0)
    where = f"{n} random in the scene box" + (f" and {n} beyond it" if unbounded else "")
    return host, where


def forward_facing(ds) -> bool:
    """A forward-facing capture in world space (clrf/data/world.py): per-view depth bounds,
    no NDC."""
    return getattr(ds, "depth_bounds", None) is not None and not ds.ndc


def no_points_message(ds) -> str:
    """The bad-input message of splat.init 'points' on a dataset without sparse points."""
    return (f"dataset {ds.name}: splat.init = 'points' but it has no sparse points (COLMAP's "
            f"sparse/0/points3D, or for a photographed capture points triangulated from its "
            f"posed views, which needs pycolmap: `bash tools/setup.sh process`); use "
            f"splat.init = 'random' or 'auto', or pose the photos with `clrf process`")


def gaussian_cap(cfg, ds, caps) -> int:
    """The most Gaussians a run on ``ds`` may hold: splat.max_gaussians, and what fits the
    device beside the training images and a view's buffers."""
    from .budget import fitting_gaussians
    sc = cfg.splat
    n_views = len(ds.split["train"])
    if cfg.train.max_train_images:
        n_views = min(n_views, int(cfg.train.max_train_images))
    px = int(ds.hw[0]) * int(ds.hw[1])
    return min(sc.max_gaussians, fitting_gaussians(sc, caps, px, train_pixels=n_views * px))


def check_inputs(cfg, ds, caps, read_ply: bool = True):
    """A new run's inputs, before anything is planned or written (Kind.check): world-space
    cameras (a forward-facing capture comes as its world-space view, Kind.world_cameras),
    sparse points where splat.init asks for them, a readable splat.init_ply under the cap
    (``read_ply``: create_model reads the file once itself). Raises Unsupported or
    SplatFileError (bad input)."""
    if ds.ndc:
        raise Unsupported(f"dataset {ds.name}: the splat model needs world-space cameras and "
                          f"this one is in NDC; load it with clrf.data.world.world_space (clrf "
                          f"train does)")
    sc = cfg.splat
    points = getattr(ds, "points", None)
    if not sc.init_ply and sc.init == "points" and (points is None or len(points) == 0):
        raise Unsupported(no_points_message(ds))
    if sc.init_ply and read_ply:
        gaussians_from_ply(sc, sc.init_ply, gaussian_cap(cfg, ds, caps))


def create_model(device, cfg, ds, background, cls=None) -> SplatModel:
    """A new model for dataset ``ds`` (world-space cameras only); ``cls``: a subclass of
    SplatModel to make instead (clrf/splat/distributed.py)."""
    check_inputs(cfg, ds, device.caps, read_ply=False)   # initial_host reads and checks it
    sc = cfg.splat
    cap = gaussian_cap(cfg, ds, device.caps)
    seed = int(cfg.train.seed) + int(sc.seed)
    host, m_from = initial_host(sc, ds, cap, seed)
    m = (cls or SplatModel)(device, sc, host, background, scene_extent(ds), ds.bbox, seed, cap)
    m.initialised_from = m_from
    m.attach(ds, cfg.train.max_train_images)
    return m


def model_from_state(device, state, cfg) -> SplatModel:
    """A checkpoint's model (for rendering and export: it has no training views)."""
    return SplatModel.from_state_dict(device, state)


def viewer_params(model: SplatModel) -> tuple:
    """(the host parameters as a viewer without clrf's filters draws them, a note for
    messages): an anti-aliased model's 3D filter baked in, scales sqrt(s^2 + f2) and opacity
    times prod s / se (the screen-space compensation is the viewer's own); else as trained."""
    p = model.host_params()
    if not model.rast.antialiased:
        return p, ""
    f2 = download(model._rparams()["filter3d"]).astype(np.float64)
    s = np.exp(p["log_scales"].astype(np.float64))
    se = np.sqrt(s * s + f2[:, None])
    o = 1.0 / (1.0 + np.exp(-p["opacity_logits"].astype(np.float64))) * np.prod(s / se, 1)
    o = np.clip(o, 1e-7, 1 - 1e-7)
    p["log_scales"] = np.log(se).astype(np.float32)
    p["opacity_logits"] = np.log(o / (1 - o)).astype(np.float32)
    return p, " (the 3D anti-aliasing filter baked into scales and opacities)"


def write_splats(model: SplatModel, path) -> str:
    """``clrf export --splats FILE``: the Gaussians in the format the ending names (files.py:
    3DGS PLY, SPZ, glTF, compressed PLY, .splat), as viewer_params gives them; an
    anti-aliased model's SPZ carries the format's flag."""
    from .files import format_of, write_splat_file
    p, note = viewer_params(model)
    n = write_splat_file(path, p["means"], p["log_scales"], p["quats"], p["opacity_logits"],
                         p["sh"], antialiased=model.rast.antialiased)
    fmt = format_of(path)
    degree = min(model.config.sh_degree, fmt.max_degree)
    if degree < model.config.sh_degree:
        note += f" (the format keeps SH degree {fmt.max_degree} only)"
    return f"saved {path} ({fmt.title}): {n} Gaussians, SH degree {degree}{note}"


__all__ = ["SplatModel", "create_model", "model_from_state", "viewer_params",
           "write_splats"]
