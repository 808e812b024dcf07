"""`clrf export --web DIR` (clrf/splat/web.py): a folder of viser's web client (index.html) and
viser's recording of the splat scene (scene.viser). Without a browser: the folder holds viser's
page with one line added and a recording much smaller than the PLY, whose Gaussians are the
PLY's (centres bit for bit, colours and opacities as viser quantises them) and whose opening
camera is the run's first test view, or, for a splat file or a run whose dataset is gone, the
view `clrf render`'s orbit starts at; every refusal (the extra missing, a folder not empty, a
model that is not a splat scene) exits 2 and writes nothing, and a failure while writing leaves
nothing behind. In headless Chromium (SwiftShader's WebGL): the folder served by `http.server`
on a free port draws the scene at the opening camera (the client's own camera log,
?logCamera), a frame that is not the background, and another frame after a mouse drag moves
the camera. Skips with the reason when viser or the browser is missing
(`bash tools/setup.sh web,test`)."""
import base64
import functools
import http.server
import math
import re
import sys
import threading
from pathlib import Path

import imageio.v3 as iio
import numpy as np
import pytest

from clrf.cli.main import main as cli
from clrf.data.cameras import orbit_poses
from clrf.outputs import checkpoint
from clrf.splat.files import read_splat_file
from clrf.testing.tolerances import (WEB_AXIS_ATOL, WEB_CAMERA_LOG_ATOL, WEB_MOVED_MEAN_LEVELS,
                                     WEB_SCENE_LEVEL, WEB_SCENE_MIN_FRACTION)
from clrf.training.models import checkpoint_dataset
from viewer_util import browser as _browser, train_tiny, wait as _wait

SH_C0 = 0.28209479177387814
THREE_UP = np.array([0.0, 1.0, 0.0])    # three.js's up axis, where viser turns the scene's up


def _viser():
    return pytest.importorskip("viser", reason="viser is not installed (bash tools/setup.sh web)")


@pytest.fixture(scope="module")
def trained(tmp_path_factory):
    out = tmp_path_factory.mktemp("web_run")
    assert cli(["--quiet", "train", "--model", "splat", "--out", str(out), "--max-seconds", "4",
                "--set", "splat.init_points=1000", "--set", "train.final_eval=false"]) == 0
    return out


@pytest.fixture(scope="module")
def ply(trained, tmp_path_factory):
    path = tmp_path_factory.mktemp("web_ply") / "scene.ply"
    assert cli(["--quiet", "export", "--ckpt", str(trained), "--splats", str(path)]) == 0
    return path


def read_recording(path):
    """(header, {message type: [messages]}, binary buffers) of a .viser file: an 8-byte size,
    then zstd of an 8-byte msgpack length, the msgpack and the buffers, each 8-byte aligned."""
    import msgspec
    import zstandard
    blob = Path(path).read_bytes()
    size = int.from_bytes(blob[:8], "little")
    inner = zstandard.ZstdDecompressor().decompress(blob[8:], max_output_size=size)
    n = int.from_bytes(inner[:8], "little")
    head = msgspec.msgpack.decode(inner[8:8 + n])
    bufs, at = [], 8 + n
    for length in head["binaryBufferLengths"]:
        at += -at % 8
        bufs.append(inner[at:at + length])
        at += length
    assert at == len(inner) == size
    msgs = {}
    for _, m in head["messages"]:
        msgs.setdefault(m["type"], []).append(m)
    return head, msgs, bufs


def _camera(msgs):
    one = {k: msgs[f"SetCamera{t}Message"][-1] for k, t in
           (("position", "Position"), ("look_at", "LookAt"), ("up", "UpDirection"),
            ("fov", "Fov"))}
    return {"position": np.asarray(one["position"]["position"]),
            "look_at": np.asarray(one["look_at"]["look_at"]),
            "up": np.asarray(one["up"]["position"]), "fov": one["fov"]["fov"]}


def _rotate(wxyz, v):
    w, x, y, z = wxyz
    r = np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
                  [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
                  [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)]])
    return r @ np.asarray(v, np.float64)


def _scene_up_in_three(msgs):
    """The scene's up axis where viser's root orientation turns it (three.js's +y if right)."""
    (root,) = [m for m in msgs["SetOrientationMessage"] if m["name"] == ""]
    return root["wxyz"]


def _background(msgs):
    (bg,) = msgs["BackgroundImageMessage"]
    return iio.imread(bg["rgb_data"], extension=".png")


