"""Every tolerance the tests use, with the reason for its size. No ad hoc tolerances in tests.

float32 has a unit roundoff of 6e-8. A forward render sums O(100) terms of size <= 1, each from
an interpolation of 8 terms and an SH dot product of <= 16 terms, so its absolute error against
float64 is a few 1e-7 in practice; we allow 2e-5 absolute + 1e-5 relative, which is ~20x
the worst case seen on random grids and still catches any convention error (those are >= 1e-3).
"""

# Forward render (rgb, acc) against the float64 reference: see module docstring.
RENDER_ATOL = 2e-5
RENDER_RTOL = 1e-5
# Depth is a sum of w_k * t_k with t_k up to the ray length (a few world units): same relative
# error budget scaled by the distances.
DEPTH_ATOL = 1e-4
DEPTH_RTOL = 1e-5

# Kernel gradients vs the float64 analytic gradient. Gradients are sums over rays and samples of
# terms formed from the remaining radiance (total - prefix, float32 cancellation ~ n_samples *
# 6e-8 * |total|) and scattered by float atomics in nondeterministic order.
GRAD_ATOL = 2e-5
GRAD_RTOL = 1e-4

# Reference analytic gradient vs central finite differences of the reference (float64,
# eps = 1e-4): truncation error O(eps^2 * f''') ~ 1e-8 on smooth random grids.
FD_ATOL = 1e-6
FD_RTOL = 1e-5

# Early termination: the march stops once transmittance < T_STOP, so closed forms that assume
# a full march (slab opacity) are exact only up to T_STOP.
from clrf.grid.render import T_STOP  # noqa: E402

CLOSED_FORM_ATOL = T_STOP + 1e-6

# Camera rays are returned in float32 (the kernels' input type): components of size <= ~10 carry
# a rounding error <= 10 * 6e-8 = 6e-7, so 2e-6 absolute; a convention error (half-pixel shift,
# flipped axis) is >= 1e-2 on the toy cameras the tests use.
CAMERA_ATOL = 2e-6
# Undistortion by Newton's method stops at a 1e-14 update in float64; 1e-6 (normalised units,
# i.e. ~1e-3 px at f = 1000) is the accuracy the data layer promises.
UNDISTORT_ATOL = 1e-6
# Camera models (clrf.data.camera_models) against the float64 COLMAP forward projection
# (clrf.references.reference_cameras): Newton stops once its update is below 1e-14 in normalised
# units and the polynomials carry ~1e-15 relative rounding, so a ray is off by ~1e-14 rad; 1e-10
# rad leaves 1e4 of margin and still catches a misread model (fisheye read as radial-tangential,
# a dropped k3) by 1e-4 rad or more at the image border of the test cameras.
CAMERA_MODEL_ANGLE = 1e-10
# The same in pixels for border round trips (pixel -> ray -> reference projection): f <= 100 px
# times 1e-10 rad.
CAMERA_MODEL_PX = 1e-8
# Resampling a second COLMAP camera's image onto the first: the source is a 16-bit PNG
# (quantisation <= 0.5 / 65535 = 7.6e-6), bilinear weights are a convex combination (no growth),
# float32 storage adds 6e-8; a wrong focal or half-pixel shift moves values by >= 1e-2.
RESAMPLE_ATOL = 2e-5
# Procedural images are computed in float64 and stored as float32 (values in [0, 1]: error
# <= 6e-8); hand-computed expected values are written with 6 decimals (error <= 5e-7).
PROCEDURAL_ATOL = 1e-6
# ---- stability suite (tools/stability.py, tests/test_stability.py) -----------------------------
# Relative error bounds below use u = 6e-8 (float32 unit roundoff) and N = samples per ray.

