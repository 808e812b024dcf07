"""Optimisers over device parameter rows, and learning-rate schedules."""
from __future__ import annotations

import math

import numpy as np
import pyopencl.array as cla

from .programs import launch

MODES = {"rmsprop": 0, "sgd": 1}


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


class RowOptimizer:
    """RMSProp (svox2 variant) or SGD over rows of a [N, D] parameter; updates touched rows only.

    The gradient buffer is consumed and reset to zero by each step (see cl/optim.cl).
    """

    def __init__(self, device, param, mode="rmsprop", beta=0.95, eps=1e-8, state=None):
        if mode not in MODES:
            raise ValueError(f"optimizer: '{mode}' is not one of {sorted(MODES)}")
        self.device = device
        self.mode = mode
        self.beta = float(beta)
        self.eps = float(eps)
        self.param = param
        self.grad = cla.zeros_like(param)
        self.state = state if state is not None else cla.zeros_like(param)

    def step(self, touched, lr, clear_touched):
        n = self.param.shape[0]
        D = 1 if self.param.ndim == 1 else self.param.shape[1]
        k = self.device.program("optim.cl", {"OPT_MODE": MODES[self.mode]}).kernel("update_rows")
        launch(self.device, k, n,
               (np.int32(n), np.int32(D), self.param.data, self.grad.data, self.state.data,
                touched.data, np.float32(lr), np.float32(self.beta), np.float32(self.eps),
                np.int32(bool(clear_touched))))
