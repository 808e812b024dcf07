"""The viewer server without a browser: bad messages, clients leaving mid-frame, many clients,
a camera inside an occupied cell, stale requests dropped, the render-time share, loopback only.

Every wait is bounded (WAIT seconds), every loop bounded in count; servers listen on 127.0.0.1."""
import json
import math
import socket
import threading
import time
import urllib.error
import urllib.request

import numpy as np
import pytest

pytest.importorskip("websockets", reason="the viewer needs websockets (clrf[view])")
from websockets.exceptions import ConnectionClosed  # noqa: E402
from websockets.sync.client import connect  # noqa: E402

from clrf.data.cameras import look_at  # noqa: E402
from clrf.cli.main import build_parser  # noqa: E402
from clrf.outputs.frames import render_pose, spec_from_fov, to_uint8  # noqa: E402
from clrf.training.models import load_model  # noqa: E402
from clrf.viewer import dataset_cameras, render_loop  # noqa: E402
from clrf.viewer.core import (Frame, RequestError, ViewerCore, frame_image,  # noqa: E402
                              parse_request)
from clrf.viewer.server import (MAX_MESSAGE, ViewerServer, decode_frame,  # noqa: E402
                                is_loopback, warn_host)
from viewer_util import train_tiny  # noqa: E402

WAIT = 60.0    # seconds any one reply may take (PoCL on a loaded 2-core machine)
HOST = "127.0.0.1"


@pytest.fixture(scope="module")
def ckpt(tmp_path_factory):
    return train_tiny(tmp_path_factory.mktemp("view") / "run")


@pytest.fixture(scope="module")
def loaded(device, ckpt):
    model, state, cfg = load_model(device, ckpt)
    return model, state


@pytest.fixture
def server(loaded, tmp_path):
    """A viewer on a free loopback port with its render thread; yields (server, core)."""
    model, state = loaded
    core = ViewerCore(model, state["dataset"])
    srv = ViewerServer(core, HOST, 0, tmp_path).start()
    stop = threading.Event()
    th = threading.Thread(target=render_loop, args=(core, 600.0, stop), daemon=True)
    th.start()
    yield srv, core
    stop.set()
    th.join(timeout=WAIT)
    srv.stop()
    assert not th.is_alive()


def request(seq=1, **kw):
    m = {"type": "render", "seq": seq, "fov": 40.0, "width": 32, "height": 24,
         "c2w": look_at([3.0, 1.0, 2.0], [0, 0, 0]).reshape(-1).tolist()}
    m.update(kw)
    return m


def recv_until(ws, pred, what):
    """Messages until pred(message) is true (bounded in time and count)."""
    deadline = time.monotonic() + WAIT
    for _ in range(1000):
        left = deadline - time.monotonic()
        if left <= 0:
            break
        m = ws.recv(timeout=left)
        m = decode_frame(m) if isinstance(m, bytes) else json.loads(m)
        if pred(m):
            return m
    raise AssertionError(f"no {what} within {WAIT:.0f} s")


def frame_of(ws, seq):
    return recv_until(ws, lambda m: isinstance(m, tuple) and m[0]["seq"] == seq, f"frame {seq}")


def error_of(ws):
    return recv_until(ws, lambda m: isinstance(m, dict) and m["type"] == "error", "error")


def ws_url(srv):
    return f"ws://{HOST}:{srv.port}/ws"


# ---- validation -------------------------------------------------------------------------
@pytest.mark.parametrize("bad, field", [
    ({"c2w": [float("nan")] * 16}, "NaN"),
    ({"c2w": [math.inf] + [0.0] * 15}, "NaN or infinite"),
    ({"c2w": [1.0] * 15}, "c2w"),
    ({"c2w": ["x"] * 16}, "c2w"),
    ({"c2w": (2 * np.eye(4)).reshape(-1).tolist()}, "rotation"),
    ({"fov": 0}, "fov"), ({"fov": 500}, "fov"), ({"fov": float("nan")}, "fov"),
    ({"fov": "50"}, "fov"), ({"width": 0}, "width"), ({"height": 1e12}, "height"),
    ({"width": True}, "width"), ({"output": "normals"}, "output"),
    ({"background": [2, 0, 0]}, "background"), ({"near": -1}, "near"),
    ({"near": float("inf")}, "near"), ({"cap": 1}, "cap"), ({"cap": 5000}, "cap"),
])
def test_bad_requests_name_the_field(bad, field):
    with pytest.raises(RequestError, match=field):
        parse_request(request(**bad))


