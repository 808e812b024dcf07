"""Anti-aliased splats (splat.antialiased; Mip-Splatting's 3D and 2D filters, cl/splat_project.cl
with ANTIALIASED=1): the projection and its backward against the float64 twin
(clrf/references/reference_splat.py with params["filter3d"]), the twin against central
differences of the whole render, the 3D filter's kernel (splat_filter3d) against its twin, the
stiff cases (a Gaussian far smaller than a pixel, a camera very close), and zooming out: the
filters keep a scene of sub-pixel Gaussians from turning fat and bright."""
import numpy as np
import pyopencl.array as cla
import pytest

from clrf.references import reference_splat as rs
from clrf.splat import SplatCamera, SplatRasterizer
from clrf.splat import raster as sr
from clrf.testing import tolerances as tol

from test_splat_kernels import (BG, PARAMS, _assert_fd, _camera, _close_rel, _f64, _gaussians,
                                _stiff_gaussians)


def _with_filter(g, seed, top=3e-4):
    g = dict(g)
    g["filter3d"] = np.random.default_rng(seed).uniform(0, top, len(g["means"])).astype(
        np.float32)
    return g


def _upload(device, r, g):
    params = r.upload({k: g[k] for k in PARAMS})
    params["filter3d"] = cla.to_device(device.queue, np.ascontiguousarray(g["filter3d"]))
    return params


def test_constants_match_the_twin():
    d = sr.project_defines(3, antialiased=True)
    assert d["ANTIALIASED"] == 1 and "ANTIALIASED" not in sr.project_defines(3)
    for name in ("FILTER3D_VAR", "FILTER3D_MARGIN"):
        assert float(np.float32(d[name])) == getattr(rs, name), name
    # the 2D filter: Mip-Splatting's in the anti-aliased projection, 3DGS's dilation without
    assert float(np.float32(d["COV_DILATION"])) == rs.AA_FILTER2D == np.float32(0.1)
    assert float(np.float32(sr.project_defines(3)["COV_DILATION"])) == rs.COV_DILATION
    assert sr.project_defines(3, antialiased=True, filter2d=0.3)["COV_DILATION"] == 0.3
    assert sr.project_defines(3, filter2d=0.05)["COV_DILATION"] == sr.COV_DILATION


def test_the_2d_filter_setting():
    """splat.aa_filter2d: Mip-Splatting's 0.1 px^2 by default, checked; an anti-aliased
    checkpoint written before the setting keeps the 0.3 px^2 it was trained with."""
    from clrf.splat.config import SplatConfig
    assert SplatConfig().aa_filter2d == pytest.approx(0.1)
    bad = SplatConfig(aa_filter2d=0.0)
    assert [c for c in bad.checks() if not c[0]][0][1] == "splat.aa_filter2d"
    old = {k: v for k, v in SplatConfig(antialiased=True).__dict__.items()
           if k != "aa_filter2d"}
    assert SplatConfig.from_dict(old).aa_filter2d == 0.3
    assert SplatConfig.from_dict(dict(old, antialiased=False)).aa_filter2d == pytest.approx(0.1)
    assert SplatConfig.from_dict(dict(old, aa_filter2d=0.2)).aa_filter2d == 0.2


def test_on_by_default_except_tiny_and_old_checkpoints():
    """splat.antialiased is on in the full preset, off in the tiny one; a checkpoint written
    before the option (no field) loads as the plain 3DGS it was trained as."""
    from clrf.splat.config import SplatConfig
    assert SplatConfig().antialiased and SplatConfig.from_preset("full").antialiased
    assert not SplatConfig.from_preset("tiny").antialiased
    assert SplatConfig.from_preset("tiny", antialiased=True).antialiased
    before = {k: v for k, v in SplatConfig().__dict__.items()
              if k not in ("antialiased", "aa_filter2d")}
    assert not SplatConfig.from_dict(before).antialiased
    assert SplatConfig.from_dict(dict(before, antialiased=True)).aa_filter2d == 0.3