# Exact identities: fully pruned grids (rgb == background bit for bit), directions scaled by a
# power of two (the set-up divides by the largest component in double: bitwise identical), and
# the absolute part of the relative-only checks below.
STAB_ZERO_ATOL = 0.0
# Closed forms that hold up to early termination (CLOSED_FORM_ATOL above) plus float32
# accumulation of N <= ~200 weights: N u = 1.2e-5 worst case; 1e-5 relative is plenty because the
# absolute part already covers everything near 1.
STAB_CLOSED_FORM_RTOL = 1e-5
# Opacity against 1 - exp(-sigma L) relative to itself, for rays that do not terminate early
# (tiny sigma: acc ~ sigma L ~ 1e-12 must still be right to float32 precision). acc is a float32
# sum of N <= 300 terms, each T_k alpha_k with ~3u error (alpha, exp of the Kahan log-T, product):
# worst case (N/2 + 3) u = 9e-6. Segment lengths telescope exactly (consecutive segment ends are
# the same float and s1 - s0 is exact for k >= 1), so a missing or doubled piece of path
# (>= one step, i.e. >= 1/N relative) fails by orders of magnitude.
STAB_SEGMENT_SUM_RTOL = 2e-5
# Long rays (N >= 4096 samples): rgb is a plain float32 sum of N terms (worst case N u |rgb|
# = 2.5e-4, random-walk sqrt(N) u = 4e-6) and sample positions p0 + s dg carry ulp(s) ~ 1e-5
# voxels at s ~ 128..512 voxels. 5e-5 absolute is 10x the random-walk estimate plus position error,
# 5x below the worst case; a drift that grows with N (no Kahan in log T) reaches 1e-3.
STAB_LONG_RAY_ATOL = 5e-5
# Long-ray gradients: remaining radiance = total - Kahan prefix, so its error is ~ u |total| per
# sample instead of N u; summed over the ~N/Z samples of a voxel (tens) with deltas ~1e-3: 2e-5
# (GRAD_ATOL) stays the right scale. Kept separate so a future change is visible.
STAB_LONG_GRAD_ATOL = 2e-5
# Reductions of n = 4M..16M squared differences against float64 numpy (relative):
# fp64: each work-item adds n / 16384 terms in double then a 7-level tree: (n/16384 + 20) * 1.1e-16
# < 2e-13; 1e-12 leaves margin.
STAB_REDUCE_FP64_RTOL = 1e-12
# compensated float32 (TwoSum heads, exact squares by fma): only the tails are rounded, error
# ~ (ops) u^2 ~ 1.6e7 * 3.6e-15 = 6e-8; 1e-6 is still 4000x tighter than a float32 running sum
# (4.5e-3 measured at n = 4M).
STAB_REDUCE_F32C_RTOL = 1e-6
# PSNR in dB: d(PSNR) = (10 / ln 10) d(MSE)/MSE = 4.34 * 1e-6 at the looser reduction bound.
STAB_PSNR_ATOL = 1e-5
# Observed convergence order of the midpoint quadrature (expected 2): the next term of the error
# is O(sigma delta) ~ 0.2 relative at step 1 (sigma = 3, delta = 1/16), i.e. ~0.25 in log2.
STAB_ORDER_ATOL = 0.25
# Very long rays (~1e6 samples, step 1e-5 voxels): what compensated accumulation gives
# independent of N (Kahan: 2u + N u^2 = 1.6e-7 relative at N = 1e6, plus ~3u per term as for
# STAB_SEGMENT_SUM_RTOL); 1e-5 is 60x that. A plain float32 sum drifts up to N u / 2 = 3e-2.
STAB_VERY_LONG_RTOL = 1e-5
# ---- optimiser, regulariser and structure cases (cl/optim.cl, cl/grid_ops.cl) -----------------
# One optimiser step against the float64 twin (lr = 0.1, |param| <~ 4). The kernel's step
# lr * (g / (sqrt(s) + eps)) may carry OpenCL's allowed 3 ulp (sqrt) + 2.5 ulp (divide) + 0.5 ulp
# (lr *) + ~1 ulp (state lerp, halved by sqrt) ~ 7 ulp = 8e-7 relative; steps are <= lr /
# sqrt(1 - beta) = 0.45, so <= 3.6e-7 absolute, and the update p - step rounds to 0.5 ulp(|p|)
# (1.2e-7 at |p| < 4). Hence 5e-7 absolute + 1e-6 relative (the relative part alone for
# quantities compared relatively: first steps from 0, the state, SGD steps of lr * 1e18).
# PoCL measures <= 1e-1 of this; a wrong rule (eps placement, missed first-touch branch, beta
# vs 1 - beta) is off by >= 1e-3 relative.
STAB_OPT_ATOL = 5e-7
STAB_OPT_RTOL = 1e-6
# Long sparse runs (1% of 2000 rows per step, up to K ~ 40 updates per entry in 2000 steps),
# compared normwise (max |err| / max |param|): each update rounds p - step (0.5 ulp of max |p|)
# and adds the step error (7 ulp of a step that is <= 0.45 ~ max |p| / 8 for RMSProp, 1 ulp for
# SGD), so <= 1.5 ulp = 1.8e-7 per update, K = 40: 7e-6 worst case; 1e-5. Measured ~1e-7 (the
# errors are not all of one sign). A step applied twice or skipped is >= 1e-3.
STAB_OPT_LONG_NORM = 1e-5
# RMSProp state after a long run, relative per entry: s <- beta s + (1 - beta) g^2 rounds twice
# (~1 ulp) per update and is contracting only when g^2 keeps up with s; when s decays (tiny g
# after a huge one) the relative errors add: K = 40 updates -> 4.8e-6; 1e-5.
STAB_OPT_LONG_STATE_RTOL = 1e-5

# ============================================================================================
# NeRF (cl/encode.cl, cl/mlp.cl, cl/sample.cl, cl/composite.cl, cl/optim.cl)
# ============================================================================================

# Encoding vs float64: sinpi/cospi of an exactly scaled float32 argument are accurate to a few
# ulp (OpenCL allows 4 ulp), i.e. <= ~5e-7 absolute for values in [-1, 1], at ANY |x| (the test
# goes to |x| = 1e3 with 16 frequencies, phase 2^15 * 1e3). 2e-6 is 4x that; a kernel that
# formed 2^k*pi*x in float32 would be off by O(1) there, so the test still discriminates.
ENCODE_ATOL = 2e-6
# Encoding backward: entries are 2^k pi (cos g_s - sin g_c) summed over k; the largest term is
# 2^(L-1) pi ~ 1e5 for L = 16, so the float32 sum carries ~L * 2^(L-1) pi * 6e-8 ~ 0.1 absolute
# on a total of the same magnitude order as the largest term: relative 2e-5 of the norm.
ENCODE_GRAD_RTOL = 2e-5