def test_request_scaled_to_the_cap_with_the_same_field_of_view():
    fr = parse_request(request(width=1600, height=1200, cap=400))
    assert (fr.width, fr.height, fr.moving) == (400, 300, False)
    fr = parse_request(request(width=1600, height=1200, moving=True, move_cap=200))
    assert (fr.width, fr.height, fr.moving) == (200, 150, True)
    fr = parse_request(request(width=64, height=48, cap=800))
    assert (fr.width, fr.height) == (64, 48)


# ---- one frame in flight per client, render-time share ---------------------------------------
def test_stale_requests_are_dropped(loaded):
    model, state = loaded
    core = ViewerCore(model, state["dataset"])
    got = []
    cid = core.add_client(lambda h, img: got.append(h))
    for s in range(1, 6):
        core.submit(cid, request(seq=s))
    assert core.serve_pending(budget=False) == 1
    assert [h["seq"] for h in got] == [5] and core._clients[cid].dropped == 4
    assert core.serve_pending(budget=False) == 0


def test_render_share_is_bounded(loaded):
    model, state = loaded
    core = ViewerCore(model, state["dataset"], share=0.2, training=True)
    cid = core.add_client(lambda h, img: None)
    core.render_seconds = 1.0
    core._t0 = time.perf_counter() - 2.0      # 1 s of 2 s rendered: over a 20 % share
    core.submit(cid, request())
    assert core.serve_pending() == 0 and core.has_pending()
    core._t0 = time.perf_counter() - 10.0     # 1 s of 10 s: within it
    assert core.serve_pending() == 1


# ---- the server ------------------------------------------------------------------------------
def test_page_and_hello(server):
    srv, core = server
    html = urllib.request.urlopen(srv.url, timeout=WAIT).read().decode()
    assert "clrfViewer" in html and "<canvas" in html
    with pytest.raises(urllib.error.HTTPError):
        urllib.request.urlopen(srv.url + "nothing-here", timeout=WAIT)
    with connect(ws_url(srv), open_timeout=WAIT) as ws:
        hello = json.loads(ws.recv(timeout=WAIT))
        assert hello["type"] == "hello" and not hello["training"]
        assert np.asarray(hello["scene"]["bbox"]).shape == (2, 3)


def test_frame_equals_the_shared_render_path(server, loaded):
    srv, core = server
    model, state = loaded
    m = request(seq=7, width=40, height=30)
    with connect(ws_url(srv), open_timeout=WAIT) as ws:
        ws.send(json.dumps(m))
        hdr, img = frame_of(ws, 7)
    spec = spec_from_fov(m["fov"], 40, 30, state["dataset"])
    ref = to_uint8(render_pose(model, spec, np.reshape(m["c2w"], (4, 4)))["rgb"])
    np.testing.assert_array_equal(img, ref)   # the same code path: identical bytes
    assert img.std() > 5, "a blank frame proves nothing"


@pytest.mark.parametrize("garbage", [
    "not json {", "[1, 2, 3]", "null", '{"type": "fly"}', '{"no_type": 1}',
    '{"type": "render", "c2w": [NaN, NaN, NaN, NaN, NaN, NaN, NaN, NaN, NaN, NaN, NaN, NaN, '
    'NaN, NaN, NaN, NaN], "fov": 40, "width": 8, "height": 8}',
    '{"type": "render", "c2w": "identity"}', '{"type": "render", "c2w": [1e400]}',
    '{"type": "pause"}', '{"type": "save_path", "keyframes": "x"}',
    json.dumps(request(fov=float("inf"))), "[" * 100000 + "]" * 100000,
])
def test_garbage_messages_get_an_error_and_the_server_keeps_answering(server, garbage):
    srv, core = server
    with connect(ws_url(srv), open_timeout=WAIT) as ws:
        ws.send(garbage)
        assert error_of(ws)["message"]
        ws.send(b"\x00\x01binary")
        assert "JSON" in error_of(ws)["message"]
        ws.send(json.dumps(request(seq=3)))
        frame_of(ws, 3)
    assert core.errors == 0


