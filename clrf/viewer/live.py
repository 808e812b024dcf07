"""``clrf train --view``: the viewer page while training runs.

The training thread calls :meth:`LiveViewer.step` after every iteration (and
:meth:`LiveViewer.evaluated` after every evaluation). ``step`` renders the pending frames there,
between iterations, on the training thread itself: OpenCL command queues are not thread-safe
in every implementation, and a second queue on the same context would still compete for the
same device while the training kernels run, so rendering in the gaps keeps the device's work
in one ordered stream and makes the viewer's cost measurable. Frames are rendered only while
the time spent on them stays within ``share`` of the wall time since the viewer started
(default 20 %), so training slows by at most about that share (one frame may overrun the
budget; the next ones wait until the average is back under it). The server's own threads only
read and write sockets. Pausing from the page holds the training loop in :meth:`step` (frames
are then rendered without the budget); closing the page changes nothing for training.
"""
from __future__ import annotations

import math
import sys
import time

from . import dataset_cameras, up_vector
from .core import ViewerCore, ViewerError
from .server import ViewerServer, need_websockets, warn_host

STATS_EVERY = 0.5      # seconds between stats messages to the pages
PAUSE_POLL = 0.2       # seconds between checks while paused
MAX_PAUSE_FRAMES = 4   # frames rendered per poll while paused


class LiveViewer:
    def __init__(self, trainer, share=0.2, host="127.0.0.1", port=8080, **access):
        """``access``: ViewerServer's token, allow_hosts, max_clients, max_fps."""
        need_websockets()
        if not 0 < share <= 1:
            raise ViewerError(f"--view-share {share}: must be in (0, 1], the largest fraction of "
                           f"wall time the viewer may render for")
        from ..training.trainer import dataset_meta
        cams = dataset_cameras(trainer.ds)
        self.core = ViewerCore(trainer.model, dataset_meta(trainer.ds), cams, share=share,
                               training=True)
        self.core.up = up_vector(cams)
        self.server = ViewerServer(self.core, host, port, trainer.out, **access).start()
        warn_host(host)
        self._last_stats = 0.0
        print(f"clrf: viewer at {self.server.url} (closing the page does not stop training)",
              file=sys.stderr, flush=True)

    @property
    def url(self):
        return self.server.url

    def step(self, trainer, loss):
        """After an iteration: new stats, frames within the time share, and the pause. A
        failure in the viewer is reported once and turns the viewer off; training goes on."""
        if self.failed:
            return
        try:
            self._step(trainer, loss)
        except Exception as e:   # noqa: BLE001 - the viewer must never stop training
            self.failed = True
            print(f"clrf: viewer stopped after an error ({type(e).__name__}: {e}); training "
                  f"goes on", file=sys.stderr)
            self.close()

    failed = False

    def _step(self, trainer, loss):
        from ..training.metrics import psnr_from_mse
        core = self.core
        core.model = trainer.model
        if math.isfinite(float(loss)):   # NaN: no loss read yet (a model that defers it)
            core.update_stats(iteration=trainer.iteration, seconds=trainer.seconds,
                              loss=float(loss),
                              psnr=psnr_from_mse(float(loss)) if loss > 0 else math.inf,
                              rays_per_s=float(trainer._rate), model=trainer.model.describe())
        self._maybe_stats()
        if core.n_clients():
            core.serve_pending(max_frames=4, max_seconds=1.0, budget=True)
        if core.paused:
            self._hold()

    def evaluated(self, trainer, ev):
        s = self.core.stats
        if s.curve:
            s.curve[-1] = (s.curve[-1][0], s.curve[-1][1], round(float(ev["psnr"]), 3))
        self._maybe_stats(force=True)

    def _maybe_stats(self, force=False):
        now = time.monotonic()
        if force or now - self._last_stats >= STATS_EVERY:
            self._last_stats = now
            if self.core.n_clients():
                self.core.broadcast(self.core.stats_message())

    def _hold(self):
        """Paused: render what the pages ask for (no budget: training waits anyway) until a
        page resumes. Ctrl-C still interrupts (KeyboardInterrupt propagates)."""
        core = self.core
        self._maybe_stats(force=True)
        while core.paused:
            if core.n_clients() == 0:   # the last page closed: never leave training paused
                core.paused = False
                print("clrf: viewer: every page closed while paused; training resumes",
                      file=sys.stderr)
                break
            if core.wait(PAUSE_POLL):
                core.serve_pending(max_frames=MAX_PAUSE_FRAMES, max_seconds=PAUSE_POLL,
                                   budget=False)
            self._maybe_stats()
        # the share is of training time: start its accounting afresh after a pause
        core.render_seconds = 0.0
        core._t0 = time.perf_counter()
        self._maybe_stats(force=True)

    def close(self):
        self.server.stop()
