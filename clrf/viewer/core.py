"""The viewer's state, independent of the transport: requests, rendering, training stats.

Each client holds at most one pending request (a newer one replaces it: stale cameras are
dropped, never queued). :meth:`ViewerCore.serve_pending` renders pending requests, oldest client
first, on the thread that calls it: a dedicated render thread under ``clrf view``, the training
thread between iterations under ``clrf train --view``. Only that one thread ever touches the
model and its OpenCL queue, so no queue is shared between threads.

A request (a dict parsed from the client's JSON)::

    {"type": "render", "seq": int, "c2w": [16 numbers, rows first, OpenGL axes],
     "fov": vertical degrees, "width": W, "height": H, "moving": bool,
     "output": "rgb" | "depth" | "acc", "background": [r, g, b] (0..1) or null,
     "near": float >= 0, "cap": largest side at rest, "move_cap": largest side while moving}

The frame is rendered at (W, H) scaled down so its larger side is at most ``cap`` (or
``move_cap`` while the camera moves), with the same field of view; the reply is a header dict
and an RGB uint8 image [h, w, 3].
"""
from __future__ import annotations

import math
import threading
import time
from dataclasses import dataclass, field
from typing import Callable, Dict, Optional

import numpy as np

from ..outputs.frames import MAX_SIDE, check_pose, render_pose, spec_from_fov, to_uint8

OUTPUTS = ("rgb", "depth", "acc")
DEFAULT_CAP = 800        # largest frame side at rest
DEFAULT_MOVE_CAP = 200   # largest frame side while the camera moves
MAX_CAP = 2048           # largest frame side the viewer renders (4 M rays; camera paths: 4096)
MAX_NEAR = 1e6


class RequestError(ValueError):
    pass


class ViewerError(Exception):
    """The viewer cannot start (a missing package, a port in use, a bad option); the CLI prints
    the message and exits 2."""


@dataclass
class Frame:
    """Camera of one frame, already validated and scaled to its render size."""
    seq: int
    pose: np.ndarray
    fov: float
    width: int
    height: int
    moving: bool
    output: str
    background: Optional[tuple]
    near: float


def _num(msg, key, lo, hi, default=None, integer=False):
    v = msg.get(key, default)
    if v is None or isinstance(v, bool) or not isinstance(v, (int, float)):
        raise RequestError(f"field '{key}': expected a number, got {v!r}")
    v = float(v)
    if not (math.isfinite(v) and lo <= v <= hi):
        raise RequestError(f"field '{key}' = {v}: must be in [{lo}, {hi}]")
    return int(round(v)) if integer else v


def parse_request(msg) -> Frame:
    """Validate a render request (see the module docstring); RequestError names the field."""
    if not isinstance(msg, dict):
        raise RequestError("a request must be a JSON object")
    c2w = msg.get("c2w")
    if not isinstance(c2w, list) or len(c2w) != 16 or not all(
            isinstance(v, (int, float)) and not isinstance(v, bool) for v in c2w):
        raise RequestError("field 'c2w': expected 16 numbers (camera-to-world, rows first)")
    try:
        pose = check_pose(c2w)
    except ValueError as e:
        raise RequestError(str(e)) from None
    fov = _num(msg, "fov", 1e-3, 179.0)
    w = _num(msg, "width", 1, MAX_SIDE, integer=True)
    h = _num(msg, "height", 1, MAX_SIDE, integer=True)
    moving = bool(msg.get("moving", False))
    cap = _num(msg, "move_cap" if moving else "cap", 8, MAX_CAP,
               DEFAULT_MOVE_CAP if moving else DEFAULT_CAP, integer=True)
    s = min(1.0, cap / max(w, h))
    w, h = max(1, round(w * s)), max(1, round(h * s))
    out = msg.get("output", "rgb")
    if out not in OUTPUTS:
        raise RequestError(f"field 'output' = {out!r}: must be one of {', '.join(OUTPUTS)}")
    bg = msg.get("background")
    if bg is not None:
        if not (isinstance(bg, list) and len(bg) == 3 and all(
                isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v)
                and 0 <= v <= 1 for v in bg)):
            raise RequestError("field 'background': expected [r, g, b] in 0..1, or null")
        bg = tuple(float(v) for v in bg)
    near = _num(msg, "near", 0.0, MAX_NEAR, 0.0)
    seq = msg.get("seq", 0)
    seq = int(seq) if isinstance(seq, int) and not isinstance(seq, bool) else 0
    return Frame(seq, pose, fov, w, h, moving, out, bg, near)


