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

Access (see :class:`Access`). Browsers let any web page open a WebSocket to 127.0.0.1, so the
server decides itself who it answers: every HTTP request must name this server in its ``Host``
header (no DNS rebinding), a WebSocket handshake that carries an ``Origin`` must come from this
server's own page, and it must present the run's secret token (``/ws?token=...``, or an
``Authorization: token ...`` header), which is printed once in the page's URL. At most
``max_clients`` pages are connected at once, and each may ask for at most ``max_fps`` frames a
second.
"""
from __future__ import annotations

import hmac
import ipaddress
import json
import math
import re
import secrets
import socket
import struct
import sys
import threading
import time
from importlib import resources
from pathlib import Path
from urllib.parse import parse_qs, urlsplit

import numpy as np

from .core import DEFAULT_CAP, DEFAULT_MOVE_CAP, RequestError, ViewerCore, ViewerError

MAX_MESSAGE = 1 << 20      # largest client message, bytes (a request is < 1 KiB)
SENDER_JOIN = 10.0         # seconds a leaving client's handler waits for its sender thread
PING = 20.0                # keepalive ping interval and timeout: a dead client is dropped
MAX_OUTBOX = 8             # text messages waiting for a client's sender thread
MAX_KEYFRAMES = 1000
MAX_PATH_FRAMES = 100_000
TOKEN_BYTES = 24           # the URL's secret: 24 random bytes (192 bits), URL-safe base64
MIN_TOKEN_CHARS = 22       # a --token of the user's: at least 22 base64url characters (132 bits)
TOKEN_RE = re.compile(r"[A-Za-z0-9_-]+")
MAX_CLIENTS = 8            # pages connected at once (default of --max-clients)
MAX_CLIENTS_LIMIT = 64
MAX_FPS = 30               # render requests a second per page (default of --max-fps)
MAX_FPS_LIMIT = 240
LOOPBACK_NAMES = ("localhost", "127.0.0.1", "::1")


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


def is_wildcard(host: str) -> bool:
    """True for the any-address hosts (0.0.0.0, ::): the server listens on every interface."""
    try:
        return ipaddress.ip_address(host).is_unspecified
    except ValueError:
        return host == ""


def new_token() -> str:
    return secrets.token_urlsafe(TOKEN_BYTES)


def check_options(host: str, port, token=None, no_token=False, max_clients=MAX_CLIENTS,
                  max_fps=MAX_FPS):
    """Validate the viewer's settings (the same flags in ``clrf view`` and ``clrf train
    --view``); ViewerError names the flag and the fix."""
    if isinstance(port, bool) or not isinstance(port, int) or not 0 <= port <= 65535:
        raise ViewerError(f"--port {port}: must be a TCP port in 0..65535 (0 picks a free "
                          f"one)")
    if not host or any(c.isspace() for c in host) or "/" in host:
        raise ViewerError(f"--host {host!r}: expected an address such as 127.0.0.1, ::1, "
                          f"localhost or 0.0.0.0")
    if no_token and token is not None:
        raise ViewerError("--no-token and --token: pass one of them, not both")
    if no_token and not is_loopback(host):
        raise ViewerError(f"--no-token: only allowed on a loopback address (127.0.0.1, ::1, "
                          f"localhost); on {host} the viewer must require its token. Remove "
                          f"--no-token")
    if token is not None and (len(token) < MIN_TOKEN_CHARS or not TOKEN_RE.fullmatch(token)):
        raise ViewerError(f"--token: must be at least {MIN_TOKEN_CHARS} characters of "
                          f"A-Z, a-z, 0-9, '-' and '_' (e.g. python -c \"import secrets; "
                          f"print(secrets.token_urlsafe(24))\"); or leave it out and a new one "
                          f"is made")
    if isinstance(max_clients, bool) or not isinstance(max_clients, int) or \
            not 1 <= max_clients <= MAX_CLIENTS_LIMIT:
        raise ViewerError(f"--max-clients {max_clients}: must be in 1..{MAX_CLIENTS_LIMIT}")
    if not (isinstance(max_fps, (int, float)) and math.isfinite(max_fps)
            and 0 < max_fps <= MAX_FPS_LIMIT):
        raise ViewerError(f"--max-fps {max_fps}: must be in (0, {MAX_FPS_LIMIT}]")


def _split_host(value: str):
    """(name, port) of a Host header or an origin's netloc; port None when absent; None when
    malformed. IPv6 literals come in brackets and are returned without them, lower case."""
    m = re.fullmatch(r"\[([0-9A-Fa-f:.]+)\](?::(\d{1,5}))?|([^\[\]:/@\s]+)(?::(\d{1,5}))?",
                     value or "")
    if m is None:
        return None
    name = (m.group(1) or m.group(3)).lower().rstrip(".")
    port = m.group(2) or m.group(4)
    return name, (int(port) if port is not None else None)


class Access:
    """Who the viewer answers. ``host_ok(Host header)``: the request names this server: its
    port, and a name from ``names`` (on loopback: localhost, 127.0.0.1 and ::1, aliases of one
    another; on a given address: that address and the ``allow_hosts``; on every interface
    (0.0.0.0, ::): any IP address, localhost and the ``allow_hosts``, but no other DNS name,
    which is what a DNS-rebinding page would send). ``origin_ok``: an ``http://`` origin whose
    host passes the same test (``Origin: null``, https or a foreign page: refused).
    ``token_ok(path, headers)``: the secret, compared in constant time (None: no token)."""

    def __init__(self, host: str, port: int, token=None, allow_hosts=()):
        self.port = int(port)
        self.token = token
        self.any_ip = is_wildcard(host)
        names = {h.lower().strip("[]").rstrip(".") for h in allow_hosts}
        if is_loopback(host):
            names.update(LOOPBACK_NAMES)
        if self.any_ip:
            names.add("localhost")
        elif host:
            names.add(host.lower().strip("[]").rstrip("."))
        self.names = names

    def _name_ok(self, name: str) -> bool:
        if name in self.names:
            return True
        if self.any_ip:
            try:
                ipaddress.ip_address(name)
                return True
            except ValueError:
                return False
        return False

    def host_ok(self, value, default_port=80) -> bool:
        hp = _split_host(value)
        if hp is None:
            return False
        name, port = hp
        return (default_port if port is None else port) == self.port and self._name_ok(name)

    def origin_ok(self, origin) -> bool:
        if not origin or origin == "null":
            return False
        try:
            u = urlsplit(origin)
        except ValueError:
            return False
        if u.scheme != "http" or u.path not in ("", "/") or u.query or u.fragment:
            return False
        return self.host_ok(u.netloc)

    def token_ok(self, path: str, headers) -> bool:
        if self.token is None:
            return True
        given = parse_qs(urlsplit(path).query).get("token", [None])[0]
        if given is None:
            auth = headers.get("Authorization", "")
            if auth.lower().startswith(("token ", "bearer ")):
                given = auth.split(None, 1)[1].strip() if " " in auth else ""
        return given is not None and hmac.compare_digest(given.encode(), self.token.encode())


class _RateLimit:
    """A token bucket: at most ``rate`` events a second on average, bursts of ``rate``."""

    def __init__(self, rate: float):
        self.rate = float(rate)
        self.level = float(rate)
        self.t = time.monotonic()

    def take(self) -> bool:
        now = time.monotonic()
        self.level = min(self.rate, self.level + (now - self.t) * self.rate)
        self.t = now
        if self.level >= 1.0:
            self.level -= 1.0
            return True
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
    ``url`` is the page's address with the token, ``ws_url`` the WebSocket's.

    ``token``: "auto" (default) makes a new random one; a string uses that one; None serves
    without a token, which only a loopback ``host`` allows. ``allow_hosts``: more names the
    ``Host`` and ``Origin`` headers may carry (a DNS name of this machine with ``--host``).
    """

    def __init__(self, core: ViewerCore, host="127.0.0.1", port=8080, path_dir=None,
                 token="auto", allow_hosts=(), max_clients=MAX_CLIENTS, max_fps=MAX_FPS):
        need_websockets()
        token = new_token() if token == "auto" else token
        check_options(host, port, token, token is None, max_clients, max_fps)
        self.core = core
        self.host = host
        self.port = int(port)
        self.path_dir = Path(path_dir) if path_dir else None
        self.token = token
        self.allow_hosts = tuple(allow_hosts)
        self.max_clients = int(max_clients)
        self.max_fps = float(max_fps)
        self.access = Access(host, self.port, token, self.allow_hosts)
        self._clients = 0
        self._lock = threading.Lock()
        self._server = None
        self._thread = None

    @property
    def url(self):
        h = "127.0.0.1" if is_wildcard(self.host) else self.host
        h = h if ":" not in h else f"[{h}]"
        return f"http://{h}:{self.port}/" + (f"?token={self.token}" if self.token else "")

    @property
    def ws_url(self):
        base = self.url.replace("http://", "ws://", 1).split("?")[0]
        return base + "ws" + (f"?token={self.token}" if self.token else "")

    def start(self):
        from websockets.sync.server import serve
        try:
            self._server = serve(self._handler, self.host, self.port, max_size=MAX_MESSAGE,
                                 process_request=self._http, compression=None,
                                 ping_interval=PING, ping_timeout=PING)
        except (OSError, OverflowError) as e:
            why = getattr(e, "strerror", None) or e
            raise ViewerError(f"cannot listen on {self.host}:{self.port} ({why}); pass "
                              f"another --port (0 picks a free one) or --host") from None
        self.port = self._server.socket.getsockname()[1]
        self.access.port = self.port
        self._thread = threading.Thread(target=self._server.serve_forever, daemon=True,
                                        name="clrf-viewer-server")
        self._thread.start()
        return self

    def stop(self):
        if self._server is not None:
            self._server.shutdown()
            self._thread.join(timeout=5)
            self._server = None

    # ---- HTTP: the page, and the checks before any WebSocket -------------------------------
    def _http(self, conn, request):
        from websockets.datastructures import Headers
        from websockets.http11 import Response

        def refuse(status, reason, why):
            body = (why + "\n").encode()
            return Response(status, reason, Headers([("Content-Type", "text/plain"),
                                                     ("Content-Length", str(len(body))),
                                                     ("Connection", "close")]), body)

        host = request.headers.get("Host", "")
        if not self.access.host_ok(host):
            return refuse(403, "Forbidden", f"clrf viewer: Host {host!r} is not this server; "
                          f"open the address clrf printed")
        path = request.path.split("?")[0]
        if request.headers.get("Upgrade", "").lower() == "websocket" and path == "/ws":
            origin = request.headers.get("Origin")
            if origin is not None and not self.access.origin_ok(origin):
                return refuse(403, "Forbidden", f"clrf viewer: a page from {origin!r} may not "
                              f"connect; only this viewer's own page may")
            if not self.access.token_ok(request.path, request.headers):
                return refuse(403, "Forbidden", "clrf viewer: missing or wrong token; open the "
                              "address clrf printed (with its ?token=)")
            if self.n_clients() >= self.max_clients:
                return refuse(503, "Service Unavailable", f"clrf viewer: {self.max_clients} "
                              f"pages are connected, the most allowed (--max-clients); close one")
            return None   # go on with the WebSocket handshake
        if path in ("/", "/index.html"):
            body = page_html()
            return Response(200, "OK", Headers([("Content-Type", "text/html; charset=utf-8"),
                                                ("Content-Length", str(len(body))),
                                                ("Cache-Control", "no-store"),
                                                ("Referrer-Policy", "no-referrer"),
                                                ("X-Frame-Options", "DENY"),
                                                ("Content-Security-Policy",
                                                 "frame-ancestors 'none'")]), body)
        if path == "/favicon.ico":
            return Response(204, "No Content", Headers([("Content-Length", "0")]), b"")
        return conn.respond(404, "not found\n")

    def n_clients(self) -> int:
        with self._lock:
            return self._clients

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
        with self._lock:   # the handshake's check can race with another client's
            if self._clients >= self.max_clients:
                full = True
            else:
                full = False
                self._clients += 1
        if full:
            ws.close(1013, "too many clients")
            return
        box = _Outbox()
        sender = threading.Thread(target=self._sender, args=(ws, box), daemon=True,
                                  name="clrf-viewer-send")
        sender.start()
        cid = self.core.add_client(box.put)
        limit = _RateLimit(self.max_fps)
        try:
            box.put(self._hello(), None)
            if self.core.training:
                box.put(self.core.stats_message(), None)
            for raw in ws:   # ends when the client goes
                try:
                    self._message(cid, box, raw, limit)
                except RequestError as e:
                    box.put({"type": "error", "message": str(e)}, None)
        except Exception:   # noqa: BLE001 - a broken connection ends this client only
            pass
        finally:
            self.core.remove_client(cid)
            box.close()
            sender.join(timeout=SENDER_JOIN)
            with self._lock:
                self._clients -= 1

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

    def _message(self, cid, box, raw, limit=None):
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
            if limit is not None and not limit.take():
                raise RequestError(f"render: more than {self.max_fps:g} requests a second "
                                   f"(--max-fps); this one is dropped")
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


