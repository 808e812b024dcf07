"""Host side of cl/mlp.cl: the fused NeRF MLP (one contiguous parameter buffer) and its kernels.

The parameter layout is defined once, in ``layer_desc`` of cl/mlp.cl; ``MLP.layout`` reads it
from the built program (the ``mlp_layout`` kernel), so host and kernels cannot disagree. So is
the register tile (rows and columns per work-item): the host's work split reads it back too.
The tile comes from the MLPSpec fields that are set, else the autotuner's cache, else the
device's default (clrf/mlp/autotune.py). Devices whose tuning has ``gpu_kernels`` (GPUs;
``CLRF_FORCE_GPU_KERNELS=1`` anywhere) run the GPU tiling instead (cl/mlp_gpu.h, MLP_GPU=1;
clrf/mlp/tiling.py): one launch of work-groups of GPU_BM samples per pass, the same
parameter and scratch layouts, and a weight gradient whose chunk the host picks per batch.

>>> spec = MLPSpec(width=64, depth=4, skip=-1, color_width=32, in_dim=51, dir_dim=27)
>>> net = MLP(dev, spec, seed=0)
>>> sigma, rgb = net.forward(x_enc_d, d_enc_d)        # device arrays [n], [n, 3]
>>> net.backward(dsigma_d, drgb_d, net.grad)          # net.grad: dL/dparams, same layout
"""
from __future__ import annotations

from dataclasses import asdict, dataclass, replace

import numpy as np
import pyopencl as cl
import pyopencl.array as cla

from .tiling import GPU_GROUPS_PER_CU, GPU_MIN_CHUNK, MLPTiling, mlp_tiling_for
from ..runtime.programs import count_arg, device_empty, device_zeros, launch, scratch, upload

MAX_RENDER_SCRATCH = 256 << 20  # bytes of MLP activations per render chunk (rows x NSLOT x 4)

ACT = {"none": 0, "relu": 1, "softplus": 2, "sigmoid": 3, "trunc_exp": 4}
SIGMA_EXP_MAX = 15.0   # cl/mlp.cl: trunc_exp's clamp of the pre-activation
GROUP_BYTES = None   # interleave backward and weight gradient per rows of this much A + G;
# None: one launch each. Measured on PoCL (Zen 4, AVX-512, n = 8192): launches cost more than
# the cache misses that interleaving saves (8x256: 16 MB groups 0.93x numpy, one launch 0.99x).
# Work-group sizes come from device.tuning (clrf/runtime/tuning.py): mlp_fused_local_size (big private
# tiles: 1) and elementwise_local_size; the GPU tiling's from its GPUTiling (GPU_WG).
GPU_KERNELS = ("mlp_forward", "mlp_density", "mlp_backward", "mlp_weight_grad")


@dataclass(frozen=True)
class MLPSpec:
    """Shape of the NeRF MLP and, optionally, its register tile (all compile-time defines of
    cl/mlp.cl). Tile fields left None come from the tuned cache or the device default."""

    width: int = 64            # trunk width W (multiple of 16)
    depth: int = 4             # trunk layers D
    skip: int = -1             # encoded position re-enters at the input of layer skip+1; -1 none
    color_width: int = 32      # view-dependent colour layer width (multiple of 16)
    in_dim: int = 51           # encoded position dims
    dir_dim: int = 27          # encoded direction dims
    hidden_act: str = "relu"   # "relu" | "softplus"
    sigma_act: str = "relu"    # "relu" | "softplus" | "trunc_exp" (exp of min(x, 15))
    color_depth: int = 1       # colour hidden layers (NeRF: 1; the hash model: 2)
    features: int | None = None  # feature outputs of the head (multiple of 16); None: width
    rows: int | None = None    # samples per work-item (register block); None: per device
    cols: int | None = None    # columns per tile, 16 or 32; None: per device
    dw_rows: int | None = None  # output neurons per work-item in the weight gradient
    dw_cols: int | None = None  # input columns per work-item in the weight gradient, 16 or 32
    dw_chunk: int | None = None  # rows per partial weight gradient (a second pass sums them)

    def defines(self) -> dict:
        """The shape defines (the tile's come from MLPTiling.defines)."""
        if self.hidden_act not in ("relu", "softplus"):
            raise ValueError(f"MLPSpec.hidden_act: must be 'relu' or 'softplus', got "
                             f"{self.hidden_act!r}")
        if self.sigma_act not in ("relu", "softplus", "trunc_exp"):
            raise ValueError(f"MLPSpec.sigma_act: must be 'relu', 'softplus' or 'trunc_exp', "
                             f"got {self.sigma_act!r}")
        d = {"MLP_WIDTH": self.width, "MLP_DEPTH": self.depth, "MLP_SKIP": self.skip,
             "MLP_COLOR_WIDTH": self.color_width, "MLP_IN": self.in_dim,
             "MLP_DIR_IN": self.dir_dim, "HIDDEN_ACT": ACT[self.hidden_act],
             "SIGMA_ACT": ACT[self.sigma_act]}
        if self.color_depth != 1:       # only when set: NeRF's builds keep their defines
            d["MLP_COLOR_DEPTH"] = self.color_depth
        if self.features is not None and self.features != self.width:
            d["MLP_FEAT"] = self.features
        return d

    @property
    def feat(self) -> int:
        """Feature outputs of the head."""
        return self.width if self.features is None else self.features

    def flops_per_sample(self) -> tuple:
        """(forward, forward+backward) multiply-add flops per sample, logical (unpadded) sizes."""
        W, D, WC, Fe = self.width, self.depth, self.color_width, self.feat
        macs = self.in_dim * W + (D - 1) * W * W + (self.in_dim * W if self.skip >= 0 else 0)
        macs += W * (Fe + 1) + (Fe + self.dir_dim) * WC + (self.color_depth - 1) * WC * WC
        macs += WC * 3
        return 2 * macs, 6 * macs


