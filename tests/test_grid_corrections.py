"""grid.pose_opt and grid.exposure in the grid model: the step's gradient through the exposure
transform against the float64 render's, a perturbed camera pulled toward its true pose, gains
learned, checkpoints with the corrections (and older ones without), and one clear error for
each refused or bad setting (each ray's camera gradient: tests/test_grid_pose.py)."""
import dataclasses

import numpy as np
import pyopencl.array as cla
import pytest

import clrf
from clrf.references import reference as ref
from clrf.testing import tolerances as tol


def _up(dev, a, dtype=np.float32):
    return cla.to_device(dev.queue, np.ascontiguousarray(a, dtype))


# ---- the model -----------------------------------------------------------------------------
FROZEN = dict(lr_density=1e-12, lr_density_final=1e-12, lr_sh=1e-12, lr_sh_final=1e-12,
              lambda_tv=0.0, lambda_tv_sh=0.0, lambda_beta=0.0)   # the scene held still


def _model(device, reso=24, **cfg):
    """A GridModel over [-4, 4]^3 holding a smooth blob (radius ~1.5) whose colour varies
    across it, SH degree 1, empty in its outer shells; the cameras below sit inside the box,
    so each ray's march starts at its origin and the held sample distances are the march's
    (the step loss is the function the ray gradient differentiates)."""
    from clrf.grid.config import GridConfig
    from clrf.grid.model import GridModel
    bbox = np.array([[-4.0] * 3, [4.0] * 3])
    c = (np.arange(reso) + 0.5) / reso * 8.0 - 4.0
    x, y, z = np.meshgrid(c, c, c, indexing="ij")
    r2 = x * x + y * y + z * z
    dens = np.where(r2 < 9.0, 6.0 * np.exp(-r2 / 1.2), 0.0).astype(np.float32)
    sh = np.zeros((reso,) * 3 + (12,), np.float32)
    for ch, (f, p) in enumerate(((1.3, x), (1.1, y), (0.9, z))):
        sh[..., ch * 4] = 0.8 * np.sin(f * p + ch)         # the DC term of each channel
        sh[..., ch * 4 + 3] = 0.2 * np.cos(p)              # some view dependence
    sh[dens == 0] = 0
    grid = clrf.SparseGrid.from_dense(device, dens, sh, bbox)
    gc = GridConfig(reso=[[reso] * 3], upsample_at=[], sh_degree=1, step=0.5, **{**FROZEN, **cfg})
    return GridModel(device, gc, grid, (0.2, 0.3, 0.4))


def _view(c2w, hw=(16, 16), focal=14.0):
    from clrf.data.cameras import _posed, camera_dirs
    d_cam = camera_dirs([focal, focal, hw[1] / 2, hw[0] / 2], *hw).reshape(-1, 3)
    return _posed(np.asarray(c2w, np.float64)[None], d_cam)


def _given_pose(c2w_true, w, tau, pivot):
    """The camera-to-world whose correction (w, tau) about ``pivot`` is the true camera
    (clrf/corrections/pose.py's parametrisation)."""
    from clrf.corrections.pose import so3_exp
    from clrf.corrections.ray_pose import OPENGL_TO_OPENCV, viewmat_of
    V = viewmat_of(c2w_true)
    E = so3_exp(-np.asarray(w))
    p = np.array([0.0, 0.0, pivot])
    V0 = np.eye(4)
    V0[:3, :3] = E @ V[:3, :3]
    V0[:3, 3] = E @ (V[:3, 3] - p - tau) + p
    return np.linalg.inv(OPENGL_TO_OPENCV @ V0), V0


CAMERAS = (([0.3, -3.0, 0.8], [2.8, 1.0, -0.5], [-2.5, 1.5, 1.2], [0.5, 2.9, -1.0]))


def _looks(eyes):
    from clrf.data.cameras import look_at
    return [look_at(e, [0.0, 0.0, 0.0]) for e in eyes]


def _batch(device, rays, targets):
    return (_up(device, np.concatenate([r[0] for r in rays])),
            _up(device, np.concatenate([r[1] for r in rays])),
            _up(device, np.concatenate(targets)),
            _up(device, np.arange(sum(len(t) for t in targets)), np.int32))


