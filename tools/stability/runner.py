"""Command line: run the matrix and write DIR/stability.md, stability.json (and convergence.csv)."""
from __future__ import annotations

import argparse
import csv
import json
import platform
import sys
import time
from dataclasses import asdict
from pathlib import Path

import clrf

from .cases_render import convergence_table
from .matrix import run_all
from .report import headline, markdown


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--quick", action=argparse.BooleanOptionalAction, default=False,
                    help="small sizes (the test-suite sizes)")
    ap.add_argument("--out", type=Path, required=True, help="output folder")
    ap.add_argument("--convergence", action=argparse.BooleanOptionalAction, default=False,
                    help="also write convergence.csv (error and time against step size)")
    ap.add_argument("--select", default=None, help="only cases whose name contains this")
    ap.add_argument("--device", default=None, help="device spec (see `clrf devices`)")
    a = ap.parse_args(argv)
    dev = clrf.Device(a.device)
    a.out.mkdir(parents=True, exist_ok=True)
    t = time.perf_counter()
    rows = run_all(dev, a.quick, a.select)
    meta = {"device": repr(dev), "driver": dev.caps.driver_version, "fp64": dev.caps.fp64,
            "platform": f"{platform.platform()}, Python {platform.python_version()}",
            "date": time.strftime("%Y-%m-%d %H:%M"), "quick": a.quick,
            "seconds": time.perf_counter() - t}
    meta["headline"] = headline(rows)
    (a.out / "stability.md").write_text(markdown(rows, meta))
    (a.out / "stability.json").write_text(json.dumps(
        {"meta": meta, "rows": [asdict(r) for r in rows]}, indent=1, default=str))
    if a.convergence:
        conv = convergence_table(dev, a.quick)
        with open(a.out / "convergence.csv", "w", newline="") as f:
            w = csv.DictWriter(f, fieldnames=list(conv[0]))
            w.writeheader()
            w.writerows(conv)
    print(json.dumps(meta["headline"]))
    return 0 if meta["headline"]["failed"] == 0 else 1


if __name__ == "__main__":
    sys.exit(main())
