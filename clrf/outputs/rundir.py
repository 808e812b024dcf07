"""Keeping a run directory consistent across crashes (SIGKILL, power loss) and resumes.

Every file of a run is replaced atomically (written to a temporary name, then renamed), so a
process killed at any moment leaves the previous complete file plus, at worst, a stale
temporary file. On the next start of a run in the directory:

- ``remove_stale_temps`` deletes those temporary files;
- ``trim_metrics`` cuts metrics.csv back to the checkpoint being resumed: rows logged after
  it describe training that was lost with the process and are dropped, as is a row cut short
  by the kill, so the resumed run appends after the checkpoint's iteration with no duplicated
  or missing rows.
"""
from __future__ import annotations

import csv
import io
import os
from pathlib import Path

# temporary names of the run's files (checkpoint.save, plot_error_vs_time, the JSON outputs;
# the per-rank brick checkpoints of a distributed run)
TEMP_PATTERNS = ("ckpt.npz.tmp*", "ckpt.it*.npz.tmp*", "*.tmp", ".*.tmp", "*.tmp.png")


def remove_stale_temps(out: Path) -> list:
    """Delete temporary files a killed process left in run directory ``out``; returns them."""
    gone = []
    for pat in TEMP_PATTERNS:
        for p in Path(out).glob(pat):
            if p.is_file():
                p.unlink()
                gone.append(p)
    return gone


def write_atomic(path: Path, text: str) -> None:
    """Replace ``path`` by ``text`` with a temporary file and a rename (never half-written)."""
    path = Path(path)
    tmp = path.with_name(f".{path.name}.tmp")
    with open(tmp, "w", newline="") as f:
        f.write(text)
        f.flush()
        os.fsync(f.fileno())
    os.replace(tmp, path)


def trim_metrics(path: Path, fields: list, iteration: int) -> int:
    """Keep the header and the complete rows of metrics.csv ``path`` whose iteration is at most
    ``iteration`` (the resumed checkpoint's); returns the number of rows dropped."""
    path = Path(path)
    text = ""
    if path.is_file():
        with open(path, newline="") as f:             # keep csv's \r\n line ends as written
            text = f.read()
    lines = text.splitlines(keepends=True)
    kept, dropped = [], 0
    for line in lines[1:]:
        row = next(csv.reader([line]), [])
        ok = line.endswith("\n") and len(row) == len(fields)
        if ok:
            try:
                ok = int(row[0]) <= iteration
            except ValueError:
                ok = False
        if ok:
            kept.append(line)
        else:
            dropped += 1
    header = io.StringIO()
    csv.writer(header).writerow(fields)
    new = header.getvalue() + "".join(kept)
    if new != text or not path.is_file():
        write_atomic(path, new)
    return dropped
