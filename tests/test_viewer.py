"""The viewer server without a browser: bad messages, clients leaving mid-frame, many clients,
a camera inside an occupied cell, stale requests dropped, the render-time share, loopback only.

Every wait is bounded (WAIT seconds), every loop bounded in count; servers listen on 127.0.0.1."""
import http.client
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
from websockets.exceptions import ConnectionClosed, InvalidStatus  # noqa: E402
from websockets.sync.client import connect  # noqa: E402

from clrf.data.cameras import look_at  # noqa: E402
from clrf.cli.main import build_parser  # noqa: E402
from clrf.outputs.frames import render_pose, spec_from_fov, to_uint8  # noqa: E402
from clrf.training.models import load_model  # noqa: E402
from clrf.viewer import dataset_cameras, render_loop  # noqa: E402
from clrf.viewer.core import (Frame, RequestError, ViewerCore, frame_image,  # noqa: E402
                              parse_request)
from clrf.viewer.server import (MAX_MESSAGE, Access, ViewerServer,  # noqa: E402
                                decode_frame, is_loopback, warn_host)
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
    return srv.ws_url


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
@pytest.mark.slow
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
        urllib.request.urlopen(f"http://{HOST}:{srv.port}/nothing-here", timeout=WAIT)
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


@pytest.mark.slow
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


# ---- access: Host, Origin, token, limits --------------------------------------------------------
# A browser lets any web page open a WebSocket to 127.0.0.1; these are what such a page, a
# DNS-rebinding page or a client without the printed URL gets: no page, no hello, no frame.
def raw_get(port, host_header, path="/", headers=()):
    """(status, body) of a GET with a chosen Host header (urllib always sends the real one)."""
    c = http.client.HTTPConnection(HOST, port, timeout=WAIT)
    try:
        c.putrequest("GET", path, skip_host=True)
        c.putheader("Host", host_header)
        for k, v in headers:
            c.putheader(k, v)
        c.endheaders()
        r = c.getresponse()
        return r.status, r.read()
    finally:
        c.close()


def refused_with(status, url, **kw):
    with pytest.raises(InvalidStatus) as e:
        with connect(url, open_timeout=WAIT, **kw):
            pass
    assert e.value.response.status_code == status
    return e.value.response.body.decode()


def hello_of(url, **kw):
    with connect(url, open_timeout=WAIT, **kw) as ws:
        return json.loads(ws.recv(timeout=WAIT))


def test_foreign_origin_gets_no_hello_even_with_the_token(server):
    srv, core = server
    for origin in ("http://evil.example", f"http://evil.example:{srv.port}", "null",
                   f"https://127.0.0.1:{srv.port}", f"http://127.0.0.1:{srv.port + 1}",
                   f"http://127.0.0.1.evil.example:{srv.port}"):
        body = refused_with(403, srv.ws_url, origin=origin)
        assert "may not connect" in body
    # the page's own origin, under any loopback alias, with the token: the hello
    for name in ("127.0.0.1", "localhost", "[::1]"):
        assert hello_of(srv.ws_url, origin=f"http://{name}:{srv.port}")["type"] == "hello"
    assert core.n_clients() <= 1


def test_no_token_or_a_wrong_one_is_refused(server):
    srv, core = server
    base = srv.ws_url.split("?")[0]
    assert len(srv.token) >= 32 and srv.token in srv.url   # 24 random bytes, in the URL
    assert "missing or wrong token" in refused_with(403, base)
    wrong = srv.token[:-1] + ("y" if srv.token[-1] == "x" else "x")   # one character off
    assert "missing or wrong token" in refused_with(403, base + "?token=" + wrong)
    assert "missing or wrong token" in refused_with(403, base + "?token=")
    # the token as a header (tools), and in the URL (the page)
    assert hello_of(base, additional_headers={"Authorization": f"token {srv.token}"})["type"] \
        == "hello"
    assert hello_of(srv.ws_url)["type"] == "hello"


def test_foreign_host_gets_no_page_and_no_socket(server):
    srv, core = server
    port = srv.port
    status, body = raw_get(port, f"127.0.0.1:{port}")
    assert status == 200 and b"clrfViewer" in body
    for host in (f"evil.example:{port}", "evil.example", f"127.0.0.1:{port + 1}", "",
                 f"localhost.evil.example:{port}", f"[::2]:{port}", "a b"):
        status, body = raw_get(port, host)
        assert status == 403 and b"clrfViewer" not in body, host
    status, _ = raw_get(port, f"localhost:{port}")
    assert status == 200
    # a WebSocket handshake with the token but a rebinding Host
    ws_headers = [("Upgrade", "websocket"), ("Connection", "Upgrade"),
                  ("Sec-WebSocket-Key", "dGhlIHNhbXBsZSBub25jZQ=="), ("Sec-WebSocket-Version", "13")]
    status, _ = raw_get(port, f"evil.example:{port}", "/ws?token=" + srv.token, ws_headers)
    assert status == 403
    status, _ = raw_get(port, f"127.0.0.1:{port}", "/ws?token=" + srv.token, ws_headers)
    assert status == 101