# ---- the folder ----------------------------------------------------------------------------------
def test_covariances_hand_made():
    from clrf.splat.web import covariances
    q = [math.cos(math.pi / 4), 0.0, 0.0, math.sin(math.pi / 4)]     # 90 degrees about z
    cov = covariances([[math.log(2.0), 0.0, 0.0]], [q])[0]
    np.testing.assert_allclose(cov, np.diag([1.0, 4.0, 1.0]), rtol=0, atol=WEB_AXIS_ATOL)


def test_web_folder_is_viser_client_and_its_recording(trained, ply, tmp_path, capsys):
    viser = _viser()
    from clrf.splat.web import covariances
    site = tmp_path / "site"
    assert cli(["export", "--ckpt", str(trained), "--web", str(site)]) == 0
    out = capsys.readouterr().out
    assert sorted(p.name for p in site.iterdir()) == ["index.html", "scene.viser"]
    # viser's own page, one script added before the end of its head
    client = (Path(viser.__file__).parent / "client" / "build" / "index.html").read_text()
    html = (site / "index.html").read_text()
    at = client.index("</head>")
    assert html.startswith(client[:at]) and html.endswith(client[at:])
    added = html[at:len(html) - (len(client) - at)]
    assert added.startswith("<script>") and "playbackPath" in added and "scene.viser" in added
    # compressed: 32 bytes a Gaussian before zstd against the PLY's 248 (SH degree 3)
    assert (site / "scene.viser").stat().st_size < ply.stat().st_size / 5
    head, msgs, bufs = read_recording(site / "scene.viser")
    assert head["viserVersion"] == viser.__version__
    g = read_splat_file(ply)
    n = len(g["means"])
    (splats,) = msgs["GaussianSplatsMessage"]
    rows = np.frombuffer(bufs[splats["props"]["buffer"]["__binary_index"]], np.uint8)
    rows = rows.reshape(n, 32)
    np.testing.assert_array_equal(rows[:, :12].copy().view(np.float32), g["means"])
    cov = covariances(g["log_scales"], g["quats"]).reshape(n, 9)[:, [0, 1, 2, 4, 5, 8]]
    np.testing.assert_array_equal(rows[:, 16:28].copy().view(np.float16),
                                  cov.astype(np.float16))
    rgb = np.clip(0.5 + SH_C0 * g["sh"][:, 0].astype(np.float64), 0, 1)
    alpha = 0.5 * (1 + np.tanh(0.5 * g["opacity_logits"].astype(np.float64)))
    np.testing.assert_array_equal(rows[:, 28:31], (255 * rgb).astype(np.uint8))
    np.testing.assert_array_equal(rows[:, 31], (255 * alpha).astype(np.uint8))
    # the opening camera: the first test view
    ds = checkpoint_dataset(checkpoint.load(trained))
    view = int(ds.split["test"][0])
    pose = np.asarray(ds.poses[view], np.float64)
    cam = _camera(msgs)
    np.testing.assert_array_equal(cam["position"], pose[:3, 3])
    np.testing.assert_array_equal(cam["up"], pose[:3, 1])
    assert cam["fov"] == 2 * math.atan(0.5 * ds.hw[0] / ds.intrinsics[1])
    axis = cam["look_at"] - cam["position"]
    np.testing.assert_allclose(axis / np.linalg.norm(axis),
                               -pose[:3, 2] / np.linalg.norm(pose[:3, 2]), rtol=0,
                               atol=WEB_AXIS_ATOL)
    up = ds.poses[ds.split["train"], :3, 1].astype(np.float64).sum(0)
    np.testing.assert_allclose(_rotate(_scene_up_in_three(msgs), up / np.linalg.norm(up)),
                               THREE_UP, rtol=0, atol=WEB_AXIS_ATOL)
    assert np.all(_background(msgs) == 255)            # the procedural scene's white
    assert f"{n} Gaussians" in out and f"opens at test view {view} of procedural" in out
    assert f"viser {viser.__version__}" in out and "SH degree 3" in out


