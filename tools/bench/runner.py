"""Run specs until their timing is stable, compute metrics and ratios to the peaks, write JSON;
the command line."""
from __future__ import annotations

import argparse
import datetime as _dt
import fnmatch
import importlib
import json
import os
import platform
import socket
import sys
import time
from pathlib import Path

import numpy as np
import pyopencl as cl
import clrf

from .framework import Case, Context, FACTORIES, ROOT, Skip, Spec
from .specs import SPECS, _peak_specs, external_specs


# ---- runner ---------------------------------------------------------------------------------
def _requires_ok(spec):
    for modname, attr in spec.requires:
        try:
            mod = importlib.import_module(modname)
        except ModuleNotFoundError as e:
            if e.name and modname.startswith(e.name):
                return f"{modname} does not exist (not landed on this branch)"
            return f"{modname} not importable: {e}"
        except ImportError as e:
            return f"{modname} not importable: {e}"
        if not hasattr(mod, attr):
            return f"{modname}.{attr} does not exist (not landed on this branch)"
    return None


def time_case(case: Case, min_repeats, max_repeats, max_seconds, tol, warmup=1):
    for _ in range(warmup):
        case.run()
    ts, cpu = [], []
    t_start = time.perf_counter()
    while True:
        t = time.perf_counter()
        c = time.process_time()
        case.run()
        ts.append(time.perf_counter() - t)
        cpu.append(time.process_time() - c)
        n = len(ts)
        if n >= max_repeats:
            break
        if n >= min_repeats:
            q1, med, q3 = np.percentile(ts, [25, 50, 75])
            if (q3 - q1) / med < tol or time.perf_counter() - t_start > max_seconds:
                break
    return ts, cpu


def metrics(work, median_s):
    m = {}
    for key, unit in (("samples", "samples/s"), ("rays", "rays/s"), ("segments", "segments/s"),
                      ("cells", "cells/s"), ("rows", "rows/s")):
        if key in work:
            m[unit] = work[key] / median_s
    if "bytes" in work:
        m["GB/s"] = work["bytes"] / median_s / 1e9
    if "flop" in work:
        m["GFLOP/s"] = work["flop"] / median_s / 1e9
    return m


def device_info(dev):
    c = dev.caps
    return {"name": c.name, "platform": c.platform, "platform_version": c.platform_version,
            "driver_version": c.driver_version, "type": c.type, "compute_units": c.compute_units,
            "global_mem_gb": c.global_mem_size / 1e9, "max_alloc_gb": c.max_alloc_size / 1e9,
            "repr": repr(dev)}


def host_info():
    try:
        load = os.getloadavg()
    except OSError:
        load = None
    cpu = platform.processor()
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                cpu = line.split(":", 1)[1].strip()
                break
    except OSError:
        pass
    return {"host": socket.gethostname(), "cpu": cpu, "cpus": os.cpu_count(), "loadavg": load,
            "python": platform.python_version(), "numpy": np.__version__,
            "pyopencl": cl.VERSION_TEXT}


def build_spec(ctx, spec):
    """(record so far, Case or None): the case set up and checked, or why it is not timed."""
    params = dict(spec.params)
    if ctx.quick:
        params.update(spec.quick)
    rec = {"name": spec.name, "kind": spec.kind, "params": params, "metric": spec.metric}
    why = _requires_ok(spec)
    if why:
        rec["skipped"] = why
        return rec, None
    try:
        t0 = time.perf_counter()
        case = FACTORIES[spec.kind](ctx, params)
        rec["setup_s"] = time.perf_counter() - t0
    except Skip as e:
        rec["skipped"] = str(e)
        return rec, None
    rec.update(work=case.work, info=case.info, check=case.check)
    if case.check is not None and not case.check.get("ok", True):
        rec["failed"] = "check against the reference failed"
        return rec, None
    return rec, case


def record_times(ctx, rec, case, ts, cpu):
    """Add the timing figures of repetitions ts (wall s) and cpu (process CPU s) to rec."""
    med = float(np.median(ts))
    rec["time_s"] = {"median": med, "min": float(min(ts)), "max": float(max(ts)),
                     "repeats": len(ts)}
    # CPU time of this process (all threads) per repetition: on a shared host, work / (CPU time
    # / compute units) estimates what the case would reach with the cores to itself.
    cus = ctx.dev.caps.compute_units if ctx.dev.is_cpu else 0
    rec["cpu_s"] = {"median": float(np.median(cpu))}
    if cus:
        rec["metrics_cpu_normalised"] = metrics(case.work, float(np.median(cpu)) / cus)
    rec["metrics"] = metrics(case.work, med)
    rec["metrics_min_max"] = {k: [metrics(case.work, max(ts))[k], metrics(case.work, min(ts))[k]]
                              for k in rec["metrics"]}
    return rec


def run_spec(ctx, spec, args):
    rec, case = build_spec(ctx, spec)
    if case is None:
        return rec
    if ctx.quick:
        case.run()
        return rec
    ts, cpu = time_case(case, spec.min_repeats or args.min_repeats, args.max_repeats,
                        args.max_seconds, args.tol)
    return record_times(ctx, rec, case, ts, cpu)


def run_interleaved(ctx, specs, rounds):
    """Every spec set up first, then `rounds` rounds that run each case once, in order: a ratio
    of two cases (clrf against a peer) is then measured over the same minutes of a shared or
    drifting machine. Records as run_spec's, plus the round-by-round times."""
    built = [build_spec(ctx, s) for s in specs]
    live = [(rec, case) for rec, case in built if case is not None]
    for _, case in live:
        case.run()   # warm-up
    ts = [[] for _ in live]
    cpu = [[] for _ in live]
    for _ in range(rounds):
        for i, (_, case) in enumerate(live):
            t = time.perf_counter()
            c = time.process_time()
            case.run()
            ts[i].append(time.perf_counter() - t)
            cpu[i].append(time.process_time() - c)
    for i, (rec, case) in enumerate(live):
        record_times(ctx, rec, case, ts[i], cpu[i])
        rec["time_s"]["rounds"] = ts[i]
        rec["time_s"]["interleaved"] = True
    return [rec for rec, _ in built]


