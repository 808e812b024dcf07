"""Sparse points for a posed capture that came without them (LLFF / mip-NeRF 360
``poses_bounds.npy``, transforms.json), triangulated from its known poses: COLMAP's features
and matches (pycolmap, the ``process`` extra) on the dataset's training views as they were
loaded, and the triangulation here, in numpy, with the dataset's own cameras.

1. up to ``max_views`` training views, evenly spaced, written as PNG to a scratch folder;
2. SIFT features and exhaustive matching with COLMAP's geometric verification (the inlier
   matches of each verified pair);
3. each inlier match triangulated by the linear (DLT) method from the two views' known
   projection matrices (intrinsics, poses), kept when it lies in front of both cameras, its
   reprojection error is under MAX_REPROJ_PX in both views and the rays meet at MIN_ANGLE_DEG
   or more; its colour is the first view's pixel under the keypoint;
4. float32 [P, 6] (xyz in the dataset's frame, RGB in [0, 1]), at most MAX_POINTS of them.

No incremental mapping runs: the poses are known, and the mapper registered 6 of 80 bonsai
views at 200x133 where matching pairs and triangulating them gives thousands of points. The
result is cached under ``$XDG_CACHE_HOME/clrf/points/`` (default ``~/.cache``) by a hash of the
views' pixels, poses and intrinsics, so a second run on the same capture starts at once.

``train.points`` "auto" keeps what the capture has; for a model that starts from points
(Kind.wants_points: the splat model) it also triangulates a photographed capture without
points (CAPTURE_PRESETS: LLFF, mip-NeRF 360, instant-ngp; not the rendered synthetic scenes,
which start random in their box as published) when pycolmap is installed, and otherwise says
once how to get them (``points_for_run``).

>>> ds = with_points(load_dataset("data/bonsai_800", downscale=4), "triangulate")
>>> ds.points.shape                                    # (P, 6): xyz, RGB in [0, 1]
"""
from __future__ import annotations

import dataclasses
import hashlib
import os
import tempfile
import time
from pathlib import Path

import numpy as np

from ..runtime.atomicfile import atomic_path
from ..runtime.progress import message
from .base import DataError

MAX_VIEWS = 80          # views given to COLMAP (evenly spaced over the training views)
MAX_REPROJ_PX = 2.0     # largest reprojection error of a kept point, pixels, in both views
MIN_ANGLE_DEG = 1.0     # smallest angle between the two rays of a kept point
MAX_POINTS = 200000     # points kept at most (a seeded random subset beyond it)
MIN_PAIR_INLIERS = 15   # verified pairs with fewer inlier matches are skipped
MODES = ("auto", "triangulate", "none")
CAPTURE_PRESETS = ("forward_facing", "real360", "real360_box")   # photographed scenes
SETUP_HINT = ("`bash tools/setup.sh process` (or `pip install clrf[process]`) installs "
              "pycolmap")
CACHE_VERSION = 2
OPENGL_TO_OPENCV = np.diag([1.0, -1.0, -1.0, 1.0])


def _cache_file(ds, views) -> Path:
    h = hashlib.sha256()
    h.update(f"v{CACHE_VERSION} {MAX_VIEWS} {MAX_REPROJ_PX} {MIN_ANGLE_DEG} {MAX_POINTS}"
             .encode())
    for v in views:
        h.update(np.ascontiguousarray(ds.images[v]).tobytes())
        h.update(np.ascontiguousarray(ds.poses[v], np.float64).tobytes())
    h.update(np.asarray(ds.intrinsics, np.float64).tobytes())
    base = os.environ.get("XDG_CACHE_HOME") or str(Path.home() / ".cache")
    return Path(base) / "clrf" / "points" / f"{ds.name}-{h.hexdigest()[:24]}.npy"


def projection(c2w, intrinsics) -> np.ndarray:
    """The 3 x 4 pixel projection matrix of an OpenGL camera-to-world pose (COLMAP's pixel
    coordinates: the centre of pixel (u, v) at (u + 0.5, v + 0.5), as clrf's cameras)."""
    fx, fy, cx, cy = (float(v) for v in intrinsics)
    K = np.array([[fx, 0, cx], [0, fy, cy], [0, 0, 1.0]])
    w2c = OPENGL_TO_OPENCV @ np.linalg.inv(np.asarray(c2w, np.float64))
    return K @ w2c[:3]


