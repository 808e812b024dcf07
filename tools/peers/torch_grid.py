"""PyTorch-CPU peer of clrf's grid render: vectorised over rays x samples, autograd backward.

Written as a user of PyTorch would: rays are processed in chunks; each chunk's samples are laid
out [rays, max_steps] (padded), the 8 corner rows are gathered through the links, weights and
colours are tensors, transmittance is an exclusive cumulative sum in log space, and the
gradient comes from ``loss.backward()`` (the index backward scatter-adds into fresh dense
row gradients). Same conventions as cl/grid_render.cl: midpoint samples, clipped last segment,
clamp-to-edge trilinear, ReLU density, colour max(0, SH.Y + 0.5), T_STOP early termination
(a sample counts while the transmittance before it is >= T_STOP). The per-ray set-up (box
entry, step count, SH basis) is precomputed once, outside the timed calls (O(rays), < 1 %).
"""
from __future__ import annotations

import os

import numpy as np
import torch

from .common import COLOR_OFFSET, T_STOP, ray_setup

CHUNK_SAMPLES = 1 << 17   # samples (rays x padded steps) per chunk: bounds the autograd memory


class TorchGrid:
    def __init__(self, links, density, sh, origins, dirs, params, target, bbox=None):
        from bench_scenes import BBOX
        torch.set_num_threads(os.cpu_count() or 1)
        self.reso = tuple(links.shape)
        self.links = torch.from_numpy(links.reshape(-1).astype(np.int64))
        self.density = torch.from_numpy(np.array(density, np.float32)).requires_grad_(True)
        self.sh = torch.from_numpy(np.array(sh, np.float32)).requires_grad_(True)
        self.C = sh.shape[1]
        self.B = self.C // 3
        s = ray_setup(origins, dirs, self.reso, BBOX if bbox is None else bbox, params["step"],
                      params["degree"])
        self.s = {k: torch.from_numpy(v) for k, v in s.items()}
        self.target = torch.from_numpy(target)
        self.n = origins.shape[0]
        self.bg = torch.ones(3)
        # chunks of consecutive rays of about CHUNK_SAMPLES padded samples each
        ns = s["nsteps"]
        self.chunks = []
        lo = 0
        while lo < self.n:
            hi = lo + 1
            while hi < self.n and (hi + 1 - lo) * max(1, ns[lo:hi + 1].max()) <= CHUNK_SAMPLES:
                hi += 1
            self.chunks.append((lo, hi))
            lo = hi

    def describe(self):
        return f"torch {torch.__version__} CPU, {torch.get_num_threads()} threads"

    def _render(self, lo, hi):
        s = {k: v[lo:hi] for k, v in self.s.items()}
        R = hi - lo
        S = int(s["nsteps"].max()) if R else 0
        if S == 0:
            return self.bg.expand(R, 3).clone()
        k = torch.arange(S, dtype=torch.float32)
        dt, ln = s["dt"][:, None], s["len"][:, None]
        s0 = k * dt
        s1 = torch.minimum((k + 1) * dt, ln)
        mid = 0.5 * (s0 + s1)
        delta = s1 - s0
        valid = torch.arange(S)[None, :] < s["nsteps"][:, None]
        p = s["p0"][:, None, :] + mid[..., None] * s["dg"][:, None, :]        # [R,S,3]
        reso = torch.tensor(self.reso)
        u = torch.minimum(torch.clamp(p - 0.5, min=0.0), (reso - 1).float())
        i0 = torch.minimum(u.long(), torch.clamp(reso - 2, min=0))
        i1 = torch.minimum(i0 + 1, reso - 1)
        f = u - i0.float()
        rows, ws = [], []
        for c in range(8):
            bits = ((c >> 2) & 1, (c >> 1) & 1, c & 1)
            ix = [i1[..., a] if bits[a] else i0[..., a] for a in range(3)]
            wc = torch.ones_like(f[..., 0])
            for a in range(3):
                wc = wc * (f[..., a] if bits[a] else 1.0 - f[..., a])
            rows.append(self.links[(ix[0] * self.reso[1] + ix[1]) * self.reso[2] + ix[2]])
            ws.append(wc)
        rows = torch.stack(rows, -1)                                          # [R,S,8]
        w = torch.stack(ws, -1) * (rows >= 0)
        rows = rows.clamp(min=0)
        sigma = torch.relu((w * self.density[rows]).sum(-1))                 # [R,S]
        co = torch.einsum("rsc,rscj->rsj", w, self.sh[rows])                  # [R,S,C]
        pre = torch.einsum("rskb,rb->rsk", co.view(R, S, 3, self.B), s["Y"]) + COLOR_OFFSET
        col = torch.relu(pre)
        tau = sigma * delta * valid
        logT = torch.cumsum(-tau, dim=1)
        logT_before = logT + tau
        alive = torch.exp(logT_before) >= T_STOP
        wgt = torch.exp(logT_before) * (-torch.expm1(-tau)) * alive
        T_end = torch.exp((-tau * alive).sum(1))
        return (wgt[..., None] * col).sum(1) + T_end[:, None] * self.bg

    def forward(self):
        with torch.no_grad():
            return torch.cat([self._render(lo, hi) for lo, hi in self.chunks]).numpy()

    def forward_backward(self):
        self.density.grad = None
        self.sh.grad = None
        scale = 1.0 / self.n
        for lo, hi in self.chunks:
            rgb = self._render(lo, hi)
            loss = scale * ((rgb - self.target[lo:hi]) ** 2).sum()
            loss.backward()
        return self.density.grad.numpy(), self.sh.grad.numpy()
