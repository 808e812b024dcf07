"""Shared reading and checking for the loaders. Every failure is a DataError naming the file,
the field and the fix; loaders check everything before building a Dataset, so nothing
half-loaded is ever returned."""
from __future__ import annotations

import json
import os
import warnings
from pathlib import Path

import numpy as np

from .base import DataError
from .images import collect

ROTATION_TOL = 1e-3       # max |R^T R - I| entry for a pose to count as a rigid transform
BOTTOM_ROW_TOL = 1e-6     # max |bottom row - [0, 0, 0, 1]| entry
IMAGE_EXTS = (".png", ".jpg", ".jpeg", ".PNG", ".JPG", ".JPEG")
MAX_IMAGE_FRACTION = 0.25  # largest decoded image (float32 RGBA) as a fraction of RAM


def require_file(path: Path, what: str, fix: str = "") -> Path:
    path = Path(path)
    if not path.is_file():
        kind = "is a folder, not a file" if path.is_dir() else "does not exist"
        raise DataError(f"{path}: {what} {kind}" + (f"; {fix}" if fix else ""))
    return path


def require_dir(path: Path, what: str, fix: str = "") -> Path:
    path = Path(path)
    if not path.is_dir():
        raise DataError(f"{path}: {what} folder does not exist" + (f"; {fix}" if fix else ""))
    return path


def inside(root: Path, rel: str, jpath: Path, field: str) -> Path:
    """``root / rel`` resolved (symlinks followed), or a DataError naming ``field`` of ``jpath``
    when it is absolute or resolves outside ``root`` (by '..' or a symlink)."""
    root = Path(root).resolve()
    if Path(rel).is_absolute():
        raise DataError(f"{jpath}: field '{field}' = {rel!r} is an absolute path; image paths "
                        f"must be relative to {root} (move the images into the dataset folder)")
    p = (root / rel).resolve()
    if not p.is_relative_to(root):
        raise DataError(f"{jpath}: field '{field}' = {rel!r} resolves to {p}, outside the "
                        f"dataset folder {root} (by '..' or a symlink); copy the image into it")
    return p


def read_json(path: Path) -> dict:
    """Parse a JSON object, or raise DataError with the file, line and column."""
    require_file(path, "JSON file", "check the dataset folder is complete")
    try:
        with open(path, "r", encoding="utf-8") as f:
            obj = json.load(f)
    except json.JSONDecodeError as e:
        raise DataError(f"{path}: malformed JSON at line {e.lineno}, column {e.colno} ({e.msg}); "
                        f"fix the file (e.g. check it with `python -m json.tool {path.name}`)"
                        ) from None
    except (OSError, UnicodeDecodeError) as e:
        raise DataError(f"{path}: cannot read the JSON file ({e})") from None
    if not isinstance(obj, dict):
        raise DataError(f"{path}: expected a JSON object at the top level, got {type(obj).__name__}")
    return obj


def get_field(obj: dict, key: str, path: Path, where: str = "", kind=None):
    """obj[key], or a DataError naming the file and the (dotted) field."""
    name = f"{where}.{key}" if where else key
    if not isinstance(obj, dict) or key not in obj:
        raise DataError(f"{path}: required field '{name}' is missing; add it to the file")
    val = obj[key]
    if kind is not None and not isinstance(val, kind):
        want = kind.__name__ if isinstance(kind, type) else "/".join(k.__name__ for k in kind)
        raise DataError(f"{path}: field '{name}' must be a {want}, got {type(val).__name__}")
    return val


def as_number(val, path: Path, name: str) -> float:
    if isinstance(val, bool) or not isinstance(val, (int, float)) or not np.isfinite(val):
        raise DataError(f"{path}: field '{name}' must be a finite number, got {val!r}")
    return float(val)


def as_matrix(val, path: Path, name: str) -> np.ndarray:
    """A JSON 4x4 (or 3x4) nested list as a float64 [4, 4] matrix."""
    try:
        m = np.asarray(val, np.float64)
    except (TypeError, ValueError):
        raise DataError(f"{path}: field '{name}' must be a 4x4 list of numbers") from None
    if m.shape == (3, 4):
        m = np.concatenate([m, [[0.0, 0.0, 0.0, 1.0]]], 0)
    if m.shape != (4, 4):
        raise DataError(f"{path}: field '{name}' must be a 4x4 matrix, got shape {m.shape}")
    return m


