"""The Taichi peer of the Gaussian-splatting rasteriser (tools/peers/taichi_splat.py) against
clrf's float64 twin (clrf/references/reference_splat.py rasterize / rasterize_backward) with the
kernel tests' tolerances, on clrf's own projection and binning of a small scene and on drawn
screen-space splats (a long list on one tile, the opacity-near-one toy, no Gaussians); and the
splat benchmarks (tools/bench cases ``splat.raster.clrf`` / ``splat.raster.taichi``) in smoke
mode. Skipped with the reason when taichi is not installed (extra ``peers``: pip install
'clrf[peers]' or bash tools/setup.sh test,peers)."""
import sys
from pathlib import Path

import numpy as np
import pyopencl.array as cla
import pytest

from clrf.splat import SplatCamera, SplatRasterizer
from clrf.splat.raster import GRAD2D_NAMES
from clrf.references import reference_splat as rs
from clrf.testing import tolerances as tol

ROOT = Path(__file__).resolve().parents[1]
BG = (0.2, 0.1, 0.3)


def _taichi_splat():
    pytest.importorskip("taichi", reason="taichi is not installed (extra 'peers')")
    if str(ROOT / "tools") not in sys.path:
        sys.path.insert(0, str(ROOT / "tools"))
    from peers import taichi_splat
    return taichi_splat


def _f64(d):
    return {k: np.asarray(v, np.float64) for k, v in d.items()}


def _close_rel(got, want, rel, name):
    """max |got - want| <= rel * max |want| (per-Gaussian sums of mixed scales)."""
    scale = max(float(np.abs(want).max(initial=0.0)), 1e-30)
    err = float(np.abs(np.asarray(got, np.float64) - want).max(initial=0.0))
    assert err <= rel * scale, f"{name}: max error {err:.3g} > {rel} * {scale:.3g}"


def _lists_as_bins(lists):
    """The twin's per-tile lists as clrf's binning: (ids [P], ranges [ntiles, 2])."""
    lens = np.array([len(x) for x in lists])
    ends = np.cumsum(lens)
    ranges = np.where(lens[:, None] > 0, np.stack([ends - lens, ends], 1), 0)
    ids = np.concatenate(lists) if lens.sum() else np.zeros(0)
    return ids.astype(np.int32), ranges.astype(np.int32)


def _check_peer(ts, sp, lists, width, height, grad, atol, grad_rel):
    """Peer forward and backward on splats ``sp`` (float32) and the twin's ``lists`` vs the twin
    on the same numbers; returns the twin's forward."""
    ids, ranges = _lists_as_bins(lists)
    peer = ts.TaichiSplat(sp["xy"], sp["conic"], sp["opacity"], sp["color"], ids, ranges,
                          width, height, background=BG, grad_rgb=grad)
    want = rs.rasterize(_f64(sp), lists, width, height, BG)
    got = peer.forward()
    np.testing.assert_array_equal(got["n_contrib"], want["n_contrib"])
    np.testing.assert_allclose(got["rgb"], want["rgb"], rtol=0, atol=atol)
    np.testing.assert_allclose(got["T"], want["T"], rtol=0, atol=atol)
    ref = rs.rasterize_backward(_f64(sp), lists, want, width, height, grad, BG)
    g = peer.backward()
    for name in GRAD2D_NAMES:
        assert g[name].shape == ref[name].shape, name
        assert np.all(np.isfinite(g[name])), name
        _close_rel(g[name], ref[name], grad_rel, name)
    return want, ref


