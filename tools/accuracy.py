"""Largest kernel-vs-float64-reference errors of the grid renderer over random problems.

Random grids (SH degrees 0-3, several shapes, 30% empty voxels), random rays around and inside
the box, random backgrounds and steps; forward outputs and backward gradients against
clrf.references.reference. Prints a table and writes JSON with --json.

    python tools/accuracy.py [--trials 6] [--json out.json]
"""
import argparse
import json
import sys
from pathlib import Path

import numpy as np

sys.path.append(str(Path(__file__).resolve().parent.parent))   # the checkout's clrf only where none is installed
import clrf  # noqa: E402
from clrf.references import reference as ref  # noqa: E402


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--trials", type=int, default=6)
    ap.add_argument("--json")
    a = ap.parse_args(argv)
    dev = clrf.Device()
    rng = np.random.default_rng(2026)
    worst = {}
    shapes = [(1, 1, 1), (2, 2, 2), (3, 50, 7), (9, 8, 10), (16, 16, 16)]
    for degree in range(4):
        for shape in shapes:
            for _ in range(a.trials):
                C = 3 * (degree + 1) ** 2
                dens = rng.uniform(0, 4, shape).astype(np.float32)
                sh = rng.normal(0, 0.4, shape + (C,)).astype(np.float32)
                if np.prod(shape) > 8:
                    e = rng.random(shape) < 0.3
                    dens[e] = 0
                    sh[e] = 0
                lo = rng.uniform(-2, 0, 3)
                bbox = np.array([lo, lo + rng.uniform(0.5, 3, 3)])
                grid = clrf.SparseGrid.from_dense(dev, dens, sh, bbox)
                n = 400
                c = bbox.mean(0)
                o = (c + rng.normal(0, 2, (n, 3))).astype(np.float32)
                d = (c + rng.uniform(-0.5, 0.5, (n, 3)) * (bbox[1] - bbox[0]) - o).astype(np.float32)
                step = float(rng.uniform(0.2, 1.0))
                bg = rng.uniform(0, 1, 3)
                out = clrf.render_rays(grid, o, d, step=step, background=bg)
                r = ref.render_forward(dens, sh, bbox, o, d, step, bg)
                g = rng.normal(size=(n, 3)).astype(np.float32)
                gk = clrf.render_rays_backward(grid, o, d, g, step=step, background=bg)
                gr = ref.render_backward(dens, sh, bbox, o, d, g, step, bg)
                errs = {f"forward {k}": np.abs(out[k] - r[k]).max() for k in ("rgb", "depth", "acc")}
                for k in ("density", "sh"):
                    scale = max(np.abs(gr[k]).max(), 1e-30)
                    errs[f"backward {k}"] = np.abs(gk[k] - gr[k]).max()
                    errs[f"backward {k} (rel. to max |grad|)"] = errs[f"backward {k}"] / scale
                for k, v in errs.items():
                    worst[k] = max(worst.get(k, 0.0), float(v))
    print(f"device: {dev}")
    print(f"{4 * len(shapes) * a.trials} random problems (SH 0-3, shapes {shapes}), 400 rays each")
    print("| quantity | largest abs. error vs float64 |")
    print("| --- | --- |")
    for k, v in worst.items():
        print(f"| {k} | {v:.3g} |")
    if a.json:
        Path(a.json).write_text(json.dumps({"device": repr(dev), "worst": worst}, indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())
