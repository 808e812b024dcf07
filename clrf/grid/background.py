"""The background model of a GridModel: an MSIBackground (clrf/grid/msi.py) behind the grid,
its optimisers and per-batch buffers.

Geometry. The MSI is centred on the grid box's centre and its inner radius ``r_inner`` is the
box's half-diagonal, the sphere through the box's corners, so every MSI sample lies outside the
foreground grid. Each ray's background starts where it leaves the grid box (``ray_exit``,
t_start; 0 for rays that miss the box). For a normalised Mip-NeRF 360 scene (clrf/data/llff.py:
farthest camera at distance 1, box [-1, 1]^3) that is r_inner = sqrt(3).

Per batch of rays (origins, dirs, device [B, 3]):

    t_start = ray_exit(grid)                       (cl/grid_render.cl)
    bg_rgb  = MSI forward from t_start             (cl/background.cl; includes T_msi * const)
    pixel   = C_fg + T_fg * bg_rgb                 (grid backward with BG_PER_RAY, fused MSE)
    dL/d bg_rgb = T_fg * dL/dpixel                 (written by the grid backward)
    MSI backward, then RMSProp on bg density and colour.

Optimiser: the grid's family (clrf/runtime/optim.py, RMSProp unless grid.optimizer = sgd) over the MSI
texels as rows (density [L H W], colour [L H W, 3]). Every row is flagged as touched, and
update_rows leaves an entry whose gradient is exactly 0 unchanged (parameter and state), so
what moves is exactly the texels this batch's rays reached: svox2's sparse background update,
without a separate touched pass in the background kernel. The flags are never cleared.
"""
from __future__ import annotations

import numpy as np

from .msi import MSIBackground
from ..runtime.optim import Optimizer, expon_lr
from .render import ray_exit_device
from ..runtime.programs import device_empty, download, upload


def msi_geometry(bbox):
    """(center [3], r_inner) of the MSI around the grid box bbox [[lo], [hi]]: the box centre
    and its half-diagonal (the sphere through the box's corners)."""
    bbox = np.asarray(bbox, np.float64)
    return bbox.mean(0), 0.5 * float(np.linalg.norm(bbox[1] - bbox[0]))


class GridBackground:
    """MSIBackground + its two optimisers; ``msi`` is the MSIBackground itself."""

    def __init__(self, device, cfg, msi: MSIBackground, opt_state=None):
        self.device = device
        self.cfg = cfg
        self.msi = msi
        st = opt_state or {}
        self.opt_density = Optimizer(device, msi.density.reshape(-1), cfg.optimizer, cfg.rms_beta,
                                     state=st.get("density"))
        self.opt_color = Optimizer(device, msi.color.reshape(-1, 3), cfg.optimizer, cfg.rms_beta,
                                   state=st.get("color"))
        n = int(np.prod(msi.shape))
        self.all_rows = device_empty(device.queue, n, np.uint8).fill(np.uint8(1))
        self._buf = None   # per-batch (t_start, bg_rgb, bg_T, grad_bg), reused while B is fixed

    @classmethod
    def create(cls, device, cfg, bbox, background):
        center, r_inner = msi_geometry(bbox)
        msi = MSIBackground(device, cfg.background_layers, cfg.background_height, r_inner,
                            center=center, background=background,
                            init_density=cfg.background_init_density,
                            init_color=cfg.background_init_color)
        return cls(device, cfg, msi)

    def _buffers(self, n):
        if self._buf is None or self._buf[1].shape[0] != n:
            q = self.device.queue
            self._buf = tuple(device_empty(q, shape, np.float32)
                              for shape in (max(n, 1), (n, 3), max(n, 1), (n, 3)))
        return self._buf

    def forward(self, grid, origins, dirs, step, reuse=True):
        """(t_start [n], bg_rgb [n, 3]) device arrays of device rays [n, 3]: where each ray
        leaves the grid box and the MSI colour behind it (buffers reused per batch size when
        ``reuse``; fresh ones otherwise)."""
        n = int(origins.shape[0])
        if reuse:
            t_start, rgb, T, _ = self._buffers(n)
            ray_exit_device(grid, origins, dirs, step, out=t_start)
            self.msi.forward_device(origins, dirs, t_start, out=(rgb, T))
            return t_start, rgb
        t_start = ray_exit_device(grid, origins, dirs, step)
        rgb, _ = self.msi.forward_device(origins, dirs, t_start)
        return t_start, rgb

    def grad_buffer(self, n):
        """The [n, 3] buffer the grid backward writes dL/d bg_rgb into."""
        return self._buffers(n)[3]

    def backward_step(self, it, origins, dirs, t_start, grad_bg):
        """MSI backward for dL/d bg_rgb = grad_bg, then one optimiser step on its texels."""
        self.msi.backward_device(origins, dirs, t_start, grad_bg, self.opt_density.grad,
                                 self.opt_color.grad)
        lr_d, lr_c = self.learning_rates(it)
        self.opt_density.step(self.all_rows, lr_d)
        self.opt_color.step(self.all_rows, lr_c)

    def learning_rates(self, it):
        c = self.cfg
        return (expon_lr(it, c.lr_bg_density, c.lr_bg_density_final, c.lr_decay_steps),
                expon_lr(it, c.lr_bg_color, c.lr_bg_color_final, c.lr_decay_steps))

    # ---- state -------------------------------------------------------------------------
    def state_dict(self):
        """The MSI's own fields (bg_*) and its optimiser states (opt_bg_density, opt_bg_color)."""
        d = self.msi.state_dict()
        d.update(opt_bg_density=download(self.opt_density.state).reshape(self.msi.shape),
                 opt_bg_color=download(self.opt_color.state).reshape(self.msi.shape + (3,)))
        return d

    @classmethod
    def from_state_dict(cls, device, state, cfg):
        msi = MSIBackground.from_state_dict(device, state)
        if (msi.layers, msi.height) != (cfg.background_layers, cfg.background_height):
            raise ValueError(
                f"checkpoint background is {msi.layers} layers x {msi.height} rows but the "
                f"configuration asks for grid.background_layers = {cfg.background_layers}, "
                f"grid.background_height = {cfg.background_height}; resume with the run's own "
                f"configuration")
        q = device.queue
        opt = {k: upload(q, np.ascontiguousarray(state[f"opt_bg_{k}"], np.float32)
                                .reshape((-1,) if k == "density" else (-1, 3)))
               for k in ("density", "color") if f"opt_bg_{k}" in state}
        return cls(device, cfg, msi, opt)
