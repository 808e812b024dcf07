"""Pose refinement (splat.pose_opt): the camera's gradient out of the projection's backward
(cl/splat_project.cl with POSE_GRAD=1) against its float64 twin
(clrf/references/reference_splat.py camera_backward) and the twin against central differences,
stiff Gaussians included; the host's chain to the per-camera correction (clrf/corrections/pose.py)
against central differences; a perturbed camera recovered on a fixed scene; and a run that
refines, saves, reports and resumes its poses."""
import json
from dataclasses import dataclass

import numpy as np
import pyopencl.array as cla
import pytest

from clrf.references import reference_splat as rs
from clrf.splat import SplatRasterizer
from clrf.corrections import pose as sp
from clrf.splat.raster import camera_gradient
from clrf.testing import tolerances as tol

from test_splat_kernels import _camera, _f64, _gaussians, _stiff_gaussians


def _g2d(n, seed):
    rng = np.random.default_rng(seed)
    g = {"xy": rng.normal(size=(n, 2)), "conic": rng.normal(size=(n, 3)) * 10.0,
         "color": rng.normal(size=(n, 3)), "opacity": rng.normal(size=n)}
    return {k: v.astype(np.float32) for k, v in g.items()}


def _loss(g, cam, g2d):
    """L = sum of the projected outputs weighted by g2d (so dL/d(outputs) = g2d)."""
    p = rs.project(g, cam)
    return sum(float(np.sum(p[k] * g2d[k])) for k in ("xy", "conic", "color", "opacity"))


def test_twin_camera_gradient_vs_finite_differences():
    """dL/dR and dL/dt of the twin (summed over ordinary and stiff Gaussians: clamped x/z and
    y/z, one just past the near plane, a zero-volume disc, a huge one) against central
    differences of its forward in every entry of the 3 x 4 [R t]."""
    g = _f64(_stiff_gaussians(3, seed=5))
    g2d = _f64(_g2d(len(g["means"]), 6))
    _, cam = _camera()
    cam = dict(cam, viewmat=np.asarray(cam["viewmat"], np.float64))
    I = rs._intermediates(g, cam)
    assert I["clamp_x"][I["vis"]].any() and I["clamp_y"][I["vis"]].any()
    got = rs.camera_backward(g, cam, g2d)
    assert np.all(got["R"][~I["vis"]] == 0) and np.all(got["t"][~I["vis"]] == 0)
    analytic = np.concatenate([got["R"].sum(0), got["t"].sum(0)[:, None]], 1)
    eps = tol.SPLAT_FD_EPS
    fd = np.zeros((3, 4))
    for idx in np.ndindex(3, 4):
        plus, minus = cam["viewmat"].copy(), cam["viewmat"].copy()
        plus[idx] += eps
        minus[idx] -= eps
        fd[idx] = (_loss(g, dict(cam, viewmat=plus), g2d)
                   - _loss(g, dict(cam, viewmat=minus), g2d)) / (2 * eps)
    assert np.abs(fd).min() > 1e-2
    np.testing.assert_allclose(analytic, fd, rtol=tol.SPLAT_FD_RTOL,
                               atol=tol.SPLAT_FD_ATOL * np.abs(fd).max())


@pytest.mark.parametrize("degree", [0, 3])
def test_camera_gradient_on_the_device_matches_the_twin(device, degree):
    """splat_project_backward with POSE_GRAD=1: each Gaussian's share of dL/d(R, t) as the
    twin's (culled ones zero, stiff ones included), their sums as camera_gradient reads them,
    and the parameters' gradients bit for bit those of the program without it."""
    g = _stiff_gaussians(degree, seed=5)
    n = len(g["means"])
    g2d = _g2d(n, 6)
    cam, rcam = _camera()
    r = SplatRasterizer(device, degree)
    params = r.upload(g)
    g2d_d = {k: cla.to_device(device.queue, v) for k, v in g2d.items()}
    plain = r.project_backward(params, cam, g2d_d)
    got = r.project_backward(params, cam, g2d_d, camera_grad=True)
    for name in plain:
        np.testing.assert_array_equal(got[name].get(), plain[name].get(), err_msg=name)
    want = rs.camera_backward(_f64(g), rcam, _f64(g2d))
    shares = got["camera"].get()
    assert shares.shape == (12, n) and np.all(np.isfinite(shares))
    want_shares = np.concatenate([want["R"].reshape(n, 9), want["t"]], 1).T
    vis = rs.project(_f64(g), rcam)["visible"]
    assert np.all(shares[:, ~vis] == 0)
    scale = np.abs(want_shares).max()
    assert np.abs(shares - want_shares).max() <= tol.SPLAT_GRAD_REL_TO_MAX * scale
    dR, dt = camera_gradient(got["camera"])
    # the sums: float32 rounding of n terms, relative to the sum of their magnitudes
    mag = np.abs(want_shares).sum(1)
    err = np.abs(np.concatenate([dR.ravel(), dt]) - want_shares.sum(1))
    assert np.all(err <= tol.SPLAT_CAMERA_SUM_REL * mag), (err, mag)


