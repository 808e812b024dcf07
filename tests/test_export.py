"""Mesh and point-cloud export, PLY files, video and depth outputs, and their bad input."""
import numpy as np
import pytest

from clrf.outputs import export
from clrf.references import reference_export
from clrf.data.cameras import to_ndc
from clrf.cli.main import main as cli
from clrf.grid.config import GridConfig
from clrf.data.synthetic import ProceduralScene, Sphere, load_procedural
from clrf.grid import SparseGrid
from clrf.grid.model import GridModel
from clrf.outputs.ply import read_ply, write_ply
from clrf.data.cameras import view_rays
from clrf.testing.tolerances import EXPORT_FIELD_ATOL, EXPORT_FIELD_RTOL, EXPORT_GEOMETRY_VOXELS

BBOX = np.array([[-1.5] * 3, [1.5] * 3])
R = 64
VOXEL = 3.0 / R
SCENE = ProceduralScene()


def sdf(p):
    """Signed distance to the union of the procedural scene's objects (exact outside them)."""
    p = np.asarray(p, np.float64)
    ds = []
    for s in SCENE.shapes:
        if isinstance(s, Sphere):
            ds.append(np.linalg.norm(p - s.center, axis=1) - s.radius)
        else:
            lo, hi = np.array(s.lo), np.array(s.hi)
            q = np.abs(p - (lo + hi) / 2) - (hi - lo) / 2
            ds.append(np.linalg.norm(np.maximum(q, 0), axis=1) + np.minimum(q.max(1), 0))
    return np.min(ds, 0)


@pytest.fixture(scope="module")
def exact_model(device):
    """A grid of the procedural scene: raw density 1e5 * clip(-sdf / voxel, -2, 2) (the
    renderer's ReLU makes it 0 outside and a steep ramp inside, so the scene is opaque within a
    small fraction of a voxel of the exact surfaces); red SH band 0 = 1, all else 0."""
    c = (np.arange(R) + 0.5) * VOXEL - 1.5
    P = np.stack(np.meshgrid(c, c, c, indexing="ij"), -1).reshape(-1, 3)
    dens = (1e5 * np.clip(-sdf(P) / VOXEL, -2, 2)).reshape(R, R, R).astype(np.float32)
    sh = np.zeros((R, R, R, 3), np.float32)
    sh[..., 0] = 1.0
    g = SparseGrid.from_dense(device, dens, sh, BBOX, mask=np.ones((R, R, R), bool))
    return GridModel(device, GridConfig(), g, (1.0, 1.0, 1.0))


def test_sample_fields_matches_reference(device):
    rng = np.random.default_rng(3)
    reso = (5, 7, 6)
    dens = rng.normal(size=reso).astype(np.float32)
    sh = rng.normal(size=reso + (12,)).astype(np.float32)
    mask = rng.uniform(size=reso) < 0.7
    dens[~mask], sh[~mask] = 0, 0
    bbox = np.array([[-1.0, -0.5, 0.0], [1.0, 1.5, 2.5]])
    g = SparseGrid.from_dense(device, dens, sh, bbox, mask=mask)
    model = GridModel(device, GridConfig(), g, (1, 1, 1))
    pts = rng.uniform(bbox[0] - 0.3, bbox[1] + 0.3, size=(5000, 3))   # some outside: clamped
    sig, rgb = export.sample_fields(model, pts, block=1024)
    rs, rr = reference_export.sample_fields(dens, sh, bbox, pts)
    np.testing.assert_allclose(sig, rs, atol=EXPORT_FIELD_ATOL, rtol=EXPORT_FIELD_RTOL)
    np.testing.assert_allclose(rgb, rr, atol=EXPORT_FIELD_ATOL, rtol=EXPORT_FIELD_RTOL)
    assert np.any(rs < 0) and np.any(rr == 0)    # the raw sign and the colour ReLU are exercised


