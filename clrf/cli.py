"""clrf train | render | eval | devices | bench.

Bad input (a missing or malformed dataset, an unknown option, an out-of-range value, an
unusable device or checkpoint) prints one message naming the file or field and the fix, and
exits with code 2; nothing is written for a run that could not start.
"""
from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

EXIT_USAGE = 2


class CliError(Exception):
    pass


def _user_errors():
    from .checkpoint import CheckpointError
    from .config import ConfigError
    from .data.base import DataError
    from .device import DeviceError
    from .programs import BuildError
    return (CliError, ConfigError, DataError, CheckpointError, DeviceError, BuildError)


def parse_set(items):
    """--set section.key=value (value parsed as JSON, else a string) -> nested dict."""
    out = {}
    for it in items or []:
        if "=" not in it or "." not in it.split("=", 1)[0]:
            raise CliError(f"--set {it!r}: expected SECTION.KEY=VALUE, e.g. grid.batch_size=4000")
        key, val = it.split("=", 1)
        sect, name = key.split(".", 1)
        try:
            v = json.loads(val)
        except json.JSONDecodeError:
            v = val
        out.setdefault(sect, {})[name] = v
    return out


def load_data(path, downscale=1):
    from .data import load_dataset
    opts = {"downscale": int(downscale)} if downscale and int(downscale) > 1 else {}
    return load_dataset(path or None, **opts)


def cmd_train(a):
    from .config import build_config
    from .device import Device
    from .models import FACTORIES
    from .train import Trainer

    overrides = parse_set(a.set)
    tr = overrides.setdefault("train", {})
    for k, v in (("max_seconds", a.max_seconds), ("model", a.model), ("data", a.data),
                 ("seed", a.seed)):
        if v is not None:
            tr[k] = v
    out = Path(a.out)
    if a.resume:
        from .checkpoint import load
        state = load(out)
        base = state["run_config"]
        if not a.config:
            # resume with the run's own configuration unless a new file is given
            for sect, vals in base.items():
                for k, v in vals.items():
                    overrides.setdefault(sect, {}).setdefault(k, v)
            overrides["train"]["max_seconds"] = (a.max_seconds if a.max_seconds is not None
                                                 else base["train"]["max_seconds"])
    elif (out / "ckpt.npz").exists() and not a.force:
        raise CliError(f"{out} already holds a run: pass --resume to continue it, --force to "
                       f"start over there, or another --out")
    data_path = overrides["train"].get("data") or ""
    if a.config and "data" not in tr:
        from .config import load_config_file
        data_path = load_config_file(a.config).get("train", {}).get("data", "") or data_path
    ds = load_data(data_path)
    cfg = build_config(a.preset or "", a.config, overrides, dataset_preset=ds.preset)
    if cfg.train.downscale > 1 and data_path:
        ds = load_data(data_path, cfg.train.downscale)
    cfg.train.data = str(data_path)
    dev = Device(a.device)
    print(f"clrf: device {dev}", file=sys.stderr)
    print(f"clrf: scene '{ds.name}' ({len(ds.split['train'])} train / "
          f"{len(ds.split.get('test', []))} test views, {ds.hw[1]}x{ds.hw[0]}), preset "
          f"'{cfg.train.preset}', model {cfg.train.model}, budget {cfg.train.max_seconds:.0f} s, "
          f"output {out}", file=sys.stderr)
    trainer = Trainer(dev, ds, cfg, out, resume=a.resume, model_factory=FACTORIES[cfg.train.model],
                      log=lambda m: print(f"clrf: {m}", file=sys.stderr))
    res = trainer.run()
    if res.get("interrupted"):
        print(f"clrf: interrupted; checkpoint kept at {trainer.ckpt_path} (resume with "
              f"`clrf train --out {out} --resume`)", file=sys.stderr)
        return 130
    print(json.dumps({k: v for k, v in res.items() if k != "views"}))
    return 0


