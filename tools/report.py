"""Markdown tables and plots from tools/bench.py JSON.

    python tools/report.py bench-results/bench-XXXX.json [--out-dir bench-results/report]

Writes ``report.md`` (device, host load, the peaks of the same run, then one table per group
with median [min-max], the throughput metrics and their ratios to the peaks; peers side by
side with clrf on the same case) and ``*.png`` bar charts (matplotlib, Agg backend), and
prints the Markdown.
"""
from __future__ import annotations

import argparse
import json
from pathlib import Path

import sys

import matplotlib

sys.path.insert(0, str(Path(__file__).resolve().parent))
matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402


def enrich(doc):
    """Model GFLOP/s and its ratio to the FMA peak for grid cases recorded without a flop
    count (runs before the flop model was added)."""
    try:
        import bench_scenes
    except ImportError:
        return
    fma = doc.get("peaks", {}).get("fma")
    for r in doc["results"]:
        p, m = r.get("params", {}), r.get("metrics")
        if not m or "degree" not in p or "samples/s" not in m or r["name"].startswith("train/"):
            continue
        if "GFLOP/s" not in m:
            bwd = p.get("mode", "fwd") != "fwd"
            m["GFLOP/s"] = m["samples/s"] * bench_scenes.grid_flop_per_sample(p["degree"], bwd) / 1e9
        if fma:
            r.setdefault("ratios", {})["GFLOP/s / fma"] = m["GFLOP/s"] / fma


def _case_key(name):
    """'peer.taichi/fwd/128/sh2/dense/camera' -> ('peer.taichi', 'fwd/128/sh2/dense/camera')."""
    impl, _, case = name.partition("/")
    return impl, case


def _fmt_rate(v):
    if v >= 1e6:
        return f"{v / 1e6:.2f} M"
    if v >= 1e3:
        return f"{v / 1e3:.1f} k"
    return f"{v:.3g}"


def peaks_table(doc):
    lines = ["| peak (cl/bench.cl) | start | end | used for ratios |", "| --- | --- | --- | --- |"]
    byname = {}
    for r in doc["results"]:
        if r["name"].startswith("peak/") and "metrics" in r:
            base, _, tag = r["name"].partition("@")
            m = r["metrics"][r["metric"]]
            lo, hi = r["metrics_min_max"][r["metric"]]
            byname.setdefault(base, {})[tag] = f"{m:.1f} [{lo:.1f}-{hi:.1f}] {r['metric']}"
    for base, tags in byname.items():
        key = base.split("/", 1)[1]
        lines.append(f"| {base} | {tags.get('start', '')} | {tags.get('end', '')} | "
                     f"{doc['peaks'].get(key, float('nan')):.1f} |")
    return "\n".join(lines)


def grid_table(doc):
    """clrf and peers per case: samples/s [min-max], rays/s, model GB/s, % of triad."""
    rows = {}
    impls = []
    for r in doc["results"]:
        if r["name"].startswith(("peak/", "train/")):
            continue
        impl, case = _case_key(r["name"])
        if impl not in impls:
            impls.append(impl)
        rows.setdefault(case, {})[impl] = r
    lines = ["| case (mode/reso/SH/occupancy/rays) | implementation | samples/s [min-max] | "
             "rays/s | ms | model GB/s | % of triad | model GFLOP/s | % of FMA | vs clrf | "
             "samples/s, CPU-normalised |",
             "| --- | --- | --- | --- | --- | --- | --- | --- | --- | --- | --- |"]
    for case, byimpl in rows.items():
        base = byimpl.get("grid", {}).get("metrics", {}).get("samples/s")
        for impl in impls:
            r = byimpl.get(impl)
            if r is None:
                continue
            label = "clrf" if impl == "grid" else impl.replace("peer.", "")
            if "metrics" not in r:
                why = r.get("skipped") or r.get("failed") or "smoke only"
                lines.append(f"| {case} | {label} | {why} | | | | | | | | |")
                continue
            m = r["metrics"]
            lo, hi = r["metrics_min_max"].get("samples/s", [0, 0])
            sps = m.get("samples/s", 0.0)
            ratio = r.get("ratios", {}).get("GB/s / triad", float("nan"))
            vs = f"{sps / base:.3g}x" if base and impl != "grid" else ""
            lines.append(f"| {case} | {label} | {_fmt_rate(sps)} [{_fmt_rate(lo)}-{_fmt_rate(hi)}] "
                         f"| {_fmt_rate(m.get('rays/s', 0))} | {r['time_s']['median'] * 1e3:.1f} | "
                         f"{m.get('GB/s', 0):.2f} | {100 * ratio:.1f}% | "
                         f"{m.get('GFLOP/s', 0):.1f} | "
                         f"{100 * r.get('ratios', {}).get('GFLOP/s / fma', float('nan')):.1f}% | "
                         f"{vs} | "
                         f"{_fmt_rate(r.get('metrics_cpu_normalised', {}).get('samples/s', 0))} |")
    return "\n".join(lines)


