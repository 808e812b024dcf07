"""``clrf export`` (mesh / point cloud PLY; a model kind's own files and folders) and the
video and depth outputs of ``clrf render``.

Options are checked before anything is computed or written; bad ones raise ExportError, which
the CLI reports as ``clrf: error: ...`` with exit code 2.
"""
from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from ..runtime.atomicfile import atomic_path
from ..runtime.progress import bar

MAX_RESO = 2048          # marching-cubes cells per side (the host volume is reso^3 floats)
DEPTH_MIN_OPACITY = 0.5  # depth maps are NaN / background where less light is absorbed


def _error(msg):
    from ..outputs.export import ExportError
    return ExportError(msg)


def _check_ply(opt, path):
    p = Path(path)
    if p.suffix.lower() != ".ply":
        raise _error(f"{opt} {path}: the output must be a .ply file, e.g. {opt} scene.ply")
    if p.is_dir():
        raise _error(f"{opt} {path} is a folder: pass a file name ending in .ply")
    return p


def kind_exports(a) -> dict:
    """{flag name: path} of the model kinds' own export flags the user gave (checked)."""
    from .. import registry
    out = {}
    for name, (exp, _) in registry.exports().items():
        v = getattr(a, name.replace("-", "_"), None)
        if v:
            p = Path(v)
            if exp.folder:
                out[name] = p
                continue
            if not p.name.lower().endswith(exp.suffixes) or p.is_dir():
                raise _error(f"--{name} {v}: the output must be a {exp.suffix_list()} file, "
                             f"e.g. --{name} scene{exp.suffixes[0]}")
            out[name] = p
    return out


def export_views(state, data):
    """The cameras an export may open at (interface.ExportViews): the run's dataset or
    ``data``'s, or None and why (a splat file without --data, a capture that is gone)."""
    from ..data.base import DataError
    from ..data.cameras import orbit_poses
    from ..interface import ExportViews
    from ..training import models
    if data is None and state.get("scene_file"):
        return ExportViews(None, "a splat file has no cameras (--data names a capture's)",
                           orbit_poses)
    try:
        return ExportViews(models.checkpoint_dataset(state, data), "", orbit_poses)
    except (DataError, OSError) as e:
        return ExportViews(None, f"the run's cameras are unavailable: {e}", orbit_poses)


def check_export_args(a):
    """Validate ``clrf export`` options; returns (mesh path | None, points path | None)."""
    own = kind_exports(a)
    if not a.mesh and not a.points and not own:
        from .. import registry
        kinds = ", ".join(f"--{n} {'DIR' if e.folder else 'FILE'}"
                          for n, (e, _) in registry.exports().items())
        raise _error(f"export: nothing to do: pass --mesh FILE.ply, --points FILE.ply or a "
                     f"model's own export ({kinds})")
    from .. import registry
    for name, path in own.items():   # before the model loads (an extra, a folder to write)
        exp = registry.exports()[name][0]
        if exp.check is not None:
            exp.check(path)
    mesh = _check_ply("--mesh", a.mesh) if a.mesh else None
    points = _check_ply("--points", a.points) if a.points else None
    if a.level is not None and not (math.isfinite(a.level) and a.level > 0):
        raise _error(f"--level {a.level}: must be a finite density > 0 (default: ln 2 / the "
                     f"model's step length)")
    if a.reso is not None and not 2 <= a.reso <= MAX_RESO:
        raise _error(f"--reso {a.reso}: must be in 2..{MAX_RESO} (cells along the longest side)")
    if a.bbox is not None:
        b = np.asarray(a.bbox, np.float64).reshape(2, 3)
        if not np.all(np.isfinite(b)) or np.any(b[1] <= b[0]):
            raise _error(f"--bbox {' '.join(map(str, a.bbox))}: need finite X0 Y0 Z0 X1 Y1 Z1 "
                         f"with X0 < X1, Y0 < Y1, Z0 < Z1")
    if a.n < 1:
        raise _error(f"--n {a.n}: the number of rays must be >= 1")
    if not 0.0 < a.min_opacity <= 1.0:
        raise _error(f"--min-opacity {a.min_opacity}: must be in (0, 1]")
    return mesh, points


def _ndc_of(meta):
    return (np.asarray(meta["intrinsics"]), int(meta["H"]), int(meta["W"])) if meta["ndc"] else None


