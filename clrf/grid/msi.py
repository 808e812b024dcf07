"""Multi-sphere-image (MSI) background for unbounded scenes: host side of cl/background.cl.

L spheres around ``center``, uniform in inverse radius from the foreground's bounding sphere
(radius ``r_inner``) outwards: 1/r_l = (1 - (l + 0.5)/L) / r_inner, l = 0 .. L-1 (the outermost
at 2 L r_inner). Each is an equirectangular image, H rows of latitude x W = 2H columns of
longitude (z up), of raw density and raw colour. The field is trilinear in (longitude,
latitude, inverse radius); a ray is sampled once between each pair of consecutive outgoing
sphere crossings (midpoint quadrature, L - 1 samples) beyond ``t_start`` (the far end of the
foreground), then composited front to back:

    bg_rgb = sum_k T_k alpha_k max(c_k, 0) + T_msi * background,   bg_T = T_msi

with sigma_k = max(density(x_k), 0), c_k = color(x_k) + 0.5, alpha_k = 1 - exp(-sigma_k
delta_k). The final pixel is C_fg + T_fg * bg_rgb, so the backward pass takes
dL/d bg_rgb = T_fg * dL/d pixel. The equations and index formulas are in cl/background.cl.

>>> bgm = MSIBackground(dev, layers=8, height=16, r_inner=1.5, background=(1, 1, 1))
>>> rgb, T = bgm.forward(np.zeros((1, 3)), [[1.0, 0, 0]])   # density 0: only the constant
>>> rgb, T
(array([[1., 1., 1.]], dtype=float32), array([1.], dtype=float32))
"""
from __future__ import annotations

import numpy as np

from ..runtime.programs import device_empty, device_zeros, download, float4, launch, upload

PER_RAY_LOCAL_SIZE = 16  # one ray per work-item with a loop over its L - 1 samples


def _f32(device, a, shape):
    a = np.ascontiguousarray(np.asarray(a, np.float32).reshape(shape))
    return upload(device.queue, a)


def _float4(v):
    v = [float(x) for x in np.broadcast_to(np.asarray(v, np.float64), (3,))]
    return float4(v[0], v[1], v[2], 0.0)


def program(device, layers: int, height: int):
    """cl/background.cl for ``layers`` spheres of ``height`` rows on ``device``."""
    return device.program("background.cl", {"BG_LAYERS": layers, "BG_H": height})