def add_flags(parser, training=False):
    """The viewer's address and access flags, the same for ``clrf view`` and ``clrf train
    --view`` (``training``: the help says they apply with --view)."""
    w = "--view: " if training else ""
    parser.add_argument("--port", type=int, default=8080,
                        help=f"{w}TCP port (default 8080; 0: any free one)")
    parser.add_argument("--host", default="127.0.0.1",
                        help=f"{w}address to listen on (default 127.0.0.1, this machine only; "
                             f"another address exposes the viewer to the network, with a "
                             f"warning, and always needs the token)")
    parser.add_argument("--token", default=None, metavar="SECRET",
                        help=f"{w}the secret the page's URL carries (default: a new random one "
                             f"each run, printed in the URL; at least {MIN_TOKEN_CHARS} "
                             f"characters of A-Z a-z 0-9 - _)")
    parser.add_argument("--no-token", action="store_true",
                        help=f"{w}serve without a token (loopback addresses only; any program "
                             f"of this machine's users can then connect)")
    parser.add_argument("--allow-host", action="append", default=[], metavar="NAME",
                        help=f"{w}another name the browser may reach the viewer by (this "
                             f"machine's DNS name with --host); repeatable")
    parser.add_argument("--max-clients", type=int, default=MAX_CLIENTS, metavar="N",
                        help=f"{w}pages connected at once (default {MAX_CLIENTS}, at most "
                             f"{MAX_CLIENTS_LIMIT})")
    parser.add_argument("--max-fps", type=float, default=MAX_FPS, metavar="N",
                        help=f"{w}frames a second one page may ask for (default {MAX_FPS})")