def test_camera_gradient_of_no_gaussians(device):
    r = SplatRasterizer(device, 0)
    g = {k: v[:0] for k, v in _gaussians(1, 0, 0).items()}
    cam, _ = _camera()
    out = r.project_backward(r.upload(g), cam, {k: cla.zeros(device.queue, s, np.float32)
                                                for k, s in (("xy", (0, 2)), ("conic", (0, 3)),
                                                             ("color", (0, 3)),
                                                             ("opacity", (0,)))},
                             camera_grad=True)
    dR, dt = camera_gradient(out["camera"])
    assert not dR.any() and not dt.any()


# ---- the host's chain -------------------------------------------------------------------------
def test_exp_and_left_jacobian():
    rng = np.random.default_rng(1)
    for w in (np.zeros(3), 1e-9 * rng.normal(size=3), 0.02 * rng.normal(size=3),
              rng.normal(size=3), np.array([np.pi - 1e-3, 0, 0])):
        E = sp.so3_exp(w)
        np.testing.assert_allclose(E @ E.T, np.eye(3), atol=1e-14)
        assert np.linalg.det(E) == pytest.approx(1.0, abs=1e-14)
        assert sp.rotation_angle(E) == pytest.approx(np.linalg.norm(w), abs=1e-12)
        # Exp(w + d) = Exp(J_l(w) d) Exp(w) to first order
        J = sp.left_jacobian(w)
        for k in range(3):
            d = np.zeros(3)
            d[k] = 1e-6
            lhs = (sp.so3_exp(w + d) - sp.so3_exp(w - d)) / 2e-6
            np.testing.assert_allclose(lhs, sp.hat(J[:, k]) @ E, atol=1e-8)
    # the series near 0 and the closed form meet
    w = np.array([3e-7, -2e-7, 1e-7])
    np.testing.assert_allclose(sp.so3_exp(w), np.eye(3) + sp.hat(w), atol=1e-13)


@pytest.mark.parametrize("pivot", [0.0, 3.0])
def test_pose_gradient_vs_finite_differences(pivot):
    """PoseCorrection.gradient (reg 0, then reg > 0) against central differences of the loss
    in the correction (w, tau) of a camera already corrected by a few degrees, turned about
    its centre (pivot 0) and about a point 3 units ahead (the scene's centre)."""
    g = _f64(_gaussians(30, 2, seed=11))
    g2d = _f64(_g2d(30, 12))
    _, cam0 = _camera()
    V0 = np.asarray(cam0["viewmat"], np.float64)
    for reg in (0.0, 0.3):
        pc = sp.PoseCorrection(2, lr=1e-3, reg=reg, scale=2.5, pivots=[1.0, pivot])
        pc.params[1] = [0.03, -0.05, 0.02, 0.04, -0.02, 0.05]

        def loss(p):
            V = sp.corrected_viewmat(V0, p[:3], p[3:], pivot)
            return (_loss(g, dict(cam0, viewmat=V), g2d) + reg * np.sum(p[:3] ** 2)
                    + reg * np.sum((p[3:] / 2.5) ** 2))
        V = pc.viewmat(V0, 1)
        part = rs.camera_backward(g, dict(cam0, viewmat=V), g2d)
        got = pc.gradient(1, V, part["R"].sum(0), part["t"].sum(0))
        fd = np.zeros(6)
        for k in range(6):
            d = np.zeros(6)
            d[k] = 1e-6
            fd[k] = (loss(pc.params[1] + d) - loss(pc.params[1] - d)) / 2e-6
        assert np.abs(fd).min() > 1e-2
        np.testing.assert_allclose(got, fd, rtol=tol.SPLAT_FD_RTOL,
                                   atol=tol.SPLAT_FD_ATOL * np.abs(fd).max())


