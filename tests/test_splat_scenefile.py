"""A splat file as a trained scene (clrf/splat/scenefile.py, Kind.scene_file): `clrf render`,
`eval`, `export` and `view` take `--ckpt FILE` for every splat format clrf reads, and a
malformed file is one clear error naming it, exit 2."""
import gzip
import struct

import numpy as np
import pytest

from clrf.splat.files import SUFFIXES, write_splat_file

DEGREE = 3


def _splats(n=300, degree=DEGREE, seed=2):
    """n random Gaussians about the origin (clrf's axes), as a file's arrays."""
    rng = np.random.default_rng(seed)
    q = rng.normal(size=(n, 4))
    return {"means": rng.normal(0, 0.5, (n, 3)).astype(np.float32),
            "log_scales": rng.uniform(-3.5, -2.0, (n, 3)).astype(np.float32),
            "quats": (q / np.linalg.norm(q, axis=1, keepdims=True)).astype(np.float32),
            "opacity_logits": rng.uniform(-1.0, 3.0, n).astype(np.float32),
            "sh": rng.normal(0, 0.3, (n, (degree + 1) ** 2, 3)).astype(np.float32)}


def _write(path, g):
    write_splat_file(path, g["means"], g["log_scales"], g["quats"], g["opacity_logits"], g["sh"])
    return path


def test_ply_scene_renders_as_the_model_of_its_splats(device, tmp_path):
    """The model load_model makes of a .ply holds the file's splats: its render equals a
    SplatModel's of the same arrays; the state names the file and orbits the splats' box."""
    from clrf.splat.model import SplatModel
    from clrf.splat.config import SplatConfig
    from clrf.training.models import load_model
    g = _splats()
    f = _write(tmp_path / "scene.ply", g)
    model, state, cfg = load_model(device, f)
    assert model.n == 300 and model.config.sh_degree == DEGREE and cfg.train.model == "splat"
    assert state["dataset"]["name"] == "scene.ply"
    lo, hi = np.asarray(state["dataset"]["bbox"])
    assert np.all(lo < 0) and np.all(hi > 0) and np.all(hi - lo < 3.0)
    direct = SplatModel(device, SplatConfig(sh_degree=DEGREE), g, (0.0, 0.0, 0.0), 1.0,
                        [lo, hi], 0, 300)
    direct.active_degree = DEGREE
    c2w = np.eye(4)
    c2w[:3, 3] = [0.0, 0.0, 3.0]              # OpenGL camera on +z looking down -z
    K = np.asarray(state["dataset"]["intrinsics"]) * 64 / state["dataset"]["W"]
    a = model.render_image(c2w, K, (64, 64), depth=False)["rgb"]
    b = direct.render_image(c2w, K, (64, 64), depth=False)["rgb"]
    assert a.std() > 0.01
    np.testing.assert_array_equal(a, b)


@pytest.mark.parametrize("suffix", SUFFIXES)
def test_render_eval_export_take_every_format(tmp_path, suffix):
    """`clrf render --ckpt FILE` (an orbit), `clrf eval --ckpt FILE` (the built-in scene's
    test views) and `clrf export --ckpt FILE --splats OUT.ply` for a file of each ending."""
    from clrf.cli.main import main as cli
    from clrf.splat.files import read_splat_file
    degree = 0 if suffix == ".splat" else DEGREE
    f = _write(tmp_path / f"scene{suffix}", _splats(degree=degree))
    out = tmp_path / "frames"
    assert cli(["--quiet", "render", "--ckpt", str(f), "--frames", "2", "--scale", "0.125",
                "--out", str(out)]) == 0
    assert sorted(p.name for p in out.glob("*.png")) == ["orbit_000.png", "orbit_001.png"]
    assert cli(["--quiet", "eval", "--ckpt", str(f), "--max-views", "1",
                "--out", str(tmp_path / "eval.json")]) == 0
    assert cli(["--quiet", "export", "--ckpt", str(f), "--splats",
                str(tmp_path / "back.ply")]) == 0
    assert read_splat_file(tmp_path / "back.ply")["means"].shape == (300, 3)