# MLP forward vs float64: each output is a chain of <= 10 dot products of <= 320 terms with
# Glorot-scale weights; float32 accumulation (FMA, sequential over k) gives relative error
# ~ sqrt(K) * 6e-8 per layer, a few 1e-6 after 10 layers; sigma and rgb are O(1).
MLP_ATOL = 1e-5
MLP_RTOL = 1e-4
# MLP gradients vs the float64 analytic gradient: weight gradients are sums over the batch (up
# to a few hundred samples) of products of activations and backpropagated gradients, in
# float32 per chunk; relative to the largest entry of each gradient, 1e-5 is ~20x the error
# seen, while a wrong index or transposition gives O(1).
MLP_GRAD_REL_TO_MAX = 2e-5
# Reference analytic gradient vs central differences of the reference (float64, eps 1e-6):
# truncation O(eps^2) and roundoff O(1e-16 / eps) are both ~1e-10.
MLP_FD_ATOL = 1e-7
MLP_FD_RTOL = 1e-6
MLP_FD_EPS = 1e-6
# Directional derivative of the float32 kernel itself (loss(p + e v) - loss(p - e v)) / 2e
# with e = 1e-2 on a unit-norm v: roundoff 1e-7 * |loss| / e ~ 1e-5 and truncation
# O(e^2 |f'''|) ~ 1e-4 for smooth activations; 2e-3 relative still catches a wrong gradient.
MLP_KERNEL_FD_EPS = 1e-2
MLP_KERNEL_FD_RTOL = 2e-3

# Sampling vs float64: stratified t = near + (far - near)(k + u)/K in float32 is within a few
# ulp of far (<= 6 units here): 4e-6. Importance samples invert a float32 CDF walk (running sum
# of <= 128 masses): the CDF error ~ K * 6e-8 relative moves t by that fraction of a bin width.
SAMPLE_ATOL = 4e-6
IMPORTANCE_ATOL = 2e-5
# Importance samples compared through the float64 CDF: the kernel walks a float32 running sum
# of <= 64 masses, error <= 64 * 6e-8 of the total; 1e-5 of the total is ~3x that. (Positions
# themselves are ill-conditioned in bins of mass ~PDF_PAD: a 1e-6 CDF error moves a sample by
# 10% of such a bin, so positions are compared directly only where all bins carry mass.)
IMPORTANCE_CDF_RTOL = 1e-5

# Compositing vs float64: the same budget as the grid renderer (module docstring): sums of
# <= 200 weights with log-space transmittance.
COMPOSITE_ATOL = 2e-5
COMPOSITE_RTOL = 1e-5
# Compositing backward vs float64: dL/dsigma_k = delta_k (T_{k+1} g.c_k - R_k) with R_k from
# total - Kahan prefix: cancellation ~ K * 6e-8 * |total|, times delta <= 1.
COMPOSITE_GRAD_ATOL = 2e-5
COMPOSITE_GRAD_RTOL = 1e-4
# Reference compositing gradient vs its own central differences (float64, eps 1e-6).
COMPOSITE_FD_ATOL = 1e-7
COMPOSITE_FD_EPS = 1e-6

# Adam vs float64 on the same gradients: one update of size <= lr with float32 moments.
ADAM_ATOL = 1e-7
ADAM_RTOL = 1e-5

# Encoding reference gradient vs central differences (float64, eps 1e-6): truncation
# O(eps^2 (2^k pi)^3) ~ 1e-9 for k < 3, roundoff ~1e-10.
ENCODE_FD_ATOL = 1e-6
ENCODE_FD_RTOL = 1e-6
# Points o + t d/|d| in float32 vs float64: a few ulp of |o| + t <= ~4 (normalising d costs
# ~2 ulp); unit directions a few ulp of 1.
RAY_POINTS_RTOL = 1e-6
RAY_POINTS_ATOL = 1e-6
# Hand-computed toy values (exact in decimal) evaluated in float32: a few ulp of O(1) numbers.
TOY_ATOL = 1e-6
# The loss train_step returns vs the MSE of a render of the same rays with the same samples:
# two float32 evaluations summed in different orders (per-ray kernel sum vs numpy mean).
MODEL_LOSS_RTOL = 1e-4
# Two models restored from one checkpoint run the same kernels on the same data: only the
# nondeterminism of nothing (no atomics in the NeRF path) -> they agree to float32 roundoff.
CHECKPOINT_RTOL = 1e-5

