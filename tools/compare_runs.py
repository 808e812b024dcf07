"""Error-against-run-time curves of several runs on one plot (e.g. NeRF vs Plenoxels).

    python tools/compare_runs.py runs/tiny_grid runs/tiny_nerf --out compare.png \
        [--labels "Plenoxels" "NeRF"] [--title "tiny_lego"]

Reads each run's metrics.csv (periodic held-out evaluations; the final all-views evaluation is
drawn as a star) and writes a PNG plus a Markdown table of PSNR reached at a few time marks.
"""
import argparse
import csv
import sys
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402


def load(run):
    rows = [r for r in csv.DictReader(open(Path(run) / "metrics.csv")) if r["eval_psnr"]]
    periodic = [r for r in rows if r["train_loss"] or r is rows[0]]
    final = rows[-1] if rows and not rows[-1]["train_loss"] and rows[-1] is not rows[0] else None
    if final is not None and final in periodic:
        periodic.remove(final)
    return periodic, final, (rows[-1]["model"] if rows else "")


def psnr_at(periodic, t):
    """Last periodic PSNR at or before t seconds; None past the end of the run."""
    if not periodic or t > 1.05 * float(periodic[-1]["seconds"]):
        return None
    best = None
    for r in periodic:   # evaluations land a step after their due time: allow 2 %
        if float(r["seconds"]) <= 1.02 * t:
            best = float(r["eval_psnr"])
    return best


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("runs", nargs="+")
    ap.add_argument("--labels", nargs="*")
    ap.add_argument("--out", default="compare.png")
    ap.add_argument("--title", default="")
    ap.add_argument("--marks", default="30,60,120,300,600,900,1800,3600")
    ap.add_argument("--log", action="store_true", help="log time axis (drops the t = 0 points)")
    a = ap.parse_args(argv)
    labels = a.labels or [Path(r).name for r in a.runs]
    fig, ax = plt.subplots(figsize=(7, 4.5), dpi=110)
    table = []
    for run, label in zip(a.runs, labels):
        periodic, final, model = load(run)
        t = [float(r["seconds"]) for r in periodic]
        p = [float(r["eval_psnr"]) for r in periodic]
        (line,) = ax.plot(t, p, "o-", ms=3, label=f"{label} ({model})")
        if final is not None:
            ax.plot([float(final["seconds"])], [float(final["eval_psnr"])], "*", ms=11,
                    color=line.get_color())
        marks = [float(m) for m in a.marks.split(",")]
        table.append((label, [psnr_at(periodic, m) for m in marks],
                      None if final is None else float(final["eval_psnr"]), marks))
    if a.log:
        ax.set_xscale("log")
    else:
        ax.set_xlim(left=0)
    ax.set_xlabel(f"training time (s{', log scale' if a.log else ''}; evaluation excluded)")
    ax.set_ylabel("held-out PSNR (dB)")
    ax.set_title(a.title or "error against run time", fontsize=10)
    ax.grid(alpha=0.3, which="both")
    ax.legend(loc="lower right", fontsize=8)
    fig.tight_layout()
    fig.savefig(a.out)
    marks = table[0][3] if table else []
    print("| run | " + " | ".join(f"{m:g} s" for m in marks) + " | final (all test views) |")
    print("| --- |" + " --- |" * (len(marks) + 1))
    for label, vals, fin, _ in table:
        cells = ["" if v is None else f"{v:.2f}" for v in vals]
        print(f"| {label} | " + " | ".join(cells) + f" | {'' if fin is None else f'{fin:.2f}'} |")
    print(f"wrote {a.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