def _malformed(tmp_path) -> dict:
    """Ten broken splat files: {name: path}."""
    g = _splats(50)
    out = {}
    good = {s: _write(tmp_path / f"good{s}", _splats(50, degree=0 if s == ".splat" else 3))
            for s in (".ply", ".spz", ".glb", ".compressed.ply", ".splat")}
    for s, p in good.items():                 # each cut short
        b = p.read_bytes()
        cut = tmp_path / f"cut{s}"
        # (an odd length: half a .splat is a whole file of fewer Gaussians)
        cut.write_bytes(b[:len(b) // 2 + 7] if s != ".spz" else gzip.compress(
            gzip.decompress(b)[:40]))
        out[f"cut{s}"] = cut
    nan = dict(g)
    nan["means"] = g["means"].copy()
    nan["means"][3, 1] = np.nan
    out["nan.ply"] = _write(tmp_path / "nan.ply", nan)
    empty = tmp_path / "empty.glb"
    empty.write_bytes(b"")
    out["empty.glb"] = empty
    txt = tmp_path / "json.gltf"
    txt.write_text("{not json")
    out["json.gltf"] = txt
    ply = (tmp_path / "good.ply").read_bytes()
    head, body = ply.split(b"end_header\n", 1)
    more = head.replace(b"element vertex 50", b"element vertex 60") + b"end_header\n" + body
    (tmp_path / "count.ply").write_bytes(more)
    out["count.ply"] = tmp_path / "count.ply"
    gone = head.replace(b"property float opacity\n", b"") + b"end_header\n" + body
    (tmp_path / "noopacity.ply").write_bytes(gone)
    out["noopacity.ply"] = tmp_path / "noopacity.ply"
    assert struct.calcsize("<I") == 4
    return out


def test_malformed_files_are_one_clear_error(tmp_path, capsys):
    """Each broken file: exit 2 from `clrf render --ckpt`, one message naming the file, no
    traceback."""
    from clrf.cli.main import main as cli
    bad = _malformed(tmp_path)
    assert len(bad) == 10
    for name, path in bad.items():
        code = cli(["render", "--ckpt", str(path), "--frames", "1", "--out",
                    str(tmp_path / f"o_{name}")])
        err = capsys.readouterr().err
        assert code == 2, (name, err)
        assert path.name in err and "Traceback" not in err, (name, err)
        assert not (tmp_path / f"o_{name}").exists(), name


def test_a_file_scored_on_an_rgba_capture_takes_its_background(scene, tmp_path):
    """A run on an RGBA capture (lego_400 at a quarter, composited on white) and its PLY read
    back as a scene score alike on the capture's test views: the file renders on the capture's
    background and at its resolution (a file carries neither; `--downscale 4` for the run's
    quarter), for `clrf eval --data` and `clrf render --views test --data`."""
    import json
    from clrf.cli.main import main as cli
    data, run = str(scene("lego_400")), tmp_path / "run"
    assert cli(["--quiet", "train", "--model", "splat", "--data", data, "--out", str(run),
                "--max-seconds", "300", "--set", "train.downscale=4",
                "--set", "train.max_iters=400"]) == 0
    ply = tmp_path / "scene.ply"
    assert cli(["--quiet", "export", "--ckpt", str(run), "--splats", str(ply)]) == 0
    scores = {}
    for name, ckpt, scale in (("run", run, "1"), ("file", ply, "4")):
        out = tmp_path / f"eval_{name}.json"
        assert cli(["--quiet", "eval", "--ckpt", str(ckpt), "--data", data, "--lpips", "none",
                    "--max-views", "8", "--downscale", scale, "--out", str(out)]) == 0
        scores[name] = json.loads(out.read_text())["psnr"]
    assert scores["run"] > 20
    # the PLY bakes the anti-aliasing filter into scales and opacities (docs/splat.md)
    assert abs(scores["file"] - scores["run"]) < 0.5, scores
    frames = tmp_path / "frames"
    assert cli(["--quiet", "render", "--ckpt", str(ply), "--views", "test", "--data", data,
                "--max-views", "1", "--out", str(frames)]) == 0
    import imageio.v3 as iio
    img = iio.imread(next(frames.glob("*.png")))
    assert img.shape[:2] == (400, 400) and img[0, 0].min() > 240   # a white corner


