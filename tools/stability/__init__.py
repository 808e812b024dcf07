"""Numerical-stability matrix of clrf: stiff, extreme and long cases through the public API.

Every case drives ``clrf.render_rays`` / ``clrf.render_rays_backward`` / ``clrf.training.metrics`` and
compares with the float64 reference (clrf/references/reference.py) or a closed form. Each
comparison is one row of the report: the largest absolute error, the largest relative error
(normwise: max|got - want| / max|want|), the tolerance it is held to (constants of
clrf/testing/tolerances.py, stability section), the usage
max_i |got_i - want_i| / (atol + rtol |want_i|) (<= 1 passes) and the number of non-finite
values among the outputs / gradients it covers.

    python tools/stability.py [--quick] --out DIR         # DIR/stability.md, DIR/stability.json
    python tools/stability.py --convergence --out DIR     # also DIR/convergence.csv
    python tools/plot_convergence.py DIR/convergence.csv  # error vs step and vs seconds

Cases are data: ``Case(name, group, fn, tol)``; ``fn(run)`` calls ``run.compare`` /
``run.finite`` / ``run.raises`` and ``tol`` is the default tolerance of its comparisons. Adding
a case is appending to ``CASES`` in matrix.py (tests/test_stability.py parametrises over it).
``xfail`` holds the reason when a case documents a known kernel bug (the test then expects it
to fail, strictly).

Groups: stiff, closed form, geometry, values, reduction, scale sweep (renderer and reductions);
optimiser (cl/optim.cl against the float64 twin reference.update_rows: zero, huge, tiny
gradients, eps 0..1 with state 0, long sparse runs in lockstep), regulariser (cl/grid_ops.cl
tv_grad: flat regions, step edges, missing and outside neighbours, values up to 3e38, Cauchy
sparsity at sigma 0..+-3e38, the beta prior fused into the render backward at T = 1, T -> 0
and acc = 1e-7), structure (prune to nothing, resampling of single voxels, flat
grids and values up to 3e38, batch indices at extremes).

Adam (cl/optim.cl OPT_MODE 2) is held to its formula by tests/test_nerf_model.py; it has no
extreme-value case here yet.

Layout: framework.py (rows, tolerances, Run, shared building blocks), cases_render.py,
cases_train.py, cases_nerf.py (the case functions by group), matrix.py (CASES, run_all),
report.py (Markdown / JSON), runner.py (command line); tools/stability.py is the entry script.
"""
from .framework import Case, Run, Tol, run_case
from .matrix import CASES, run_all
from .runner import main

__all__ = ["CASES", "Case", "Run", "Tol", "main", "run_all", "run_case"]
