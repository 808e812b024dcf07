"""Memory estimate of a NeRF run: 5 P per network (params, transposed copy, gradient, Adam m
and v), activations and their gradients 2 * 4 B s nslot, per-sample encodings and gradients,
plus the ray store (clrf/training/budget.py's docstring, docs/memory.md)."""
from __future__ import annotations

from ..runtime.memory import StageEstimate, ray_store_bytes, training_stages


def nerf_stage(nc, n_rays: int, caps) -> StageEstimate:
    """StageEstimate of a NeRF run with NerfConfig ``nc`` on a device described by ``caps``
    (its default register tile sets the weight-gradient chunk when the config leaves it open)."""
    from ..mlp.tiling import CHUNK_TILES, device_default
    spec = nc.mlp_spec()
    dw_chunk = spec.dw_chunk or (CHUNK_TILES * spec.rows if spec.rows
                                 else device_default(caps, spec).dw_chunk)
    W, D, WC = spec.width, spec.depth, spec.color_width
    pad = lambda x: -(-x // 16) * 16                           # noqa: E731 - kernel padding
    params = (pad(spec.in_dim) * W + (D - 1) * W * W + (pad(spec.in_dim) * W if spec.skip >= 0
                                                          else 0)
              + W * (W + 16) + (W + pad(spec.dir_dim)) * WC + WC * 16 + (D + 4) * (W + 16))
    nslot = pad(spec.in_dim) + pad(spec.dir_dim) + (D + 1) * W + 16 + WC + 16
    B = nc.batch_rays
    nets = [nc.n_coarse, nc.n_coarse + nc.n_fine] if nc.n_fine else [nc.n_coarse]
    if nc.shared_net:
        nets = [max(nets)]
    act = sum(2 * 4 * pad(B * s) * nslot + 4 * (-(-B * s // dw_chunk)) * params
              for s in nets)
    samples = B * (nc.n_coarse + nc.n_fine)
    per_sample = 4 * samples * (2 * (spec.in_dim + spec.dir_dim) + 16)
    total = 5 * 4 * params * len(nets) + act + per_sample + ray_store_bytes(n_rays, B)
    big = 4 * pad(B * max(nets)) * nslot
    return StageEstimate(f"NeRF training ({B} rays x {max(nets)} samples, width {W})", total,
                         big, "MLP activations")


NERF_FIX = ("lower nerf.batch_rays, nerf.n_coarse / nerf.n_fine or nerf.width, or load fewer "
            "rays with train.downscale / train.max_train_images")


def memory(cfg, n_rays: int, caps, tuning=None, is_cpu: bool = True):
    """(stages, fix) of cfg.nerf's run on ``n_rays`` rays on the device ``caps``."""
    return training_stages(nerf_stage(cfg.nerf, n_rays, caps), n_rays), NERF_FIX