def test_mesh_within_one_voxel_of_exact_surfaces(exact_model):
    mesh = export.extract_mesh(exact_model, BBOX)
    assert mesh.level == pytest.approx(np.log(2) / VOXEL)
    err = np.abs(sdf(mesh.verts)) / VOXEL
    assert len(err) > 5000 and err.max() <= EXPORT_GEOMETRY_VOXELS, err.max()
    # coverage: every exact surface point (sphere 0's upper half, the slab's top) has a vertex
    # within one voxel, so the mesh is not just a subset of the scene
    from scipy.spatial import cKDTree
    rng = np.random.default_rng(0)
    u = rng.normal(size=(500, 3))
    u[:, 2] = np.abs(u[:, 2])
    sphere = 0.6 * u / np.linalg.norm(u, axis=1, keepdims=True)
    slab = np.c_[rng.uniform(-1.1, 1.1, (500, 2)), np.full(500, -0.7)]
    slab = slab[sdf(slab + [0, 0, 0.05]) > 0.05]          # not under another object
    gap, _ = cKDTree(mesh.verts).query(np.vstack([sphere, slab]))
    assert gap.max() <= EXPORT_GEOMETRY_VOXELS * VOXEL
    # closed (the padded border) and consistently oriented: every edge in exactly two faces,
    # once in each direction; normals of the winding point outwards
    e = mesh.faces[:, [0, 1, 1, 2, 2, 0]].reshape(-1, 2)
    key = np.minimum(e[:, 0], e[:, 1]) * len(mesh.verts) + np.maximum(e[:, 0], e[:, 1])
    assert np.all(np.unique(key, return_counts=True)[1] == 2)
    assert len(np.unique(e[:, 0] * len(mesh.verts) + e[:, 1])) == len(e)
    v = mesh.verts[mesh.faces]
    fn = np.cross(v[:, 1] - v[:, 0], v[:, 2] - v[:, 0])
    top = np.abs(v.mean(1)[:, 2] + 0.7) < 1e-3      # faces on the slab's top look up
    assert np.all(fn[top, 2] > 0)
    # colour: red band 0 = 1 -> (0.5 + C0, 0.5, 0.5) everywhere
    expect = (np.array([0.5 + reference_export.SH_C0, 0.5, 0.5]) * 255 + 0.5).astype(int)
    assert np.all(np.abs(mesh.colors.astype(int) - expect) <= 1)


def test_point_cloud_within_one_voxel(exact_model):
    ds = load_procedural(n_train=6, n_test=1, size=32)
    o, d = view_rays(ds, ds.poses[ds.split["train"]])
    pts, cols = export.point_cloud(exact_model, o, d, (1, 1, 1), chunk=2000)
    hit = np.isfinite(SCENE.trace(o, d)["depth"])
    assert len(pts) > 0.9 * hit.sum()                 # the rays that hit something are kept
    assert np.abs(sdf(pts)).max() <= EXPORT_GEOMETRY_VOXELS * VOXEL
    assert cols.dtype == np.uint8 and cols.shape == pts.shape


def test_ply_roundtrip(tmp_path):
    rng = np.random.default_rng(1)
    v = rng.normal(size=(10, 3)).astype(np.float32)
    c = rng.integers(0, 256, (10, 3)).astype(np.uint8)
    f = rng.integers(0, 10, (4, 3))
    write_ply(tmp_path / "a.ply", v, c, f)
    got = read_ply(tmp_path / "a.ply")
    assert np.array_equal(got["verts"], v) and np.array_equal(got["colors"], c)
    assert np.array_equal(got["faces"], f)
    assert (tmp_path / "a.ply").read_bytes().startswith(b"ply\nformat binary_little_endian 1.0")
    write_ply(tmp_path / "b.ply", v, c)
    assert len(read_ply(tmp_path / "b.ply")["faces"]) == 0


def test_ndc_to_world_inverts_to_ndc():
    rng = np.random.default_rng(2)
    intr, H, W = np.array([50.0, 60.0, 20.0, 15.0]), 30, 40
    o = rng.normal(scale=0.1, size=(50, 3))
    d = np.c_[rng.normal(scale=0.3, size=(50, 2)), -np.ones(50)]
    on, dn = to_ndc(o, d, intr, H, W)
    s = rng.uniform(0, 0.95, size=(50, 1))
    w = export.ndc_to_world(on + s * dn, intr, H, W)
    rel = np.cross(w - o, d) / np.linalg.norm(w - o, axis=1, keepdims=True)
    assert np.abs(rel).max() < 1e-4                      # on the world ray
    assert np.allclose(export.ndc_to_world(on, intr, H, W)[:, 2], -1.0, atol=1e-5)  # near plane


