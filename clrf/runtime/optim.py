"""The optimisers (RMSProp, SGD, Adam; cl/optim.cl), Adam's constants and its host step for
small float64 parameter sets (``adam_host_step``), and learning-rate schedules."""
from __future__ import annotations

import math

import numpy as np
import pyopencl.array as cla

from .programs import float4, launch

MODES = {"rmsprop": 0, "sgd": 1, "adam": 2}   # OPT_MODE of cl/optim.cl
ADAM_LOCAL_SIZE = 64   # adam_step has no loop: PoCL vectorises across the group
ADAM_BETAS = (0.9, 0.999)   # PyTorch's defaults (the published splat code and gsplat's)
ADAM_EPS = 1e-15            # parameters with tiny gradients still move (the hash tables', the
#                             per-view corrections')


def adam_host_step(param, m, v, grad, t: int, lr, betas=ADAM_BETAS, eps: float = ADAM_EPS):
    """Adam step t (1-based) of a small parameter set on the host, in place: numpy arrays
    ``param``, ``m`` (first moment), ``v`` (second moment) of one shape, ``grad`` its gradient,
    ``lr`` a rate or an array of rates of that shape.

        m <- b1 m + (1 - b1) g,   v <- b2 v + (1 - b2) g^2,
        param <- param - lr (m / (1 - b1^t)) / (sqrt(v / (1 - b2^t)) + eps)

    >>> p, m, v = np.zeros(2), np.zeros(2), np.zeros(2)
    >>> adam_host_step(p, m, v, np.array([1.0, -4.0]), 1, 0.1)
    >>> p            # the first step moves every entry by lr against its gradient's sign
    array([-0.1,  0.1])
    """
    b1, b2 = betas
    m[...] = b1 * m + (1 - b1) * grad
    v[...] = b2 * v + (1 - b2) * grad * grad
    mh = m / (1 - b1 ** t)
    vh = v / (1 - b2 ** t)
    param -= lr * mh / (np.sqrt(vh) + eps)


def expon_lr(step, lr_init, lr_final, max_steps, delay_steps=0, delay_mult=1.0):
    """Log-linear decay from lr_init to lr_final over max_steps, with an optional reverse-cosine
    warm-up from delay_mult * lr over delay_steps (svox2's schedule shape)."""
    if step < 0 or (lr_init == 0.0 and lr_final == 0.0):
        return 0.0
    if delay_steps > 0:
        delay = delay_mult + (1 - delay_mult) * math.sin(0.5 * math.pi * min(step / delay_steps, 1))
    else:
        delay = 1.0
    t = min(max(step / max(max_steps, 1), 0.0), 1.0)
    return delay * math.exp(math.log(lr_init) * (1 - t) + math.log(lr_final) * t)


def program(device, mode: str):
    """cl/optim.cl for optimiser ``mode`` (MODES) on ``device``."""
    return device.program("optim.cl", {"OPT_MODE": MODES[mode]})


