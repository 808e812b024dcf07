"""The viewer's web server: one page over HTTP and a WebSocket per client (``websockets``).

Threads: the ``websockets`` server thread accepts connections and runs one handler thread per
client (it reads the client's messages and hands render requests to :class:`ViewerCore`); one
sender thread per client writes what is addressed to it, so a client that stops reading never
blocks the thread that renders (nor training); the model is touched only by the thread that
calls ``ViewerCore.serve_pending`` (see core.py).

Wire format. Client -> server: JSON text messages with a "type": "render" (core.py),
"pause" / "resume" (training only), "save_path" (keyframes -> camera_path.json). Server ->
client: JSON text ("hello" with the scene and its cameras, "stats", "error", "saved") and, per
frame, one binary message: a 4-byte little-endian header length, the JSON header ("seq",
"width", "height", "output", "moving", "ms") and the RGB bytes of the image, rows first.
"""
from __future__ import annotations

import ipaddress
import json
import math
import socket
import struct
import sys
import threading
from importlib import resources
from pathlib import Path

import numpy as np

from .core import DEFAULT_CAP, DEFAULT_MOVE_CAP, RequestError, ViewerCore, ViewerError

MAX_MESSAGE = 1 << 20      # largest client message, bytes (a request is < 1 KiB)
SENDER_JOIN = 10.0         # seconds a leaving client's handler waits for its sender thread
PING = 20.0                # keepalive ping interval and timeout: a dead client is dropped
MAX_OUTBOX = 8             # text messages waiting for a client's sender thread
MAX_KEYFRAMES = 1000
MAX_PATH_FRAMES = 100_000


def need_websockets():
    try:
        import websockets.sync.server  # noqa: F401
    except ImportError:
        raise ViewerError("the viewer needs the 'websockets' package: pip install websockets "
                       "(or clrf[view], or `bash tools/setup.sh view`)") from None


def is_loopback(host: str) -> bool:
    if host == "localhost":
        return True
    try:
        return ipaddress.ip_address(host).is_loopback
    except ValueError:
        return False


def page_html() -> bytes:
    return resources.files("clrf.viewer").joinpath("page.html").read_bytes()


def encode_frame(header: dict, img: np.ndarray) -> bytes:
    h = json.dumps(header).encode()
    return struct.pack("<I", len(h)) + h + np.ascontiguousarray(img, np.uint8).tobytes()


def decode_frame(data: bytes):
    """(header dict, uint8 [h, w, 3]) of a binary frame message (tests, tools)."""
    n = struct.unpack("<I", data[:4])[0]
    hdr = json.loads(data[4:4 + n])
    img = np.frombuffer(data[4 + n:], np.uint8).reshape(hdr["height"], hdr["width"], 3)
    return hdr, img


class _Outbox:
    """What waits to be sent to one client: the newest frame (a newer one replaces it) and up
    to MAX_OUTBOX text messages (the oldest dropped beyond that)."""

    def __init__(self):
        self.cv = threading.Condition()
        self.frame = None
        self.texts = []
        self.closed = False

    def put(self, header, img):
        with self.cv:
            if self.closed:
                raise ConnectionError("client closed")
            if img is not None:
                self.frame = encode_frame(header, img)
            else:
                self.texts = (self.texts + [json.dumps(header)])[-MAX_OUTBOX:]
            self.cv.notify()

    def take(self, timeout):
        with self.cv:
            if self.frame is None and not self.texts and not self.closed:
                self.cv.wait(timeout)
            if self.texts:
                return self.texts.pop(0)
            f, self.frame = self.frame, None
            return f

    def close(self):
        with self.cv:
            self.closed = True
            self.cv.notify()