def test_nerf_mesh_path(device):
    from clrf.nerf import NerfConfig, NerfModel
    model = NerfModel(device, NerfConfig.from_preset("tiny"), 2.0, 6.0, (1, 1, 1))
    vol = export.density_volume(model, BBOX, (12, 12, 12))
    level = float(np.median(vol))
    mesh = export.extract_mesh(model, BBOX, (12, 12, 12), level)
    assert len(mesh.faces) > 0 and mesh.colors.dtype == np.uint8
    assert np.all(np.abs(mesh.verts) <= 1.5 + 1e-5)
    assert export.default_level(model) == pytest.approx(np.log(2) / (4.0 / 64))
    # blocks are independent: 7 blocks of 100 give the one-block result bit for bit
    pts = np.random.default_rng(4).uniform(-1.5, 1.5, (650, 3))
    a, b = export.sample_fields(model, pts, block=100), export.sample_fields(model, pts)
    assert np.array_equal(a[0], b[0]) and np.array_equal(a[1], b[1])


# ---- CLI ---------------------------------------------------------------------------------------
def run_cli(*args):
    return cli([str(a) for a in args])


@pytest.fixture(scope="module")
def trained(tmp_path_factory):
    out = tmp_path_factory.mktemp("exp") / "r"
    # a fixed number of iterations (not seconds), so the geometry does not depend on load
    assert run_cli("--quiet", "train", "--out", out, "--max-seconds", 120,
                   "--set", "train.max_iters=100",
                   "--set", "grid.reso=[[32,32,32],[64,64,64]]", "--set", "grid.upsample_at=[40]",
                   "--set", "train.eval_every=1000", "--set", "train.eval_views=1") == 0
    return out


@pytest.mark.slow
def test_cli_export_trained_scene(trained, tmp_path):
    assert run_cli("export", "--ckpt", trained, "--mesh", tmp_path / "m.ply",
                   "--points", tmp_path / "p.ply", "--n", 20000) == 0
    mesh, pts = read_ply(tmp_path / "m.ply"), read_ply(tmp_path / "p.ply")
    assert len(mesh["faces"]) > 1000 and len(pts["verts"]) > 2000
    # a briefly trained grid has floaters and loose density inside the objects, so the check
    # is looser than on the exact grid: most points and vertices lie near the exact surfaces
    # (measured at 100 iterations: medians 0.94 voxel for points, 1.7 for vertices)
    vox = 3.0 / 64
    assert np.median(np.abs(sdf(pts["verts"]))) < 1.5 * vox
    assert np.median(np.abs(sdf(mesh["verts"]))) < 3 * vox


def test_cli_render_video_and_depth(trained, tmp_path, capsys):
    pytest.importorskip("imageio_ffmpeg", reason="--video needs imageio-ffmpeg (clrf[video])")
    import imageio.v3 as iio
    out = tmp_path / "v"
    assert run_cli("--quiet", "render", "--ckpt", trained, "--views", "orbit", "--frames", 5,
                   "--out", out, "--video", "--fps", 10, "--depth", "--scale", 0.75) == 0
    assert capsys.readouterr().err == ""                  # quiet: no progress output
    frames = iio.imread(out / "orbit.mp4", index=None)
    assert frames.shape == (5, 48, 48, 3)
    z = np.load(out / "orbit_000_depth.npy")
    assert z.shape == (48, 48) and np.isnan(z).any() and np.nanmin(z) > 2.0
    assert iio.imread(out / "orbit_004_depth.png").shape == (48, 48, 3)
    assert run_cli("--quiet", "render", "--ckpt", trained, "--views", "spiral", "--frames", 3,
                   "--out", out, "--video", "--scale", 0.5) == 0
    assert len(list(out.glob("spiral_*.png"))) == 3
    assert iio.imread(out / "spiral.mp4", index=None).shape == (3, 32, 32, 3)