def settings(a) -> dict:
    """ViewerServer keyword arguments from add_flags' flags, validated (ViewerError names the
    flag); call it before anything is written or loaded."""
    check_options(a.host, a.port, a.token, a.no_token, a.max_clients, a.max_fps)
    for name in a.allow_host:
        if not name or any(c.isspace() or c in "/@[]" for c in name.strip("[]")):
            raise ViewerError(f"--allow-host {name!r}: expected a host name or address, e.g. "
                              f"myhost.local")
    return dict(host=a.host, port=a.port, token=None if a.no_token else (a.token or "auto"),
                allow_hosts=tuple(a.allow_host), max_clients=a.max_clients, max_fps=a.max_fps)


def warn_host(host: str):
    if not is_loopback(host):
        print(f"clrf: warning: the viewer listens on {host}, reachable from other machines; "
              f"anyone who has the printed URL's token sees your scene, and the traffic is not "
              f"encrypted. Prefer the default (127.0.0.1) with an SSH tunnel (ssh -L "
              f"8080:localhost:8080 HOST) unless this network is trusted", file=sys.stderr)


def free_port(host="127.0.0.1") -> int:
    with socket.socket(socket.AF_INET6 if ":" in host else socket.AF_INET) as s:
        s.bind((host, 0))
        return s.getsockname()[1]
