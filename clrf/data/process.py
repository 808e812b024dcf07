"""``clrf process``: pose a video or a folder of photos with COLMAP (pycolmap) and write a scene
folder that ``clrf train --data OUT`` reads (the COLMAP layout of clrf/data/colmap.py).

Stages (each reported on stderr):

1. frames: a folder's images are copied in name order; a video is read with imageio's ffmpeg
   plugin in two passes. Pass one scores every frame's sharpness s = Var(L(gray)), the variance
   of the 4-neighbour Laplacian L (blur lowers high frequencies, so lowers s). The frame range
   [0, N) is cut into ``frames`` equal time windows and the sharpest frame of each window is
   kept, so the blurriest frames are skipped while the frames stay spread over the video. Pass
   two saves the kept frames as PNGs.
2. features: SIFT (pycolmap.extract_features), one shared camera (CameraMode.SINGLE) of model
   ``camera_model`` whose focal length the mapper refines.
3. matching: sequential (each frame with its ``overlap`` successors; video) or exhaustive (all
   pairs; folders of up to EXHAUSTIVE_MAX images), with two-view geometric verification.
4. mapping: incremental mapping; the largest model is kept. Fewer than MIN_REGISTERED frames,
   or fewer than ``min_fraction`` of them, registered is an error that names the frames left
   out; otherwise the frames left out are listed in a warning.
5. undistort: pycolmap.undistort_images resamples the registered frames onto PINHOLE cameras.
6. write: images/ + sparse/0/{cameras,images,points3D}.bin and clrf_process.json (the
   detected preset, the frames kept and left out).

Preset: with v_i the unit viewing direction of camera i, the capture is forward-facing when
|mean_i v_i| >= FACING_THRESHOLD (the cameras look the same way) and 360 otherwise; this is the
rule the COLMAP loader applies on its own (clrf/data/llff.py), so ``clrf train --data OUT``
picks the same preset without a flag.

Nothing half-finished is left at ``--out``: the work happens in a scratch folder beside it, the
scene is built in a temporary folder beside it that is renamed to ``--out`` only after the last
stage (clrf.runtime.atomicfile.atomic_dir: with --force, the old ``--out`` is deleted only once
the new one is in place); on failure both temporary folders are removed.
"""
from __future__ import annotations

import json
import shutil
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from .base import DataError
from .io import IMAGE_EXTS
from .llff import FACING_THRESHOLD
from ..runtime.atomicfile import atomic_dir
from ..runtime.progress import bar, message

VIDEO_EXTS = (".mp4", ".mov", ".avi", ".mkv", ".webm", ".m4v", ".mpg", ".mpeg")
EXHAUSTIVE_MAX = 100     # "auto" matcher: exhaustive up to this many images, else sequential
MIN_REGISTERED = 3       # fewest registered frames a scene can be trained on
LOG_LEVEL = 1            # COLMAP's log: warnings and errors only (0 shows its INFO lines)
MAX_LISTED = 10          # frame names shown in an error or warning
INSTALL = "install it with `pip install clrf[process]` (or `bash tools/setup.sh process`)"


class ProcessError(DataError):
    """`clrf process` cannot produce a dataset; the message names the frames and the fix."""


@dataclass
class ProcessOptions:
    frames: int = 100              # video: number of frames to keep (the sharpest per window)
    matcher: str = "auto"          # "auto" | "sequential" | "exhaustive"
    overlap: int = 10              # sequential matcher: successors matched per frame
    camera_model: str = "SIMPLE_RADIAL"   # COLMAP model estimated before undistortion
    max_features: int = 8192       # SIFT features per image
    min_fraction: float = 0.5      # fewest registered frames, as a fraction of all frames
    threads: int = -1              # pycolmap threads (-1: all cores)
    seed: int = 0                  # mapper's random seed (repeatable runs)
    force: bool = False            # replace an existing --out


def _pycolmap():
    try:
        import pycolmap
    except ImportError:
        raise ProcessError(f"clrf process needs pycolmap, which is not installed; "
                           f"{INSTALL}") from None
    pycolmap.logging.minloglevel = LOG_LEVEL
    return pycolmap