def depth_image(depth, acc, lo=None, hi=None):
    """Expected depth (depth / acc where acc >= 0.5, else background white) through matplotlib's
    turbo colour map between its 1st and 99th percentiles (or [lo, hi]); uint8 [H, W, 3]."""
    from matplotlib import colormaps
    valid = acc >= 0.5
    z = np.where(valid, depth / np.maximum(acc, 1e-12), np.nan)
    if valid.any():
        lo = float(np.percentile(z[valid], 1)) if lo is None else lo
        hi = float(np.percentile(z[valid], 99)) if hi is None else hi
    else:
        lo, hi = 0.0, 1.0
    t = np.clip((z - lo) / max(hi - lo, 1e-12), 0, 1)
    rgb = colormaps["turbo"](np.nan_to_num(t))[..., :3]
    rgb[~valid] = 1.0
    return to_uint8(rgb)


def frame_image(model, fr: Frame, meta):
    """Render one validated frame with the shared render path; uint8 [h, w, 3]. meta: the
    checkpoint's dataset metadata (its NDC frame, if the scene has one)."""
    spec = spec_from_fov(fr.fov, fr.width, fr.height, meta)
    r = render_pose(model, spec, fr.pose, fr.near, depth=fr.output == "depth")
    if fr.output == "depth":
        return depth_image(r["depth"], r["acc"])
    if fr.output == "acc":
        return to_uint8(np.repeat(r["acc"][..., None], 3, -1))
    rgb = r["rgb"]
    if fr.background is not None and getattr(model, "bg_model", None) is None:
        # rgb = sum_k w_k c_k + (1 - acc) bg: swap the constant background exactly
        diff = np.asarray(fr.background, np.float32) - np.asarray(model.background, np.float32)
        rgb = rgb + (1 - r["acc"])[..., None] * diff
    return to_uint8(rgb)


@dataclass
class Client:
    cid: int
    send: Callable            # send(header: dict, image: uint8 [h, w, 3]) -> None; may raise
    pending: Optional[Frame] = None
    since: float = 0.0        # when the pending request arrived
    dropped: int = 0          # requests replaced before they were rendered
    sent: int = 0
    closed: bool = False


@dataclass
class TrainStats:
    """What ``clrf train --view`` shows: the training log's figures and its curve."""
    iteration: int = 0
    seconds: float = 0.0
    loss: float = float("nan")
    psnr: float = float("nan")
    rays_per_s: float = 0.0
    model: str = ""
    curve: list = field(default_factory=list)   # [(seconds, train PSNR, eval PSNR or None)]