@pytest.mark.parametrize("filter2d", [0.1, 0.3])
def test_twin_gradient_vs_finite_differences(filter2d):
    """The anti-aliased twin's analytic gradient of L = sum(w * rgb) against central differences
    of its render, for Gaussians whose filters matter: opacity factors c2 below 0.3 and c3
    below 0.7 (with either 2D filter: one Gaussian of a tenth of a pixel), one with x/z
    clamped."""
    g = _f64(_gaussians(6, 2, seed=21, spread=0.4, log_scale=(-4.5, -2.5)))
    g["means"][0] = [2.6, 0.1, 0.2]
    g["log_scales"][0] = [-0.6, -1.0, -0.8]
    g["log_scales"][1] = [-5.5, -5.0, -5.2]
    g["filter3d"] = np.random.default_rng(3).uniform(0, 3e-4, 6)
    g["filter2d"] = np.array(filter2d)
    cam = {"viewmat": rs.look_at((0.3, -0.2, -3.0), (0, 0, 0)), "fx": 30.0, "fy": 32.0,
           "cx": 16.0, "cy": 15.0, "width": 32, "height": 32, "near": 0.1}
    I = rs._intermediates(g, cam)
    assert I["dil"] == pytest.approx(filter2d)
    assert I["c2"].min() < 0.3 and I["c3"].min() < 0.7 and I["clamp_x"][0]
    w = np.random.default_rng(22).normal(size=(32, 32, 3))
    grads = rs.render_backward(g, cam, w, BG)

    def loss(p):
        return float(np.sum(rs.render(p, cam, BG)[2]["rgb"] * w))
    _assert_fd(g, loss, grads)


def test_without_the_filter_the_twin_is_the_plain_projection():
    g = _f64(_gaussians(20, 1, seed=2))
    _, cam = _camera()
    plain = rs.project(g, cam)
    same = dict(g, filter3d=np.zeros(20), filter2d=rs.COV_DILATION)
    zero = rs.project(same, cam)
    c2 = rs._intermediates(same, cam)["c2"]
    # f2 = 0 leaves the 3D part out; with the plain dilation as the 2D filter, its
    # compensation alone scales the opacity
    for k in ("xy", "conic", "radius", "color"):
        np.testing.assert_array_equal(zero[k], plain[k])
    np.testing.assert_allclose(zero["opacity"], plain["opacity"] * c2, rtol=1e-15)
    assert 0 < c2[plain["visible"]].min() and c2.max() < 1
    # the default 2D filter adds 0.1 px^2 where the plain projection adds 0.3
    Ip = rs._intermediates(g, cam)
    Ia = rs._intermediates(dict(g, filter3d=np.zeros(20)), cam)
    np.testing.assert_allclose(Ia["a"] + rs.COV_DILATION - rs.AA_FILTER2D, Ip["a"], rtol=1e-12)
    np.testing.assert_allclose(Ia["c"] + rs.COV_DILATION - rs.AA_FILTER2D, Ip["c"], rtol=1e-12)


@pytest.mark.parametrize("degree,filter2d", [(1, 0.1), (3, 0.1), (1, 0.3)])
def test_project_and_backward_match_the_twin(device, degree, filter2d):
    """ANTIALIASED=1 forward and backward against the twin on ordinary and stiff Gaussians
    (the stiff set has a point-sized Gaussian, whose 2D factor is ~0, and a huge one), with
    the default 2D filter and gsplat's 0.3 px^2."""
    g = dict(_with_filter(_stiff_gaussians(degree, seed=5), seed=7), filter2d=filter2d)
    n = len(g["means"])
    cam, rcam = _camera()
    r = SplatRasterizer(device, degree, antialiased=True, filter2d=filter2d)
    assert r.filter2d == filter2d
    params = _upload(device, r, g)
    proj = r.project(params, cam)
    want = rs.project(_f64(g), rcam)
    vis = want["visible"]
    np.testing.assert_array_equal(proj.radius.get() > 0, vis)
    for name in ("xy", "depth", "color", "opacity", "radius"):
        got = getattr(proj, name).get()
        assert np.all(np.isfinite(got)), name
        np.testing.assert_allclose(got[vis], want[name][vis], rtol=tol.SPLAT_PROJECT_RTOL,
                                   atol=tol.SPLAT_PROJECT_ATOL, err_msg=name)
    rng = np.random.default_rng(6)
    g2d = {"xy": rng.normal(size=(n, 2)), "conic": rng.normal(size=(n, 3)) * 10.0,
           "color": rng.normal(size=(n, 3)), "opacity": rng.normal(size=n)}
    g2d = {k: v.astype(np.float32) for k, v in g2d.items()}
    got = r.project_backward(params, cam, {k: cla.to_device(device.queue, v)
                                           for k, v in g2d.items()})
    wantg = rs.project_backward(_f64(g), rcam, _f64(g2d))
    ordinary = np.arange(n) < 24
    for name in PARAMS:
        out = got[name].get()
        assert np.all(np.isfinite(out)) and np.all(out[~vis] == 0), name
        _close_rel(out[ordinary], wantg[name][ordinary], tol.SPLAT_GRAD_REL_TO_MAX, name)
        for i in np.flatnonzero(vis & ~ordinary):
            scale = max(np.abs(wantg[name][i]).max(), np.abs(wantg[name][ordinary]).max())
            _close_rel(out[i], wantg[name][i], tol.SPLAT_GRAD_REL_TO_MAX, f"{name}[{i}]", scale)