def _ckpt_dataset(state, data_override):
    """The run's dataset (or data_override), loaded at the resolution the run trained on."""
    tr = state["run_config"]["train"]
    path = data_override if data_override is not None else tr.get("data", "")
    return load_data(path, tr.get("downscale", 1) if path else 1)


def cmd_eval(a):
    from .device import Device
    from .models import load_model
    from .train import evaluate

    dev = Device(a.device)
    model, state, cfg = load_model(dev, a.ckpt)
    ds = _ckpt_dataset(state, a.data)
    views = np.asarray(ds.split.get("test", ds.split.get("val")))
    if a.max_views:
        views = views[:a.max_views]
    t = time.perf_counter()
    ev = evaluate(model, ds, views)
    secs = time.perf_counter() - t
    for m in ev["views"]:
        print(f"view {m['view']:4d}  PSNR {m['psnr']:6.2f}  SSIM {m['ssim']:.4f}")
    print(f"mean over {len(views)} views: PSNR {ev['psnr']:.3f}  SSIM {ev['ssim']:.4f}  "
          f"(render {secs:.1f} s)")
    out = Path(a.out) if a.out else Path(a.ckpt) / "eval_cli.json"
    if out.suffix != ".json":
        out = out / "eval.json"
    out.parent.mkdir(parents=True, exist_ok=True)
    tmp = out.with_suffix(".tmp")
    tmp.write_text(json.dumps({"psnr": ev["psnr"], "ssim": ev["ssim"], "views": ev["views"],
                               "data": str(a.data or state["run_config"]["train"].get("data", "")),
                               "device": repr(dev)}, indent=2))
    tmp.replace(out)
    print(f"saved {out}")
    return 0


def cmd_render(a):
    import imageio.v3 as iio

    from .cameras import orbit_poses
    from .device import Device
    from .models import load_model
    from .train import view_rays

    dev = Device(a.device)
    model, state, cfg = load_model(dev, a.ckpt)
    meta = state["dataset"]
    H, W = int(meta["H"]), int(meta["W"])
    out = Path(a.out)
    out.mkdir(parents=True, exist_ok=True)

    class _View:  # the bits of a Dataset that view_rays needs
        hw = (H, W)
        intrinsics = np.asarray(meta["intrinsics"])
        distortion = None if meta.get("distortion") is None else np.asarray(meta["distortion"])
        ndc = bool(meta["ndc"])

    if a.views == "test":
        ds = _ckpt_dataset(state, a.data)
        poses = ds.poses[np.asarray(ds.split.get("test", ds.split.get("val")))]
    else:
        if meta["ndc"]:
            from .cameras import spiral_poses
            ds = _ckpt_dataset(state, a.data)
            poses = spiral_poses(ds.poses[ds.split["train"]], n=a.frames)
        else:
            bbox = np.asarray(meta["bbox"])
            radius = a.radius or float(np.linalg.norm(bbox[1] - bbox[0])) * 1.15
            poses = orbit_poses(a.frames, radius=radius, elevation_deg=a.elevation,
                                center=bbox.mean(0))
    if a.max_views:
        poses = poses[:a.max_views]
    frames = []
    t = time.perf_counter()
    for i, p in enumerate(poses):
        o, d = view_rays(_View, p[None])
        img = np.clip(model.render(o, d)["rgb"].reshape(H, W, 3), 0, 1)
        frame = (img * 255 + 0.5).astype(np.uint8)
        frames.append(frame)
        tmp = out / f".{a.views}_{i:03d}.png"
        iio.imwrite(tmp, frame, extension=".png")
        tmp.replace(out / f"{a.views}_{i:03d}.png")
    secs = time.perf_counter() - t
    print(f"rendered {len(frames)} {a.views} views at {W}x{H} in {secs:.1f} s to {out}")
    if a.views == "orbit" and frames:
        vid = out / "orbit.gif"
        tmp = out / ".orbit.tmp.gif"
        iio.imwrite(tmp, np.stack(frames), extension=".gif", duration=1000 / 24, loop=0)
        tmp.replace(vid)
        print(f"saved {vid}")
    return 0


