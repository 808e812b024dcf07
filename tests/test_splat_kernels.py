"""Gaussian splatting kernels (cl/splat_project.cl, cl/splat_raster.cl) against their float64
twin (clrf/references/reference_splat.py): projection and its backward, the binning's per-tile
lists, the tile rasteriser forward and backward, the whole chain, the twin's own gradient
against central differences, and the stiff cases (degenerate, huge and tiny covariances,
Gaussians behind or across the near plane, opacity near 1, 5,000 Gaussians on one tile, no
Gaussians, image sizes that are not multiples of the tile)."""
import numpy as np
import pyopencl.array as cla
import pytest

from clrf.runtime.buildlog import diagnostics
from clrf.runtime.programs import build, build_log
from clrf.splat import raster as sr
from clrf.splat import Projected, SplatCamera, SplatRasterizer
from clrf.references import reference_splat as rs
from clrf.testing import tolerances as tol

BG = (0.2, 0.1, 0.3)
PARAMS = ("means", "log_scales", "quats", "opacity_logits", "sh")


# ---- helpers ----------------------------------------------------------------------------------
def _gaussians(n, degree, seed, spread=0.6, log_scale=(-3.0, -1.2), logit=(-2.0, 2.0)):
    """n random 3D Gaussians about the origin, float32."""
    rng = np.random.default_rng(seed)
    return {"means": rng.normal(0, spread, (n, 3)).astype(np.float32),
            "log_scales": rng.uniform(*log_scale, (n, 3)).astype(np.float32),
            "quats": rng.normal(size=(n, 4)).astype(np.float32),
            "opacity_logits": rng.uniform(*logit, n).astype(np.float32),
            "sh": rng.normal(0, 0.3, (n, (degree + 1) ** 2, 3)).astype(np.float32)}


def _camera(width=33, height=17, eye=(0.3, -0.2, -3.0), f=(30.0, 32.0), near=0.1):
    """(SplatCamera, the twin's camera dict with the same float32 numbers)."""
    cam = SplatCamera(rs.look_at(eye, (0, 0, 0)).astype(np.float32), f[0], f[1],
                      width / 2 - 0.5, height / 2 + 0.25, width, height, near)
    ref = {"viewmat": cam.viewmat, "fx": f[0], "fy": f[1], "cx": cam.cx, "cy": cam.cy,
           "width": width, "height": height, "near": near}
    return cam, ref


def _f64(d):
    return {k: np.asarray(v, np.float64) for k, v in d.items()}


def _close_rel(got, want, rel, name="", scale=None):
    """max |got - want| <= rel * scale, by default scale = max |want| (gradients and outputs of
    mixed scales)."""
    if scale is None:
        scale = max(float(np.abs(want).max(initial=0.0)), 1e-30)
    err = float(np.abs(np.asarray(got, np.float64) - want).max(initial=0.0))
    assert err <= rel * scale, f"{name}: max error {err:.3g} > {rel} * {scale:.3g}"