class MSIBackground:
    """The background's parameters on the device and its forward/backward launches.

    Parameters (device arrays, float32, C order): ``density`` [L, H, W], ``color``
    [L, H, W, 3], W = 2H. ``init_density``/``init_color`` fill them (raw values: colour 0 is
    grey 0.5).
    """

    def __init__(self, device, layers: int, height: int, r_inner: float,
                 center=(0.0, 0.0, 0.0), background=(0.0, 0.0, 0.0),
                 init_density: float = 0.0, init_color: float = 0.0):
        layers, height = int(layers), int(height)
        if layers < 2:
            raise ValueError(f"background layers = {layers}: need >= 2 (samples lie between "
                             "consecutive spheres)")
        if height < 1:
            raise ValueError(f"background height = {height}: need >= 1")
        if not (np.isfinite(r_inner) and r_inner > 0):
            raise ValueError(f"background r_inner = {r_inner}: need a finite radius > 0")
        self.device = device
        self.layers, self.height, self.width = layers, height, 2 * height
        # rounded to float32 here: the values the kernels receive, so a float64 reference given
        # these attributes sees the same geometry (a ray along a pole stays on it)
        self.r_inner = float(np.float32(r_inner))
        self.center = np.asarray(center, np.float32).astype(np.float64).reshape(3)
        self.background = np.asarray(background, np.float64).reshape(3)
        shape = self.shape
        self.density = device_empty(device.queue, shape, np.float32).fill(np.float32(init_density))
        self.color = device_empty(device.queue, shape + (3,), np.float32).fill(
            np.float32(init_color))

    @property
    def shape(self):
        """(L, H, W) of the density image stack."""
        return (self.layers, self.height, self.width)

    def _program(self):
        return program(self.device, self.layers, self.height)

    def _common_args(self, origins_d, dirs_d, t_start_d):
        return (origins_d.data, dirs_d.data, t_start_d.data, self.density.data, self.color.data,
                _float4(self.center), np.float32(self.r_inner), _float4(self.background))

    def forward_device(self, origins_d, dirs_d, t_start_d, out=None):
        """(bg_rgb [n, 3], bg_T [n]) device arrays for origins/dirs [n, 3] and t_start [n]
        (device float32; t_start = where the foreground ends along the unit direction, or 0).
        out: optional (bg_rgb, bg_T) float32 device arrays to write into (reused per batch)."""
        n = int(origins_d.shape[0])
        if out is not None:
            rgb, T = out
        else:
            rgb = device_empty(self.device.queue, (n, 3), np.float32)
            T = device_empty(self.device.queue, (n,), np.float32)
        launch(self.device, self._program().kernel("bg_forward"), n,
               (np.int32(n),) + self._common_args(origins_d, dirs_d, t_start_d)
               + (rgb.data, T.data), PER_RAY_LOCAL_SIZE)
        return rgb, T

    def backward_device(self, origins_d, dirs_d, t_start_d, grad_bg_rgb_d, grad_density_d,
                        grad_color_d):
        """Add dL/d density [L, H, W] and dL/d color [L, H, W, 3] into the given device arrays
        for dL/d bg_rgb = grad_bg_rgb_d [n, 3] (not zeroed here: gradients accumulate)."""
        n = int(origins_d.shape[0])
        launch(self.device, self._program().kernel("bg_backward"), n,
               (np.int32(n),) + self._common_args(origins_d, dirs_d, t_start_d)
               + (grad_bg_rgb_d.data, grad_density_d.data, grad_color_d.data),
               PER_RAY_LOCAL_SIZE)

    def _rays(self, origins, dirs, t_start):
        o = np.asarray(origins, np.float32).reshape(-1, 3)
        n = o.shape[0]
        t = np.zeros(n, np.float32) if t_start is None else t_start
        return (_f32(self.device, o, (n, 3)), _f32(self.device, dirs, (n, 3)),
                _f32(self.device, t, (n,)))

    def forward(self, origins, dirs, t_start=None):
        """numpy (bg_rgb [n, 3], bg_T [n]); t_start [n] defaults to 0."""
        rgb, T = self.forward_device(*self._rays(origins, dirs, t_start))
        return rgb.get(), T.get()

    def backward(self, origins, dirs, grad_bg_rgb, t_start=None):
        """numpy (dL/d density [L, H, W], dL/d color [L, H, W, 3])."""
        o, d, t = self._rays(origins, dirs, t_start)
        gd = device_zeros(self.device.queue, self.shape, np.float32)
        gc = device_zeros(self.device.queue, self.shape + (3,), np.float32)
        self.backward_device(o, d, t, _f32(self.device, grad_bg_rgb, (o.shape[0], 3)), gd, gc)
        return gd.get(), gc.get()

    def set_params(self, density=None, color=None):
        """Copy numpy parameters (shapes as the attributes) to the device."""
        if density is not None:
            self.density.set(_checked(density, self.shape, "bg_density"))
        if color is not None:
            self.color.set(_checked(color, self.shape + (3,), "bg_color"))

    def state_dict(self) -> dict:
        """numpy arrays for a checkpoint (keys prefixed bg_)."""
        return {"bg_density": download(self.density), "bg_color": download(self.color),
                "bg_center": self.center.copy(), "bg_r_inner": np.float64(self.r_inner),
                "bg_background": self.background.copy()}

    def load_state_dict(self, state: dict):
        """Restore from state_dict()'s output; shapes must match this model's (L, H, W)."""
        for key in ("bg_density", "bg_color", "bg_center", "bg_r_inner", "bg_background"):
            if key not in state:
                raise ValueError(f"checkpoint has no field {key!r}: it was not saved with an "
                                 "MSI background")
        self.set_params(state["bg_density"], state["bg_color"])
        self.center = np.asarray(state["bg_center"], np.float32).astype(np.float64).reshape(3)
        self.r_inner = float(np.float32(state["bg_r_inner"]))
        self.background = np.asarray(state["bg_background"], np.float64).reshape(3)

    @classmethod
    def from_state_dict(cls, device, state: dict) -> "MSIBackground":
        """A new model with the shapes and values of state_dict()'s output."""
        L, H, _ = np.shape(state["bg_density"])
        m = cls(device, L, H, float(state["bg_r_inner"]))
        m.load_state_dict(state)
        return m


def _checked(a, shape, name):
    a = np.asarray(a)
    if a.shape != tuple(shape):
        raise ValueError(f"{name} has shape {a.shape}, expected {tuple(shape)} (layers, height, "
                         "2*height[, 3])")
    return np.ascontiguousarray(a, np.float32)