def _pose_scene(device, **cfg):
    """(model, (w*, tau*), batch, pixels): two 16 x 16 views rendered from their true
    cameras; image 0's rays made by a given camera off by a known correction (w*, tau*)."""
    from clrf.corrections.ray_pose import pivot_depth, viewmat_of
    from clrf.data.cameras import look_at
    model = _model(device, pose_opt=True, **cfg)
    c2w = [look_at(e, [0.0, 0.0, 0.0]) for e in CAMERAS[:2]]
    star = (np.array([0.02, -0.015, 0.01]), np.array([-0.03, 0.04, 0.01]))
    pivots = [pivot_depth(viewmat_of(p), model.grid.bbox) for p in c2w]
    given, vm0 = _given_pose(c2w[0], *star, pivots[0])
    targets = [model.render(*_view(p))["rgb"] for p in c2w]
    pixels = len(targets[0])
    model.attach_corrections(2, pixels, False, viewmats=lambda: np.stack(
        [vm0, viewmat_of(c2w[1])]), pivots=lambda: pivots)
    return model, star, _batch(device, [_view(given), _view(c2w[1])], targets), pixels


def test_pose_opt_moves_a_perturbed_camera_toward_its_true_pose(device):
    """Steps of grid.pose_opt (the scene held still) bring image 0's correction toward the
    known (w*, tau*) (0.025 rad, 0.05 units): the error falls to a quarter in 150 steps, and
    the first Adam step (lr times the gradient's sign) moves each coordinate of (w*, tau*)
    larger than 0.015 that way; image 1, at its true pose, stays near it."""
    model, star, (o, d, target, index), _ = _pose_scene(
        device, lr_pose=3e-3, lr_pose_final=3e-3, pose_reg=0.0, pose_hold_frame=False)
    assert model.ray_index and "pose" in model.describe()
    pose = model.corrections.get("pose")
    w_star, tau_star = star
    want = np.concatenate([w_star, tau_star / model.extent])

    def error():
        p = pose.pose.params[0]
        return np.linalg.norm(np.concatenate([p[:3], p[3:] / model.extent]) - want)

    before = error()
    for it in range(150):
        assert np.isfinite(float(model.train_step(it, o, d, target, index=index)))
        if it == 0:
            first = pose.pose.params[0].copy()
            big = np.abs(np.concatenate([w_star, tau_star])) > 0.015
            assert np.all(np.sign(first[big]) == np.sign(
                np.concatenate([w_star, tau_star])[big])), (first, star)
    assert error() < 0.25 * before, (before, error(), pose.pose.params[0], star)
    p1 = pose.pose.params[1]
    assert np.all(np.abs(p1[:3]) < 0.25 * np.abs(w_star).max()), p1
    assert pose.pose.steps.tolist() == [150, 150]
    with pytest.raises(ValueError, match="index"):
        model.train_step(150, o, d, target)


def _exposure_scene(device, gains, **cfg):
    """(model, batch, pixels): views from CAMERAS rendered by the model, image v's colours
    times gains[v] (no clipping: the transform can fit them exactly)."""
    from clrf.data.cameras import look_at
    model = _model(device, exposure=True, **cfg)
    c2w = [look_at(e, [0.0, 0.0, 0.0]) for e in CAMERAS[:len(gains)]]
    rays = [_view(p) for p in c2w]
    targets = [model.render(*r)["rgb"] * np.float32(g) for r, g in zip(rays, gains)]
    pixels = len(targets[0])
    model.attach_corrections(len(gains), pixels, False)
    return model, _batch(device, rays, targets), pixels


