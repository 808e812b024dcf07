"""The case matrix (CASES: every case with its group and tolerance) and run_all."""
from __future__ import annotations

import functools
import time

from .framework import (CLOSED, Case, EXACT, FINITE, GRAD, LONG_FWD, NERF_ENCODE, OPT, OPT_LONG,
                        RAISES, REL, RENDER, Row, run_case)
from .cases_render import (bad_inputs, convergence, degenerate, dir_scale, far_origin, grazing,
                           huge_sh, inside_start, long_ray, nearly_opaque, negative_density,
                           one_hot_voxel, pruned, ramp, scale_sweep, segment_sum, sh3_poles, slab,
                           step_overflow, stiff_sigma_delta, tau_overflow, tiny_dirs,
                           very_long_ray, very_long_transmittance, world_scale)
from .cases_train import (batch_extremes, beta_prior, flat_grid_upsample, opt_eps_state0,
                          opt_huge_grad, opt_long_sparse, opt_tiny_grad, opt_zero_grad,
                          prune_to_nothing, reduce_case, resample_huge, single_voxel_upsample,
                          sparsity, tv_flat, tv_huge_values, tv_missing_neighbours, tv_step_edge)
from .cases_hash import (hash_contracted_long_rays, hash_density_saturation,
                         hash_empty_occupancy, hash_levels_finer_than_images, hash_rays_leave_occupied_cells,
                         hash_tiny_table_gradients, hash_tiny_tables)
from .cases_nerf import (nerf_composite_stiff, nerf_encode_large, nerf_importance_degenerate,
                         nerf_mlp_saturated, nerf_near_equals_far)


