"""`clrf process`: pose a rendered capture with known cameras and compare with the truth.

The scene is rendered here by a small numpy ray caster: a cube (half-size 0.5) at the origin
inside a closed room [-3, 3]^2 x [-1, 2], every face covered with a random multi-octave value
noise (strong texture for SIFT). 30 cameras orbit the cube (radius 1.8, height 0.6) looking at
it, so the capture is a 360 one. After pycolmap poses the images, the recovered camera centres
are aligned to the true ones with a similarity transform (Umeyama, least squares), and the
rotations and centres must agree within 1 degree and 1 % of the scene scale (the diameter of
the camera orbit).
"""
from __future__ import annotations

import json
import subprocess
import sys

import numpy as np
import pytest

pycolmap = pytest.importorskip("pycolmap", reason="clrf process needs pycolmap (clrf[process])")
imageio = pytest.importorskip("imageio")

from clrf.data.process import detect_preset, pick_frames, sharpness  # noqa: E402

W, H, FOCAL = 160, 120, 130.0         # pixels; horizontal field of view about 63 degrees
N_VIEWS, RADIUS, HEIGHT = 30, 1.8, 0.6
CONTRAST = 4.0                        # noise contrast stretch (SIFT needs strong texture)
SUPER = 3                             # supersampling per axis (anti-aliasing)
ROT_TOL_DEG = 1.0                     # the bounds
CENTRE_TOL = 0.01                     # fraction of the scene scale (orbit diameter)
BOXES = [(np.array([-0.5, -0.5, -0.5]), np.array([0.5, 0.5, 0.5]), False),   # the cube
         (np.array([-3.0, -3.0, -1.0]), np.array([3.0, 3.0, 2.0]), True)]     # the room (inside)


def _noise_tables(seed=3):
    rng = np.random.default_rng(seed)
    # per (box, face): octaves of random RGB grids, sampled bilinearly
    return [[[rng.random((r + 1, r + 1, 3)) for r in (4, 9, 19, 41)] for _ in range(6)]
            for _ in BOXES]


def _bilinear(grid, u, v):
    r = grid.shape[0] - 1
    x, y = np.clip(u, 0, 1) * r, np.clip(v, 0, 1) * r
    x0, y0 = np.minimum(x.astype(int), r - 1), np.minimum(y.astype(int), r - 1)
    fx, fy = (x - x0)[..., None], (y - y0)[..., None]
    return ((1 - fx) * (1 - fy) * grid[y0, x0] + fx * (1 - fy) * grid[y0, x0 + 1]
            + (1 - fx) * fy * grid[y0 + 1, x0] + fx * fy * grid[y0 + 1, x0 + 1])


def _hit_box(o, d, lo, hi, inside):
    """Ray parameter of the first hit with the box (from outside) or its wall (from inside)."""
    with np.errstate(divide="ignore", invalid="ignore"):
        t1, t2 = (lo - o) / d, (hi - o) / d
    tn, tf = np.minimum(t1, t2).max(-1), np.maximum(t1, t2).min(-1)
    if inside:
        return np.where(tf > 0, tf, np.inf)
    return np.where((tn <= tf) & (tn > 1e-6), tn, np.inf)


def _shade(p, lo, hi, tables):
    """Noise colour at surface points p [M, 3] of box (lo, hi): the face is the axis where p is
    closest to a side; (u, v) are the other two coordinates normalised to [0, 1]."""
    gap = np.stack([np.abs(p - lo), np.abs(p - hi)], 1)            # [M, 2, 3]
    idx = gap.reshape(len(p), 6).argmin(-1)
    side, axis = idx // 3, idx % 3
    rgb = np.zeros((len(p), 3))
    for a in range(3):
        for s in range(2):
            m = (axis == a) & (side == s)
            if not m.any():
                continue
            ua, va = [k for k in range(3) if k != a]
            u = (p[m, ua] - lo[ua]) / (hi[ua] - lo[ua])
            v = (p[m, va] - lo[va]) / (hi[va] - lo[va])
            octs = tables[2 * a + s]
            rgb[m] = sum(_bilinear(g, u, v) for g in octs) / len(octs)
    return np.clip((rgb - 0.5) * CONTRAST + 0.5, 0, 1)