def test_a_turn_about_the_pivot_keeps_the_pivot_and_moves_the_centre():
    """corrected_viewmat turns the camera about the point ``pivot`` ahead of it: that point's
    camera coordinates stay (0, 0, pivot), the camera centre moves by 2 pivot sin(|w| / 2) as
    centre_shift says, and a shift tau moves every camera coordinate by tau."""
    V0 = rs.look_at((0.4, -0.3, -3.0), (0, 0, 0))
    centre0 = -V0[:3, :3].T @ V0[:3, 3]
    ahead = centre0 + 3.0 * V0[2, :3]          # 3 units along the optical axis (OpenCV +z)
    w = np.radians(2.0) * np.array([0.6, -0.8, 0.0])
    pc = sp.PoseCorrection(1, lr=1e-3, reg=0.0, scale=1.0, pivots=[3.0])
    pc.params[0, :3] = w
    V = pc.viewmat(V0, 0)
    np.testing.assert_allclose(V[:3, :3] @ ahead + V[:3, 3], [0, 0, 3.0], atol=1e-12)
    centre = -V[:3, :3].T @ V[:3, 3]
    moved = np.linalg.norm(centre - centre0)
    assert moved == pytest.approx(2 * 3.0 * np.sin(np.radians(2.0) / 2), rel=1e-12)
    assert pc.centre_shift(0) == pytest.approx(moved, rel=1e-12)
    pc.params[0, 3:] = [0.01, -0.02, 0.03]
    x = np.array([0.2, 0.1, -0.3, 1.0])
    np.testing.assert_allclose(pc.viewmat(V0, 0) @ x - V @ x, [0.01, -0.02, 0.03, 0.0],
                               atol=1e-12)
    assert pc.centre_shift(0) == pytest.approx(
        np.linalg.norm(-pc.viewmat(V0, 0)[:3, :3].T @ pc.viewmat(V0, 0)[:3, 3] - centre0),
        rel=1e-12)


def test_pose_state_round_trip_and_bad_values():
    pc = sp.PoseCorrection(3, lr=1e-3, reg=1e-4, scale=2.0, pivots=[0.0, 1.5, 4.0])
    pc.step(2, np.eye(4), np.arange(9.0).reshape(3, 3), np.ones(3))
    assert pc.steps.tolist() == [0, 0, 1] and pc.params[2].any() and not pc.params[:2].any()
    back = sp.PoseCorrection(3, lr=1e-3, reg=1e-4, scale=2.0, state=pc.state_dict())
    for k, v in pc.state_dict().items():
        np.testing.assert_array_equal(back.state_dict()[k], v)
    s = pc.summary()
    assert s["images"] == 1 and s["rotation_deg"] > 0 and s["translation"] > 0
    # a checkpoint written before the pivots turned its cameras about their centres
    old = {k: v for k, v in pc.state_dict().items() if k != "pose_pivot"}
    assert not sp.PoseCorrection(3, 1e-3, 1e-4, 2.0, state=old, pivots=[1, 1, 1]).pivots.any()
    before = pc.params.copy()
    pc.step(0, np.eye(4), np.full((3, 3), np.nan), np.ones(3))   # a NaN step changes nothing
    np.testing.assert_array_equal(pc.params, before)
    for bad in ({"n_images": 0}, {"lr": 0.0}, {"reg": -1.0}, {"scale": 0.0},
                {"pivots": [1.0, -1.0]}, {"pivots": [1.0, np.inf]}):
        kw = {**dict(n_images=2, lr=1e-3, reg=0.0, scale=1.0), **bad}
        with pytest.raises(ValueError):
            sp.PoseCorrection(**kw)


