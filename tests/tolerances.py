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
