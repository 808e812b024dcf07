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
from clrf.render import T_STOP  # noqa: E402

CLOSED_FORM_ATOL = T_STOP + 1e-6

# Camera rays are returned in float32 (the kernels' input type): components of size <= ~10 carry
# a rounding error <= 10 * 6e-8 = 6e-7, so 2e-6 absolute; a convention error (half-pixel shift,
# flipped axis) is >= 1e-2 on the toy cameras the tests use.
CAMERA_ATOL = 2e-6
# Undistortion by fixed-point iteration stops at 1e-12 in float64; 1e-6 (normalised units, i.e.
# ~1e-3 px at f = 1000) is the accuracy the data layer promises.
UNDISTORT_ATOL = 1e-6
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
# sum of N <= 300 terms, each T_k alpha_k with ~3u error (expm1, exp of the Kahan log-T, product):
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
