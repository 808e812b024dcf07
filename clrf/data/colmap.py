"""A scene folder as COLMAP leaves it: ``images/`` plus ``sparse/0/`` (text or binary model).

The model (COLMAP's documented output format) is three files, each either ``.txt`` or ``.bin``:

- cameras: id, model, width, height, parameters. Models read here (parameters in order):
  SIMPLE_PINHOLE (f, cx, cy), PINHOLE (fx, fy, cx, cy), SIMPLE_RADIAL (f, cx, cy, k),
  RADIAL (f, cx, cy, k1, k2), OPENCV (fx, fy, cx, cy, k1, k2, p1, p2), OPENCV_FISHEYE
  (fx, fy, cx, cy, k1, k2, k3, k4), FULL_OPENCV (fx, fy, cx, cy, k1, k2, p1, p2, k3, k4, k5,
  k6), SIMPLE_RADIAL_FISHEYE (f, cx, cy, k), RADIAL_FISHEYE (f, cx, cy, k1, k2); their
  distortion is a ``clrf.data.camera_models.Distortion`` (the equations are there). FOV,
  THIN_PRISM_FISHEYE and RAD_TAN_THIN_PRISM_FISHEYE are refused by name. COLMAP's pixel
  convention (centre of the top-left pixel at (0.5, 0.5)) is clrf's.
- images: per registered image its id, world-to-camera rotation as a unit quaternion
  (qw, qx, qy, qz), translation t, camera id and file name (relative to ``images/``), then its
  2D observations (x, y, point3D id or -1).
- points3D: per point its id, xyz, colour, error and track (image id, 2D index) pairs.

Binary files are little-endian: cameras.bin = uint64 count, then per camera int32 id, int32
model id, uint64 width, uint64 height, float64 params; images.bin = uint64 count, then per image
uint32 id, float64 q[4], float64 t[3], uint32 camera id, NUL-terminated name, uint64 n2d, n2d x
(float64 x, float64 y, int64 point id); points3D.bin = uint64 count, then per point uint64 id,
float64 xyz[3], uint8 rgb[3], float64 error, uint64 track length, that many (uint32 image id,
uint32 2D index).

Conversion: x_cam = R(q) x_world + t in OpenCV camera axes (x right, y down, z forward), so the
camera-to-world pose is [R^T | -R^T t] with its y and z columns negated for OpenGL axes. Per
image depth bounds are LLFF's: the 0.1 and 99.9 percentiles of the depths of the points whose
track contains the image. Images are ordered by file name; from there on the poses and bounds
go through exactly the LLFF processing (forward-facing versus 360, rescale, recentring, NDC).
Files in ``images/`` that COLMAP did not register have no pose and are skipped with a warning.

When the images use cameras with different parameters, every image is resampled (bilinear) onto
the camera of the first image, so the scene keeps one set of intrinsics.
"""
from __future__ import annotations

import struct
from pathlib import Path

import numpy as np

from .camera_models import MODELS, UNSUPPORTED, check_camera, from_colmap
from .cameras import camera_dirs, distort
from .base import Dataset, DataError
from .io import (IMAGE_EXTS, check_downscale, check_splits, downscale_image,
                 holdout_split, inside, limit_split, parse_background, read_image, require_dir, warn)
from .images import collect, composite
from .llff import depth_bounds, normalize_capture, scene_extent

# model id -> (name, number of parameters); the models clrf reads
CAMERA_MODELS = {mid: (name, len(params)) for name, (mid, params) in MODELS.items()}
MODEL_IDS = {name: mid for mid, (name, _) in CAMERA_MODELS.items()}
NEAR_PERCENTILE, FAR_PERCENTILE = 0.1, 99.9     # LLFF's imgs2poses depth bounds
UNDISTORT = ("undistort the images first with `colmap image_undistorter` (it writes a PINHOLE "
             "model) and use its output folder")
MIN_POINTS = 1            # an image must see at least this many 3D points for its bounds
MAX_LISTED = 5            # file names shown in a warning
PARAM_TOL = 1e-9          # relative difference below which two cameras count as the same
MODEL_FIX = "re-run COLMAP's mapper, or export the model with `colmap model_converter`"


def is_colmap(root: Path) -> bool:
    """True when ``root`` holds images/ and a sparse model (sparse/0/ or sparse/ itself)."""
    return _model_dir(root) is not None