# ============================================================================================
# MSI background (cl/background.cl)
# ============================================================================================
# Forward vs float64: at most L - 1 <= 15 samples of 8-tap trilinear values; float32 atan2
# (OpenCL allows 6 ulp: ~1e-6 rad) moves a sample by 1e-6 * W / (2 pi) <= 3e-6 texels, i.e.
# <= 3e-6 times a texel-to-texel difference of O(1). The same budget as the grid renderer.
BG_ATOL = 2e-5
BG_RTOL = 1e-5
# Background gradients vs the float64 analytic gradient: dL/dsigma carries delta_k, up to the
# outermost shell's thickness (~L r_inner ~ 20 world units here), times the remaining-radiance
# cancellation (~L * 6e-8 * |total|), summed over a few hundred rays per texel by float atomics in
# nondeterministic order: 1e-4 absolute + 1e-4 relative.
BG_GRAD_ATOL = 1e-4
BG_GRAD_RTOL = 1e-4
# Reference gradient vs central differences of the reference (float64, eps 1e-5): truncation
# O(eps^2 f''') with f''' up to delta^3 ~ 1e2 gives ~1e-8; roundoff 1e-16 / eps ~ 1e-11.
BG_FD_EPS = 1e-5
BG_FD_ATOL = 1e-7
BG_FD_RTOL = 1e-6
# The float32 kernels against their own directional central difference (step 1e-2 on a unit
# direction): roundoff 6e-8 * |loss| (~50) / 1e-2 ~ 3e-4 and truncation O(e^2) ~ 1e-4 relative
# to a directional derivative of O(1..10): 1e-2 relative; a wrong sign or factor is O(1).
BG_KERNEL_FD_EPS = 1e-2
BG_KERNEL_FD_RTOL = 1e-2

# ============================================================================================
# Export (clrf/outputs/export.py, cl/export.cl)
# ============================================================================================
# Fields at points are one 8-corner trilinear interpolation (plus one multiply-add for colour):
# float32 error a few u times the largest corner value; the render's budget is ample.
EXPORT_FIELD_ATOL = RENDER_ATOL
EXPORT_FIELD_RTOL = RENDER_RTOL
# Geometry: marching cubes and expected depth locate a surface to within the sampling cell,
# which is what the issue asks ("within one voxel of the exact surfaces").
EXPORT_GEOMETRY_VOXELS = 1.0

# ============================================================================================
# Distributed bricks (clrf/grid/bricks.py, clrf/grid/distributed.py)
# ============================================================================================
# Composed partials vs the single-grid kernel render (both float32, same samples, no early
# termination): the same terms, only T_k = T_b T'_k formed as a product of two float32
# exponentials instead of one, and the partial sums of each brick added in float64: a few ulp
# of O(1) values, seen <= 5e-7 on random grids. 1e-5 absolute (the bound).
BRICK_COMPOSE_ATOL = 1e-5
# Depth: the same relative budget on distances of a few world units (seen <= 5e-7).
BRICK_DEPTH_ATOL = 1e-5
# Composition of float64 reference partials vs the float64 single-grid reference: the same
# sums regrouped; float64 roundoff only.
BRICK_REF_ATOL = 1e-12
# A short distributed training run vs the same run in one process (same batches, same
# optimiser, a prune + upsample midway): the single process stops rays at T < T_STOP = 1e-4
# (the distributed one does not), which changes each colour by <= 1e-4, and float sums run in
# another order; RMSProp's first steps after the upsample (about lr * sign(gradient)) amplify
# that for rows with near-zero gradients. On the procedural scene (20 steps, 16^3 -> 32^3) the
# mean training losses agreed to 1e-4 relative and the PSNRs to 0.005 dB (SSIM 1e-4); these
# bounds are 10x / 4x that and still 20x below what the 20 steps change (loss -70%, PSNR +13).
DIST_TRAIN_RTOL = 1e-3   # mean training loss, relative
DIST_TRAIN_ATOL = 0.02   # eval PSNR (dB) and SSIM, absolute
# Data-parallel hash grid (clrf/runtime/dataparallel.py) vs one process on the same device and
# batch: each rank sums its share's terms, then the shares are added; only the order of the
# float32 sums differs. Seen on the test's scene: 1.2e-7 of the largest network gradient, 7e-8
# of the largest table gradient, 4e-8 relative on the loss. A rank's share missing or counted
# twice moves the gradients by O(1) of their size and the loss by O(1e-1).
DATA_PARALLEL_GRAD_REL_TO_MAX = 1e-5
DATA_PARALLEL_LOSS_RTOL = 1e-6
# A few training steps: the losses, each of a batch through parameters Adam moved from the
# same gradients up to that rounding (Adam's first steps are about lr * sign(gradient), so a
# table entry whose gradient rounds to the other sign moves 2 lr apart: the parameters are
# not compared). Seen: 1.5e-7 relative over 6 steps.
DATA_PARALLEL_STEPS_LOSS_RTOL = 1e-5
# ---- viewer (clrf/viewer, tests/test_viewer_browser.py) ------------------------------------------
# The browser shows the viewer's frame and `clrf render --camera-path` writes one for the same
# camera: both come from identical rays (the page's float64 matrix travels as shortest round-trip
# JSON numbers, read back exactly) through the same kernels and the same uint8 rounding, and the
# page copies the opaque RGB bytes 1:1 into its 2D canvas (putImageData, then drawImage at the
# same size), which Chromium does exactly. One uint8 level allows for a browser whose canvas
# colour handling rounds differently; a wrong camera (half-pixel shift, transposed matrix, fov in
# radians, the frame before the last mouse move) changes edge pixels by tens of levels.
VIEWER_PIXEL_ATOL = 1
# An NDC point of a world ray against the viewer's NDC ray (tests/test_frames.py): the ray is
# float32 (components <= ~3 here, rounding <= 3 * 6e-8) and the projection onto it multiplies
# that by the point's parameter (<= ~10): ~2e-6; 1e-5 leaves 5x. Using the viewing camera's own
# NDC map instead of the training camera's moves the points by ~0.2.
NDC_LINE_ATOL = 1e-5
# Standard SSIM (scikit-image, Gaussian window) vs the test's own float64 separable 'valid'
# convolution: the same float64 sums in another order, over <= 64x64x3 pixels; roundoff only.
SSIM_REF_ATOL = 1e-10
# clrf's LPIPS (torch.nn backbone, float32) vs the lpips package's forward with the same
# float32 weights: the same float32 convolutions, possibly another summation order inside torch
# (a distance of ~0.1-0.7 summed over five layers); float32 roundoff is ~1e-7 relative per op.
LPIPS_REF_ATOL = 1e-5
# clrf's LPIPS (torch, float32) vs the float64 numpy reference (clrf/testing/lpips_ref.py) with
# the same random backbone and the package's linear weights, 64x48 images: seen <= 3e-7
# relative (float32 convolutions over <= 4608 terms); 30x that, far below any layout or scaling
# error (those change the distance by > 1e-2 relative).
LPIPS_F64_RTOL = 1e-5

