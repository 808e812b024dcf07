"""Helpers of the viewer tests: a tiny checkpoint, and `clrf view` as a subprocess."""
import importlib.util
import os
import queue
import shutil
import subprocess
import sys
import threading
import time
from pathlib import Path
from urllib.parse import urlsplit

import pytest

from clrf.cli.main import main as cli

ROOT = Path(__file__).resolve().parent.parent
# the built-in procedural scene, 16^3 -> 32^3 after 8 iterations (as tests/test_train.py)
FAST = ["--set", "grid.reso=[[16,16,16],[32,32,32]]", "--set", "grid.upsample_at=[8]",
        "--set", "grid.batch_size=1024", "--set", "train.eval_every=1.0",
        "--set", "train.eval_views=2", "--set", "train.final_eval=false"]
START_TIMEOUT = 120.0   # seconds for `clrf view` to build its kernels and print its URL
BROWSER_WAIT = 120.0    # seconds for any one wait on the page (PoCL on a loaded machine)


def train_tiny(out, seconds=2.0):
    assert cli(["--quiet", "train", "--out", str(out), "--max-seconds", str(seconds), *FAST]) == 0
    return out


class ViewProcess:
    """`clrf view --ckpt CK --port 0 ...` in a subprocess; .url once it has printed it."""

    def __init__(self, ckpt, *extra, exit_after=300):
        env = dict(os.environ)   # the installed clrf (tests/conftest.py)
        self.p = subprocess.Popen(
            [sys.executable, "-m", "clrf.cli", "view", "--ckpt", str(ckpt), "--port", "0",
             "--exit-after", str(exit_after), *extra],
            stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, env=env, cwd=str(Path(ckpt).parent))
        self.lines = queue.Queue()
        threading.Thread(target=self._read, daemon=True).start()
        self.output = []
        self.url = None
        deadline = time.monotonic() + START_TIMEOUT
        while self.url is None and time.monotonic() < deadline:
            try:
                line = self.lines.get(timeout=1.0)
            except queue.Empty:
                if self.p.poll() is not None:
                    break
                continue
            self.output.append(line)
            if "viewer at " in line:
                self.url = line.split("viewer at ", 1)[1].split()[0]
        if self.url is None:
            self.close()
            raise AssertionError("clrf view did not start:\n" + "".join(self.output))
        self.port = urlsplit(self.url).port

    def _read(self):
        for line in self.p.stdout:
            self.lines.put(line)

    def alive(self):
        return self.p.poll() is None

    def close(self):
        if self.p.poll() is None:
            self.p.terminate()
            try:
                self.p.wait(timeout=10)
            except subprocess.TimeoutExpired:
                self.p.kill()
                self.p.wait(timeout=10)


def browser(webgl=False, extras="view,test"):
    """Headless Chromium through Selenium; skips the test with the reason when missing.
    ``webgl``: with WebGL drawn by SwiftShader (Chromium's CPU renderer; no GPU needed) and the
    page's whole console log kept (console.log lines too, in d.get_log("browser")); ``extras``
    names what `tools/setup.sh` installs it with, for the skip message."""
    if importlib.util.find_spec("selenium") is None:
        pytest.skip(f"selenium is not installed (bash tools/setup.sh {extras})")
    if "view" in extras.split(",") and importlib.util.find_spec("websockets") is None:
        pytest.skip("websockets is not installed (clrf[view])")
    binary = next((shutil.which(n) for n in ("chromium", "chromium-browser", "google-chrome")
                   if shutil.which(n)), None)
    driver = shutil.which("chromedriver")
    if binary is None or driver is None:
        pytest.skip("no headless Chromium here: install Debian's chromium and chromium-driver "
                    f"(bash tools/setup.sh {extras})")
    from selenium import webdriver
    from selenium.webdriver.chrome.service import Service
    opts = webdriver.ChromeOptions()
    opts.binary_location = binary
    gpu = ("--use-angle=swiftshader", "--enable-unsafe-swiftshader") if webgl else \
        ("--disable-gpu",)
    for a in ("--headless=new", "--no-sandbox", *gpu, "--disable-dev-shm-usage",
              "--window-size=1100,720", "--force-device-scale-factor=1"):
        opts.add_argument(a)
    if webgl:
        opts.set_capability("goog:loggingPrefs", {"browser": "ALL"})
    return webdriver.Chrome(options=opts, service=Service(driver))


def wait(what, fn, timeout=BROWSER_WAIT):
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        v = fn()
        if v:
            return v
        time.sleep(0.2)
    raise AssertionError(f"timed out after {timeout:.0f} s waiting for {what}")


def console_errors(d):
    """The page's JavaScript errors so far (Chromium's SEVERE console entries)."""
    return [e["message"] for e in d.get_log("browser") if e.get("level") == "SEVERE"]