def _model_dir(root: Path):
    for d in (root / "sparse" / "0", root / "sparse"):
        if any((d / f"cameras{ext}").is_file() for ext in (".bin", ".txt")):
            return d
    return None


class _Reader:
    """Little-endian struct reader over a whole .bin file; truncation -> DataError."""

    def __init__(self, path: Path):
        self.path, self.buf, self.pos = path, path.read_bytes(), 0

    def read(self, fmt: str, what: str):
        size = struct.calcsize("<" + fmt)
        if self.pos + size > len(self.buf):
            raise DataError(f"{self.path}: file ends inside {what} (truncated at byte "
                            f"{len(self.buf)}); {MODEL_FIX}")
        out = struct.unpack_from("<" + fmt, self.buf, self.pos)
        self.pos += size
        return out

    def name(self, what: str) -> str:
        end = self.buf.find(b"\0", self.pos)
        if end < 0:
            raise DataError(f"{self.path}: file ends inside {what} (no NUL terminator); "
                            f"{MODEL_FIX}")
        s = self.buf[self.pos:end].decode("utf-8", "replace")
        self.pos = end + 1
        return s


def _text_lines(path: Path):
    """(line number, fields) of every line that is not a comment; blank lines give no fields
    (images.txt leaves the points line of an image without observations blank)."""
    with open(path, "r", encoding="utf-8") as f:
        for no, line in enumerate(f, 1):
            s = line.strip()
            if not s.startswith("#"):
                yield no, s.split()


def _numbers(fields, path, no, what, kind=float):
    try:
        return [kind(v) for v in fields]
    except ValueError:
        raise DataError(f"{path}: line {no}: {what} has a non-numeric field ({' '.join(fields)})"
                        f"; {MODEL_FIX}") from None


def _unsupported(model, path, where):
    return DataError(f"{path}: {where}: camera model {model} is not supported (clrf reads "
                     f"{', '.join(MODEL_IDS)}); {UNDISTORT}")


def _camera(cid, model, w, h, params, path, where):
    """Checked camera dict: model name, size, (fx, fy, cx, cy), Distortion or None."""
    if model not in MODEL_IDS:
        raise _unsupported(model, path, where)
    try:
        intr, dist = from_colmap(model, params)
    except ValueError as e:
        raise DataError(f"{path}: {where}: {e}; {MODEL_FIX}") from None
    if not (np.all(np.isfinite(params)) and intr[0] > 0 and intr[1] > 0 and w > 0 and h > 0):
        raise DataError(f"{path}: {where}: needs a positive size and focal length and finite "
                        f"parameters, got {w}x{h} {list(params)}; {MODEL_FIX}")
    bad = check_camera(dist, intr, int(h), int(w))
    if bad:
        raise DataError(f"{path}: {where}: the {model} parameters {list(params)} are not a "
                        f"usable lens: {bad}; {MODEL_FIX}, or {UNDISTORT}")
    return dict(id=cid, model=model, wh=(int(w), int(h)), intr=intr, dist=dist)


def read_cameras(path: Path) -> dict:
    """camera id -> camera dict, from cameras.txt or cameras.bin."""
    cams = {}
    if path.suffix == ".bin":
        r = _Reader(path)
        (n,) = r.read("Q", "the camera count")
        for i in range(n):
            cid, mid, w, h = r.read("iiQQ", f"camera {i}")
            if mid not in CAMERA_MODELS:
                name = UNSUPPORTED.get(mid, ("unknown to COLMAP",))[0]
                raise _unsupported(f"id {mid} ({name})", path, f"camera {cid}")
            name, k = CAMERA_MODELS[mid]
            cams[cid] = _camera(cid, name, w, h, r.read("d" * k, f"camera {cid}'s parameters"),
                                path, f"camera {cid}")
        return cams
    for no, f in _text_lines(path):
        if not f:
            continue
        if len(f) < 4:
            raise DataError(f"{path}: line {no}: expected CAMERA_ID MODEL WIDTH HEIGHT PARAMS...,"
                            f" got {' '.join(f)}; {MODEL_FIX}")
        cid, w, h = _numbers([f[0], f[2], f[3]], path, no, "the camera", int)
        cams[cid] = _camera(cid, f[1], w, h, _numbers(f[4:], path, no, "the camera"), path,
                            f"line {no} (camera {cid})")
    return cams