def test_exposure_gradient_is_the_gradient_through_the_transform(device):
    """With each image's transform a random (A, b) near the identity, the step's grid
    gradient is the float64 render's backward of dL/dpixel = 2 s A^T r (r = A pixel + b -
    target, s = 1 / (3 B)) and its loss s sum |r|^2: the whole pixel, background
    included, goes through the transform."""
    model, (o, d, target, index), pixels = _exposure_scene(device, (1.0, 1.0),
                                                           exposure_matrix="full")
    rng = np.random.default_rng(90)
    exp = model.corrections.colour
    rows = exp.rows() + rng.normal(0, 0.1, exp.rows().shape)
    exp.P.set(rows.astype(np.float32))
    rows = exp.P.get().astype(np.float64)
    target.set(rng.uniform(0, 1, target.shape).astype(np.float32))
    model.opt_density.step = model.opt_sh.step = lambda *a, **k: None   # keep the gradients
    loss = float(model.train_step(0, o, d, target, index=index))
    dens, sh = model.grid.to_dense()
    on, dn, tg = o.get(), d.get(), target.get().astype(np.float64)
    pix = ref.render_forward(dens, sh, model.grid.bbox, on, dn, 0.5, model.background)["rgb"]
    A, b = rows[index.get() // pixels, :9].reshape(-1, 3, 3), rows[index.get() // pixels, 9:]
    r = np.einsum("nij,nj->ni", A, pix) + b - tg
    B = len(tg)
    s = 1.0 / (3 * B)
    want = ref.render_backward(dens, sh, model.grid.bbox, on, dn,
                               np.einsum("nji,nj->ni", A, r), 0.5, model.background)
    gd, gs = model.grid.rows_to_dense(model.opt_density.grad.get(), model.opt_sh.grad.get())
    np.testing.assert_allclose(gd / (2 * s), want["density"], atol=tol.GRAD_ATOL,
                               rtol=tol.GRAD_RTOL)
    np.testing.assert_allclose(gs / (2 * s), want["sh"], atol=tol.GRAD_ATOL, rtol=tol.GRAD_RTOL)
    assert np.abs(want["density"]).max() > 0.1
    np.testing.assert_allclose(loss, s * np.sum(r * r), rtol=1e-5)


def test_a_masked_captures_gradient_leaves_its_background_alone(device):
    """A masked (RGBA) capture: the loss compares out = A C + (1 - T) b + T bg with the
    target (the transform leaves the composited background alone), and the step's gradient is
    the float64 render's backward of that loss: C + T bg' rendered on each ray's bg' = A^-1 (bg
    - b) and dL/dpixel' = 2 s A^T r, the densities' share through T included."""
    from clrf.references import reference_exposure as rex
    model, (o, d, target, index), pixels = _exposure_scene(device, (1.0, 1.0),
                                                           exposure_matrix="full")
    model.attach_corrections(2, pixels, True)
    rng = np.random.default_rng(91)
    exp = model.corrections.colour
    exp.P.set((exp.rows() + rng.normal(0, 0.1, exp.rows().shape)).astype(np.float32))
    rows = exp.P.get().astype(np.float64)
    target.set(rng.uniform(0, 1, target.shape).astype(np.float32))
    model.opt_density.step = model.opt_sh.step = lambda *a, **k: None   # keep the gradients
    loss = float(model.train_step(0, o, d, target, index=index))
    dens, sh = model.grid.to_dense()
    on, dn, tg, ix = o.get(), d.get(), target.get().astype(np.float64), index.get()
    bg = np.asarray(model.background, np.float64)
    black = ref.render_forward(dens, sh, model.grid.bbox, on, dn, 0.5, (0, 0, 0), record=True)
    C, T = black["rgb"], black["T_end"]
    A, b = rows[ix // pixels, :9].reshape(-1, 3, 3), rows[ix // pixels, 9:]
    r = np.einsum("nij,nj->ni", A, C) + (1 - T)[:, None] * b + T[:, None] * bg - tg
    B = len(tg)
    s = 1.0 / (3 * B)
    np.testing.assert_allclose(loss, s * np.sum(r * r), rtol=1e-5)
    behind = rex.rays_behind(rows, ix, pixels, bg)
    assert np.abs(behind - bg).max() > 0.05
    want = ref.render_backward(dens, sh, model.grid.bbox, on, dn,
                               np.einsum("nji,nj->ni", A, r), 0.5, behind)
    gd, gs = model.grid.rows_to_dense(model.opt_density.grad.get(), model.opt_sh.grad.get())
    np.testing.assert_allclose(gd / (2 * s), want["density"], atol=tol.GRAD_ATOL,
                               rtol=tol.GRAD_RTOL)
    np.testing.assert_allclose(gs / (2 * s), want["sh"], atol=tol.GRAD_ATOL, rtol=tol.GRAD_RTOL)
    # the densities' gradient differs from the unmasked transform's (the background's share)
    plain = ref.render_backward(dens, sh, model.grid.bbox, on, dn,
                                np.einsum("nji,nj->ni", A, r), 0.5, bg)
    assert np.abs(plain["density"] - want["density"]).max() > 100 * tol.GRAD_ATOL


def test_exposure_learns_each_images_gain(device):
    """Images whose colours are scaled by gains (geometric mean 1, so the recentring keeps
    them) on a scene held still: after 150 steps of grid.exposure (gain matrices) each
    image's diagonal has come at least two thirds of the way to its gain."""
    gains = (0.8, 1.25, 0.7, 1 / 0.7)
    model, (o, d, target, index), _ = _exposure_scene(
        device, gains, exposure_matrix="gain", lr_exposure=0.01, exposure_reg=0.0)
    exp = model.corrections.colour
    for it in range(150):
        assert np.isfinite(float(model.train_step(it, o, d, target, index=index)))
    diag = exp.rows()[:, [0, 4, 8]]
    for v, g in enumerate(gains):
        assert np.all(np.abs(diag[v] - g) < np.abs(1 - g) / 3), (v, g, diag[v])
    assert np.all(exp.rows()[:, [1, 2, 3, 5, 6, 7, 9, 10, 11]] == 0)


def test_sh_diffuse_until_trains_band_0_alone_before_it(device):
    """grid.sh_diffuse_until 0.5 with grid.exposure: steps before half the budget move each
    channel's band-0 coefficient and leave bands 1.. exactly as they were (their gradients
    consumed); from the fraction on every band steps."""
    from types import SimpleNamespace
    model, (o, d, target, index), _ = _exposure_scene(
        device, (0.8, 1.25), lr_sh=1e-2, lr_sh_final=1e-2, sh_diffuse_until=0.5)
    dc = np.arange(12) % 4 == 0
    sh0 = model.grid.sh.get()
    assert "SH band 0 alone" in model.describe()
    for it in range(3):
        model.on_iteration(it, SimpleNamespace(fraction=0.1 * it))
        model.train_step(it, o, d, target, index=index)
    sh1 = model.grid.sh.get()
    np.testing.assert_array_equal(sh1[:, ~dc], sh0[:, ~dc])
    assert np.any(sh1[:, dc] != sh0[:, dc])
    assert not np.any(model.opt_sh.grad.get()) and not np.any(model.opt_sh.state.get()[:, ~dc])
    model.on_iteration(3, SimpleNamespace(fraction=0.5))
    assert "SH band 0" not in model.describe()
    model.train_step(3, o, d, target, index=index)
    assert np.any(model.grid.sh.get()[:, ~dc] != sh1[:, ~dc])


def test_checkpoint_keeps_the_corrections_and_older_ones_load(device, tmp_path):
    """A model with grid.pose_opt and grid.exposure after a few steps, through a checkpoint
    file: the same corrections, moments and rows, and the next step the same; a checkpoint
    written without them (before these keys) loads with none."""
    from clrf.grid.model import GridModel
    from clrf.outputs import checkpoint
    model, _, (o, d, target, index), _ = _pose_scene(device, exposure=True)
    for it in range(3):
        model.train_step(it, o, d, target, index=index)
    assert "pose" in model.describe() and "exposure" in model.describe()
    checkpoint.save(tmp_path / "ckpt.npz", model.state_dict())
    back = GridModel.from_state_dict(device, checkpoint.load(tmp_path / "ckpt.npz"), model.cfg)
    a, b = model.corrections.get("pose"), back.corrections.get("pose")
    for k in ("params", "m", "v", "steps", "pivots"):
        np.testing.assert_array_equal(getattr(a.pose, k), getattr(b.pose, k))
    np.testing.assert_array_equal(a.viewmats0, b.viewmats0)
    np.testing.assert_array_equal(a.rows.get(), b.rows.get())
    ea, eb = model.corrections.colour, back.corrections.colour
    np.testing.assert_array_equal(ea.rows(), eb.rows())
    assert ea.steps == eb.steps == 3 and eb.pixels == ea.pixels
    for m in (model, back):
        m.train_step(3, o, d, target, index=index)
    np.testing.assert_array_equal(a.pose.params, b.pose.params)
    np.testing.assert_array_equal(ea.rows(), eb.rows())
    old = {k: v for k, v in model.state_dict().items()
           if not k.startswith(("pose", "exposure"))}
    plain = dataclasses.replace(model.cfg, exposure=False, pose_opt=False)
    before = GridModel.from_state_dict(device, old, plain)
    assert not before.corrections and not before.ray_index
    np.testing.assert_array_equal(before.grid.density.get(), back.grid.density.get())


def test_corrections_are_refused_with_one_clear_error():
    """NDC rays are not a camera's, the distributed grid sums no corrections, and a masked
    capture's exposure renders each image on a background of its own, which the MSI
    background would replace: one ValueError naming the key and the fix each."""
    from types import SimpleNamespace

    from clrf.grid.config import GridConfig
    from clrf.grid.kind import Distributed, attach, create
    cfg = SimpleNamespace(grid=GridConfig(pose_opt=True))
    with pytest.raises(ValueError, match=r"grid.pose_opt.*NDC.*--set grid.pose_opt=false"):
        create(None, cfg, SimpleNamespace(name="fern", ndc=True), (0, 0, 0))
    for key in ("pose_opt", "exposure"):
        c = SimpleNamespace(grid=GridConfig(**{key: True}))
        with pytest.raises(ValueError, match=rf"grid.{key}.*MPI ranks.*--set grid.{key}=false"):
            Distributed(SimpleNamespace(Get_size=lambda: 2, Get_rank=lambda: 0)).check(c)
    with pytest.raises(ValueError, match=r"grid.exposure.*alpha.*--set grid.exposure=false"):
        attach(SimpleNamespace(bg_model=object()),
               SimpleNamespace(grid=GridConfig(exposure=True)),
               SimpleNamespace(name="lego", alpha=np.ones(1)))


@pytest.mark.parametrize("key,value", [("lr_pose", 0.0), ("lr_pose", -1.0),
                                       ("lr_pose_final", 0.0), ("pose_reg", -1.0),
                                       ("pose_opt_after", 1.0), ("lr_exposure", 0.0),
                                       ("exposure_reg", -0.1), ("exposure_matrix", "mixed"),
                                       ("sh_diffuse_until", 1.5), ("pose_opt_every", 0),
                                       ("pose_opt_rays", -1)])
def test_bad_settings_are_one_clear_error(key, value, capsys, tmp_path):
    from clrf.cli.main import main as cli
    rc = cli(["--quiet", "train", "--model", "grid", "--out", str(tmp_path / "run"),
              "--set", "grid.pose_opt=true", "--set", "grid.exposure=true",
              "--set", f"grid.{key}={value}", "--max-seconds", "1"])
    err = capsys.readouterr().err
    assert rc == 2 and err.count("clrf: error:") == 1 and f"grid.{key}" in err, err


@pytest.mark.slow
def test_a_grid_run_with_corrections_reports_them_and_resumes(tmp_path):
    """`clrf train` on the procedural scene with both corrections, resumed, then `clrf eval`:
    eval.json has the pose correction's summary and the half-fitted protocol of a colour
    correction, as for the hash model."""
    import json

    from clrf.cli.main import main as cli
    out = tmp_path / "run"
    assert cli(["--quiet", "train", "--out", str(out), "--max-seconds", "3",
                "--set", "grid.pose_opt=true", "--set", "grid.exposure=true",
                "--set", "train.eval_every=100"]) == 0
    ev = json.loads((out / "eval.json").read_text())
    assert ev["pose_correction"]["images"] > 0 and np.isfinite(ev["psnr_half_fitted"])
    assert cli(["--quiet", "train", "--out", str(out), "--resume", "--max-seconds", "4"]) == 0
    assert cli(["--quiet", "eval", "--ckpt", str(out), "--max-views", "2", "--lpips", "none",
                "--out", str(tmp_path / "e.json")]) == 0
    e = json.loads((tmp_path / "e.json").read_text())
    assert e["pose_correction"]["images"] > 0 and "psnr_half_fitted" in e


def test_exposure_at_the_identity_is_the_plain_step_with_an_msi_background(device):
    """With an MSI background behind the grid and every transform at the identity, the step
    with grid.exposure gives the grid and the MSI the gradients and loss of the step without
    it (the transform acts on the whole pixel, the MSI's colour included): the same up to the
    float32 rounding of target = pixel - (pixel - target)."""
    from clrf.grid.background import GridBackground
    from clrf.grid.model import GridModel
    steps = []
    for on in (False, True):
        base = _model(device)
        cfg = dataclasses.replace(base.cfg, background_layers=2, background_height=8,
                                  exposure=on)
        bgm = GridBackground.create(device, cfg, base.grid.bbox, base.background)
        m = GridModel(device, cfg, base.grid, base.background, bg_model=bgm)
        o, d = (np.concatenate(a) for a in zip(*[_view(p) for p in _looks(CAMERAS[:2])]))
        target = np.random.default_rng(5).uniform(0, 1, o.shape).astype(np.float32)
        if on:
            m.attach_corrections(2, len(o) // 2, False)
        for opt in (m.opt_density, m.opt_sh, bgm.opt_density, bgm.opt_color):
            opt.step = lambda *a, **k: None          # keep the gradients
        loss = float(m.train_step(0, _up(device, o), _up(device, d), _up(device, target),
                                  index=_up(device, np.arange(len(o)), np.int32)))
        steps.append((loss, [a.grad.get() for a in (m.opt_density, m.opt_sh, bgm.opt_density,
                                                     bgm.opt_color)]))
    (l0, g0), (l1, g1) = steps
    np.testing.assert_allclose(l1, l0, rtol=1e-6)
    for a, b in zip(g0, g1):
        assert np.abs(a).max() > 0
        np.testing.assert_allclose(b, a, rtol=0, atol=1e-5 * np.abs(a).max())