def _names(names) -> str:
    names = list(names)
    more = f", ... ({len(names)} in all)" if len(names) > MAX_LISTED else ""
    return ", ".join(names[:MAX_LISTED]) + more


def sharpness(rgb: np.ndarray) -> float:
    """Var(L(gray)) of an [H, W, C] (or [H, W]) image, L the 4-neighbour Laplacian on the
    interior pixels; gray = channel mean scaled to [0, 1] for uint8 input."""
    g = np.asarray(rgb, np.float64)
    if g.ndim == 3:
        g = g[..., :3].mean(-1)
    if np.asarray(rgb).dtype == np.uint8:
        g = g / 255.0
    lap = (g[:-2, 1:-1] + g[2:, 1:-1] + g[1:-1, :-2] + g[1:-1, 2:] - 4.0 * g[1:-1, 1:-1])
    return float(lap.var())


def pick_frames(scores, count: int) -> list:
    """Indices of the kept frames: [0, N) cut into min(count, N) equal windows, the frame of
    highest ``scores`` in each (the first on ties), ascending."""
    n = len(scores)
    k = min(int(count), n)
    edges = np.linspace(0, n, k + 1).round().astype(int)
    return [int(a + np.argmax(scores[a:b])) for a, b in zip(edges[:-1], edges[1:]) if b > a]


def _video_reader(path: Path):
    import imageio
    try:
        return imageio.get_reader(str(path), "ffmpeg")
    except Exception as e:   # imageio raises ImportError/ValueError/RuntimeError by backend
        if "ffmpeg" in str(e).lower() and ("install" in str(e).lower()
                                           or isinstance(e, ImportError)):
            raise ProcessError(f"{path}: reading a video needs imageio-ffmpeg; {INSTALL}") \
                from None
        raise ProcessError(f"{path}: cannot read the video ({_last_line(e)}); convert it to "
                           f"MP4 (H.264) or extract its frames into a folder") from None


def _last_line(e: Exception) -> str:
    """The reason of a reader's error in one line: ffmpeg's message is its whole log (banner,
    build flags), whose last line says what went wrong."""
    lines = [x.strip() for x in str(e).splitlines() if x.strip() and x.strip() != ")"]
    return lines[-1].rstrip(")") if lines else type(e).__name__


def extract_video(path: Path, dest: Path, count: int) -> list:
    """Stage 1 for a video: score every frame, save the sharpest of each of ``count`` windows
    as dest/frame_XXXXX.png (XXXXX the frame index). Returns the saved names."""
    import imageio
    scores = []
    reader = _video_reader(path)
    total = reader.get_meta_data().get("nframes", 0)
    total = int(total) if np.isfinite(total or 0) else 0
    with reader, bar(total, "frames: sharpness", "frame") as b:
        for frame in reader:
            scores.append(sharpness(frame))
            b.update(1)
    if len(scores) < MIN_REGISTERED:
        raise ProcessError(f"{path}: the video has {len(scores)} frames; at least "
                           f"{MIN_REGISTERED} are needed")
    keep = set(pick_frames(np.array(scores), count))
    names = []
    reader = _video_reader(path)
    with reader, bar(len(keep), "frames: save", "frame") as b:
        for i, frame in enumerate(reader):
            if i in keep:
                name = f"frame_{i:05d}.png"
                imageio.imwrite(dest / name, np.asarray(frame)[..., :3])
                names.append(name)
                b.update(1)
    message(f"frames: kept {len(names)} of {len(scores)} video frames (the sharpest of each "
            f"window; median sharpness kept {np.median([scores[i] for i in keep]):.3g}, all "
            f"{np.median(scores):.3g})")
    return names