# ---- the matrix ----------------------------------------------------------------------------
# Former kernel findings, fixed (kept here as the cases that guard them):
# - very long rays: rgb/acc/depth and the per-cell gradient registers were plain float32 sums
#   (error ~ N u: acc 3.9e-4 relative at 8e5 samples); now Kahan-compensated when a ray can
#   exceed LONG_RAY_SAMPLES (COMPENSATED_SUMS in cl/march.h, chosen by clrf/grid/render.py).
# - a step needing > 2^31 samples overflowed the int step count and rendered background
#   silently; the host now rejects it with a ValueError naming `step`.
# --------------------------------------------------------------------------------
def _cases() -> list[Case]:
    P = functools.partial
    cs: list[Case] = []
    for sd in (0.0, 1e-12, 1e-8, 1e-4, 1.0, 10.0, 1e2, 1e4, 1e8, 1e30):
        cs.append(Case(f"stiff sigma*delta={sd:g}", "stiff", P(stiff_sigma_delta, sd=sd)))
    cs += [Case("sigma*delta overflows float32", "stiff", tau_overflow),
           Case("one-hot voxel 1e10", "stiff", one_hot_voxel),
           Case("nearly opaque", "stiff", nearly_opaque),
           Case("long ray fwd+bwd", "stiff", long_ray, LONG_FWD),
           Case("very long ray transmittance", "stiff", very_long_transmittance),
           Case("very long ray acc/rgb/grads", "stiff", very_long_ray),
           Case("step below 2^31 samples limit", "stiff", step_overflow)]
    for s in (1e-6, 1e-4, 1e-2, 1.0, 1e2, 1e4, 1e6):
        cs.append(Case(f"slab sigma={s:g}", "closed form", P(slab, sigma=s), CLOSED))
    for axis in range(3):
        for sign in (+1, -1):
            cs.append(Case(f"density ramp {'+-'[sign < 0]}{'xyz'[axis]}", "closed form",
                           P(ramp, axis=axis, sign=sign), REL))
    cs += [Case("segments add to path length", "closed form", segment_sum, REL),
           Case("convergence order 2", "closed form", convergence)]
    cs += [Case("dir components 0, +-1e-30", "geometry", tiny_dirs),
           Case("unnormalised dirs 1e-20..1e20", "geometry", dir_scale),
           Case("origin 1e4 outside", "geometry", far_origin),
           Case("grazing faces/edges/corners", "geometry", grazing),
           Case("start inside / on voxel boundary", "geometry", inside_start),
           Case("world scale 1e-10..1e10", "geometry", world_scale)]
    for shape in ((1, 1, 1), (1, 4, 4), (4, 1, 1), (2, 1, 3)):
        cs.append(Case(f"degenerate grid {shape}", "geometry", P(degenerate, shape=shape)))
    cs += [Case("fully pruned grid", "geometry", pruned, EXACT),
           Case("negative densities", "values", negative_density),
           Case("SH coefficients 1e20", "values", huge_sh),
           Case("SH degree 3 at the poles", "values", sh3_poles),
           Case("NaN/Inf inputs rejected", "values", bad_inputs, RAISES)]
    for mode in ("rmsprop", "sgd"):
        cs += [Case(f"{mode} zero and NaN gradients", "optimiser", P(opt_zero_grad, mode=mode), EXACT),
               Case(f"{mode} huge gradients 1e20..inf", "optimiser", P(opt_huge_grad, mode=mode),
                    OPT),
               Case(f"{mode} long sparse run vs float64", "optimiser",
                    P(opt_long_sparse, mode=mode), OPT_LONG)]
    cs += [Case("rmsprop tiny gradients 1e-20..1e-45", "optimiser", opt_tiny_grad, OPT),
           Case("rmsprop eps 0..1 with state 0", "optimiser", opt_eps_state0, OPT),
           Case("TV flat regions", "regulariser", tv_flat, EXACT),
           Case("TV step edge", "regulariser", tv_step_edge, GRAD),
           Case("TV missing / outside neighbours", "regulariser", tv_missing_neighbours, GRAD)]
    for big in (1e10, 1e19, 1e30, 1e38, 3e38):
        cs.append(Case(f"TV values +-{big:g}", "regulariser", P(tv_huge_values, big=big), GRAD))
    cs += [Case("encode |x| <= 1e3, 16 frequencies", "nerf", nerf_encode_large, NERF_ENCODE),
           Case("importance sampling degenerate weights", "nerf", nerf_importance_degenerate,
                EXACT),
           Case("near == far", "nerf", nerf_near_equals_far, EXACT),
           Case("composite sigma 0..1e30", "nerf", nerf_composite_stiff, RENDER),
           Case("fused MLP saturated inputs", "nerf", nerf_mlp_saturated, FINITE)]
    cs += [Case("hash tables T = 2, 16 (collisions)", "hash", hash_tiny_tables),
           Case("hash levels finer than the images", "hash", hash_levels_finer_than_images),
           Case("hash 1e-8 gradients in fp32 tables", "hash", hash_tiny_table_gradients),
           Case("hash density saturation (exp overflow)", "hash", hash_density_saturation,
                FINITE),
           Case("hash rays leaving every occupied cell", "hash", hash_rays_leave_occupied_cells,
                EXACT),
           Case("hash empty occupancy grid", "hash", hash_empty_occupancy, EXACT),
           Case("hash contracted rays 1e6 long", "hash", hash_contracted_long_rays)]
    cs += [Case("beta prior at T = 0, 1 - 1e-7, 1", "regulariser", beta_prior, GRAD),
           Case("sparsity sigma 0..+-3e38", "regulariser", sparsity, GRAD),
           Case("prune to nothing", "structure", prune_to_nothing, EXACT),
           Case("single voxel upsampled", "structure", single_voxel_upsample, RENDER),
           Case("resample values 1e30, 3e38", "structure", resample_huge, RENDER),
           Case("resample flat grids", "structure", flat_grid_upsample, RENDER),
           Case("batch indices at extremes", "structure", batch_extremes, EXACT)]
    for fp64 in (True, False):
        for kind in ("tiny", "O(1)"):
            cs.append(Case(f"reduce {'fp64' if fp64 else 'f32 compensated'} {kind} diffs",
                           "reduction", P(reduce_case, fp64=fp64, kind=kind)))
    for dm in (0.0, 1e-10, 1e-3, 1.0, 1e3, 1e10, 1e30):
        for sm in (1e-3, 1.0, 10.0):
            cs.append(Case(f"sweep density x{dm:g} step x{sm:g}", "scale sweep",
                           P(scale_sweep, dm=dm, sm=sm)))
    return cs


CASES = _cases()


def run_all(device, quick: bool, select: str | None = None, log=print) -> list[Row]:
    rows = []
    for c in CASES:
        if select and select not in c.name:
            continue
        t = time.perf_counter()
        rr = run_case(c, device, quick)
        rows += rr
        state = "ok " if all(r.passed for r in rr) else ("xf " if c.xfail else "BAD")
        log(f"{time.perf_counter() - t:6.2f}s  {state} "
            f"{c.name}")
    return rows
