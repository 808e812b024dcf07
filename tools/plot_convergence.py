#!/usr/bin/env python3
"""Plot the renderer's error against step size and against run time (log-log).

    python tools/plot_convergence.py OUT/convergence.csv [--out OUT/convergence.png]

The CSV comes from ``tools/stability.py --convergence`` (columns step, samples, max_err,
seconds, rays): the max rgb error of the closed-form linear-colour slab against the step, and
the wall time of rendering ``rays`` rays at that step. A reference slope-2 line shows the
expected order of the midpoint quadrature; the float32 floor shows where it stops.
"""
from __future__ import annotations

import argparse
import csv
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402


def read(path: Path):
    with open(path, newline="") as f:
        rows = list(csv.DictReader(f))
    return {k: [float(r[k]) for r in rows] for k in rows[0]}


def plot(data, out: Path):
    fig, (a, b) = plt.subplots(1, 2, figsize=(10, 4))
    step, err, sec = data["step"], data["max_err"], data["seconds"]
    a.loglog(step, err, "o-", label="max |rgb - exact|")
    ref = [err[1] * (s / step[1]) ** 2 for s in step]
    a.loglog(step, ref, "k--", lw=0.8, label="slope 2")
    a.set_xlabel("step (voxels)")
    a.set_ylabel("max rgb error")
    a.invert_xaxis()
    a.legend()
    a.grid(True, which="both", alpha=0.3)
    b.loglog(sec, err, "o-")
    for s, e, t in zip(step, err, sec):
        b.annotate(f"{s:g}", (t, e), textcoords="offset points", xytext=(4, 4), fontsize=7)
    b.set_xlabel(f"seconds to render {int(data['rays'][0])} rays")
    b.set_ylabel("max rgb error")
    b.grid(True, which="both", alpha=0.3)
    fig.suptitle("clrf renderer: error against step and run time (labels: step)")
    fig.tight_layout()
    fig.savefig(out, dpi=120)
    return out


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("csv", type=Path)
    ap.add_argument("--out", type=Path, default=None, help="PNG path (default: next to the CSV)")
    a = ap.parse_args(argv)
    out = a.out or a.csv.with_suffix(".png")
    print(plot(read(a.csv), out))


if __name__ == "__main__":
    main()