def test_peer_on_clrf_projection_matches_reference(device):
    """300 Gaussians (SH degree 3) in a 48 x 40 image (tiles 3 x 3, the last row and column
    partial): clrf projects and bins on the device (its bins equal the twin's lists), the peer
    rasterises those float32 splats; forward (n_contrib exactly) and backward vs the twin."""
    ts = _taichi_splat()
    n, width, height, degree = 300, 48, 40, 3
    rng = np.random.default_rng(11)
    g = {"means": rng.normal(0, 0.6, (n, 3)).astype(np.float32),
         "log_scales": rng.uniform(-3.0, -1.5, (n, 3)).astype(np.float32),
         "quats": rng.normal(size=(n, 4)).astype(np.float32),
         "opacity_logits": rng.uniform(-2, 2, n).astype(np.float32),
         "sh": rng.normal(0, 0.3, (n, (degree + 1) ** 2, 3)).astype(np.float32)}
    cam = SplatCamera(rs.look_at((0.3, -0.2, -3.0), (0, 0, 0)).astype(np.float32), 44.0, 46.0,
                      width / 2 - 0.5, height / 2 + 0.25, width, height, 0.1)
    r = SplatRasterizer(device, degree)
    proj = r.project(r.upload(g), cam)
    bins = r.bin(proj, cam)
    sp = {k: getattr(proj, k).get() for k in ("xy", "conic", "opacity", "color", "rect",
                                              "depth")}
    ntx, nty = cam.tiles()
    lists = rs.bin_gaussians(sp["rect"], sp["depth"], ntx, nty)
    ids, ranges = _lists_as_bins(lists)
    np.testing.assert_array_equal(bins.ids.get(), ids)
    np.testing.assert_array_equal(bins.ranges.get(), ranges)
    grad = np.random.default_rng(12).normal(size=(height, width, 3)).astype(np.float32)
    want, ref = _check_peer(ts, sp, lists, width, height, grad, tol.SPLAT_RASTER_ATOL,
                            tol.SPLAT_GRAD_REL_TO_MAX)
    # the scene is not trivial: pixels composite many Gaussians, some stop, gradients flow
    assert want["n_contrib"].max() > 20 and (want["T"] < 0.01).any() and (want["T"] > 0.5).any()
    for name in GRAD2D_NAMES:
        assert np.abs(ref[name]).max() > 0, name
    # from_clrf reads the same arrays back from the device
    peer = ts.TaichiSplat.from_clrf(proj, bins, cam, BG, grad)
    ras = r.rasterize(proj, bins, cam, BG)
    out = peer.forward()
    np.testing.assert_array_equal(out["n_contrib"], ras.n_contrib.get())
    np.testing.assert_allclose(out["rgb"], ras.rgb.get(), rtol=0, atol=tol.SPLAT_RASTER_ATOL)
    got = r.rasterize_backward(proj, bins, ras, cam, cla.to_device(device.queue, grad), BG)
    pg = peer.backward()
    for name in GRAD2D_NAMES:
        _close_rel(pg[name], got[name].get(), 2 * tol.SPLAT_GRAD_REL_TO_MAX, name)


