"""The runtime's small JSON caches (device probes, workloads, self-check verdicts): read one as
a dict, write one atomically. A cache is an optimisation: an unreadable file reads as empty,
and one that cannot be written is skipped (the figure is measured again next time)."""
from __future__ import annotations

import json
import os
import tempfile
from pathlib import Path


def read_dict(path: Path) -> dict:
    """The JSON object in ``path``; {} when the file is missing, unreadable or not an object."""
    try:
        d = json.loads(Path(path).read_text())
    except (OSError, ValueError):
        return {}
    return d if isinstance(d, dict) else {}


def write_atomic(path: Path, obj) -> bool:
    """Write ``obj`` as JSON to ``path`` through a temporary file and a rename, so a reader
    never sees half a file; False (and nothing left behind) when it cannot be written."""
    path = Path(path)
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        fd, tmp = tempfile.mkstemp(prefix=f".{path.stem}.", suffix=".tmp", dir=path.parent)
    except OSError:
        return False
    try:
        with os.fdopen(fd, "w") as f:
            json.dump(obj, f, indent=1, sort_keys=True)
        os.replace(tmp, path)
        return True
    except OSError:
        Path(tmp).unlink(missing_ok=True)
        return False