def test_oversized_message_closes_only_that_client(server):
    srv, core = server
    with connect(ws_url(srv), open_timeout=WAIT, max_size=None) as ws:
        ws.send("x" * (MAX_MESSAGE + 1))
        with pytest.raises(ConnectionClosed):
            recv_until(ws, lambda m: False, "the close")
    with connect(ws_url(srv), open_timeout=WAIT) as ws:
        ws.send(json.dumps(request(seq=2)))
        frame_of(ws, 2)


def test_client_disconnecting_mid_frame(server):
    srv, core = server
    for i in range(4):   # leave while a large frame renders: closing, or dropping the socket
        with connect(ws_url(srv), open_timeout=WAIT) as ws:
            ws.send(json.dumps(request(seq=1, width=300, height=300)))
            time.sleep(0.05 * i)
            if i % 2:
                ws.socket.shutdown(socket.SHUT_RDWR)
    with connect(ws_url(srv), open_timeout=WAIT) as ws:
        ws.send(json.dumps(request(seq=9)))
        frame_of(ws, 9)
    deadline = time.monotonic() + WAIT
    while core.n_clients() > 0 and time.monotonic() < deadline:
        time.sleep(0.05)
    assert core.n_clients() == 0 and core.errors == 0


def test_many_clients_at_once(server):
    srv, core = server
    n, results, errors = 6, {}, []

    def client(k):
        try:
            with connect(ws_url(srv), open_timeout=WAIT) as ws:
                c2w = look_at([3.0, 0.5 * k - 1, 2.0], [0, 0, 0]).reshape(-1).tolist()
                for s in range(1, 4):        # newer requests replace older ones
                    ws.send(json.dumps(request(seq=s, c2w=c2w)))
                results[k] = frame_of(ws, 3)
        except Exception as e:   # noqa: BLE001 - reported below
            errors.append(repr(e))

    threads = [threading.Thread(target=client, args=(k,)) for k in range(n)]
    for t in threads:
        t.start()
    for t in threads:
        t.join(timeout=2 * WAIT)
    assert not errors and len(results) == n
    imgs = [results[k][1] for k in range(n)]
    assert any(np.abs(imgs[0].astype(int) - im.astype(int)).max() > 10 for im in imgs[1:]), \
        "each client gets its own camera's frame"


def test_camera_inside_an_occupied_cell(server, loaded):
    srv, core = server
    model, state = loaded
    g = model.grid
    links, dens = g.links.get(), g.density.get()
    occ = np.argwhere(links >= 0)
    ijk = occ[np.argmax(dens[links[tuple(occ.T)]])]          # the densest voxel
    b = np.asarray(g.bbox, np.float64)
    centre = b[0] + (ijk + 0.5) * (b[1] - b[0]) / np.asarray(g.reso)
    c2w = look_at(centre, centre + [0.3, 0.2, 0.1]).reshape(-1).tolist()
    with connect(ws_url(srv), open_timeout=WAIT) as ws:
        for out in ("rgb", "depth", "acc"):
            ws.send(json.dumps(request(seq=4, c2w=c2w, output=out)))
            hdr, img = frame_of(ws, 4)
            assert hdr["output"] == out and img.shape == (24, 32, 3)
    fr = Frame(1, np.reshape(c2w, (4, 4)), 40.0, 32, 24, False, "rgb", None, 0.0)
    r = render_pose(model, spec_from_fov(40.0, 32, 24), fr.pose)
    assert all(np.isfinite(v).all() for v in r.values())


def test_background_and_near_controls(loaded):
    model, state = loaded
    base = Frame(1, look_at([3.0, 1.0, 2.0], [0, 0, 0]), 40.0, 32, 24, False, "rgb", None, 0.0)
    r = render_pose(model, spec_from_fov(40.0, 32, 24), base.pose)
    red = frame_image(model, Frame(**{**base.__dict__, "background": (1.0, 0.0, 0.0)}),
                      state["dataset"])
    bg = np.asarray(model.background, np.float32)
    want = to_uint8(r["rgb"] + (1 - r["acc"])[..., None] * (np.array([1, 0, 0], np.float32) - bg))
    np.testing.assert_array_equal(red, want)
    far = frame_image(model, Frame(**{**base.__dict__, "near": 100.0, "output": "acc"}),
                      state["dataset"])
    assert far.max() == 0, "a near plane beyond the scene leaves nothing to see"


