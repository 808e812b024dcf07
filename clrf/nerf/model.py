"""NeRF model: positional encoding, coarse + fine fused MLPs, hierarchical sampling, compositing
and Adam, all as OpenCL kernels; this module only schedules them.

One training step on B rays (nothing per sample crosses to the host):
  t_c  = stratified(B, n_coarse, near, far, jitter)           (sample.cl)
  x, d = o + t_c d/|d|, d/|d|;  gamma(x), gamma(d)            (sample.cl, encode.cl)
  sigma, rgb = coarse MLP;  composite + MSE backward -> w_c   (mlp.cl, composite.cl)
  coarse MLP backward -> dL/dtheta_c                           (gradients of the coarse loss)
  t_f = importance(t_c, w_c, n_fine);  t = merge(t_c, t_f)    (sample.cl; no gradient to w_c)
  fine MLP forward / composite + MSE backward / MLP backward  -> dL/dtheta_f
  Adam on both, exponential lr decay; refresh the transposed weights.
Loss = MSE(fine) + coarse_loss_weight * MSE(coarse), MSE = mean over rays and channels.

Per-view corrections (clrf/corrections; ``attach_corrections``, each ray's image from the
``index`` the trainer passes):
  nerf.exposure: each pass's loss compares the ray's colour under its image's transform with
  the target (RayExposure): the composite state of the pass (composite_state, on black) gives
  the transformed residual and the target whose MSE backward on a black background is the
  colour's gradient through the transform; the background's share of dL/dsigma is added; the
  coarse pass's gradient of the rows is kept (``backward``) and the fine pass's steps them.
  nerf.pose_opt: the batch's rays are remade from their images' corrected cameras (RayPose),
  and each pass adds its rays' dL/d(origin, direction): the MLP's input gradient through the
  encodings' derivative (encode.cl encode_backward) to dL/dpoint and dL/dview-direction per
  sample, summed along each ray with the sample distances t held constant (sample.cl
  ray_points_backward: the importance samples' distances count as given, no gradient flows
  through the coarse weights that placed them); one Adam step of each touched image.

>>> model = NerfModel(dev, NerfConfig.from_preset("tiny"), near=2.0, far=6.0, background=(0, 0, 0))
>>> loss = model.train_step(0, origins_d, dirs_d, target_d)     # pyopencl arrays [B, 3]
>>> out = model.render(origins, dirs)                           # numpy: rgb [n,3], depth, acc
"""
from __future__ import annotations

from dataclasses import asdict

import numpy as np
import pyopencl.array as cla

from . import ops
from ..corrections import RAYS, Corrections, Views, build, from_state
from ..runtime.optim import AdamSet, Optimizer
from ..runtime.pending import Pending
from .config import NerfConfig
from ..mlp.mlp import MAX_RENDER_SCRATCH, MLP
from ..runtime.programs import device_empty, device_zeros, download, scratch, upload
from ..runtime.rng import step_key as _key



