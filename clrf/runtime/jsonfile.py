"""The runtime's small JSON caches (device probes, workloads, self-check verdicts): read one as
a dict (read_dict), write one atomically (write_dict). A cache is an optimisation: an unreadable
file reads as empty, and one that cannot be written is skipped (the figure is measured again
next time)."""
from __future__ import annotations

import json
from pathlib import Path

from .atomicfile import write_text


def read_dict(path: Path) -> dict:
    """The JSON object in ``path``; {} when the file is missing, unreadable or not an object."""
    try:
        d = json.loads(Path(path).read_text())
    except (OSError, ValueError):
        return {}
    return d if isinstance(d, dict) else {}


def write_dict(path: Path, obj) -> bool:
    """Write ``obj`` as JSON to ``path`` atomically (atomicfile.py; not fsynced: a cache), so a
    reader never sees half a file; False (and nothing left behind) when it cannot be written."""
    path = Path(path)
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        write_text(path, json.dumps(obj, indent=1, sort_keys=True), sync=False)
    except OSError:
        return False
    return True