def test_access_rules():
    lo = Access("127.0.0.1", 8080, "t" * 32)
    assert lo.host_ok("127.0.0.1:8080") and lo.host_ok("localhost:8080") and \
        lo.host_ok("[::1]:8080") and lo.host_ok("LOCALHOST:8080")
    assert not lo.host_ok("127.0.0.1:8081") and not lo.host_ok("127.0.0.1") and \
        not lo.host_ok("10.0.0.1:8080") and not lo.host_ok("evil.example:8080") and \
        not lo.host_ok(None) and not lo.host_ok("127.0.0.1:8080:1")
    assert Access("127.0.0.1", 80).host_ok("localhost")   # port 80: browsers omit it
    assert lo.origin_ok("http://localhost:8080") and not lo.origin_ok("http://localhost:8080/x")
    assert not lo.origin_ok("http://user@localhost:8080") and not lo.origin_ok("")
    # every interface: IP literals and localhost, never a DNS name unless allowed
    anyip = Access("0.0.0.0", 9000, "t" * 32, allow_hosts=["box.lan"])
    assert anyip.host_ok("192.168.1.5:9000") and anyip.host_ok("[fe80::1]:9000") and \
        anyip.host_ok("localhost:9000") and anyip.host_ok("box.lan:9000")
    assert not anyip.host_ok("rebind.evil.example:9000") and not anyip.host_ok("box.lan:9001")
    one = Access("192.168.1.5", 9000, "t" * 32)
    assert one.host_ok("192.168.1.5:9000") and not one.host_ok("localhost:9000")
    # the token: the query or an Authorization header, nothing else
    assert lo.token_ok("/ws?token=" + "t" * 32, {}) and not lo.token_ok("/ws", {})
    assert lo.token_ok("/ws", {"Authorization": "Bearer " + "t" * 32})
    assert not lo.token_ok("/ws", {"Authorization": "Basic " + "t" * 32})
    assert Access("127.0.0.1", 1, None).token_ok("/ws", {})


def test_tokens_are_new_each_run(loaded):
    model, state = loaded
    a = ViewerServer(ViewerCore(model, state["dataset"]), HOST, 0)
    b = ViewerServer(ViewerCore(model, state["dataset"]), HOST, 0)
    assert a.token != b.token and len(a.token) >= 32


def test_no_token_on_loopback_still_checks_origin(loaded):
    model, state = loaded
    core = ViewerCore(model, state["dataset"])
    srv = ViewerServer(core, HOST, 0, token=None).start()
    try:
        assert "token" not in srv.url and srv.ws_url.endswith("/ws")
        assert hello_of(srv.ws_url)["type"] == "hello"
        refused_with(403, srv.ws_url, origin="http://evil.example")
    finally:
        srv.stop()
    from clrf.viewer.core import ViewerError
    with pytest.raises(ViewerError, match="loopback"):
        ViewerServer(core, "0.0.0.0", 0, token=None)


def test_client_cap_and_render_rate(loaded):
    model, state = loaded
    core = ViewerCore(model, state["dataset"])
    srv = ViewerServer(core, HOST, 0, max_clients=2, max_fps=2).start()
    stop = threading.Event()
    th = threading.Thread(target=render_loop, args=(core, 600.0, stop), daemon=True)
    th.start()
    try:
        with connect(srv.ws_url, open_timeout=WAIT) as a, \
                connect(srv.ws_url, open_timeout=WAIT) as b:
            for ws in (a, b):
                assert json.loads(ws.recv(timeout=WAIT))["type"] == "hello"
            assert "--max-clients" in refused_with(503, srv.ws_url)
            # 8 requests at once: the first 2 pass (a burst of max_fps), the rest are refused
            for i in range(8):
                a.send(json.dumps(request(seq=i + 1)))
            # the 6 refusals and the frame of the newest accepted request, in whatever order
            # they come (with the kernels already compiled the frame can come before the
            # refusals are all sent)
            errors, frames = [], []

            def refusals_and_frame(m):
                if isinstance(m, dict) and m["type"] == "error":
                    errors.append(m["message"])
                elif isinstance(m, tuple):
                    frames.append(m[0]["seq"])
                return len(errors) == 6 and 2 in frames
            recv_until(a, refusals_and_frame, "6 refusals and frame 2")
            assert all("--max-fps" in m for m in errors)
            assert set(frames) <= {1, 2}     # nothing refused was rendered
        # both gone: a new page connects
        wait_for = time.monotonic() + WAIT
        while srv.n_clients() and time.monotonic() < wait_for:
            time.sleep(0.05)
        assert hello_of(srv.ws_url)["type"] == "hello"
    finally:
        stop.set()
        th.join(timeout=WAIT)
        srv.stop()