@dataclass(frozen=True)
class Layout:
    """Offsets read from cl/mlp.cl (see its header)."""

    n_layers: int
    nslot: int
    n_params: int
    rows: int                  # MLP_ROWS: samples per forward / backward work-item
    dw_chunk: int              # DW_CHUNK: scratch rows per partial weight gradient
    cols: int                  # MLP_COLS
    dw_rows: int               # DW_ROWS: output neurons per weight-gradient work-item
    dw_cols: int               # DW_COLS: input columns per weight-gradient work-item
    wgrad_items_per_chunk: int  # mlp_weight_grad work-items (GPU: work-groups) per chunk
    slots: dict                # SL_X, SL_XS, SL_HD, SL_FEAT, SL_DV, SL_C, SL_RGB
    layers: tuple              # per layer dict(in_off, nin, out_off, nout, w_off, b_off)
    gpu: dict | None = None    # the GPU tiling's sizes (wg, tm, tn, nc, bk, local_bytes,
    #                            dw_bs; rows is then GPU_BM, cols GPU_NC, dw_rows x dw_cols
    #                            the weight gradient's group tile), None for the CPU tiles

    def logical_shapes(self, spec: MLPSpec):
        """Per layer (rows, cols) of the unpadded weight matrix, and which padded rows / cols
        they occupy: list of (out_idx, in_idx) index arrays into the padded matrix."""
        D, W = spec.depth, spec.width
        out = []
        for l, L in enumerate(self.layers):
            if l < D:
                cols = np.arange(spec.in_dim) if l == 0 else np.arange(W)
                if l == spec.skip + 1 and l > 0:
                    cols = np.concatenate([np.arange(W), W + np.arange(spec.in_dim)])
                rows = np.arange(W)
            elif l == D:
                rows = np.concatenate([[0], 16 + np.arange(spec.feat)])
                cols = np.arange(W)
            elif l == D + 1:
                rows = np.arange(spec.color_width)
                cols = np.concatenate([np.arange(spec.feat), spec.feat + np.arange(spec.dir_dim)])
            elif l < self.n_layers - 1:
                rows = cols = np.arange(spec.color_width)
            else:
                rows = np.arange(3)
                cols = np.arange(spec.color_width)
            out.append((rows, cols))
        return out


LAYOUT_HEAD = 24   # ints before the per-layer records in mlp_layout's output


def read_layout(device, program) -> Layout:
    buf = device_zeros(device.queue, LAYOUT_HEAD + 6 * 64, np.int32)
    program.kernel("mlp_layout")(device.queue, (1,), (1,), buf.data)
    a = buf.get()
    nl = int(a[0])
    names = ("in_off", "nin", "out_off", "nout", "w_off", "b_off")
    h = LAYOUT_HEAD
    layers = tuple({k: int(v) for k, v in zip(names, a[h + 6 * l: h + 6 * l + 6])}
                   for l in range(nl))
    slots = dict(zip(("SL_X", "SL_XS", "SL_HD", "SL_FEAT", "SL_DV", "SL_C", "SL_RGB"),
                     (int(a[5]), int(a[6]), int(a[7]), int(a[8]), int(a[9]), int(a[10]),
                      int(a[11]))))
    gpu = None
    if a[16]:
        gpu = dict(zip(("wg", "tm", "tn", "nc", "bk", "local_bytes", "dw_bs"),
                       (int(v) for v in a[17:24])))
    return Layout(nl, int(a[1]), int(a[2]), int(a[3]), int(a[4]), int(a[12]), int(a[13]),
                  int(a[14]), int(a[15]), slots, layers, gpu)