def _c2w(i, n=N_VIEWS):
    """OpenCV camera-to-world (x right, y down, z forward) of view i on the orbit."""
    a = 2 * np.pi * i / n
    c = np.array([RADIUS * np.cos(a), RADIUS * np.sin(a), HEIGHT])
    z = -c / np.linalg.norm(c)
    x = np.cross(z, [0, 0, 1.0])
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    m = np.eye(4)
    m[:3, :3] = np.stack([x, y, z], 1)
    m[:3, 3] = c
    return m


def render(c2w, tables):
    """[H, W, 3] uint8 view through the pinhole camera (FOCAL, centre (W/2, H/2))."""
    s = (np.arange(SUPER) + 0.5) / SUPER
    u = (np.arange(W)[:, None] + s[None]).ravel()
    v = (np.arange(H)[:, None] + s[None]).ravel()
    uu, vv = np.meshgrid(u, v)
    d = np.stack([(uu - W / 2) / FOCAL, (vv - H / 2) / FOCAL, np.ones_like(uu)], -1)
    d = d.reshape(-1, 3) @ c2w[:3, :3].T
    o = np.broadcast_to(c2w[:3, 3], d.shape)
    ts = np.stack([_hit_box(o, d, lo, hi, ins) for lo, hi, ins in BOXES])
    which, t = ts.argmin(0), ts.min(0)
    rgb = np.zeros_like(d)
    for k, (lo, hi, _) in enumerate(BOXES):
        m = which == k
        rgb[m] = _shade(o[m] + t[m, None] * d[m], lo, hi, tables[k])
    img = rgb.reshape(H, SUPER, W, SUPER, 3).mean((1, 3))
    return np.clip(img * 255 + 0.5, 0, 255).astype(np.uint8)


@pytest.fixture(scope="module")
def capture(tmp_path_factory):
    tables = _noise_tables()
    root = tmp_path_factory.mktemp("capture")
    (root / "images").mkdir()
    poses = {}
    for i in range(N_VIEWS):
        name = f"view_{i:03d}.png"
        poses[name] = _c2w(i)
        imageio.imwrite(root / "images" / name, render(poses[name], tables))
    return root, poses, tables


def _run(*args):
    return subprocess.run([sys.executable, "-m", "clrf.cli", "--quiet", "process", *args],
                          capture_output=True, text=True, timeout=600)


def umeyama(src, dst):
    """Similarity (s, R, t) minimising sum |s R src_i + t - dst_i|^2; src, dst [N, 3]."""
    ms, md = src.mean(0), dst.mean(0)
    a, b = src - ms, dst - md
    u, sig, vt = np.linalg.svd(b.T @ a / len(src))
    e = np.eye(3)
    e[2, 2] = np.sign(np.linalg.det(u @ vt))
    r = u @ e @ vt
    s = np.trace(np.diag(sig) @ e) / (a ** 2).sum(1).mean()
    return s, r, md - s * r @ ms


def test_umeyama_recovers_a_known_similarity():
    rng = np.random.default_rng(0)
    x = rng.normal(size=(10, 3))
    q, _ = np.linalg.qr(rng.normal(size=(3, 3)))
    q *= np.sign(np.linalg.det(q))
    s, r, t = umeyama(x, 2.5 * x @ q.T + [1.0, -2.0, 0.5])
    assert s == pytest.approx(2.5) and np.allclose(r, q) and np.allclose(t, [1.0, -2.0, 0.5])


def test_pick_frames_keeps_the_sharpest_per_window():
    scores = np.array([1, 5, 2, 9, 3, 3, 0, 7, 7, 1.0])
    assert pick_frames(scores, 3) == [1, 3, 7]         # windows [0,3) [3,7) [7,10)
    assert pick_frames(scores, 20) == list(range(10))
    img = np.random.default_rng(1).random((40, 40))
    blurred = (img + np.roll(img, 1, 0) + np.roll(img, 1, 1) + np.roll(img, (1, 1), (0, 1))) / 4
    assert sharpness(blurred) < 0.5 * sharpness(img)


def test_detect_preset():
    assert detect_preset(np.tile([0, 0, 1.0], (5, 1))) == "forward_facing"
    a = np.linspace(0, 2 * np.pi, 12, endpoint=False)
    assert detect_preset(np.stack([np.cos(a), np.sin(a), 0 * a], 1)) == "real360"