class ViewerCore:
    """Clients, their pending frames, and the model they are rendered from.

    share: the largest fraction of wall time that :meth:`serve_pending` may spend rendering
    (``clrf train --view``; 1.0 for ``clrf view``), measured since the core was made."""

    MAX_CURVE = 600   # curve points kept (every other one dropped when full)

    def __init__(self, model, meta, cameras=(), share: float = 1.0, training: bool = False):
        self.model = model
        self.meta = meta
        self.cameras = list(cameras)
        self.share = float(share)
        self.training = training
        self.paused = False
        self.up = [0.0, 0.0, 1.0]   # world up the page orbits about
        self.stats = TrainStats()
        self._clients: Dict[int, Client] = {}
        self._next = 0
        self._lock = threading.Lock()
        self._wake = threading.Condition(self._lock)
        self._t0 = time.perf_counter()
        self.render_seconds = 0.0
        self.frames_rendered = 0
        self.errors = 0

    # ---- clients (any thread) ---------------------------------------------------------
    def add_client(self, send) -> int:
        with self._lock:
            self._next += 1
            self._clients[self._next] = Client(self._next, send)
            return self._next

    def remove_client(self, cid: int):
        with self._lock:
            c = self._clients.pop(cid, None)
            if c is not None:
                c.closed = True

    def n_clients(self) -> int:
        with self._lock:
            return len(self._clients)

    def submit(self, cid: int, msg) -> Frame:
        """Validate a render request and make it client ``cid``'s pending one (replacing an
        older unrendered one). Raises RequestError for a bad request (nothing changes)."""
        fr = parse_request(msg)
        with self._wake:
            c = self._clients.get(cid)
            if c is None:
                raise RequestError("unknown client")
            if c.pending is not None:
                c.dropped += 1
            c.pending, c.since = fr, time.perf_counter()
            self._wake.notify_all()
        return fr

    def has_pending(self) -> bool:
        with self._lock:
            return any(c.pending is not None for c in self._clients.values())

    def wait(self, timeout: float) -> bool:
        """Block until a request is pending or ``timeout`` seconds pass; True if one is."""
        with self._wake:
            if not any(c.pending is not None for c in self._clients.values()):
                self._wake.wait(timeout)
            return any(c.pending is not None for c in self._clients.values())

    def wake(self):
        with self._wake:
            self._wake.notify_all()

    # ---- rendering (the model's thread only) -------------------------------------------
    def within_share(self) -> bool:
        wall = time.perf_counter() - self._t0
        return self.render_seconds <= self.share * wall

    def serve_pending(self, max_frames: int = 16, max_seconds: float = 1.0,
                      budget: bool = True) -> int:
        """Render up to ``max_frames`` pending frames (oldest request first) for at most about
        ``max_seconds`` (a frame in progress is finished); with ``budget`` stop as soon as the
        rendering time exceeds ``share`` of the wall time. Returns frames rendered."""
        done = 0
        t_end = time.perf_counter() + max_seconds
        while done < max_frames and time.perf_counter() < t_end:
            if budget and not self.within_share():
                break
            with self._lock:
                ready = [c for c in self._clients.values() if c.pending is not None]
                if not ready:
                    break
                c = min(ready, key=lambda c: c.since)
                fr, c.pending = c.pending, None
            t = time.perf_counter()
            try:
                img = frame_image(self.model, fr, self.meta)
            except Exception as e:   # noqa: BLE001 - a bad frame must not stop the server
                self.errors += 1
                self._send(c, {"type": "error", "seq": fr.seq, "message": f"render failed: {e}"},
                           None)
                continue
            finally:
                self.render_seconds += time.perf_counter() - t
            ms = (time.perf_counter() - t) * 1e3
            self.frames_rendered += 1
            done += 1
            self._send(c, {"type": "frame", "seq": fr.seq, "width": int(img.shape[1]),
                           "height": int(img.shape[0]), "moving": fr.moving, "output": fr.output,
                           "ms": round(ms, 2)}, img)
        return done

    def _send(self, c: Client, header, img):
        if c.closed:
            return
        try:
            c.send(header, img)
            c.sent += 1
        except Exception:   # noqa: BLE001 - a client gone mid-frame: forget it
            self.remove_client(c.cid)

    # ---- training (the training thread) -------------------------------------------------
    def update_stats(self, **kw):
        s = self.stats
        for k, v in kw.items():
            setattr(s, k, v)
        if "seconds" in kw:
            s.curve.append((round(s.seconds, 3), None if not math.isfinite(s.psnr) else
                            round(s.psnr, 3), kw.get("eval_psnr")))
            if len(s.curve) > self.MAX_CURVE:
                s.curve = s.curve[::2]

    def stats_message(self) -> dict:
        s = self.stats
        f = (lambda v: None if not math.isfinite(v) else v)
        return {"type": "stats", "iteration": s.iteration, "seconds": s.seconds,
                "loss": f(s.loss), "psnr": f(s.psnr), "rays_per_s": s.rays_per_s,
                "model": s.model, "paused": self.paused, "curve": s.curve,
                "render_share": self.render_seconds / max(1e-9, time.perf_counter() - self._t0)}

    def broadcast(self, msg: dict):
        with self._lock:
            clients = list(self._clients.values())
        for c in clients:
            self._send(c, msg, None)

    def set_model(self, model):
        self.model = model
