"""Memory estimate of a hash-grid run: tables with gradient and Adam moments, the MLPs'
activations, per-sample buffers, the occupancy grid and the ray store (docs/memory.md)."""
from __future__ import annotations

from ..runtime.memory import StageEstimate, ray_store_bytes, training_stages


def hash_stage(hc, n_rays: int) -> StageEstimate:
    """StageEstimate of a hash-grid run with HashConfig ``hc``: tables with gradient and Adam
    moments (the backward needs no scratch copy on either path), the MLP's activations for
    every sample of a batch (all live: the occupancy grid starts full), per-sample buffers, the
    occupancy grid and the ray store (with the images' alpha for random backgrounds)."""
    pad = lambda x: -(-x // 16) * 16                           # noqa: E731 - kernel padding
    table = 4 * hc.levels * (1 << hc.log2_table) * hc.features
    tables = 4 * table
    W, WC, din = hc.width, hc.color_width, pad(hc.levels * hc.features)
    nslot = din + W + 16 + hc.geo_features + 16 + hc.color_depth * WC + 16
    # an adapted batch (hash.batch_samples) aims at batch_samples live samples; BOUND_FACTOR
    # times that covers a step whose rays hold more than the last step's (and is the bounded
    # step's capacity on GPUs)
    from .model import BATCH_RAYS_RANGE, BOUND_FACTOR
    samples = BOUND_FACTOR * hc.batch_samples if hc.batch_samples else hc.batch_rays * hc.samples
    act = 2 * 4 * pad(samples) * nslot
    per_sample = 4 * samples * (2 * (din + 16) + 20)
    occ = 5 * hc.occ_res ** 3
    rays = BATCH_RAYS_RANGE[1] if hc.batch_samples else hc.batch_rays
    alpha = 4 * int(n_rays) if hc.random_background else 0
    total = tables + act + per_sample + occ + ray_store_bytes(n_rays, rays) + alpha
    what = (f"{hc.batch_samples} live samples" if hc.batch_samples else
            f"{hc.batch_rays} rays x {hc.samples} samples")
    return StageEstimate(f"hash training ({what}, "
                         f"T 2^{hc.log2_table})", total, max(table, 4 * pad(samples) * nslot),
                         "hash table or MLP activations")


HASH_FIX = ("lower hash.log2_table, hash.batch_samples (or hash.batch_rays) or hash.samples, or "
            "load fewer rays with "
            "train.downscale / train.max_train_images")


def memory(cfg, n_rays: int, caps, tuning=None, is_cpu: bool = True):
    """(stages, fix) of cfg.hash's run on ``n_rays`` rays."""
    return training_stages(hash_stage(cfg.hash, n_rays), n_rays), HASH_FIX