def cmd_export(a):
    from ..runtime.device import Device
    from ..outputs.export import default_reso, extract_mesh, point_cloud
    from ..training.models import load_model
    from ..outputs.ply import write_ply

    mesh_path, points_path = check_export_args(a)
    own = kind_exports(a)
    dev = Device(a.device)
    model, state, _ = load_model(dev, a.ckpt)
    from .. import registry
    exports = registry.get(model.kind).exports
    for name in own:
        if name not in exports:
            owners = registry.exports()[name][1]
            raise _error(f"--{name}: a --model {', '.join(owners)} export; this checkpoint holds "
                         f"a {model.kind} model: use --mesh or --points")
    meta = state["dataset"]
    ndc = _ndc_of(meta)
    if points_path:   # load the dataset first: a bad one must stop the run before any output
        from ..training.models import checkpoint_dataset
        ds = checkpoint_dataset(state, a.data)
    if mesh_path:
        bbox = np.asarray(a.bbox if a.bbox is not None else meta["bbox"], np.float64).reshape(2, 3)
        if a.reso is not None:
            ext = bbox[1] - bbox[0]
            reso = tuple(int(max(2, round(a.reso * e / ext.max()))) for e in ext)
        else:
            reso = default_reso(model, bbox)
        with bar(reso[0], "export mesh", "slab") as b:
            mesh = extract_mesh(model, bbox, reso, a.level, ndc, progress=b.update)
        mesh_path.parent.mkdir(parents=True, exist_ok=True)
        write_ply(mesh_path, mesh.verts, mesh.colors, mesh.faces)
        print(f"saved {mesh_path}: {len(mesh.verts)} vertices, {len(mesh.faces)} triangles, "
              f"level {mesh.level:.4g}, {reso[0]}x{reso[1]}x{reso[2]} cells"
              f"{' (NDC, mapped to world space)' if ndc else ''}")
    if points_path:
        o, d = training_ray_sample(ds, a.n, a.seed)
        with bar(len(o), "export points", "ray") as b:
            pts, cols = point_cloud(model, o, d, model.background, a.min_opacity, ndc,
                                    progress=b.update)
        points_path.parent.mkdir(parents=True, exist_ok=True)
        write_ply(points_path, pts, cols)
        print(f"saved {points_path}: {len(pts)} points from {len(o)} training rays "
              f"(accumulated opacity >= {a.min_opacity})")
    for name, path in own.items():
        path.parent.mkdir(parents=True, exist_ok=True)
        views = export_views(state, a.data) if exports[name].wants_views else None
        print(exports[name].write(model, path, state=state, views=views))
    return 0


def training_ray_sample(ds, n, seed=0):
    """Rays (model space: NDC when the scene uses it) of ``n`` training pixels drawn without
    replacement (all of them if there are fewer), built one view at a time."""
    from ..data.cameras import view_rays
    H, W = ds.hw
    views = np.asarray(ds.split["train"])
    total = len(views) * H * W
    pick = np.sort(np.random.default_rng(seed).choice(total, min(n, total), replace=False))
    os_, ds_ = [], []
    for i, v in enumerate(views):
        sel = pick[(pick >= i * H * W) & (pick < (i + 1) * H * W)] - i * H * W
        if len(sel):
            o, d = view_rays(ds, ds.poses[v:v + 1])
            os_.append(o[sel])
            ds_.append(d[sel])
    return np.concatenate(os_), np.concatenate(ds_)


# ---- render: video and depth ---------------------------------------------------------------------
def check_render_args(a):
    """Validate the video/depth/resolution options of ``clrf render`` before rendering."""
    if a.fps <= 0 or not math.isfinite(a.fps):
        raise _error(f"--fps {a.fps}: the frame rate must be > 0")
    if not 0 < a.scale <= 8:
        raise _error(f"--scale {a.scale}: the resolution factor must be in (0, 8]")
    if a.frames < 1:
        raise _error(f"--frames {a.frames}: need at least one frame")
    if a.video:
        import importlib.util
        if importlib.util.find_spec("imageio_ffmpeg") is None:
            raise _error("--video needs the ffmpeg plugin of imageio: pip install "
                         "imageio-ffmpeg (or clrf[video])")


def depth_outputs(out, name, depth, acc):
    """Save ``name``.npy (float32 [H, W]: expected depth sum w t / sum w along the unit ray,
    model units; NaN where the accumulated opacity is < DEPTH_MIN_OPACITY) and ``name``.png
    (turbo colour map between the 1st and 99th percentile of the valid depths; white elsewhere)."""
    import imageio.v3 as iio
    from matplotlib import colormaps

    valid = acc >= DEPTH_MIN_OPACITY
    z = np.where(valid, depth / np.maximum(acc, 1e-12), np.nan).astype(np.float32)
    with atomic_path(out / f"{name}.npy") as tmp:
        np.save(tmp, z)
    img = np.ones(z.shape + (3,))
    if np.any(valid):
        lo, hi = np.percentile(z[valid], [1, 99])
        t = np.clip((z[valid] - lo) / max(hi - lo, 1e-12), 0, 1)
        img[valid] = colormaps["turbo"](t)[:, :3]
    with atomic_path(out / f"{name}.png") as tmp:
        iio.imwrite(tmp, (img * 255 + 0.5).astype(np.uint8), extension=".png")


def write_video(path, frames, fps):
    """H.264 MP4 of uint8 frames [N, H, W, 3] through imageio's ffmpeg plugin, written to a
    temporary name and renamed. Frames are padded (edge pixels) to even sizes, which H.264
    (yuv420p) requires."""
    import imageio.v2 as iio2
    frames = np.asarray(frames)
    ph, pw = frames.shape[1] % 2, frames.shape[2] % 2
    if ph or pw:
        frames = np.pad(frames, ((0, 0), (0, ph), (0, pw), (0, 0)), mode="edge")
    with atomic_path(path, suffix=".mp4") as tmp:   # ffmpeg picks the container by the name
        w = iio2.get_writer(tmp, format="FFMPEG", mode="I", fps=float(fps), codec="libx264",
                            pixelformat="yuv420p", macro_block_size=1, quality=8)
        with w:
            for f in frames:
                w.append_data(f)
