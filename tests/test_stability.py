"""Numerical stability: the whole case matrix of tools/stability/ at quick sizes.

One test per case. A case passes when every comparison it makes is within its documented
tolerance (clrf/testing/tolerances.py, stability section) and no output or gradient is non-finite.
Cases that document a known kernel bug carry ``xfail`` (strict: they must keep failing, for the
stated reason, until the kernel is fixed; a crash is never an expected failure).
"""
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


sys.path.insert(0, str(ROOT / "tools"))
import stability as stab  # noqa: E402  (the package tools/stability/)


class StabilityFailure(AssertionError):
    """A comparison outside its tolerance, or non-finite values (the expected failure type)."""


def _params():
    for c in stab.CASES:
        marks = [pytest.mark.xfail(strict=True, raises=StabilityFailure, reason=c.xfail)] \
            if c.xfail else []
        yield pytest.param(c, id=c.name, marks=marks)


def _describe(rows):
    return "\n".join(f"  {r.quantity}: max abs {r.max_abs:.3g}, max rel {r.max_rel:.3g}, "
                     f"usage {r.usage:.3g} of {r.tol}, non-finite {r.nonfinite}; {r.note}"
                     for r in rows)


@pytest.mark.parametrize("case", list(_params()))
def test_stability_case(device, case):
    rows = stab.run_case(case, device, quick=True)
    crashed = [r for r in rows if r.quantity in ("exception", "no checks")]
    if crashed:
        raise RuntimeError(f"{case.name} did not run:\n{_describe(crashed)}")
    bad = [r for r in rows if not r.passed]
    if bad:
        raise StabilityFailure(f"{case.name}: {len(bad)} of {len(rows)} checks failed:\n"
                               f"{_describe(bad)}")
    assert sum(r.nonfinite for r in rows) == 0


# The grid renderer's cases that the GPU shape (per-corner colours and colour gradients,
# SH_PER_CORNER, with and without compensated sums) could get wrong in its own way.
GPU_SHAPE_CASES = ("long ray fwd+bwd", "very long ray acc/rgb/grads", "SH coefficients 1e20",
                   "SH degree 3 at the poles", "stiff sigma*delta=1e+08", "fully pruned grid")


_GPU_SHAPE_PARAMS = [c for c in _params() if c.values[0].name in GPU_SHAPE_CASES]
assert len(_GPU_SHAPE_PARAMS) == len(GPU_SHAPE_CASES), "a GPU_SHAPE_CASES name is not a case"


@pytest.mark.parametrize("case", _GPU_SHAPE_PARAMS)
def test_stability_case_gpu_shape(device_gpu_path, case):
    test_stability_case(device_gpu_path, case)


def test_case_names_unique():
    names = [c.name for c in stab.CASES]
    assert len(names) == len(set(names))


def test_compare_can_fail(device):
    """The comparison helper itself: an error just above atol + rtol |want| fails, NaN fails."""
    case = stab.Case("self-check", "meta", lambda run: None, stab.Tol(1e-6, 0.0, "t"))
    run = stab.Run(device, True, case)
    run.compare("inside", [1.0 + 0.9e-6], [1.0])
    run.compare("outside", [1.0 + 1.1e-6], [1.0])
    run.compare("nan", [float("nan")], [1.0])
    run.finite("inf", [1.0, float("inf")])
    run.raises("no raise", lambda: None, "x")
    assert [r.passed for r in run.rows] == [True, False, False, False, False]
    assert run.rows[2].nonfinite == 1 and run.rows[3].nonfinite == 1