def init_params(spec: MLPSpec, layout: Layout, rng: np.random.Generator) -> np.ndarray:
    """NeRF's initialisation (Keras Dense defaults): Glorot-uniform weights over the logical
    fan-in/fan-out, zero biases; padding zero."""
    p = np.zeros(layout.n_params, np.float32)
    for L, (rows, cols) in zip(layout.layers, layout.logical_shapes(spec)):
        fan_in, fan_out = len(cols), len(rows)
        lim = np.sqrt(6.0 / (fan_in + fan_out))
        Wm = np.zeros((L["nout"], L["nin"]), np.float32)
        Wm[np.ix_(rows, cols)] = rng.uniform(-lim, lim, (fan_out, fan_in))
        p[L["w_off"]:L["b_off"]] = Wm.ravel()
    return p


def program(device, spec: MLPSpec, tiling: MLPTiling | None = None):
    """cl/mlp.cl for an MLP of ``spec`` with ``tiling`` (default ``mlp_tiling_for(device,
    spec)``) on ``device``: the GPU tiling's defines, or the CPU tiles' with the tuning's
    software prefetch."""
    tiling = tiling or mlp_tiling_for(device, spec)
    d = {**spec.defines(), **tiling.defines()}
    if tiling.gpu is None:
        d["MLP_PREFETCH"] = int(device.tuning.mlp_prefetch)
    return device.program("mlp.cl", d)


