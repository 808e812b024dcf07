"""`clrf view` in a real browser: headless Chromium (Debian `chromium` + `chromium-driver`)
through Selenium. The camera is moved with the page's own mouse controls (drag to orbit, wheel
to zoom); the image the page displays is read back from its canvas and compared with
`clrf render --camera-path` for the same camera. Skips with the reason when no browser is
installed (`bash tools/setup.sh view,test` installs one).

CLRF_VIEWER_SCREENSHOT=FILE.png also saves a larger screenshot of the page there (the README's
docs/img/viewer.png is made this way; the model then trains 20 s instead of 2)."""
import os

import imageio.v3 as iio
import numpy as np
import pytest

from clrf.outputs import camera_path
from clrf.cli.main import main as cli
from clrf.testing.tolerances import VIEWER_PIXEL_ATOL
from viewer_util import ViewProcess, browser as _browser, console_errors, train_tiny
from viewer_util import wait as _wait

pytestmark = pytest.mark.slow

W, H = 96, 72           # canvas pixels: below the default resolution cap, so shown 1:1


def _rest_frame(d):
    """The displayed frame once it is the full-resolution one of the page's current camera."""
    def ready():
        disp = d.execute_script("return clrfViewer.displayed()")
        cam = d.execute_script("return clrfViewer.camera()")
        if disp and not disp["moving"] and disp["c2w"] == cam["c2w"] and \
                disp["width"] == cam["width"] and disp["height"] == cam["height"] and \
                not d.execute_script("return clrfViewer.state.inflight || "
                                     "clrfViewer.state.dirty"):
            return disp
        return None
    return _wait("a full-resolution frame of the current camera", ready)


def _canvas_pixels(d):
    data = d.execute_script("const c = document.getElementById('view');"
                            "return Array.from(c.getContext('2d')"
                            ".getImageData(0, 0, c.width, c.height).data);")
    return np.asarray(data, np.uint8).reshape(H, W, 4)


def _clrf_render(ckpt, pose, fov, out):
    out.mkdir(parents=True, exist_ok=True)
    f = out / "camera_path.json"
    camera_path.save(f, camera_path.CameraPath(np.asarray(pose)[None], np.array([fov]), W, H))
    assert cli(["--quiet", "render", "--ckpt", str(ckpt), "--camera-path", str(f),
                "--out", str(out)]) == 0
    return iio.imread(out / "path_000.png")


def test_browser_shows_what_clrf_render_renders(tmp_path):
    d = _browser()
    shot = os.environ.get("CLRF_VIEWER_SCREENSHOT")
    ckpt = train_tiny(tmp_path / "run", 20.0 if shot else 2.0)   # a clearer model to show
    view = ViewProcess(ckpt)
    try:
        from selenium.webdriver.common.action_chains import ActionChains
        from selenium.webdriver.common.actions.wheel_input import ScrollOrigin
        from selenium.webdriver.common.by import By
        d.get(view.url)
        _wait("the page's API", lambda: d.execute_script(
            "return window.clrfViewer && clrfViewer.state.scene !== null"))
        d.execute_script(f"clrfViewer.fixedSize = true; clrfViewer.setSize({W}, {H})")
        first = _rest_frame(d)
        canvas = d.find_element(By.ID, "view")
        # orbit with the mouse, then zoom with the wheel: the page's own controls
        ActionChains(d).move_to_element(canvas).click_and_hold().move_by_offset(25, 8) \
            .move_by_offset(20, -4).release().perform()
        ActionChains(d).scroll_from_origin(ScrollOrigin.from_element(canvas), 0, 150).perform()
        shown = _rest_frame(d)
        assert shown["seq"] > first["seq"]
        moved = np.abs(np.subtract(shown["c2w"], first["c2w"])).max()
        assert moved > 0.05, "the drag and the wheel must have moved the camera"
        assert d.execute_script("return clrfViewer.state.errors") == []
        px = _canvas_pixels(d)
        assert (px[..., 3] == 255).all()
        ref = _clrf_render(ckpt, np.reshape(shown["c2w"], (4, 4)), shown["fov"], tmp_path / "a")
        assert ref.shape == (H, W, 3) and ref.std() > 5, "a blank render proves nothing"
        diff = np.abs(px[..., :3].astype(int) - ref.astype(int))
        assert diff.max() <= VIEWER_PIXEL_ATOL, (diff.max(), (diff > VIEWER_PIXEL_ATOL).mean())
        # the comparison can fail: the camera before the mouse moved gives another image
        before = _clrf_render(ckpt, np.reshape(first["c2w"], (4, 4)), first["fov"],
                              tmp_path / "b")
        assert np.abs(px[..., :3].astype(int) - before.astype(int)).max() > 10 * VIEWER_PIXEL_ATOL
        # a camera from the list: the page takes its pose and field of view
        button = d.find_element(By.XPATH, "//div[@id='cams']/button[starts-with(., 'test')]")
        name = button.text
        button.click()
        cam = next(c for c in d.execute_script("return clrfViewer.state.cameras")
                   if c["name"] == name)
        now = _rest_frame(d)
        assert now["c2w"] == cam["c2w"] and now["fov"] == pytest.approx(cam["fov"])
        # record two keyframes with an orbit between them, save the camera path
        d.find_element(By.ID, "addkey").click()
        ActionChains(d).move_to_element(canvas).click_and_hold().move_by_offset(-30, 0) \
            .release().perform()
        _rest_frame(d)
        d.find_element(By.ID, "addkey").click()
        keys = d.execute_script("return clrfViewer.state.keys")
        for field, value in (("fps", "4"), ("secs", "1")):
            el = d.find_element(By.ID, field)
            el.clear()
            el.send_keys(value)
        d.find_element(By.ID, "savepath").click()
        _wait("the saved path", lambda: "camera_path.json" in d.find_element(By.ID, "saved").text)
        saved = camera_path.load(ckpt / "camera_path.json")
        assert (saved.width, saved.height, saved.fps, len(saved.poses)) == (W, H, 4.0, 4)
        assert len(keys) == len(saved.keyframes) == 2
        for k, (pose, fov) in zip(keys, saved.keyframes):
            np.testing.assert_array_equal(pose.reshape(-1), k["c2w"])
            assert fov == k["fov"]
        np.testing.assert_array_equal(saved.poses[0], saved.keyframes[0][0])
        # a refused request (a resolution below the minimum) does not leave the page stuck
        d.execute_script("document.getElementById('movecap').value = '1'; "
                         "clrfViewer.request(true)")
        _wait("the refusal", lambda: d.execute_script("return clrfViewer.state.errors.length"))
        d.execute_script("document.getElementById('movecap').value = '200'; "
                         "clrfViewer.request(false)")
        _rest_frame(d)
        d.save_screenshot(str(tmp_path / "viewer.png"))
        assert console_errors(d) == []
        if shot:   # a larger view for the README
            d.execute_script("clrfViewer.setSize(640, 480)")
            _rest_frame_any(d)
            d.save_screenshot(shot)
        assert view.alive()
    finally:
        d.quit()
        view.close()