# ============================================================================================
# Hash encoding (cl/hash.cl, clrf/hash/)
# ============================================================================================
# Forward vs float64: kernel and reference pick the same cell and weights (the reference
# repeats the kernel's float32 u and p), so only the float32 interpolation differs: 8 products
# of 3 weights and a feature (|feature| <= 1 in the tests), each ~4 u relative, summed: <= 40 u
# = 2.4e-6 worst case; seen ~3e-7. A wrong corner, weight or hash moves values by >= 1e-2.
HASH_ATOL = 3e-6
# Backward vs float64: each table entry sums <= n * 8 terms (n <= 65 points, |dL/denc| <= 1)
# in float32, in any order (atomics): <= (n * 8) u * max|term| ~ 3e-5 worst case; 1e-5 relative
# of the largest entry plus 3e-6 absolute is still 1000x below a misplaced contribution (O(0.1)).
HASH_GRAD_ATOL = 3e-6
HASH_GRAD_RTOL = 1e-5
# Reference gradient vs central differences of the reference: the encoding is LINEAR in the
# table, so a central difference is exact up to float64 roundoff (~1e-15 / eps with eps 1e-3).
HASH_FD_EPS = 1e-3
HASH_FD_ATOL = 1e-10
# Kernel self-consistency: enc(table + h e_j) - enc(table) with h = 1 equals h times the
# kernel's gradient column for a linear map; both in float32 on O(1) values: a few u -> 1e-6.
HASH_KERNEL_FD_ATOL = 1e-6
# Spatial derivative (hash_dx) vs float64: same cell and float32 weights as the twin; each
# level's sum of 8 corner terms (each 2 weight products times a float32 dot of F features) and
# the sum over levels carry <= ~16 u relative of the sum of the terms' magnitudes, which the
# tests bound by B_a = 2 inv_ext_a sum_l N_l sum_f |dL/denc_lf| max|table|: 16 u ~ 1e-6 of B,
# 2e-6 with margin. A wrong sign, corner or level scale moves dx by O(N_l / sum N_l) of B.
HASH_DX_RTOL_OF_BOUND = 2e-6
# Twin vs central differences of the float64 twin (u and p in float64) with x steps of 1e-7
# box units: along one axis the encoding is linear inside a cell, so the difference is exact
# up to roundoff, |L| ~ 10 times 1e-16 over 1e-7 ~ 1e-8; 1e-6 is 100x that and still ~1e6
# below a missing level's share.
HASH_DX_FD_EPS = 1e-7
HASH_DX_FD_ATOL = 1e-6
# ... and relative to dx: p = u N_l rounds by ~u64 N_l, which shifts L by u64 |dL/dx| / inv_ext
# (dL/dx = N_l inv_ext dL/dw); over a step of h = 1e-7: u64 / (h inv_ext) ~ 7e-9 relative at
# inv_ext = 1/3 (fine levels, where |dx| ~ 1e3, see 3e-6 absolute); 3e-8 with margin.
HASH_DX_FD_RTOL = 3e-8
# Each ray's dL/d(origin, direction) (packed_ray_grad) vs float64: float32 sums of <= 9
# samples' terms t_k dL/dx_k and SH derivatives (16 terms each), each a few u relative, then
# the projection over |d|: relative to the terms' magnitudes (the tests' per-ray scale, which
# the result may cancel far below) 2e-6 (~30 u) covers the sums' growth. A sample dropped, a
# missing t_k or projection moves the ray's gradient by O(1) of its terms.
HASH_RAY_GRAD_RTOL = 2e-6
# The float64 chain's dL/d(o, d) vs central differences of its loss (steps of 1e-6 world units
# in o and d): the chain is smooth where no sample crosses a cell face (piecewise multilinear
# encoding, relu MLP); its second-order error is h^2 |L'''| ~ 1e-12, and roundoff of a loss of
# ~0.1 over 2h is ~1e-11. A kink crossed within h costs at most |jump in dL/dx| h / (2h) of one
# sample: rare, and bounded below 1e-5 of the largest component here; 1e-5 is still 1e4 below
# a missing sample's share.
HASH_RAY_FD_EPS = 1e-6
HASH_RAY_FD_RTOL = 1e-5
# NeRF's dL/d(origin, direction) of each ray (cl/sample.cl ray_points_backward) vs float64:
# float32 sums of K (<= 16 here) terms t_k dL/dx_k + dL/dv_k, a few u each, then the
# projection over |d|: relative to the terms' magnitudes (the test's per-ray scale) 2e-6
# (~30 u), as HASH_RAY_GRAD_RTOL. A dropped sample, t_k or projection is O(1) of a term.
NERF_RAY_GRAD_RTOL = 2e-6
# The float64 twin's / chain's dL/d(o, d) vs central differences of its loss (steps 1e-6 in o,
# 1e-6 |d| in d): the loss is smooth (softplus MLP, sines, the composite's exponentials with
# the sample distances held), its second-order error ~h^2 |L'''| ~ 1e-12 and the roundoff of
# a loss of ~0.1 over 2h ~1e-10 relative to the largest component (~0.1 .. 10); 1e-5 of it
# is still 1e4 below a missing pass or sample's share.
NERF_RAY_FD_EPS = 1e-6
NERF_RAY_FD_RTOL = 1e-5
# One whole NeRF step (both passes: encodings, fused MLP, composite, MLP backward,
# encode_backward, the per-ray sums; with nerf.exposure the transforms' gradients) vs the
# float64 chain: the MLP's float32 error (~1e-5 relative) compounds through its backward and
# the importance samples' distances, drawn from float32 weights, differ by ~1e-6 of a bin;
# relative to the largest entry 1e-4, as HASH_STEP_GRAD_REL_TO_MAX: 100x below a missing
# pass, a wrong row or a transposed term (O(1e-2)).
NERF_STEP_GRAD_REL_TO_MAX = 1e-4
# Rays from corrected cameras (cl/ray_pose.cl): the rows are float32 roundings of float64
# (|A| <= 1, |c| ~ 3: 2e-7 absolute), a direction a float32 dot of 3 (|d0| ~ 1): a few u of
# |A||d0| ~ 5e-7; 1e-6 for the rows and centres, three times that for the directions. A
# wrong row, transposed A or wrong image moves them by O(1).
RAY_POSE_ATOL = 1e-6
# Per-image sums of a batch (ray_pose_sums): float32 sums of <= 300 products in a fixed tree,
# the error <= ~log2(n) + 2 u of the sum of the terms' magnitudes (the test's bound): 1e-6.
RAY_POSE_SUM_RTOL = 1e-6
# dL/dR, dL/dt (float64) vs central differences with steps of 1e-6 in R's and t's entries: the
# loss is smooth (sines and squares of O(1)), second-order error ~1e-12 / h^0, roundoff
# ~1e-16 |L| / h ~ 1e-9; 1e-6 relative (of max(1, |g|)) is far below a wrong sign or
# transpose (O(1)).
RAY_POSE_FD_RTOL = 1e-6
# hash.pose_opt's dL/d(w, tau) (each ray's gradient, the per-image sums, the host's chain)
# vs central differences of the float32 step loss in (w, tau) with steps of 1e-3: the
# difference's own error is its second-order term, h^2 |L'''| / 6 (the field's cells are ~1
# unit seen from ~3: curvature scales of ~0.3 rad, so ~1e-3 of |g|), and float32 roundoff of
# a loss of ~5e-4, ~1e-7 relative over 2h: ~2e-8 absolute; seen 7e-4 of the largest
# component. 2e-3 of it is still far below a wrong sign, transpose or missing term (O(1)).
HASH_POSE_FD_REL_TO_MAX = 2e-3
# SH direction encoding: degree-3 polynomials of a float32-normalised direction, coefficients
# <= 2.9: a few u times 3 -> 1e-6 (a wrong sign or index is O(0.1)).
HASH_SH_ATOL = 1e-6
# One whole hash-model step (occupancy compaction, hash encoding, fused MLP, compositing, MLP
# and hash backward) vs the same chain of float64 references: every stage's float32 error
# (MLP ~1e-5 relative, composite ~1e-6) compounds through the MLP backward into table
# gradients that sum a few hundred samples; relative to the largest entry, 1e-4 is ~10x the
# error seen and still 100x below a missing sample, a wrong row or a transposed layer (O(1e-2)).
HASH_STEP_GRAD_REL_TO_MAX = 1e-4
# The step's loss: a float32 sum of B per-ray squared errors vs float64: ~1e-6 relative.
HASH_STEP_LOSS_RTOL = 1e-5
# Occupancy update: decay is one float32 multiply (0.5 ulp), the max is exact.
HASH_OCC_RTOL = 1e-6
# Contracted scenes (cl/hash_march.cl HASH_CONTRACT): t and dt are near exp(s ln(far/near)) in
# float32, exp's argument up to ~10: a few ulp of the argument, relative 1e-6 of t.
HASH_CONTRACT_RTOL = 2e-6
# Contracted points: o + t d in float32 carries t's relative error times t (tests bound it by
# HASH_CONTRACT_RTOL t / half), plus the contraction's own few ulp of |y| <= 2.
HASH_CONTRACT_ATOL = 1e-6

