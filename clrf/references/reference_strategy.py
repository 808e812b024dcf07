"""Float64 twins of the density strategies' kernels (cl/splat_train.cl; clrf/splat/strategies/):
the default strategy's statistics (splat_densify_stats), and MCMC's regularisers' gradients
(splat_mcmc_reg) and noise on the means (splat_mcmc_noise), drawn from the kernel's
counter-based hash so that both draw the same normals."""
from __future__ import annotations

import numpy as np

from .reference_splat import quat_rot as unit_quat_rot
from .reference_splat import sigmoid  # noqa: F401  (clrf/splat/strategies use it from here)

GOLDEN = 0x9E3779B9
MIX = 0x85EBCA6B
NOISE_SHARPNESS = 100.0    # k = scale sigmoid(-100 (o - 0.005)) = scale / (1 + e^(100 (o - 0.005)))
NOISE_OPACITY = 0.005


def mcmc_hash(x):
    """cl/splat_train.cl mcmc_hash over uint32 arrays (wrapping arithmetic)."""
    x = np.asarray(x, np.uint64) & 0xFFFFFFFF
    x ^= x >> np.uint64(16)
    x = (x * np.uint64(0x7FEB352D)) & 0xFFFFFFFF
    x ^= x >> np.uint64(15)
    x = (x * np.uint64(0x846CA68B)) & 0xFFFFFFFF
    x ^= x >> np.uint64(16)
    return x


def uniform(key, c: int):
    return ((mcmc_hash(key ^ np.uint64(c)) >> np.uint64(8)).astype(np.float64) + 0.5) / 2.0 ** 24


def normals(n: int, seed: int, step: int) -> np.ndarray:
    """The three standard normals [n, 3] of each Gaussian at (seed, step)."""
    i = np.arange(n, dtype=np.uint64)
    key = mcmc_hash(mcmc_hash(np.uint64(seed)) ^ mcmc_hash(np.uint64((step + GOLDEN) & 0xFFFFFFFF))
                    ^ mcmc_hash((i * np.uint64(MIX)) & 0xFFFFFFFF))
    u1, u2, u3, u4 = (uniform(key, c) for c in (1, 2, 3, 4))
    r1, r2 = np.sqrt(-2 * np.log(u1)), np.sqrt(-2 * np.log(u3))
    return np.stack([r1 * np.cos(2 * np.pi * u2), r1 * np.sin(2 * np.pi * u2),
                     r2 * np.cos(2 * np.pi * u4)], 1)


def quat_rot(q) -> np.ndarray:
    """Rotation matrices [n, 3, 3] of quaternions [n, 4] (w, x, y, z), normalised first (a
    zero quaternion gives the identity, as in the kernel)."""
    q = np.asarray(q, np.float64)
    return unit_quat_rot(q / np.maximum(np.linalg.norm(q, axis=1, keepdims=True), 1e-12))


def mcmc_noise(means, log_scales, quats, opacity_logits, scale: float, seed: int,
               step: int) -> np.ndarray:
    """The means [n, 3] after splat_mcmc_noise."""
    m = np.asarray(means, np.float64)
    o = sigmoid(opacity_logits)
    k = scale * sigmoid(-NOISE_SHARPNESS * (o - NOISE_OPACITY))
    z = normals(len(m), seed, step)
    R = quat_rot(quats)
    s2 = np.exp(2 * np.asarray(log_scales, np.float64))
    a = np.einsum("nji,nj->ni", R, z) * s2          # S^2 R^T z
    return m + k[:, None] * np.einsum("nij,nj->ni", R, a)


def mcmc_reg_grads(opacity_logits, log_scales, opacity_reg: float, scale_reg: float):
    """(dL/dopacity_logits [n], dL/dlog_scales [n, 3]) of opacity_reg mean(sigmoid(logits)) +
    scale_reg mean(exp(log_scales))."""
    o = sigmoid(opacity_logits)
    s = np.exp(np.asarray(log_scales, np.float64))
    n = max(len(o), 1)
    return opacity_reg / n * o * (1 - o), scale_reg / (3 * n) * s


def densify_stats(grad_xy, radius, width: int, height: int, stats):
    """The default strategy's statistics (grad_accum, grad_count, max_radius) [n] each after
    one step of screen-position gradients ``grad_xy`` [n, 2] (pixels) and screen radii
    ``radius`` [n]: for each seen Gaussian (radius > 0) with a finite norm
    |(gx W / 2, gy H / 2)|, the norm added and the count raised by one; the largest radius
    of every seen one."""
    accum, count, max_radius = (np.array(a, np.float64) for a in stats)
    g = np.asarray(grad_xy, np.float64) * [0.5 * width, 0.5 * height]
    r = np.asarray(radius, np.float64)
    seen = r > 0
    norm = np.sqrt((g * g).sum(1))
    add = seen & np.isfinite(norm)
    accum[add] += norm[add]
    count[add] += 1
    max_radius[seen] = np.maximum(max_radius[seen], r[seen])
    return accum, count, max_radius
