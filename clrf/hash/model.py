"""The hash-grid model: a multiresolution hash encoding (cl/hash.cl) feeding the fused tiny MLP
(cl/mlp.cl), stratified samples kept only in occupied cells of an occupancy grid
(cl/hash_occ.cl), packed per ray and composited (cl/hash_march.cl, volrend.h's steps), and
Adam (cl/optim.cl).

Network (the fused MLP of cl/mlp.cl, clrf.mlp.mlp.MLPSpec with depth 1):
  density MLP: h = relu(W_0 enc(x) + b_0),  [sigma_raw, feat] = W_1 h + b_1,
               sigma = exp(min(sigma_raw, 15)) (density_act trunc_exp: never overflows, its
               gradient sigma does not vanish beyond the clamp; or softplus)
               enc(x): L F hash features, h: ``width``, feat: ``geo_features`` (16)
  colour MLP:  c_0 = relu(W_2 [feat, SH(d)] + b_2), c_1 = relu(W_3 c_0 + b_3) (color_depth 2,
               ``color_width`` each), rgb = sigmoid(W_4 c_1 + b_4)
               SH(d): the view direction's real SH basis, degree 3 (16 coefficients).
The published network has 15 features next to sigma (16 outputs); the kernel pads the head to
16 + 16 outputs, so ``geo_features`` is 16.

One training step on B rays (three numbers come back: the live and kept sample totals, which
size the buffers, and the loss; a bounded step, on GPUs, waits for none of them: train_step):
  S stratified bins over [near, far] per ray; keep the samples inside the box in occupied
  cells, packed per ray (so the sample count adapts per ray)          (hash_march.cl)
  sigma of the M samples (hash encoding, density MLP); keep each ray's
  samples in front of transmittance train_t_stop when that drops
  >= 15 % of them                                                     (hash_march.cl)
  sigma, rgb of the kept samples (hash + SH encodings, MLP)          (hash.cl, mlp.cl)
  composite + MSE backward over each ray's live samples (each stands
  for its bin: segment length dt = (far - near) / S)                  (hash_march.cl)
  MLP backward -> dL/dtheta, dL/denc;  hash backward -> dL/dtable     (mlp.cl, hash.cl)
  Adam (eps 1e-15) on tables and MLP, weight decay on the MLP only    (optim.cl)
Every occ_every steps from occ_warmup the occupancy grid is updated from the density (the
first update measures every cell, later ones occ_points cells of a sweep over all).
Renders march RENDER_WINDOW bins at a time and stop rays whose transmittance fell below
1e-4 (early ray termination).

>>> model = HashModel(dev, HashConfig.from_preset("tiny"), near=2.0, far=6.0,
...                   bbox=[[-1.5] * 3, [1.5] * 3], background=(1, 1, 1))
>>> loss = model.train_step(0, origins_d, dirs_d, target_d)      # pyopencl arrays [B, 3]
>>> out = model.render(origins, dirs)                            # numpy rgb [n,3], depth, acc
"""
from __future__ import annotations

import dataclasses
from dataclasses import asdict

import numpy as np
import pyopencl.array as cla

from .config import PUBLISHED_MAX_RES, PUBLISHED_WIDTH, HashConfig
from ..corrections import RAYS, Corrections, Views, build, from_state
from ..mlp.mlp import MAX_RENDER_SCRATCH, MLP, MLPSpec
from ..runtime.optim import AdamSet, Optimizer
from ..runtime.pending import Pending
from ..runtime.programs import (device_empty, device_zeros, download, first_run, launch,
                                scratch, upload)
from ..runtime.rng import step_key
from .encoding import SH_DIM, HashEncoding
from .march import (STATE, Contraction, contract_points, finish_state, keep_front, march,
                    packed_backward, packed_forward)
from .march import ray_grad as packed_ray_grad
from .occupancy import OccupancyGrid

RENDER_ROUND_SAMPLES = (1 << 16, 1 << 20)   # (ray, bin) pairs a render round marches at most
#   (before compaction), CPU shapes and GPU shapes: on a GPU the round trips, not the
#   arithmetic, bound a render of small chunks (0.8 s a 400x400 view on an H200 at 2,048
#   rays a chunk); on the 2-vCPU Xeon 32,768 rays a chunk were slower than 2,048 (4 views
#   of lego_400: 150.6 s against 131.1 s)
BATCH_RAYS_RANGE = (256, 1 << 16)   # rays per step when config.batch_samples adapts them
KEEP_BELOW = 0.85             # training-time termination copies the kept rows when >= 15 % go
RENDER_WINDOW = 32             # bins marched per round of a render (then finished rays stop)
BOUND_FACTOR = 2               # a bounded step's sample buffers: this many batch_samples