def _splats(n, width, height, seed, opacity=(0.05, 0.95), sigma=(0.7, 6.0), margin=4.0,
            tile=rs.TILE):
    """n screen-space splats (the rasteriser's inputs) as float32 host arrays, drawn directly:
    means over the image +- margin, rotated anisotropic covariances, distinct depths."""
    rng = np.random.default_rng(seed)
    xy = np.stack([rng.uniform(-margin, width + margin, n),
                   rng.uniform(-margin, height + margin, n)], 1)
    th = rng.uniform(0, np.pi, n)
    s1, s2 = rng.uniform(*sigma, n), rng.uniform(*sigma, n)
    c, s = np.cos(th), np.sin(th)
    a = c * c * s1 ** 2 + s * s * s2 ** 2
    b = c * s * (s1 ** 2 - s2 ** 2)
    cc = s * s * s1 ** 2 + c * c * s2 ** 2
    det = a * cc - b * b
    ntx, nty = -(-width // tile), -(-height // tile)
    out = {"xy": xy.astype(np.float32),
           "conic": np.stack([cc / det, -b / det, a / det], 1).astype(np.float32),
           "radius": (3 * np.sqrt(0.5 * (a + cc) + np.hypot(0.5 * (a - cc), b))).astype(
               np.float32),
           "depth": (1.0 + rng.permutation(n) * (5.0 / max(n, 1))).astype(np.float32),
           "color": rng.uniform(0, 1, (n, 3)).astype(np.float32),
           "opacity": rng.uniform(*opacity, n).astype(np.float32)}
    out["rect"] = rs.tile_rect(out["xy"], out["radius"], ntx, nty, tile).astype(np.int32)
    return out


def _upload_splats(device, sp):
    q = device.queue
    return Projected(len(sp["depth"]), *(cla.to_device(q, np.ascontiguousarray(sp[k]))
                                         for k in ("xy", "conic", "radius", "depth", "color",
                                                   "opacity", "rect")))


def _raster_both(device, sp, width, height, bg=BG, shape=None):
    """Kernel (bins, raster) and twin (lists, forward) of splats ``sp``, with the rasteriser's
    ``shape`` (None: the device's default)."""
    r = SplatRasterizer(device, 0, shape=shape)
    cam, _ = _camera(width, height)
    proj = _upload_splats(device, sp)
    bins = r.bin(proj, cam)
    ras = r.rasterize(proj, bins, cam, bg)
    ntx, nty = cam.tiles()
    lists = rs.bin_gaussians(sp["rect"], sp["depth"], ntx, nty)
    want = rs.rasterize(_f64(sp), lists, width, height, bg)
    return r, cam, proj, bins, ras, lists, want


def _assert_raster(ras, want, atol=tol.SPLAT_RASTER_ATOL):
    np.testing.assert_array_equal(ras.n_contrib.get(), want["n_contrib"])
    np.testing.assert_allclose(ras.rgb.get(), want["rgb"], rtol=0, atol=atol)
    np.testing.assert_allclose(ras.T.get(), want["T"], rtol=0, atol=atol)


# ---- build and constants ----------------------------------------------------------------------
def test_splat_constants_match_reference():
    """The kernels' defines and the twin use the same float32 numbers."""
    d = sr.defines(3)
    for name in ("ALPHA_MAX", "ALPHA_MIN", "T_MIN", "COV_DILATION", "FRUSTUM_GUARD",
                 "SIGMA_RADIUS"):
        assert float(np.float32(d[name])) == getattr(rs, name), name
    assert d["TILE"] == rs.TILE


@pytest.mark.parametrize("degree", [0, 1, 2, 3])
def test_splat_programs_build_without_diagnostics(device, degree):
    for source in ("splat_project.cl", "splat_raster.cl"):
        prg = build(device, source, sr.defines(degree))
        found = diagnostics(build_log(prg.cl_program, device))
        assert found == [], f"{source}:\n" + "\n".join(x.text for x in found)


# ---- projection -------------------------------------------------------------------------------
def _stiff_gaussians(degree, seed=3):
    """Ordinary Gaussians plus the stiff ones, each with a comment on what it exercises."""
    g = _gaussians(24, degree, seed)
    extra = [  # (mean, log_scales, quat)
        ((0.0, 0.0, -6.0), (-1.5, -1.5, -1.5), (1, 0, 0, 0)),    # behind the camera (z < 0)
        ((0.3, -0.2, -2.95), (-2.0, -2.0, -2.0), (1, 0, 0, 0)),  # between camera and near plane
        ((0.3, -0.2, -2.85), (-0.5, -0.5, -0.5), (1, 0, 0, 0)),  # just past near, reaching over it
        ((0.2, 0.1, 0.0), (-2.0, -2.0, -2.0), (0, 0, 0, 0)),     # zero quaternion: culled
        ((0.0, 0.2, 0.0), (-30.0, -2.0, -2.0), (0.9, 0.1, 0.3, 0.2)),   # zero-volume disc
        ((0.1, 0.0, 0.2), (-30.0, -30.0, -30.0), (1, 0, 0, 0)),  # a point: only the dilation
        ((0.0, 0.0, 0.5), (3.0, 3.0, 2.0), (0.6, 0.3, 0.1, 0.7)),  # huge, covers every tile
        ((4.0, 0.0, 0.0), (-1.0, -2.0, -1.5), (1, 0, 0, 0)),     # x/z beyond 1.3 tan: clamped
        ((0.0, -3.0, 0.5), (-0.5, -1.0, -0.5), (0.5, 0.5, 0.5, 0.5)),   # y/z clamped
    ]
    for k, (m, ls, q) in enumerate(extra):
        g["means"] = np.concatenate([g["means"], np.float32([m])])
        g["log_scales"] = np.concatenate([g["log_scales"], np.float32([ls])])
        g["quats"] = np.concatenate([g["quats"], np.float32([q])])
    n = len(g["means"])
    rng = np.random.default_rng(seed + 1)
    g["opacity_logits"] = rng.uniform(-2, 2, n).astype(np.float32)
    g["sh"] = rng.normal(0, 0.3, (n, (degree + 1) ** 2, 3)).astype(np.float32)
    return g


@pytest.mark.parametrize("degree", [0, 1, 2, 3])
def test_splat_project_matches_reference(device, degree):
    """splat_project vs the twin on ordinary and stiff Gaussians: the same ones culled, splats
    within float32 error, and the tile rectangles exactly those of the kernel's own xy and
    radius."""
    g = _stiff_gaussians(degree)
    cam, rcam = _camera()
    r = SplatRasterizer(device, degree)
    proj = r.project(r.upload(g), cam)
    want = rs.project(_f64(g), rcam)
    radius = proj.radius.get()
    np.testing.assert_array_equal(radius > 0, want["visible"])
    assert not want["visible"][[24, 25, 27]].any() and want["visible"][[26, 28, 29, 30, 31]].all()
    assert want["rect"][30].tolist() == [0, 0, 3, 2]          # the huge one covers every tile
    vis = want["visible"]
    for name in ("xy", "depth", "color", "opacity", "radius"):
        got = getattr(proj, name).get()
        assert np.all(np.isfinite(got)), name
        np.testing.assert_allclose(got[vis], want[name][vis], rtol=tol.SPLAT_PROJECT_RTOL,
                                   atol=tol.SPLAT_PROJECT_ATOL, err_msg=name)
        assert np.all(got[~vis] == 0), name
    conic = proj.conic.get()
    scale = np.abs(want["conic"]).max(1, keepdims=True)
    rel_err = float((np.abs(conic - want["conic"])[vis] / scale[vis]).max())
    assert rel_err <= tol.SPLAT_CONIC_REL, f"conic: {rel_err:.3g} of its largest entry"
    xy, rad = proj.xy.get(), radius
    ntx, nty = cam.tiles()
    np.testing.assert_array_equal(proj.rect.get(), rs.tile_rect(xy, rad, ntx, nty))


@pytest.mark.parametrize("degree", [1, 3])
def test_splat_project_backward_matches_reference(device, degree):
    """splat_project_backward vs the twin's analytic chain for random screen-space gradients,
    stiff Gaussians included (culled ones get zeros)."""
    g = _stiff_gaussians(degree, seed=5)
    n = len(g["means"])
    rng = np.random.default_rng(6)
    g2d = {"xy": rng.normal(size=(n, 2)), "conic": rng.normal(size=(n, 3)) * 10.0,
           "color": rng.normal(size=(n, 3)), "opacity": rng.normal(size=n)}
    g2d = {k: v.astype(np.float32) for k, v in g2d.items()}
    cam, rcam = _camera()
    r = SplatRasterizer(device, degree)
    params = r.upload(g)
    got = r.project_backward(params, cam, {k: cla.to_device(device.queue, v)
                                           for k, v in g2d.items()})
    want = rs.project_backward(_f64(g), rcam, _f64(g2d))
    vis = rs.project(_f64(g), rcam)["visible"]
    ordinary = np.arange(n) < 24
    for name in PARAMS:
        out = got[name].get()
        assert np.all(np.isfinite(out)), name
        assert np.all(out[~vis] == 0), name
        # the ordinary Gaussians relative to their largest entry, each stiff one (degenerate,
        # clamped, near the near plane) relative to the larger of its own and that entry
        # (tolerances.py SPLAT_GRAD_REL_TO_MAX)
        _close_rel(out[ordinary], want[name][ordinary], tol.SPLAT_GRAD_REL_TO_MAX, name)
        for i in np.flatnonzero(vis & ~ordinary):
            scale = max(np.abs(want[name][i]).max(), np.abs(want[name][ordinary]).max())
            _close_rel(out[i], want[name][i], tol.SPLAT_GRAD_REL_TO_MAX, f"{name}[{i}]", scale)


# ---- binning ----------------------------------------------------------------------------------
@pytest.mark.parametrize("shape", sr.SHAPES)
@pytest.mark.parametrize("n,width,height", [(1, 16, 16), (40, 33, 17), (300, 100, 70)])
def test_splat_binning_matches_reference(device, n, width, height, shape):
    """Ids and tile ranges vs the twin's per-tile lists (front to back; equal depths keep
    ascending ids: both sorts are stable); the pair sort's keys (shape "group")."""
    sp = _splats(n, width, height, seed=n)
    sp["depth"][: n // 3] = np.float32(2.5)           # ties
    r = SplatRasterizer(device, 0, shape=shape)
    cam, _ = _camera(width, height)
    bins = r.bin(_upload_splats(device, sp), cam)
    ntx, nty = cam.tiles()
    lists = rs.bin_gaussians(sp["rect"], sp["depth"], ntx, nty)
    lens = np.array([len(x) for x in lists])
    assert bins.n_pairs == lens.sum() > 0
    ids = bins.ids.get()
    np.testing.assert_array_equal(ids, np.concatenate(lists))
    if shape == "group":
        keys = bins.keys.get()
        tile_of = np.repeat(np.arange(ntx * nty), lens)
        np.testing.assert_array_equal(keys >> np.uint64(32), tile_of)
        np.testing.assert_array_equal((keys & np.uint64(0xFFFFFFFF)).astype(np.uint32),
                                      sp["depth"][ids].view(np.uint32))
    ranges = bins.ranges.get()
    ends = np.cumsum(lens)
    want = np.where(lens[:, None] > 0, np.stack([ends - lens, ends], 1), 0)
    np.testing.assert_array_equal(ranges, want)


@pytest.mark.parametrize("cells", [None, 2 * 7 * 5])
def test_splat_rows_binning_in_many_chunks(device, monkeypatch, cells):
    """The rows shape's binning cuts the depth order into chunks (a work-item each): in 60
    chunks of 5 Gaussians (or 2 of 150 where the (chunk, tile) counters are capped at 2 x 35
    tiles), runs of equal depths and tiles cross chunk boundaries; ids and ranges vs the
    twin's lists."""
    from clrf.runtime import sort
    monkeypatch.setattr(sort, "MIN_CHUNK", 4)
    if cells is not None:
        monkeypatch.setattr(sr, "CHUNK_CELLS", cells)
    n, width, height = 300, 100, 70
    assert sort.chunking(n, 64 if cells is None else 2) == ((5, 60) if cells is None else (150, 2))
    sp = _splats(n, width, height, seed=11)
    sp["depth"][::3] = np.float32(2.5)
    r = SplatRasterizer(device, 0, shape="rows")
    cam, _ = _camera(width, height)
    bins = r.bin(_upload_splats(device, sp), cam)
    ntx, nty = cam.tiles()
    assert ntx * nty == 35
    lists = rs.bin_gaussians(sp["rect"], sp["depth"], ntx, nty)
    lens = np.array([len(x) for x in lists])
    np.testing.assert_array_equal(bins.ids.get(), np.concatenate(lists))
    ends = np.cumsum(lens)
    want = np.where(lens[:, None] > 0, np.stack([ends - lens, ends], 1), 0)
    np.testing.assert_array_equal(bins.ranges.get(), want)


# ---- rasteriser ------------------------------------------------------------------------------
@pytest.mark.parametrize("n,width,height", [(1, 1, 1), (12, 33, 17), (60, 32, 32),
                                            (150, 17, 40)])
@pytest.mark.parametrize("shape", sr.SHAPES)
def test_splat_rasterize_matches_reference(device, shape, n, width, height):
    """rgb, final transmittance and n_contrib vs the twin, awkward sizes included."""
    sp = _splats(n, width, height, seed=100 + n)
    *_, ras, _, want = _raster_both(device, sp, width, height, shape=shape)
    _assert_raster(ras, want)
    if n > 1:
        assert want["n_contrib"].max() > 1 and (want["T"] < 1).any()


@pytest.mark.parametrize("n,width,height", [(12, 33, 17), (60, 32, 32)])
@pytest.mark.parametrize("shape", sr.SHAPES)
def test_splat_rasterize_backward_matches_reference(device, shape, n, width, height):
    """dL/d(xy, conic, opacity, color) vs the twin's analytic backward."""
    sp = _splats(n, width, height, seed=200 + n)
    r, cam, proj, bins, ras, lists, want = _raster_both(device, sp, width, height, shape=shape)
    _assert_raster(ras, want)
    grad = np.random.default_rng(n).normal(size=(height, width, 3)).astype(np.float32)
    got = r.rasterize_backward(proj, bins, ras, cam, cla.to_device(device.queue, grad), BG)
    ref = rs.rasterize_backward(_f64(sp), lists, want, width, height, grad, BG)
    for name in sr.GRAD2D_NAMES:
        _close_rel(got[name].get(), ref[name], tol.SPLAT_GRAD_REL_TO_MAX, name)
        assert np.abs(ref[name]).max() > 0, name


@pytest.mark.parametrize("copies", [1, 3, 7])
def test_splat_rows_backward_copies_match_reference_and_repeat(device, copies):
    """The rows shape's backward adds each work-item's tiles into a copy of its own and sums
    the copies afterwards (no atomics): any number of copies gives the twin's gradients, and a
    second run gives the same bits."""
    width, height, n = 41, 27, 90
    sp = _splats(n, width, height, seed=520 + copies, tile=8)
    r = SplatRasterizer(device, 0, tile=8, shape="rows")
    r.backward_copies = lambda: copies
    cam, _ = _camera(width, height)
    proj = _upload_splats(device, sp)
    bins = r.bin(proj, cam)
    assert cam.tiles(8)[0] * cam.tiles(8)[1] > copies   # every copy holds tiles
    ras = r.rasterize(proj, bins, cam, BG)
    lists = rs.bin_gaussians(sp["rect"], sp["depth"], *cam.tiles(8))
    want = rs.rasterize(_f64(sp), lists, width, height, BG, tile=8)
    grad = np.random.default_rng(copies).normal(size=(height, width, 3)).astype(np.float32)
    g_dev = cla.to_device(device.queue, grad)
    ref = rs.rasterize_backward(_f64(sp), lists, want, width, height, grad, BG, tile=8)
    first = r.rasterize_backward(proj, bins, ras, cam, g_dev, BG, absgrad=True)
    again = r.rasterize_backward(proj, bins, ras, cam, g_dev, BG, absgrad=True)
    for name in sr.GRAD2D_NAMES + ("xy_abs",):
        _close_rel(first[name].get(), ref[name], tol.SPLAT_GRAD_REL_TO_MAX, name)
        assert np.abs(ref[name]).max() > 0, name
        np.testing.assert_array_equal(first[name].get(), again[name].get(), err_msg=name)


@pytest.mark.parametrize("shape,tile", [("group", 16), ("rows", 16), ("rows", 8)])
def test_splat_depth_and_absgrad_match_reference(device, shape, tile):
    """The render record's depth (RENDER_DEPTH: sum_k T_k alpha_k z_k, in the forward's own
    pass) and the absolute screen gradients (ABSGRAD: |dL/dxy| per pixel, summed) vs the twin;
    the variant builds give the plain build's image and gradients."""
    width, height, n = 37, 29, 70
    sp = _splats(n, width, height, seed=410 + tile, tile=tile)
    r = SplatRasterizer(device, 0, tile=tile, shape=shape)
    cam, _ = _camera(width, height)
    proj = _upload_splats(device, sp)
    bins = r.bin(proj, cam)
    ras = r.rasterize(proj, bins, cam, BG, depth=True)
    plain = r.rasterize(proj, bins, cam, BG)
    assert plain.depth is None
    ntx, nty = cam.tiles(tile)
    lists = rs.bin_gaussians(sp["rect"], sp["depth"], ntx, nty)
    want = rs.rasterize(_f64(sp), lists, width, height, BG, tile=tile)
    _assert_raster(ras, want)
    np.testing.assert_array_equal(ras.rgb.get(), plain.rgb.get())
    _close_rel(ras.depth.get(), want["depth"], tol.SPLAT_RASTER_ATOL, "depth")
    assert want["depth"].max() > 1.0
    grad = np.random.default_rng(tile).normal(size=(height, width, 3)).astype(np.float32)
    g_dev = cla.to_device(device.queue, grad)
    got = r.rasterize_backward(proj, bins, ras, cam, g_dev, BG, absgrad=True)
    base = r.rasterize_backward(proj, bins, plain, cam, g_dev, BG)
    ref = rs.rasterize_backward(_f64(sp), lists, want, width, height, grad, BG, tile=tile)
    for name in sr.GRAD2D_NAMES + ("xy_abs",):
        _close_rel(got[name].get(), ref[name], tol.SPLAT_GRAD_REL_TO_MAX, name)
    for name in sr.GRAD2D_NAMES:
        _close_rel(got[name].get(), base[name].get(), tol.SPLAT_GRAD_REL_TO_MAX, name)
    # opposite pixels' terms cancel in xy, not in xy_abs
    assert np.all(ref["xy_abs"] >= np.abs(ref["xy"]) - 1e-12)
    assert np.sum(ref["xy_abs"]) > 1.5 * np.sum(np.abs(ref["xy"]))
    assert "xy_abs" not in base


@pytest.mark.parametrize("shape", sr.SHAPES)
def test_splat_thin_faint_splats_skip_nothing_they_reach(device, shape):
    """Needles (sigma 0.4 by 14 px at any angle) and faint splats (opacity near 1/255, whose
    ellipse where alpha reaches ALPHA_MIN is far inside the 3-sigma square their tiles come
    from): the CPU shape drops list entries whose ellipse misses the tile's columns and rows
    whose power cannot reach the threshold before the exp; the image, the entries each pixel
    used and the gradients must still be the twin's."""
    width, height, n = 48, 40, 90
    sp = _splats(n, width, height, seed=77, opacity=(0.0045, 0.9), sigma=(0.4, 14.0))
    r, cam, proj, bins, ras, lists, want = _raster_both(device, sp, width, height, shape=shape)
    _assert_raster(ras, want)
    # many listed entries reach no pixel of their tile (brute force): the case the skip is for
    ntx = cam.tiles()[0]
    ys, xs = np.mgrid[0:height, 0:width] + 0.5
    unreached = 0
    for t, ids in enumerate(lists):
        x0, y0 = (t % ntx) * rs.TILE, (t // ntx) * rs.TILE
        px = xs[y0:y0 + rs.TILE, x0:x0 + rs.TILE].ravel()
        py = ys[y0:y0 + rs.TILE, x0:x0 + rs.TILE].ravel()
        for g in ids:
            A, B, C = sp["conic"][g].astype(np.float64)
            dx, dy = sp["xy"][g, 0] - px, sp["xy"][g, 1] - py
            power = -0.5 * (A * dx * dx + C * dy * dy) - B * dx * dy
            unreached += not np.any(sp["opacity"][g] * np.exp(power) >= sr.ALPHA_MIN)
    assert unreached > 0.2 * bins.n_pairs, (unreached, bins.n_pairs)
    grad = np.random.default_rng(78).normal(size=(height, width, 3)).astype(np.float32)
    got = r.rasterize_backward(proj, bins, ras, cam, cla.to_device(device.queue, grad), BG)
    ref = rs.rasterize_backward(_f64(sp), lists, want, width, height, grad, BG)
    for name in sr.GRAD2D_NAMES:
        _close_rel(got[name].get(), ref[name], tol.SPLAT_GRAD_REL_TO_MAX, name)


@pytest.mark.parametrize("tile", [4, 8])
def test_splat_rows_shape_with_small_tiles(device, tile):
    """The CPU shape with 4- and 8-pixel tiles (float4 / float8 rows), forward and backward
    vs the twin binned with the same tiles."""
    width, height, n = 29, 19, 80
    sp = _splats(n, width, height, seed=300 + tile, tile=tile)
    r = SplatRasterizer(device, 0, tile=tile, shape="rows")
    cam, _ = _camera(width, height)
    proj = _upload_splats(device, sp)
    bins = r.bin(proj, cam)
    ras = r.rasterize(proj, bins, cam, BG)
    ntx, nty = cam.tiles(tile)
    lists = rs.bin_gaussians(sp["rect"], sp["depth"], ntx, nty)
    want = rs.rasterize(_f64(sp), lists, width, height, BG, tile=tile)
    _assert_raster(ras, want)
    grad = np.random.default_rng(tile).normal(size=(height, width, 3)).astype(np.float32)
    got = r.rasterize_backward(proj, bins, ras, cam, cla.to_device(device.queue, grad), BG)
    ref = rs.rasterize_backward(_f64(sp), lists, want, width, height, grad, BG, tile=tile)
    for name in sr.GRAD2D_NAMES:
        _close_rel(got[name].get(), ref[name], tol.SPLAT_GRAD_REL_TO_MAX, name)


def test_splat_rows_skip_only_unreachable_rows():
    """The CPU shape skips a row when the Gaussian's largest power on it, -dy^2 det / (2A),
    is below log(ALPHA_MIN / o): checked here on the formula, in float64, for random conics
    and rows, against the brute-force maximum over a fine sweep of x (a row the kernel skips
    has no x where alpha reaches ALPHA_MIN)."""
    rng = np.random.default_rng(5)
    for _ in range(200):
        s1, s2, th = rng.uniform(0.3, 8), rng.uniform(0.3, 8), rng.uniform(0, np.pi)
        c, s = np.cos(th), np.sin(th)
        cov = np.array([[c * c * s1 ** 2 + s * s * s2 ** 2, c * s * (s1 ** 2 - s2 ** 2)],
                        [c * s * (s1 ** 2 - s2 ** 2), s * s * s1 ** 2 + c * c * s2 ** 2]])
        A, B, C = np.linalg.inv(cov)[[0, 0, 1], [0, 1, 1]]
        dy = rng.uniform(-40, 40)
        pmax = -0.5 * dy * dy * (A * C - B * B) / A
        reach = 50 + 2 * abs(B / A * dy)       # wider than the argmax, -B dy / A
        dx = np.linspace(-reach, reach, 400001)
        brute = np.max(-0.5 * (A * dx * dx + C * dy * dy) - B * dx * dy)
        assert brute <= pmax + 1e-9
        assert brute >= pmax - 1e-3 * (1 + abs(pmax))


@pytest.mark.parametrize("shape", sr.SHAPES)
def test_splat_five_thousand_on_one_tile(device, shape):
    """5,000 Gaussians all on the one tile of a 16 x 16 image, faint (alpha just above 1/255),
    so that about 1,800 are composited per pixel over several local batches before the pixels
    stop; forward and backward vs the twin."""
    n, w, h = 5000, 16, 16
    sp = _splats(n, w, h, seed=7, opacity=(0.005, 0.012), sigma=(12.0, 24.0), margin=-6.0)
    assert np.all(sp["rect"] == [0, 0, 1, 1])
    r, cam, proj, bins, ras, lists, want = _raster_both(device, sp, w, h, shape=shape)
    assert bins.n_pairs == n
    assert want["n_contrib"].min() > 2 * rs.TILE ** 2 and (want["n_contrib"] < n).all()
    _assert_raster(ras, want, tol.SPLAT_LONG_ATOL)
    grad = np.random.default_rng(8).normal(size=(h, w, 3)).astype(np.float32)
    got = r.rasterize_backward(proj, bins, ras, cam, cla.to_device(device.queue, grad), BG)
    ref = rs.rasterize_backward(_f64(sp), lists, want, w, h, grad, BG)
    for name in sr.GRAD2D_NAMES:
        out = got[name].get()
        assert np.all(np.isfinite(out)), name
        _close_rel(out, ref[name], tol.SPLAT_LONG_GRAD_REL_TO_MAX, name)


@pytest.mark.parametrize("shape", sr.SHAPES)
def test_splat_opacity_near_one_toy(device, shape):
    """Two opaque Gaussians (o = 1 - 1e-6) centred on pixel (4, 4) of an 8 x 8 image, colours
    c1 = (1, 0, 0) in front and c2 = (0, 1, 0). At that pixel alpha clamps to 0.99: after the
    first T = 0.01, and the second would leave T = 1e-4 (in float32 (1 - 0.99)^2 = 9.99998e-5)
    < T_MIN, so the pixel stops: n_contrib = 1, T = 0.01, rgb = 0.99 c1 + 0.01 bg. The clamped
    alpha passes no gradient to the opacity there."""
    sp = {"xy": np.float32([[4.5, 4.5], [4.5, 4.5]]),
          "conic": np.float32([[0.5, 0.0, 0.5], [0.5, 0.0, 0.5]]),
          "radius": np.float32([4.3, 4.3]), "depth": np.float32([1.0, 2.0]),
          "color": np.float32([[1, 0, 0], [0, 1, 0]]),
          "opacity": np.float32([1 - 1e-6, 1 - 1e-6])}
    sp["rect"] = rs.tile_rect(sp["xy"], sp["radius"], 1, 1).astype(np.int32)
    r, cam, proj, bins, ras, lists, want = _raster_both(device, sp, 8, 8, shape=shape)
    _assert_raster(ras, want)
    assert ras.n_contrib.get()[4, 4] == 1
    np.testing.assert_allclose(ras.T.get()[4, 4], 0.01, rtol=0, atol=tol.TOY_ATOL)
    np.testing.assert_allclose(ras.rgb.get()[4, 4], [0.99 + 0.01 * BG[0], 0.01 * BG[1],
                                                     0.01 * BG[2]], rtol=0, atol=tol.TOY_ATOL)
    grad = np.zeros((8, 8, 3), np.float32)
    grad[4, 4] = 1.0
    got = r.rasterize_backward(proj, bins, ras, cam, cla.to_device(device.queue, grad), BG)
    assert got["opacity"].get()[0] == 0.0 and np.all(got["xy"].get() == 0)
    np.testing.assert_allclose(got["color"].get()[0], [0.99] * 3, rtol=0, atol=tol.TOY_ATOL)


@pytest.mark.parametrize("shape", sr.SHAPES)
def test_splat_no_gaussians(device, shape):
    """n = 0, and n > 0 with every Gaussian culled: the background, T = 1, no contributions,
    zero (or empty) gradients."""
    r = SplatRasterizer(device, 1, shape=shape)
    cam, _ = _camera(33, 17)
    for g in (_gaussians(0, 1, 0), _gaussians(5, 1, 0, spread=0.01)):
        if len(g["means"]):
            g["means"][:, 2] = -10.0                  # all behind the camera
        out = r.render(g, cam, BG)
        np.testing.assert_array_equal(out["rgb"], np.broadcast_to(np.float32(BG), (17, 33, 3)))
        np.testing.assert_array_equal(out["T"], 1.0)
        np.testing.assert_array_equal(out["n_contrib"], 0)
        grads = r.render_backward(g, cam, np.ones((17, 33, 3)), BG)
        for name in PARAMS:
            assert grads[name].shape == r.shapes(len(g["means"]))[name]
            assert np.all(grads[name] == 0)


# ---- the whole chain ---------------------------------------------------------------------------
@pytest.mark.parametrize("degree,width,height", [(3, 33, 17), (1, 32, 32), (0, 20, 45)])
@pytest.mark.parametrize("shape", sr.SHAPES)
def test_splat_render_matches_reference(device, shape, degree, width, height):
    """project -> bin -> rasterize and back, kernels vs the twin."""
    g = _gaussians(60, degree, seed=degree + width)
    cam, rcam = _camera(width, height)
    r = SplatRasterizer(device, degree, shape=shape)
    out = r.render(g, cam, BG)
    _, _, want = rs.render(_f64(g), rcam, BG)
    np.testing.assert_array_equal(out["n_contrib"], want["n_contrib"])
    for name in ("rgb", "T"):
        np.testing.assert_allclose(out[name], want[name], rtol=0, atol=tol.SPLAT_RASTER_ATOL)
    grad = np.random.default_rng(degree).normal(size=(height, width, 3))
    got = r.render_backward(g, cam, grad, BG)
    ref = rs.render_backward(_f64(g), rcam, grad, BG)
    for name in PARAMS:
        _close_rel(got[name], ref[name], tol.SPLAT_GRAD_REL_TO_MAX, name)


@pytest.mark.parametrize("shape", sr.SHAPES)
def test_splat_extreme_scales_finite(device, shape):
    """A sweep of log-scales -30 .. 45 and opacity logits +-30 around and behind the camera:
    every output and gradient is finite, culled Gaussians have zero radius and gradients, and
    the images still match the twin where nothing overflows float32."""
    degree = 2
    rng = np.random.default_rng(11)
    ls = np.repeat(np.float32([-30, -10, -3, 0, 5, 10, 20, 45]), 4)
    n = ls.size
    g = _gaussians(n, degree, seed=11, spread=1.0)
    g["log_scales"] = np.stack([ls, ls + rng.uniform(-1, 1, n), ls - 1], 1).astype(np.float32)
    g["opacity_logits"] = rng.choice(np.float32([-30, -5, 0, 5, 30]), n)
    g["means"][::7, 2] = -3.5                          # behind the camera
    cam, rcam = _camera(33, 17)
    r = SplatRasterizer(device, degree, shape=shape)
    proj = r.project(r.upload(g), cam)
    for name in ("xy", "conic", "radius", "depth", "color", "opacity"):
        assert np.all(np.isfinite(getattr(proj, name).get())), name
    out = r.render(g, cam, BG)
    for name in ("rgb", "T"):
        assert np.all(np.isfinite(out[name])), name
    grads = r.render_backward(g, cam, np.random.default_rng(1).normal(size=(17, 33, 3)), BG)
    culled = proj.radius.get() == 0
    assert culled[ls == 45].all() and culled[::7].all() and not culled.all()
    for name in PARAMS:
        assert np.all(np.isfinite(grads[name])), name
        assert np.all(grads[name][culled] == 0), name
    keep = ls < 45                                   # float32 holds these covariances
    sub = {k: v[keep] for k, v in g.items()}
    _, _, want = rs.render(_f64(sub), rcam, BG)
    np.testing.assert_allclose(r.render(sub, cam, BG)["rgb"], want["rgb"], rtol=0,
                               atol=tol.SPLAT_RASTER_ATOL)


# ---- the twin's gradient vs central differences -------------------------------------------------
def test_splat_reference_gradient_vs_finite_differences():
    """The twin's analytic gradient of L = sum(w * rgb) vs central differences of its forward
    (float64) for every parameter of 5 Gaussians on a 32 x 32 image: one with x/z clamped by the
    frustum guard, one opaque enough that alpha clamps at 0.99 near its centre."""
    degree = 3
    g = _f64(_gaussians(5, degree, seed=21, spread=0.4, log_scale=(-2.3, -1.3)))
    g["means"][0] = [2.6, 0.1, 0.2]                 # x/z beyond 1.3 tan(fov/2): clamped J
    g["log_scales"][0] = [-0.6, -1.0, -0.8]
    g["opacity_logits"][1] = 8.0                     # o = 0.9997: alpha clamps near the centre
    cam = {"viewmat": rs.look_at((0.3, -0.2, -3.0), (0, 0, 0)), "fx": 30.0, "fy": 32.0,
           "cx": 16.0, "cy": 15.0, "width": 32, "height": 32, "near": 0.1}
    I = rs._intermediates(g, cam)
    assert I["clamp_x"][0] and I["vis"][0]
    proj, lists, fwd = rs.render(g, cam, BG)
    assert proj["radius"][0] > 0 and proj["rect"][0][2] > proj["rect"][0][0]
    w = np.random.default_rng(22).normal(size=(32, 32, 3))
    grads = rs.render_backward(g, cam, w, BG)

    def loss(p):
        return float(np.sum(rs.render(p, cam, BG)[2]["rgb"] * w))

    _assert_fd(g, loss, grads)
    assert np.abs(grads["means"][0]).max() > 1e-3


def _assert_fd(g, loss, grads):
    """Every parameter's analytic gradient ``grads[name]`` against central differences of
    ``loss`` (float64, eps SPLAT_FD_EPS), each gradient non-trivial."""
    eps = tol.SPLAT_FD_EPS
    for name in PARAMS:
        fd = np.zeros_like(g[name])
        for idx in np.ndindex(g[name].shape):
            plus = {k: v.copy() for k, v in g.items()}
            minus = {k: v.copy() for k, v in g.items()}
            plus[name][idx] += eps
            minus[name][idx] -= eps
            fd[idx] = (loss(plus) - loss(minus)) / (2 * eps)
        assert np.abs(fd).max() > 1e-3, name
        np.testing.assert_allclose(grads[name], fd, rtol=tol.SPLAT_FD_RTOL,
                                   atol=tol.SPLAT_FD_ATOL, err_msg=name)


# ---- validation ---------------------------------------------------------------------------------
def test_splat_bad_inputs(device):
    r = SplatRasterizer(device, 1)
    cam, _ = _camera()
    g = _gaussians(4, 1, 0)
    bad_shape = dict(g, sh=np.zeros((4, 9, 3), np.float32))       # degree 2 rows for degree 1
    with pytest.raises(ValueError, match="sh"):
        r.upload(bad_shape)
    with pytest.raises(ValueError, match="NaN"):
        r.upload(dict(g, means=np.full((4, 3), np.nan)))
    with pytest.raises(KeyError, match="quats"):
        r.upload({k: v for k, v in g.items() if k != "quats"})
    params = r.upload(g)
    with pytest.raises(TypeError, match="dtype"):
        r.project(dict(params, quats=cla.to_device(device.queue, g["quats"].astype(float))), cam)
    with pytest.raises(ValueError, match="contiguous"):
        wide = cla.to_device(device.queue, np.zeros((4, 6), np.float32))
        r.project(dict(params, means=wide[:, :3]), cam)
    with pytest.raises(TypeError, match="pyopencl"):
        r.project(dict(params, means=g["means"]), cam)
    with pytest.raises(ValueError, match="near"):
        SplatCamera(np.eye(4), 10, 10, 5, 5, 10, 10, near=0.0)
    with pytest.raises(ValueError, match="width"):
        SplatCamera(np.eye(4), 10, 10, 5, 5, 0, 10)
    with pytest.raises(ValueError, match="viewmat"):
        SplatCamera(np.eye(3), 10, 10, 5, 5, 10, 10)
    with pytest.raises(ValueError, match="sh_degree"):
        SplatRasterizer(device, 4)
    with pytest.raises(ValueError, match="shape"):
        SplatRasterizer(device, 1, shape="pixels")
    with pytest.raises(ValueError, match="4, 8 or 16"):
        SplatRasterizer(device, 1, tile=32, shape="rows")
    proj, bins, ras = r.forward(params, cam)
    with pytest.raises(ValueError, match="grad_rgb"):
        r.rasterize_backward(proj, bins, ras, cam, cla.zeros(device.queue, (17, 33), np.float32))


def test_splat_default_tile_follows_the_shape(device):
    """Models rasterise in 8-pixel tiles with the rows shape (CPUs), 16 with the work-group
    shape (GPUs, or CLRF_FORCE_GPU_KERNELS=1)."""
    tile = sr.default_tile(device)
    assert sr.default_shape(device, tile) == ("rows" if tile == sr.CPU_TILE else "group")
    assert tile == (sr.TILE if getattr(device.tuning, "gpu_kernels", False) else sr.CPU_TILE)


# ---- the batch's gradient sum (clrf/splat/distributed.py) ------------------------------------
@pytest.mark.parametrize("n", [0, 1, 257, 4099])
def test_grad_sum_rounds_as_numpy_float32(device, n):
    """total = (total + g) * scale on the device: the float32 roundings of numpy's, bit for bit
    (the distributed step's mean over the batch stays the one-process sum's), stiff values and
    non-finite ones passing through as IEEE arithmetic has them."""
    import pyopencl.array as cla
    from clrf.splat.distributed import grad_sum
    rng = np.random.default_rng(n)
    total = (rng.normal(size=n) * 10.0 ** rng.integers(-30, 30, n)).astype(np.float32)
    g = rng.normal(size=n).astype(np.float32)
    if n > 4:
        total[:4] = [np.inf, np.nan, 3e38, -1e-45]
        g[:4] = [1.0, 2.0, 3e38, 1e-45]
    q = device.queue
    for scale in (1.0, 0.5, 1.0 / 3):
        t = cla.to_device(q, total)
        grad_sum(device, t, cla.to_device(q, g), scale)
        want = (total + g) * np.float32(scale)
        np.testing.assert_array_equal(t.get(), want)
    with pytest.raises(ValueError, match="entries added"):
        grad_sum(device, cla.to_device(q, total), cla.zeros(q, n + 1, np.float32), 1.0)
