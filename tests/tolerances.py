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


# ============================================================================================
# NeRF (cl/encode.cl, cl/mlp.cl, cl/sample.cl, cl/composite.cl, cl/optim_adam.cl)
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
