"""The training loop shared by every model kind (clrf/interface.py's Model).

Rays of every training pixel are built once (vectorised numpy) and kept on the device; each
step draws a random batch on the device (cl/batch.cl), runs the model's fused step, and reads
back one number (the batch loss; a model may return it as a Pending, clrf/runtime/pending.py,
which the loop reads once it has arrived, so that the host does not wait for the step; before
an evaluation, a checkpoint or the end, the device's queue is drained inside the step's time,
so the clock counts all of its work). Held-out views are evaluated every ``eval_every`` seconds of
training, or less often where an evaluation is slow, so that evaluations take at most
EVAL_SHARE of the wall time (``next_eval_at``; an evaluation renders as many of its views as
that share allows, at least one; the untrained model's point renders one view,
downscaled to at most ANCHOR_PIXELS; one more before stopping);
the clock excludes evaluation, checkpointing and one-off program builds, so ``seconds`` in
metrics.csv is pure training time. Outputs in the run directory:

- ``config.json``       the effective configuration (feed it back with --config)
- ``metrics.csv``       iteration, seconds, train_loss, train_psnr, eval_psnr, eval_ssim, ...
                        (a row every ``eval_every`` seconds; where evaluations are spaced
                        out, the rows between them hold the training loss alone)
- ``error_vs_time.png`` eval PSNR against training seconds
- ``ckpt.npz``          the last checkpoint, replaced atomically; --resume continues from it
- ``eval.json``         per-view and mean PSNR/SSIM of the final evaluation (``ssim_window``:
                        "gaussian11", the standard SSIM; files without it hold the old 7x7 one),
                        the colour-corrected PSNR (``psnr_color_corrected``: docs/evaluation.md)
                        and ``device_memory``: training's peak of clrf's device buffers and
                        memory pool (clrf/runtime/devmem.py; on a GPU, the card's memory the
                        run needed)

Under MPI (a factory with ``comm``: a kind's ``distributed``) every rank runs this loop in step:
the step times are the slowest rank's (allreduce), so evaluations, checkpoints and the stop
happen at the same iteration everywhere; rank 0 writes the run's files, the model writes the
checkpoint (one file per rank plus the manifest ckpt.npz).
"""
from __future__ import annotations

import csv
import json
import signal
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import pyopencl as cl
from pyopencl.elementwise import ElementwiseKernel
from pyopencl.tools import context_dependent_memoize

from .. import corrections, registry
from ..interface import Budget, StateError, render_view
from ..outputs import checkpoint, rundir
from ..runtime.atomicfile import atomic_path, write_text
from ..runtime.trust import ensure_trusted
from ..data.cameras import as_distortion, view_rays
from ..data.io import downscale_image
from .metrics import SSIM_NAME, SSIM_WINDOW, image_metrics, psnr_from_mse
from ..runtime.pending import Pending
from ..runtime.memory import RAY_PART
from ..runtime.programs import device_empty, download, first_run, float4, launch
from ..runtime.progress import TrainProgress

EVAL_MIN_SIDE = SSIM_WINDOW   # smallest evaluated image side (the SSIM window)
CSV_FIELDS = ["iteration", "seconds", "train_loss", "train_psnr", "eval_psnr", "eval_ssim",
              "eval_views", "rays_per_s", "model"]


def _hold_sigint(trainer) -> bool:
    """Ctrl-C in the training loop sets ``trainer._sigint``, read after each step, instead of
    raising KeyboardInterrupt wherever the interpreter happens to be: raised inside a
    finalizer (pyopencl frees buffers from weakref callbacks) it is printed and dropped, and
    the run trained on past the signal (a CI run). A second Ctrl-C raises at once. Returns
    whether the handler was installed (only the main thread can; a process that ignores
    SIGINT keeps ignoring it)."""
    def on_sigint(signum, frame):
        if trainer._sigint:
            raise KeyboardInterrupt
        trainer._sigint = True
    if signal.getsignal(signal.SIGINT) is signal.SIG_IGN:
        return False        # started ignoring it (a shell's background job): left so
    try:
        signal.signal(signal.SIGINT, on_sigint)
    except ValueError:      # not the main thread: Python's own handler stays
        return False
    return True