@pytest.mark.slow
def test_process_recovers_known_poses(capture, tmp_path):
    root, truth, _ = capture
    out = tmp_path / "scene"
    r = _run(str(root / "images"), "--out", str(out))
    assert r.returncode == 0, r.stderr
    assert sorted(p.name for p in out.iterdir()) == ["clrf_process.json", "images", "sparse"]
    summary = json.loads((out / "clrf_process.json").read_text())
    assert summary["registered"] == N_VIEWS and summary["preset"] == "real360"

    rec = pycolmap.Reconstruction(str(out / "sparse" / "0"))
    cam = next(iter(rec.cameras.values()))
    assert cam.model.name == "PINHOLE"
    names = sorted(truth)
    imgs = {rec.image(i).name: rec.image(i) for i in rec.reg_image_ids()}
    assert sorted(imgs) == names
    est_c = np.array([imgs[n].projection_center() for n in names])
    est_r = np.array([imgs[n].cam_from_world().rotation.matrix().T for n in names])  # c2w
    true_c = np.array([truth[n][:3, 3] for n in names])
    true_r = np.array([truth[n][:3, :3] for n in names])
    s, rot, t = umeyama(est_c, true_c)
    centre_err = np.linalg.norm(s * est_c @ rot.T + t - true_c, axis=1)
    scale = 2 * RADIUS
    rel = rot @ est_r                                       # aligned c2w rotations
    cosang = (np.einsum("nij,nij->n", rel, true_r) - 1) / 2
    rot_err = np.degrees(np.arccos(np.clip(cosang, -1, 1)))
    print(f"pose accuracy: max rotation error {rot_err.max():.3f} deg, max centre error "
          f"{centre_err.max() / scale * 100:.3f} % of the scene scale ({scale}), focal "
          f"{cam.params[0]:.2f} (true {FOCAL})")
    assert rot_err.max() < ROT_TOL_DEG
    assert centre_err.max() < CENTRE_TOL * scale

    from clrf.data import load_dataset
    ds = load_dataset(out)
    assert ds.preset == summary["preset"] and len(ds.images) == N_VIEWS


def _posed_dataset(capture, world_scale=1.0, world_shift=(0.0, 0.0, 0.0)):
    """The capture as a loaded dataset with known poses (OpenGL axes) in a world moved by
    p -> world_scale p + world_shift, no sparse points (like a poses_bounds.npy capture)."""
    from clrf.data.base import Dataset
    root, truth, _ = capture
    names = sorted(truth)
    images = np.stack([imageio.imread(root / "images" / n) for n in names]) / 255.0
    poses = np.stack([truth[n] for n in names])
    poses[:, :3, 1:3] *= -1.0                                  # OpenCV -> OpenGL camera axes
    poses[:, :3, 3] = world_scale * poses[:, :3, 3] + np.asarray(world_shift)
    return Dataset(name="capture", images=images.astype(np.float32),
                   poses=poses.astype(np.float32),
                   intrinsics=np.array([FOCAL, FOCAL, W / 2, H / 2]),
                   split={"train": np.arange(len(names)), "test": np.arange(0)},
                   preset="real360")


def _surface_distance(p):
    """Distance of points p [P, 3] to the nearest face of the cube or the room."""
    out = np.full(len(p), np.inf)
    for lo, hi, _ in BOXES:
        inside = np.all((p >= lo) & (p <= hi), 1)
        to_face = np.minimum(np.abs(p - lo), np.abs(p - hi))
        outside = np.linalg.norm(np.maximum(np.maximum(lo - p, p - hi), 0), axis=1)
        d = np.where(inside, to_face.min(1), np.maximum(outside, 0))
        out = np.minimum(out, d)
    return out