def read_images(path: Path) -> dict:
    """image id -> (name, camera id, 4x4 world-to-camera, set of point3D ids it observes)."""
    out = {}
    if path.suffix == ".bin":
        r = _Reader(path)
        (n,) = r.read("Q", "the image count")
        for i in range(n):
            iid, *qt, cid = r.read("I7dI", f"image {i}")
            name = r.name(f"image {iid}'s name")
            (n2d,) = r.read("Q", f"image {iid}'s point count")
            obs = np.frombuffer(bytes(r.read(f"{24 * n2d}s", f"image {iid}'s points")[0]),
                                dtype=np.dtype([("xy", "<f8", 2), ("pid", "<i8")]))
            out[iid] = (name, cid, _w2c(qt, path, f"image {iid}"), set(obs["pid"][obs["pid"] >= 0]
                                                                          .tolist()))
        return out
    lines = list(_text_lines(path))
    k = 0
    while k < len(lines):
        no, f = lines[k]
        if not f:                      # blank line between records
            k += 1
            continue
        if len(f) < 10:
            raise DataError(f"{path}: line {no}: expected IMAGE_ID QW QX QY QZ TX TY TZ "
                            f"CAMERA_ID NAME, got {' '.join(f)}; {MODEL_FIX}")
        iid, cid = _numbers([f[0], f[8]], path, no, "the image", int)
        qt = _numbers(f[1:8], path, no, "the image")
        pts = lines[k + 1][1] if k + 1 < len(lines) else []
        pids = _numbers(pts[2::3], path, no + 1, "the points line", int)
        out[iid] = (" ".join(f[9:]), cid, _w2c(qt, path, f"line {no} (image {iid})"),
                    {p for p in pids if p >= 0})
        k += 2
    return out


def read_points(path: Path, colours: bool = False):
    """(xyz float64 [P, 3], {point id: row}) from points3D.txt or points3D.bin, and with
    ``colours`` their RGB as float32 [P, 3] in [0, 1] third. Which images see a point is read
    from images (their observations), so tracks are skipped."""
    ids, xyz, rgb = [], [], []
    if path.suffix == ".bin":
        r = _Reader(path)
        (n,) = r.read("Q", "the point count")
        for i in range(n):
            pid, x, y, z, cr, cg, cb, _err, tl = r.read("Q3d3BdQ", f"point {i}")
            r.read(f"{8 * tl}s", f"point {pid}'s track")
            ids.append(pid)
            xyz.append((x, y, z))
            rgb.append((cr, cg, cb))
    else:
        for no, f in _text_lines(path):
            if not f:
                continue
            if len(f) < 8:
                raise DataError(f"{path}: line {no}: expected POINT3D_ID X Y Z R G B ERROR "
                                f"TRACK..., got {' '.join(f)}; {MODEL_FIX}")
            ids.append(_numbers(f[:1], path, no, "the point", int)[0])
            xyz.append(_numbers(f[1:4], path, no, "the point"))
            rgb.append(_numbers(f[4:7], path, no, "the point's colour"))
    xyz = np.asarray(xyz, np.float64).reshape(-1, 3)
    bad = np.flatnonzero(~np.isfinite(xyz).all(1))
    if bad.size:
        raise DataError(f"{path}: point {ids[bad[0]]} has non-finite coordinates "
                        f"{xyz[bad[0]].tolist()} ({bad.size} such points); {MODEL_FIX}")
    row_of = {p: i for i, p in enumerate(ids)}
    if not colours:
        return xyz, row_of
    rgb = np.clip(np.asarray(rgb, np.float64).reshape(-1, 3), 0, 255) / 255.0
    return xyz, row_of, np.nan_to_num(rgb).astype(np.float32)


def similarity(before, after):
    """(s, R, t) with after = [s R | t] before for camera-to-world poses [N, 4, 4] moved by one
    similarity (the capture normalisation): R from the rotations, s and t from the camera
    centres by least squares (s = 1, t from the centres' means when they coincide)."""
    b = np.asarray(before, np.float64)
    a = np.asarray(after, np.float64)
    u, _, vt = np.linalg.svd(np.einsum("nij,nkj->ik", a[:, :3, :3], b[:, :3, :3]))
    R = u @ vt
    cb, ca = b[:, :3, 3], a[:, :3, 3]
    db, da = cb - cb.mean(0), ca - ca.mean(0)
    rb = db @ R.T
    den = float(np.sum(rb * rb))
    s = float(np.sum(rb * da)) / den if den > 0 else 1.0
    return s, R, ca.mean(0) - s * (R @ cb.mean(0))


