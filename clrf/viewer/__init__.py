"""Interactive web viewer: ``clrf view --ckpt DIR`` and ``clrf train --view``.

core.py holds the requests and renders them with the shared render path (clrf/outputs/frames.py);
server.py is the page and the WebSocket; page.html the browser side. See docs/viewer.md.
"""
from __future__ import annotations

import math
import sys
import time
from pathlib import Path

import numpy as np


def dataset_cameras(ds, limit: int = 400) -> list:
    """The dataset's train and test cameras for the page: name, split, c2w (16, rows first),
    vertical fov (degrees, from fy and H), aspect W / H. At most ``limit`` (evenly thinned)."""
    H, W = ds.hw
    fov = math.degrees(2 * math.atan(0.5 * H / float(ds.intrinsics[1])))
    out = []
    for split in ("train", "test"):
        idx = np.asarray(ds.split.get(split, []))
        if idx.size > limit // 2:
            idx = idx[np.linspace(0, idx.size - 1, limit // 2).astype(int)]
        for i in idx:
            out.append({"name": f"{split} {int(i)}", "split": split, "fov": fov,
                        "aspect": W / H,
                        "c2w": [float(v) for v in np.asarray(ds.poses[i]).reshape(-1)]})
    return out


def up_vector(cameras) -> list:
    """World up for orbiting: the cameras' mean y axis (z when there are none)."""
    if not cameras:
        return [0.0, 0.0, 1.0]
    y = np.sum([np.asarray(c["c2w"]).reshape(4, 4)[:3, 1] for c in cameras], 0)
    n = np.linalg.norm(y)
    return (y / n).tolist() if n > 1e-9 else [0.0, 0.0, 1.0]


def run_view(a):
    """``clrf view``: serve a checkpoint until Ctrl-C (or --exit-after seconds)."""
    from ..runtime.device import Device
    from ..training.models import load_model
    from .core import ViewerCore, ViewerError
    from .server import ViewerServer, need_websockets, settings, warn_host

    need_websockets()
    access = settings(a)   # the flags, checked before the checkpoint is loaded
    if not (math.isfinite(a.exit_after) and a.exit_after >= 0):
        raise ViewerError(f"--exit-after {a.exit_after}: must be a number of seconds >= 0 "
                          f"(0: run until Ctrl-C)")
    dev = Device(a.device)
    model, state, cfg = load_model(dev, a.ckpt)
    meta = state["dataset"]
    cams = []
    if not a.no_cameras:
        from ..training.models import checkpoint_dataset
        try:
            cams = dataset_cameras(checkpoint_dataset(state, a.data))
        except Exception as e:   # noqa: BLE001 - the viewer works without the dataset
            print(f"clrf: note: no dataset cameras in the viewer ({e})", file=sys.stderr)
    ck = Path(a.ckpt)
    core = ViewerCore(model, meta, cams)
    core.up = up_vector(cams)
    srv = ViewerServer(core, path_dir=ck if ck.is_dir() else ck.parent, **access).start()
    warn_host(a.host)
    print(f"clrf: viewer at {srv.url} (Ctrl-C to stop)", flush=True)
    try:
        render_loop(core, a.exit_after or math.inf)
    except KeyboardInterrupt:
        pass
    finally:
        srv.stop()
    return 0


def render_loop(core, seconds=math.inf, stop=None):
    """Render the core's pending frames on this thread (the only one that touches the model)
    for ``seconds`` or until the threading.Event ``stop`` is set."""
    t_end = time.monotonic() + seconds
    while time.monotonic() < t_end and not (stop is not None and stop.is_set()):
        if core.wait(min(0.25, max(0.0, t_end - time.monotonic()))):
            core.serve_pending(max_frames=8, max_seconds=2.0, budget=False)
