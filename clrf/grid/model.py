"""GridModel: a Plenoxels model being trained: the SparseGrid, its optimisers and schedule.

Implements the model interface the trainer drives (shared with clrf.nerf.NerfModel):
``train_step(it, origins, dirs, target) -> mse``, ``render(origins, dirs) -> dict``,
``state_dict()``, ``from_state_dict(device, state)``, ``on_iteration(it, budget)``.

With ``cfg.background_layers > 0`` an MSI background (clrf/grid/background.py) sits behind the
grid: each ray's pixel is C_fg + T_fg * bg_rgb, trained jointly. With 0 (the default) no
background kernel is built or launched and every call is the constant-background one.

Per-image corrections (clrf/corrections, ``attach_corrections``; ray i of a batch comes from
training image index[i] // pixels, so training steps take ``index``):

- ``grid.pose_opt`` (RayPose): the batch's rays are remade from their images' corrected
  cameras, after the fused backward render_ray_grad (the GRID_POSE_GRAD build of
  cl/grid_render.cl: sample distances held) gives each ray's dL/d(origin, direction) of the
  same loss, and each image with rays in the batch takes its correction's Adam step from
  them.
- ``grid.exposure`` (RayExposure): the loss compares out = A_v pixel + b_v with the target,
  where pixel = C + T_end bg is the ray's whole render (the MSI's colour included). The
  transform acts on the pixel as rendered, so the correction is given the composite state
  (pixel, opacity 1): T = 0, nothing behind for it to add. The fused backward, built with
  RAY_EXPOSURE (``RayExposure.in_backward``), applies each ray's transform to the pixel it
  has just marched and takes g = 2 s A^T r = dL/dpixel (r = out - target): every gradient of
  the grid (and the MSI's) through the transform, the beta prior unchanged, in the one march
  of a step without the correction; it writes the state and r that the rows' step reads. On
  a step where the camera takes one too (grid.pose_opt), render_ray_grad needs a target
  instead: the pixel is rendered first (``pixel_state``), the correction's ``forward``
  returns eff = pixel - A^T r, and the backward on eff gives g = 2 s (pixel - eff), the same
  gradient, at one more forward render. A masked (RGBA) capture, whose transform must leave
  the composited background bg alone (out = A C + (1 - T) b + T bg), renders each ray on
  bg'_v = A_v^-1 (bg - b_v) instead (RayExposure.behind): then A_v (C + T bg'_v) + b_v is
  that out exactly, and the same backward, on bg', gives every gradient, the background's
  share of the densities' included, as the splat model's masked exposure does with whole
  views.
"""
from __future__ import annotations

import numpy as np
import pyopencl as cl
import pyopencl.array as cla

from ..corrections import RAY_STATE, RAYS, Corrections, Views, build, from_state
from . import ops as grid_ops
from .config import GridConfig
from .background import GridBackground
from .grid import SparseGrid, sh_dim
from ..runtime.optim import Optimizer, expon_lr
from .render import render_backward_device, render_forward_device, render_ray_grad_device
from ..runtime.pending import Pending
from ..runtime.programs import device_empty, device_zeros, download, launch, upload


def initial_grid(device, cfg: GridConfig, bbox) -> SparseGrid:
    """First (coarsest) grid: constant density, grey colour; optionally only voxels inside the
    box's inscribed ellipsoid (svox2's sphere bound for 360 scenes)."""
    reso = tuple(cfg.reso[0])
    mask = np.ones(reso, bool)
    if cfg.sphere_bound:
        c = [(np.arange(r) + 0.5) / r * 2 - 1 for r in reso]
        x, y, z = np.meshgrid(*c, indexing="ij")
        mask = x * x + y * y + z * z <= 1.0
    n = int(mask.sum())
    links = np.full(reso, -1, np.int32)
    links[mask] = np.arange(n, dtype=np.int32)
    return SparseGrid.from_arrays(device, links, np.full(n, cfg.init_density, np.float32),
                                  np.zeros((n, sh_dim(cfg.sh_degree)), np.float32), bbox)




