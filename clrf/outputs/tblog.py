"""Optional TensorBoard event files of the training metrics (``clrf train --log tensorboard``).

Each metrics.csv row is also written as scalars ``metrics/<column>`` at step = iteration, with
tensorboardX's SummaryWriter (a small writer that needs only protobuf, not TensorFlow or
TensorBoard). The package is imported only when the option is on, so it costs nothing when
off. View with ``tensorboard --logdir RUN/tensorboard``.
"""
from __future__ import annotations

import importlib.util

SUBDIR = "tensorboard"


def available() -> bool:
    return importlib.util.find_spec("tensorboardX") is not None


class TensorBoardLog:
    """Metric sink: ``row(fields)`` with metrics.csv's fields (strings or numbers)."""

    def __init__(self, run_dir):
        from tensorboardX import SummaryWriter
        self.writer = SummaryWriter(logdir=str(run_dir) + "/" + SUBDIR, flush_secs=30)

    def row(self, fields: dict):
        step = int(fields["iteration"])
        for k, v in fields.items():
            if k == "iteration" or v in ("", None):
                continue
            try:
                self.writer.add_scalar(f"metrics/{k}", float(v), step)
            except (TypeError, ValueError):   # non-numeric columns (the model description)
                continue

    def close(self):
        self.writer.close()