# ---- recovering a perturbed camera --------------------------------------------------------------
@pytest.mark.parametrize("about", ["centre", "scene"])
def test_a_perturbed_camera_is_recovered_on_a_fixed_scene(device, about):
    """A fixed scene of 400 Gaussians rendered by the true camera is the target; the camera
    starts turned by 2 degrees and moved by 2 % of its distance; Adam on its correction alone
    (the device's render, loss gradient, backward and camera_gradient), turned about the
    camera's centre or about the scene's, takes the rotation error down by at least 70 % and
    the translation error by at least half."""
    rng = np.random.default_rng(4)
    g = _gaussians(400, 1, seed=4, spread=0.7, log_scale=(-3.2, -2.2), logit=(0.5, 3.0))
    g["sh"][:, 0] = rng.uniform(-1.2, 1.2, (400, 3))        # strong colours: a textured view
    W = H = 48
    true = rs.look_at((0.4, -0.3, -3.0), (0, 0, 0))
    cam_true, _ = _camera(W, H, eye=(0.4, -0.3, -3.0), f=(50.0, 50.0))
    r = SplatRasterizer(device, 1)
    params = r.upload(g)
    target = r.forward(params, cam_true)[2].rgb.get()
    axis = rng.normal(size=3)
    turn = sp.so3_exp(np.radians(2.0) * axis / np.linalg.norm(axis))
    dist = float(np.linalg.norm(true[:3, 3]))
    move = rng.normal(size=3)
    given = np.eye(4)
    given[:3, :3] = turn @ true[:3, :3]
    given[:3, 3] = turn @ true[:3, 3] + 0.02 * dist * move / np.linalg.norm(move)
    cam0 = type(cam_true)(given, cam_true.fx, cam_true.fy, cam_true.cx, cam_true.cy, W, H,
                          cam_true.near)

    def errors(V):
        return (np.degrees(sp.rotation_angle(V[:3, :3] @ true[:3, :3].T)),
                float(np.linalg.norm(-V[:3, :3].T @ V[:3, 3] + true[:3, :3].T @ true[:3, 3])))
    pivot = 0.0 if about == "centre" else float(given[2, 3])   # the origin's depth
    pc = sp.PoseCorrection(1, lr=2e-3, reg=0.0, scale=dist, pivots=[pivot])
    rot0, pos0 = errors(given)
    for _ in range(150):
        cam = pc.camera(cam0, 0)
        proj, bins, ras = r.forward(params, cam)
        grad = cla.to_device(device.queue, (2.0 * (ras.rgb.get() - target) / target.size)
                             .astype(np.float32))
        g2d = r.rasterize_backward(proj, bins, ras, cam, grad)
        out = r.project_backward(params, cam, g2d, camera_grad=True)
        pc.step(0, cam.viewmat, *camera_gradient(out["camera"]))
    rot1, pos1 = errors(pc.viewmat(given, 0))
    print(f"rotation {rot0:.3f} -> {rot1:.3f} deg, position {pos0:.4f} -> {pos1:.4f}")
    assert rot1 <= 0.3 * rot0 and pos1 <= 0.5 * pos0, (rot0, rot1, pos0, pos1)


def test_refine_view_pose_brings_a_test_camera_back(device):
    """SplatModel.refine_view_pose (clrf eval --refine-poses): a model holding a fixed scene of
    400 Gaussians, a test camera given 1.5 degrees and 2 % of its distance off; the refined
    camera-to-world pose is within 30 % of the rotation error and half the centre error, and
    its render is closer to the true image than the given pose's."""
    from clrf.splat.config import SplatConfig
    from clrf.splat.model import OPENGL_TO_OPENCV, SplatModel
    rng = np.random.default_rng(8)
    g = _gaussians(400, 1, seed=8, spread=0.7, log_scale=(-3.2, -2.2), logit=(0.5, 3.0))
    g["sh"][:, 0] = rng.uniform(-1.2, 1.2, (400, 3))
    W = H = 48
    true = rs.look_at((-0.5, 0.3, -3.0), (0, 0, 0))
    dist = float(np.linalg.norm(true[:3, 3]))
    model = SplatModel(device, SplatConfig(sh_degree=1), g, (0.0, 0.0, 0.0), dist,
                       [[-1, -1, -1], [1, 1, 1]])
    intr = (50.0, 50.0, W / 2, H / 2)

    def c2w_of(V):
        return np.linalg.inv(OPENGL_TO_OPENCV @ V)
    target = model.render_image(c2w_of(true), intr, (H, W), depth=False)["rgb"]
    axis, move = rng.normal(size=3), rng.normal(size=3)
    turn = sp.so3_exp(np.radians(1.5) * axis / np.linalg.norm(axis))
    given = np.eye(4)
    given[:3, :3] = turn @ true[:3, :3]
    given[:3, 3] = turn @ true[:3, 3] + 0.02 * dist * move / np.linalg.norm(move)

    def errors(c2w):
        V = OPENGL_TO_OPENCV @ np.linalg.inv(c2w)
        return (np.degrees(sp.rotation_angle(V[:3, :3] @ true[:3, :3].T)),
                float(np.linalg.norm(-V[:3, :3].T @ V[:3, 3] + true[:3, :3].T @ true[:3, 3])))
    c2w, summary = model.refine_view_pose(c2w_of(given), intr, (H, W), target, 120, 3e-3)
    (rot0, pos0), (rot1, pos1) = errors(c2w_of(given)), errors(c2w)
    print(f"rotation {rot0:.3f} -> {rot1:.3f} deg, position {pos0:.4f} -> {pos1:.4f}")
    assert rot1 <= 0.3 * rot0 and pos1 <= 0.5 * pos0, (rot0, rot1, pos0, pos1)
    assert summary["images"] == 1 and summary["rotation_deg"] > 0.3 * 1.5
    err = [np.mean((model.render_image(c, intr, (H, W), depth=False)["rgb"] - target) ** 2)
           for c in (c2w_of(given), c2w)]
    assert err[1] < 0.25 * err[0], err
    with pytest.raises(ValueError):
        model.refine_view_pose(c2w, intr, (H, W), target, 0, 1e-3)