def copy_images(src: Path, dest: Path) -> list:
    """Stage 1 for a folder: its image files (top level, name order) copied to dest."""
    files = sorted(f for f in src.iterdir() if f.is_file() and f.suffix.lower() in IMAGE_EXTS)
    if len(files) < MIN_REGISTERED:
        raise ProcessError(f"{src}: holds {len(files)} images ({', '.join(IMAGE_EXTS)}); add "
                           f"photos: at least {MIN_REGISTERED} overlapping ones are needed")
    with bar(len(files), "frames: copy", "image") as b:
        for f in files:
            shutil.copy2(f, dest / f.name)
            b.update(1)
    return [f.name for f in files]


def detect_preset(viewing_dirs: np.ndarray) -> str:
    """'forward_facing' when |mean of the unit viewing directions [N, 3]| >= FACING_THRESHOLD,
    else 'real360' (the COLMAP loader's own rule)."""
    v = np.asarray(viewing_dirs, np.float64)
    v = v / np.linalg.norm(v, axis=-1, keepdims=True)
    return "forward_facing" if np.linalg.norm(v.mean(0)) >= FACING_THRESHOLD else "real360"


def _stage(name: str, fn, *args, **kw):
    message(f"{name}: ...")
    t0 = time.perf_counter()
    out = fn(*args, **kw)
    message(f"{name}: done in {time.perf_counter() - t0:.1f} s")
    return out


def _map(pc, db: Path, image_dir: Path, sparse: Path, n: int, opt: ProcessOptions):
    """Stage 4: incremental mapping; the largest model (or None)."""
    o = pc.IncrementalPipelineOptions()
    o.min_model_size = MIN_REGISTERED
    o.num_threads = opt.threads
    o.random_seed = opt.seed
    o.mapper.random_seed = opt.seed
    o.triangulation.random_seed = opt.seed
    b = bar(n, "mapping", "image")
    try:
        models = pc.incremental_mapping(db, image_dir, sparse, o,
                                        initial_image_pair_callback=lambda: b.update(2),
                                        next_image_callback=lambda: b.update(1))
    finally:
        b.close()
    if not models:
        return None
    return max(models.values(), key=lambda r: r.num_reg_images())


def run_colmap(image_dir: Path, work: Path, names: list, sequential: bool,
               opt: ProcessOptions):
    """Stages 2-4 on the images in image_dir; returns the largest pycolmap.Reconstruction.
    ProcessError when too few frames registered (naming those left out)."""
    pc = _pycolmap()
    db = work / "database.db"
    reader = pc.ImageReaderOptions()
    reader.camera_model = opt.camera_model
    ext = pc.FeatureExtractionOptions()
    ext.num_threads = opt.threads
    ext.sift.max_num_features = opt.max_features
    _stage("features (SIFT)", pc.extract_features, db, image_dir, image_names=names,
           camera_mode=pc.CameraMode.SINGLE, reader_options=reader, extraction_options=ext,
           device=pc.Device.cpu)
    match = pc.FeatureMatchingOptions()
    match.num_threads = opt.threads
    if sequential:
        pairing = pc.SequentialPairingOptions()
        pairing.overlap = opt.overlap
        _stage(f"matching (sequential, overlap {opt.overlap})", pc.match_sequential, db,
               matching_options=match, pairing_options=pairing, device=pc.Device.cpu)
    else:
        _stage("matching (exhaustive)", pc.match_exhaustive, db, matching_options=match,
               device=pc.Device.cpu)
    sparse = work / "sparse"
    sparse.mkdir()
    rec = _stage("mapping", _map, pc, db, image_dir, sparse, len(names), opt)
    got = set() if rec is None else {rec.image(i).name for i in rec.reg_image_ids()}
    missing = [nm for nm in names if nm not in got]
    need = max(MIN_REGISTERED, int(np.ceil(opt.min_fraction * len(names))))
    if len(got) < need:
        why = ("no two frames overlap enough to start a model" if rec is None else
               f"only {len(got)} of {len(names)} frames registered (need {need})")
        raise ProcessError(
            f"{image_dir.parent.name}: COLMAP could not pose the capture: {why}; frames not "
            f"registered: {_names(missing)}. Use frames that overlap (consecutive views sharing "
            f"most of the scene, textured surfaces, no motion blur), more frames (--frames), or "
            f"--matcher exhaustive")
    if missing:
        message(f"warning: {len(missing)} of {len(names)} frames were not registered and are "
                f"left out: {_names(missing)}")
    return rec, missing