class ViewerServer:
    """Serve ``core`` on host:port (port 0: any free port). ``start()`` returns at once;
    ``url`` is the page's address."""

    def __init__(self, core: ViewerCore, host="127.0.0.1", port=8080, path_dir=None):
        need_websockets()
        self.core = core
        self.host = host
        self.port = int(port)
        self.path_dir = Path(path_dir) if path_dir else None
        self._server = None
        self._thread = None

    @property
    def url(self):
        h = self.host if ":" not in self.host else f"[{self.host}]"
        return f"http://{h}:{self.port}/"

    def start(self):
        from websockets.sync.server import serve
        try:
            self._server = serve(self._handler, self.host, self.port, max_size=MAX_MESSAGE,
                                 process_request=self._http, compression=None,
                                 ping_interval=PING, ping_timeout=PING)
        except OSError as e:
            raise ViewerError(f"cannot listen on {self.host}:{self.port} ({e.strerror or e}); pass "
                           f"another --port (0 picks a free one)") from None
        self.port = self._server.socket.getsockname()[1]
        self._thread = threading.Thread(target=self._server.serve_forever, daemon=True,
                                        name="clrf-viewer-server")
        self._thread.start()
        return self

    def stop(self):
        if self._server is not None:
            self._server.shutdown()
            self._thread.join(timeout=5)
            self._server = None

    # ---- HTTP: the page -----------------------------------------------------------------
    def _http(self, conn, request):
        from websockets.datastructures import Headers
        from websockets.http11 import Response
        if request.headers.get("Upgrade", "").lower() == "websocket" and request.path == "/ws":
            return None   # go on with the WebSocket handshake
        if request.path.split("?")[0] in ("/", "/index.html"):
            body = page_html()
            return Response(200, "OK", Headers([("Content-Type", "text/html; charset=utf-8"),
                                                ("Content-Length", str(len(body))),
                                                ("Cache-Control", "no-store")]), body)
        if request.path == "/favicon.ico":
            return Response(204, "No Content", Headers([("Content-Length", "0")]), b"")
        return conn.respond(404, "not found\n")

    # ---- WebSocket: one thread per client --------------------------------------------------
    def _hello(self):
        m = self.core.meta
        return {"type": "hello", "training": self.core.training, "paused": self.core.paused,
                "scene": {"name": m.get("name", ""), "bbox": np.asarray(m["bbox"]).tolist(),
                          "ndc": bool(m.get("ndc", False)), "H": int(m["H"]), "W": int(m["W"]),
                          "background": list(map(float, getattr(self.core.model, "background",
                                                                (1, 1, 1))))},
                "cameras": self.core.cameras, "up": list(self.core.up), "cap": DEFAULT_CAP,
                "move_cap": DEFAULT_MOVE_CAP,
                "can_save_path": self.path_dir is not None,
                # an MSI background is not one colour: the background control cannot swap it
                "background_control": getattr(self.core.model, "bg_model", None) is None}

    def _handler(self, ws):
        box = _Outbox()
        sender = threading.Thread(target=self._sender, args=(ws, box), daemon=True,
                                  name="clrf-viewer-send")
        sender.start()
        cid = self.core.add_client(box.put)
        try:
            box.put(self._hello(), None)
            if self.core.training:
                box.put(self.core.stats_message(), None)
            for raw in ws:   # ends when the client goes
                try:
                    self._message(cid, box, raw)
                except RequestError as e:
                    box.put({"type": "error", "message": str(e)}, None)
        except Exception:   # noqa: BLE001 - a broken connection ends this client only
            pass
        finally:
            self.core.remove_client(cid)
            box.close()
            sender.join(timeout=SENDER_JOIN)

    @staticmethod
    def _sender(ws, box):
        try:
            while True:
                data = box.take(0.5)
                if data is None:
                    if box.closed:
                        return
                    continue
                ws.send(data)
        except Exception:   # noqa: BLE001 - client gone or too slow: close it
            box.close()
            try:
                ws.close()
            except Exception:   # noqa: BLE001
                pass

    def _message(self, cid, box, raw):
        if isinstance(raw, bytes):
            raise RequestError("messages must be JSON text")
        try:
            msg = json.loads(raw)
        except (json.JSONDecodeError, RecursionError):
            raise RequestError("not valid JSON") from None
        if not isinstance(msg, dict):
            raise RequestError("a message must be a JSON object with a 'type'")
        kind = msg.get("type")
        if kind == "render":
            self.core.submit(cid, msg)
        elif kind in ("pause", "resume"):
            if not self.core.training:
                raise RequestError("pause/resume: nothing is training (this is `clrf view`)")
            self.core.paused = kind == "pause"
            self.core.wake()
            self.core.broadcast(self.core.stats_message())
        elif kind == "save_path":
            box.put({"type": "saved", "file": str(self._save_path(msg))}, None)
        else:
            raise RequestError(f"field 'type' = {kind!r}: expected render, pause, resume or "
                               f"save_path")

    def _save_path(self, msg):
        from ..outputs import camera_path as cp
        from ..outputs.frames import check_pose
        if self.path_dir is None:
            raise RequestError("save_path: this viewer has no folder to save into")
        keys = msg.get("keyframes")
        if not isinstance(keys, list) or not 1 <= len(keys) <= MAX_KEYFRAMES:
            raise RequestError(f"field 'keyframes': expected a list of 1..{MAX_KEYFRAMES} "
                               f"cameras")
        kf = []
        for i, k in enumerate(keys):
            if not isinstance(k, dict):
                raise RequestError(f"keyframes[{i}]: expected an object with c2w and fov")
            try:
                pose = check_pose(k.get("c2w"))
                fov = float(k.get("fov"))
            except (ValueError, TypeError) as e:
                raise RequestError(f"keyframes[{i}]: {e}") from None
            if not (math.isfinite(fov) and 0 < fov < 180):
                raise RequestError(f"keyframes[{i}]: field 'fov' = {fov}: must be in (0, 180)")
            kf.append((pose, fov))
        w, h = int(msg.get("width", 0) or 0), int(msg.get("height", 0) or 0)
        fps, secs = float(msg.get("fps", 24) or 24), float(msg.get("seconds", 4) or 4)
        n = int(round(fps * secs))
        if not (1 <= w <= 4096 and 1 <= h <= 4096 and 1 <= n <= MAX_PATH_FRAMES):
            raise RequestError("save_path: width, height in 1..4096 and fps * seconds in "
                               f"1..{MAX_PATH_FRAMES} needed")
        poses, fovs = cp.interpolate(kf, n)
        path = cp.CameraPath(poses, fovs, w, h, fps, kf)
        self.path_dir.mkdir(parents=True, exist_ok=True)
        f = self.path_dir / "camera_path.json"
        cp.save(f, path)
        return f


def warn_host(host: str):
    if not is_loopback(host):
        print(f"clrf: warning: the viewer listens on {host}, reachable from other machines; it "
              f"has no password and shows your scene to anyone who can connect. Use the default "
              f"(127.0.0.1) with an SSH tunnel (ssh -L 8080:localhost:8080 HOST) unless this "
              f"network is trusted", file=sys.stderr)


def free_port(host="127.0.0.1") -> int:
    with socket.socket(socket.AF_INET6 if ":" in host else socket.AF_INET) as s:
        s.bind((host, 0))
        return s.getsockname()[1]