# ---- through the trainer and the command line ----------------------------------------------------
@pytest.mark.slow
def test_a_run_refines_saves_reports_and_resumes_its_poses(tmp_path, capsys):
    from clrf.cli.main import main as cli
    from clrf.outputs import checkpoint
    out = tmp_path / "run"
    args = ["--quiet", "train", "--model", "splat", "--out", str(out), "--max-seconds", "120",
            "--set", "train.max_iters=40", "--set", "splat.preset=tiny", "--set",
            "splat.pose_opt=true", "--set", "splat.pose_opt_after=0", "--set",
            "train.eval_views=1"]
    assert cli(args) == 0
    st = checkpoint.load(out)
    steps = np.asarray(st["pose_steps"])
    assert st["pose"].shape == (len(steps), 6) and steps.sum() == st["step"] == 40
    assert np.all(np.isfinite(st["pose"])) and np.abs(st["pose"][steps > 0]).max() > 0
    final = json.loads((out / "eval.json").read_text())
    pc = final["pose_correction"]
    assert pc["images"] == int((steps > 0).sum()) and pc["rotation_deg"] > 0
    capsys.readouterr()
    assert cli(["eval", "--ckpt", str(out), "--max-views", "1", "--lpips", "none",
                "--out", str(tmp_path / "e.json")]) == 0
    said = capsys.readouterr().out
    assert "training poses corrected by" in said
    assert json.loads((tmp_path / "e.json").read_text())["pose_correction"] == pc
    # BARF's protocol beside the plain scores: each test view refined against its own image
    assert cli(["eval", "--ckpt", str(out), "--max-views", "2", "--lpips", "none",
                "--refine-poses", "3", "--out", str(tmp_path / "r.json")]) == 0
    assert "with each test view's pose refined (3 steps" in capsys.readouterr().out
    r = json.loads((tmp_path / "r.json").read_text())
    assert r["n_views"] == 2 and r["poses_refined"]["steps"] == 3
    assert np.isfinite(r["psnr_poses_refined"]) and 0 < r["ssim_poses_refined"] <= 1
    assert r["poses_refined"]["rotation_deg"] > 0
    assert all("psnr_poses_refined" in m for m in r["views"])
    for bad, why in ((["--refine-poses", "2", "--downscale", "2"], "--downscale"),
                     (["--refine-poses", "-1"], "step count"),
                     (["--refine-poses", "2", "--refine-poses-lr", "0"], "--refine-poses-lr")):
        assert cli(["eval", "--ckpt", str(out), "--max-views", "1", "--lpips", "none",
                    "--out", str(tmp_path / "bad.json"), *bad]) == 2
        assert why in capsys.readouterr().err
        assert not (tmp_path / "bad.json").exists()
    # resumed: the corrections and their Adam state carry on
    assert cli(["--quiet", "train", "--out", str(out), "--resume", "--set",
                "train.max_iters=60"]) == 0
    st2 = checkpoint.load(out)
    assert np.asarray(st2["pose_steps"]).sum() == 60
    assert np.all(np.asarray(st2["pose_steps"]) >= steps)


@pytest.mark.parametrize("setting", ["splat.lr_pose=0", "splat.lr_pose=-1",
                                     "splat.pose_reg=-0.1", "hash.lr_pose=0",
                                     "hash.lr_pose_final=1"])
def test_bad_pose_settings_are_one_clear_error(setting, tmp_path, capsys):
    from clrf.cli.main import main as cli
    model = setting.split(".")[0]
    rc = cli(["--quiet", "train", "--model", model, "--out", str(tmp_path / "run"),
              "--set", "splat.pose_opt=true" if model == "splat" else "train.seed=0",
              "--set", setting, "--max-seconds", "1"])
    err = capsys.readouterr().err
    assert rc == 2 and err.count("clrf: error:") == 1 and setting.split("=")[0] in err, err
    assert not (tmp_path / "run").exists()