VIEW_W, VIEW_H = 64, 48        # the frame's pixels, below the viewer's resolution cap
VIEW_FOV = 40.0                # degrees, vertical
VIEW_WAIT = 120.0              # seconds for the frame (PoCL on a loaded 2-core machine)


@pytest.mark.slow
@pytest.mark.parametrize("suffix", [".spz", ".glb"])
def test_view_serves_what_render_renders(tmp_path, suffix):
    """`clrf view --ckpt FILE` on a splat file, in a subprocess: the frame it serves over its
    WebSocket for a camera is `clrf render --camera-path` of that camera, to VIEWER_PIXEL_ATOL
    (both through clrf/outputs/frames.py); it is not blank, and the render of a camera 10
    degrees about the scene's vertical from it is clearly another image."""
    pytest.importorskip("websockets", reason="the viewer needs websockets (clrf[view])")
    import json
    import time

    import imageio.v3 as iio
    from websockets.sync.client import connect

    from clrf.cli.main import main as cli
    from clrf.data.cameras import look_at
    from clrf.outputs import camera_path
    from clrf.testing.tolerances import VIEWER_PIXEL_ATOL
    from clrf.viewer.server import decode_frame
    from viewer_util import ViewProcess
    f = _write(tmp_path / f"scene{suffix}", _splats())
    c2w = look_at([1.6, 1.0, 2.2], [0.0, 0.0, 0.0], up=(0.0, -1.0, 0.0))
    turn = np.radians(10.0)
    other = look_at([1.6 * np.cos(turn) + 2.2 * np.sin(turn), 1.0,
                     2.2 * np.cos(turn) - 1.6 * np.sin(turn)], [0.0, 0.0, 0.0],
                    up=(0.0, -1.0, 0.0))
    view = ViewProcess(f)
    try:
        ws_url = view.url.replace("http://", "ws://", 1).replace("/?token=", "/ws?token=", 1)
        with connect(ws_url, open_timeout=VIEW_WAIT) as ws:
            assert json.loads(ws.recv(timeout=VIEW_WAIT))["type"] == "hello"
            ws.send(json.dumps({"type": "render", "seq": 1, "fov": VIEW_FOV, "width": VIEW_W,
                                "height": VIEW_H, "c2w": c2w.reshape(-1).tolist()}))
            deadline = time.monotonic() + VIEW_WAIT
            frame = None
            while frame is None and time.monotonic() < deadline:
                m = ws.recv(timeout=max(0.1, deadline - time.monotonic()))
                if isinstance(m, bytes):
                    frame = decode_frame(m)
                else:
                    assert json.loads(m)["type"] != "error", m
        assert frame is not None, "no frame from clrf view"
        hdr, img = frame
        assert hdr["seq"] == 1 and img.shape == (VIEW_H, VIEW_W, 3)
    finally:
        view.close()
    out = tmp_path / "render"
    out.mkdir()
    path = out / "camera_path.json"
    camera_path.save(path, camera_path.CameraPath(np.stack([c2w, other]),
                                                  np.array([VIEW_FOV, VIEW_FOV]), VIEW_W, VIEW_H))
    assert cli(["--quiet", "render", "--ckpt", str(f), "--camera-path", str(path),
                "--out", str(out)]) == 0
    want = iio.imread(out / "path_000.png")[..., :3]
    assert img.std() > 5, "a blank frame proves nothing"
    diff = np.abs(img.astype(int) - want.astype(int))
    assert diff.max() <= VIEWER_PIXEL_ATOL, diff.max()
    turned = iio.imread(out / "path_001.png")[..., :3]
    assert np.abs(img.astype(int) - turned.astype(int)).mean() > 5