CONTRACT_FAR = 1000.0   # contracted scenes: samples out to this many box half-sizes


def mlp_spec(config: HashConfig) -> MLPSpec:
    """The fused MLP of a hash model of ``config`` (its input: levels x features hash
    features, the SH basis of the view direction)."""
    c = config
    return MLPSpec(width=c.width, depth=1, skip=-1, color_width=c.color_width,
                   in_dim=c.levels * c.features, dir_dim=SH_DIM, hidden_act="relu",
                   sigma_act=c.density_act, color_depth=c.color_depth,
                   features=c.geo_features, rows=c.mlp_rows)


def budget_lr(lr: float, final: float, hold: float, progress: float) -> float:
    """lr while ``progress`` (the spent fraction of a run's budget, in [0, 1]) is below
    ``hold``, then falling exponentially to lr * final at progress 1."""
    x = min(1.0, max(0.0, (progress - hold) / (1.0 - hold)))
    return lr * final ** x


def resolve_contract(config: HashConfig, ds) -> HashConfig:
    """config with ``contract`` "auto" decided for dataset ``ds``: on for unbounded 360 captures
    (scene preset real360), off otherwise (NDC scenes never: their space is already bounded)."""
    if config.contract != "auto":
        if config.contract == "on" and ds.ndc:
            raise ValueError(f"dataset {ds.name}: hash.contract=on does not apply to NDC "
                             f"(forward-facing) rays, whose space is already bounded; set "
                             f"hash.contract=off or auto")
        return config
    on = getattr(ds, "preset", None) == "real360" and not ds.ndc
    return dataclasses.replace(config, contract="on" if on else "off")


def resolve_max_res(config: HashConfig, ds) -> HashConfig:
    """config with ``max_res`` 0 ("auto") decided for dataset ``ds``. Object-centric scenes
    (scene preset synthetic: Blender-style captures, no NDC, no contraction): the published
    2048 cells for 800-pixel-wide views, in proportion to the training images' width (1024 at
    400 pixels), so the finest level keeps about the published cells per pixel; at least
    min_res. Every other scene (and ds None): 2048. lego_400, 1,500 steps, 10 test views
    (Xeon, PoCL): 2048 30.01 dB, 1024 30.12, 512 30.17."""
    if config.max_res:
        return config
    res = PUBLISHED_MAX_RES
    if getattr(ds, "preset", None) == "synthetic" and not ds.ndc and config.contract != "on":
        res = min(res, round(PUBLISHED_MAX_RES * int(ds.hw[1]) / PUBLISHED_WIDTH))
    return dataclasses.replace(config, max_res=max(config.min_res, res))


def ray_range(ds, contract: bool = False, ndc_far: float | None = None) -> tuple:
    """(near, far) of the hash model's bins for a dataset: the dataset's, with far cut to the
    farthest box corner seen from any camera (nothing is sampled outside the box, and
    unbounded scenes say far = 1e10). NDC scenes: ``ndc_far``, their far along unit
    directions (clrf.data.cameras.ndc_reach: the sampler normalises the NDC rays, whose |d| is
    ~2), else the dataset's.
    ``contract``: far reaches CONTRACT_FAR box half-sizes past the farthest camera, and near
    is at least a thousandth of a half-size (the bins are even in log t)."""
    near, far = float(ds.near), float(ds.far)
    box = np.asarray(ds.bbox, np.float64)
    if contract:
        half = (box[1] - box[0]).max() / 2
        cams = np.asarray(ds.poses, np.float64)[:, :3, 3] if len(ds.poses) else np.zeros((1, 3))
        reach = np.linalg.norm(cams - box.mean(axis=0), axis=1).max()
        return max(near, 1e-3 * half), float(reach + CONTRACT_FAR * half)
    if ds.ndc:
        far = far if ndc_far is None else float(ndc_far)
    elif len(ds.poses):
        corners = np.array([[box[i >> a & 1, a] for a in range(3)] for i in range(8)])
        cams = np.asarray(ds.poses, np.float64)[:, :3, 3]
        reach = np.linalg.norm(cams[:, None, :] - corners[None], axis=2).max()
        far = min(far, float(reach))
    if not far > near:
        raise ValueError(f"dataset {ds.name}: near {near} >= far {far} for the hash model's "
                         f"samples (is the box {np.asarray(ds.bbox).tolist()} behind every "
                         f"camera?); set the dataset's near/far or box")
    return near, far


