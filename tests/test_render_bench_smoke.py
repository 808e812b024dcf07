"""Smoke test of tools/bench.py: every benchmark spec runs at tiny sizes, nothing is timed.

The grid-render cases at these sizes check the kernel against the float64 reference before
running; here we also check forward and backward (both gradient modes) of each distinct grid
configuration the benchmarks use against clrf.references.reference, with clrf/testing/tolerances.py margins.
"""
import sys
from pathlib import Path

import numpy as np
import pyopencl.array as cla
import pytest

sys.path.insert(0, str(Path(__file__).resolve().parent.parent / "tools"))
import bench  # noqa: E402
import bench_scenes as scenes  # noqa: E402
from clrf.references import reference  # noqa: E402
from clrf.grid.render import render_backward_device, render_rays  # noqa: E402
from clrf.testing.tolerances import (DEPTH_ATOL, DEPTH_RTOL, GRAD_ATOL, GRAD_RTOL,  # noqa: E402
                                     RENDER_ATOL, RENDER_RTOL)


def _smoke_specs():
    return [s for s in bench._peak_specs() + bench.SPECS
            if not s.kind.startswith("peer.") or s.kind == "peer.numpy_ref"]


@pytest.mark.parametrize("spec", _smoke_specs(), ids=lambda s: s.name)
def test_spec_smoke(device, spec):
    class A:
        pass
    ctx = bench.Context(device, quick=True)
    rec = bench.run_spec(ctx, spec, A())
    assert "failed" not in rec, rec
    assert "skipped" not in rec, rec
    if rec.get("check") is not None:
        assert rec["check"]["ok"], rec["check"]


CONFIGS = sorted({(s.params["degree"], s.params["occupancy"], s.params["rays"])
                  for s in bench.SPECS if s.kind == "grid.render"})


@pytest.mark.parametrize("degree,occupancy,rays", CONFIGS)
@pytest.mark.parametrize("grad_mode", [0, 1])
def test_bench_configs_match_reference(device, degree, occupancy, rays, grad_mode):
    import clrf
    links, dens, sh = scenes.make_grid_rows(12, degree, occupancy if occupancy >= 1 else 0.2)
    grid = clrf.SparseGrid.from_arrays(device, links, dens, sh, scenes.BBOX)
    o, d = scenes.make_rays(rays, 100)
    dn, shd = scenes.dense_from_rows(links, dens, sh)
    ref = reference.render_forward(dn, shd, scenes.BBOX, o, d, 0.5, (1, 1, 1))
    got = render_rays(grid, o, d, 0.5, (1, 1, 1))
    np.testing.assert_allclose(got["rgb"], ref["rgb"], atol=RENDER_ATOL, rtol=RENDER_RTOL)
    np.testing.assert_allclose(got["acc"], ref["acc"], atol=RENDER_ATOL, rtol=RENDER_RTOL)
    np.testing.assert_allclose(got["depth"], ref["depth"], atol=DEPTH_ATOL, rtol=DEPTH_RTOL)

    rng = np.random.default_rng(5)
    q = device.queue
    n = o.shape[0]
    ray_in = rng.uniform(0, 1, (n, 3)).astype(np.float32)
    scale = 1.0   # gradients O(1) like grad_mode 0, so the absolute GRAD_ATOL applies as is
    if grad_mode == 1:
        g = 2.0 * scale * (ref["rgb"] - ray_in)
    else:
        g = ray_in.astype(np.float64)
    rb = reference.render_backward(dn, shd, scenes.BBOX, o, d, g, 0.5, (1, 1, 1), mask=links >= 0)
    gd = cla.zeros(q, grid.density.shape[0], np.float32)
    gs = cla.zeros(q, grid.sh.shape, np.float32)
    loss = cla.empty(q, n, np.float32)
    render_backward_device(grid, cla.to_device(q, o), cla.to_device(q, d), cla.to_device(q, ray_in),
                           0.5, (1, 1, 1), gd, gs, grad_mode=grad_mode, loss_scale=scale,
                           ray_out=loss)
    gdd, gsd = grid.rows_to_dense(gd.get(), gs.get())
    np.testing.assert_allclose(gdd, rb["density"], atol=GRAD_ATOL, rtol=GRAD_RTOL)
    np.testing.assert_allclose(gsd, rb["sh"], atol=GRAD_ATOL, rtol=GRAD_RTOL)
    if grad_mode == 1:
        np.testing.assert_allclose(loss.get(), np.sum((ref["rgb"] - ray_in) ** 2, axis=1),
                                   atol=10 * RENDER_ATOL, rtol=RENDER_RTOL)


def test_interleaved_rounds_alternate_cases(device):
    """--interleave: every case set up first, warmed up once, then each round runs every case
    once in order; the records carry one time per round."""
    from bench.framework import FACTORIES, Case, Spec
    log = []

    def make(ctx, p):
        return Case(lambda: log.append(p["tag"]), {"samples": 10})
    FACTORIES["test.fake"] = make
    try:
        specs = [Spec("fake/a", "test.fake", {"tag": "a"}), Spec("fake/b", "test.fake", {"tag": "b"}),
                 Spec("fake/skipped", "test.fake", {"tag": "s"}, requires=(("no_such_mod", "x"),))]
        recs = bench.run_interleaved(bench.Context(device, quick=False), specs, 3)
    finally:
        del FACTORIES["test.fake"]
    assert log == ["a", "b"] + ["a", "b"] * 3
    assert [r["name"] for r in recs] == ["fake/a", "fake/b", "fake/skipped"]
    for r in recs[:2]:
        assert r["time_s"]["interleaved"] and len(r["time_s"]["rounds"]) == 3
        assert r["metrics"]["samples/s"] > 0
    assert "skipped" in recs[2] and "time_s" not in recs[2]