def cmd_devices(a):
    from .device import check_default, format_devices
    if a.check:
        return check_default(refresh=a.reprobe)
    print(format_devices(refresh=a.reprobe))
    return 0


def cmd_bench(a):
    from .benchmark import main as bench_main
    return bench_main(["--reso", str(a.reso), "--degree", str(a.degree)])


def build_parser():
    p = argparse.ArgumentParser(prog="clrf", description="Portable OpenCL radiance fields.")
    p.add_argument("--device", default=None,
                   help="'cpu', 'gpu' or 'P:D' (default: $CLRF_DEVICE, else first working GPU, else CPU)")
    sub = p.add_subparsers(dest="cmd", required=True)

    t = sub.add_parser("train", help="train on a dataset (default: the built-in procedural scene)")
    t.add_argument("--data", default=None, help="dataset folder or .npz (default: built-in scene)")
    t.add_argument("--config", default=None, help="JSON config file (sections grid/train/nerf)")
    t.add_argument("--out", default="runs/latest", help="run directory (default: runs/latest)")
    t.add_argument("--max-seconds", type=float, default=None, help="training time budget")
    t.add_argument("--model", choices=["grid", "nerf"], default=None)
    t.add_argument("--preset", default=None, help="scene preset (default: the dataset's)")
    t.add_argument("--seed", type=int, default=None)
    t.add_argument("--set", action="append", metavar="SECTION.KEY=VALUE",
                   help="override one option, e.g. --set grid.batch_size=4000 (repeatable)")
    t.add_argument("--resume", action="store_true", help="continue the run in --out")
    t.add_argument("--force", action="store_true", help="start over in an --out that holds a run")
    t.set_defaults(func=cmd_train)

    r = sub.add_parser("render", help="render test views or an orbit from a checkpoint")
    r.add_argument("--ckpt", required=True, help="run directory (or its ckpt.npz)")
    r.add_argument("--views", choices=["test", "orbit"], default="orbit")
    r.add_argument("--out", required=True, help="output folder for PNGs (and orbit.gif)")
    r.add_argument("--data", default=None, help="dataset for test views (default: the run's)")
    r.add_argument("--frames", type=int, default=60, help="orbit frames")
    r.add_argument("--radius", type=float, default=0.0, help="orbit radius (default from bbox)")
    r.add_argument("--elevation", type=float, default=30.0, help="orbit elevation in degrees")
    r.add_argument("--max-views", type=int, default=0)
    r.set_defaults(func=cmd_render)

    e = sub.add_parser("eval", help="PSNR/SSIM of a checkpoint on its test views")
    e.add_argument("--ckpt", required=True)
    e.add_argument("--data", default=None, help="dataset (default: the run's)")
    e.add_argument("--out", default=None, help="JSON output (default: CKPT/eval_cli.json)")
    e.add_argument("--max-views", type=int, default=0)
    e.set_defaults(func=cmd_eval)

    d = sub.add_parser("devices", help="list OpenCL devices, their probe figures and the default")
    d.add_argument("--reprobe", action="store_true",
                   help="measure every device again instead of reading the cached figures")
    d.add_argument("--check", action="store_true",
                   help="print only the default device; exit 0 if it is fine, 3 if it is a slow "
                        "driver (the warning names the fix), 1 if no device works")
    d.set_defaults(func=cmd_devices)

    b = sub.add_parser("bench", help="quick renderer throughput on this device")
    b.add_argument("--reso", type=int, default=128)
    b.add_argument("--degree", type=int, default=2)
    b.set_defaults(func=cmd_bench)
    return p


def main(argv=None):
    parser = build_parser()
    a = parser.parse_args(argv)   # argparse exits 2 on unknown options, with usage
    if a.device is not None:
        import os
        os.environ["CLRF_DEVICE"] = a.device
    try:
        return a.func(a)
    except _user_errors() as e:
        print(f"clrf: error: {e}", file=sys.stderr)
        return EXIT_USAGE


if __name__ == "__main__":
    sys.exit(main())
