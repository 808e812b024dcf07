"""Checks at the API boundary: dtypes, shapes, finiteness. Errors name the argument and the fix."""
from __future__ import annotations

import numpy as np


def check_array(name: str, a, ndim: int | None = None, shape_tail: tuple | None = None,
                dtype=np.float32, finite: bool = True) -> np.ndarray:
    """``a`` as a contiguous array of ``dtype``, after checking rank, trailing shape, finiteness."""
    try:
        arr = np.asarray(a)
    except Exception as e:  # noqa: BLE001
        raise TypeError(f"{name}: cannot be read as an array ({e})") from None
    if arr.dtype.kind not in "biuf":
        raise TypeError(f"{name}: expected a numeric array, got dtype {arr.dtype}")
    if ndim is not None and arr.ndim != ndim:
        raise ValueError(f"{name}: expected {ndim} dimensions, got shape {arr.shape}")
    if shape_tail is not None and tuple(arr.shape[-len(shape_tail):]) != tuple(shape_tail):
        raise ValueError(f"{name}: expected shape [..., {', '.join(map(str, shape_tail))}], "
                         f"got {arr.shape}")
    if finite and arr.dtype.kind == "f" and arr.size and not np.all(np.isfinite(arr)):
        bad = int(np.size(arr) - np.count_nonzero(np.isfinite(arr)))
        raise ValueError(f"{name}: {bad} of {arr.size} values are NaN or Inf; clean the input "
                         f"(e.g. np.nan_to_num) before passing it")
    with np.errstate(over="ignore"):   # an overflowing cast is reported just below, not warned
        out = np.ascontiguousarray(arr, dtype=dtype)
    if finite and dtype == np.float32 and arr.dtype.kind == "f" and arr.size:
        if not np.all(np.isfinite(out)):
            raise ValueError(f"{name}: values overflow float32 (|x| > 3.4e38)")
    return out


def as_bbox(bbox) -> np.ndarray:
    b = np.asarray(bbox, np.float64)
    if b.shape != (2, 3):
        raise ValueError(f"bbox: expected [[x0,y0,z0],[x1,y1,z1]], got shape {b.shape}")
    if not np.all(np.isfinite(b)):
        raise ValueError("bbox: values must be finite")
    if not np.all(b[1] > b[0]):
        raise ValueError(f"bbox: every max must exceed its min, got {b.tolist()}")
    return b


def check_rays(origins, dirs):
    o = check_array("origins", origins, ndim=2, shape_tail=(3,))
    d = check_array("dirs", dirs, ndim=2, shape_tail=(3,))
    if o.shape != d.shape:
        raise ValueError(f"origins {o.shape} and dirs {d.shape} must have the same shape")
    zero = np.flatnonzero(~np.any(d != 0, axis=1))
    if zero.size:
        raise ValueError(f"dirs: {zero.size} of {d.shape[0]} direction vectors are zero (first at "
                         f"row {int(zero[0])}); every ray needs a non-zero direction")
    return o, d


def check_positive(name: str, v) -> float:
    v = float(v)
    if not (np.isfinite(v) and v > 0):
        raise ValueError(f"{name}: must be a finite number > 0, got {v}")
    return v