class MLP:
    """One NeRF MLP on a device: parameters, their transposed copy, scratch and gradients.
    ``tiling`` is the register tile it was built with (MLPTiling; ``tiling.gpu`` set: the GPU
    tiling), by default ``mlp_tiling_for(device, spec)``."""

    def __init__(self, device, spec: MLPSpec, seed: int = 0, params: np.ndarray | None = None,
                 tiling: MLPTiling | None = None):
        self.device = device
        self.spec = spec
        self.tiling: MLPTiling = tiling or mlp_tiling_for(device, spec)
        self.gpu = self.tiling.gpu is not None
        if self.gpu:
            self.program = self._build_gpu()
        else:
            self.program = program(device, spec, self.tiling)
        self.layout = read_layout(device, self.program)
        q = device.queue
        if params is None:
            params = init_params(spec, self.layout, np.random.default_rng(seed))
        params = np.asarray(params, np.float32)
        if params.shape != (self.layout.n_params,):
            raise ValueError(f"params: expected {self.layout.n_params} floats for {spec}, got "
                             f"shape {params.shape}")
        self.params = upload(q, params)
        self.params_t = cla.empty_like(self.params)
        self.grad = cla.zeros_like(self.params)
        self._scratch_rows = 0
        self.group_bytes = GROUP_BYTES
        self.A = self.G = self.partial = None
        self._n = 0
        self._count = None        # the last forward's device count (bounded buffers), or None
        self._stale = False       # density() overwrote the last forward's activations
        self._k = {name: self.program.kernel(name) for name in (
            "mlp_forward", "mlp_density", "mlp_backward", "mlp_weight_grad", "mlp_reduce",
            "mlp_transpose")}
        self.sync_params()

    def _build_gpu(self):
        """The GPU tiling's program; where a kernel built for GPU_WG work-items allows fewer
        (CL_KERNEL_WORK_GROUP_SIZE: registers), rebuilt with half the group until it fits."""
        dev = self.device
        while True:
            prg = program(dev, self.spec, self.tiling)
            wg = self.tiling.gpu.wg
            info = cl.kernel_work_group_info.WORK_GROUP_SIZE
            most = min(prg.kernel(k).get_work_group_info(info, dev.cl_device)
                       for k in GPU_KERNELS)
            if most >= wg or wg == 1:
                return prg
            half = replace(self.tiling.gpu, wg=wg // 2)
            self.tiling = replace(self.tiling, gpu=half)

    # ---- buffers ------------------------------------------------------------------------
    def n_rows(self, n: int) -> int:
        r = self.layout.rows
        return (n + r - 1) // r * r

    def _ensure_scratch(self, n: int, backward: bool = False):
        """A (forward) and, for a backward, G and the partial gradients, for >= n rows. Only
        grown, never shrunk; a render allocates no G."""
        rows = max(self.n_rows(n), self.layout.rows)
        q = self.device.queue
        if rows > self._scratch_rows:
            self.A = device_zeros(q, rows * self.layout.nslot, np.float32)
            self._scratch_rows = rows
            self.G = self.partial = None
        if backward and self.G is None:
            self.G = device_zeros(q, self._scratch_rows * self.layout.nslot, np.float32)
            if self.gpu:       # grown per batch (_gpu_chunks)
                self.partial = device_empty(q, self.layout.n_params, np.float32)
            else:
                chunks = (self._scratch_rows + self.layout.dw_chunk - 1) // self.layout.dw_chunk
                self.partial = device_empty(q, chunks * self.layout.n_params, np.float32)

    def sync_params(self):
        """Refresh the transposed copy the forward reads; call after every update of params."""
        launch(self.device, self._k["mlp_transpose"], self.layout.n_params,
               (self.params.data, self.params_t.data),
               self.device.tuning.elementwise_local_size)

    def set_params(self, params: np.ndarray):
        self.params.set(np.ascontiguousarray(params, np.float32))
        self.sync_params()

    # ---- passes -------------------------------------------------------------------------
    def forward(self, x_enc, d_enc, sigma=None, rgb=None, count=None):
        """sigma [n], rgb [n, 3] (device) of encoded inputs x_enc [n, in_dim], d_enc [n, dir_dim].
        Keeps every activation in self.A for a following backward. ``count`` (int32 [1] on the
        device, or None): only its first count rows (a bounded buffer of n; the backward then
        reads the same count)."""
        n = int(x_enc.shape[0])
        self._ensure_scratch(n)
        sigma = sigma if sigma is not None else scratch(self.device, n)
        rgb = rgb if rgb is not None else scratch(self.device, (n, 3))
        self._n, self._count = n, count
        self._stale = False
        self._launch_tiles(self._k["mlp_forward"], n,
                           (np.int32(n), count_arg(count), x_enc.data, d_enc.data,
                            self.params_t.data, self.A.data, sigma.data, rgb.data))
        return sigma, rgb

    def _launch_tiles(self, kernel, n: int, args):
        """The forward, density or backward over n samples: one work-item per tile of
        layout.rows samples (CPU tiles) or one work-group per block of them (GPU tiling)."""
        tiles = self.n_rows(n) // self.layout.rows
        if self.gpu:
            wg = self.layout.gpu["wg"]
            launch(self.device, kernel, tiles * wg, args, wg)
        else:
            launch(self.device, kernel, tiles, args, self.device.tuning.mlp_fused_local_size)

    def density(self, x_enc, sigma=None, count=None):
        """sigma [n] (device) of encoded positions x_enc [n, in_dim]: the trunk and the head
        only (no direction, no colour layers; about a third of a forward for the hash model's
        networks). Uses the activation scratch: a backward must follow a forward, not this.
        ``count``: as in forward."""
        n = int(x_enc.shape[0])
        self._ensure_scratch(n)
        sigma = sigma if sigma is not None else scratch(self.device, n)
        self._stale = True
        self._launch_tiles(self._k["mlp_density"], n,
                           (np.int32(n), count_arg(count), x_enc.data, self.params_t.data,
                            self.A.data, sigma.data))
        return sigma

    def backward(self, dsigma, drgb, grad=None, accumulate=False, want_input=False):
        """Gradients of the last forward: grad (default self.grad) gets dL/dparams (added to it
        with accumulate=True); returns (dx_enc [n, in_dim], dd_enc [n, dir_dim]) device arrays
        with want_input, else None."""
        if self._stale:
            raise RuntimeError("MLP.backward: density() overwrote the activations; run "
                               "forward() again first")
        n = self._n
        grad = self.grad if grad is None else grad
        dx = dd = None
        if want_input:
            dx = scratch(self.device, (n, self.spec.in_dim))
            dd = scratch(self.device, (n, self.spec.dir_dim))
        self._ensure_scratch(n, backward=True)
        dummy = self.A.data
        kb = self._k["mlp_backward"]
        args = (np.int32(n), count_arg(self._count), dsigma.data, drgb.data, self.params.data,
                self.A.data, self.G.data, np.int32(bool(want_input)),
                dx.data if dx is not None else dummy, dd.data if dd is not None else dummy)
        if self.gpu:     # one launch each: backward, weight gradient, reduce
            self._launch_tiles(kb, n, args)
            self.weight_grad(grad, accumulate)
            return (dx, dd) if want_input else None
        kb.set_args(*args)
        # The backward, then the weight gradient: in one launch each, or (group_bytes set)
        # interleaved by groups of rows so that the weight gradient reads A and G while they
        # are still in the last-level cache.
        rows, R = self.n_rows(n), self.layout.rows
        chunk = self.layout.dw_chunk
        n_chunks = (rows + chunk - 1) // chunk
        per_group = max(1, n_chunks)
        if self.group_bytes is not None:
            per_group = max(1, self.group_bytes // (8 * self.layout.nslot) // chunk)
        for c0 in range(0, n_chunks, per_group):
            c1 = min(n_chunks, c0 + per_group)
            t0, t1 = c0 * chunk // R, min(rows, c1 * chunk) // R
            self._enqueue(kb, t0, t1 - t0)
            self._weight_grad_chunks(rows, c0, c1)
        self._reduce(grad, n_chunks, accumulate)
        return (dx, dd) if want_input else None

    def _enqueue(self, kernel, start: int, count: int):
        """Items start .. start+count-1 exactly (local size 1, so no rounding spills into the
        next group)."""
        if count > 0:
            cl.enqueue_nd_range_kernel(self.device.queue, kernel, (count,), (1,),
                                       global_work_offset=(start,))

    def _weight_grad_chunks(self, rows: int, c0: int, c1: int):
        """Partial weight and bias gradients of chunks c0 .. c1-1 (after their backward), all
        layers in one launch."""
        k = self._k["mlp_weight_grad"]
        k.set_args(np.int32(rows), count_arg(self._count), self.A.data, self.G.data,
                   self.partial.data)
        ipc = self.layout.wgrad_items_per_chunk
        self._enqueue(k, c0 * ipc, (c1 - c0) * ipc)

    def _reduce(self, grad, n_chunks: int, accumulate: bool):
        k = self._k["mlp_reduce"]
        k.set_args(np.int32(n_chunks), self.partial.data, grad.data, np.int32(bool(accumulate)))
        ng = self.layout.n_params // 16
        ls = self.device.tuning.elementwise_local_size
        cl.enqueue_nd_range_kernel(self.device.queue, k, ((ng + ls - 1) // ls * ls,), (ls,))

    def weight_grad(self, grad, accumulate=False):
        """Weight and bias gradients of the last forward/backward pair into grad (all chunks;
        backward() already does this, interleaved; tools/nerf_bench.py times it alone)."""
        rows = self.n_rows(self._n)
        if self.gpu:
            chunk, n_chunks = self._gpu_chunks(rows)
            if n_chunks * self.layout.n_params > self.partial.size:
                self.partial = device_empty(self.device.queue, n_chunks * self.layout.n_params,
                                         np.float32)
            if n_chunks:
                wg = self.layout.gpu["wg"]
                launch(self.device, self._k["mlp_weight_grad"],
                       n_chunks * self.layout.wgrad_items_per_chunk * wg,
                       (np.int32(rows), count_arg(self._count), np.int32(chunk), self.A.data,
                        self.G.data, self.partial.data), wg)
            self._reduce(grad, n_chunks, accumulate)
            return
        n_chunks = (rows + self.layout.dw_chunk - 1) // self.layout.dw_chunk
        self._weight_grad_chunks(rows, 0, n_chunks)
        self._reduce(grad, n_chunks, accumulate)

    def _gpu_chunks(self, rows: int) -> tuple:
        """(rows per chunk, chunks) of the GPU tiling's weight gradient over ``rows`` scratch
        rows: the tiling's chunk if set, else enough chunks for GPU_GROUPS_PER_CU work-groups
        per compute unit (each chunk is wgrad_items_per_chunk groups), none under
        GPU_MIN_CHUNK rows, each a whole number of staging steps (dw_bs rows)."""
        if rows <= 0:
            return 1, 0
        chunk = self.tiling.gpu.chunk
        if not chunk:
            target = GPU_GROUPS_PER_CU * self.device.caps.compute_units
            p = max(1, min(-(-target // self.layout.wgrad_items_per_chunk),
                           rows // GPU_MIN_CHUNK))
            per, bs = -(-rows // p), self.layout.gpu["dw_bs"]
            chunk = -(-per // bs) * bs
        return chunk, -(-rows // chunk)

    def spec_dict(self) -> dict:
        return asdict(self.spec)
