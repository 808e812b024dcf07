"""`clrf eval`: PSNR, the standard SSIM and LPIPS of a checkpoint, on the run's own test views
or under a published protocol (``--protocol``, clrf/data/protocols.py).

Output JSON (default CKPT/eval_cli.json, or CKPT/eval_PROTOCOL.json with --protocol): the means
``psnr``, ``ssim`` (``ssim_window`` names it), ``lpips`` (null when unavailable, the reason in
``lpips_unavailable``), ``views`` (per view), ``n_views``, ``resolution`` [W, H]; with a protocol
also ``protocol``, ``protocol_resolution``, ``standard`` (false: NOT the protocol) and ``note``;
with ``--downscale N`` (the test views rendered at 1/N of the training resolution against the
test images box-averaged by N) also ``downscale``; with ``--refine-poses N`` (splat, hash grid
and Plenoxels grid runs, with or without pose refinement in training) also
``psnr_poses_refined`` and ``ssim_poses_refined``: each test view scored again after N steps of
a pose correction of its own against its own image, the scene held still (BARF's protocol for
runs that refine their poses: such a scene may sit a little off the given poses' frame), and
``poses_refined``, the test corrections' mean. The splat model renders the whole view each
step; the ray models take a training step's batch of the view's rays a step (the hash grid's
adapted batch, grid.batch_size; clrf/corrections/ray_pose.py refine_view_pose), so a view
costs about N training steps either way.
"""
from __future__ import annotations

import json
import sys
import time
from pathlib import Path

import numpy as np

from .. import corrections
from ..runtime.atomicfile import write_text


def _lpips_setup(a):
    """(net, None) when LPIPS will be computed, else (net or None, the stated reason)."""
    if a.lpips == "none":
        return None, "LPIPS not requested (--lpips none)"
    from ..training.perceptual import lpips_status
    why = lpips_status(a.lpips, a.lpips_backbone)
    return a.lpips, why


def _views_and_data(a, state):
    """(dataset, views, protocol info or None) for the command's arguments."""
    from ..training.models import checkpoint_dataset, dataset_for
    if a.protocol:
        if getattr(a, "downscale", 1) != 1:
            from .common import CliError
            raise CliError("--downscale does not apply with --protocol: a protocol fixes its "
                           "resolution")
        from .. import registry
        from ..data.protocols import prepare
        path = a.data if a.data is not None else state["run_config"]["train"].get("data", "")
        pd = prepare(a.protocol, path, a.allow_downscaled, a.scene_type)
        # as the run's model kind takes the scene (world-space cameras where it needs them)
        pd.dataset = dataset_for(str(state.get("kind", registry.DEFAULT)), pd.dataset)
        meta = state["dataset"]
        if bool(meta["ndc"]) != bool(pd.dataset.ndc):
            from .common import CliError
            raise CliError(f"--ckpt {a.ckpt}: the run was trained on a "
                           f"{'forward-facing (NDC)' if meta['ndc'] else 'non-NDC'} scene, but "
                           f"{path} under the {a.protocol} protocol is "
                           f"{'forward-facing' if pd.dataset.ndc else 'not forward-facing'}; "
                           f"evaluate it with its own data")
        return pd.dataset, pd.views, pd
    ds = checkpoint_dataset(state, a.data)
    return ds, np.asarray(ds.split.get("test", ds.split.get("val"))), None


