"""clrf train | render | eval | view | export | devices | bench.

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

from .. import registry
from ..training.models import adopt_capture, checkpoint_dataset, load_data
from .common import EXIT_BUG, EXIT_USAGE, CliError, out_dir as _out_dir, user_errors as _user_errors


def parse_set(items):
    """--set section.key=value (value parsed as JSON, else a string) -> nested dict."""
    out = {}
    for it in items or []:
        if "=" not in it or "." not in it.split("=", 1)[0]:
            raise CliError(f"--set {it!r}: expected SECTION.KEY=VALUE, e.g. train.max_seconds=300")
        key, val = it.split("=", 1)
        sect, name = key.split(".", 1)
        try:
            v = json.loads(val)
        except json.JSONDecodeError:
            v = val
        out.setdefault(sect, {})[name] = v
    return out


def cmd_train(a):
    from ..training.config import build_config
    from ..runtime.device import Device
    from ..runtime.hostmem import host_budget
    from ..training.budget import check_training_fits
    from ..training.trainer import Trainer

    viewer = None
    if a.view:   # the viewer's flags, checked before anything is loaded or written
        from ..viewer.server import settings as viewer_settings
        viewer = viewer_settings(a)
        if not 0 < a.view_share <= 1:
            raise CliError(f"--view-share {a.view_share}: must be in (0, 1], the largest "
                           f"fraction of wall time the viewer may render for")
    if a.log == "tensorboard":
        from ..outputs.tblog import available
        if not available():
            raise CliError("--log tensorboard needs tensorboardX: pip install tensorboardX (or "
                           "clrf[tensorboard])")
    from .config_flags import config_flags, merge_overrides
    overrides = merge_overrides(parse_set(a.set), config_flags(a))   # --set, then --SECTION.KEY
    tr = overrides.setdefault("train", {})
    for k, v in (("max_seconds", a.max_seconds), ("model", a.model), ("data", a.data),
                 ("seed", a.seed)):
        if v is not None:
            tr[k] = v
    out = _out_dir(a.out)
    if a.resume:
        from ..outputs.checkpoint import load
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
        from ..training.config import load_config_file
        data_path = load_config_file(a.config).get("train", {}).get("data", "") or data_path
    # load at the command line's downscale straight away (a full-size load only to learn the
    # dataset's preset took 14 s on bonsai); reload only if a config file sets another one
    first = overrides["train"].get("downscale", 1)
    if not (data_path and isinstance(first, int) and not isinstance(first, bool) and first >= 1):
        first = 1   # an invalid value is reported by build_config with the field's name
    ds = load_data(data_path, first)
    cfg = build_config(a.preset or "", a.config, overrides, dataset_preset=ds.preset)
    if cfg.train.downscale != first and data_path:
        ds = load_data(data_path, cfg.train.downscale)
    cfg.train.data = str(data_path)
    kind = registry.get(cfg.train.model)
    from ..training.models import dataset_for
    ds = dataset_for(kind.name, ds)   # world-space cameras for the kinds that need them
    from ..data.triangulate import points_for_run
    # a resumed run's model comes from its checkpoint: no points to triangulate for it
    wants = not a.resume and kind.wants_points is not None and bool(kind.wants_points(cfg))
    ds, points_note = points_for_run(ds, cfg.train.points, wants)
    from ..runtime.hostmem import release_free_heap
    release_free_heap()   # what decoding the images and triangulating freed
    comm = _mpi_world()
    factory = kind
    if comm is not None and a.view:
        raise CliError("--view: the viewer runs with single-process training; drop --view "
                       "under mpirun (view the checkpoint afterwards with `clrf view`)")
    if comm is not None:
        if kind.distributed is None:
            able = [k.name for k in registry.kinds() if k.distributed is not None]
            raise CliError(f"train.model = '{cfg.train.model}': distributed training "
                           f"({comm.Get_size()} MPI ranks) is not supported for it, only for "
                           f"{', '.join(able) or 'none'}; run '{cfg.train.model}' as one "
                           f"process")
        factory = kind.distributed(comm)
        try:
            factory.check(cfg)
        except ValueError as e:
            raise CliError(str(e)) from None
        if comm.Get_rank() > 0:
            from ..runtime.progress import set_quiet
            set_quiet(True)
    if comm is None:   # the device that runs this model kind fastest (clrf/runtime/workload.py)
        from ..runtime.workload import device_for
        dev = device_for(kind.workload, a.device)
    else:
        dev = Device(a.device)
    n_views = len(ds.split["train"])
    n_views = min(n_views, cfg.train.max_train_images) if cfg.train.max_train_images else n_views
    n_rays = n_views * ds.hw[0] * ds.hw[1]
    if kind.check is not None:
        kind.check(cfg, ds, dev.caps)
    if points_note and (comm is None or comm.Get_rank() == 0):
        print(f"clrf: {points_note}", file=sys.stderr)
    if comm is None:
        plan = check_training_fits(dev.caps, dev.is_cpu, cfg, n_rays, dev.tuning, host_budget())
        print(f"clrf: memory: {plan.describe()}", file=sys.stderr)
    else:   # each rank holds its part (the grid: the largest brick's box per stage)
        try:
            # the device only: ranks sharing a host share its memory, which one rank
            # cannot budget alone
            check_training_fits(dev.caps, dev.is_cpu, factory.rank_config(cfg), n_rays,
                                dev.tuning)
        except ValueError as e:
            raise CliError(f"per MPI rank ({comm.Get_size()} ranks): {e}") from None
    rank_note = f" (MPI rank {comm.Get_rank()} of {comm.Get_size()})" if comm is not None else ""
    why = f": {dev.choice}" if getattr(dev, "choice", None) else ""
    print(f"clrf: device {dev}{rank_note}{why}", file=sys.stderr)
    if comm is None or comm.Get_rank() == 0:
        print(f"clrf: scene '{ds.name}' ({len(ds.split['train'])} train / "
              f"{len(ds.split.get('test', []))} test views, {ds.hw[1]}x{ds.hw[0]}), preset "
              f"'{cfg.train.preset}', model {cfg.train.model}, budget {cfg.train.max_seconds:.0f} s, "
              f"output {out}", file=sys.stderr)
    calibrated = None
    from ..training.calibrate import CALIBRATION_DIR, calibrate_exposure, wants_calibration
    if not a.resume and wants_calibration(cfg):
        try:   # the transforms' start, from a short run at a fraction of the resolution
            calibrated = calibrate_exposure(dev, ds, cfg, out / CALIBRATION_DIR, factory,
                                            log=lambda m: print(f"clrf: {m}", file=sys.stderr))
        except KeyboardInterrupt:
            print("clrf: interrupted during the exposure calibration: nothing trained yet",
                  file=sys.stderr)
            return 130
        cfg.train.max_seconds -= calibrated[1]["seconds_budget"]   # the run's own share
    trainer = Trainer(dev, ds, cfg, out, resume=a.resume, model_factory=factory,
                      log=lambda m: print(f"clrf: {m}", file=sys.stderr))
    if calibrated is not None:
        sect = cfg.section(kind.name)
        from .. import corrections
        have = corrections.of(trainer.model)
        exposure, grids = have.get("exposure"), have.get("bilateral")
        if calibrated[1]["steady"]:   # the rows' noise left out (the grids: the identity)
            if exposure is not None:
                exposure.slow(sect.exposure_steady_rate)   # and the rates lowered
        else:
            (grids if exposure is None else exposure).seed(calibrated[0],
                                                           sect.exposure_calibrate_hold)
        trainer.calibration = calibrated[1]
    if a.log == "tensorboard":
        from ..outputs.tblog import TensorBoardLog
        trainer.metric_sinks = (TensorBoardLog(out),)
    if a.view:
        from ..viewer.live import LiveViewer
        trainer.viewer = LiveViewer(trainer, a.view_share, **viewer)
    try:
        res = trainer.run()
    finally:
        for sink in trainer.metric_sinks:
            sink.close()
        if trainer.viewer is not None:
            trainer.viewer.close()
    if res.get("interrupted"):
        print(f"clrf: interrupted; checkpoint kept at {trainer.ckpt_path} (resume with "
              f"`clrf train --out {out} --resume`)", file=sys.stderr)
        return 130
    if trainer.primary:
        print(json.dumps({k: v for k, v in res.items() if k not in ("views", "renders")}))
        print(end_message(out, res, data_path), file=sys.stderr)
    return 0


def end_message(out, res, data_path="") -> str:
    """What a finished run leaves and what to try next: the report (metrics.csv and the
    PSNR-against-time plot), the renders of test views, the next commands."""
    out = Path(out)
    lines = []
    if "psnr" in res:
        lines.append(f"clrf: done: PSNR {res['psnr']:.2f} dB, SSIM {res['ssim']:.3f} after "
                     f"{res['seconds']:.1f} s of training ({res['iteration']} iterations)")
    lines.append(f"clrf: report:  {out / 'error_vs_time.png'} (PSNR against time), "
                 f"{out / 'metrics.csv'}" + (f", {out / 'eval.json'}"
                                              if (out / "eval.json").exists() else ""))
    if res.get("renders"):
        lines.append(f"clrf: renders: {Path(res['renders'][0]).parent}/ (test views, render "
                     f"left, ground truth right)")
    lines.append(f"clrf: next:    clrf render --ckpt {out} --out {out / 'orbit'}   "
                 f"(an orbit of the scene, orbit.gif)")
    if not data_path:
        lines.append("clrf:          clrf train --data FOLDER --out runs/mine   (your own "
                     "photos: a COLMAP, Blender, LLFF or instant-ngp folder)")
    else:
        lines.append(f"clrf:          clrf train --out {out} --resume --max-seconds "
                     f"{2 * res['seconds']:.0f}   (train on from the checkpoint)")
    return "\n".join(lines)


def _mpi_world():
    """The MPI communicator of a `mpirun -n N clrf train` (N > 1), else None."""
    from ..runtime.mpi import world
    try:
        return world()
    except RuntimeError as e:
        raise CliError(str(e)) from None


def cmd_eval(a):
    from .evaluate import cmd_eval as run
    return run(a)


def cmd_render(a):
    import imageio.v3 as iio

    from ..data.cameras import camera_orbit_poses, orbit_poses, spiral_poses
    from .export import check_render_args, depth_outputs, write_video
    from ..runtime.atomicfile import atomic_path
    from ..runtime.device import Device
    from ..outputs.frames import render_pose, spec_from_fov, spec_from_meta, to_uint8
    from ..training.models import load_model
    from ..runtime.progress import bar

    path = None
    if a.camera_path:
        from ..outputs.camera_path import load as load_path
        path = load_path(a.camera_path)
        a.views = "path"
        if a.fps is None:
            a.fps = path.fps
    if a.fps is None:
        a.fps = 24.0
    check_render_args(a)
    dev = Device(a.device)
    model, state, cfg = load_model(dev, a.ckpt)
    meta = state["dataset"]
    out = _out_dir(a.out)
    spec = spec_from_meta(meta, a.scale)
    fovs = None
    if path is not None:
        poses, fovs = path.poses, path.fovs
        pw, ph = max(1, round(path.width * a.scale)), max(1, round(path.height * a.scale))
    elif a.views == "test":
        ds = checkpoint_dataset(state, a.data)
        poses = ds.poses[np.asarray(ds.split.get("test", ds.split.get("val")))]
        spec = spec_from_meta(adopt_capture(model, state, ds), a.scale)
    elif a.views == "spiral" or meta["ndc"] or meta.get("preset") == "forward_facing":
        ds = checkpoint_dataset(state, a.data)
        poses = spiral_poses(ds.poses[ds.split["train"]], n=a.frames)
    elif str(meta.get("preset", "")).startswith("real360") and not a.radius:
        # an unbounded capture: the box-based orbit would leave the scene; follow the cameras
        ds = checkpoint_dataset(state, a.data)
        poses = camera_orbit_poses(ds.poses[ds.split["train"]], a.frames,
                                   np.asarray(meta["bbox"]).mean(0))
    else:
        bbox = np.asarray(meta["bbox"])
        radius = a.radius or float(np.linalg.norm(bbox[1] - bbox[0])) * 1.15
        poses = orbit_poses(a.frames, radius=radius, elevation_deg=a.elevation,
                            center=bbox.mean(0))
    if a.max_views:
        poses = poses[:a.max_views]
    out.mkdir(parents=True, exist_ok=True)
    frames = []
    t = time.perf_counter()
    with bar(len(poses), f"render {a.views}", "view") as b:
        for i, p in enumerate(poses):
            if fovs is not None:
                spec = spec_from_fov(float(fovs[i]), pw, ph, meta)
            r = render_pose(model, spec, p, depth=bool(a.depth))
            frame = to_uint8(r["rgb"])
            frames.append(frame)
            with atomic_path(out / f"{a.views}_{i:03d}.png") as tmp:
                iio.imwrite(tmp, frame, extension=".png")
            if a.depth:
                depth_outputs(out, f"{a.views}_{i:03d}_depth", r["depth"], r["acc"])
            b.update(1)
    secs = time.perf_counter() - t
    H, W = frames[0].shape[:2] if frames else spec.hw
    print(f"rendered {len(frames)} {a.views} views at {W}x{H} in {secs:.1f} s to {out}")
    if a.views == "orbit" and frames:
        vid = out / "orbit.gif"
        with atomic_path(vid) as tmp:
            iio.imwrite(tmp, np.stack(frames), extension=".gif", duration=1000 / 24, loop=0)
        print(f"saved {vid}")
    if a.video and frames:
        vid = out / f"{a.views}.mp4"
        write_video(vid, frames, a.fps)
        print(f"saved {vid} ({len(frames)} frames at {a.fps:g} fps)")
    return 0


def cmd_export(a):
    from .export import cmd_export as run
    return run(a)


def cmd_view(a):
    from ..viewer import run_view
    return run_view(a)


def cmd_devices(a):
    from ..runtime.device import check_default, format_devices
    from ..runtime.workload import format_choices
    if a.check:
        return check_default(refresh=a.reprobe)
    print(format_devices(refresh=a.reprobe, workloads=format_choices(
        [k.workload for k in registry.kinds() if k.workload is not None], measure=a.workloads),
        checks=[k.selfcheck for k in registry.kinds() if k.selfcheck]))
    return 0


def cmd_bench(a):
    from ..testing.benchmark import main as bench_main
    return bench_main(["--reso", str(a.reso), "--degree", str(a.degree)])


class _VersionAction(argparse.Action):
    """--version: ``clrf 0.1.0 (commit 012b9a6)``; the commit is looked up only when asked."""

    def __init__(self, option_strings, dest, **kw):
        kw.setdefault("nargs", 0)
        kw.setdefault("default", argparse.SUPPRESS)
        super().__init__(option_strings, dest, **kw)

    def __call__(self, parser, namespace, values, option_string=None):
        from ..runtime.version import describe
        print(describe())
        parser.exit()


def build_parser():
    p = argparse.ArgumentParser(prog="clrf", description="Portable OpenCL radiance fields.")
    p.add_argument("--version", action=_VersionAction,
                   help="print clrf's version (and the commit it runs from or was built from)")
    p.add_argument("--device", default=None,
                   help="'auto', 'cpu', 'gpu', 'P:D' or an OpenCL implementation ('pocl', 'intel', "
                        "'rusticl', ...; optionally ':cpu'/':gpu') (default: $CLRF_DEVICE, else 'auto': the "
                        "fastest working device of any type by a measured throughput probe, "
                        "cached per driver; `clrf devices` lists the figures and the choice)")
    p.add_argument("--quiet", action="store_true",
                   help="no progress bars or progress lines (results and errors still print)")
    sub = p.add_subparsers(dest="cmd", required=True)

    t = sub.add_parser("train", help="train on a dataset (default: the built-in procedural scene)")
    t.add_argument("--data", default=None, help="dataset folder or .npz (default: built-in scene)")
    t.add_argument("--config", default=None,
                   help=f"JSON config file (sections {'/'.join(['train', *registry.names()])})")
    t.add_argument("--out", default="runs/latest", help="run directory (default: runs/latest)")
    t.add_argument("--max-seconds", type=float, default=None, help="training time budget")
    t.add_argument("--model", choices=registry.names(), default=None,
                   help=registry.help_text())
    t.add_argument("--preset", default=None, help="scene preset (default: the dataset's)")
    t.add_argument("--seed", type=int, default=None)
    t.add_argument("--set", action="append", metavar="SECTION.KEY=VALUE",
                   help=f"override one option, e.g. --set {registry.DEFAULT}.batch_size=4000 "
                        f"(repeatable)")
    t.add_argument("--resume", action="store_true", help="continue the run in --out")
    t.add_argument("--force", action="store_true", help="start over in an --out that holds a run")
    t.add_argument("--log", choices=["csv", "tensorboard"], default="csv",
                   help="metrics.csv always; 'tensorboard' also writes event files to "
                        "OUT/tensorboard (needs tensorboardX)")
    t.add_argument("--view", action="store_true",
                   help="serve the interactive viewer while training (needs clrf[view])")
    from ..viewer.server import add_flags as add_viewer_flags
    add_viewer_flags(t, training=True)   # --port --host --token --no-token --max-clients ...
    t.add_argument("--view-share", type=float, default=0.2, metavar="FRACTION",
                   help="--view: largest fraction of wall time spent rendering for the viewer "
                        "(default 0.2)")
    from .config_flags import add_config_flags
    add_config_flags(t)   # --train.max_seconds and each kind's --SECTION.KEY
    t.set_defaults(func=cmd_train)

    r = sub.add_parser("render", help="render test views or an orbit from a checkpoint")
    r.add_argument("--ckpt", required=True, help="run directory (or its ckpt.npz)")
    r.add_argument("--views", choices=["test", "orbit", "spiral"], default="orbit",
                   help="test views, an orbit around the box, or a forward-facing spiral "
                        "(forward-facing scenes always get the spiral for orbit)")
    r.add_argument("--out", required=True, help="output folder for PNGs (and orbit.gif)")
    r.add_argument("--video", action="store_true", help="also write VIEWS.mp4 (H.264)")
    r.add_argument("--fps", type=float, default=None,
                   help="video frame rate (default 24; with --camera-path the file's fps)")
    r.add_argument("--camera-path", default=None, metavar="FILE",
                   help="render the cameras of a camera_path.json instead of --views (saved by "
                        "`clrf view`, or nerfstudio's layout) to path_NNN.png (and path.mp4 with --video), at "
                        "the file's render_width x render_height times --scale")
    r.add_argument("--depth", action="store_true",
                   help="also write colour-mapped depth PNGs and raw depth .npy per view")
    r.add_argument("--scale", type=float, default=1.0,
                   help="resolution factor relative to the training images (default 1)")
    r.add_argument("--data", default=None, help="dataset for test views (default: the run's)")
    r.add_argument("--frames", type=int, default=60, help="orbit / spiral frames")
    r.add_argument("--radius", type=float, default=0.0, help="orbit radius (default: from the box; real360 scenes: the cameras' own circle)")
    r.add_argument("--elevation", type=float, default=30.0, help="orbit elevation in degrees")
    r.add_argument("--max-views", type=int, default=0)
    r.set_defaults(func=cmd_render)

    from .evaluate import add_eval_parser
    add_eval_parser(sub, cmd_eval)

    x = sub.add_parser("export", help="mesh (marching cubes) or point cloud of a checkpoint "
                                      "as binary PLY; a splat scene's files or web page")
    x.add_argument("--ckpt", required=True, help="run directory (or its ckpt.npz)")
    x.add_argument("--mesh", default=None, metavar="FILE.ply", help="write a coloured mesh")
    x.add_argument("--points", default=None, metavar="FILE.ply",
                   help="write a coloured point cloud")
    x.add_argument("--level", type=float, default=None,
                   help="density of the surface (default ln 2 / the model's step length: one "
                        "render step there absorbs half the light)")
    x.add_argument("--reso", type=int, default=None,
                   help="mesh cells along the longest side of the box (default: the model's own "
                        "resolution where it has one, a voxel grid's; else 256)")
    x.add_argument("--bbox", type=float, nargs=6, default=None,
                   metavar=("X0", "Y0", "Z0", "X1", "Y1", "Z1"),
                   help="mesh box in model space (NDC for forward-facing scenes; default: the "
                        "scene box)")
    x.add_argument("--n", type=int, default=200_000, help="training rays for --points")
    x.add_argument("--min-opacity", type=float, default=0.5,
                   help="keep rays whose accumulated opacity is at least this (--points)")
    x.add_argument("--seed", type=int, default=0, help="which training rays --points uses")
    x.add_argument("--data", default=None,
                   help="dataset for --points and --web's cameras (default: the run's)")
    for name, (exp, owners) in registry.exports().items():   # a kind's own files
        x.add_argument(f"--{name}", default=None,
                       metavar="DIR" if exp.folder else f"FILE{'|'.join(exp.suffixes)}",
                       help=f"{exp.help} (--model {', '.join(owners)} checkpoints)")
    x.set_defaults(func=cmd_export)

    v = sub.add_parser("view", help="interactive web viewer of a checkpoint (needs clrf[view])")
    v.add_argument("--ckpt", required=True, help="run directory (or its ckpt.npz)")
    add_viewer_flags(v)
    v.add_argument("--data", default=None, help="dataset for the camera list (default: the run's)")
    v.add_argument("--no-cameras", action="store_true",
                   help="do not load the dataset to list its cameras")
    v.add_argument("--exit-after", type=float, default=0.0, metavar="SECONDS",
                   help="stop after this many seconds (scripts, tests; default: run until Ctrl-C)")
    v.set_defaults(func=cmd_view)

    d = sub.add_parser("devices", help="list OpenCL devices, their probe figures and the default")
    d.add_argument("--reprobe", action="store_true",
                   help="measure every device again and run its gradient self-checks again, "
                        "instead of reading the cached figures and verdicts")
    d.add_argument("--workloads", action="store_true",
                   help="time each model kind's kernels on every working device (cached) and "
                        "show which device each --model gets by default")
    d.add_argument("--check", action="store_true",
                   help="print only the default device; exit 0 if it is fine, 3 if it is a slow "
                        "driver (the warning names the fix), 1 if no device works")
    d.set_defaults(func=cmd_devices)

    b = sub.add_parser("bench", help="quick renderer throughput on this device")
    b.add_argument("--reso", type=int, default=128)
    b.add_argument("--degree", type=int, default=2)
    b.set_defaults(func=cmd_bench)

    from .process import add_process_parser
    add_process_parser(sub)   # clrf process VIDEO|IMAGE_DIR --out DIR
    return p


def main(argv=None):
    parser = build_parser()
    a = parser.parse_args(argv)   # argparse exits 2 on unknown options, with usage
    from ..runtime.progress import set_quiet
    set_quiet(a.quiet)
    if a.device is not None:
        import os
        os.environ["CLRF_DEVICE"] = a.device
    import faulthandler
    if not faulthandler.is_enabled():
        faulthandler.enable()   # a crash inside a driver leaves the Python stack on stderr
    from ..runtime.selfcheck import ClrfBug, InstallError
    try:
        status = a.func(a)
    except (*_user_errors(), InstallError) as e:
        print(f"clrf: error: {e}", file=sys.stderr)
        status = EXIT_USAGE
    except ClrfBug as e:
        print(f"clrf: internal error: {e}", file=sys.stderr)
        status = EXIT_BUG
    from ..runtime.mpi import end_job_if_failed
    end_job_if_failed(status)   # under mpirun: one rank's failure ends every rank
    return status


if __name__ == "__main__":
    sys.exit(main())