def triangulate_pairs(P1, P2, x1, x2):
    """DLT triangulation of matched pixels x1, x2 [M, 2] seen by projections P1, P2 [3, 4]:
    (points [M, 3], reprojection error [M] (the larger of the two views), depth in view 1 and
    view 2 [M], the angle between the rays [M], degrees)."""
    A = np.stack([x1[:, :1] * P1[2] - P1[0], x1[:, 1:2] * P1[2] - P1[1],
                  x2[:, :1] * P2[2] - P2[0], x2[:, 1:2] * P2[2] - P2[1]], 1)   # [M, 4, 4]
    _, _, vt = np.linalg.svd(A)
    Xh = vt[:, -1]
    w = Xh[:, 3:]
    X = Xh[:, :3] / np.where(np.abs(w) > 1e-12, w, 1e-12)
    Xh1 = np.concatenate([X, np.ones((len(X), 1))], 1)
    err, depth = [], []
    for P, x in ((P1, x1), (P2, x2)):
        q = Xh1 @ P.T
        depth.append(q[:, 2])
        err.append(np.linalg.norm(q[:, :2] / np.where(np.abs(q[:, 2:]) > 1e-12, q[:, 2:], 1e-12)
                                  - x, axis=1))
    c1 = -np.linalg.solve(P1[:, :3], P1[:, 3])
    c2 = -np.linalg.solve(P2[:, :3], P2[:, 3])
    r1, r2 = X - c1, X - c2
    cos = np.sum(r1 * r2, 1) / np.maximum(np.linalg.norm(r1, axis=1) * np.linalg.norm(r2, axis=1),
                                          1e-300)
    angle = np.degrees(np.arccos(np.clip(cos, -1, 1)))
    return X, np.maximum(*err), depth[0], depth[1], angle


def triangulate(ds, max_views: int = MAX_VIEWS, threads: int = -1) -> np.ndarray:
    """Sparse points [P, 6] (xyz in ds's frame, RGB in [0, 1]) of dataset ``ds``'s training
    views (see the module docstring). DataError naming the fix when pycolmap is missing or no
    point survives."""
    from .process import ProcessError, _pycolmap
    try:
        pc = _pycolmap()
    except ProcessError as e:
        raise DataError(f"train.points = 'triangulate': {e}") from None
    train = np.asarray(ds.split["train"])
    if len(train) < 2:
        raise DataError(f"dataset {ds.name}: {len(train)} training views are too few to "
                        f"triangulate points from; use train.points = 'auto'")
    pick = train[np.unique(np.linspace(0, len(train) - 1, min(max_views, len(train)))
                           .round().astype(int))]
    cache = _cache_file(ds, pick)
    if cache.is_file():
        pts = np.load(cache)
        message(f"points: {len(pts)} triangulated points from the cache ({cache})")
        return pts
    import imageio.v3 as iio
    t0 = time.perf_counter()
    with tempfile.TemporaryDirectory(prefix="clrf-points-") as tmp:
        work = Path(tmp)
        images = work / "images"
        images.mkdir()
        view_of = {}
        for v in pick:
            name = f"view_{int(v):05d}.png"
            rgb = np.clip(np.asarray(ds.images[v]) * 255 + 0.5, 0, 255).astype(np.uint8)
            iio.imwrite(images / name, rgb)
            view_of[name] = int(v)
        message(f"points: COLMAP features and matches on {len(pick)} of {len(train)} "
                f"training views ({ds.hw[1]}x{ds.hw[0]}), triangulated with their poses")
        db_path = work / "database.db"
        reader = pc.ImageReaderOptions()
        reader.camera_model = "PINHOLE"
        ext = pc.FeatureExtractionOptions()
        ext.num_threads = threads
        pc.extract_features(db_path, images, image_names=sorted(view_of),
                            camera_mode=pc.CameraMode.SINGLE, reader_options=reader,
                            extraction_options=ext, device=pc.Device.cpu)
        match = pc.FeatureMatchingOptions()
        match.num_threads = threads
        pc.match_exhaustive(db_path, matching_options=match, device=pc.Device.cpu)
        db = pc.Database.open(db_path)
        try:
            name_of = {im.image_id: im.name for im in db.read_all_images()}
            keys = {i: np.asarray(db.read_keypoints(i), np.float64)[:, :2] for i in name_of}
            pair_ids, geoms = db.read_two_view_geometries()
        finally:
            db.close()
    P = {i: projection(ds.poses[view_of[n]], ds.intrinsics) for i, n in name_of.items()}
    H, W = ds.hw
    xyz, rgb, pairs = [], [], 0
    for pid, g in zip(pair_ids, geoms):
        m = np.asarray(g.inlier_matches, np.int64).reshape(-1, 2)
        if len(m) < MIN_PAIR_INLIERS:
            continue
        i1, i2 = pc.pair_id_to_image_pair(pid)
        x1, x2 = keys[i1][m[:, 0]], keys[i2][m[:, 1]]
        X, err, d1, d2, angle = triangulate_pairs(P[i1], P[i2], x1, x2)
        ok = (err < MAX_REPROJ_PX) & (d1 > 0) & (d2 > 0) & (angle >= MIN_ANGLE_DEG)
        ok &= np.isfinite(X).all(1)
        if not ok.any():
            continue
        pairs += 1
        u = np.clip(x1[ok, 0].astype(int), 0, W - 1)
        v = np.clip(x1[ok, 1].astype(int), 0, H - 1)
        xyz.append(X[ok])
        rgb.append(np.asarray(ds.images[view_of[name_of[i1]]])[v, u])
    if not xyz:
        raise DataError(f"dataset {ds.name}: no matched feature of its training views "
                        f"triangulates consistently with its poses; use train.points = "
                        f"'auto' (random initial points)")
    xyz, rgb = np.concatenate(xyz), np.concatenate(rgb)
    if len(xyz) > MAX_POINTS:
        keep = np.sort(np.random.default_rng(0).choice(len(xyz), MAX_POINTS, replace=False))
        xyz, rgb = xyz[keep], rgb[keep]
    pts = np.concatenate([xyz, np.clip(rgb, 0, 1)], 1).astype(np.float32)
    message(f"points: {len(pts)} points from {pairs} view pairs in "
            f"{time.perf_counter() - t0:.1f} s")
    cache.parent.mkdir(parents=True, exist_ok=True)
    with atomic_path(cache, suffix=".npy", sync=False) as tmp:   # a cache: computed again
        np.save(tmp, pts)
    return pts


