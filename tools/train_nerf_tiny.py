"""Train NerfModel on tiny_lego for a time budget; print test PSNR over time as CSV.

Standalone (the shared training loop lives in clrf.training.trainer): rays from poses and focal in
numpy (vectorised), random batches over all training pixels, evaluation on the test views.

    CLRF_DATA=/work/shared/data PYTHONPATH=. python tools/train_nerf_tiny.py --minutes 10

CSV columns: seconds (training time, evaluation excluded), step, train_mse (mean of the last
steps), test_psnr, load1 (the host's 1-minute load average: the machine is shared).
"""
from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path

import numpy as np
import pyopencl.array as cla

import clrf
from clrf.training.metrics import psnr_from_mse
from clrf.nerf import NerfConfig, NerfModel


def camera_rays(poses: np.ndarray, H: int, W: int, focal: float):
    """origins, dirs [N*H*W, 3] through pixel centres; poses camera-to-world [N, 4, 4] in
    OpenGL axes (x right, y up, looking down -z)."""
    j, i = np.meshgrid(np.arange(W, dtype=np.float64), np.arange(H, dtype=np.float64))
    cam = np.stack([(j + 0.5 - 0.5 * W) / focal, -(i + 0.5 - 0.5 * H) / focal,
                    -np.ones_like(i)], axis=-1)                          # [H, W, 3]
    dirs = np.einsum("nab,hwb->nhwa", poses[:, :3, :3].astype(np.float64), cam)
    origins = np.broadcast_to(poses[:, None, None, :3, 3], dirs.shape)
    return (origins.reshape(-1, 3).astype(np.float32), dirs.reshape(-1, 3).astype(np.float32))


def psnr(a, b) -> float:
    mse = float(np.mean((np.asarray(a, np.float64) - np.asarray(b, np.float64)) ** 2))
    return psnr_from_mse(max(mse, 1e-12))


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data", default=None,
                    help="tiny_lego .npz (default: $CLRF_DATA/tiny_lego/*.npz)")
    ap.add_argument("--minutes", type=float, default=10.0, help="training time budget")
    ap.add_argument("--eval-every", type=float, default=60.0, help="seconds between evaluations")
    ap.add_argument("--preset", default="tiny")
    ap.add_argument("--set", action="append", default=[], metavar="FIELD=VALUE",
                    help="override a NerfConfig field (JSON value), e.g. --set lr=2e-3")
    ap.add_argument("--n-test", type=int, default=6, help="test views to evaluate (last ones)")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--out", default=None, help="also write the CSV and config here")
    args = ap.parse_args(argv)

    if args.data:
        path = Path(args.data)
    else:
        if "CLRF_DATA" not in os.environ:
            sys.exit("train_nerf_tiny: pass --data FILE.npz or set CLRF_DATA to the shared data "
                     "folder (it holds tiny_lego/)")
        path = next(Path(os.environ["CLRF_DATA"], "tiny_lego").glob("*.npz"))
    d = np.load(path)
    images, poses, focal = d["images"], d["poses"], float(d["focal"])
    n_train = 100
    H, W = images.shape[1:3]
    o_tr, d_tr = camera_rays(poses[:n_train], H, W, focal)
    c_tr = images[:n_train].reshape(-1, 3).astype(np.float32)
    test = np.arange(n_train, images.shape[0])[-args.n_test:]
    o_te, d_te = camera_rays(poses[test], H, W, focal)
    c_te = images[test].reshape(-1, 3)

    overrides = {}
    for s in args.set:
        k, v = s.split("=", 1)
        overrides[k] = json.loads(v)
    cfg = NerfConfig.from_preset(args.preset, **overrides)
    dev = clrf.Device()
    model = NerfModel(dev, cfg, near=2.0, far=6.0, background=(0, 0, 0), seed=args.seed)
    q = dev.queue
    rng = np.random.default_rng(args.seed)
    print(f"# device {dev}; config {json.dumps(cfg.__dict__)}", file=sys.stderr)
    lines = ["seconds,step,train_mse,test_psnr,load1"]
    print(lines[0], flush=True)
    budget = 60.0 * args.minutes
    trained, it, next_eval, recent = 0.0, 0, 0.0, []

    def evaluate():
        out = model.render(o_te, d_te)
        row = f"{trained:.1f},{it},{np.mean(recent) if recent else float('nan'):.5f}," \
              f"{psnr(out['rgb'], c_te):.3f},{os.getloadavg()[0]:.2f}"
        lines.append(row)
        print(row, flush=True)

    while trained < budget:
        if trained >= next_eval:
            evaluate()
            recent = []
            next_eval += args.eval_every
        t0 = time.perf_counter()
        idx = rng.integers(0, o_tr.shape[0], cfg.batch_rays)
        loss = model.train_step(it, cla.to_device(q, o_tr[idx]), cla.to_device(q, d_tr[idx]),
                                cla.to_device(q, c_tr[idx]))
        trained += time.perf_counter() - t0
        recent.append(loss)
        it += 1
    evaluate()
    if args.out:
        Path(args.out).mkdir(parents=True, exist_ok=True)
        Path(args.out, "psnr.csv").write_text("\n".join(lines) + "\n")
        Path(args.out, "config.json").write_text(json.dumps(cfg.__dict__, indent=1))


if __name__ == "__main__":
    main()