def _drawn_splats(n, width, height, seed, opacity, sigma, margin):
    """n screen-space splats drawn directly (float32): means over the image +- margin, rotated
    anisotropic covariances of standard deviations ``sigma`` px, distinct depths."""
    rng = np.random.default_rng(seed)
    xy = np.stack([rng.uniform(-margin, width + margin, n),
                   rng.uniform(-margin, height + margin, n)], 1)
    th = rng.uniform(0, np.pi, n)
    s1, s2 = rng.uniform(*sigma, n) ** 2, rng.uniform(*sigma, n) ** 2
    c, s = np.cos(th), np.sin(th)
    a, b, cc = c * c * s1 + s * s * s2, c * s * (s1 - s2), s * s * s1 + c * c * s2
    det = a * cc - b * b
    ntx, nty = -(-width // rs.TILE), -(-height // rs.TILE)
    sp = {"xy": xy.astype(np.float32),
          "conic": np.stack([cc / det, -b / det, a / det], 1).astype(np.float32),
          "radius": (3 * np.sqrt(0.5 * (a + cc) + np.hypot(0.5 * (a - cc), b))).astype(
              np.float32),
          "depth": (1.0 + rng.permutation(n) * (5.0 / n)).astype(np.float32),
          "color": rng.uniform(0, 1, (n, 3)).astype(np.float32),
          "opacity": rng.uniform(*opacity, n).astype(np.float32)}
    sp["rect"] = rs.tile_rect(sp["xy"], sp["radius"], ntx, nty)
    return sp, rs.bin_gaussians(sp["rect"], sp["depth"], ntx, nty)


def test_peer_long_list_matches_reference():
    """3,000 faint Gaussians on the one tile of a 16 x 16 image: hundreds composited per pixel
    before it stops (the kernel's several local batches; the peer has none); the long-list
    tolerances of the kernel tests."""
    ts = _taichi_splat()
    sp, lists = _drawn_splats(3000, 16, 16, 7, opacity=(0.005, 0.012), sigma=(12.0, 24.0),
                              margin=-6.0)
    assert len(lists) == 1 and len(lists[0]) == 3000
    grad = np.random.default_rng(8).normal(size=(16, 16, 3)).astype(np.float32)
    want, _ = _check_peer(ts, sp, lists, 16, 16, grad, tol.SPLAT_LONG_ATOL,
                          tol.SPLAT_LONG_GRAD_REL_TO_MAX)
    assert want["n_contrib"].min() > 2 * rs.TILE ** 2


def test_peer_opacity_near_one_toy():
    """cl tests' toy: two opaque Gaussians on pixel (4, 4) of an 8 x 8 image; the first's alpha
    clamps to 0.99, the second would bring T to (1 - 0.99)^2 < T_MIN, so the pixel stops after
    one: n_contrib 1, T 0.01, rgb 0.99 c1 + 0.01 bg; no opacity or position gradient through
    the clamp."""
    ts = _taichi_splat()
    sp = {"xy": np.float32([[4.5, 4.5], [4.5, 4.5]]),
          "conic": np.float32([[0.5, 0.0, 0.5], [0.5, 0.0, 0.5]]),
          "color": np.float32([[1, 0, 0], [0, 1, 0]]), "opacity": np.float32([1 - 1e-6] * 2)}
    grad = np.zeros((8, 8, 3), np.float32)
    grad[4, 4] = 1.0
    peer = ts.TaichiSplat(sp["xy"], sp["conic"], sp["opacity"], sp["color"], [0, 1],
                          [[0, 2]], 8, 8, background=BG, grad_rgb=grad)
    out = peer.forward()
    assert out["n_contrib"][4, 4] == 1
    np.testing.assert_allclose(out["T"][4, 4], 0.01, rtol=0, atol=tol.TOY_ATOL)
    np.testing.assert_allclose(out["rgb"][4, 4], [0.99 + 0.01 * BG[0], 0.01 * BG[1],
                                                  0.01 * BG[2]], rtol=0, atol=tol.TOY_ATOL)
    g = peer.backward()
    assert g["opacity"][0] == 0.0 and np.all(g["xy"] == 0)
    np.testing.assert_allclose(g["color"][0], [0.99] * 3, rtol=0, atol=tol.TOY_ATOL)


def test_peer_no_gaussians():
    """No Gaussians, and Gaussians with empty lists: the background, T = 1, no contributions,
    zero gradients of the right shapes."""
    ts = _taichi_splat()
    for n in (0, 3):
        z = np.zeros((n, 3), np.float32)
        peer = ts.TaichiSplat(np.zeros((n, 2)), z, np.zeros(n), z, np.zeros(0, np.int32),
                              np.zeros((6, 2), np.int32), 33, 17, background=BG,
                              grad_rgb=np.ones((17, 33, 3)))
        out = peer.forward()
        np.testing.assert_array_equal(out["rgb"], np.broadcast_to(np.float32(BG), (17, 33, 3)))
        np.testing.assert_array_equal(out["T"], 1.0)
        np.testing.assert_array_equal(out["n_contrib"], 0)
        g = peer.backward()
        assert g["xy"].shape == (n, 2) and g["opacity"].shape == (n,)
        assert all(np.all(v == 0) for v in g.values())


def _splat_specs():
    sys.path.insert(0, str(ROOT / "tools"))
    import bench
    return bench, [s for s in bench.SPECS if s.kind in ("splat.raster", "peer.taichi_splat")]


def test_splat_bench_cases_smoke(device):
    """The splat benchmarks at their --quick sizes: both set up, the peer checked against clrf
    on identical inputs, one repetition each (nothing timed)."""
    _taichi_splat()
    bench, specs = _splat_specs()
    assert {s.kind for s in specs} == {"splat.raster", "peer.taichi_splat"}

    class A:
        pass
    for spec in specs:
        rec = bench.run_spec(bench.Context(device, quick=True), spec, A())
        assert "failed" not in rec and "skipped" not in rec, rec
        assert rec["work"]["samples"] > 0 and rec["work"]["flop"] > 0, rec["work"]
        if spec.kind == "peer.taichi_splat":
            assert rec["check"]["ok"], rec["check"]