@pytest.mark.parametrize("args, msg", [
    ([], "nothing to do"),
    (["--mesh", "m.txt"], ".ply"),
    (["--mesh", "m.ply", "--level", "-1"], "--level"),
    (["--mesh", "m.ply", "--reso", "1"], "--reso"),
    (["--mesh", "m.ply", "--bbox", "0", "0", "0", "1", "-1", "1"], "--bbox"),
    (["--points", "p.ply", "--n", "0"], "--n"),
    (["--points", "p.ply", "--min-opacity", "0"], "--min-opacity"),
    (["--mesh", "m.ply", "--level", "1e30"], "no surface"),
    (["--points", "p.ply", "--data", "/no/such/dataset"], "/no/such/dataset"),
])
def test_cli_export_bad_input(trained, tmp_path, capsys, monkeypatch, args, msg):
    monkeypatch.chdir(tmp_path)
    assert run_cli("export", "--ckpt", trained, *args) == 2
    err = capsys.readouterr().err
    assert "clrf: error:" in err and msg in err and "Traceback" not in err
    assert not list(tmp_path.glob("*.ply"))              # nothing half-written


def test_cli_export_missing_checkpoint(tmp_path, capsys):
    assert run_cli("export", "--ckpt", tmp_path / "none", "--mesh", tmp_path / "m.ply") == 2
    assert "no checkpoint" in capsys.readouterr().err


@pytest.mark.parametrize("args, msg", [
    (["--fps", "0"], "--fps"), (["--scale", "0"], "--scale"), (["--frames", "0"], "--frames"),
])
def test_cli_render_bad_input(trained, tmp_path, capsys, args, msg):
    out = tmp_path / "r"
    assert run_cli("render", "--ckpt", trained, "--out", out, "--video", *args) == 2
    err = capsys.readouterr().err
    assert "clrf: error:" in err and msg in err
    assert not out.exists()


# ---- progress and TensorBoard ---------------------------------------------------------------
def test_log_progress_lines(monkeypatch, capsys):
    """Not a terminal: one line at the end (and every LOG_EVERY s), rate and ETA; quiet: none."""
    from clrf.runtime import progress
    with progress.bar(4, "work", "view") as b:
        for _ in range(4):
            b.update(1)
    err = capsys.readouterr().err.splitlines()
    assert len(err) == 1 and err[0].startswith("work: 4/4 view (") and "ETA 0 s" in err[0]
    monkeypatch.setattr(progress, "QUIET", True)
    with progress.bar(4, "work") as b:
        b.update(4)
    progress.message("eval line")
    assert capsys.readouterr().err == "eval line\n"     # messages are the log: always printed


@pytest.mark.slow
def test_train_tensorboard_events(tmp_path, capsys):
    pytest.importorskip("tensorboardX", reason="the tensorboard extra is not installed")
    out = tmp_path / "tb"
    assert run_cli("--quiet", "train", "--out", out, "--max-seconds", 1, "--log", "tensorboard",
                   "--set", "grid.reso=[[16,16,16]]", "--set", "grid.upsample_at=[]",
                   "--set", "train.eval_every=0.5", "--set", "train.eval_views=1") == 0
    err = capsys.readouterr().err
    assert "eval PSNR" in err and "train:" not in err     # eval lines, no progress lines
    events = list((out / "tensorboard").glob("events.out.tfevents.*"))
    assert len(events) == 1 and events[0].stat().st_size > 100
    import struct
    data = events[0].read_bytes()
    tags = set()
    while data:                            # TFRecord framing: length, crc, payload, crc
        (length,) = struct.unpack("<Q", data[:8])
        payload = data[12:12 + length]
        data = data[16 + length:]
        for tag in (b"metrics/eval_psnr", b"metrics/train_loss"):
            if tag in payload:
                tags.add(tag)
    assert tags == {b"metrics/eval_psnr", b"metrics/train_loss"}
    rows = (out / "metrics.csv").read_text().splitlines()
    assert rows[0].startswith("iteration,seconds,train_loss")  # metrics.csv unchanged


def test_train_tensorboard_bad_option(tmp_path, capsys):
    with pytest.raises(SystemExit) as e:          # argparse: usage and exit 2
        run_cli("train", "--out", tmp_path / "x", "--log", "wandb")
    assert e.value.code == 2 and "--log" in capsys.readouterr().err
    assert not (tmp_path / "x").exists()