def summarise_peaks(results):
    """Median of the start and end measurements of each peak."""
    peaks = {}
    for r in results:
        if r["name"].startswith("peak/") and "metrics" in r:
            key = r["name"].split("/", 1)[1].split("@")[0]
            unit = r["metric"]
            peaks.setdefault(key, []).append(r["metrics"][unit])
    return {k: float(np.mean(v)) for k, v in peaks.items()}


def add_ratios(results, peaks):
    bw = peaks.get("triad")
    fl = peaks.get("fma")
    for r in results:
        m = r.get("metrics")
        if not m:
            continue
        ratios = {}
        if bw and "GB/s" in m:
            ratios["GB/s / triad"] = m["GB/s"] / bw
        if fl and "GFLOP/s" in m:
            ratios["GFLOP/s / fma"] = m["GFLOP/s"] / fl
        r["ratios"] = ratios


def main(argv=None):
    ap = argparse.ArgumentParser(description="clrf benchmarks (see the module docstring)")
    ap.add_argument("--only", action="append", default=[],
                    help="fnmatch pattern on benchmark names; repeatable (peaks always run)")
    ap.add_argument("--quick", action="store_true", help="smoke mode: tiny sizes, no timing")
    ap.add_argument("--list", action="store_true", help="print the benchmarks and exit")
    ap.add_argument("--out", help="JSON output path (default bench-results/bench-<time>.json)")
    ap.add_argument("--device", help="CLRF_DEVICE-style spec ('cpu', 'gpu', 'P:D', 'pocl', 'intel', ...)")
    ap.add_argument("--min-repeats", type=int, default=5)
    ap.add_argument("--max-repeats", type=int, default=25)
    ap.add_argument("--max-seconds", type=float, default=20.0,
                    help="stop repeating a case after this long even if not stable")
    ap.add_argument("--tol", type=float, default=0.05,
                    help="stable when (q3 - q1) / median < tol")
    ap.add_argument("--interleave", type=int, default=0, metavar="ROUNDS",
                    help="set every selected case up first, then time ROUNDS rounds that run "
                         "each case once (ratios between cases over the same minutes)")
    args = ap.parse_args(argv)

    specs = SPECS + external_specs()
    if args.only:
        specs = [s for s in specs if any(fnmatch.fnmatch(s.name, pat) for pat in args.only)]
    if args.list:
        for s in _peak_specs() + specs:
            print(f"{s.name:50s} {s.kind:16s} {json.dumps(s.params)}")
        return 0

    dev = clrf.Device(args.device)
    ctx = Context(dev, args.quick)
    started = _dt.datetime.now().isoformat(timespec="seconds")
    host0 = host_info()
    results = []

    def run_peaks(tag):
        for s in _peak_specs():
            s = Spec(f"{s.name}@{tag}", s.kind, s.params, s.metric, s.quick)
            results.append(run_spec(ctx, s, args))
            _print(results[-1])

    run_peaks("start")
    if args.interleave > 0 and not args.quick:
        for rec in run_interleaved(ctx, specs, args.interleave):
            results.append(rec)
            _print(rec)
    else:
        for s in specs:
            results.append(run_spec(ctx, s, args))
            _print(results[-1])
    run_peaks("end")
    peaks = summarise_peaks(results)
    add_ratios(results, peaks)
    doc = {"started": started, "finished": _dt.datetime.now().isoformat(timespec="seconds"),
           "quick": args.quick, "device": device_info(dev), "host_start": host0,
           "host_end": host_info(), "peaks": peaks, "argv": sys.argv[1:], "results": results}
    out = Path(args.out) if args.out else (
        ROOT / "bench-results" / f"bench-{started.replace(':', '')}.json")
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(doc, indent=1, default=_jsonable))
    print(f"peaks: {json.dumps(peaks)}")
    print(f"wrote {out}")
    bad = [r["name"] for r in results if "failed" in r]
    if bad:
        print(f"FAILED checks: {bad}", file=sys.stderr)
        return 1
    return 0


def _jsonable(o):
    if isinstance(o, (np.integer,)):
        return int(o)
    if isinstance(o, (np.floating,)):
        return float(o)
    if isinstance(o, np.ndarray):
        return o.tolist()
    return str(o)


def _print(r):
    if "skipped" in r:
        print(f"{r['name']:50s} skipped: {r['skipped']}", flush=True)
    elif "failed" in r:
        print(f"{r['name']:50s} FAILED: {r['failed']} {r.get('check')}", flush=True)
    elif "metrics" in r:
        t = r["time_s"]
        m = r["metrics"]
        head = m.get(r["metric"], float("nan"))
        scale, unit = (1e-6, "M " + r["metric"]) if r["metric"].endswith("/s") and \
            r["metric"] not in ("GB/s", "GFLOP/s") else (1.0, r["metric"])
        extra = f"  {m['GB/s']:.2f} GB/s" if "GB/s" in m and r["metric"] != "GB/s" else ""
        print(f"{r['name']:50s} {head * scale:9.3f} {unit}  {t['median'] * 1e3:9.2f} ms "
              f"[{t['min'] * 1e3:.2f}-{t['max'] * 1e3:.2f}] x{t['repeats']}{extra}", flush=True)
    else:
        print(f"{r['name']:50s} ok (smoke) {r.get('check') or ''}", flush=True)
