"""Time the same benchmark cases on several OpenCL devices (or tunings of one), interleaved.

Each contender is a device spec, optionally with tuning fields changed:

    python tools/impl_bench.py --only 'grid/fwdbwd/128/sh2/*/camera' \\
        --contender 0:0 --contender 1:0 --contender '1:0;grid_local_size=8;prefetch=0'

Every case of every contender is set up (and checked against the reference where the case
does that) first; then ``--rounds`` rounds run each case once, contender after contender, so
the ratios between implementations are measured over the same minutes of a shared or drifting
machine. It prints, per case, each contender's median throughput and its ratio to the first
contender, and writes the records (bench.py's format, plus ``contender``) as JSON.
"""
from __future__ import annotations

import argparse
import dataclasses
import datetime as _dt
import fnmatch
import json
import sys
import time
from pathlib import Path


sys.path.append(str(Path(__file__).resolve().parents[1]))   # the checkout's clrf only where none is installed

import clrf  # noqa: E402
from bench.framework import Context  # noqa: E402
from bench.runner import (_jsonable, build_spec, device_info, host_info,  # noqa: E402
                          record_times)
from bench.specs import SPECS  # noqa: E402


def parse_contender(text: str):
    """``'1:0;grid_local_size=8;prefetch=0'`` -> ('1:0', {'grid_local_size': '8', 'prefetch':
    '0'}): the device spec, then the Tuning fields to change (converted by ``tuned``)."""
    spec, *sets = [p.strip() for p in text.split(";") if p.strip()]
    return spec, dict(s.partition("=")[::2] for s in sets)


def tuned(dev, raw: dict):
    """``dev`` with the Tuning fields in ``raw`` changed, each converted to its field's type."""
    if not raw:
        return dev
    kw = {}
    for key, val in raw.items():
        if not hasattr(dev.tuning, key):
            raise SystemExit(f"impl_bench: unknown tuning field {key!r}; known: "
                             f"{', '.join(sorted(dataclasses.asdict(dev.tuning)))}")
        typ = type(getattr(dev.tuning, key))
        kw[key] = (val not in ("0", "false", "False")) if typ is bool else typ(val)
    return dev.with_tuning(**kw)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--only", action="append", required=True,
                    help="fnmatch pattern on bench.py's case names; repeatable")
    ap.add_argument("--contender", action="append", required=True,
                    help="device spec 'P:D', optionally ';field=value' tuning changes")
    ap.add_argument("--rounds", type=int, default=9)
    ap.add_argument("--out", default=None,
                    help="JSON output (default bench-results/impl-<time>.json)")
    a = ap.parse_args(argv)

    specs = [s for s in SPECS if any(fnmatch.fnmatch(s.name, p) for p in a.only)]
    if not specs:
        raise SystemExit(f"impl_bench: no case matches {a.only}")
    contenders = []
    for text in a.contender:
        spec, raw = parse_contender(text)
        dev = tuned(clrf.Device(spec), raw)
        ctx = Context(dev, quick=False)
        for s in specs:
            rec, case = build_spec(ctx, s)
            rec["contender"] = text
            rec["device"] = device_info(dev)
            rec["tuning"] = dataclasses.asdict(dev.tuning)
            if case is None:
                print(f"{text:40s} {s.name}: not timed ({rec.get('skipped') or rec.get('failed')})")
            contenders.append((text, ctx, rec, case))
    live = [c for c in contenders if c[3] is not None]
    for *_, case in live:
        case.run()   # warm-up (and the builds)
    ts = [[] for _ in live]
    cpu = [[] for _ in live]
    for r in range(a.rounds):
        for i, (*_, case) in enumerate(live):
            t, c = time.perf_counter(), time.process_time()
            case.run()
            ts[i].append(time.perf_counter() - t)
            cpu[i].append(time.process_time() - c)
    for i, (_, ctx, rec, case) in enumerate(live):
        record_times(ctx, rec, case, ts[i], cpu[i])
        rec["time_s"]["rounds"] = ts[i]

    print(f"\n{'case':38s} {'contender':40s} {'M samples/s':>12s} {'ratio':>6s}")
    for s in specs:
        recs = [rec for _, _, rec, _ in contenders if rec["name"] == s.name and "metrics" in rec]
        if not recs:
            continue
        base = recs[0]["metrics"]["samples/s"]
        for rec in recs:
            v = rec["metrics"]["samples/s"]
            print(f"{s.name:38s} {rec['contender']:40s} {v / 1e6:12.2f} {v / base:6.2f}")
    out = Path(a.out or f"bench-results/impl-{_dt.datetime.now():%Y%m%d-%H%M%S}.json")
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(_jsonable({"host": host_info(), "rounds": a.rounds,
                                          "results": [c[2] for c in contenders]}), indent=1))
    print(f"\nwrote {out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