def cmd_eval(a):
    from ..runtime.device import Device
    from ..training.metrics import SSIM_NAME
    from ..training.models import adopt_capture, load_model
    from ..training.perceptual import lpips
    from ..data.io import downscale_image
    from ..runtime.progress import bar
    from ..training.trainer import evaluate

    if a.downscale < 1:
        from .common import CliError
        raise CliError(f"--downscale {a.downscale}: must be a whole factor >= 1")
    dev = Device(a.device)
    model, state, cfg = load_model(dev, a.ckpt)
    if a.refine_poses:
        _check_refine(a, model)
    ds, views, pd = _views_and_data(a, state)
    if a.refine_poses:
        _check_refine_scene(ds)
    adopt_capture(model, state, ds)
    full = len(views)
    if a.max_views:
        views = views[:a.max_views]
    net, lp_why = _lpips_setup(a)
    if pd is not None and pd.background is not None:
        model.background = tuple(pd.background)      # the protocol's background, not the run's
    t = time.perf_counter()
    per_view, gain_sums = [], []
    corr = corrections.of(model)
    with bar(len(views), f"eval {a.protocol or 'test'}", "view") as b:
        for v in views:
            ev = evaluate(model, ds, [v], keep_images=lp_why is None, downscale=a.downscale,
                          half_fitted=corr.colour is not None)
            m = ev["views"][0]
            gain_sums += ev.get("gain_sums", [])
            if lp_why is None:
                m["lpips"] = lpips(ev["images"][0], downscale_image(ds.images[v], a.downscale),
                                   net, a.lpips_backbone)
            if a.refine_poses:
                m.update(_refined(model, ds, v, a))
            per_view.append(m)
            b.update(1)
    secs = time.perf_counter() - t
    H, W = (int(x) // a.downscale for x in ds.hw)
    res = {"psnr": float(np.mean([m["psnr"] for m in per_view])),
           "ssim": float(np.mean([m["ssim"] for m in per_view])), "ssim_window": SSIM_NAME,
           "psnr_color_corrected": float(np.mean([m["psnr_color_corrected"]
                                                  for m in per_view])),
           "lpips": (float(np.mean([m["lpips"] for m in per_view])) if lp_why is None else None),
           "lpips_net": net, "lpips_unavailable": lp_why,
           "n_views": len(per_view), "resolution": [W, H]}
    if a.downscale != 1:   # test images box-averaged: a zoomed-out view
        res["downscale"] = a.downscale
    if "psnr_half_fitted" in per_view[0]:   # a model with a colour transform per image
        for k in ("psnr_half_fitted", "psnr_right_half"):
            res[k] = float(np.mean([m[k] for m in per_view]))
        from ..references.reference_exposure import shared_gain_psnr
        gain, shared = shared_gain_psnr(gain_sums)   # one gain for all the views
        for m, p in zip(per_view, shared):
            m["psnr_shared_gain"] = float(p)
        res["psnr_shared_gain"], res["shared_gain"] = float(np.mean(shared)), gain.tolist()
    summaries = corr.summaries()   # e.g. how far the training poses were corrected
    res.update(summaries)
    if a.refine_poses:   # the same views, each after a correction of its own (BARF's protocol)
        for k in ("psnr", "ssim"):
            res[f"{k}_poses_refined"] = float(np.mean([m[f"{k}_poses_refined"]
                                                       for m in per_view]))
        res["poses_refined"] = {
            "steps": a.refine_poses, "lr": _refine_lr(a, model),
            "rotation_deg": float(np.mean([m["pose_refined_deg"] for m in per_view])),
            "translation_rel": float(np.mean([m["pose_refined_rel"] for m in per_view]))}
    if pd is not None:
        ph, pw = pd.protocol_hw
        standard = pd.standard and len(per_view) == full
        note = pd.note or ("" if standard else f"NOT the {pd.protocol} protocol: {len(per_view)} "
                                               f"of its {full} views (--max-views)")
        res.update(protocol=pd.protocol, protocol_resolution=[pw, ph], standard=standard,
                   note=note, **pd.detail)
    for m in per_view:
        lp = f"  LPIPS {m['lpips']:.4f}" if "lpips" in m else ""
        print(f"view {m['view']:4d}  PSNR {m['psnr']:6.2f}  SSIM {m['ssim']:.4f}{lp}")
    lp = (f"  LPIPS({net}) {res['lpips']:.4f}" if lp_why is None else "")
    head = f"{a.protocol} protocol, " if pd is not None else ""
    print(f"{head}mean over {len(per_view)} views at {W}x{H}: PSNR {res['psnr']:.3f}  "
          f"SSIM {res['ssim']:.4f}{lp}  (render {secs:.1f} s); colour-corrected PSNR "
          f"{res['psnr_color_corrected']:.3f}")
    if lp_why is not None:
        print(lp_why)
    if "psnr_shared_gain" in res:
        print(f"a colour correction per training image: NeRF-W protocol (fitted on each view's "
              f"left half) right halves PSNR {res['psnr_half_fitted']:.3f} (as rendered "
              f"{res['psnr_right_half']:.3f}); under one gain per channel for all views PSNR "
              f"{res['psnr_shared_gain']:.3f} (gain "
              f"{' '.join(f'{g:.3f}' for g in res['shared_gain'])})")
    for c in corr:
        s = summaries.get(f"{c.name}_correction")
        if s:
            print(c.report(s))
    if a.refine_poses:
        pr = res["poses_refined"]
        print(f"with each test view's pose refined ({a.refine_poses} steps against its own "
              f"image, the scene held still): PSNR {res['psnr_poses_refined']:.3f}  SSIM "
              f"{res['ssim_poses_refined']:.4f}; the test poses moved by "
              f"{pr['rotation_deg']:.3f} deg and {100 * pr['translation_rel']:.2f} % of the "
              f"scene's extent on average")
    if pd is not None and not res["standard"]:
        print(res["note"])
    default = f"eval_{a.protocol}.json" if a.protocol else "eval_cli.json"
    out = Path(a.out) if a.out else Path(a.ckpt) / default
    if out.suffix != ".json":
        out = out / "eval.json"
    out.parent.mkdir(parents=True, exist_ok=True)
    res.update(views=per_view, device=repr(dev),
               data=str(a.data or state["run_config"]["train"].get("data", "")))
    write_text(out, json.dumps(res, indent=2))
    print(f"saved {out}")
    sys.stdout.flush()
    return 0


def _refine_lr(a, model) -> float:
    """--refine-poses-lr, else the run's own first pose learning rate (its section's
    ``lr_pose``, whether or not the run refined its training poses)."""
    if a.refine_poses_lr is not None:
        return float(a.refine_poses_lr)
    section = getattr(model, "config", None) or getattr(model, "cfg")
    return float(section.lr_pose)


def _check_refine(a, model):
    """--refine-poses applies to the models with ``refine_view_pose`` (splat, hash, grid, nerf) at
    their test images' own resolution; one clear error else."""
    from .common import CliError
    if a.refine_poses < 0:
        raise CliError(f"--refine-poses {a.refine_poses}: must be a step count >= 0")
    if not hasattr(model, "refine_view_pose"):
        raise CliError(f"--refine-poses: the {getattr(model, 'kind', '?')} model cannot refine "
                       f"a camera's pose; --model splat, hash, grid and nerf runs can")
    if a.downscale != 1:
        raise CliError("--refine-poses does not apply with --downscale: the poses are refined "
                       "at the test images' own resolution")
    if a.refine_poses_lr is not None and not 0 < a.refine_poses_lr <= 0.1:
        raise CliError(f"--refine-poses-lr {a.refine_poses_lr}: must be in (0, 0.1] (radians "
                       f"a step)")


def _check_refine_scene(ds):
    """--refine-poses corrects the camera that makes a view's rays: not NDC rays."""
    if ds.ndc:
        from .common import CliError
        raise CliError(f"--refine-poses: {ds.name} is a forward-facing (NDC) scene, whose rays "
                       f"are not a camera's; its test poses cannot be refined")


def _refined(model, ds, v, a) -> dict:
    """View v's metrics after its pose is refined against its own image (--refine-poses): the
    model's refine_view_pose from the view's given pose and rays (the ray models step on
    batches of them), then the view rendered from the corrected pose."""
    from ..data.cameras import view_rays
    from ..interface import render_view
    from ..training.metrics import image_metrics
    c2w, pc = model.refine_view_pose(np.asarray(ds.poses[v], np.float64), ds.intrinsics, ds.hw,
                                     ds.images[v], a.refine_poses, _refine_lr(a, model),
                                     rays=lambda: view_rays(ds, ds.poses[v:v + 1]))
    rgb = render_view(model, c2w, ds.intrinsics, ds.hw, lambda: view_rays(ds, c2w[None]),
                      depth=False)["rgb"]
    m = image_metrics(rgb, ds.images[v])
    return {"psnr_poses_refined": m["psnr"], "ssim_poses_refined": m["ssim"],
            "pose_refined_deg": pc["rotation_deg"], "pose_refined_rel": pc["translation_rel"]}


def add_eval_parser(sub, func):
    from ..data.protocols import PROTOCOLS
    e = sub.add_parser("eval", help="PSNR / SSIM / LPIPS of a checkpoint on its test views or "
                                    "under a published protocol")
    e.add_argument("--ckpt", required=True)
    e.add_argument("--data", default=None, help="dataset (default: the run's)")
    e.add_argument("--out", default=None,
                   help="JSON output (default: CKPT/eval_cli.json, CKPT/eval_PROTOCOL.json)")
    e.add_argument("--max-views", type=int, default=0)
    e.add_argument("--downscale", type=int, default=1, metavar="N",
                   help="render the test views at 1/N of the run's training resolution and "
                        "score them against the test images box-averaged by N (a zoomed-out "
                        "view)")
    described = "; ".join(f"{k}: {v}" for k, v in PROTOCOLS.items())
    e.add_argument("--protocol", choices=sorted(PROTOCOLS), default=None,
                   help="evaluate under a published protocol, whatever the run trained at: "
                        + described.replace("%", "%%"))     # argparse %-formats help text
    e.add_argument("--allow-downscaled", action="store_true",
                   help="with --protocol: when the data lacks the protocol's resolution, "
                        "evaluate the protocol's views at the data's own resolution, labelled "
                        "NOT the protocol")
    e.add_argument("--scene-type", choices=["indoor", "outdoor"], default=None,
                   help="mipnerf360: indoor (1/2 resolution) or outdoor (1/4) for a scene whose "
                        "name is not one of the published ones")
    e.add_argument("--refine-poses", type=int, default=0, metavar="N",
                   help="splat, hash, grid and nerf runs: also score each test view after N Adam "
                        "steps of a pose correction of its own against its own image, the "
                        "scene held still (BARF's protocol for runs that refined their training "
                        "poses, whose scene may sit a little off the given poses' frame); about "
                        "N training steps of time a view (hash, grid, nerf: a training batch of the "
                        "view's rays a step); 100 steps are plenty for poses off by a degree")
    e.add_argument("--refine-poses-lr", type=float, default=None, metavar="RAD",
                   help="with --refine-poses: the first step's rate in radians, falling to a "
                        "tenth (default: the run's own lr_pose, whether or not it refined its "
                        "training poses: splat 3e-3, hash and grid 1e-3)")
    e.add_argument("--lpips", choices=["alex", "vgg", "none"], default="alex",
                   help="LPIPS backbone (default alex; vgg as the NeRF paper's Blender table); "
                        "needs the 'eval' extra and the backbone's ImageNet weights, else the "
                        "output states why it is absent")
    e.add_argument("--lpips-backbone", default=None, metavar="FILE",
                   help="torchvision's backbone weights file (default: $CLRF_LPIPS_WEIGHTS, then "
                        "torch's hub cache)")
    e.set_defaults(func=func)
    return e