def check_poses(poses: np.ndarray, path: Path, field: str) -> None:
    """Poses [N, 4, 4] must be finite rigid transforms: R orthonormal within ROTATION_TOL, bottom
    row [0, 0, 0, 1]. ``field`` is a format string with one {} for the index."""
    for i, m in enumerate(np.asarray(poses, np.float64)):
        name = field.format(i)
        if not np.all(np.isfinite(m)):
            raise DataError(f"{path}: {name} contains NaN or Inf; fix or remove this camera")
        bottom = np.abs(m[3] - [0.0, 0.0, 0.0, 1.0]).max()
        if bottom > BOTTOM_ROW_TOL:
            raise DataError(f"{path}: {name} is not a rigid transform: bottom row is "
                            f"{m[3].tolist()}, expected [0, 0, 0, 1]; store camera-to-world "
                            f"matrices")
        r = m[:3, :3]
        dev = np.abs(r.T @ r - np.eye(3)).max()
        if dev > ROTATION_TOL:
            raise DataError(f"{path}: {name} is not a rigid transform: its rotation part is not "
                            f"orthonormal (max |R^T R - I| = {dev:.3g} > {ROTATION_TOL}); remove "
                            f"scale/shear from the camera-to-world matrix")


def image_header(path: Path, what: str = "image") -> tuple:
    """(width, height, mode) from the file header, without decoding the pixels; a DataError
    when the decoded float32 RGBA image would take more than MAX_IMAGE_FRACTION of RAM (a
    decompression bomb: a small file declaring a huge size)."""
    from PIL import Image

    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", Image.DecompressionBombWarning)
            Image.MAX_IMAGE_PIXELS, limit = None, Image.MAX_IMAGE_PIXELS
            try:
                with Image.open(path) as im:
                    w, h, mode = im.width, im.height, im.mode
            finally:
                Image.MAX_IMAGE_PIXELS = limit
    except Exception as e:  # noqa: BLE001 - Pillow raises many types; all mean "unreadable"
        raise DataError(f"{path}: unreadable {what} ({type(e).__name__}: {e}); replace the file "
                        f"with a valid PNG/JPEG") from None
    need = 16 * w * h                                   # float32 RGBA
    ram = os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES")
    if need > MAX_IMAGE_FRACTION * ram:
        raise DataError(f"{path}: {what} header declares {w}x{h} pixels ({need / 2**30:.1f} GiB "
                        f"decoded), more than this machine's memory allows ({ram / 2**30:.1f} "
                        f"GiB RAM); the file is corrupt or far too large: resize it")
    return w, h, mode


def read_image(path: Path, what: str = "image") -> np.ndarray:
    """An image file as float32 [H, W, C] in [0, 1] (C = 3 or 4); grey becomes RGB. The header
    is checked first (image_header), so nothing huge is decoded."""
    import imageio.v3 as iio

    path = Path(path)
    if not path.is_file():
        raise DataError(f"{path}: {what} file does not exist; restore it, or remove its entry")
    image_header(path, what)
    try:
        with warnings.catch_warnings():        # imageio probes legacy plugins on a bad file
            warnings.simplefilter("ignore", DeprecationWarning)
            a = np.asarray(iio.imread(path))
    except Exception as e:  # noqa: BLE001 - imageio raises many types; all mean "unreadable"
        raise DataError(f"{path}: unreadable {what} ({type(e).__name__}: {e}); replace the file "
                        f"with a valid PNG/JPEG") from None
    if a.ndim == 2:
        a = a[..., None]
    if a.ndim != 3 or a.shape[-1] not in (1, 2, 3, 4) or a.shape[0] == 0 or a.shape[1] == 0:
        raise DataError(f"{path}: unsupported {what} shape {a.shape}; expected HxW, HxWx3 or "
                        f"HxWx4")
    if a.dtype == np.uint8:
        a = a.astype(np.float32) / 255.0
    elif a.dtype == np.uint16:
        a = a.astype(np.float32) / 65535.0
    elif a.dtype.kind == "f":
        a = a.astype(np.float32)
    else:
        raise DataError(f"{path}: unsupported {what} dtype {a.dtype}; expected 8/16-bit or float")
    if a.shape[-1] in (1, 2):                           # grey (+ alpha)
        a = np.concatenate([np.repeat(a[..., :1], 3, -1), a[..., 1:]], -1)
    check_finite(a, path, what)
    return a