def _w2c(qt, path, where):
    q = np.asarray(qt[:4], np.float64)
    norm = np.linalg.norm(q)
    if not np.all(np.isfinite(qt)) or abs(norm - 1.0) > 1e-3:
        raise DataError(f"{path}: {where}: the rotation quaternion must be finite and unit length "
                        f"(|q| = {norm:.6g}); {MODEL_FIX}")
    w, x, y, z = q / norm
    m = np.eye(4)
    m[:3, :3] = [[1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
                 [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
                 [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)]]
    m[:3, 3] = qt[4:7]
    return m


def _model_file(model: Path, stem: str) -> Path:
    for ext in (".bin", ".txt"):
        if (model / f"{stem}{ext}").is_file():
            return model / f"{stem}{ext}"
    raise DataError(f"{model}: {stem}.bin / {stem}.txt is missing; {MODEL_FIX}")


def _image_file(folder: Path, name: str) -> Path:
    """folder / name; in an images_<d>/ folder also the same stem with another image extension
    (LLFF's downscaled copies are PNGs of the JPEGs COLMAP saw)."""
    f = folder / name
    if f.is_file() or folder.name == "images":
        return f
    alt = [f.with_suffix(ext) for ext in IMAGE_EXTS if f.with_suffix(ext).is_file()]
    return alt[0] if alt else f


def _resample(img, cam, ref, hw):
    """``img`` (taken by ``cam``, already at its loaded size) seen through camera ``ref`` at
    size ``hw``: bilinear lookup of each ref pixel's ray in ``img``."""
    from scipy.ndimage import map_coordinates

    d = camera_dirs(ref["intr"], hw[0], hw[1], ref["dist"])
    xy = distort(np.stack([d[..., 0], -d[..., 1]], -1), cam["dist"])    # y down again
    u = xy[..., 0] * cam["intr"][0] + cam["intr"][2] - 0.5
    v = xy[..., 1] * cam["intr"][1] + cam["intr"][3] - 0.5
    return np.stack([map_coordinates(img[..., c], [v, u], order=1, mode="nearest")
                     for c in range(img.shape[-1])], -1).astype(np.float32)


def _same_lens(a, b) -> bool:
    """Two Distortions (or None) equal within PARAM_TOL."""
    if a is None or b is None:
        return a is b
    return a.family == b.family and np.allclose(a.coeffs, b.coeffs, rtol=PARAM_TOL, atol=0)


def load_colmap(path, kind="auto", downscale=None, holdout=8, max_images=None,
                background="white") -> Dataset:
    """Load a COLMAP scene folder (images/ + sparse/0/ with cameras, images, points3D).

    kind: "forward_facing", "real360" or "auto" (decided from the camera spread exactly as for
    poses_bounds.npy). downscale: integer factor; images_<d>/ is used when present (the same
    file names as images/), else images/ is box-averaged. holdout: every holdout-th image in
    name order is test. max_images: first this-many views of each split. background: used to
    composite RGBA images.
    """
    root = require_dir(path, "COLMAP scene", "pass the folder holding images/ and sparse/0/")
    model = _model_dir(root)
    if model is None:
        raise DataError(f"{root}: no sparse/0/cameras.bin or cameras.txt; run COLMAP's "
                        f"feature_extractor, exhaustive_matcher and mapper (output sparse/)")
    factor = check_downscale(downscale)
    if kind not in ("auto", "forward_facing", "real360"):
        raise DataError(f"kind: expected 'auto', 'forward_facing' or 'real360', got {kind!r}")
    cams = read_cameras(_model_file(model, "cameras"))
    ipath = _model_file(model, "images")
    records = read_images(ipath)
    xyz, row_of, rgb = read_points(_model_file(model, "points3D"), colours=True)
    if not records:
        raise DataError(f"{ipath}: no registered images; COLMAP could not pose any photo: check "
                        f"the mapper's log and add photos with more overlap")
    folder = root / "images"
    extra = factor
    if factor > 1 and (root / f"images_{factor}").is_dir():
        folder, extra = root / f"images_{factor}", 1
    require_dir(folder, "images", "put the photos COLMAP was run on in images/")

    recs = sorted(records.values(), key=lambda r: r[0])
    for name, cid, _, _ in recs:
        inside(folder, name, ipath, "NAME")   # no '..', absolute paths or symlinks out of it
        if cid not in cams:
            raise DataError(f"{ipath}: image {name} uses camera {cid}, which "
                            f"{_model_file(model, 'cameras').name} does not define; {MODEL_FIX}")
    registered = {r[0] for r in recs}
    if folder.name == "images":
        unposed = sorted(str(f.relative_to(folder)) for f in folder.rglob("*")
                         if f.suffix in IMAGE_EXTS and str(f.relative_to(folder)) not in registered)
        if unposed:
            shown = ", ".join(unposed[:MAX_LISTED]) + (", ..." if len(unposed) > MAX_LISTED
                                                       else "")
            warn(f"{folder}: skipping {len(unposed)} images COLMAP did not register (no pose): "
                 f"{shown}")

    n = len(recs)
    w2c = np.stack([r[2] for r in recs])
    c2w = np.linalg.inv(w2c)
    c2w[:, :3, 1:3] *= -1.0                                      # OpenCV -> OpenGL camera axes
    bounds = np.full((n, 2), np.nan)
    blind = []
    for i, (name, _, m, pids) in enumerate(recs):
        rows = [row_of[p] for p in pids if p in row_of]
        if len(rows) < MIN_POINTS:
            blind.append(name)
            continue
        depth = xyz[rows] @ m[2, :3] + m[2, 3]
        bounds[i] = np.percentile(depth, [NEAR_PERCENTILE, FAR_PERCENTILE])
    if blind:
        warn(f"{ipath}: {len(blind)} images observe no 3D point, so their depth bounds are "
             f"unknown (a forward-facing scene needs them): {', '.join(blind[:MAX_LISTED])}")

    poses, kind = normalize_capture(c2w, bounds, kind, ipath,
                                    "depth bounds (from the points each image sees)")
    s, R, t = similarity(c2w, poses)
    points = np.concatenate([s * xyz @ R.T + t, rgb], 1).astype(np.float32)
    split = holdout_split(n, holdout)
    check_splits(split, ipath, f"use a holdout between 2 and {n}")
    keep, split = limit_split(split, max_images)
    check_splits(split, ipath, "pass max_images >= 1")

    bg = parse_background(background)
    ref = cams[recs[keep[0]][1]]
    hw = None

    def each():      # one image at a time into collect (8-bit levels where exact)
        nonlocal hw, ref
        for i in keep:
            name, cid = recs[i][:2]
            a = downscale_image(read_image(_image_file(folder, name), "image"), extra)
            cam = cams[cid]
            s = a.shape[1] / cam["wh"][0]
            if abs(a.shape[0] / cam["wh"][1] / s - 1.0) > 0.02:
                raise DataError(f"{folder / name}: the image is {a.shape[1]}x{a.shape[0]} (WxH "
                                f"after downscaling) but camera {cid} is {cam['wh'][0]}x"
                                f"{cam['wh'][1]}; the aspect ratios differ, so this is not the "
                                f"photo COLMAP posed; restore that photo or re-run COLMAP")
            scaled = dict(cam, intr=cam["intr"] * s)
            if hw is None:
                hw, ref = a.shape[:2], scaled
            same = (a.shape[:2] == hw and np.allclose(scaled["intr"], ref["intr"],
                                                      rtol=PARAM_TOL)
                    and _same_lens(cam["dist"], ref["dist"]))
            yield composite(a if same else _resample(a, scaled, ref, hw), bg)

    images, _ = collect(each(), len(keep))
    if any(cams[recs[i][1]]["id"] != ref["id"] for i in keep):
        warn(f"{ipath}: images use {len({recs[i][1] for i in keep})} cameras; those differing "
             f"from camera {ref['id']} were resampled onto it")
    dist = ref["dist"]
    poses = poses[keep].astype(np.float32)
    return Dataset(name=root.name, images=images, poses=poses, intrinsics=ref["intr"],
                   split=split, background=bg, distortion=dist, points=points,
                   depth_bounds=depth_bounds(kind, bounds, keep),
                   **scene_extent(kind, poses, ref["intr"], images.shape[1:3], dist))


__all__ = ["load_colmap", "is_colmap", "read_cameras", "read_images", "read_points",
           "similarity",
           "CAMERA_MODELS"]