def span_groups(spans, local_size: int) -> np.ndarray:
    """The work-groups of AdamSet's table: int32 [groups, 2] (first entry, end of its span) of
    each work-group when the (start, stop) ``spans`` are cut into pieces of ``local_size``
    entries."""
    parts = [np.stack([np.arange(a, b, local_size), np.full(-(-(b - a) // local_size), b)], 1)
             for a, b in spans if b > a]
    return np.concatenate(parts).astype(np.int32) if parts else np.zeros((0, 2), np.int32)


class AdamSet:
    """Adam optimisers (Optimizer, mode "adam", the same betas and eps) over up to MAX buffers,
    stepped in one launch (cl/optim.cl adam_multi): one launch for every parameter group of a
    model where the device runs the GPU-shaped kernels. Each optimiser keeps its buffers,
    moments, gradient (read at each step) and weight decay; lrs and spans are per optimiser.

    >>> both = AdamSet(dev, [adam_table, adam_net])
    >>> both.step([lr, lr], t, spans=[table_spans, None], clear_grad=[True, False])
    """

    MAX = 4

    def __init__(self, device, optimizers):
        opts = list(optimizers)
        if not 1 <= len(opts) <= self.MAX:
            raise ValueError(f"AdamSet: 1 to {self.MAX} optimisers, got {len(opts)}")
        first = opts[0]
        for o in opts:
            if o.mode != "adam" or (o.beta, o.beta2, o.eps) != (first.beta, first.beta2,
                                                                 first.eps):
                raise ValueError("AdamSet: every optimiser must be Adam with the same beta, "
                                 "beta2 and eps")
        self.device = device
        self.optimizers = opts
        self._key = self._table = None

    def _groups(self, spans):
        """adam_multi's table (int32 [groups, 4]: buffer, first entry, end of its span, 0) on
        the device and the local size, rebuilt when the spans change."""
        key = tuple(tuple(s) for s in spans)
        if self._key != key:
            ls = max(1, min(ADAM_LOCAL_SIZE, self.device.caps.max_work_group_size))
            parts = []
            for b, sp in enumerate(spans):
                g = span_groups(sp, ls)
                parts.append(np.concatenate([np.full((len(g), 1), b, np.int32), g,
                                             np.zeros((len(g), 1), np.int32)], 1))
            table = np.concatenate(parts).astype(np.int32)
            self._table = (cla.to_device(self.device.queue, table) if len(table) else None, ls)
            self._key = key
        return self._table

    def step(self, lrs, t: int, spans=None, clear_grad=None):
        """One Adam update of every optimiser: lrs[b] its learning rate, spans[b] its (start,
        stop) entries (None: all), clear_grad[b] zeroes its gradient once read (default no)."""
        opts = self.optimizers
        spans = [None] * len(opts) if spans is None else list(spans)
        clear = [False] * len(opts) if clear_grad is None else list(clear_grad)
        if not len(lrs) == len(spans) == len(clear) == len(opts):
            raise ValueError("AdamSet.step: one lr, span list and clear flag per optimiser")
        spans = [[(0, int(o.param.size))] if sp is None else
                 [(int(a), int(b)) for a, b in sp if b > a] for o, sp in zip(opts, spans)]
        groups, ls = self._groups(spans)
        if groups is None:
            return
        first = opts[0]
        bufs = []
        for b in range(self.MAX):
            o = opts[b] if b < len(opts) else None
            bufs += [None] * 4 if o is None else [o.param.data, o.grad.data, o.state.data,
                                                  o.state2.data]
        pad = lambda v: [float(x) for x in v] + [0.0] * (self.MAX - len(v))   # noqa: E731
        f4 = float4
        mask = sum(1 << b for b, c in enumerate(clear) if c)
        launch(self.device, first._kernel("adam_multi"), groups.shape[0] * ls,
               (groups.data, *bufs, f4(*pad(lrs)), f4(*pad([o.weight_decay for o in opts])),
                np.int32(mask), np.float32(first.beta), np.float32(first.beta2),
                np.float32(first.eps), np.float32(1.0 - first.beta ** t),
                np.float32(1.0 - first.beta2 ** t)), ls)


class Optimizer:
    """One optimiser over a device parameter buffer; its gradient buffer is ``self.grad``.

    - ``rmsprop`` (svox2 variant) / ``sgd``: param [N, D] or [N]; ``step(touched, lr, ...)``
      updates the rows with touched[k] != 0 only, then zeroes their gradient (cl/optim.cl), so
      gradient buffers never need a dense zero-fill. ``state``: RMSProp's mean square.
    - ``adam``: param [n]; ``step(None, lr, t=t)`` updates every entry with bias correction for
      the 1-based update count t. ``state`` / ``state2``: the first / second moments (beta,
      beta2 their decay rates); ``weight_decay`` adds weight_decay * p to the gradient (L2).
      The gradient is not reset (the MLP backward overwrites it) unless ``clear_grad`` (for
      gradients that a backward adds into, the hash tables').

    >>> opt = Optimizer(dev, grid.density)              # RMSProp over rows
    >>> opt.step(touched, lr=0.1, clear_touched=False)
    >>> adam = Optimizer(dev, net.params, "adam", beta=0.9, beta2=0.999, eps=1e-7, grad=net.grad)
    >>> adam.step(None, 5e-4, t=1)
    """

    def __init__(self, device, param, mode="rmsprop", beta=0.95, eps=1e-8, state=None,
                 grad=None, beta2=0.999, state2=None, weight_decay=0.0):
        if mode not in MODES:
            raise ValueError(f"optimizer: '{mode}' is not one of {sorted(MODES)}")
        self.device = device
        self.mode = mode
        self.beta = float(beta)
        self.beta2 = float(beta2)
        self.eps = float(eps)
        self.weight_decay = float(weight_decay)   # Adam only: g + weight_decay * p
        self.param = param
        self.grad = grad if grad is not None else cla.zeros_like(param)
        self.state = state if state is not None else cla.zeros_like(param)
        self.state2 = None
        if mode == "adam":
            self.state2 = state2 if state2 is not None else cla.zeros_like(param)
        self._one_launch = None   # AdamSet([self]): several spans in one launch (GPU shapes)

    def _kernel(self, name):
        return program(self.device, self.mode).kernel(name)

    def step(self, touched, lr, clear_touched=False, t: int = 1, clear_grad=False, spans=None,
             columns=None):
        """One update. RMSProp / SGD: rows with touched[k] != 0 (their gradient zeroed);
        ``columns`` (group, live): only the columns j with j % group < live step, the others'
        gradient is dropped (None: every column).
        Adam: every entry, or only those in ``spans`` ((start, stop) index pairs of the flat
        buffer: entries that can never get a gradient need no update; one launch for them all
        where the device runs the GPU-shaped kernels, a launch a span on CPUs); clear_grad
        zeroes the gradient once read."""
        if self.mode == "adam":
            bc1, bc2 = 1.0 - self.beta ** t, 1.0 - self.beta2 ** t
            tail = (self.param.data, self.grad.data, self.state.data, self.state2.data,
                    np.float32(lr), np.float32(self.beta), np.float32(self.beta2),
                    np.float32(self.eps), np.float32(bc1), np.float32(bc2),
                    np.float32(self.weight_decay), np.int32(bool(clear_grad)))
            spans = [(0, int(self.param.size))] if spans is None else \
                [(int(a), int(b)) for a, b in spans if b > a]
            if len(spans) > 1 and getattr(self.device.tuning, "gpu_kernels", False):
                if self._one_launch is None:              # every span in one launch
                    self._one_launch = AdamSet(self.device, [self])
                self._one_launch.step([lr], t, spans=[spans], clear_grad=[clear_grad])
                return
            for a, b in spans:   # CPUs: a launch a span (faster there: cl/optim.cl)
                launch(self.device, self._kernel("adam_step"), b - a,
                       (np.int32(a), np.int32(b)) + tail, ADAM_LOCAL_SIZE)
            return
        n = self.param.shape[0]
        D = 1 if self.param.ndim == 1 else self.param.shape[1]
        group, live = (D, D) if columns is None else (int(columns[0]), int(columns[1]))
        if not 1 <= group <= D or D % group or not 0 <= live <= group:
            raise ValueError(f"optimizer: columns {columns} do not divide a row of {D}")
        launch(self.device, self._kernel("update_rows"), n,
               (np.int32(n), np.int32(D), self.param.data, self.grad.data, self.state.data,
                touched.data, np.float32(lr), np.float32(self.beta), np.float32(self.eps),
                np.int32(bool(clear_touched)), np.int32(group), np.int32(live)))