class HashModel:
    kind = "hash"

    def __init__(self, device, config: HashConfig, near: float, far: float, bbox,
                 background=(0.0, 0.0, 0.0), seed: int = 0, bounded: bool = False):
        if not (np.isfinite(near) and np.isfinite(far) and 0 <= near < far):
            raise ValueError(f"near/far: need finite 0 <= near < far, got {near}, {far}")
        bg = np.broadcast_to(np.asarray(background, np.float64), (3,))
        if not np.all(np.isfinite(bg)):
            raise ValueError(f"background: must be finite, got {background}")
        box = np.asarray(bbox, np.float64)
        if box.shape != (2, 3):
            raise ValueError(f"bbox: expected [[x0, y0, z0], [x1, y1, z1]], got {bbox}")
        self.device = device
        config = resolve_max_res(config, None)   # "auto" with no dataset to decide: 2048
        self.config = c = config
        self.near, self.far = float(near), float(far)
        self.bbox = box
        self.background = tuple(float(b) for b in bg)
        self.seed = int(seed)
        self.bounded = bool(bounded)   # sizes stay on the device (see train_step)
        self._marched = None           # bounded: (rays, Pending live samples) of the last step
        self.step = 0
        self.progress = 0.0   # spent fraction of the budget (on_iteration; lr_schedule "budget")
        self.batch_rays = c.batch_rays   # rays of the next step (adapted: config.batch_samples)
        self._adapt_batch(1, c.samples)  # adapted: as if every bin were live
        # unbounded scenes: the encoding and the occupancy grid cover the contracted space
        self.contraction = Contraction(box) if c.contract == "on" else None
        space = Contraction.BOX if self.contraction else box
        if self.contraction and not self.near > 0:
            raise ValueError(f"near: a contracted scene's bins are even in log t and need "
                             f"near > 0, got {near}")
        self.enc = HashEncoding(device, c.levels, c.features, c.log2_table, c.min_res, c.max_res,
                                (space[0], space[1]), seed=self.seed)
        self.spec = mlp_spec(c)
        self.net = MLP(device, self.spec, seed=self.seed)
        self.occ = OccupancyGrid(device, c.occ_res, (space[0], space[1]))
        self.occ_prg = self.occ.prg
        self._adam_table = Optimizer(device, self.enc.table, "adam", beta=c.beta1,
                                     beta2=c.beta2, eps=c.adam_eps, grad=self.enc.grad)
        self._table_spans = self.enc.used_spans()
        self._adam_net = Optimizer(device, self.net.params, "adam", beta=c.beta1, beta2=c.beta2,
                                   eps=c.adam_eps, grad=self.net.grad,
                                   weight_decay=c.weight_decay)
        # GPU shapes: the tables and the network in one launch; CPUs: a launch a table span
        # and one for the network (faster on PoCL: cl/optim.cl)
        self._adam_all = (AdamSet(device, [self._adam_table, self._adam_net])
                          if getattr(device.tuning, "gpu_kernels", False) else None)
        self.corrections = Corrections()   # per-view corrections (clrf/corrections)
        # one rank of a data-parallel run over MPI (clrf/runtime/dataparallel.py), or None
        self.ranks = None

    def attach_corrections(self, n_images: int, pixels: int, masked: bool, viewmats=None,
                           pivots=None):
        """The per-view corrections the config turns on, a row per training image of
        ``pixels`` pixels (masked: an RGBA capture); training steps then may need each ray's
        index in the concatenated training images (``ray_index``). hash.pose_opt: ``viewmats``
        and ``pivots``, functions giving the training cameras' world-to-camera [V, 4, 4]
        (OpenCV axes) and pivot depths (clrf/corrections/pose.py)."""
        views = Views(n_images, masked, pixels, scale=self.extent, pivots=pivots,
                      viewmats=viewmats)
        self.corrections = build(self.device, self.config, views, RAYS)

    @property
    def extent(self) -> float:
        """The scene's extent: the box's largest side (pose translations are relative to it)."""
        return float((self.bbox[1] - self.bbox[0]).max())

    @property
    def ray_index(self) -> bool:
        """Whether train_step needs each ray's index in the training images (the trainer
        passes it)."""
        return self.corrections.ray_index

    # ---- evaluation of the fields at points ---------------------------------------------
    @property
    def dt(self) -> float:
        """Sample spacing along a ray (world units); contracted scenes: the spacing at one box
        half-size from the camera (it grows in proportion to the distance)."""
        S = self.config.samples
        if self.contraction is None:
            return (self.far - self.near) / S
        return float(self.contraction.half.mean() * np.expm1(np.log(self.far / self.near) / S))

    def _fields(self, xyz, vdir):
        """sigma [m], rgb [m, 3] at the encoding's points xyz [m, 3] seen along vdir [m, 3]
        (device)."""
        xe = self.enc.forward(xyz)
        de = self.enc.sh_encode(vdir)
        return self.net.forward(xe, de)

    def fields(self, xyz, vdir):
        """sigma [m], rgb [m, 3] (device) at world points xyz [m, 3] along vdir [m, 3] (device)
        as the renderer sees them: sigma = 0 outside the box (the encoding clamps there) unless
        the scene is contracted (then every point is in the model)."""
        if self.contraction is not None:
            return self._fields(contract_points(self.device, self.contraction, xyz), vdir)
        sigma, rgb = self._fields(xyz, vdir)
        launch(self.device, self.occ_prg.kernel("zero_outside"), int(xyz.shape[0]),
               (np.int32(xyz.shape[0]), xyz.data, self.occ.lo4, self.occ.inv4, sigma.data),
               self.device.tuning.elementwise_local_size)
        return sigma, rgb

    # ---- export (clrf/outputs/export.py) -------------------------------------------------
    view_dependent = True

    @property
    def sample_length(self) -> float:
        return self.dt

    def export_block(self, block: int) -> int:
        """The MLP keeps every activation: at most MAX_RENDER_SCRATCH bytes of them."""
        return max(1, min(block, MAX_RENDER_SCRATCH // (4 * self.net.layout.nslot)))

    def native_reso(self, bbox):
        return None

    def export_fields(self, points, dirs):
        return self.fields(points, dirs)

    def density(self, xyz):
        """sigma [m] (device) at world points xyz [m, 3] (device); the view direction is
        irrelevant to sigma (any direction gives the same value)."""
        if self.contraction is not None and int(xyz.shape[0]):
            xyz = contract_points(self.device, self.contraction, xyz)
        return self._density(xyz)

    def _density(self, xyz):
        """sigma [m] (device) at the encoding's points xyz [m, 3] (device)."""
        m = int(xyz.shape[0])
        if m == 0:
            return device_zeros(self.device.queue, 0, np.float32)
        return self.net.density(self.enc.forward(xyz))

    def lr_at(self, it: int) -> float:
        """Adam's learning rate at step ``it``: with lr_schedule "budget", of self.progress (the
        spent fraction of the run's budget, set by on_iteration; 0 outside a trainer)."""
        c = self.config
        if c.lr_schedule == "steps":
            return c.lr * 0.1 ** (it / c.lr_decay_steps)
        return budget_lr(c.lr, c.lr_final, c.lr_hold, self.progress)

    @property
    def random_background(self) -> bool:
        """Trains on a random background per step where the images have alpha (the trainer
        then keeps the alpha and asks step_background)."""
        return bool(self.config.random_background)

    def step_background(self, it: int):
        """The background colour of training step ``it`` when the images have alpha: random
        (config.random_background; deterministic in the seed and step), else None (the model's
        own background)."""
        if not self.config.random_background:
            return None
        rng = np.random.default_rng([self.seed, int(it), 7])
        return tuple(float(x) for x in rng.random(3))

    def train_step(self, it: int, origins, dirs, target, background=None, index=None):
        """One optimiser step on a batch. origins/dirs/target are pyopencl float32 arrays [B,3]
        on device; background: the RGB the targets are composited on (None: the model's own).
        Returns the batch MSE (mean over rays and channels): a float, or with ``bounded`` a
        Pending (clrf/runtime/pending.py; float() reads it).

        ``bounded`` (GPUs: the registry's factory sets it from device.tuning.gpu_kernels): no
        size is read back inside the step. The samples go to buffers of sample_capacity(B)
        rows whose live count stays on the device, every kernel is launched over the capacity
        and reads that count (cl/common.h live_rows), training-time termination always
        compacts, Adam steps even when no sample was live, and the loss stays on the device
        until read. The one number the host takes is the step's marched total, for the next
        batch's size, copied without blocking right after the march and read at the end of
        the step (the device then still has the step's network passes queued).

        index: each ray's place in the concatenated training images (int32 device [B]),
        needed with hash.exposure (``ray_index``)."""
        for name, a in (("origins", origins), ("dirs", dirs), ("target", target)):
            if not isinstance(a, cla.Array) or a.dtype != np.float32 or a.ndim != 2 \
                    or a.shape[1] != 3 or not a.flags.c_contiguous:
                raise TypeError(f"train_step: {name} must be a C-contiguous pyopencl float32 "
                                f"array [B, 3]; got {type(a).__name__} "
                                f"{getattr(a, 'shape', None)} {getattr(a, 'dtype', None)}")
        B = int(origins.shape[0])
        if dirs.shape[0] != B or target.shape[0] != B or B == 0:
            raise ValueError(f"train_step: origins, dirs, target need the same B > 0 rows, got "
                             f"{origins.shape}, {dirs.shape}, {target.shape}")
        if self.ray_index and (index is None or int(index.shape[0]) != B):
            raise ValueError("train_step: the per-image corrections need each ray's image "
                             "index [B]")
        self.maybe_update_occupancy(it)
        if self.ranks is None:
            loss, live = self.loss_and_grad(it, origins, dirs, target, background=background,
                                            index=index)
        else:   # this rank's share of the batch; the gradients summed over the ranks
            loss, live = self._rank_loss_and_grad(it, origins, dirs, target, background)
        if live:
            lr = self.lr_at(it)
            if self._adam_all is not None:
                self._adam_all.step([lr, lr], self.step + 1, spans=[self._table_spans, None],
                                    clear_grad=[True, False])
            else:
                self._adam_table.step(None, lr, t=self.step + 1, clear_grad=True,
                                      spans=self._table_spans)
                self._adam_net.step(None, lr, t=self.step + 1)
            self.net.sync_params()
        if self._marched is not None:
            rays, marched = self._marched
            self._marched = None
            if self.ranks is None:
                self._adapt_batch(rays, int(marched))
            else:   # the whole batch's rays and live samples, the same on every rank
                self._adapt_batch(B, self.ranks.total(int(marched)))
        self.step += 1
        return loss

    def _rank_loss_and_grad(self, it: int, origins, dirs, target, background):
        """(loss, live samples) of the whole batch when this model is one rank of a
        data-parallel run (``ranks``, clrf/runtime/dataparallel.py): this rank marches its
        share of the rays, scaled by the whole batch's size, and every rank then holds the
        gradients summed over the ranks; the loss and the live samples are the sums too."""
        dp, B = self.ranks, int(origins.shape[0])
        lo, hi = dp.share(B)
        mine = [a[lo:hi].copy() for a in (origins, dirs, target)]
        if hi > lo:
            loss, live = self.loss_and_grad(it, *mine, background=background, rays_total=B)
        else:   # fewer rays than ranks: nothing of this batch here
            loss, live, self._marched = 0.0, 0, (0, 0)
        if live == 0:       # loss_and_grad left the network's gradient as it was
            self.net.grad.fill(0)
        loss, total = dp.total(float(loss)), dp.total(int(live))
        if total:
            dp.sum_gradients([(self.net.grad, None), (self.enc.grad, self._table_spans)])
        return loss, total

    def sample_capacity(self, rays: int) -> int:
        """Rows of a bounded step's sample buffers for a batch of ``rays``: every bin of every
        ray, or BOUND_FACTOR times config.batch_samples where that is less (the batch adapts to
        about batch_samples live samples; a ray past the capacity keeps what fits)."""
        full = int(rays) * self.config.samples
        target = self.config.batch_samples
        return full if target <= 0 else min(full, BOUND_FACTOR * int(target))

    def loss_and_grad(self, it: int, origins, dirs, target, jitter=None, background=None,
                      index=None, rays_total: int | None = None, ray_grad=None):
        """(loss, live samples) of a batch; net.grad gets dL/dparams (overwritten) and
        enc.grad dL/dtable ADDED (it is zero between steps: the table's Adam step clears it);
        both untouched when no sample is live. L = sum over rays
        and channels of (rgb - target)^2 / (3 B). jitter: None for config.perturb. background:
        the RGB behind the rays (None: the model's own). With ``bounded`` (see train_step) the
        loss is a Pending and the live samples the buffers' capacity. With hash.exposure the
        loss compares each ray's colour under its image's transform (index: the rays' places
        in the training images), and the transforms take their Adam step here. ``ray_grad``
        (device float32 [B, 6], or None): filled with each ray's dL/d(origin, direction)
        (zero when no sample is live). With hash.pose_opt the rays are first remade from
        their images' corrected cameras, and each image with rays in the batch takes its
        correction's Adam step here (none when no sample is live)."""
        c, dev = self.config, self.device
        B = int(origins.shape[0])
        camera = self.corrections.ray_camera   # hash.pose_opt: the corrected cameras' rays
        if camera is not None:
            origins, dirs = camera.rays(index, origins, dirs)
            if camera.gradient_due():
                ray_grad = device_empty(dev.queue, (B, 6), np.float32)
            else:                              # hash.pose_opt_every: no camera step now
                camera = None
        scale = 1.0 / (3.0 * (B if rays_total is None else int(rays_total)))
        jitter = c.perturb if jitter is None else bool(jitter)
        # each rank of a data-parallel run jitters its rays with its own stream
        stream = 0 if self.ranks is None or self.ranks.rank == 0 else 100 + self.ranks.rank
        pk = march(dev, self.occ, origins, dirs, c.samples, self.near, self.far, jitter,
                   step_key(self.seed, it, stream), contract=self.contraction,
                   cap=self.sample_capacity(B) if self.bounded else None)
        q = dev.queue
        marched = pk.m
        if pk.total is not None:   # copied now, read at the end of the step
            self._marched = (B, Pending(q, pk.total))
        if pk.m:
            xe = self.enc.forward(pk.xyz, count=pk.count)
            # training-time termination: the density first, then the whole network on each
            # ray's samples in front of transmittance train_t_stop, when that drops at least
            # 1 - KEEP_BELOW of them (else the density pass was the only extra cost)
            kept = None
            if c.train_t_stop > 0:
                kept = keep_front(dev, pk, self.net.density(xe, count=pk.count),
                                  c.train_t_stop, (xe,), KEEP_BELOW)
            if kept is not None:
                pk, (xe,) = kept
            sigma, rgb = self.net.forward(xe, self.enc.sh_encode(pk.vdir, count=pk.count),
                                          count=pk.count)
        else:
            sigma, rgb = device_zeros(q, 1, np.float32), device_zeros(q, (1, 3), np.float32)
        bg = self.background if background is None else background
        colour = self.corrections.colour
        if colour is not None:   # the backward sees the target whose gradient is the
            state = device_zeros(q, (B, STATE), np.float32)   # one through the transform
            if pk.m:
                packed_forward(dev, pk, sigma, rgb, state)
            eff, sq_rays = colour.forward(state, bg, target, index)
            g = packed_backward(dev, pk, sigma, rgb, (0.0, 0.0, 0.0), eff, scale)
            colour.add_background(pk, sigma, scale, g["sigma"])
            with first_run(dev, ("cla.sum", sq_rays.dtype)):
                sq = cla.sum(sq_rays, queue=q)
            colour.backward_and_step(state, bg, index, scale)
        else:
            g = packed_backward(dev, pk, sigma, rgb, bg, target, scale)
            # summed on the device (pyopencl's reduction): one number comes back, not B
            with first_run(dev, ("cla.sum", g["sq_err"].dtype)):
                sq = cla.sum(g["sq_err"][:B], queue=q)
        if self.bounded:
            loss = Pending(q, sq, scale)
        else:
            loss = float(sq.get()) * scale
            if rays_total is None:
                self._adapt_batch(B, marched)
            else:   # train_step adapts to the whole batch's live samples
                self._marched = (B, marched)
        if pk.m == 0:            # no live sample in the batch: nothing to train
            if ray_grad is not None:
                ray_grad.fill(np.float32(0))
            return loss, 0
        dx, dd = self.net.backward(g["sigma"], g["rgb"], want_input=True)
        self.enc.backward(pk.xyz, dx, count=pk.count)
        if ray_grad is not None:
            gp = self.enc.dx(pk.xyz, dx, count=pk.count)
            packed_ray_grad(dev, pk, origins, dirs, gp, dd, self.contraction, out=ray_grad)
        if camera is not None:
            camera.step_rays(index, dirs, ray_grad)
        return loss, pk.m

    def ray_loss_grad(self, origins, dirs, target):
        """Each ray's dL/d(origin, direction) [B, 6] (device float32; zero where no sample is
        live) of the training loss L = sum over rays and channels of (rgb - target)^2 / (3 B)
        of rays origins/dirs/target [B, 3] (device), marched and composited as a training step
        does (its termination included) but without jitter, on the model's background and
        under no per-image correction. The model is held still: the parameters, their
        gradients (the network's goes to a scratch buffer, the table's is not formed), Adam's
        state, the occupancy grid and the next batch's size are as they were (test-time
        camera refinement: ``refine_view_pose``)."""
        c, dev, q = self.config, self.device, self.device.queue
        B = int(origins.shape[0])
        out = device_zeros(q, (max(B, 1), 6), np.float32)[:B]
        pk = march(dev, self.occ, origins, dirs, c.samples, self.near, self.far, False, 0,
                   contract=self.contraction)
        if pk.m == 0:
            return out
        xe = self.enc.forward(pk.xyz)
        kept = None
        if c.train_t_stop > 0:
            kept = keep_front(dev, pk, self.net.density(xe), c.train_t_stop, (xe,), KEEP_BELOW)
        if kept is not None:
            pk, (xe,) = kept
        sigma, rgb = self.net.forward(xe, self.enc.sh_encode(pk.vdir))
        g = packed_backward(dev, pk, sigma, rgb, self.background, target, 1.0 / (3.0 * B))
        dx, dd = self.net.backward(g["sigma"], g["rgb"], grad=scratch(dev, self.net.grad.shape),
                                   want_input=True)
        packed_ray_grad(dev, pk, origins, dirs, self.enc.dx(pk.xyz, dx), dd, self.contraction,
                        out=out)
        return out

    def refine_view_pose(self, c2w, intrinsics, hw, image, steps: int, lr: float, rays=None):
        """Test-time pose refinement (``clrf eval --refine-poses``): clrf/corrections/ray_pose.py
        ``refine_view_pose`` of camera ``c2w`` against ``image``, a training batch of its rays
        (``rays()``, as evaluation makes them) a step through ``ray_loss_grad``. Returns (the
        corrected camera-to-world [4, 4], the correction's summary)."""
        from ..corrections.ray_pose import refine_view_pose as refine
        return refine(self.device, self.ray_loss_grad, c2w, rays, image, steps, lr, self.bbox,
                      self.extent, batch=self.batch_size)

    def _adapt_batch(self, rays: int, live: int):
        """Rays of the next step: batch_samples over this step's live samples per ray, within
        BATCH_RAYS_RANGE, in multiples of 256 (no change when batch_samples is 0)."""
        target = self.config.batch_samples
        if target <= 0:
            return
        per_ray = max(live / max(rays, 1), 1.0)
        lo, hi = BATCH_RAYS_RANGE
        self.batch_rays = int(min(hi, max(lo, round(target / per_ray / 256) * 256)))

    # ---- occupancy ----------------------------------------------------------------------
    def occupancy_threshold(self) -> float:
        """Density below which a cell counts as empty: occ_tau over the sample spacing."""
        return self.config.occ_tau / self.dt

    def maybe_update_occupancy(self, it: int) -> bool:
        """Update the occupancy grid at steps occ_warmup, occ_warmup + occ_every, ...: the first
        update measures every cell, each later one the next occ_points cells of the sweep (so
        every cell is measured once per n_cells / occ_points updates)."""
        c = self.config
        if it < c.occ_warmup or (it - c.occ_warmup) % c.occ_every != 0:
            return False
        k = (it - c.occ_warmup) // c.occ_every
        if k == 0:
            self.update_occupancy(step_key(self.seed, it, 2), self.occ.n_cells, 0)
        else:
            self.update_occupancy(step_key(self.seed, it, 2), c.occ_points, (k - 1) * c.occ_points)
        return True

    def update_occupancy(self, key: int, n_points: int | None = None, start: int = 0):
        """One occupancy update measuring n_points cells (default occ_points) from sweep
        position start."""
        c = self.config
        n = c.occ_points if n_points is None else int(n_points)
        self.occ.update(self._density, key, n, c.occ_decay, self.occupancy_threshold(),
                        start % self.occ.n_cells)

    # ---- rendering ----------------------------------------------------------------------
    def render(self, origins: np.ndarray, dirs: np.ndarray, chunk: int | None = None) -> dict:
        """Evaluation render (no jitter) of numpy rays [n, 3]: numpy rgb [n,3], depth [n],
        acc [n]. Rays go in chunks of ``chunk`` (default: as many as a round of RENDER_WINDOW
        bins of RENDER_ROUND_SAMPLES holds)."""
        from ..runtime.validate import check_rays
        o, d = check_rays(origins, dirs)
        if np.any(np.max(np.abs(d), axis=1) == 0):
            raise ValueError("dirs: every direction must be non-zero")
        q = self.device.queue
        n = o.shape[0]
        cap = RENDER_ROUND_SAMPLES[bool(self.device.tuning.gpu_kernels)]
        step = max(1, cap // min(self.render_samples, RENDER_WINDOW))
        step = step if chunk is None else max(1, min(int(chunk), step))
        out = {"rgb": np.zeros((n, 3), np.float32), "depth": np.zeros(n, np.float32),
               "acc": np.zeros(n, np.float32)}
        for s in range(0, n, step):
            e = min(n, s + step)
            od, dd = upload(q, o[s:e]), upload(q, d[s:e])
            st = self._render_chunk(od, dd)
            for k, v in finish_state(st, self.background).items():
                out[k][s:e] = v
        self.device.pool.free_held()   # a render's chunks are larger than a step's: not kept
        return out

    @property
    def render_samples(self) -> int:
        """Bins per ray of a render: config.samples times config.render_oversample."""
        return self.config.samples * self.config.render_oversample

    def _render_chunk(self, od, dd):
        """Per-ray composite state [n, STATE] (numpy) of rays od/dd (device), marched in
        windows of RENDER_WINDOW bins; a ray stops once its transmittance is below the
        kernel's HASH_T_STOP (early ray termination)."""
        dev, q = self.device, self.device.queue
        n = int(od.shape[0])
        state = device_zeros(q, (n, STATE), np.float32)
        alive = device_empty(q, n, np.uint8)
        alive.fill(np.uint8(1))
        S = self.render_samples
        for k0 in range(0, S, RENDER_WINDOW):
            pk = march(dev, self.occ, od, dd, S, self.near, self.far, False, 0, k0,
                       min(S, k0 + RENDER_WINDOW), alive, self.contraction)
            if pk.m == 0:
                continue
            sigma, rgb = self._fields(pk.xyz, pk.vdir)
            packed_forward(dev, pk, sigma, rgb, state, alive)
        return state.get()

    # ---- trainer interface (clrf.training.trainer) --------------------------------------------------
    @property
    def batch_size(self) -> int:
        """Rays of the next training step (adapts when config.batch_samples > 0)."""
        return self.batch_rays

    def on_iteration(self, it, budget):
        """The budget spent before step ``it`` (``budget.fraction``: the larger of the run's
        seconds and iterations over their limits) is the learning rate's clock under
        lr_schedule "budget"."""
        self.progress = float(budget.fraction)
        self.corrections.schedule(self.progress)
        return None

    def describe(self) -> str:
        c = self.config
        return (f"hash L{c.levels} F{c.features} T2^{c.log2_table} {c.min_res}-{c.max_res}, "
                f"MLP {c.width}+{c.geo_features} / {c.color_depth}x{c.color_width}, "
                f"{c.samples} samples{' (contracted scene)' if self.contraction else ''}, "
                f"occupied {100 * self.occ.occupied_fraction():.1f}%"
                + (f", {self.corrections.describe()}" if self.corrections else ""))

    # ---- checkpoints --------------------------------------------------------------------
    def state_dict(self) -> dict:
        """numpy arrays + python scalars: tables, MLP, Adam moments, occupancy, step, config."""
        return {"kind": self.kind, "config": asdict(self.config), "near": self.near,
                "far": self.far, "bbox": self.bbox.tolist(), "background": list(self.background),
                "seed": self.seed, "step": self.step, "batch_rays": self.batch_rays,
                "table": download(self.enc.table),
                "table_adam_m": download(self._adam_table.state),
                "table_adam_v": download(self._adam_table.state2),
                "mlp_params": download(self.net.params),
                "mlp_adam_m": download(self._adam_net.state),
                "mlp_adam_v": download(self._adam_net.state2), "occ_ema": download(self.occ.ema),
                "occ_threshold": self.occ.threshold,
                **self.corrections.state_dict()}

    @classmethod
    def from_state_dict(cls, device, state: dict, bounded: bool = False) -> "HashModel":
        if state.get("kind") != cls.kind:
            raise ValueError(f"state_dict: kind is {state.get('kind')!r}, expected 'hash'")
        model = cls(device, HashConfig.from_dict(dict(state["config"])), state["near"],
                    state["far"], state["bbox"], tuple(state["background"]), int(state["seed"]),
                    bounded)
        model.step = int(state["step"])
        model.batch_rays = int(state.get("batch_rays", model.config.batch_rays))
        for key, arr in (("table", model.enc.table), ("table_adam_m", model._adam_table.state),
                         ("table_adam_v", model._adam_table.state2),
                         ("mlp_params", model.net.params), ("mlp_adam_m", model._adam_net.state),
                         ("mlp_adam_v", model._adam_net.state2), ("occ_ema", model.occ.ema)):
            v = np.asarray(state[key], np.float32)
            if v.shape != arr.shape:
                raise ValueError(f"state_dict[{key!r}]: shape {v.shape}, the config needs "
                                 f"{arr.shape}")
            arr.set(np.ascontiguousarray(v))
        model.net.sync_params()
        model.occ._threshold(float(state["occ_threshold"]))
        model.corrections = from_state(device, model.config, state, Views(scale=model.extent),
                                       RAYS)
        return model