# ============================================================================================
# Gaussian splatting (cl/splat_project.cl, cl/splat_raster.cl, clrf/splat/)
# ============================================================================================
# Compositing vs float64 (image and final transmittance): a pixel sums <= ~100 terms
# T_k alpha_k c_k, each from an exp of a quadratic form (a few ulp) and a running product of
# (1 - alpha) (one rounding per step): <= ~100 u ~ 6e-6 worst case; seen <= 4.4e-7 on PoCL and
# Intel's CPU runtime. 2e-6 is 5x that; a skipped or doubled Gaussian, a half-pixel shift or
# a wrong stopping rule moves pixels by >= 1/255 * colour ~ 1e-3. (Kernel and twin must also
# agree exactly on n_contrib: the tests compare it with equality.)
SPLAT_RASTER_ATOL = 2e-6
# The projection's outputs (mean in pixels, depth, radius, colour, opacity) vs float64: chains
# of <= ~40 float32 operations on O(1..100) numbers; seen <= 1.1e-6 relative (xy near 0 carries
# the rounding of fx x / z ~ 30 px: ~5e-6 px absolute). 5e-6 relative + 2e-5 px absolute;
# a wrong convention (pixel centre, principal point, transposed rotation) is >= 1e-2.
SPLAT_PROJECT_RTOL = 5e-6
SPLAT_PROJECT_ATOL = 2e-5
# The conic Sigma2^-1 relative to its own largest entry: inverting a 2 x 2 matrix of condition
# kappa amplifies the float32 error of Sigma2 (a few u) by kappa; the test's Gaussians (flat
# discs included, which the 0.3 px^2 dilation keeps at kappa <~ 1e2) show <= 9e-7. 5e-6.
SPLAT_CONIC_REL = 5e-6
# Gradients (kernel vs the twin's analytic backward), relative to the largest entry of each
# array: per-(pixel, Gaussian) terms summed over <= ~1000 pixels by float atomics in any
# order, then the projection's chain (~100 operations) in float32; seen <= 1.6e-6 (PoCL, Intel)
# for ordinary and stiff Gaussians alike. Stiff ones are compared relative to the larger of
# their own largest entry and that of the ordinary ones, so that an exactly-zero twin gradient
# (the rotation of an isotropic Gaussian) is checked against float32 noise of the others.
# 1e-5; a wrong sign, factor 2 or transposition is >= 1e-2.
SPLAT_GRAD_REL_TO_MAX = 1e-5
# 5,000 Gaussians on one tile, ~1,100-1,300 composited per pixel: the running transmittance
# product carries ~n u relative error (seen 2.8e-6 relative on T, 2.2e-6 absolute on rgb), the
# backward's T recovered by division drifts alike (seen <= 1.6e-6 of the largest entry).
# 2e-5 absolute and 1e-5 relative to the largest entry: still 50x below one skipped Gaussian
# (~5e-3 alpha x colour).
SPLAT_LONG_ATOL = 2e-5
SPLAT_LONG_GRAD_REL_TO_MAX = 1e-5
# The twin's analytic gradient vs its own central differences (float64, eps 1e-6): truncation
# eps^2 f''' and roundoff 1e-16 |L| / eps (|L| ~ 10) are ~1e-9 each; seen <= 3.3e-9 absolute
# on gradients up to 7. 1e-7 absolute + 1e-6 relative; a missing term (the clamp's
# derivative, the view direction's pull on the mean) is >= 1e-3.
SPLAT_FD_EPS = 1e-6
SPLAT_FD_ATOL = 1e-7
SPLAT_FD_RTOL = 1e-6
# The camera's gradient (splat.pose_opt): the float32 sum over the Gaussians of their shares of
# dL/d(R, t), each within SPLAT_GRAD_REL_TO_MAX of the largest share, compared relative to the
# sum of the shares' magnitudes (what a sum's rounding scales with).
SPLAT_CAMERA_SUM_REL = 1e-5
# The default strategy's statistics (splat_densify_stats): each step adds a float32 norm of
# two scaled products (~3 ulps) to a float32 sum of norms, rounded once more; two steps of
# norms of similar size stay within ~6 ulps (3.6e-7) of the float64 sum; 1e-6 relative.
SPLAT_STATS_RTOL = 1e-6

