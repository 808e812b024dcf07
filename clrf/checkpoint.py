"""Checkpoints: one .npz per run directory, written atomically (temporary file, then rename)."""
from __future__ import annotations

import json
import os
import time
from pathlib import Path

import numpy as np

from .rundir import checkpoint_write_delay

CKPT_NAME = "ckpt.npz"


class CheckpointError(ValueError):
    pass


def save(path, state: dict):
    """Write ``state`` (numpy arrays and JSON-able values) to ``path`` atomically."""
    path = Path(path)
    arrays = {}
    meta = {}
    for k, v in state.items():
        if isinstance(v, np.ndarray):
            arrays[k] = v
        else:
            meta[k] = v
    arrays["__meta__"] = np.frombuffer(json.dumps(meta).encode(), np.uint8)
    tmp = path.with_name(path.name + f".tmp{os.getpid()}")
    try:
        with open(tmp, "wb") as f:
            np.savez(f, **arrays)
            f.flush()
            os.fsync(f.fileno())
        delay = checkpoint_write_delay()
        if delay:
            time.sleep(delay)
        os.replace(tmp, path)
    finally:
        if tmp.exists():
            tmp.unlink()


def load(path) -> dict:
    path = Path(path)
    if path.is_dir():
        path = path / CKPT_NAME
    if not path.is_file():
        raise CheckpointError(f"no checkpoint at {path}: pass a run directory written by "
                              f"`clrf train --out DIR` (it holds {CKPT_NAME})")
    try:
        with np.load(path) as z:
            state = {k: z[k] for k in z.files if k != "__meta__"}
            meta = json.loads(bytes(z["__meta__"]).decode())
    except Exception as e:  # noqa: BLE001 - any decoding failure is a bad checkpoint
        raise CheckpointError(f"checkpoint {path} is unreadable ({e}); it may be from an "
                              f"interrupted copy: use a complete run directory") from None
    state.update(meta)
    return state
