"""The same hash checkpoint evaluated with several render settings: how much of a run's test PSNR
its renderer's bin count costs, separately from the training.

    python tools/render_bins.py --ckpt runs/lego400 --every 20 --oversample 1,2,4
    python tools/render_bins.py --ckpt runs/lego400 --every 20 --oversample 2 --json out.json

Renders every ``--every``-th test view at ``hash.samples x k`` bins per ray for each k of
``--oversample`` (the model's ``render_oversample``; training is not touched) and prints the mean
PSNR / SSIM and the seconds per setting, with the CPU and OpenCL implementation beside them.
"""
from __future__ import annotations

import argparse
import dataclasses
import json
import sys
import time
from pathlib import Path

sys.path.append(str(Path(__file__).resolve().parents[1]))   # the checkout's clrf only where none is installed

from profile_step import cpu_model  # noqa: E402  (tools/ is on the path when run as a script)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--ckpt", required=True, help="run directory written by clrf train --out")
    ap.add_argument("--data", default=None, help="dataset folder (default: the run's)")
    ap.add_argument("--every", type=int, default=1, help="every this-many-th test view")
    ap.add_argument("--oversample", default="1,2", help="comma-separated render_oversample values")
    ap.add_argument("--device", default=None, help="CLRF_DEVICE-style spec")
    ap.add_argument("--json", default=None, help="write the figures here too")
    a = ap.parse_args(argv)

    import numpy as np

    from clrf.hash.config import HashConfig
    from clrf.runtime.device import Device
    from clrf.training.models import checkpoint_dataset, load_model
    from clrf.training.trainer import evaluate

    dev = Device(a.device)
    model, state, _ = load_model(dev, a.ckpt)
    if not isinstance(model.config, HashConfig):
        raise SystemExit(f"--ckpt {a.ckpt}: a {state.get('kind', 'grid')} checkpoint; this tool "
                         f"changes a hash model's render bins")
    ds = checkpoint_dataset(state, a.data)
    views = np.asarray(ds.split.get("test", ds.split.get("val")))[::max(1, a.every)]
    caps = dev.caps
    print(f"CPU: {cpu_model()}; OpenCL: {caps.platform_version}; device {caps.name}")
    print(f"{a.ckpt}: {model.describe()}; {len(views)} test views")
    rows = []
    for k in (int(s) for s in a.oversample.split(",")):
        model.config = dataclasses.replace(model.config, render_oversample=k)
        t = time.perf_counter()
        ev = evaluate(model, ds, views)
        secs = time.perf_counter() - t
        rows.append({"render_oversample": k, "bins": model.render_samples, "psnr": ev["psnr"],
                     "ssim": ev["ssim"], "seconds": secs, "views": len(views)})
        print(f"render_oversample {k} ({model.render_samples} bins): PSNR {ev['psnr']:.3f} dB, "
              f"SSIM {ev['ssim']:.4f}, {secs:.1f} s", flush=True)
    if a.json:
        Path(a.json).write_text(json.dumps({"cpu": cpu_model(), "opencl": caps.platform_version,
                                            "device": caps.name, "ckpt": str(a.ckpt),
                                            "rows": rows}, indent=2))


if __name__ == "__main__":
    main()