@pytest.mark.slow
def test_the_measurement_tools_perturb_and_score_poses(tmp_path, scene):
    """tools/perturb_capture.py --poses turns every training camera by exactly 1 degree and
    moves it by 1 % of its distance; tools/pose_error.py reads those errors back from a run on
    the perturbed copy, and the corrected ones where the run refined its poses."""
    import subprocess
    import sys
    from pathlib import Path
    root = Path(__file__).resolve().parents[1]
    src = scene("lego_400")
    cap = tmp_path / "lego_poses"
    subprocess.run([sys.executable, str(root / "tools" / "perturb_capture.py"), str(src),
                    str(cap), "--poses"], check=True, capture_output=True)
    from clrf.cli.main import main as cli
    out = tmp_path / "run"
    assert cli(["--quiet", "train", "--model", "splat", "--data", str(cap), "--out", str(out),
                "--max-seconds", "2", "--set", "splat.preset=tiny", "--set",
                "splat.pose_opt=true", "--set", "train.downscale=8", "--set",
                "train.final_eval=false", "--set", "train.eval_views=1"]) == 0
    p = subprocess.run([sys.executable, str(root / "tools" / "pose_error.py"), str(out),
                        str(src), "--json"], capture_output=True, text=True, check=True)
    res = json.loads(p.stdout)
    assert res["views"] == 100
    assert res["given"]["rotation_deg"] == pytest.approx(1.0, abs=1e-6)
    assert res["given"]["centre"] == pytest.approx(0.01 * res["camera_distance"], rel=1e-6)
    assert np.isfinite(res["corrected"]["rotation_deg"]) and "rotation_error_reduction" in res
    assert np.isfinite(res["corrected_aligned"]["rotation_deg"])
    assert "rotation_error_reduction_aligned" in res
    # 100 random 1-degree turns hardly share a common part: aligning removes little of them
    assert 0.8 < res["given_aligned"]["rotation_deg"] < 1.1


def test_pose_error_alignment_removes_a_common_similarity():
    """tools/pose_error.py's Umeyama alignment: cameras that are the true ones moved together by
    a similarity of the world (scale, turn, shift) align back exactly; per-camera errors stay."""
    import importlib.util
    from pathlib import Path
    path = Path(__file__).resolve().parents[1] / "tools" / "pose_error.py"
    spec = importlib.util.spec_from_file_location("pose_error", path)
    pe = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(pe)
    rng = np.random.default_rng(3)
    true = [rs.look_at(rng.normal(size=3) * 3 + 0.1, (0, 0, 0)) for _ in range(12)]
    Q, s, b = sp.so3_exp([0.1, -0.2, 0.05]), 1.3, np.array([0.2, -0.1, 0.4])
    moved = []
    for T in true:       # the world x -> s Q x + b, the cameras with it
        V = np.eye(4)
        V[:3, :3] = T[:3, :3] @ Q.T
        V[:3, 3] = s * T[:3, 3] - T[:3, :3] @ Q.T @ b
        moved.append(V)
    assert pe.errors(moved, true)["rotation_deg"] > 5
    back = pe.errors(pe.aligned(moved, true), true)
    assert back["rotation_deg"] < 1e-6 and back["centre"] < 1e-9
    turned = [np.diag([1.0, 1, 1, 1]) for _ in true]
    for i, V in enumerate(moved):
        turned[i][:3, :3] = sp.so3_exp(np.radians(1.0) * np.eye(3)[i % 3]) @ V[:3, :3]
        turned[i][:3, 3] = sp.so3_exp(np.radians(1.0) * np.eye(3)[i % 3]) @ V[:3, 3]
    # each turned about its own centre: the centres align exactly, the turns remain
    left = pe.errors(pe.aligned(turned, true), true)
    assert left["centre"] < 1e-9 and left["rotation_deg"] == pytest.approx(1.0, abs=1e-6)


# ---- the frame held --------------------------------------------------------------------------
def test_so3_log_inverts_exp_from_zero_to_a_half_turn():
    rng = np.random.default_rng(5)
    for th in (0.0, 1e-9, 1e-5, 0.3, 2.0, np.pi - 1e-3, np.pi - 1e-7, np.pi):
        axis = rng.normal(size=3)
        w = th * axis / np.linalg.norm(axis)
        back = sp.so3_log(sp.so3_exp(w))
        # a half turn about a is one about -a: compare the rotations there
        np.testing.assert_allclose(sp.so3_exp(back), sp.so3_exp(w), atol=1e-9)
        if th < np.pi - 1e-3:
            np.testing.assert_allclose(back, w, atol=1e-9)


def _frame_case(n=9, seed=7):
    """Given world-to-camera transforms of n cameras looking at the origin, a correction with
    pivots, and a rigid motion G of the world (0.8 degrees, 2 % of the scale)."""
    rng = np.random.default_rng(seed)
    given = [rs.look_at(rng.normal(size=3) * 3 + 0.1, (0, 0, 0)) for _ in range(n)]
    pc = sp.PoseCorrection(n, lr=1e-3, reg=0.0, scale=3.0, pivots=rng.uniform(0, 4, n))
    G = sp.twist_matrix(np.radians(0.8) * np.array([0.6, -0.8, 0.0]), [0.03, -0.05, 0.02])
    return rng, given, pc, G