class NerfModel:
    """Coarse + fine NeRF on one device; see the module docstring for the step."""

    kind = "nerf"

    def __init__(self, device, config: NerfConfig, near: float, far: float,
                 background=(1, 1, 1), seed: int = 0):
        near, far = float(near), float(far)
        if not (np.isfinite(near) and np.isfinite(far) and 0 <= near <= far):
            raise ValueError(f"near/far: need finite 0 <= near <= far, got {near}, {far}")
        bg = np.broadcast_to(np.asarray(background, np.float64), (3,))
        if not np.all(np.isfinite(bg)):
            raise ValueError(f"background: must be finite, got {background}")
        if config.n_coarse < 1 or config.n_fine < 0:
            raise ValueError("NerfConfig: n_coarse must be >= 1 and n_fine >= 0")
        self.device = device
        self.config = config
        self.near, self.far = near, far
        self.background = tuple(float(b) for b in bg)
        self.seed = int(seed)
        self.step = 0
        spec = config.mlp_spec()
        self.coarse = MLP(device, spec, seed=self.seed)
        self.fine = self.coarse if config.shared_net else MLP(device, spec, seed=self.seed + 1)
        self._adam = {id(n): Optimizer(device, n.params, "adam", beta=config.beta1,
                                       beta2=config.beta2, eps=config.adam_eps, grad=n.grad)
                      for n in self._nets()}
        # GPU shapes: the loss stays on the device until read, and the networks' Adam steps
        # take one launch (CPUs: a launch a network, the loss read back each step)
        self.defer_loss = bool(getattr(device.tuning, "gpu_kernels", False))
        self._adam_all = (AdamSet(device, [self._adam[id(n)] for n in self._nets()])
                          if self.defer_loss and len(self._nets()) > 1 else None)
        self.corrections = Corrections()   # per-view corrections (clrf/corrections)
        self.extent = 1.0   # the scene's extent (pose translations are relative to it)
        self.bbox = None    # the scene's box [2, 3] (a refined camera turns about its centre)

    def attach_corrections(self, n_images: int, pixels: int, masked: bool, extent: float,
                           viewmats=None, pivots=None, bbox=None):
        """The per-view corrections the config turns on (nerf.exposure, nerf.pose_opt), a row
        per training image of ``pixels`` pixels (masked: an RGBA capture); training steps then
        need each ray's index in the concatenated training images (``ray_index``).
        ``extent``: the scene's size (pose translations are relative to it); nerf.pose_opt:
        ``viewmats`` and ``pivots``, functions giving the training cameras' world-to-camera
        [V, 4, 4] (OpenCV axes) and pivot depths (clrf/corrections/pose.py). ``bbox``: the
        scene's box [2, 3], kept for test-time pose refinement (``refine_view_pose``)."""
        self.extent = float(extent)
        if bbox is not None:
            self.bbox = np.asarray(bbox, np.float64).reshape(2, 3)
        views = Views(n_images, masked, pixels, scale=self.extent, pivots=pivots,
                      viewmats=viewmats)
        self.corrections = build(self.device, self.config, views, RAYS)

    @property
    def ray_index(self) -> bool:
        """Whether train_step needs each ray's index in the training images (the trainer
        passes it)."""
        return self.corrections.ray_index

    def _nets(self):
        return [self.coarse] if self.fine is self.coarse else [self.coarse, self.fine]

    # ---- one pass over a sample list --------------------------------------------------------
    def _eval(self, net: MLP, origins, dirs, t, points=None):
        """sigma, rgb of the samples t [n, K] of the rays; ``points``: a list that gets the
        samples' points and view directions (the camera gradient reads them)."""
        c = self.config
        xyz, vdir = ops.ray_points(self.device, origins, dirs, t)
        if points is not None:
            points[:] = [xyz, vdir]
        xe = ops.encode(self.device, xyz, c.pos_freqs, c.include_input, c.pos_scale)
        de = ops.encode(self.device, vdir, c.dir_freqs, c.include_input, c.dir_scale)
        return net.forward(xe, de)

    def _pass_backward(self, net, t, sig, rgb, target, loss_scale, want_weights, index,
                       last, accumulate, dirs, points, ray_grad, add_rays):
        """The backward of one pass (coarse or fine) over the batch: the network's gradient
        (added with ``accumulate``), the colour correction's (stepped when ``last``), the rays'
        camera gradient into ``ray_grad`` (when given; added to it with ``add_rays``).
        Returns the composite backward's dict (its weights) and each ray's squared residual
        [B] as the loss sees it."""
        dev, c = self.device, self.config
        colour = self.corrections.colour
        if colour is None:
            cb = ops.composite_backward(dev, t, sig, rgb, self.far, target, self.background,
                                        mse=True, loss_scale=loss_scale,
                                        want_weights=want_weights)
            sq = cb["sq_err"]
        else:   # the backward sees the target whose gradient is the one through the transform
            rs = ops.composite_state(dev, t, sig, rgb, self.far)
            eff, sq = colour.forward(rs.state, self.background, target, index)
            cb = ops.composite_backward(dev, t, sig, rgb, self.far, eff, (0.0, 0.0, 0.0),
                                        mse=True, loss_scale=loss_scale,
                                        want_weights=want_weights)
            colour.add_background(rs, sig, loss_scale, cb["sigma"])
            if last:
                colour.backward_and_step(rs.state, self.background, index, loss_scale)
            else:
                colour.backward(rs.state, self.background, index, loss_scale)
        want = ray_grad is not None
        g = net.backward(cb["sigma"], cb["rgb"], accumulate=accumulate, want_input=want)
        if want:
            dx, dd = g
            xyz, vdir = points
            gx = ops.encode_backward(dev, xyz, dx, c.pos_freqs, c.include_input, c.pos_scale)
            gv = ops.encode_backward(dev, vdir, dd, c.dir_freqs, c.include_input, c.dir_scale)
            ops.ray_points_backward(dev, dirs, t, gx, gv, ray_grad, accumulate=add_rays)
        return cb, sq

    def ray_loss_grad(self, origins, dirs, target):
        """Each ray's dL/d(origin, direction) [B, 6] (device float32) of the training loss,
        L = MSE(fine) + coarse_loss_weight MSE(coarse) over rays and channels, of rays
        origins/dirs/target [B, 3] (device), sampled as a training step samples them but
        without jitter, on the model's background and under no per-image correction (each
        pass's gradient as ``train_step`` forms it with nerf.pose_opt). The model is held
        still: the parameters, their gradients (the networks' go to a scratch buffer), Adam's
        state and the step count are as they were (test-time camera refinement:
        ``refine_view_pose``)."""
        c, dev = self.config, self.device
        B = int(origins.shape[0])
        scale = 1.0 / (3.0 * B)
        out = device_zeros(dev.queue, (max(B, 1), 6), np.float32)[:B]
        t_c = ops.sample_stratified(dev, B, c.n_coarse, self.near, self.far, False, 0)
        passes = [(self.coarse, t_c, scale * c.coarse_loss_weight)]
        for k, (net, t, s) in enumerate(passes):
            points = []
            sig, rgb = self._eval(net, origins, dirs, t, points)
            want_weights = k == 0 and c.n_fine > 0
            cb = ops.composite_backward(dev, t, sig, rgb, self.far, target, self.background,
                                        mse=True, loss_scale=s, want_weights=want_weights)
            dx, dd = net.backward(cb["sigma"], cb["rgb"], grad=scratch(dev, net.grad.shape),
                                  want_input=True)
            xyz, vdir = points
            gx = ops.encode_backward(dev, xyz, dx, c.pos_freqs, c.include_input, c.pos_scale)
            gv = ops.encode_backward(dev, vdir, dd, c.dir_freqs, c.include_input, c.dir_scale)
            ops.ray_points_backward(dev, dirs, t, gx, gv, out, accumulate=k > 0)
            if want_weights:
                t_f = ops.sample_importance(dev, t_c, cb["weights"], c.n_fine, self.near,
                                            self.far, False, 0)
                passes.append((self.fine, ops.merge_sorted(dev, t_c, t_f), scale))
        return out

    def refine_view_pose(self, c2w, intrinsics, hw, image, steps: int, lr: float, rays=None):
        """Test-time pose refinement (``clrf eval --refine-poses``): clrf/corrections/ray_pose.py
        ``refine_view_pose`` of camera ``c2w`` against ``image``, a training batch of its rays
        (``rays()``, as evaluation makes them) a step through ``ray_loss_grad``, the camera
        turned about the depth of the scene box's centre (a checkpoint from before the box
        was kept: the origin's). Returns (the corrected camera-to-world [4, 4], the
        correction's summary)."""
        from ..corrections.ray_pose import refine_view_pose as refine
        box = self.bbox if self.bbox is not None else np.zeros((2, 3))
        return refine(self.device, self.ray_loss_grad, c2w, rays, image, steps, lr, box,
                      self.extent, batch=self.batch_size)

    def lr_at(self, it: int) -> float:
        return self.config.lr * 0.1 ** (it / self.config.lr_decay_steps)

    def train_step(self, it: int, origins, dirs, target, index=None):
        """One optimiser step on a batch. origins/dirs/target are pyopencl float32 arrays [B,3]
        on device. Returns the batch MSE (mean over rays and channels) of the fine network: a
        float, or with ``defer_loss`` (the GPU shapes) a Pending the trainer reads when it
        reports. index: each ray's place in the concatenated training images (int32 device
        [B]), needed with the per-view corrections (``ray_index``); the loss is then the one
        the corrections see (under each image's colour transform)."""
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
        c, dev = self.config, self.device
        scale = 1.0 / (3.0 * B)
        camera = self.corrections.ray_camera   # nerf.pose_opt: the corrected cameras' rays
        ray_grad = points = None
        if camera is not None:
            origins, dirs = camera.rays(index, origins, dirs)
            if camera.gradient_due():
                ray_grad = device_empty(dev.queue, (B, 6), np.float32)
                points = []
            else:                              # nerf.pose_opt_every: no camera step now
                camera = None
        t_c = ops.sample_stratified(dev, B, c.n_coarse, self.near, self.far, c.perturb,
                                    _key(self.seed, it, 0))
        sig, rgb = self._eval(self.coarse, origins, dirs, t_c, points)
        cb, sq_err = self._pass_backward(self.coarse, t_c, sig, rgb, target,
                                         scale * c.coarse_loss_weight, c.n_fine > 0, index,
                                         c.n_fine == 0, False, dirs, points, ray_grad, False)
        if c.n_fine > 0:
            t_f = ops.sample_importance(dev, t_c, cb["weights"], c.n_fine, self.near, self.far,
                                        c.perturb, _key(self.seed, it, 1))
            t_all = ops.merge_sorted(dev, t_c, t_f)
            sig, rgb = self._eval(self.fine, origins, dirs, t_all, points)
            _, sq_err = self._pass_backward(self.fine, t_all, sig, rgb, target, scale, False,
                                            index, True, self.fine is self.coarse, dirs,
                                            points, ray_grad, True)
        if camera is not None:
            camera.step_rays(index, dirs, ray_grad)
        lr = self.lr_at(it)
        nets = self._nets()
        if self._adam_all is not None:
            self._adam_all.step([lr] * len(nets), self.step + 1)
        for net in nets:
            if self._adam_all is None:
                self._adam[id(net)].step(None, lr, t=self.step + 1)
            net.sync_params()
        self.step += 1
        if self.defer_loss:   # summed on the device in float32, read when reported
            return Pending(dev.queue, cla.sum(sq_err, queue=dev.queue), scale)
        return float(np.sum(sq_err.get(), dtype=np.float64) * scale)

    def render(self, origins: np.ndarray, dirs: np.ndarray, chunk: int = 4096) -> dict:
        """Evaluation render (no jitter) of numpy rays [n, 3]; numpy rgb [n,3], depth [n],
        acc [n] of the fine pass (the coarse pass when n_fine == 0)."""
        from ..runtime.validate import check_rays
        o, d = check_rays(origins, dirs)
        if np.any(np.max(np.abs(d), axis=1) == 0):
            raise ValueError("dirs: every direction must be non-zero")
        c, dev, q = self.config, self.device, self.device.queue
        n = o.shape[0]
        per_ray = c.n_coarse + c.n_fine
        max_rows = MAX_RENDER_SCRATCH // (4 * self.coarse.layout.nslot)
        step = max(1, min(int(chunk), max_rows // per_ray))
        out = {"rgb": np.zeros((n, 3), np.float32), "depth": np.zeros(n, np.float32),
               "acc": np.zeros(n, np.float32)}
        for s in range(0, n, step):
            e = min(n, s + step)
            od, dd = upload(q, o[s:e]), upload(q, d[s:e])
            t = ops.sample_stratified(dev, e - s, c.n_coarse, self.near, self.far, False)
            sig, rgb = self._eval(self.coarse, od, dd, t)
            res = ops.composite_forward(dev, t, sig, rgb, self.far, self.background,
                                        want_weights=c.n_fine > 0)
            if c.n_fine > 0:
                t_f = ops.sample_importance(dev, t, res["weights"], c.n_fine, self.near,
                                            self.far, False)
                t = ops.merge_sorted(dev, t, t_f)
                sig, rgb = self._eval(self.fine, od, dd, t)
                res = ops.composite_forward(dev, t, sig, rgb, self.far, self.background)
            for k in out:
                out[k][s:e] = res[k].get()
        return out

    # ---- trainer interface (clrf.training.trainer) --------------------------------------------------
    @property
    def batch_size(self) -> int:
        return self.config.batch_rays

    def on_iteration(self, it, budget):
        """The corrections' rates follow the spent fraction of the budget."""
        self.corrections.schedule(float(budget.fraction))
        return None

    # ---- export (clrf/outputs/export.py) -------------------------------------------------
    view_dependent = True

    @property
    def sample_length(self) -> float:
        """The mean spacing (far - near) / (n_coarse + n_fine) of the render samples."""
        c = self.config
        return (self.far - self.near) / (c.n_coarse + c.n_fine)

    def export_block(self, block: int) -> int:
        """The MLP keeps every activation: at most MAX_RENDER_SCRATCH bytes of them."""
        return max(1, min(block, MAX_RENDER_SCRATCH // (4 * self.fine.layout.nslot)))

    def native_reso(self, bbox):
        return None

    def export_fields(self, points, dirs):
        """sigma [n], rgb [n, 3] of the fine network at gamma(points) looking along dirs."""
        c, dev = self.config, self.device
        xe = ops.encode(dev, points, c.pos_freqs, c.include_input, c.pos_scale)
        de = ops.encode(dev, dirs, c.dir_freqs, c.include_input, c.dir_scale)
        return self.fine.forward(xe, de)

    def describe(self) -> str:
        c = self.config
        return (f"NeRF {c.depth}x{c.width}, {c.n_coarse}+{c.n_fine} samples"
                f"{', shared net' if c.shared_net else ''}"
                + (f", {self.corrections.describe()}" if self.corrections else ""))

    # ---- checkpoints --------------------------------------------------------------------
    def state_dict(self) -> dict:
        """numpy arrays + python scalars: weights, Adam moments, step, config as dict, and the
        per-view corrections with the scene's extent where the model has any."""
        st = {"kind": self.kind, "config": asdict(self.config), "near": self.near,
              "far": self.far, "background": list(self.background), "seed": self.seed,
              "step": self.step, "n_params": self.coarse.layout.n_params}
        for name, net in (("coarse", self.coarse), ("fine", self.fine)):
            if name == "fine" and net is self.coarse:
                continue
            a = self._adam[id(net)]
            st[f"{name}_params"] = download(net.params)
            st[f"{name}_adam_m"] = download(a.state)
            st[f"{name}_adam_v"] = download(a.state2)
        if self.corrections:   # checkpoints without them (older ones too) load without them
            st.update(self.corrections.state_dict())
        st["extent"] = self.extent
        if self.bbox is not None:
            st["bbox"] = self.bbox.copy()
        return st

    @classmethod
    def from_state_dict(cls, device, state: dict) -> "NerfModel":
        if state.get("kind") != cls.kind:
            raise ValueError(f"state_dict: kind is {state.get('kind')!r}, expected 'nerf'")
        model = cls(device, NerfConfig.from_dict(dict(state["config"])), state["near"],
                    state["far"], tuple(state["background"]), int(state["seed"]))
        model.step = int(state["step"])
        for name, net in (("coarse", model.coarse), ("fine", model.fine)):
            if name == "fine" and net is model.coarse:
                continue
            for key, arr in ((f"{name}_params", net.params),
                             (f"{name}_adam_m", model._adam[id(net)].state),
                             (f"{name}_adam_v", model._adam[id(net)].state2)):
                v = np.asarray(state[key], np.float32)
                if v.shape != arr.shape:
                    raise ValueError(f"state_dict[{key!r}]: shape {v.shape}, the config needs "
                                     f"{arr.shape}")
                arr.set(np.ascontiguousarray(v))
            net.sync_params()
        model.extent = float(state.get("extent", 1.0))
        if state.get("bbox") is not None:
            model.bbox = np.asarray(state["bbox"], np.float64).reshape(2, 3)
        model.corrections = from_state(device, model.config, state, Views(scale=model.extent),
                                       RAYS)
        return model
