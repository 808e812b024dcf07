"""Keeping a run directory consistent across crashes (SIGKILL, power loss) and resumes.

Every file of a run is replaced atomically (clrf.runtime.atomicfile: written to a temporary
name, then renamed), so a process killed at any moment leaves the previous complete file plus,
at worst, a stale temporary file. On the next start of a run in the directory:

- ``remove_stale_temps`` deletes those temporary files;
- ``trim_metrics`` cuts metrics.csv back to the checkpoint being resumed: rows logged after
  it describe training that was lost with the process and are dropped, as is a row cut short
  by the kill, so the resumed run appends after the checkpoint's iteration with no duplicated
  or missing rows.
"""
from __future__ import annotations

import csv
import io
from pathlib import Path

from ..runtime.atomicfile import write_text

# temporary names of the run's files, in the run folder and its renders/ (every one written by
# clrf.runtime.atomicfile: NAME.tmp<pid>-<hex><ext>), then those of earlier versions of clrf
# (ckpt.npz.tmp<pid>, .config.json.tmp, eval.json.tmp, error_vs_time.png.tmp.png,
# renders/.test_000.tmp.png). pathlib's glob matches hidden names with "*".
TEMP_PATTERNS = ("*.tmp[0-9]*", "renders/*.tmp[0-9]*", "*.tmp", "*.tmp.png", "renders/*.tmp.png")


def remove_stale_temps(out: Path) -> list:
    """Delete temporary files a killed process left in run directory ``out``; returns them."""
    gone = []
    for pat in TEMP_PATTERNS:
        for p in Path(out).glob(pat):
            if p.is_file():
                p.unlink()
                gone.append(p)
    return gone


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
        write_text(path, new)
    return dropped