def _write_layout(pc, rec, image_dir: Path, work: Path, final: Path):
    """Stage 5-6: undistort to PINHOLE into ``final`` (images/, sparse/0/*.bin)."""
    model = work / "model"
    model.mkdir()
    rec.write_binary(str(model))
    und = work / "undistorted"
    _stage("undistort (PINHOLE)", pc.undistort_images, und, model, image_dir,
           output_type="COLMAP")
    final.mkdir()
    shutil.move(str(und / "images"), str(final / "images"))
    (final / "sparse" / "0").mkdir(parents=True)
    out = pc.Reconstruction(str(und / "sparse"))
    out.write_binary(str(final / "sparse" / "0"))
    return out


def process(source, out, opt: ProcessOptions = None) -> dict:
    """Pose ``source`` (a video file or a folder of images) and write the scene to ``out``.
    Returns the summary written to out/clrf_process.json."""
    src, out = Path(source), Path(out)
    opt = opt or ProcessOptions()
    if opt.matcher not in ("auto", "sequential", "exhaustive"):
        raise ProcessError(f"--matcher: expected auto, sequential or exhaustive, got "
                           f"{opt.matcher!r}")
    if opt.frames < MIN_REGISTERED:
        raise ProcessError(f"--frames: needs at least {MIN_REGISTERED}, got {opt.frames}")
    is_video = src.is_file() and src.suffix.lower() in VIDEO_EXTS
    if not (is_video or src.is_dir()):
        what = ("does not exist" if not src.exists() else
                f"is neither a video ({', '.join(VIDEO_EXTS)}) nor a folder of images")
        raise ProcessError(f"{src}: {what}; pass a video file or a folder of images")
    if out.exists() and not (out.is_dir() and not any(out.iterdir())) and not opt.force:
        raise ProcessError(f"{out}: already exists; choose another --out or pass --force to "
                           f"replace it")
    pc = _pycolmap()
    out.parent.mkdir(parents=True, exist_ok=True)
    # the scratch folder (frames, COLMAP's database and models) is deleted; the scene is built
    # beside ``out`` and takes its place (replacing it with --force) once complete
    tmp = Path(tempfile.mkdtemp(prefix=f".{out.name}.clrf-process-", dir=out.parent))
    try:
        with atomic_dir(out) as final:
            raw = tmp / "frames"
            raw.mkdir()
            names = (extract_video(src, raw, opt.frames) if is_video else copy_images(src, raw))
            sequential = (opt.matcher == "sequential" or (
                opt.matcher == "auto" and (is_video or len(names) > EXHAUSTIVE_MAX)))
            rec, missing = run_colmap(raw, tmp, names, sequential, opt)
            rec = _write_layout(pc, rec, raw, tmp, final)
            views = np.array([rec.image(i).viewing_direction() for i in rec.reg_image_ids()])
            preset = detect_preset(views)
            summary = dict(source=str(src), preset=preset, frames=len(names),
                           registered=len(names) - len(missing), not_registered=missing,
                           points=rec.num_points3D(), matcher="sequential" if sequential
                           else "exhaustive", pycolmap=getattr(pc, "__version__", "?"),
                           reprojection_error_px=float(rec.compute_mean_reprojection_error()))
            (final / "clrf_process.json").write_text(json.dumps(summary, indent=1) + "\n")
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    message(f"process: {summary['registered']} of {summary['frames']} frames posed, "
            f"{summary['points']} points, mean reprojection error "
            f"{summary['reprojection_error_px']:.2f} px, preset {preset} (detected from the "
            f"spread of the viewing directions)")
    print(f"wrote {out}; train with: clrf train --data {out}")
    return summary


__all__ = ["process", "ProcessOptions", "ProcessError", "sharpness", "pick_frames",
           "detect_preset"]
