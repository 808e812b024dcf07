"""Taichi-CPU peer of clrf's Gaussian-splatting tile rasteriser (cl/splat_raster.cl): forward
and backward.

The same compositing, written the way a Taichi user would: one pixel per iteration of the
outermost (parallel) loop over ``ti.ndrange(height, width)``; each pixel walks its tile's
front-to-back list with the kernel's equations (cl/splat.h, cl/splat_raster.cl header): pixel
centre (px + 0.5, py + 0.5), power = -0.5 (A dx^2 + C dy^2) - B dx dy with d = mean - centre,
alpha = min(ALPHA_MAX, o exp(power)), entries with power > 0 or alpha < ALPHA_MIN skipped, the
pixel stops before the entry that would bring T below T_MIN, the background composited with the
final T; outputs rgb [H, W, 3], T [H, W] and n_contrib [H, W] as clrf's. The backward walks each
pixel's list back to front from its n_contrib, recovers T_k = T_{k+1} / (1 - alpha_k) from the
final T, keeps the colour behind the entry, and adds the per-(pixel, Gaussian) gradient terms
into dL/d(xy, conic, opacity, colour) with Taichi's atomic ``+=`` (no gradient through a
clamped alpha). The differences from clrf's kernel are the ones a Taichi user would not write:
no work-group per tile, no local-memory batches of the list, no tile-wide early exit; every
pixel reads the Gaussians it needs from the global arrays.

What it consumes: the projected 2D Gaussians (screen means xy [n, 2], conics [n, 3] (A, B, C),
opacities [n], colours [n, 3]) and the per-tile sorted lists (ids [P], ranges [ntiles, 2]) that
clrf's ``SplatRasterizer.project`` and ``.bin`` produced, as numpy arrays (``from_clrf``). The
projection (3D covariance, EWA splatting, SH colour) and the binning are clrf's: the timed
comparison in tools/bench.py (``splat.raster.taichi`` beside ``splat.raster.clrf``) is the
rasteriser's forward + backward on identical inputs. (The issue asked for gsplat's PyTorch
projection, ``gsplat.cuda._torch_impl``, for the peer's front half; gsplat is not installed
here, and its projection is not what the comparison times.)

The gradient buffers are zeroed inside the timed backward (clrf's rasterize_backward allocates
zeroed ones at every call too). Arrays are numpy buffers passed as ``ti.types.ndarray``;
``fast_math`` is Taichi's default, as in the other peers (the results agree with clrf's within
the tolerances of tools/bench/cases.py PEER_SPLAT_*). Written for the measurement; no code from
other projects.
"""

import os

import numpy as np
import taichi as ti

from clrf.splat.raster import ALPHA_MAX, ALPHA_MIN, GRAD2D_NAMES, T_MIN, TILE

from .common import init_taichi

_KERNELS = {}