def test_camera_gradient_with_the_filters(device):
    """POSE_GRAD=1 and ANTIALIASED=1 together: the camera's gradient as the twin's."""
    g = _with_filter(_gaussians(40, 1, seed=8), seed=9)
    n = 40
    rng = np.random.default_rng(10)
    g2d = {"xy": rng.normal(size=(n, 2)), "conic": rng.normal(size=(n, 3)) * 10.0,
           "color": rng.normal(size=(n, 3)), "opacity": rng.normal(size=n)}
    g2d = {k: v.astype(np.float32) for k, v in g2d.items()}
    cam, rcam = _camera()
    r = SplatRasterizer(device, 1, antialiased=True)
    out = r.project_backward(_upload(device, r, g), cam,
                             {k: cla.to_device(device.queue, v) for k, v in g2d.items()},
                             camera_grad=True)
    want = rs.camera_backward(_f64(g), rcam, _f64(g2d))
    shares = out["camera"].get()
    want_shares = np.concatenate([want["R"].reshape(n, 9), want["t"]], 1).T
    assert np.abs(shares - want_shares).max() <= tol.SPLAT_GRAD_REL_TO_MAX * np.abs(
        want_shares).max()


def test_filter3d_matches_the_twin(device):
    """splat_filter3d over three cameras (one very close, one that sees few of the means) and
    the fill of means no camera sees."""
    g = _gaussians(300, 0, seed=12, spread=1.5)
    g["means"][0] = [0.0, 0.0, -40.0]                # behind every camera: unseen
    cams = [_camera(40, 30, eye=e, f=(35.0, 35.0))[0]
            for e in ((0.3, -0.2, -3.0), (0.0, 0.0, -0.6), (2.5, 0.0, -0.5))]
    r = SplatRasterizer(device, 0, antialiased=True)
    f2 = r.filter3d(cla.to_device(device.queue, g["means"]), cams).get()
    ref_cams = [{"viewmat": c.viewmat, "fx": c.fx, "fy": c.fy, "cx": c.cx, "cy": c.cy,
                 "width": c.width, "height": c.height, "near": c.near} for c in cams]
    want = rs.filter3d(g["means"], ref_cams)
    seen = want >= 0
    assert not seen[0] and 150 < seen.sum() < 299
    np.testing.assert_allclose(f2[seen], want[seen], rtol=1e-5)
    assert f2[0] == pytest.approx(want[seen].max(), rel=1e-5)
    # the close camera samples finer: it sets the filter of the means it sees
    close_only = rs.filter3d(g["means"], ref_cams[1:2])
    both = (close_only >= 0) & seen
    assert np.all(want[both] <= close_only[both] * (1 + 1e-12))
    # no camera sees anything: every f2 is 0
    far = [_camera(40, 30, eye=(0.0, 0.0, -30.0), f=(35.0, 35.0))[0]]   # it looks away
    none = r.filter3d(cla.to_device(device.queue, g["means"][:1]), far).get()
    assert none.tolist() == [0.0]


def test_anti_aliased_rasteriser_needs_the_filter(device):
    r = SplatRasterizer(device, 0, antialiased=True)
    g = _gaussians(3, 0, seed=1)
    cam, _ = _camera()
    with pytest.raises(KeyError, match="filter3d"):
        r.project(r.upload(g), cam)


