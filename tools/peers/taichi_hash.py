"""Taichi-CPU peer of clrf's multiresolution hash encoding (cl/hash.cl): forward and backward.

The same encoding, written the way a Taichi user would: one (point, level) pair per iteration
of the outermost parallel loop (``ti.ndrange``); the cell, its 8 table rows (dense indexing
where (N+1)^3 <= T, else the xor of the coordinates times 1, 2654435761, 805459861 mod T in
uint32) and the trilinear weights as in the kernel; the backward adds each corner's gradient
with Taichi's atomic ``+=``. Points are clamped to the box like clrf. The gradient table is
zeroed inside the timed backward (clrf's training step zeroes it too). Arrays are numpy
buffers passed as ``ti.types.ndarray``.
"""

import os

import numpy as np
import taichi as ti

from .common import init_taichi

PRIME_Y = 2654435761
PRIME_Z = 805459861

_KERNELS = {}


def _kernels(F):
    if F in _KERNELS:
        return _KERNELS[F]
    nd1i = ti.types.ndarray(dtype=ti.i32, ndim=1)
    nd2f = ti.types.ndarray(dtype=ti.f32, ndim=2)
    nd3f = ti.types.ndarray(dtype=ti.f32, ndim=3)

    @ti.func
    def cell(x: nd2f, i, lo, inv, N, T):
        u = ti.Vector([0.0, 0.0, 0.0])
        for a in ti.static(range(3)):
            v = (x[i, a] - lo[a]) * inv[a]
            u[a] = ti.min(ti.max(v, 0.0), 1.0)
        p = u * ti.cast(N, ti.f32)
        fl = ti.min(ti.floor(p), ti.cast(N - 1, ti.f32))
        w = p - fl
        iv = ti.cast(fl, ti.u32)
        R = ti.cast(N + 1, ti.u32)
        dense = ti.cast(R, ti.u64) * R * R <= ti.cast(T, ti.u64)
        rows = ti.Vector([0] * 8, dt=ti.i32)
        ws = ti.Vector([0.0] * 8, dt=ti.f32)
        for k in ti.static(range(8)):
            cx, cy, cz = k & 1, (k >> 1) & 1, (k >> 2) & 1
            vx, vy, vz = iv[0] + ti.u32(cx), iv[1] + ti.u32(cy), iv[2] + ti.u32(cz)
            r = ti.u32(0)
            if dense:
                r = vx + R * (vy + R * vz)
            else:
                r = (vx ^ (vy * ti.u32(PRIME_Y)) ^ (vz * ti.u32(PRIME_Z))) & ti.u32(T - 1)
            rows[k] = ti.cast(r, ti.i32)
            ws[k] = (w[0] if cx else 1.0 - w[0]) * (w[1] if cy else 1.0 - w[1]) \
                * (w[2] if cz else 1.0 - w[2])
        return rows, ws

    @ti.kernel
    def forward(x: nd2f, lo: ti.types.vector(3, ti.f32), inv: ti.types.vector(3, ti.f32),
                res: nd1i, table: nd3f, out: nd2f):
        L, T = table.shape[0], table.shape[1]
        for i, l in ti.ndrange(x.shape[0], L):
            rows, ws = cell(x, i, lo, inv, res[l], T)
            for f in ti.static(range(F)):
                acc = 0.0
                for k in ti.static(range(8)):
                    acc += ws[k] * table[l, rows[k], f]
                out[i, l * F + f] = acc

    @ti.kernel
    def zero(g: nd3f):
        for a, b, c in g:
            g[a, b, c] = 0.0

    @ti.kernel
    def backward(x: nd2f, lo: ti.types.vector(3, ti.f32), inv: ti.types.vector(3, ti.f32),
                 res: nd1i, genc: nd2f, grad: nd3f):
        L, T = grad.shape[0], grad.shape[1]
        for i, l in ti.ndrange(x.shape[0], L):
            rows, ws = cell(x, i, lo, inv, res[l], T)
            for f in ti.static(range(F)):
                g = genc[i, l * F + f]
                for k in ti.static(range(8)):
                    grad[l, rows[k], f] += ws[k] * g

    _KERNELS[F] = (forward, zero, backward)
    return _KERNELS[F]


class TaichiHash:
    """points x [n, 3], table [L, T, F], res [L] (int), box lo [3] / inv_ext [3] (float32)."""

    def __init__(self, x, table, res, lo, inv_ext, genc):
        init_taichi()
        self.x = np.ascontiguousarray(x, np.float32)
        self.table = np.ascontiguousarray(table, np.float32)
        self.res = np.ascontiguousarray(res, np.int32)
        self.lo = ti.Vector([float(v) for v in np.asarray(lo, np.float32)])
        self.inv = ti.Vector([float(v) for v in np.asarray(inv_ext, np.float32)])
        self.genc = np.ascontiguousarray(genc, np.float32)
        L, _, F = self.table.shape
        self.out = np.zeros((self.x.shape[0], L * F), np.float32)
        self.grad = np.zeros_like(self.table)
        self.fwd, self.zero, self.bwd = _kernels(F)

    def forward(self):
        self.fwd(self.x, self.lo, self.inv, self.res, self.table, self.out)
        ti.sync()
        return self.out

    def forward_backward(self):
        self.forward()
        self.zero(self.grad)
        self.bwd(self.x, self.lo, self.inv, self.res, self.genc, self.grad)
        ti.sync()
        return self.grad

    def describe(self):
        return f"taichi {'.'.join(map(str, ti.__version__))} (CPU, {os.cpu_count()} threads)"