def test_dataset_cameras(ckpt):
    from clrf.outputs import checkpoint
    from clrf.training.models import checkpoint_dataset
    ds = checkpoint_dataset(checkpoint.load(ckpt), None)
    cams = dataset_cameras(ds)
    assert len(cams) == len(ds.split["train"]) + len(ds.split["test"])
    c = cams[-1]
    i = int(c["name"].split()[1])
    np.testing.assert_allclose(np.reshape(c["c2w"], (4, 4)), ds.poses[i])
    fy = 0.5 * ds.hw[0] / math.tan(math.radians(c["fov"]) / 2)
    assert fy == pytest.approx(ds.intrinsics[1])


# ---- exposure ----------------------------------------------------------------------------------
def test_loopback_by_default_and_a_warning_otherwise(capsys):
    a = build_parser().parse_args(["view", "--ckpt", "x"])
    assert a.host == "127.0.0.1" and is_loopback(a.host)
    assert is_loopback("::1") and is_loopback("localhost") and is_loopback("127.0.0.2")
    assert not is_loopback("0.0.0.0") and not is_loopback("192.168.1.5")
    warn_host("127.0.0.1")
    assert capsys.readouterr().err == ""
    warn_host("0.0.0.0")
    assert "warning" in capsys.readouterr().err


def test_viewer_speed_tool_runs(ckpt, tmp_path):
    import subprocess
    import sys
    from viewer_util import ROOT
    out = tmp_path / "speed.json"
    r = subprocess.run([sys.executable, str(ROOT / "tools" / "viewer_speed.py"), "--ckpt",
                        str(ckpt), "--frames", "3", "--repeats", "2", "--warmup", "1",
                        "--move-size", "24", "--rest-size", "40", "--json", str(out)],
                       capture_output=True, text=True, timeout=600, cwd=str(ROOT))
    assert r.returncode == 0, r.stderr
    res = json.loads(out.read_text())
    assert res["moving_fps"] > 0 and res["time_to_full_s_median"] > 0
    assert (res["moving_size"], res["rest_size"]) == (24, 40)


def test_nerf_checkpoint_in_the_viewer(device, tmp_path):
    """The viewer renders a NeRF checkpoint through the same path (and swaps its background)."""
    from clrf.cli.main import main as cli
    out = tmp_path / "n"
    tiny = ["--set", "nerf.width=16", "--set", "nerf.depth=2", "--set", "nerf.color_width=16",
            "--set", "nerf.n_coarse=8", "--set", "nerf.n_fine=8", "--set", "nerf.batch_rays=256",
            "--set", "train.eval_every=1.0", "--set", "train.eval_views=2",
            "--set", "train.final_eval=false"]
    assert cli(["--quiet", "train", "--model", "nerf", "--out", str(out), "--max-seconds", "1",
                *tiny]) == 0
    model, state, _ = load_model(device, out)
    core = ViewerCore(model, state["dataset"])
    got = []
    cid = core.add_client(lambda h, img: got.append((h, img)))
    core.submit(cid, request(seq=1, background=[0.0, 1.0, 0.0]))
    assert core.serve_pending(budget=False) == 1 and core.errors == 0
    hdr, img = got[0]
    r = render_pose(model, spec_from_fov(40.0, 32, 24, state["dataset"]),
                    np.reshape(request()["c2w"], (4, 4)))
    bg = np.asarray(model.background, np.float32)
    want = to_uint8(r["rgb"] + (1 - r["acc"])[..., None] * (np.float32([0, 1, 0]) - bg))
    np.testing.assert_array_equal(img, want)


def test_view_usage_errors(tmp_path, loaded, capsys):
    from clrf.viewer.core import ViewerError
    from clrf.cli.main import main as cli
    assert cli(["view", "--ckpt", str(tmp_path / "nothing"), "--port", "0"]) == 2
    assert "no checkpoint" in capsys.readouterr().err
    model, state = loaded
    with socket.socket() as busy:
        busy.bind((HOST, 0))
        busy.listen(1)
        port = busy.getsockname()[1]
        with pytest.raises(ViewerError, match="another --port"):
            ViewerServer(ViewerCore(model, state["dataset"]), HOST, port).start()