def test_web_from_a_splat_file_opens_at_the_box(ply, tmp_path, capsys):
    _viser()
    from clrf.splat.scenefile import state_from_file
    site = tmp_path / "site"
    site.mkdir()                                     # an empty folder is taken
    assert cli(["export", "--ckpt", str(ply), "--web", str(site)]) == 0
    assert "opens at a view of the scene's box (a splat file has no cameras" in \
        capsys.readouterr().out
    _, msgs, _ = read_recording(site / "scene.viser")
    bbox = np.asarray(state_from_file(ply)["dataset"]["bbox"])
    centre, diag = bbox.mean(0), float(np.linalg.norm(bbox[1] - bbox[0]))
    want = orbit_poses(1, 1.15 * diag, 30.0, centre)[0]     # clrf render's orbit, first view
    cam = _camera(msgs)
    np.testing.assert_array_equal(cam["position"], want[:3, 3])
    np.testing.assert_allclose(cam["look_at"], centre, rtol=0, atol=WEB_AXIS_ATOL * diag)
    np.testing.assert_allclose(_rotate(_scene_up_in_three(msgs), [0, 0, 1]), THREE_UP, rtol=0,
                               atol=WEB_AXIS_ATOL)
    assert np.all(_background(msgs) == 0)              # a splat file's black



def test_web_of_a_run_whose_cameras_are_gone_opens_at_the_box(trained, tmp_path, capsys,
                                                               monkeypatch):
    _viser()
    from clrf.data.base import DataError
    from clrf.training import models

    def gone(state, data=None):
        raise DataError("scenes/mine: no such folder")
    monkeypatch.setattr(models, "checkpoint_dataset", gone)
    site = tmp_path / "site"
    assert cli(["export", "--ckpt", str(trained), "--web", str(site)]) == 0
    assert "opens at a view of the scene's box (the run's cameras are unavailable: " \
           "scenes/mine: no such folder)" in capsys.readouterr().out
    _, msgs, _ = read_recording(site / "scene.viser")
    bbox = np.asarray(checkpoint.load(trained)["dataset"]["bbox"], np.float64)
    want = orbit_poses(1, 1.15 * float(np.linalg.norm(bbox[1] - bbox[0])), 30.0, bbox.mean(0))
    np.testing.assert_array_equal(_camera(msgs)["position"], want[0, :3, 3])

# ---- refusals ----------------------------------------------------------------------------------
def test_web_without_viser_names_the_extra(tmp_path, capsys, monkeypatch):
    monkeypatch.setitem(sys.modules, "viser", None)    # import viser raises ImportError
    site = tmp_path / "site"
    assert cli(["export", "--ckpt", str(tmp_path / "no_run"), "--web", str(site)]) == 2
    err = capsys.readouterr().err
    assert "--web needs viser" in err and "bash tools/setup.sh web" in err
    assert not site.exists()


def test_web_refuses_a_folder_in_use(ply, tmp_path, capsys):
    _viser()
    site = tmp_path / "site"
    site.mkdir()
    (site / "notes.txt").write_text("mine")
    assert cli(["export", "--ckpt", str(ply), "--web", str(site)]) == 2
    assert "exists and is not empty" in capsys.readouterr().err
    assert [p.name for p in site.iterdir()] == ["notes.txt"]
    f = tmp_path / "file"
    f.write_text("mine")
    assert cli(["export", "--ckpt", str(ply), "--web", str(f)]) == 2
    assert "exists and is not a folder" in capsys.readouterr().err
    assert f.read_text() == "mine"


def test_web_refuses_a_model_that_is_not_splats(tmp_path, capsys):
    _viser()
    run = train_tiny(tmp_path / "grid")
    site = tmp_path / "site"
    assert cli(["export", "--ckpt", str(run), "--web", str(site)]) == 2
    err = capsys.readouterr().err
    assert "--web: a --model splat export" in err and "holds a grid model" in err
    assert not site.exists()


def test_web_leaves_nothing_when_writing_fails(ply, tmp_path, monkeypatch):
    _viser()
    from clrf.splat import web

    def broken(viser):
        raise OSError("disk full")
    monkeypatch.setattr(web, "page", broken)
    parent = tmp_path / "out"
    parent.mkdir()
    with pytest.raises(OSError, match="disk full"):
        cli(["export", "--ckpt", str(ply), "--web", str(parent / "site")])
    assert list(parent.iterdir()) == []


# ---- in a browser --------------------------------------------------------------------------
class StaticServer:
    """``python -m http.server`` of ``folder`` on a free loopback port, in a thread."""

    def __init__(self, folder):
        class Quiet(http.server.SimpleHTTPRequestHandler):
            def log_message(self, *args):
                pass
        self.httpd = http.server.ThreadingHTTPServer(
            ("127.0.0.1", 0), functools.partial(Quiet, directory=str(folder)))
        self.url = f"http://127.0.0.1:{self.httpd.server_port}/"
        self.thread = threading.Thread(target=self.httpd.serve_forever, daemon=True)
        self.thread.start()

    def close(self):
        self.httpd.shutdown()
        self.httpd.server_close()
        self.thread.join()