def _rest_frame_any(d):
    return _wait("a full-resolution frame", lambda: (lambda disp: disp if disp and not
                 disp["moving"] and disp["width"] == d.execute_script(
                     "return clrfViewer.camera().width") else None)(
        d.execute_script("return clrfViewer.displayed()")))


_ATTACK_PAGE = """<!doctype html><html><body><script>
// another web page open in the same browser: it tries the viewer's WebSocket, without the
// token and with it (as if the token had leaked), and logs what it gets
window.events = [];
function attempt(name, url) {
  let ws;
  try { ws = new WebSocket(url); } catch (e) { events.push([name, "throw"]); return; }
  ws.onopen = () => events.push([name, "open"]);
  ws.onmessage = m => events.push([name, "message", String(m.data).slice(0, 80)]);
  ws.onclose = () => events.push([name, "close"]);
}
attempt("no token", "ws://127.0.0.1:%(port)d/ws");
attempt("leaked token", "ws://127.0.0.1:%(port)d/ws?token=%(token)s");
attempt("localhost", "ws://localhost:%(port)d/ws?token=%(token)s");
fetch("http://127.0.0.1:%(port)d/").then(r => r.text()).then(
  t => events.push(["fetch", "read", t.slice(0, 80)]), () => events.push(["fetch", "blocked"]));
</script></body></html>"""


@pytest.mark.quick        # the quick tier's test of this module (tests/conftest.py)
def test_another_page_cannot_reach_the_viewer(tmp_path):
    """A page served from another local port opens the viewer's WebSocket in headless
    Chromium and gets no hello and no frame (the Origin check), and cannot read the page
    (same-origin policy); the printed URL then works in the same browser, and the URL without
    its token shows the refusal."""
    import http.server
    import threading
    from urllib.parse import urlsplit
    d = _browser()
    ckpt = train_tiny(tmp_path / "run", 2.0)
    view = ViewProcess(ckpt)
    token = urlsplit(view.url).query.split("token=")[1]
    page = (_ATTACK_PAGE % {"port": view.port, "token": token}).encode()

    class Attack(http.server.BaseHTTPRequestHandler):
        def do_GET(self):
            self.send_response(200)
            self.send_header("Content-Type", "text/html")
            self.send_header("Content-Length", str(len(page)))
            self.end_headers()
            self.wfile.write(page)

        def log_message(self, *args):
            pass

    evil = http.server.ThreadingHTTPServer(("127.0.0.1", 0), Attack)
    threading.Thread(target=evil.serve_forever, daemon=True).start()
    try:
        d.get(f"http://127.0.0.1:{evil.server_address[1]}/")
        events = _wait("the attack page's three attempts to end", lambda: (lambda ev: ev if sum(
            e[1] in ("close", "throw") for e in ev) == 3 and any(e[0] == "fetch" for e in ev)
            else None)(d.execute_script("return window.events")))
        assert not [e for e in events if e[1] in ("open", "message", "read")], events
        refused = console_errors(d)   # the browser's own report of the refused handshakes
        assert sum("WebSocket" in m and "403" in m for m in refused) == 3, refused
        # the printed URL, in the same browser: connected, the scene and a frame
        d.get(view.url)
        _wait("the hello", lambda: d.execute_script(
            "return window.clrfViewer && clrfViewer.state.scene !== null"))
        _wait("a frame", lambda: d.execute_script("return clrfViewer.displayed() !== null"))
        assert console_errors(d) == []
        # the same address without the token: refused, said on the page
        d.get(view.url.split("?")[0])
        status = d.find_element("id", "status")
        _wait("the refusal on the page", lambda: "refused" in status.text)
        assert d.execute_script("return clrfViewer.state.scene") is None
        assert view.alive()
    finally:
        evil.shutdown()
        d.quit()
        view.close()