@dataclass
class _Cam:
    viewmat: np.ndarray


def _rendered(pc, given):
    """Every camera rendered once (the correction records its given transform)."""
    return [pc.camera(_Cam(V), v).viewmat for v, V in enumerate(given)]


def test_a_common_motion_of_every_camera_is_taken_out():
    """Corrections that all move the world by one rigid motion are the frame's, not the
    cameras': after a pass they are gone, to float64 rounding, and the frame records it."""
    rng, given, pc, G = _frame_case()
    for v, V in enumerate(given):
        pc.set_viewmat(v, V, V @ G)
    pc.steps[:] = 1
    _rendered(pc, given)
    assert np.degrees(np.abs(pc.params[:, :3]).max()) > 0.3
    out = pc.remove_common_motion()
    assert np.abs(pc.params).max() < 1e-9
    np.testing.assert_allclose(sp.twist_matrix(out[:3], out[3:]), G, atol=1e-9)
    assert pc.summary()["frame_rotation_deg"] == pytest.approx(0.8, abs=1e-6)


def test_a_common_scale_of_every_camera_is_taken_out():
    """Corrections that move every camera as the world moved and scaled by 1 % would move
    the scene with them (the images cannot tell): after a pass they are gone, and the frame
    records the scale; with hold_scale=False only the rigid part goes and the scale stays."""
    rng, given, pc, G = _frame_case()
    omega, nu = sp.so3_log(G[:3, :3]), G[:3, 3]
    keep = sp.PoseCorrection(len(given), 1e-3, 0.0, 3.0, pivots=pc.pivots, hold_scale=False)
    for c in (pc, keep):
        for v, V in enumerate(given):
            c.set_viewmat(v, V, sp.similar_viewmat(V, omega, nu, np.log(1.01)))
        c.steps[:] = 1
        _rendered(c, given)
    pc.remove_common_motion()
    assert np.abs(pc.params).max() < 1e-9
    assert pc.summary()["frame_scale_rel"] == pytest.approx(0.01, abs=1e-9)
    assert "a scale of +1.00 %" in pc.report(pc.summary())
    keep.remove_common_motion()
    left = [keep.viewmat(V, v) for v, V in enumerate(given)]
    for V, L in zip(given, left):     # what is left is the scale alone
        np.testing.assert_allclose(L[:3, :3], V[:3, :3], atol=1e-9)
        np.testing.assert_allclose(L[:3, 3], 1.01 * V[:3, 3], atol=1e-9)
    assert keep.frame_scale == 0.0


def test_a_similarity_and_its_removal_are_inverse():
    rng = np.random.default_rng(3)
    V = rs.look_at(rng.normal(size=3) * 3, (0, 0, 0))
    w, nu, s = rng.normal(size=3) * 0.1, rng.normal(size=3) * 0.2, 0.05
    back = sp.remove_similarity(sp.similar_viewmat(V, w, nu, s), w, nu, s)
    np.testing.assert_allclose(back, V, atol=1e-12)
    # the camera sees the moved and scaled world as V saw the world: a point x at e^s G^-1 x
    x = rng.normal(size=3)
    G = sp.twist_matrix(w, nu)
    y = np.exp(s) * (np.linalg.inv(G) @ np.append(x, 1.0))[:3]
    a = (V @ np.append(x, 1.0))[:3]
    b = (sp.similar_viewmat(V, w, nu, s) @ np.append(y, 1.0))[:3]
    np.testing.assert_allclose(b / b[2], a / a[2], atol=1e-12)


def test_taking_the_frame_out_keeps_what_each_camera_corrected():
    """Corrections of their own plus a common motion: afterwards every corrected camera is
    its corrected camera before moved by one and the same similarity of the world (the scene
    sees the same relative poses: the world's scale taken out, then one rigid motion), the
    common motion fitted to what is left is nil, and an untrained image keeps the identity."""
    rng, given, pc, G = _frame_case()
    for v, V in enumerate(given[:-1]):
        own = sp.corrected_viewmat(V, rng.normal(size=3) * 0.01, rng.normal(size=3) * 0.02,
                                   pc.pivots[v])
        pc.set_viewmat(v, V, own @ G)
    pc.steps[:-1] = 1
    _rendered(pc, given)
    before = [pc.viewmat(V, v) for v, V in enumerate(given)]
    pc.remove_common_motion()
    after = [pc.viewmat(V, v) for v, V in enumerate(given)]
    assert pc.frame_scale != 0.0
    unscaled = [sp.similar_viewmat(b, np.zeros(3), np.zeros(3), -pc.frame_scale)
                for b in before[:-1]]
    H = [np.linalg.inv(b) @ a for a, b in zip(after[:-1], unscaled)]
    for h in H:
        np.testing.assert_allclose(h, H[0], atol=1e-12)
    assert sp.rotation_angle(H[0][:3, :3]) > np.radians(0.5)
    # each fit leaves a rest of second order in the corrections (about 1 %): three leave
    # 1e-6 of the 0.014 radians taken out
    rest = sp.common_motion(given[:-1], after[:-1], pc.scale)
    assert np.abs(np.hstack(rest)).max() < 1e-7
    assert not pc.params[-1].any()