def _kernels():
    """(forward, backward), defined once (after ti.init)."""
    if _KERNELS:
        return _KERNELS["forward"], _KERNELS["backward"]
    nd1i = ti.types.ndarray(dtype=ti.i32, ndim=1)
    nd2i = ti.types.ndarray(dtype=ti.i32, ndim=2)
    nd1f = ti.types.ndarray(dtype=ti.f32, ndim=1)
    nd2f = ti.types.ndarray(dtype=ti.f32, ndim=2)
    nd3f = ti.types.ndarray(dtype=ti.f32, ndim=3)
    vec3 = ti.types.vector(3, ti.f32)

    @ti.func
    def alpha_at(xy: ti.template(), conic: ti.template(), opacity: ti.template(), g, cx, cy):
        """Gaussian g at the pixel centre (cx, cy): (alpha, 0 where skipped; o G before the
        clamp; G = exp(power); d = mean - centre)."""
        dx = xy[g, 0] - cx
        dy = xy[g, 1] - cy
        power = -0.5 * (conic[g, 0] * dx * dx + conic[g, 2] * dy * dy) - conic[g, 1] * dx * dy
        G = ti.exp(power)
        raw = opacity[g] * G
        alpha = ti.min(ALPHA_MAX, raw)
        if power > 0.0 or alpha < ALPHA_MIN:
            alpha = 0.0
        return alpha, raw, G, dx, dy

    @ti.func
    def rgb_of(color: ti.template(), g):
        return ti.Vector([color[g, 0], color[g, 1], color[g, 2]])

    @ti.kernel
    def forward(ranges: nd2i, ids: nd1i, xy: nd2f, conic: nd2f, opacity: nd1f, color: nd2f,
                bg: vec3, tile: ti.i32, rgb: nd3f, T_out: nd2f, n_out: nd2i):
        H, W = T_out.shape[0], T_out.shape[1]
        ntx = (W + tile - 1) // tile
        for py, px in ti.ndrange(H, W):
            t = (py // tile) * ntx + px // tile
            start, end = ranges[t, 0], ranges[t, 1]
            cx = ti.cast(px, ti.f32) + 0.5
            cy = ti.cast(py, ti.f32) + 0.5
            T = 1.0
            C = ti.Vector([0.0, 0.0, 0.0])
            last = 0
            for k in range(start, end):
                g = ids[k]
                alpha, raw, G, dx, dy = alpha_at(xy, conic, opacity, g, cx, cy)
                if alpha == 0.0:
                    continue
                nT = T * (1.0 - alpha)
                if nT < T_MIN:
                    break
                C += rgb_of(color, g) * (alpha * T)
                T = nT
                last = k - start + 1
            for ch in ti.static(range(3)):
                rgb[py, px, ch] = C[ch] + T * bg[ch]
            T_out[py, px] = T
            n_out[py, px] = last

    @ti.kernel
    def backward(ranges: nd2i, ids: nd1i, xy: nd2f, conic: nd2f, opacity: nd1f, color: nd2f,
                 bg: vec3, tile: ti.i32, T_out: nd2f, n_out: nd2i, grad_rgb: nd3f, g_xy: nd2f,
                 g_conic: nd2f, g_opacity: nd1f, g_color: nd2f):
        H, W = T_out.shape[0], T_out.shape[1]
        ntx = (W + tile - 1) // tile
        for py, px in ti.ndrange(H, W):
            t = (py // tile) * ntx + px // tile
            start = ranges[t, 0]
            n = n_out[py, px]
            cx = ti.cast(px, ti.f32) + 0.5
            cy = ti.cast(py, ti.f32) + 0.5
            T = T_out[py, px]
            gv = ti.Vector([grad_rgb[py, px, 0], grad_rgb[py, px, 1], grad_rgb[py, px, 2]])
            S = ti.Vector([bg[0], bg[1], bg[2]])   # the colour behind the current entry
            for j in range(n):
                g = ids[start + n - 1 - j]
                alpha, raw, G, dx, dy = alpha_at(xy, conic, opacity, g, cx, cy)
                if alpha == 0.0:
                    continue
                c = rgb_of(color, g)
                T = T / (1.0 - alpha)
                dc = c - S
                dalpha = T * (gv[0] * dc[0] + gv[1] * dc[1] + gv[2] * dc[2])
                S = alpha * c + (1.0 - alpha) * S
                w = T * alpha
                for ch in ti.static(range(3)):
                    g_color[g, ch] += w * gv[ch]
                if raw < ALPHA_MAX:   # else clamped: alpha does not depend on o, xy, conic
                    g_opacity[g] += G * dalpha
                    dpow = raw * dalpha
                    A, B, Cc = conic[g, 0], conic[g, 1], conic[g, 2]
                    g_xy[g, 0] += -dpow * (A * dx + B * dy)
                    g_xy[g, 1] += -dpow * (B * dx + Cc * dy)
                    g_conic[g, 0] += -0.5 * dpow * dx * dx
                    g_conic[g, 1] += -dpow * dx * dy
                    g_conic[g, 2] += -0.5 * dpow * dy * dy

    _KERNELS.update(forward=forward, backward=backward)
    return forward, backward


def _f32(name, a, shape):
    a = np.ascontiguousarray(a, np.float32)
    if a.shape != shape:
        raise ValueError(f"{name}: expected shape {shape}, got {a.shape}")
    return a


class TaichiSplat:
    """The rasteriser peer on fixed inputs (numpy): projected splats xy [n, 2], conic [n, 3],
    opacity [n], color [n, 3]; clrf's binning ids [P] (per tile, front to back) and ranges
    [ntiles, 2] ([start, end) into ids, tiles row-major, ntx = ceil(width / tile)); the image
    size, the tile side, the background [3] and dL/drgb ``grad_rgb`` [H, W, 3] (for the
    backward; zeros if None)."""

    def __init__(self, xy, conic, opacity, color, ids, ranges, width, height, tile=TILE,
                 background=(0.0, 0.0, 0.0), grad_rgb=None):
        init_taichi()
        self.width, self.height, self.tile = int(width), int(height), int(tile)
        ntx, nty = -(-self.width // self.tile), -(-self.height // self.tile)
        n = np.shape(xy)[0]
        self.xy = _f32("xy", xy, (n, 2))
        self.conic = _f32("conic", conic, (n, 3))
        self.opacity = _f32("opacity", opacity, (n,))
        self.color = _f32("color", color, (n, 3))
        self.ranges = np.ascontiguousarray(ranges, np.int32)
        if self.ranges.shape != (ntx * nty, 2):
            raise ValueError(f"ranges: expected shape {(ntx * nty, 2)}, got {self.ranges.shape}")
        ids = np.ascontiguousarray(ids, np.int32)
        # an empty list would be a zero-size ndarray: one unread entry instead (ranges are [0, 0))
        self.ids = ids if ids.size else np.zeros(1, np.int32)
        self.n, self.n_pairs = n, int(ids.size)
        self.bg = ti.Vector([float(v) for v in np.asarray(background, np.float32)])
        H, W = self.height, self.width
        self.grad_rgb = (np.zeros((H, W, 3), np.float32) if grad_rgb is None
                         else _f32("grad_rgb", grad_rgb, (H, W, 3)))
        self.rgb = np.zeros((H, W, 3), np.float32)
        self.T = np.ones((H, W), np.float32)
        self.n_contrib = np.zeros((H, W), np.int32)
        # one slot more than n: Taichi refuses zero-size arrays, and row n is never touched
        m = max(n, 1)
        self.grads = {"xy": np.zeros((m, 2), np.float32), "conic": np.zeros((m, 3), np.float32),
                      "opacity": np.zeros(m, np.float32), "color": np.zeros((m, 3), np.float32)}
        self.fwd, self.bwd = _kernels()

    @classmethod
    def from_clrf(cls, proj, bins, camera, background=(0.0, 0.0, 0.0), grad_rgb=None,
                  tile=TILE):
        """The peer on clrf's projection (clrf.splat.Projected) and binning (Binned) of
        ``camera`` (SplatCamera), read back from the device."""
        ids = bins.ids.get() if bins.n_pairs else np.zeros(0, np.int32)
        return cls(proj.xy.get(), proj.conic.get(), proj.opacity.get(), proj.color.get(), ids,
                   bins.ranges.get(), camera.width, camera.height, tile, background, grad_rgb)

    def _splats(self):
        return (self.ranges, self.ids, self.xy, self.conic, self.opacity, self.color, self.bg,
                self.tile)

    def forward(self):
        """dict(rgb [H, W, 3], T [H, W], n_contrib [H, W]) (the peer's own buffers)."""
        self.fwd(*self._splats(), self.rgb, self.T, self.n_contrib)
        ti.sync()
        return {"rgb": self.rgb, "T": self.T, "n_contrib": self.n_contrib}

    def backward(self):
        """dL/d(xy, conic, opacity, color) (GRAD2D_NAMES, [n, ...]) for ``grad_rgb``, from the
        last forward's T and n_contrib; the buffers are zeroed first."""
        for g in self.grads.values():
            g.fill(0.0)
        gr = self.grads
        self.bwd(*self._splats(), self.T, self.n_contrib, self.grad_rgb, gr["xy"], gr["conic"],
                 gr["opacity"], gr["color"])
        ti.sync()
        return {k: gr[k][: self.n] for k in GRAD2D_NAMES}

    def forward_backward(self):
        """The forward, then the backward (what the benchmark times): the backward's dict."""
        self.forward()
        return self.backward()

    def describe(self):
        return f"taichi {'.'.join(map(str, ti.__version__))} CPU, {os.cpu_count()} threads"
