"""`clrf train --view`: the page's stats, frames of the model being trained, pause and resume
from a client, and training that finishes after the client has gone. Bounded waits only."""
import json
import os
import queue
import subprocess
import sys
import threading
import time

import pytest

pytest.importorskip("websockets", reason="the viewer needs websockets (clrf[view])")
from websockets.sync.client import connect  # noqa: E402

from clrf.outputs import checkpoint  # noqa: E402
from clrf.data.cameras import look_at  # noqa: E402
from clrf.viewer.server import decode_frame  # noqa: E402
from viewer_util import FAST, ROOT, START_TIMEOUT, browser, console_errors, wait  # noqa: E402

WAIT = 60.0


def messages(ws, pred, what, timeout=WAIT):
    deadline = time.monotonic() + timeout
    for _ in range(10000):
        left = deadline - time.monotonic()
        if left <= 0:
            break
        m = ws.recv(timeout=left)
        m = decode_frame(m) if isinstance(m, bytes) else json.loads(m)
        if pred(m):
            return m
    raise AssertionError(f"no {what} within {timeout:.0f} s")


def is_stats(m):
    return isinstance(m, dict) and m["type"] == "stats"


def start_training(out, seconds):
    """`clrf train --view --port 0` in a subprocess; (process, page URL)."""
    env = dict(os.environ)   # the installed clrf (tests/conftest.py)
    p = subprocess.Popen([sys.executable, "-m", "clrf.cli", "--quiet", "train", "--out", str(out),
                          "--max-seconds", str(seconds), "--view", "--port", "0", *FAST],
                         stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env,
                         cwd=str(out.parent))
    lines = queue.Queue()
    threading.Thread(target=lambda: [lines.put(x) for x in p.stderr], daemon=True).start()
    url, seen, deadline = None, [], time.monotonic() + START_TIMEOUT
    while url is None and time.monotonic() < deadline and p.poll() is None:
        try:
            line = lines.get(timeout=1.0)
        except queue.Empty:
            continue
        seen.append(line)
        if "viewer at " in line:
            url = line.split("viewer at ", 1)[1].split()[0]
    if url is None:
        p.kill()
        p.wait(timeout=10)
        raise AssertionError("".join(seen))
    return p, url


@pytest.mark.slow
@pytest.mark.quick        # the quick tier's test of this module (tests/conftest.py)
def test_train_with_the_viewer(tmp_path):
    p, url = start_training(tmp_path / "run", 10)
    out = tmp_path / "run"
    try:
        base, token = url.split("?token=")
        with connect(base.replace("http://", "ws://") + "ws?token=" + token,
                     open_timeout=WAIT) as ws:
            hello = messages(ws, lambda m: m.get("type") == "hello", "hello")
            assert hello["training"] and hello["cameras"]
            c2w = look_at([3.0, 1.0, 2.0], [0, 0, 0]).reshape(-1).tolist()
            ws.send(json.dumps({"type": "render", "seq": 1, "c2w": c2w, "fov": 40,
                                "width": 32, "height": 24}))   # rendered after a step
            hdr, img = messages(ws, lambda m: isinstance(m, tuple), "a frame")
            assert img.shape == (24, 32, 3)
            st = messages(ws, lambda m: is_stats(m) and m["iteration"] >= 1, "stats")
            assert "grid" in st["model"] and st["rays_per_s"] > 0 and st["curve"]
            ws.send(json.dumps({"type": "pause"}))   # takes effect after the current step
            messages(ws, lambda m: is_stats(m) and m["paused"], "paused stats")
            time.sleep(1.0)
            ws.send(json.dumps({"type": "render", "seq": 2, "c2w": c2w, "fov": 40,
                                "width": 32, "height": 24}))
            messages(ws, lambda m: isinstance(m, tuple) and m[0]["seq"] == 2, "a paused frame")
            it = messages(ws, is_stats, "stats while paused")["iteration"]
            time.sleep(1.0)
            st = messages(ws, is_stats, "stats while paused")
            assert st["paused"] and st["iteration"] == it, "paused training must not step"
            ws.send(json.dumps({"type": "resume"}))
            messages(ws, lambda m: is_stats(m) and not m["paused"] and m["iteration"] > it,
                     "training again")
            # pause, then leave: training must not stay paused
            ws.send(json.dumps({"type": "pause"}))
            messages(ws, lambda m: is_stats(m) and m["paused"], "paused again")
        assert p.wait(timeout=START_TIMEOUT + 60) == 0
        st = checkpoint.load(out)
        assert st["seconds"] >= 10 and st["iteration"] > it
    finally:
        if p.poll() is None:
            p.kill()
            p.wait(timeout=10)


@pytest.mark.slow
def test_training_page_in_a_browser(tmp_path):
    """The page in training mode: stats, the curve, pause and resume by its button."""
    from selenium.webdriver.common.by import By
    d = browser()
    p, url = start_training(tmp_path / "run", 10)
    try:
        d.get(url)
        stats = d.find_element(By.ID, "stats")
        wait("training stats", lambda: "iteration" in stats.text and "grid" in stats.text)
        button = d.find_element(By.ID, "pause")
        button.click()
        wait("the paused state", lambda: "PAUSED" in stats.text and button.text == "resume")
        button.click()
        wait("training again", lambda: "PAUSED" not in stats.text and button.text == "pause")
        wait("a curve", lambda: d.execute_script(
            "return clrfViewer.state.stats.curve.length > 1"))
        wait("a frame", lambda: d.execute_script("return clrfViewer.displayed() !== null"))
        assert console_errors(d) == []
        assert d.execute_script("return clrfViewer.state.errors") == []
        d.quit()   # closing the page does not stop training
        d = None
        assert p.wait(timeout=START_TIMEOUT + 60) == 0
        assert checkpoint.load(tmp_path / "run")["seconds"] >= 10
    finally:
        if d is not None:
            d.quit()
        if p.poll() is None:
            p.kill()
            p.wait(timeout=10)