def test_ndc_mesh_is_mapped_to_world(exact_model, monkeypatch):
    """An NDC scene's mesh is the model-space mesh with every vertex through ndc_to_world
    (faces reaching NDC depth NDC_MAX_DEPTH dropped)."""
    ndc = (np.array([40.0, 40.0, 16.0, 16.0]), 32, 32)
    box = np.array([[-1.0, -1.0, -1.0], [1.0, 1.0, 0.0]])
    plain = export.extract_mesh(exact_model, box, (32, 32, 16))
    mapped = export.extract_mesh(exact_model, box, (32, 32, 16), ndc=ndc)
    assert len(mapped.faces) == len(plain.faces) > 0
    np.testing.assert_allclose(mapped.verts[mapped.faces],
                               export.ndc_to_world(plain.verts, *ndc)[plain.faces], rtol=1e-6)
    assert np.all(mapped.verts[:, 2] < 0)                 # in front of the camera (world z < 0)
    # faces reaching the far cut go, and no vertex is left unused (the cut moved to z' = -0.3
    # so that it crosses the scene's sphere 0 and box)
    monkeypatch.setattr(export, "NDC_MAX_DEPTH", -0.3)
    cut = export.extract_mesh(exact_model, box, (32, 32, 16), ndc=ndc)
    keep = np.all(plain.verts[plain.faces, 2] < -0.3, axis=1)
    assert 0 < len(cut.faces) == keep.sum() < len(plain.faces)
    assert len(np.unique(cut.faces)) == len(cut.verts)
    np.testing.assert_allclose(cut.verts[cut.faces],
                               export.ndc_to_world(plain.verts, *ndc)[plain.faces[keep]], rtol=1e-6)


def test_cli_export_bad_level_as_a_process(trained, tmp_path):
    """Through `python -m clrf.cli` (a second copy of the cli module): still exit 2, no trace."""
    import os
    import subprocess
    import sys
    from pathlib import Path
    env = dict(os.environ)   # the installed clrf (tests/conftest.py)
    r = subprocess.run([sys.executable, "-m", "clrf.cli", "--quiet", "export", "--ckpt",
                        str(trained), "--mesh", str(tmp_path / "m.ply"), "--level", "1e30"],
                       capture_output=True, text=True, env=env, cwd=tmp_path)
    assert r.returncode == 2 and "clrf: error: --level" in r.stderr
    assert "Traceback" not in r.stderr and not (tmp_path / "m.ply").exists()


def test_write_video_odd_size(tmp_path):
    """H.264 needs even sizes: odd frames are edge-padded; frame count and content survive."""
    pytest.importorskip("imageio_ffmpeg", reason="videos need imageio-ffmpeg (clrf[video])")
    import imageio.v3 as iio
    from clrf.cli.export import write_video
    frames = np.zeros((3, 33, 35, 3), np.uint8)
    frames[1] = 255
    write_video(tmp_path / "v.mp4", frames, 5)
    back = iio.imread(tmp_path / "v.mp4", index=None)
    assert back.shape == (3, 34, 36, 3)
    assert back[0].mean() < 10 and back[1].mean() > 245   # lossy codec: near, not equal
    assert [p.name for p in tmp_path.iterdir()] == ["v.mp4"]   # no temporary left


@pytest.mark.parametrize("cmd, module, msg", [
    (["render", "--views", "orbit", "--video"], "imageio_ffmpeg", "imageio-ffmpeg"),
    (["train", "--log", "tensorboard", "--max-seconds", "1"], "tensorboardX", "tensorboardX"),
])
def test_missing_optional_package(trained, tmp_path, capsys, monkeypatch, cmd, module, msg):
    """Without the optional package: exit 2 naming the pip install, before anything is written."""
    import importlib.util
    real = importlib.util.find_spec
    monkeypatch.setattr(importlib.util, "find_spec",
                        lambda name, *a: None if name == module else real(name, *a))
    out = tmp_path / "o"
    args = cmd + (["--ckpt", str(trained)] if cmd[0] == "render" else []) + ["--out", str(out)]
    assert run_cli(*args) == 2
    err = capsys.readouterr().err
    assert "clrf: error:" in err and f"pip install {msg}" in err
    assert not out.exists()
