"""Taichi-CPU peer of clrf's grid render: forward and fused forward + backward (MSE).

The same algorithm as cl/grid_render.cl, written the way a Taichi user would: one ray per
iteration of the outermost (parallel) loop; per sample the 8 corner rows are found through the
links and interpolated with ``ti.static`` loops over the SH coefficients; empty cells are
skipped to their exit as clrf does; the fused backward re-marches the ray with a remaining-
radiance accumulator and adds each sample's corner gradients with Taichi's atomic ``+=``
(one atomic per corner value per sample: no merging of consecutive samples in a cell).
The per-ray set-up (box entry, step count, SH basis) is precomputed once outside the timed
calls (O(rays), < 1 % of the work). Arrays are numpy buffers passed as ``ti.types.ndarray``.
"""

import os

import numpy as np
import taichi as ti

from .common import COLOR_OFFSET, T_STOP, init_taichi, ray_setup

_KERNELS = {}


def _kernels(C):
    """Forward and fused kernels specialised for C = 3 (d+1)^2 coefficients per row."""
    if C in _KERNELS:
        return _KERNELS[C]
    B = C // 3
    nd1f = ti.types.ndarray(dtype=ti.f32, ndim=1)
    nd2f = ti.types.ndarray(dtype=ti.f32, ndim=2)
    nd1i = ti.types.ndarray(dtype=ti.i32, ndim=1)
    nd3i = ti.types.ndarray(dtype=ti.i32, ndim=3)
    big = 3.0e38

    @ti.func
    def axis(p, r):
        u = ti.min(ti.max(p - 0.5, 0.0), ti.cast(r - 1, ti.f32))
        i = ti.min(ti.cast(u, ti.i32), ti.max(r - 2, 0))
        return i, ti.min(i + 1, r - 1), u - ti.cast(i, ti.f32)

    @ti.func
    def corners(links: ti.template(), p):
        R = ti.Vector([links.shape[0], links.shape[1], links.shape[2]])
        x0, x1, fx = axis(p[0], R[0])
        y0, y1, fy = axis(p[1], R[1])
        z0, z1, fz = axis(p[2], R[2])
        rows = ti.Vector([0] * 8, dt=ti.i32)
        ws = ti.Vector([0.0] * 8, dt=ti.f32)
        for c in ti.static(range(8)):
            cx, cy, cz = (c >> 2) & 1, (c >> 1) & 1, c & 1
            rows[c] = links[x0 + cx * (x1 - x0), y0 + cy * (y1 - y0), z0 + cz * (z1 - z0)]
            ws[c] = ((1.0 - fx) + cx * (2.0 * fx - 1.0)) * ((1.0 - fy) + cy * (2.0 * fy - 1.0)) \
                * ((1.0 - fz) + cz * (2.0 * fz - 1.0))
        return rows, ws, ti.Vector([x0, y0, z0]), R

    @ti.func
    def next_k(p0, dg, dt, k, nsteps, lo, R):
        """The segment to evaluate after segment k found an empty cell (clrf's skip_empty)."""
        s = big
        for a in ti.static(range(3)):
            blo = -big if lo[a] == 0 else ti.cast(lo[a], ti.f32) + 0.5
            bhi = big if lo[a] >= R[a] - 2 else ti.cast(lo[a], ti.f32) + 1.5
            if dg[a] > 0.0:
                s = ti.min(s, (bhi - p0[a]) / dg[a])
            elif dg[a] < 0.0:
                s = ti.min(s, (blo - p0[a]) / dg[a])
        j = ti.min(ti.ceil(s / dt - 0.5) - 1.0, ti.cast(nsteps, ti.f32))
        return ti.max(k + 1, ti.cast(j, ti.i32))

    @ti.func
    def sample(links: ti.template(), density: ti.template(), sh: ti.template(), p, Yv):
        rows, ws, lo, R = corners(links, p)
        any_ = 0
        sig = 0.0
        co = ti.Vector([0.0] * C, dt=ti.f32)
        for c in ti.static(range(8)):
            if rows[c] >= 0:
                any_ = 1
                sig += ws[c] * density[rows[c]]
                for j in ti.static(range(C)):
                    co[j] += ws[c] * sh[rows[c], j]
        pre = ti.Vector([COLOR_OFFSET] * 3, dt=ti.f32)
        for ch in ti.static(range(3)):
            for b in ti.static(range(B)):
                pre[ch] += co[ch * B + b] * Yv[b]
        return any_, sig, pre, rows, ws, lo, R

    @ti.func
    def load_ray(i, p0a: ti.template(), dga: ti.template(), Y: ti.template()):
        p0 = ti.Vector([p0a[i, 0], p0a[i, 1], p0a[i, 2]])
        dg = ti.Vector([dga[i, 0], dga[i, 1], dga[i, 2]])
        Yv = ti.Vector([0.0] * B, dt=ti.f32)
        for b in ti.static(range(B)):
            Yv[b] = Y[i, b]
        return p0, dg, Yv

    @ti.func
    def march_fwd(i, p0, dg, Yv, dt, ln, nsteps, links: ti.template(), density: ti.template(),
                  sh: ti.template()):
        rgb = ti.Vector([0.0, 0.0, 0.0])
        logT = 0.0
        k = 0
        while k < nsteps:
            s0 = ti.cast(k, ti.f32) * dt
            s1 = ti.min(ti.cast(k + 1, ti.f32) * dt, ln)
            mid = 0.5 * (s0 + s1)
            any_, sig, pre, rows, ws, lo, R = sample(links, density, sh, p0 + mid * dg, Yv)
            if any_ == 0:
                k = next_k(p0, dg, dt, k, nsteps, lo, R)
                continue
            k += 1
            if sig > 0.0:
                tau = sig * (s1 - s0)
                w = ti.exp(logT) * (1.0 - ti.exp(-tau))
                rgb += w * ti.max(pre, 0.0)
                logT -= tau
                if ti.exp(logT) < T_STOP:
                    break
        return rgb, logT

    @ti.kernel
    def forward(p0a: nd2f, dga: nd2f, dta: nd1f, lna: nd1f, nst: nd1i, Y: nd2f, links: nd3i,
                density: nd1f, sh: nd2f, out: nd2f):
        for i in range(nst.shape[0]):
            p0, dg, Yv = load_ray(i, p0a, dga, Y)
            rgb, logT = march_fwd(i, p0, dg, Yv, dta[i], lna[i], nst[i], links, density, sh)
            T = ti.exp(logT)
            for ch in ti.static(range(3)):
                out[i, ch] = rgb[ch] + T   # white background
    
    @ti.kernel
    def fused(p0a: nd2f, dga: nd2f, dta: nd1f, lna: nd1f, nst: nd1i, Y: nd2f, links: nd3i,
              density: nd1f, sh: nd2f, target: nd2f, scale: ti.f32, gd: nd1f, gs: nd2f):
        for i in range(nst.shape[0]):
            p0, dg, Yv = load_ray(i, p0a, dga, Y)
            dt, ln, nsteps = dta[i], lna[i], nst[i]
            rgb, logT_end = march_fwd(i, p0, dg, Yv, dt, ln, nsteps, links, density, sh)
            rgb += ti.exp(logT_end)
            g = ti.Vector([0.0, 0.0, 0.0])
            for ch in ti.static(range(3)):
                g[ch] = 2.0 * scale * (rgb[ch] - target[i, ch])
            total = g.dot(rgb)
            prefix = 0.0
            logT = 0.0
            k = 0
            while k < nsteps:
                s0 = ti.cast(k, ti.f32) * dt
                s1 = ti.min(ti.cast(k + 1, ti.f32) * dt, ln)
                mid = 0.5 * (s0 + s1)
                delta = s1 - s0
                any_, sig, pre, rows, ws, lo, R = sample(links, density, sh, p0 + mid * dg, Yv)
                if any_ == 0:
                    k = next_k(p0, dg, dt, k, nsteps, lo, R)
                    continue
                k += 1
                if sig > 0.0:
                    tau = sig * delta
                    w = ti.exp(logT) * (1.0 - ti.exp(-tau))
                    col = ti.max(pre, 0.0)
                    gc = g.dot(col)
                    prefix += w * gc
                    logT -= tau
                    Tn = ti.exp(logT)
                    dsig = delta * (Tn * gc - (total - prefix))
                    for c in ti.static(range(8)):
                        if rows[c] >= 0:
                            gd[rows[c]] += ws[c] * dsig
                            for ch in ti.static(range(3)):
                                if pre[ch] > 0.0:
                                    for b in ti.static(range(B)):
                                        gs[rows[c], ch * B + b] += ws[c] * w * g[ch] * Yv[b]
                    if Tn < T_STOP:
                        break

    _KERNELS[C] = (forward, fused)
    return _KERNELS[C]