def test_a_free_frame_keeps_its_corrections_and_the_frame_is_saved():
    rng, given, pc, G = _frame_case()
    free = sp.PoseCorrection(len(given), 1e-3, 0.0, 3.0, pivots=pc.pivots, hold_frame=False)
    for c in (pc, free):
        for v, V in enumerate(given):
            c.set_viewmat(v, V, V @ G)
        c.steps[:] = 1
        _rendered(c, given)
    kept = free.params.copy()
    free.after_pass()
    np.testing.assert_array_equal(free.params, kept)
    pc.after_pass()
    back = sp.PoseCorrection(len(given), 1e-3, 0.0, 3.0, state=pc.state_dict())
    np.testing.assert_array_equal(back.frame, pc.frame)
    assert "common motion of 0.800 deg" in pc.report(pc.summary())
    assert "common motion" not in free.report(free.summary())


def test_no_step_before_the_start_fraction():
    """``start`` (splat.pose_opt_after): the corrections hold still until the budget reaches
    it, then step as ever; a start outside [0, 1) is refused."""
    pc = sp.PoseCorrection(2, lr=1e-3, reg=0.0, scale=1.0, start=0.25)
    dR, dt = np.arange(9.0).reshape(3, 3), np.ones(3)
    pc.schedule(0.2)
    pc.step(0, np.eye(4), dR, dt)
    assert not pc.params.any() and pc.steps.tolist() == [0, 0]
    pc.schedule(0.25)
    pc.step(0, np.eye(4), dR, dt)
    assert pc.params[0].any() and pc.steps.tolist() == [1, 0]
    for bad in (-0.1, 1.0):
        with pytest.raises(ValueError, match="start"):
            sp.PoseCorrection(2, 1e-3, 0.0, 1.0, start=bad)


def test_the_batched_steps_are_the_single_steps():
    """step_many (hundreds of images a ray batch) takes the Adam steps that step takes one
    image at a time, rotations near 0 (the series) and far from it alike; a non-finite
    gradient leaves its image alone; the batched maths match the single functions."""
    rng = np.random.default_rng(11)
    n = 7
    given = np.stack([rs.look_at(rng.normal(size=3) * 3 + 0.1, (0, 0, 0)) for _ in range(n)])
    one = sp.PoseCorrection(n, lr=2e-3, reg=1e-3, scale=3.0, pivots=rng.uniform(0, 4, n))
    many = sp.PoseCorrection(n, lr=2e-3, reg=1e-3, scale=3.0, pivots=one.pivots)
    one.params[:] = rng.normal(size=(n, 6)) * np.array([0.3] * 3 + [0.1] * 3)
    one.params[0, :3] = 1e-8                        # the series branch
    many.params[:] = one.params
    vs = np.array([5, 0, 2, 6, 3])
    for it in range(3):
        dR = rng.normal(size=(len(vs), 3, 3))
        dt = rng.normal(size=(len(vs), 3))
        if it == 1:
            dt[2, 0] = np.nan                       # image 2 keeps its pose this step
        vm = many.viewmats(given[vs], vs)
        for k, v in enumerate(vs):
            np.testing.assert_allclose(vm[k], one.viewmat(given[v], v), rtol=0, atol=1e-14)
            one.step(v, vm[k], dR[k], dt[k])
        many.step_many(vs, vm, dR, dt)
        np.testing.assert_allclose(many.params, one.params, rtol=1e-13, atol=1e-16)
        np.testing.assert_array_equal(many.steps, one.steps)
    assert many.steps[2] == 2 and many.steps[1] == 0
    w = rng.normal(size=(4, 3))
    w[0] = 0.0
    for k in range(4):
        np.testing.assert_allclose(sp.so3_exps(w)[k], sp.so3_exp(w[k]), atol=1e-15)
        np.testing.assert_allclose(sp.left_jacobians(w)[k], sp.left_jacobian(w[k]), atol=1e-15)