def check_finite(a: np.ndarray, path: Path, field: str) -> None:
    if a.dtype.kind == "f" and not np.all(np.isfinite(a)):
        bad = int(a.size - np.count_nonzero(np.isfinite(a)))
        raise DataError(f"{path}: '{field}' has {bad} NaN/Inf values; re-export the images "
                        f"(or clean them with np.nan_to_num)")


def check_same_size(shape, first_shape, path: Path, first_path: Path) -> None:
    if tuple(shape[:2]) != tuple(first_shape[:2]):
        raise DataError(f"{path}: image size {shape[1]}x{shape[0]} (WxH) differs from "
                        f"{first_shape[1]}x{first_shape[0]} of {first_path}; all images of a "
                        f"scene must share one size (resize them, or remove the odd one)")


def downscale_image(a: np.ndarray, factor: int) -> np.ndarray:
    """Box-average by an integer factor (crops the bottom/right remainder; cx/fx scale by 1/f)."""
    if factor == 1:
        return a
    H, W = (a.shape[0] // factor) * factor, (a.shape[1] // factor) * factor
    a = a[:H, :W]
    return a.reshape(H // factor, factor, W // factor, factor, -1).mean((1, 3), dtype=np.float32)


def check_downscale(downscale) -> int:
    if downscale is None:
        return 1
    if isinstance(downscale, bool) or int(downscale) != downscale or downscale < 1:
        raise DataError(f"downscale: expected a positive integer factor, got {downscale!r}")
    return int(downscale)


def parse_background(background) -> tuple:
    if isinstance(background, str):
        named = {"white": (1.0, 1.0, 1.0), "black": (0.0, 0.0, 0.0)}
        if background not in named:
            raise DataError(f"background: expected 'white', 'black' or an RGB triple, "
                            f"got {background!r}")
        return named[background]
    bg = tuple(float(c) for c in background)
    if len(bg) != 3:
        raise DataError(f"background: expected an RGB triple, got {background!r}")
    return bg


def holdout_split(n: int, every: int) -> dict:
    """Every ``every``-th view (0, every, 2 every, ...) is test, the rest train (NeRF's llffhold)."""
    idx = np.arange(n)
    test = idx[::every] if every > 0 else idx[:0]
    return {"train": np.setdiff1d(idx, test), "test": test}


def limit_split(split: dict, max_images) -> tuple:
    """Keep the first ``max_images`` of each split. Returns (kept global indices in order,
    split re-indexed into the kept list)."""
    if max_images is not None:
        split = {k: np.asarray(v)[:max_images] for k, v in split.items()}
    keep = np.unique(np.concatenate([np.asarray(v, np.int64) for v in split.values()]))
    remap = {int(g): i for i, g in enumerate(keep)}
    return keep, {k: np.array([remap[int(g)] for g in v], np.int64) for k, v in split.items()}


def check_splits(split: dict, path: Path, fix: str) -> None:
    for name, idx in split.items():
        if len(idx) == 0:
            raise DataError(f"{path}: split '{name}' is empty; {fix}")


def load_images(paths, downscale: int = 1, what: str = "image", background=(1.0, 1.0, 1.0)):
    """Read every file, check one shared size and channel layout, downscale, and keep each as
    it comes (clrf/data/images.py ``collect``: 8-bit levels where exact, else float32
    composited on ``background``), so no float32 copy of every image is ever held twice.

    Returns (images [N, H, W, 3], alpha [N, H, W] of RGBA files or None (``collect``), (H, W)
    of the files before downscaling)."""
    paths = list(paths)
    first = []

    def each():
        for p in paths:
            a = read_image(p, what)
            if not first:
                first.append((a.shape, p))
            else:
                check_same_size(a.shape, first[0][0], p, first[0][1])
                if a.shape[-1] != first[0][0][-1]:
                    kinds = {3: "RGB (or grey/palette without alpha)", 4: "RGBA"}
                    raise DataError(f"{p}: {what} is {kinds[a.shape[-1]]} but {first[0][1]} is "
                                    f"{kinds[first[0][0][-1]]}; all images of a scene must share "
                                    f"one channel layout (convert this one, e.g. to RGBA)")
            yield downscale_image(a, downscale)

    images, alpha = collect(each(), len(paths), background)
    return images, alpha, (first[0][0][:2] if first else (0, 0))


def warn(msg: str) -> None:
    warnings.warn(msg, UserWarning, stacklevel=3)