def train_table(doc):
    """Training kernels: headline metric [min-max], ms, model GB/s and % of triad."""
    lines = ["| training kernel | metric [min-max] | ms | model GB/s | % of triad | "
             "CPU-normalised |", "| --- | --- | --- | --- | --- | --- |"]
    for r in doc["results"]:
        if not r["name"].startswith("train/"):
            continue
        if "metrics" not in r:
            why = r.get("skipped") or r.get("failed") or "smoke only"
            lines.append(f"| {r['name']} | {why} | | | | |")
            continue
        u = r["metric"]
        m = r["metrics"]
        lo, hi = r["metrics_min_max"][u]
        gbs = f"{m['GB/s']:.2f}" if "GB/s" in m else ""
        ratio = r.get("ratios", {}).get("GB/s / triad")
        pct = f"{100 * ratio:.1f}%" if ratio is not None else ""
        cpu = r.get("metrics_cpu_normalised", {}).get(u)
        lines.append(f"| {r['name']} | {_fmt_rate(m[u])} [{_fmt_rate(lo)}-{_fmt_rate(hi)}] {u} | "
                     f"{r['time_s']['median'] * 1e3:.1f} | {gbs} | {pct} | "
                     f"{_fmt_rate(cpu) if cpu else ''} |")
    return "\n".join(lines)


def plot(doc, out_dir):
    out_dir.mkdir(parents=True, exist_ok=True)
    by_mode = {}
    for r in doc["results"]:
        if r["name"].startswith(("peak/", "train/")) or "metrics" not in r:
            continue
        impl, case = _case_key(r["name"])
        mode = case.split("/")[0]
        label = ("clrf" if impl == "grid" else impl.replace("peer.", "")) + " " + \
            case.split("/", 1)[1]
        by_mode.setdefault(mode, []).append((label, r["metrics"]["samples/s"] / 1e6,
                                             [v / 1e6 for v in r["metrics_min_max"]["samples/s"]]))
    files = []
    for mode, items in by_mode.items():
        fig, ax = plt.subplots(figsize=(9, 0.32 * len(items) + 1.2))
        labels = [i[0] for i in items]
        vals = [i[1] for i in items]
        err = [[v - i[2][0] for v, i in zip(vals, items)], [i[2][1] - v for v, i in zip(vals, items)]]
        ax.barh(range(len(items)), vals, xerr=err, color="tab:blue")
        ax.set_yticks(range(len(items)), labels, fontsize=7)
        ax.invert_yaxis()
        ax.set_xscale("log")
        ax.set_xlabel("M samples/s (median, min-max)")
        ax.set_title(f"{mode} on {doc['device']['name']} "
                     f"(triad {doc['peaks'].get('triad', 0):.1f} GB/s)", fontsize=9)
        fig.tight_layout()
        f = out_dir / f"grid_{mode}.png"
        fig.savefig(f, dpi=110)
        plt.close(fig)
        files.append(f)
    return files


def render_markdown(doc, pngs=()):
    d = doc["device"]
    h0, h1 = doc["host_start"], doc["host_end"]
    md = [f"Device: **{d['name']}** ({d['platform_version']}), {d['compute_units']} compute units; "
          f"host {h0['cpu']}, {h0['cpus']} CPUs; load average {h0['loadavg']} at the start, "
          f"{h1['loadavg']} at the end; run {doc['started']} - {doc['finished']}.",
          "", peaks_table(doc), "", grid_table(doc), "", train_table(doc), "",
          "Model GB/s: bytes requested per evaluated sample with no reuse between samples "
          "(forward: 8 links + 8 rows of 1 + SH_DIM floats; fwd+bwd: two gathers plus the read "
          "and write of 8 gradient rows), divided by the time; % of triad is that over the "
          "triad bandwidth measured in the same run; model GFLOP/s likewise from a per-sample "
          "flop model (tools/bench_scenes.py), over the FMA peak (native vector width). Samples count only samples whose cell has "
          "an allocated corner (empty space is skipped). CPU-normalised: work / (process CPU time / "
          "compute units), what the case would reach with the cores to itself (the host is "
          "shared; see the load average)."]
    for p in pngs:
        md.append(f"![{p.stem}]({p.name})")
    return "\n".join(md)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("json")
    ap.add_argument("--out-dir", help="default: <json dir>/report-<json stem>")
    a = ap.parse_args(argv)
    doc = json.loads(Path(a.json).read_text())
    enrich(doc)
    out = Path(a.out_dir) if a.out_dir else Path(a.json).parent / f"report-{Path(a.json).stem}"
    pngs = plot(doc, out)
    md = render_markdown(doc, pngs)
    (out / "report.md").write_text(md + "\n")
    print(md)


if __name__ == "__main__":
    main()