def with_points(ds, mode: str = "auto"):
    """``ds`` with sparse points per ``train.points``: "auto" and "none" keep what the capture
    has ("none" drops them), "triangulate" adds triangulated ones where it has none (NDC scenes
    keep none: their frame is not the world's)."""
    if mode not in MODES:
        raise DataError(f"train.points = {mode!r}: must be one of {list(MODES)}")
    if mode == "none":
        return dataclasses.replace(ds, points=None)
    if mode == "auto" or ds.points is not None or ds.ndc:
        return ds
    return dataclasses.replace(ds, points=triangulate(ds))


def have_pycolmap() -> bool:
    """True when pycolmap imports (the ``process`` extra)."""
    from .process import ProcessError, _pycolmap
    try:
        _pycolmap()
    except ProcessError:
        return False
    return True


def points_for_run(ds, mode: str = "auto", wanted: bool = False):
    """(``ds`` with sparse points per ``train.points``, a line for the log or ""). ``wanted``:
    the run's model starts from points; then "auto" triangulates a photographed capture
    (CAPTURE_PRESETS, world-space cameras) that has none, where pycolmap is installed. Where it
    is not, or no point triangulates, the capture stays without points and the line says so
    and how to get them (the caller prints it once the run's inputs have passed their checks:
    a model that cannot start without points refuses the run with its own message)."""
    if mode != "auto" or not wanted or ds.points is not None or ds.ndc \
            or ds.preset not in CAPTURE_PRESETS:
        return with_points(ds, mode), ""
    if not have_pycolmap():
        return ds, (f"points: {ds.name} has no sparse points and pycolmap is not installed, so "
                    f"the model starts from random ones; for points triangulated from its "
                    f"posed views (better first Gaussians), {SETUP_HINT} (or set "
                    f"train.points=none to silence this)")
    try:
        return dataclasses.replace(ds, points=triangulate(ds)), ""
    except DataError as e:
        return ds, (f"points: {str(e).split(';')[0]}; the model starts from random ones "
                    f"(set train.points=none to skip the triangulation)")


__all__ = ["triangulate", "triangulate_pairs", "with_points", "points_for_run", "have_pycolmap",
           "projection", "MODES", "CAPTURE_PRESETS"]