def test_triangulated_points_sit_on_the_surfaces(capture, tmp_path, monkeypatch):
    """train.points = 'triangulate': COLMAP on the views, aligned to the dataset's own cameras
    (here in a world scaled by 2 and shifted), gives points on the cube and the room's walls
    (within 2 % of the orbit's diameter) with the surfaces' colours, cached for a second
    call; 'none' drops points and 'auto' leaves the dataset alone."""
    from clrf.data import triangulate as tri
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "cache"))
    scale, shift = 2.0, np.array([0.5, -1.0, 3.0])
    ds = _posed_dataset(capture, scale, shift)
    assert tri.with_points(ds, "auto") is ds and ds.points is None
    got = tri.with_points(ds, "triangulate").points
    assert got.shape[1] == 6 and len(got) > 200 and got.dtype == np.float32
    back = (got[:, :3].astype(np.float64) - shift) / scale     # into the rendering's world
    err = _surface_distance(back)
    print(f"triangulated {len(got)} points; surface distance median {np.median(err):.4f}, "
          f"95th percentile {np.percentile(err, 95):.4f}")
    assert np.percentile(err, 95) < 0.02 * 2 * RADIUS
    assert np.all((got[:, 3:] >= 0) & (got[:, 3:] <= 1)) and got[:, 3:].std() > 0.05
    assert len(list((tmp_path / "cache").rglob("*.npy"))) == 1
    again = tri.with_points(ds, "triangulate").points               # from the cache
    np.testing.assert_array_equal(again, got)
    assert tri.with_points(tri.with_points(ds, "triangulate"), "none").points is None
    with pytest.raises(ValueError, match="train.points"):
        tri.with_points(ds, "always")


def test_process_refuses_unrelated_images(tmp_path):
    src = tmp_path / "noise"
    src.mkdir()
    rng = np.random.default_rng(7)
    for i in range(3):
        imageio.imwrite(src / f"junk_{i}.png", (rng.random((H, W, 3)) * 255).astype(np.uint8))
    out = tmp_path / "scene"
    r = _run(str(src), "--out", str(out))
    assert r.returncode != 0
    assert "could not pose" in r.stderr
    for i in range(3):
        assert f"junk_{i}.png" in r.stderr
    assert not out.exists()
    assert [p.name for p in tmp_path.iterdir()] == ["noise"]      # no temporary folder left


def test_process_refuses_existing_out(capture, tmp_path):
    root, _, _ = capture
    out = tmp_path / "scene"
    out.mkdir()
    (out / "keep.txt").write_text("mine")
    r = _run(str(root / "images"), "--out", str(out))
    assert r.returncode != 0 and "already exists" in r.stderr
    assert (out / "keep.txt").read_text() == "mine"


@pytest.mark.slow
def test_process_video(capture, tmp_path):
    pytest.importorskip("imageio_ffmpeg", reason="video input needs imageio-ffmpeg")
    root, _, tables = capture
    video = tmp_path / "orbit.mp4"
    # 60 frames over the orbit, every other one blurred: --frames 30 must keep the sharp ones
    with imageio.get_writer(video, "ffmpeg", fps=10, quality=9, macro_block_size=8) as w:
        for i in range(2 * N_VIEWS):
            img = render(_c2w(i, 2 * N_VIEWS), tables).astype(np.float64)
            if i % 2:
                for ax in (0, 1):
                    img = (img + np.roll(img, 1, ax) + np.roll(img, -1, ax)) / 3
            w.append_data(img.astype(np.uint8))
    out = tmp_path / "scene"
    r = _run(str(video), "--out", str(out), "--frames", str(N_VIEWS))
    assert r.returncode == 0, r.stderr
    summary = json.loads((out / "clrf_process.json").read_text())
    assert summary["frames"] == N_VIEWS and summary["matcher"] == "sequential"
    kept = sorted(p.name for p in (out / "images").iterdir())
    assert all(int(n[6:11]) % 2 == 0 for n in kept), kept        # the sharp frames
    assert summary["registered"] >= 0.9 * N_VIEWS, summary


def test_process_without_pycolmap_says_how_to_install(tmp_path, monkeypatch):
    from clrf.data.process import ProcessError, process
    monkeypatch.setitem(sys.modules, "pycolmap", None)        # import pycolmap -> ImportError
    (tmp_path / "src").mkdir()
    with pytest.raises(ProcessError, match=r"pip install clrf\[process\]"):
        process(tmp_path / "src", tmp_path / "out")
    assert not (tmp_path / "out").exists()


def test_process_bad_source_is_named(tmp_path):
    r = _run(str(tmp_path / "missing.mp4"), "--out", str(tmp_path / "out"))
    assert r.returncode == 2 and "missing.mp4: does not exist" in r.stderr
    (tmp_path / "few").mkdir()
    imageio.imwrite(tmp_path / "few" / "a.png", np.zeros((8, 8, 3), np.uint8))
    r = _run(str(tmp_path / "few"), "--out", str(tmp_path / "out"))
    assert r.returncode == 2 and "holds 1 images" in r.stderr
    assert sorted(p.name for p in tmp_path.iterdir()) == ["few"]