class RayStore:
    """All training rays and colours on the device; random batches drawn on the device.

    alpha [n] (RGBA captures, else None) and background (what the colours were composited on)
    let a batch's colours be recomposited on another background (``batch(..., background)``).
    ``RayStore.empty`` and ``put`` fill a store part by part (``training_rays``: a few views at
    a time, so the host never holds every ray beside the device's copy)."""

    def __init__(self, device, origins, dirs, colors, alpha=None, background=(1.0, 1.0, 1.0)):
        self._allocate(device, int(origins.shape[0]), alpha is not None, background)
        if self.alpha is not None and np.size(alpha) != self.n:
            raise ValueError(f"RayStore: alpha has {np.size(alpha)} values for {self.n} rays")
        self.put(0, origins, dirs, colors, alpha)

    @classmethod
    def empty(cls, device, n: int, alpha: bool = False, background=(1.0, 1.0, 1.0)):
        """A store of n rays (and their alpha) to be filled with ``put``."""
        store = cls.__new__(cls)
        store._allocate(device, int(n), alpha, background)
        return store

    def _allocate(self, device, n: int, alpha: bool, background):
        q = device.queue
        self.device, self.n = device, n
        self.o, self.d, self.c = (device_empty(q, (n, 3), np.float32) for _ in range(3))
        self.alpha = device_empty(q, n, np.float32) if alpha else None
        self.background = tuple(float(b) for b in background)
        self._bufs = {}

    def put(self, start: int, origins, dirs, colors, alpha=None):
        """Write rays start, start + 1, ... (float32 [k, 3] each; alpha [k] where the store
        has alpha) to the device; the copies block, so the host arrays may be freed at once."""
        k = int(np.shape(origins)[0])
        if start < 0 or start + k > self.n:
            raise ValueError(f"RayStore.put: rays {start}..{start + k} of {self.n}")
        if k == 0:
            return
        q = self.device.queue
        parts = [(self.o, origins, 3), (self.d, dirs, 3), (self.c, colors, 3)]
        if self.alpha is not None:
            parts.append((self.alpha, alpha, 1))
        for dst, src, w in parts:
            a = np.ascontiguousarray(np.reshape(src, (k, w) if w > 1 else k), np.float32)
            cl.enqueue_copy(q, dst.data, a, dst_offset=4 * w * start, is_blocking=True)

    def batch(self, seed: int, n: int, background=None):
        """(origins, dirs, colours, indices) of n rays drawn with replacement; deterministic in
        seed. background: the colours recomposited on this RGB instead (needs alpha)."""
        q = self.device.queue
        if n not in self._bufs:
            self._bufs[n] = tuple(device_empty(q, (n, 3), np.float32) for _ in range(3)) + (
                device_empty(q, n, np.int32),)
        bo, bd, bc, bi = self._bufs[n]
        prg = self.device.program("batch.cl")
        launch(self.device, prg.kernel("gather_batch"), n,
               (np.int32(n), np.uint32(seed & 0xFFFFFFFF), np.uint32(self.n), self.o.data,
                self.d.data, self.c.data, bo.data, bd.data, bc.data, bi.data))
        if background is not None:
            if self.alpha is None:
                raise ValueError("RayStore.batch: a background needs the images' alpha (RGBA)")
            dr, dg, db = np.subtract(background, self.background)
            delta = float4(dr, dg, db, 0.0)
            launch(self.device, prg.kernel("recomposite"), n,
                   (np.int32(n), bi.data, self.alpha.data, delta, bc.data))
        return bo, bd, bc, bi

    def strided(self, n: int):
        """About n rays evenly strided over the training set: (origins, dirs) float32 [m, 3],
        rows 0, s, 2 s, ... read back from the device (the store keeps no host copy of its
        rays: 24 bytes a ray, 2.6 GB for bonsai_800's 255 views at 800 x 533)."""
        stride = max(1, self.n // max(1, n))
        m = -(-self.n // stride)
        return tuple(_strided_rows(self.device, a, stride, m) for a in (self.o, self.d))


@context_dependent_memoize
def _strided_kernel(context):
    return ElementwiseKernel(context, "float *out, const float *src, const long stride",
                             "out[i] = src[((long)i / 3) * stride * 3 + (long)i % 3]",
                             "ray_rows_strided")


def _strided_rows(device, a, stride: int, m: int) -> np.ndarray:
    """Rows 0, stride, ..., (m - 1) stride of the device array ``a`` [n, 3] float32, on the
    host (a pyopencl elementwise gather, then one download)."""
    if m == 0:
        return np.zeros((0, 3), np.float32)
    out = device_empty(device.queue, (m, 3), np.float32)
    with first_run(device, "ray_rows_strided"):
        _strided_kernel(device.context)(out, a, np.int64(stride), queue=device.queue)
    return download(out)


def training_rays(device, ds, max_images=0, alpha=False):
    """The RayStore of ds's training views (the first max_images); alpha: keep the images'
    alpha on the device too (where they have one), for training on random backgrounds."""
    idx = np.asarray(ds.split["train"])
    if max_images:
        idx = idx[:max_images]
    alpha = alpha and ds.alpha is not None
    per = int(np.prod(ds.hw))
    store = RayStore.empty(device, len(idx) * per, alpha, ds.background)
    step = max(1, RAY_PART // max(per, 1))            # about 4 M rays (150 MB on the host) a part
    for k in range(0, len(idx), step):
        views = idx[k:k + step]
        o, d = view_rays(ds, ds.poses[views])
        store.put(k * per, o, d, ds.images[views].reshape(-1, 3),
                  ds.alpha[views].reshape(-1) if alpha else None)
    return store


def train_on_batch(model, rays: RayStore, seed: int, it: int, n: int) -> float:
    """Step ``it`` of a model: n rays drawn from the store (deterministic in seed and it), on
    the step's random background where the model asks for one and the store has alpha; the
    batch MSE."""
    if rays is None:   # the model draws its own training views
        return model.train_step(it, None, None, None)
    bg = model.step_background(it) if rays.alpha is not None else None
    bo, bd, bc, bi = rays.batch(seed * 1000003 + it, n, bg)
    kw = {} if bg is None else {"background": bg}
    if getattr(model, "ray_index", False):   # a correction per image of ray batches
        kw["index"] = bi
    return model.train_step(it, bo, bd, bc, **kw)


def evaluate(model, ds, views, keep_images=False, downscale=1, half_fitted=False,
             seconds=None, comm=None):
    """PSNR/SSIM of the model's renders of the given test view indices (into ds.images), and
    the PSNR after an affine colour map per view and channel fitted to its ground truth
    (``psnr_color_corrected``: metrics.psnr_color_corrected).

    downscale f > 1: render (H // f) x (W // f) views and compare them with the box-averaged
    images (f^2 times fewer rays; for cheap evaluations between checkpoints).
    keep_images: True keeps every render in ``res["images"]`` (float [H, W, 3] in [0, 1]); an
    integer k keeps the first k.
    half_fitted: also NeRF-W's protocol for models with a colour transform per training image
    (the splat model's splat.exposure): each view's right half scored after a colour
    transform fitted on its left half (``psnr_half_fitted``), beside the right half as
    rendered (``psnr_right_half``); and the gauge-free score, every view under one gain per
    channel fitted to all of them (``psnr_shared_gain``, the gain ``shared_gain``:
    reference_exposure.shared_gain_psnr).
    seconds: a further view is started only where, at the mean time of those before it, it
    would end within this many seconds of wall time (the first always is; ``res["views"]``
    lists those rendered).
    comm: the ranks of a data-parallel run (every rank holds the whole model): the views are
    dealt out round-robin, each rank renders its own, and every rank returns the result of
    all of them, in their order (``seconds`` is then not used)."""
    keep = len(views) if keep_images is True else int(keep_images)
    if comm is None:
        per_view, images, sums = _render_views(model, ds, views, keep, downscale, half_fitted,
                                               seconds)
    else:
        P, r = comm.Get_size(), comm.Get_rank()
        parts = comm.allgather(_render_views(model, ds, list(views)[r::P],
                                             max(0, -(-(keep - r) // P)), downscale,
                                             half_fitted, None))
        order = [(g % P, g // P) for g in range(len(views))]   # view g: rank g % P's
        per_view = [parts[p][0][i] for p, i in order]
        sums = [parts[p][2][i] for p, i in order] if half_fitted else []
        images = [parts[p][1][i] for p, i in order[:keep]]
    mse = float(np.mean([m["mse"] for m in per_view]))
    res = {"psnr": float(np.mean([m["psnr"] for m in per_view])),
           "ssim": float(np.mean([m["ssim"] for m in per_view])),
           "psnr_color_corrected": float(np.mean([m["psnr_color_corrected"]
                                                  for m in per_view])),
           "psnr_of_mean_mse": psnr_from_mse(mse), "views": per_view}
    if half_fitted:
        for k in ("psnr_half_fitted", "psnr_right_half"):
            res[k] = float(np.mean([m[k] for m in per_view]))
        from ..references.reference_exposure import shared_gain_psnr
        gain, shared = shared_gain_psnr(sums)
        for m, p in zip(per_view, shared):
            m["psnr_shared_gain"] = float(p)
        res["psnr_shared_gain"], res["shared_gain"] = float(np.mean(shared)), gain.tolist()
        res["gain_sums"] = sums   # to pool views evaluated one call each (cli/evaluate.py)
    if keep:
        res["images"] = images
    return res


def _render_views(model, ds, views, keep: int, downscale: int, half_fitted: bool, seconds):
    """evaluate()'s renders: (per-view metrics, the first ``keep`` renders, the gain sums)."""
    H, W = ds.hw[0] // downscale, ds.hw[1] // downscale
    per_view, images, sums = [], [], []
    t0 = time.perf_counter()
    for i, v in enumerate(views):
        if i and seconds is not None:
            spent = time.perf_counter() - t0
            if spent + spent / i > seconds:
                break
        out = render_view(model, np.asarray(ds.poses[v], np.float64),
                          np.asarray(ds.intrinsics, np.float64) / downscale, (H, W),
                          lambda: view_rays(ds, ds.poses[v:v + 1], downscale),
                          depth=False)
        rgb = out["rgb"]
        gt = downscale_image(ds.images[v], downscale)
        m = image_metrics(rgb, gt)
        m["view"] = int(v)
        if half_fitted:
            from ..references.reference_exposure import gain_sums, half_fitted_psnr
            m["psnr_half_fitted"], m["psnr_right_half"] = half_fitted_psnr(rgb, gt)
            masked = ds.alpha is not None and "acc" in out
            sums.append(gain_sums(rgb, out.get("acc", 0.0), gt,
                                  getattr(model, "background", ds.background), masked))
        per_view.append(m)
        if i < keep:
            images.append(np.clip(rgb, 0, 1))
    return per_view, images, sums


RENDER_DIR = "renders"   # the final evaluation's first test views, render | ground truth
RENDER_VIEWS = 4


def save_renders(out_dir, ds, views, images) -> list:
    """PNGs ``out_dir/renders/test_VVV.png`` of renders [H, W, 3] in [0, 1] beside their ground
    truth (render left, ground truth right), small views enlarged (whole pixels repeated) to
    at least 256 pixels on their longer side; returns their paths."""
    import imageio.v3 as iio
    folder = Path(out_dir) / RENDER_DIR
    folder.mkdir(parents=True, exist_ok=True)
    paths = []
    for v, img in zip(views, images):
        pair = np.concatenate([img, np.clip(ds.images[v], 0, 1)], axis=1)
        k = max(1, 256 // max(img.shape[:2]))
        pair = pair.repeat(k, axis=0).repeat(k, axis=1)
        p = folder / f"test_{int(v):03d}.png"
        with atomic_path(p) as tmp:
            iio.imwrite(tmp, (pair * 255 + 0.5).astype(np.uint8))
        paths.append(p)
    return paths


def plot_error_vs_time(csv_path, png_path, title="", eval_downscale=1):
    """PSNR on held-out views against training seconds, from metrics.csv (periodic evaluations
    at 1 / eval_downscale resolution, the final one at full resolution)."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    every = list(csv.DictReader(open(csv_path)))
    rows = [r for r in every if r["eval_psnr"]]
    # the final evaluation over every test view is the row after the last periodic one
    final = rows[-1] if len(rows) > 1 and not rows[-1]["train_loss"] and rows[-1]["eval_views"] \
        and rows[-1]["eval_views"] != rows[-2]["eval_views"] else None
    periodic = rows[:-1] if final else rows
    fig, ax = plt.subplots(figsize=(6, 4), dpi=110)
    if rows:
        t = [float(r["seconds"]) for r in periodic]
        p = [float(r["eval_psnr"]) for r in periodic]
        nv = periodic[-1]["eval_views"] if periodic else "?"
        at = f" at 1/{eval_downscale} resolution" if eval_downscale > 1 else ""
        ax.plot(t, p, "o-", ms=3, label=f"eval PSNR ({nv} held-out views{at})")
        if final:
            ax.plot([float(final["seconds"])], [float(final["eval_psnr"])], "*", ms=10,
                    label=f"final: all {final['eval_views']} test views, "
                          f"{float(final['eval_psnr']):.2f} dB")
        tr = [(float(r["seconds"]), float(r["train_psnr"])) for r in every if r["train_psnr"]]
        if tr:
            ax.plot(*zip(*tr), "-", alpha=0.5, label="train PSNR (batch)")
        ax.legend(loc="lower right")
    ax.set_xlabel("training time (s, evaluation excluded)")
    ax.set_ylabel("PSNR (dB)")
    ax.set_title(title, fontsize=9)
    ax.grid(alpha=0.3)
    fig.tight_layout()
    try:
        with atomic_path(png_path) as tmp:   # Ctrl-C during the save leaves no partial file
            fig.savefig(tmp)
    finally:
        plt.close(fig)


class Trainer:
    def __init__(self, device, ds, cfg, out_dir, resume=False, model_factory=None, log=print):
        # never train on wrong gradients: every registered kind's check of the device
        ensure_trusted(device, [k.selfcheck for k in registry.kinds() if k.selfcheck], log)
        if model_factory is None:
            model_factory = registry.get(cfg.train.model)
        self.device = device
        self.ds = ds
        self.cfg = cfg
        self.out = Path(out_dir)
        self.log = log
        self.out.mkdir(parents=True, exist_ok=True)
        self.ckpt_path = self.out / checkpoint.CKPT_NAME
        self.csv_path = self.out / "metrics.csv"
        t = cfg.train
        self.background = tuple(t.background) if t.background else tuple(ds.background)
        self.iteration = 0
        self.seconds = 0.0
        self.comm = getattr(model_factory, "comm", None)
        self.primary = self.comm is None or self.comm.Get_rank() == 0   # writes the run's files
        if self.primary:
            rundir.remove_stale_temps(self.out)
            checkpoint.remove_unreferenced_bricks(self.out)
        if self.comm is not None:
            self.comm.Barrier()
        if resume:
            # a distributed run reads its own brick file when the rank count is the same
            state = checkpoint.load(self.ckpt_path, brick=getattr(model_factory, "brick", None))
            try:
                self.model = model_factory.from_state(device, state, cfg)
            except StateError as e:
                raise checkpoint.CheckpointError(f"checkpoint {self.ckpt_path}: {e}") from None
            self.iteration = int(state["iteration"])
            self.seconds = float(state["seconds"])
            if self.primary:
                rundir.trim_metrics(self.csv_path, CSV_FIELDS, self.iteration)
                self.log(f"resumed from {self.ckpt_path} at iteration {self.iteration} "
                         f"({self.seconds:.1f} s)")
        else:
            self.model = model_factory.create(device, cfg, ds, self.background)
            if self.primary:
                with open(self.csv_path, "w", newline="") as f:
                    csv.DictWriter(f, CSV_FIELDS).writeheader()
        views = registry.get(cfg.train.model).batches == "views"
        if views:   # the model draws its own training views
            self.model.attach(ds, t.max_train_images)
        if self.primary:
            write_text(self.out / "config.json", json.dumps(cfg.to_dict(), indent=2))
        # a model that draws its own views (Kind.batches "views") needs no ray store
        self.rays = None if views else training_rays(
            device, ds, t.max_train_images, alpha=getattr(self.model, "random_background", False))
        test = ds.split.get("test", ds.split.get("val"))
        self.test_views = np.asarray(test)
        k = min(t.eval_views, len(self.test_views))
        self.periodic_views = self.test_views[np.linspace(0, len(self.test_views) - 1, k).astype(int)]
        # periodic evaluations: downscaled, but no smaller than the 11x11 SSIM window
        self.eval_downscale = max(1, min(t.eval_downscale, min(ds.hw) // EVAL_MIN_SIDE))

    @property
    def _eval_comm(self):
        """The ranks that share out an evaluation's views: those of a data-parallel run, whose
        every rank holds the whole model (its ``ranks``), else None."""
        return self.comm if getattr(self.model, "ranks", None) is not None else None

    def _row(self, **kw):
        if not self.primary:
            return
        with open(self.csv_path, "a", newline="") as f:
            csv.DictWriter(f, CSV_FIELDS).writerow({k: kw.get(k, "") for k in CSV_FIELDS})
        for sink in self.metric_sinks:
            sink.row(kw)

    def save(self):
        whole = self.comm is not None and not hasattr(self.model, "checkpoint_layout")
        if whole and not self.primary:   # every rank holds the whole model: rank 0 writes it
            self.comm.Barrier()
            return
        state = self.model.state_dict()
        state.update(iteration=self.iteration, seconds=self.seconds,
                     run_config=self.cfg.to_dict(), dataset=dataset_meta(self.ds))
        if hasattr(self.model, "checkpoint_layout"):   # collective: every rank its part
            checkpoint.save_distributed(self.ckpt_path, state, self.comm,
                                        **self.model.checkpoint_layout())
        else:
            try:
                checkpoint.save(self.ckpt_path, state)
                # a distributed checkpoint's part files, resumed by one process, are stale
                checkpoint.remove_unreferenced_bricks(self.out)
            finally:
                if whole:
                    self.comm.Barrier()

    def _plot(self, title, downscale):
        if self.primary:
            plot_error_vs_time(self.csv_path, self.out / "error_vs_time.png", title, downscale)

    def run(self):
        """Train until the time or iteration budget is spent (or Ctrl-C), evaluating and
        checkpointing on the way; then save, evaluate every test view and return the result."""
        loop = self._setup()
        memory = getattr(self.device, "memory", None)   # clrf/runtime/devmem.py
        if memory is not None:
            memory.reset_peaks()   # the run's own peak (what an earlier run freed left out)
        interrupted = False
        old = signal.getsignal(signal.SIGINT)
        self._sigint = False
        held = _hold_sigint(self)
        try:
            while True:
                self._maybe_eval(loop)
                if self._done():
                    break
                self._maybe_checkpoint(loop)
                self._step(loop)
                if self._interrupt_seen():
                    raise KeyboardInterrupt
        except KeyboardInterrupt:
            interrupted = True
            loop.prog.message(f"interrupted at iteration {self.iteration}: saving a checkpoint")
        finally:
            if held:
                signal.signal(signal.SIGINT, old)
            loop.prog.close()
        self._take_losses(loop)
        if memory is not None:   # training's peak, before the final evaluation renders
            self.device_memory = memory.summary()
            loop.prog.message(memory.describe())
        self.save()
        return self._finish(loop, interrupted)

    def _interrupt_seen(self) -> bool:
        """Whether Ctrl-C came during the last step (``_hold_sigint``); under MPI, whether it
        came to any rank, so that every rank stops after the same step."""
        seen = self._sigint
        if self.comm is not None:
            from mpi4py import MPI
            seen = bool(self.comm.allreduce(int(seen), op=MPI.MAX))
        return seen

    def _setup(self) -> "_Loop":
        """The loop's state: progress output, the first evaluation and checkpoint times."""
        t = self.cfg.train
        prog = TrainProgress(t.max_seconds, self.seconds)
        if not self.primary:   # one voice per run: rank 0's
            prog.message = lambda text: None
        caps = self.device.caps
        version = caps.platform_version.split()
        title = (f"{self.ds.name}: {self.model.kind}, {caps.name} "
                 f"({version[3] if len(version) > 3 else ''})")
        return _Loop(prog=prog, batch=self.model.batch_size, title=title,
                     next_eval=self.seconds + (0 if self.iteration == 0 else t.eval_every),
                     next_row=self.seconds + t.eval_every,
                     next_ckpt=self.seconds + t.checkpoint_every)

    def _done(self) -> bool:
        t = self.cfg.train
        return self.seconds >= t.max_seconds or self.iteration >= t.max_iters

    def _maybe_eval(self, loop: "_Loop"):
        """A periodic evaluation when one is due (and always before stopping): a metrics row,
        the plot, a progress line, the viewer told."""
        t = self.cfg.train
        due = self.seconds >= loop.next_eval or self._done()
        if not due and self.seconds < loop.next_row:
            return
        self._take_losses(loop)
        loop.next_row = self.seconds + t.eval_every
        if not due:
            # the evaluations are stretched (next_eval_at); the training loss keeps
            # train.eval_every's rhythm in metrics.csv, in a row of its own
            if loop.losses:
                lt = float(np.mean(loop.losses))
                self._row(iteration=self.iteration, seconds=f"{self.seconds:.3f}",
                          train_loss=f"{lt:.6g}", train_psnr=f"{psnr_from_mse(lt):.3f}",
                          rays_per_s=f"{self._rate:.0f}", model=self.model.describe())
                loop.losses = []
            return
        # the untrained model's point of the curve: one view of at most ANCHOR_PIXELS (an
        # untrained model renders slowest, nothing is pruned yet, and its figure only
        # anchors the curve: a 800x533 hash view took 3 minutes there on 2 vCPUs)
        if self.iteration == 0:
            views, scale = self.periodic_views[:1], anchor_downscale(self.ds.hw,
                                                                      self.eval_downscale)
        else:
            views, scale = self.periodic_views, self.eval_downscale
        # as many of the views as the evaluations' share of the wall time allows (at least
        # one; a quick evaluation all of them)
        allowance = EVAL_SHARE / (1.0 - EVAL_SHARE) * self.seconds - loop.eval_spent
        t0, built = time.perf_counter(), getattr(self.device, "build_seconds", 0.0)
        # (under MPI every rank renders them all, a rank's render may be collective, or
        # where every rank holds the whole model, each renders its share)
        ev = evaluate(self.model, self.ds, views, downscale=scale,
                      seconds=None if self.comm is not None else
                      max(allowance, EVAL_STRETCH_MIN_S), comm=self._eval_comm)
        views = views[:len(ev["views"])]
        # its cost without one-off program builds (the first evaluation builds the renderer)
        loop.eval_wall = max(0.0, time.perf_counter() - t0
                             - (getattr(self.device, "build_seconds", 0.0) - built))
        if self.comm is not None:   # the slowest rank's: every rank evaluates next together
            from mpi4py import MPI
            loop.eval_wall = self.comm.allreduce(loop.eval_wall, op=MPI.MAX)
        loop.eval_spent += loop.eval_wall
        loop.last_eval = ev
        losses = loop.losses
        lt = float(np.mean(losses)) if losses else float("nan")
        self._row(iteration=self.iteration, seconds=f"{self.seconds:.3f}",
                  train_loss=f"{lt:.6g}" if losses else "",
                  train_psnr=f"{psnr_from_mse(lt):.3f}" if losses else "",
                  eval_psnr=f"{ev['psnr']:.3f}", eval_ssim=f"{ev['ssim']:.4f}",
                  eval_views=len(views),
                  rays_per_s=f"{self._rate:.0f}" if losses else "",
                  model=self.model.describe())
        loop.losses = []
        self._plot(loop.title, t.eval_downscale)
        loop.prog.message(f"it {self.iteration:6d}  {self.seconds:7.1f}s  eval PSNR "
                          f"{ev['psnr']:.2f}  SSIM {ev['ssim']:.3f}  "
                          f"({len(views)} view{'s' if len(views) > 1 else ''})  "
                          f"{self.model.describe()}")
        # a view's cost at the periodic size, predicted from this one's per pixel
        view = loop.eval_wall * _pixels(self.ds.hw, self.eval_downscale) / (
            len(views) * _pixels(self.ds.hw, scale))
        loop.next_eval = next_eval_at(self.seconds, t.eval_every, loop.eval_spent, view,
                                      len(self.periodic_views))
        if self.viewer is not None:
            self.viewer.evaluated(self, ev)

    def _maybe_checkpoint(self, loop: "_Loop"):
        if self.seconds >= loop.next_ckpt:
            self._take_losses(loop)    # a loss that became NaN keeps the last checkpoint
            self.save()
            loop.next_ckpt = self.seconds + self.cfg.train.checkpoint_every

    def budget(self) -> Budget:
        """The budget hook's view of the run before the next step."""
        t = self.cfg.train
        frac = min(1.0, max(self.seconds / t.max_seconds, self.iteration / t.max_iters))
        return Budget(self.iteration, self.seconds, frac, self.rays)

    def _step(self, loop: "_Loop"):
        """One training step: the model's per-iteration work (pruning, upsampling), a batch,
        the fused step; the clock counts only this (the slowest rank's time under MPI)."""
        t = self.cfg.train
        t0, built = time.perf_counter(), getattr(self.device, "build_seconds", 0.0)
        msg = self.model.on_iteration(self.iteration, self.budget())
        if msg:
            loop.prog.message(f"it {self.iteration:6d}  {msg}")
        loop.batch = self.model.batch_size     # a model may adapt it step by step
        loss = train_on_batch(self.model, self.rays, t.seed, self.iteration, loop.batch)
        if isinstance(loss, Pending):
            # the device may still be running this step: before anything that reports or
            # stops, wait for it inside the step's time, so that the clock counts its work
            loop.pending.append((self.iteration, loss))
            seconds = self.seconds + time.perf_counter() - t0
            if seconds >= min(loop.next_eval, loop.next_row, loop.next_ckpt, t.max_seconds) \
                    or self.iteration + 1 >= t.max_iters:
                self.device.queue.finish()
        # without one-off program builds (a first run's cold builds would otherwise spend
        # seconds of a short budget, and shift its PSNR-against-time curve)
        dt = max(0.0, time.perf_counter() - t0
                 - (getattr(self.device, "build_seconds", 0.0) - built))
        if self.comm is not None:   # the slowest rank's time, the same on every rank
            from mpi4py import MPI
            dt = self.comm.allreduce(dt, op=MPI.MAX)
        if not isinstance(loss, Pending):
            self._take_loss(loop, self.iteration, loss)
        self._take_losses(loop, wait=False)
        self.seconds += dt
        self.iteration += 1
        self._rate = loop.batch / dt if dt > 0 else 0.0
        last = loop.last_loss
        loop.prog.update(f"it {self.iteration} loss {last:.5f} PSNR {psnr_from_mse(last):5.2f} "
                         f"{self._rate / 1e3:.1f}k rays/s", self.seconds)
        if self.viewer is not None:   # clrf train --view (clrf/viewer/live.py)
            self.viewer.step(self, last)

    def _take_losses(self, loop: "_Loop", wait: bool = True):
        """The step losses still on the device (a model that returns a Pending) that have
        arrived, in step order; wait: all of them."""
        while loop.pending and (wait or loop.pending[0][1].ready):
            it, loss = loop.pending.pop(0)
            self._take_loss(loop, it, float(loss))

    def _take_loss(self, loop: "_Loop", it: int, loss: float):
        if not np.isfinite(loss):
            raise FloatingPointError(f"training loss became {loss} at iteration {it}; the "
                                     f"last checkpoint is kept")
        loop.losses.append(loss)
        loop.last_loss = loss

    def _finish(self, loop: "_Loop", interrupted: bool) -> dict:
        """The run's result: the final evaluation over every test view (renders, eval.json,
        the last metrics row) unless interrupted, else the last periodic one."""
        t = self.cfg.train
        result = {"iteration": self.iteration, "seconds": self.seconds,
                  "interrupted": interrupted}
        if self.calibration is not None:
            result["exposure_calibration"] = self.calibration
        if self.device_memory is not None:
            result["device_memory"] = self.device_memory
        if t.final_eval and not interrupted:
            corr = corrections.of(self.model)
            fitted = corr.colour is not None   # a colour transform per training image
            ev = evaluate(self.model, self.ds, self.test_views, keep_images=RENDER_VIEWS,
                          half_fitted=fitted, comm=self._eval_comm)
            if self.primary:
                result["renders"] = [str(p) for p in save_renders(
                    self.out, self.ds, self.test_views, ev.pop("images"))]
            result.update(psnr=ev["psnr"], ssim=ev["ssim"], ssim_window=SSIM_NAME,
                          psnr_color_corrected=ev["psnr_color_corrected"],
                          views=ev["views"], n_views=len(self.test_views))
            if fitted:
                result.update({k: ev[k] for k in ("psnr_half_fitted", "psnr_right_half",
                                                  "psnr_shared_gain", "shared_gain")})
            summaries = corr.summaries()   # e.g. the mean correction of the training poses
            result.update(summaries)
            self._row(iteration=self.iteration, seconds=f"{self.seconds:.3f}",
                      eval_psnr=f"{ev['psnr']:.3f}", eval_ssim=f"{ev['ssim']:.4f}",
                      eval_views=len(self.test_views), model=self.model.describe())
            self._plot(loop.title, t.eval_downscale)
            if self.primary:
                write_text(self.out / "eval.json", json.dumps(result, indent=2))
            loop.prog.message(f"final: {len(self.test_views)} test views, PSNR {ev['psnr']:.2f} "
                              f"SSIM {ev['ssim']:.3f} (colour-corrected PSNR "
                              f"{ev['psnr_color_corrected']:.2f}) after {self.seconds:.1f} s "
                              f"({self.iteration} iterations)")
            if fitted:
                loop.prog.message(
                    f"final, NeRF-W protocol (colour fitted on each view's left half): right "
                    f"halves PSNR {ev['psnr_half_fitted']:.2f} (as rendered "
                    f"{ev['psnr_right_half']:.2f}); under one gain per channel for all "
                    f"views {ev['psnr_shared_gain']:.2f} (gain "
                    f"{' '.join(f'{g:.3f}' for g in ev['shared_gain'])}); "
                    f"{corr.colour.describe()}")
            for c in corr:
                s = summaries.get(f"{c.name}_correction")
                if s:
                    loop.prog.message(f"final: training {c.describe()} (mean over "
                                      f"{s['images']} images)")
        elif loop.last_eval is not None:
            result.update(psnr=loop.last_eval["psnr"], ssim=loop.last_eval["ssim"],
                          ssim_window=SSIM_NAME)
        return result

    _rate = 0.0
    viewer = None       # clrf.viewer.live.LiveViewer of `clrf train --view`
    calibration = None  # what an exposure calibration before the run did (calibrate.py)
    device_memory = None   # training's device memory (DeviceMemory.summary), once it ends
    metric_sinks = ()   # extra receivers of every metrics.csv row (outputs/tblog.py TensorBoardLog)


EVAL_SHARE = 0.15   # periodic evaluations take at most this share of the wall time
EVAL_STRETCH_MIN_S = 1.0   # ... once one takes at least this long (short test runs keep theirs)
ANCHOR_PIXELS = 128 * 128  # the untrained model's one view is downscaled to at most this


def next_eval_at(seconds: float, every: float, spent: float, view: float,
                 views: int) -> float:
    """Training seconds of the next periodic evaluation of ``views`` views, each predicted to
    take ``view`` seconds: ``train.eval_every`` after ``seconds``, or, where an evaluation
    takes EVAL_STRETCH_MIN_S or more, once the evaluations so far (``spent`` wall seconds)
    and one more view fit in EVAL_SHARE of the wall time,
    (spent + view) / (t + spent + view) <= share; the evaluation then renders as many views
    as the share allows (``Trainer._maybe_eval``). The cost is predicted before the
    evaluation runs, so not even the first slow one oversteps: a capture whose views are
    slow to render (800x533 hash views before the occupancy grid has pruned anything: 3
    minutes a view) trains most of the time, and ``--max-seconds S`` ends near S of wall time.

    >>> next_eval_at(20.0, 10.0, 0.5, 0.1, 4), next_eval_at(20.0, 10.0, 30.0, 30.0, 4)
    (30.0, 340.0)
    """
    if view * views < EVAL_STRETCH_MIN_S:   # a quick evaluation keeps the configured rhythm
        return float(seconds) + float(every)
    return max(float(seconds) + float(every),
               (float(spent) + float(view)) * (1.0 - EVAL_SHARE) / EVAL_SHARE)


def anchor_downscale(hw, downscale: int = 1) -> int:
    """The periodic evaluations' ``downscale``, or more, until a view has at most
    ANCHOR_PIXELS pixels (the untrained model's point), its short side no less than the SSIM
    window.

    >>> anchor_downscale((533, 800)), anchor_downscale((100, 100)), anchor_downscale((20, 4000))
    (6, 1, 1)
    """
    f = max(1, int(downscale))
    while _pixels(hw, f) > ANCHOR_PIXELS and min(hw) // (f + 1) >= EVAL_MIN_SIDE:
        f += 1
    return f


def _pixels(hw, downscale: int) -> int:
    return (int(hw[0]) // downscale) * (int(hw[1]) // downscale)


@dataclass
class _Loop:
    """What Trainer.run's steps share while the loop runs."""
    prog: TrainProgress
    batch: int               # rays per step
    title: str               # of the PSNR-against-time plot
    next_eval: float         # training seconds of the next periodic evaluation
    next_ckpt: float         # and of the next checkpoint
    next_row: float          # and of the next metrics row (train.eval_every)
    losses: list = field(default_factory=list)   # batch losses since the last evaluation
    pending: list = field(default_factory=list)  # (iteration, Pending) losses not yet read
    last_loss: float = float("nan")              # the latest loss read
    last_eval: dict | None = None
    eval_wall: float = 0.0                       # wall seconds of the latest evaluation
    eval_spent: float = 0.0                      # and of all periodic ones of this run


def dataset_meta(ds):
    H, W = ds.hw
    return {"name": ds.name, "H": int(H), "W": int(W), "intrinsics": list(map(float, ds.intrinsics)),
            "background": list(map(float, ds.background)), "ndc": bool(ds.ndc),
            "near": float(ds.near), "far": float(min(ds.far, 1e10)), "preset": ds.preset,
            "bbox": np.asarray(ds.bbox).tolist(),
            "distortion": None if as_distortion(ds.distortion) is None
            else as_distortion(ds.distortion).to_json()}
