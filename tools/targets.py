"""Reproduce the Plenoxels training targets and print their figures.

    python tools/targets.py tiny            # tiny_lego, 60 s  (target: test PSNR >= 24)
    python tools/targets.py lego15          # lego_400, 15 min (target: test PSNR >= 28)
    python tools/targets.py lego60          # lego_400, 60 min (best PSNR reached)
    python tools/targets.py fern15          # fern images_8, 15 min (target: test PSNR >= 24)
    python tools/targets.py tiny --out runs/targets --data $CLRF_DATA

Each target runs `clrf train` in its own run directory (config.json, metrics.csv,
error_vs_time.png, ckpt.npz, eval.json) and appends one JSON line to targets.jsonl with the
final test PSNR/SSIM over all test views, the training seconds and the device.
"""
import argparse
import json
import os
import subprocess
import sys
import time
from pathlib import Path

TARGETS = {
    "tiny": {"scene": "tiny_lego", "seconds": 60, "goal": 24.0, "args": []},
    "lego15": {"scene": "lego_400", "seconds": 900, "goal": 28.0,
               "args": ["--set", "train.eval_every=60"]},
    "lego60": {"scene": "lego_400", "seconds": 3600, "goal": None,
               "args": ["--set", "train.eval_every=120"]},
    # forward-facing: the preset's schedule; periodic evaluations on downscaled views
    "fern15": {"scene": "fern", "seconds": 900, "goal": 24.0,
               "args": ["--set", "train.eval_every=30"]},
}


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("targets", nargs="+", choices=sorted(TARGETS))
    ap.add_argument("--data", default=os.environ.get("CLRF_DATA", "../shared/data"))
    ap.add_argument("--out", default="runs/targets")
    a = ap.parse_args(argv)
    out = Path(a.out)
    out.mkdir(parents=True, exist_ok=True)
    for name in a.targets:
        t = TARGETS[name]
        run = out / name
        cmd = [sys.executable, "-m", "clrf.cli", "train", "--data", str(Path(a.data) / t["scene"]),
               "--out", str(run), "--max-seconds", str(t["seconds"]), "--force", *t["args"]]
        print("$", " ".join(cmd), flush=True)
        t0 = time.time()
        rc = subprocess.call(cmd)
        if rc != 0:
            print(f"{name}: clrf train failed with exit code {rc}")
            return rc
        ev = json.loads((run / "eval.json").read_text())
        dev = subprocess.run([sys.executable, "-c", "import clrf; print(clrf.Device())"],
                             capture_output=True, text=True).stdout.strip()
        rec = {"target": name, "scene": t["scene"], "budget_s": t["seconds"],
               "train_seconds": ev["seconds"], "iterations": ev["iteration"],
               "test_views": ev["n_views"], "psnr": ev["psnr"], "ssim": ev["ssim"],
               "ssim_window": ev.get("ssim_window", "skimage-default-7x7"),
               "goal_psnr": t["goal"], "met": None if t["goal"] is None else ev["psnr"] >= t["goal"],
               "wall_s": time.time() - t0, "device": dev}
        with open(out / "targets.jsonl", "a") as f:
            f.write(json.dumps(rec) + "\n")
        print(json.dumps(rec, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