class TaichiGrid:
    def __init__(self, links, density, sh, origins, dirs, params, target, bbox=None):
        from bench_scenes import BBOX
        init_taichi()
        self.links = np.ascontiguousarray(links, np.int32)
        self.density = np.ascontiguousarray(density, np.float32)
        self.sh = np.ascontiguousarray(sh, np.float32)
        self.s = ray_setup(origins, dirs, links.shape, BBOX if bbox is None else bbox,
                           params["step"], params["degree"])
        self.target = np.ascontiguousarray(target, np.float32)
        self.n = origins.shape[0]
        self.fwd, self.fused_k = _kernels(self.sh.shape[1])
        self.out = np.zeros((self.n, 3), np.float32)
        self.gd = np.zeros_like(self.density)
        self.gs = np.zeros_like(self.sh)
        self._zero = True

    def describe(self):
        return f"taichi {'.'.join(map(str, ti.__version__))} CPU, {os.cpu_count()} threads"

    def _args(self):
        s = self.s
        return (s["p0"], s["dg"], s["dt"], s["len"], s["nsteps"], s["Y"], self.links,
                self.density, self.sh)

    def forward(self):
        self.fwd(*self._args(), self.out)
        return self.out

    def forward_backward(self):
        """Adds the gradient into the same buffers at every call (like clrf's timed loop:
        no dense zero-fill per step); the first call starts from zeros."""
        self.fused_k(*self._args(), self.target, 1.0 / self.n, self.gd, self.gs)
        return self.gd, self.gs
