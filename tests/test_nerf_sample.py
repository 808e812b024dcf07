"""Sampling along rays (cl/sample.cl) vs the float64 reference and hand-checkable cases."""
import numpy as np
import pyopencl.array as cla
import pytest

from clrf.nerf import ops
from clrf.references import reference_nerf as ref
from clrf.testing import tolerances as tol


def dev_arr(device, a):
    return cla.to_device(device.queue, np.ascontiguousarray(a, np.float32))


@pytest.mark.parametrize("n,K", [(0, 4), (1, 1), (7, 64), (33, 5)])
@pytest.mark.parametrize("jitter", [False, True])
def test_stratified_matches_reference(device, n, K, jitter):
    t = ops.sample_stratified(device, n, K, 2.0, 6.0, jitter, key=1234).get()
    np.testing.assert_allclose(t, ref.sample_stratified(n, K, 2.0, 6.0, jitter, 1234), rtol=0,
                               atol=tol.SAMPLE_ATOL)
    assert np.all(np.diff(t, axis=1) >= 0) and np.all((t >= 2.0) & (t <= 6.0))


def test_stratified_toy_values(device):
    t = ops.sample_stratified(device, 2, 4, 2.0, 6.0).get()
    np.testing.assert_array_equal(t, [[2.5, 3.5, 4.5, 5.5]] * 2)


def test_jitter_depends_on_key(device):
    a = ops.sample_stratified(device, 3, 8, 0.0, 1.0, True, key=1).get()
    b = ops.sample_stratified(device, 3, 8, 0.0, 1.0, True, key=2).get()
    assert not np.allclose(a, b)


def coarse(device, n, Kc, near, far, jitter=True):
    return ops.sample_stratified(device, n, Kc, near, far, jitter, key=7)


@pytest.mark.parametrize("jitter", [False, True])
def test_importance_matches_reference(device, jitter):
    n, Kc, Nf = 9, 32, 48
    tc = coarse(device, n, Kc, 2.0, 6.0)
    rng = np.random.default_rng(0)
    w = rng.exponential(size=(n, Kc)) * (rng.random((n, Kc)) < 0.5)
    w[0] = 0.0
    w[1, :] = np.nan           # NaN weights count as zero
    tf = ops.sample_importance(device, tc, dev_arr(device, w), Nf, 2.0, 6.0, jitter, key=9).get()
    w32 = w.astype(np.float32)
    expect = ref.sample_importance(tc.get(), w32, Nf, 2.0, 6.0, jitter, 9)
    # compare where the samples sit in the CDF (well conditioned), not their positions
    c_got, total = ref.importance_cdf(tc.get(), w32, 2.0, 6.0, tf)
    c_ref, _ = ref.importance_cdf(tc.get(), w32, 2.0, 6.0, expect)
    np.testing.assert_allclose(c_got, c_ref, rtol=0, atol=tol.IMPORTANCE_CDF_RTOL * total.max())
    assert np.all(np.diff(tf, axis=1) >= 0) and np.all((tf >= 2.0) & (tf <= 6.0))


def test_importance_all_zero_weights_is_uniform(device):
    """Bins around bin-centred coarse samples are the equal bins, and zero weights give equal
    masses, so the fine samples are the bin centres of Nf equal bins."""
    n, Kc, Nf = 3, 8, 16
    tc = coarse(device, n, Kc, 2.0, 6.0, jitter=False)
    tf = ops.sample_importance(device, tc, dev_arr(device, np.zeros((n, Kc))), Nf, 2.0, 6.0).get()
    np.testing.assert_allclose(tf, np.tile(2.0 + 4.0 * (np.arange(Nf) + 0.5) / Nf, (n, 1)),
                               rtol=0, atol=tol.IMPORTANCE_ATOL)


def test_importance_one_hot_weights_fill_one_bin(device):
    n, Kc, Nf = 4, 16, 64
    tc = coarse(device, n, Kc, 2.0, 6.0)
    w = np.zeros((n, Kc))
    hot = np.array([0, 5, 15, 9])
    w[np.arange(n), hot] = 1.0
    tf = ops.sample_importance(device, tc, dev_arr(device, w), Nf, 2.0, 6.0, True, 3).get()
    t = tc.get().astype(np.float64)
    edges = np.concatenate([np.full((n, 1), 2.0), 0.5 * (t[:, 1:] + t[:, :-1]),
                            np.full((n, 1), 6.0)], axis=1)
    lo, hi = edges[np.arange(n), hot], edges[np.arange(n), hot + 1]
    assert np.all((tf >= lo[:, None] - tol.SAMPLE_ATOL) & (tf <= hi[:, None] + tol.SAMPLE_ATOL))
    assert np.ptp(tf, axis=1).min() > 0.5 * (hi - lo).min()   # spread over the bin


def test_near_equals_far(device):
    n, Kc, Nf = 3, 8, 8
    tc = ops.sample_stratified(device, n, Kc, 4.0, 4.0, True, key=1)
    assert np.all(tc.get() == 4.0)
    rng = np.random.default_rng(1)
    tf = ops.sample_importance(device, tc, dev_arr(device, rng.random((n, Kc))), Nf, 4.0, 4.0,
                               True, 2)
    assert np.all(tf.get() == 4.0)
    t = ops.merge_sorted(device, tc, tf)
    sig = dev_arr(device, rng.random(n * (Kc + Nf)) * 1e3)
    rgb = dev_arr(device, rng.random((n * (Kc + Nf), 3)))
    out = ops.composite_forward(device, t, sig, rgb, 4.0, background=(1, 1, 1))
    assert np.all(out["acc"].get() == 0) and np.all(out["rgb"].get() == 1.0)


@pytest.mark.parametrize("Ka,Kb", [(1, 1), (8, 16), (5, 0)])
def test_merge_sorted(device, Ka, Kb):
    rng = np.random.default_rng(Ka)
    n = 7
    a = np.sort(rng.random((n, Ka)), axis=1)
    b = np.sort(rng.random((n, Kb)), axis=1)
    b[:, :Kb // 2] = a[:, :1] if Kb else b[:, :0]   # ties
    b = np.sort(b, axis=1)
    out = ops.merge_sorted(device, dev_arr(device, a), dev_arr(device, b)).get()
    np.testing.assert_array_equal(out, ref.merge_sorted(a.astype(np.float32), b.astype(np.float32)))


def test_ray_points(device):
    rng = np.random.default_rng(2)
    o = rng.normal(size=(5, 3))
    d = rng.normal(size=(5, 3)) * np.array([[1], [1e-20], [1e20], [1], [1]])
    t = np.sort(rng.random((5, 4)) * 3, axis=1)
    x, v = ops.ray_points(device, dev_arr(device, o), dev_arr(device, d), dev_arr(device, t))
    rx, rv = ref.ray_points(o.astype(np.float32), d.astype(np.float32), t.astype(np.float32))
    np.testing.assert_allclose(x.get(), rx, rtol=tol.RAY_POINTS_RTOL, atol=tol.RAY_POINTS_ATOL)
    np.testing.assert_allclose(v.get(), rv, rtol=tol.RAY_POINTS_RTOL, atol=tol.RAY_POINTS_ATOL)