CAMERA_LOG = re.compile(r"initialCameraPosition=(-?[\d.]+),(-?[\d.]+),(-?[\d.]+)")
WEBGL_CANVAS = ("return [...document.querySelectorAll('canvas')]"
                ".sort((a, b) => b.width * b.height - a.width * a.height)[0];")


class Page:
    """viser's page in headless Chromium: its WebGL frame and the camera it logs."""

    def __init__(self, d, url):
        self.d, self.positions = d, []
        d.get(url + "?logCamera")
        self.canvas = _wait("viser's canvas", lambda: d.execute_script(WEBGL_CANVAS))

    def frame(self):
        """The canvas's pixels, uint8 [H, W, 4] (or [H, W, 3] from an opaque canvas; viser
        keeps its drawing buffer)."""
        url = self.d.execute_script(WEBGL_CANVAS[:-1] + ".toDataURL('image/png');")
        return iio.imread(base64.b64decode(url.split(",", 1)[1]), extension=".png")

    def position(self):
        """The camera position the client logged last (None before any)."""
        for e in self.d.get_log("browser"):
            m = CAMERA_LOG.search(e["message"])
            if m:
                self.positions.append(np.array([float(v) for v in m.groups()]))
        return self.positions[-1] if self.positions else None


def _scene_fraction(frame, background):
    return float(np.mean(np.abs(frame.astype(int) - background).max(-1) > WEB_SCENE_LEVEL))


def _shows_scene(page, background, unlike=None):
    """(the frame, RGB) once it shows the scene (and differs from frame ``unlike``), else None.
    Not before every pixel is opaque: viser draws its background image over the whole canvas,
    and a transparent canvas (nothing drawn) would read back as black."""
    rgba = page.frame()
    f = rgba[..., :3]
    if (rgba.shape[-1] == 4 and np.any(rgba[..., 3] != 255)) or \
            _scene_fraction(f, background) < WEB_SCENE_MIN_FRACTION:
        return None
    if unlike is not None and not np.mean(np.abs(f.astype(int) - unlike)) > WEB_MOVED_MEAN_LEVELS:
        return None
    return (f,)


@pytest.mark.slow
def test_browser_draws_the_scene_and_follows_the_mouse(trained, ply, tmp_path):
    _viser()
    d = _browser(webgl=True, extras="web,test")
    site, file_site = tmp_path / "site", tmp_path / "file_site"
    assert cli(["--quiet", "export", "--ckpt", str(trained), "--web", str(site)]) == 0
    assert cli(["--quiet", "export", "--ckpt", str(ply), "--web", str(file_site)]) == 0
    ds = checkpoint_dataset(checkpoint.load(trained))
    start = np.asarray(ds.poses[int(ds.split["test"][0])], np.float64)[:3, 3]
    served = StaticServer(site)
    try:
        from selenium.webdriver.common.action_chains import ActionChains
        page = Page(d, served.url)
        white = np.full(3, 255)
        (first,) = _wait("a frame of the scene", lambda: _shows_scene(page, white))
        _wait("the camera at the first test view", lambda: page.position() is not None and
              np.abs(page.position() - start).max() <= WEB_CAMERA_LOG_ATOL)
        ActionChains(d).move_to_element(page.canvas).click_and_hold() \
            .move_by_offset(150, 0).move_by_offset(150, 40).release().perform()
        _wait("the camera moved by the drag", lambda: np.abs(page.position() - start).max()
              > 100 * WEB_CAMERA_LOG_ATOL)
        _wait("another frame of the scene after the drag",
              lambda: _shows_scene(page, white, unlike=first))
    finally:
        served.close()
    served = StaticServer(file_site)    # a splat file: black background, the box view
    try:
        page = Page(d, served.url)
        black = np.zeros(3, int)
        (frame,) = _wait("a frame of the splat file's scene", lambda: _shows_scene(page, black))
        corners = frame[[0, 0, -1, -1], [0, -1, 0, -1]]
        assert np.abs(corners.astype(int)).max() <= WEB_SCENE_LEVEL, corners
    finally:
        served.close()
        d.quit()