def pixel_state(device, rgb, out):
    """``out`` [n, RAY_STATE] (device): the composite state RayExposure reads of whole pixels
    rgb [n, 3] (device), their colour and opacity 1 (T = 0: the background is in the pixel); the
    other entries, which it does not read, 1. One fill and one strided copy, no kernel."""
    n = int(rgb.shape[0])
    out.fill(np.float32(1.0))
    if n:
        cl.enqueue_copy(device.queue, out.data, rgb.data, src_origin=(0, 0, 0),
                        dst_origin=(0, 0, 0), region=(12, n, 1), src_pitches=(12, 12 * n),
                        dst_pitches=(4 * RAY_STATE, 4 * RAY_STATE * n))
    return out


def export_program(device, sh_degree: int):
    """cl/export.cl for SH degree ``sh_degree`` on ``device``."""
    return device.program("export.cl", {"SH_DEGREE": sh_degree})


class GridModel:
    kind = "grid"

    def __init__(self, device, cfg: GridConfig, grid: SparseGrid, background, stage: int = 0,
                 opt_state=None, bg_model: GridBackground | None = None):
        self.device = device
        self.cfg = cfg
        self.background = tuple(float(b) for b in background)
        self.stage = stage          # index into cfg.reso of the current grid
        self.bg_model = bg_model    # GridBackground, or None: constant background only
        # the step's loss stays on the device until read (GPUs; train_step)
        self.defer_loss = bool(getattr(device.tuning, "gpu_kernels", False))
        self.corrections = Corrections()   # per-image corrections (attach_corrections)
        # a ray colour correction inside the backward's one march (train_step); False takes
        # the two-pass step on every step (tools/profile_step.py --exposure-two-pass)
        self.colour_in_backward = True
        self.progress = 0.0         # the budget fraction reached (on_iteration)
        self._set_grid(grid, opt_state)

    def attach_corrections(self, n_images: int, pixels: int, masked: bool, viewmats=None,
                           pivots=None):
        """The per-image corrections the config turns on (grid.exposure, grid.pose_opt), a
        row per training image of ``pixels`` pixels (masked: an RGBA capture); training steps
        then need each ray's index in the concatenated training images (``ray_index``).
        grid.pose_opt: ``viewmats`` and ``pivots``, functions giving the training cameras'
        world-to-camera [V, 4, 4] (OpenCV axes) and pivot depths (clrf/corrections/pose.py).
        A colour correction acts on whole pixels here, a masked capture's rendered on each
        image's own background (module doc)."""
        views = Views(n_images, masked, pixels, scale=self.extent, pivots=pivots,
                      viewmats=viewmats)
        self.corrections = build(self.device, self.cfg, views, RAYS)

    @property
    def extent(self) -> float:
        """The scene's extent: the box's largest side (pose translations are relative to it)."""
        b = np.asarray(self.grid.bbox, np.float64)
        return float((b[1] - b[0]).max())

    @property
    def ray_index(self) -> bool:
        """Whether train_step needs each ray's index in the training images (the trainer
        passes it)."""
        return self.corrections.ray_index

    @classmethod
    def create(cls, device, cfg: GridConfig, bbox, background):
        bg_model = (GridBackground.create(device, cfg, bbox, background)
                    if cfg.background_layers > 0 else None)
        return cls(device, cfg, initial_grid(device, cfg, bbox), background, bg_model=bg_model)

    def _set_grid(self, grid, opt_state=None):
        self.grid = grid
        q = self.device.queue
        st = opt_state or {}
        self.opt_density = Optimizer(self.device, grid.density, self.cfg.optimizer,
                                        self.cfg.rms_beta, state=st.get("density"))
        self.opt_sh = Optimizer(self.device, grid.sh, self.cfg.optimizer, self.cfg.rms_beta,
                                   state=st.get("sh"))
        self.touched = device_zeros(q, grid.density.shape[0], np.uint8)
        self._sqerr = None

    # ---- training ----------------------------------------------------------------------
    def learning_rates(self, it):
        c = self.cfg
        return (expon_lr(it, c.lr_density, c.lr_density_final, c.lr_decay_steps,
                         c.lr_density_delay_steps, c.lr_density_delay_mult),
                expon_lr(it, c.lr_sh, c.lr_sh_final, c.lr_decay_steps))

    def train_step(self, it, origins, dirs, target, index=None):
        """One RMSProp step on a batch (device arrays [B, 3]); returns the batch MSE: a float,
        or where the device runs the GPU-shaped kernels (``defer_loss``) a Pending that the
        trainer reads when it reports (clrf/runtime/pending.py), so that no step waits for
        the device.

        index: each ray's place in the concatenated training images (int32 device [B]),
        needed with the per-image corrections (``ray_index``; module doc): with grid.pose_opt
        the rays are remade from their images' corrected cameras and each image with rays in
        the batch takes a step; with grid.exposure the loss is that of the transformed pixels
        and the transforms take a step."""
        c = self.cfg
        B = origins.shape[0]
        q = self.device.queue
        if self.ray_index and (index is None or int(index.shape[0]) != B):
            raise ValueError("train_step: the per-image corrections need each ray's image "
                             "index [B]")
        camera, colour = self.corrections.ray_camera, self.corrections.colour
        ray_grad = None
        if camera is not None:
            origins, dirs = camera.rays(index, origins, dirs)
            if camera.gradient_due():
                ray_grad = device_empty(q, (B, 6), np.float32)
            else:                              # grid.pose_opt_every: no camera step now
                camera = None
        if self._sqerr is None or self._sqerr.shape[0] != B:
            self._sqerr = device_empty(q, B, np.float32)
        bgm = self.bg_model
        bg = self.background
        if bgm is not None:
            t_start, bg = bgm.forward(self.grid, origins, dirs, c.step)
        scale = 1.0 / (3 * B)
        eff = target
        if colour is not None and colour.masked:   # each ray on A_v^-1 (bg - b_v) (module doc)
            bg = colour.behind(bg, index)
        # the transform in the backward's own loss (one march: cl/grid_render.cl
        # RAY_EXPOSURE), but where the camera takes a step: render_ray_grad then needs the
        # target whose gradient is the transform's, from the pixel rendered first
        fused = colour is not None and ray_grad is None and self.colour_in_backward
        xf = colour.in_backward(index) if fused else None
        if colour is not None and not fused:
            pixel = render_forward_device(self.grid, origins, dirs, c.step, bg)["rgb"]
            state = pixel_state(self.device, pixel,
                                device_empty(q, (B, RAY_STATE), np.float32))
            eff, sq_rays = colour.forward(state, (0.0, 0.0, 0.0), target, index)
        grad_bg = render_backward_device(
            self.grid, origins, dirs, eff, c.step, bg, self.opt_density.grad, self.opt_sh.grad,
            grad_mode=1, loss_scale=scale, ray_out=self._sqerr, touched=self.touched,
            beta_scale=c.lambda_beta / B, grad_bg=None if bgm is None else bgm.grad_buffer(B),
            ray_grad=ray_grad, exposure=xf)
        if fused:
            state, sq_rays = xf.state, self._sqerr
        if bgm is not None:
            bgm.backward_step(it, origins, dirs, t_start, grad_bg)
        if colour is not None:
            colour.backward_and_step(state, (0.0, 0.0, 0.0), index, scale)
        if camera is not None:
            camera.step_rays(index, dirs, ray_grad)
        if not (c.tv_early_only and self.stage > 0):
            self._tv(it)
        lr_d, lr_s = self.learning_rates(it)
        self.opt_density.step(self.touched, lr_d, clear_touched=False)
        self.opt_sh.step(self.touched, lr_s, clear_touched=True, columns=self.sh_columns())
        # the loss's squared errors: the transformed pixels' with grid.exposure (unfused,
        # _sqerr holds |pixel - eff|^2, the backward's own)
        loss = cla.sum(self._sqerr if colour is None else sq_rays, queue=q)
        if self.defer_loss:
            return Pending(q, loss, scale)
        return float(loss.get()) * scale

    def sh_columns(self):
        """The SH optimiser's live columns: (SH_BASIS, 1), band 0 of each channel alone, before
        the budget fraction grid.sh_diffuse_until; None (every band) after it."""
        basis = (self.grid.sh_degree + 1) ** 2
        if basis > 1 and self.progress < self.cfg.sh_diffuse_until:
            return (basis, 1)
        return None

    def ray_loss_grad(self, origins, dirs, target):
        """Each ray's dL/d(origin, direction) [B, 6] (device float32) of the photometric part of
        the training loss, L = sum over rays and channels of (pixel - target)^2 / (3 B), of
        rays origins/dirs/target [B, 3] (device) on the model's background (the MSI's colour
        where it has one, held), under no per-image correction (the render_ray_grad kernel
        alone: render.py ``render_ray_grad_device``). The model is held still: nothing of the
        grid, its gradients, touched rows or optimiser state is written (test-time camera
        refinement: ``refine_view_pose``)."""
        B = int(origins.shape[0])
        bg = self.background
        if self.bg_model is not None:
            bg = self.bg_model.forward(self.grid, origins, dirs, self.cfg.step, reuse=False)[1]
        return render_ray_grad_device(self.grid, origins, dirs, target, self.cfg.step, bg,
                                      grad_mode=1, loss_scale=1.0 / (3 * B))

    def refine_view_pose(self, c2w, intrinsics, hw, image, steps: int, lr: float, rays=None):
        """Test-time pose refinement (``clrf eval --refine-poses``): clrf/corrections/ray_pose.py
        ``refine_view_pose`` of camera ``c2w`` against ``image``, a training batch of its rays
        (``rays()``, as evaluation makes them) a step through ``ray_loss_grad``. Returns (the
        corrected camera-to-world [4, 4], the correction's summary)."""
        from ..corrections.ray_pose import refine_view_pose as refine
        return refine(self.device, self.ray_loss_grad, c2w, rays, image, steps, lr,
                      self.grid.bbox, self.extent, batch=self.batch_size)

    def _tv(self, it):
        """TV (and the sparsity prior) over one random contiguous window of the grid's cells;
        ``_tv_cells`` / ``_tv_grad`` are the distributed model's hooks (its window is over the
        whole grid, each brick covering its own voxels)."""
        c = self.cfg
        g = self.grid
        total = int(np.prod(self._tv_cells()))
        n = max(1, int(c.tv_fraction * total))
        start = int(np.random.default_rng(it).integers(total))
        if c.lambda_tv > 0 or c.lambda_sparsity > 0:
            self._tv_grad(g, g.density, self.opt_density.grad, self.touched, start, n,
                          c.lambda_tv / n, True, c.lambda_sparsity / n)
        if c.lambda_tv_sh > 0:
            self._tv_grad(g, g.sh, self.opt_sh.grad, self.touched, start, n,
                          c.lambda_tv_sh / n, False)

    def _tv_cells(self):
        return self.grid.reso

    @staticmethod
    def _tv_grad(*args):
        grid_ops.tv_grad(*args)

    def on_iteration(self, it, budget):
        """Prune and upsample at the scheduled iterations (on ``budget.rays``, the training
        rays). Returns a log message or None."""
        c = self.cfg
        self.progress = float(budget.fraction)
        self.corrections.schedule(self.progress)
        if self.stage < len(c.upsample_at) and it >= c.upsample_at[self.stage]:
            o, d = budget.rays.strided(c.prune_rays)
            return self.upsample(o, d)
        return None

    def upsample(self, origins, dirs):
        """Prune rows whose max rendering weight over the given rays is below
        weight_thresh / new z-resolution (dilated by one voxel when prune_dilate), then resample
        to the next resolution of the schedule."""
        c = self.cfg
        new_reso = tuple(c.reso[self.stage + 1])
        before = self.grid.n_rows
        mw = grid_ops.max_weight(self.grid, origins, dirs, c.step)
        keep = grid_ops.prune_keep(self.grid, mw, c.weight_thresh / new_reso[2],
                                   dilate=c.prune_dilate)
        kept = int(cla.sum(keep.astype(np.int32)).get())
        self._set_grid(grid_ops.resample(self.grid, new_reso, keep))
        self.stage += 1
        return (f"pruned {before} -> {kept} rows, upsampled to {new_reso[0]}x{new_reso[1]}x"
                f"{new_reso[2]} ({self.grid.n_rows} rows)")

    @property
    def batch_size(self) -> int:
        return self.cfg.batch_size

    # ---- evaluation ----------------------------------------------------------------------
    def render(self, origins, dirs, chunk=1 << 16):
        """Render numpy rays [n, 3] in chunks; returns numpy rgb, depth, acc."""
        q = self.device.queue
        n = origins.shape[0]
        out = {"rgb": np.empty((n, 3), np.float32), "depth": np.empty(n, np.float32),
               "acc": np.empty(n, np.float32)}
        for s in range(0, n, chunk):
            e = min(n, s + chunk)
            r = self._render_chunk(
                upload(q, np.ascontiguousarray(origins[s:e], np.float32)),
                upload(q, np.ascontiguousarray(dirs[s:e], np.float32)))
            for k in out:
                out[k][s:e] = r[k]
        return out

    def _render_chunk(self, o, d):
        """numpy rgb, depth, acc of device rays o, d (the distributed model's hook)."""
        bg = self.background
        if self.bg_model is not None:
            bg = self.bg_model.forward(self.grid, o, d, self.cfg.step, reuse=False)[1]
        return {k: v.get() for k, v in
                render_forward_device(self.grid, o, d, self.cfg.step, bg).items()}

    # ---- export (clrf/outputs/export.py) -------------------------------------------------
    view_dependent = False     # export reads the SH's constant term: no view direction

    @property
    def sample_length(self) -> float:
        """The voxel edge (mean over the axes): the renderer's own length scale."""
        return float(np.mean(self.grid.voxel_size))

    def export_block(self, block: int) -> int:
        return block

    def native_reso(self, bbox):
        """The grid's resolution when ``bbox`` is the grid's box."""
        return tuple(self.grid.reso) if np.allclose(bbox, self.grid.bbox) else None

    def export_fields(self, points, dirs=None):
        """Raw interpolated density sigma [n] (negative where the renderer's ReLU makes it 0)
        and the view-independent colour rgb [n, 3] at device points [n, 3] (cl/export.cl)."""
        n = int(points.shape[0])
        q = self.device.queue
        sigma, rgb = device_empty(q, n, np.float32), device_empty(q, (n, 3), np.float32)
        g = self.grid
        prg = export_program(self.device, g.sh_degree)
        launch(self.device, prg.kernel("sample_fields"), n,
               (np.int32(n), points.data, *g.geometry_args(), g.links.data, g.density.data,
                g.sh.data, sigma.data, rgb.data))
        return sigma, rgb

    def describe(self):
        r = self.grid.reso
        bg = ""
        if self.bg_model is not None:
            m = self.bg_model.msi
            bg = f", MSI background {m.layers}x{m.height}x{m.width}"
        corr = f", {self.corrections.describe()}" if self.corrections else ""
        sh = ", SH band 0 alone" if self.sh_columns() else ""
        return f"{r[0]}x{r[1]}x{r[2]} grid, {self.grid.n_rows} rows{sh}{bg}{corr}"

    # ---- state -------------------------------------------------------------------------
    def state_dict(self):
        n = self.grid.n_rows
        bg = self.bg_model.state_dict() if self.bg_model is not None else {}
        return {**bg,
            "kind": "grid", "stage": self.stage, "sh_degree": self.grid.sh_degree,
            "background": list(self.background),
            "links": download(self.grid.links), "bbox": self.grid.bbox,
            "density": download(self.grid.density)[:n], "sh": download(self.grid.sh)[:n],
            "opt_density": download(self.opt_density.state)[:n],
            "opt_sh": download(self.opt_sh.state)[:n],
            **self.corrections.state_dict(),
        }

    @classmethod
    def from_state_dict(cls, device, state, cfg: GridConfig):
        grid = SparseGrid.from_arrays(device, state["links"], state["density"], state["sh"],
                                      state["bbox"])
        q = device.queue
        pad = grid.density.shape[0] - state["density"].shape[0]
        od = np.concatenate([state["opt_density"], np.zeros(pad, np.float32)])
        osh = np.concatenate([state["opt_sh"], np.zeros((pad, grid.sh_dim), np.float32)])
        opt = {"density": upload(q, od.astype(np.float32)),
               "sh": upload(q, osh.astype(np.float32))}
        has_bg = "bg_density" in state
        if has_bg != (cfg.background_layers > 0):
            raise ValueError(
                f"the checkpoint {'has' if has_bg else 'has no'} MSI background but the "
                f"configuration sets grid.background_layers = {cfg.background_layers}; resume "
                f"with the run's own configuration")
        bg_model = GridBackground.from_state_dict(device, state, cfg) if has_bg else None
        model = cls(device, cfg, grid, state["background"], int(state["stage"]), opt,
                    bg_model=bg_model)
        # the corrections the checkpoint holds (none in one written before grid.exposure and
        # grid.pose_opt: from_state finds no key)
        model.corrections = from_state(device, cfg, state, Views(scale=model.extent), RAYS)
        return model