# The splat model's colour transform (cl/splat_exposure.cl): out = A rgb + b is 3 products
# and 3 sums of terms <= ~2 in float32: a few ulps, 1e-6 absolute + relative is ~10x that.
EXPOSURE_ATOL = 1e-6
EXPOSURE_RTOL = 1e-6
# Its dL/dP: sums over n pixels in float32 (a work-item's CHUNK pixels in order, then the
# items): error ~ sqrt(n) * 6e-8 * |terms| for terms ~ N(0, 1); 1e-5 sqrt(n) absolute + 1e-5
# relative is ~20x that. dL/drgb = A^T g is 3 products: 1e-6 absolute + 1e-5 relative.
EXPOSURE_SUM_ATOL_PER_SQRT_N = 1e-5
EXPOSURE_GRAD_RTOL = 1e-5
# Three Adam steps against the float64 twin: each update is lr * m / (sqrt(v) + eps) with m, v
# formed in float32 (relative error ~1e-7 each), so rows agree to ~lr * 1e-6.
EXPOSURE_ADAM_ATOL = 1e-6

# clrf's splat render against gsplat's PyTorch reference (tests/test_splat_gsplat_reference.py),
# both of the same arrays read back from a splat file: the reference composites in float64 with
# gsplat's rules, clrf in float32 with its own. They differ by float32 rounding and at tile
# edges, where clrf's tiles of a Gaussian end at 3 standard deviations of its major axis (the
# 3DGS paper's radius) and gsplat's box at 3.33 per axis: a pixel just past the 3-sigma square
# can still get alpha >= 1/255 in gsplat (side camera: 150 of 19,200 pixels off by more than
# 1e-4, the largest, 0.007, at tile edges). Seen 80.4-95.3 dB over five formats, two cameras,
# classic and anti-aliased (PoCL 3.1, Zen 5). 45 dB would let conventions through: gsplat's
# own 2D filter 0.3 px^2 where clrf's anti-aliased mode uses 0.1 reads 45.5 dB, the opacity
# compensation left out 48.8 dB. 65 dB is
# 15 dB under the lowest seen and above both; pixel centres moved half a pixel read 30 dB, the
# odd SH bands negated 18 dB.
GSPLAT_REF_PSNR_DB = 65.0
# `clrf export --web` (tests/test_export_web.py): directions and points the recording holds in
# float64 (the float32 poses and means convert exactly), after a normalisation, a dot product and
# a quaternion rotation: each rounds at ~1e-16 relative, so 1e-9 (of a unit vector, or of the
# scene's diagonal for a point) leaves 1e6x and still catches any wrong axis or sign (>= 1e-3).
WEB_AXIS_ATOL = 1e-9
# The same page in headless Chromium. viser's client logs its
# camera (?logCamera) with three decimals (toFixed(3)): within 5e-4 of the float64 pose the
# recording holds, plus float64 roundoff of the up-direction rotation it goes through (~1e-15).
WEB_CAMERA_LOG_ATOL = 5e-4 + 1e-9
# A pixel "shows the scene" where it differs from the background colour by more than this many
# uint8 levels in some channel: SwiftShader's blending of the last faint splat edges and the
# PNG background's sRGB handling stay within a few levels; the scene's surfaces differ by tens.
WEB_SCENE_LEVEL = 16
# A frame is not blank when at least this fraction of the canvas shows the scene: the opening
# view of the test's scene fills about half of it; a page that drew nothing (or only the
# background) has none.
WEB_SCENE_MIN_FRACTION = 0.05
# A camera move changed the frame: the mean absolute difference of the two frames, uint8
# levels over all pixels and channels; a half-turn drag of the test's scene moves it by tens of
# levels, the same frame drawn twice by 0 (SwiftShader is deterministic).
WEB_MOVED_MEAN_LEVELS = 2.0
# The bilateral grid (cl/bilateral.cl). Its slice sums 8 corners' weights (products of three
# float32 factors) times cells ~1, and out = A x + y b sums 4 such products: a few ulps of
# values <= ~3, so 2e-6 absolute + 1e-6 relative (seen 3e-7).
BILATERAL_ATOL = 2e-6
BILATERAL_RTOL = 1e-6
# dL/drgb: A^T g (3 products) plus the guidance's share, a 12-term dot product scaled by L - 1
# (up to 63): rounding ~1e-7 of the largest entry times L; 1e-5 of the largest entry (seen 1.3e-7
# at L = 3) leaves room for L = 64.
BILATERAL_GRAD_REL_TO_MAX = 1e-5
# dL/dG: a cell sums w dL/dM over its footprint's n pixels in float32, in pixel order:
# ~sqrt(n) 6e-8 |terms| for terms ~ N(0, 1); 1e-5 sqrt(n) absolute, as the exposure's sums.
BILATERAL_SUM_ATOL_PER_SQRT_N = 1e-5
# The prior's gradient: a difference of two differences of entries ~1 over n_d in float32,
# a few ulps of the cells: 1e-6 of the largest entry of weight / V times 2 / n_d (seen 1e-7).
BILATERAL_TV_REL_TO_MAX = 1e-6
# Three Adam steps of every grid against the float64 twin: as the exposure's rows.
BILATERAL_ADAM_ATOL = 1e-6
# Each ray's dL/d(origin, direction) from the grid's backward (GRID_POSE_GRAD) vs its float64
# twin: per sample, float32 corner terms (dL/dsigma from the remaining radiance, itself a
# difference of float32 sums, and the colour's), times t_k, summed over up to ~900 samples,
# then the SH direction terms and the projection over |d|. Relative to the sum of the terms'
# magnitudes (reference.render_held(magnitude=True)), a few u per term plus the sums' growth:
# 1e-6 (~17 u). A dropped sample, a wrong slope, a missing t_k, SH term or projection moves a
# ray's gradient by O(1) of its terms.
GRID_RAY_GRAD_RTOL = 1e-6