def test_zooming_out_keeps_small_gaussians_from_swelling(device):
    """A wall of 1,500 Gaussians of about 1 pixel at the resolution they were fitted at (their
    3D filters from that camera), rendered at a quarter of it, where they are a quarter pixel:
    without the filters each swells to the 0.3 px^2 dilation at full opacity and the wall's
    coverage rises well above that of the full-size render box-averaged; with them the
    coverage stays close to it."""
    rng = np.random.default_rng(5)
    n = 1500
    g = {"means": np.c_[rng.uniform(-1, 1, (n, 2)), np.zeros(n)].astype(np.float32),
         "log_scales": np.full((n, 3), np.log(0.02), np.float32),
         "quats": np.tile(np.float32([1, 0, 0, 0]), (n, 1)),
         "opacity_logits": np.full(n, 0.0, np.float32),
         "sh": np.zeros((n, 1, 3), np.float32)}
    full = SplatCamera(rs.look_at((0, 0, -3.0), (0, 0, 0)), 160.0, 160.0, 64.0, 64.0, 128, 128)
    small = SplatCamera(full.viewmat, 40.0, 40.0, 16.0, 16.0, 32, 32)

    def coverage(antialiased, cam):
        r = SplatRasterizer(device, 0, antialiased=antialiased)
        params = r.upload(g)
        if antialiased:
            params["filter3d"] = r.filter3d(params["means"], [full])
        ras = r.forward(params, cam, (0.0, 0.0, 0.0))[2]
        return 1.0 - ras.T.get()

    ref = coverage(True, full).reshape(32, 4, 32, 4).mean((1, 3))   # area average
    plain = coverage(False, small)
    aa = coverage(True, small)
    err_plain = np.abs(plain - ref).mean()
    err_aa = np.abs(aa - ref).mean()
    print(f"coverage: box-averaged {ref.mean():.3f}, plain {plain.mean():.3f} (error "
          f"{err_plain:.3f}), filtered {aa.mean():.3f} (error {err_aa:.3f})")
    assert 0.2 < ref.mean() < 0.6
    assert plain.mean() > 1.3 * ref.mean() and err_aa < 0.5 * err_plain


# ---- through the model and the command line -----------------------------------------------------
@pytest.mark.slow
def test_an_anti_aliased_run_trains_saves_renders_and_exports(tmp_path):
    """`--set splat.antialiased=true`: the run trains, its checkpoint holds each Gaussian's 3D
    filter (f2 > 0, recomputed as the Gaussians change), the loaded model renders the same
    image, `clrf render --scale 0.5` renders at half size, and the PLY has the filter baked in
    (scales widened, opacities lowered)."""
    from clrf.cli.main import main as cli
    from clrf.outputs import checkpoint
    from clrf.runtime.device import Device
    from clrf.splat.ply import read_splat_ply
    out = tmp_path / "run"
    assert cli(["--quiet", "train", "--model", "splat", "--out", str(out), "--max-seconds",
                "120", "--set", "train.max_iters=80", "--set", "splat.preset=tiny", "--set",
                "splat.antialiased=true", "--set", "train.eval_views=1"]) == 0
    st = checkpoint.load(out)
    n = len(st["param_means"])
    assert st["filter3d"].shape == (n,) and np.all(st["filter3d"] > 0)
    from clrf.splat.model import SplatModel
    model = SplatModel.from_state_dict(Device(None), st)
    assert model.rast.antialiased
    np.testing.assert_array_equal(model.filter3d.get(), st["filter3d"])
    assert cli(["--quiet", "render", "--ckpt", str(out), "--views", "test", "--max-views",
                "1", "--scale", "0.5", "--out", str(tmp_path / "half")]) == 0
    import imageio.v3 as iio
    img = iio.imread(next((tmp_path / "half").glob("test_*.png")))
    assert img.shape[:2] == (32, 32)
    # the zoomed-out score: half the resolution against box-averaged test images
    import json
    assert cli(["eval", "--ckpt", str(out), "--downscale", "2", "--max-views", "2", "--lpips",
                "none", "--out", str(tmp_path / "half.json")]) == 0
    half = json.loads((tmp_path / "half.json").read_text())
    assert half["resolution"] == [32, 32] and half["downscale"] == 2
    full = json.loads((out / "eval.json").read_text())
    assert full["psnr"] > 15 and half["psnr"] > full["psnr"] - 3, (full["psnr"], half["psnr"])
    assert cli(["eval", "--ckpt", str(out), "--downscale", "0", "--lpips", "none"]) == 2
    ply = tmp_path / "s.ply"
    assert cli(["--quiet", "export", "--ckpt", str(out), "--splats", str(ply)]) == 0
    back = read_splat_ply(ply)
    assert np.all(back["log_scales"] >= st["param_log_scales"] - 1e-6)
    assert np.all(back["opacity_logits"] <= st["param_opacity_logits"] + 1e-5)
    assert (back["log_scales"] > st["param_log_scales"] + 1e-4).any()
