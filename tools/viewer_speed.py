"""Viewer speed without a browser: frames/s while the camera moves, and the time to the full
frame once it rests, measured through the viewer's own WebSocket (as a page would see it).

    python tools/viewer_speed.py --ckpt runs/lego_400 [--json out.json]

It serves the checkpoint in this process (ViewerServer on a free 127.0.0.1 port, the render
loop of `clrf view` on its own thread) and connects one client that:

- moving: orbits the scene, one request in flight at a time (the next is sent when the previous
  frame arrives, as the page does), ``--move-size`` square frames with the moving flag; reports
  frames per second over ``--frames`` frames (after ``--warmup`` frames that build kernels);
- at rest: for ``--repeats`` cameras, sends one moving frame and then the resting request for a
  ``--rest-size`` square frame, and reports the time from sending that request to receiving
  the full frame (median and worst).

Prints one JSON object (device, checkpoint, model, sizes, figures); --json also writes it.
"""
from __future__ import annotations

import argparse
import json
import math
import sys
import threading
import time
from pathlib import Path

import numpy as np

sys.path.append(str(Path(__file__).resolve().parent.parent))   # the checkout's clrf only where none is installed

WAIT = 300.0   # seconds any one frame may take before the run is abandoned


def cameras(meta, n):
    """n cameras orbiting the scene box (NDC scenes: small turns of the reference camera)."""
    from clrf.data.cameras import orbit_poses
    if meta.get("ndc"):
        out = []
        for a in np.linspace(-0.1, 0.1, n):
            m = np.eye(4)
            m[:3, :3] = [[math.cos(a), 0, math.sin(a)], [0, 1, 0], [-math.sin(a), 0, math.cos(a)]]
            out.append(m)
        return np.stack(out)
    b = np.asarray(meta["bbox"], np.float64)
    return orbit_poses(n, radius=float(np.linalg.norm(b[1] - b[0])) * 1.15, elevation_deg=30,
                       center=b.mean(0))


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--ckpt", required=True)
    p.add_argument("--device", default=None)
    p.add_argument("--move-size", type=int, default=200)
    p.add_argument("--rest-size", type=int, default=400)
    p.add_argument("--frames", type=int, default=40)
    p.add_argument("--warmup", type=int, default=3)
    p.add_argument("--repeats", type=int, default=5)
    p.add_argument("--json", default=None)
    a = p.parse_args(argv)

    from websockets.sync.client import connect

    from clrf.runtime.device import Device
    from clrf.training.models import load_model
    from clrf.viewer import render_loop
    from clrf.viewer.core import ViewerCore
    from clrf.viewer.server import ViewerServer, decode_frame

    dev = Device(a.device)
    model, state, _ = load_model(dev, a.ckpt)
    meta = state["dataset"]
    fov = math.degrees(2 * math.atan(0.5 * int(meta["H"]) / float(meta["intrinsics"][1])))
    core = ViewerCore(model, meta)
    srv = ViewerServer(core, "127.0.0.1", 0).start()
    stop = threading.Event()
    th = threading.Thread(target=render_loop, args=(core, math.inf, stop), daemon=True)
    th.start()
    poses = cameras(meta, a.warmup + a.frames + a.repeats)
    seq = [0]

    def frame(ws, pose, size, moving):
        seq[0] += 1
        ws.send(json.dumps({"type": "render", "seq": seq[0], "c2w": pose.reshape(-1).tolist(),
                            "fov": fov, "width": size, "height": size, "moving": moving,
                            "cap": size, "move_cap": size}))
        deadline = time.monotonic() + WAIT
        while time.monotonic() < deadline:
            m = ws.recv(timeout=deadline - time.monotonic())
            if isinstance(m, bytes):
                hdr, img = decode_frame(m)
                if hdr["seq"] == seq[0]:
                    assert img.shape == (size, size, 3)
                    return hdr
            elif json.loads(m).get("type") == "error":
                raise RuntimeError(json.loads(m)["message"])
        raise TimeoutError(f"no frame within {WAIT:.0f} s")

    try:
        with connect(srv.ws_url, open_timeout=60, max_size=None) as ws:
            for i in range(a.warmup):            # kernels built here, not timed
                frame(ws, poses[i], a.move_size, True)
                frame(ws, poses[i], a.rest_size, False)
            t = time.perf_counter()
            for i in range(a.warmup, a.warmup + a.frames):
                frame(ws, poses[i], a.move_size, True)
            moving_fps = a.frames / (time.perf_counter() - t)
            rest = []
            for i in range(a.warmup + a.frames, a.warmup + a.frames + a.repeats):
                frame(ws, poses[i], a.move_size, True)
                t = time.perf_counter()
                frame(ws, poses[i], a.rest_size, False)
                rest.append(time.perf_counter() - t)
    finally:
        stop.set()
        th.join(timeout=WAIT)
        srv.stop()
    res = {"device": repr(dev), "ckpt": str(a.ckpt), "model": model.describe(),
           "moving_size": a.move_size, "moving_frames": a.frames,
           "moving_fps": round(moving_fps, 2), "rest_size": a.rest_size,
           "rest_repeats": a.repeats, "time_to_full_s_median": round(float(np.median(rest)), 4),
           "time_to_full_s_max": round(float(np.max(rest)), 4)}
    print(json.dumps(res, indent=1))
    if a.json:
        Path(a.json).write_text(json.dumps(res, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
