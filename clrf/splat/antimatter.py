"""Gaussian splats as the ``.splat`` file of antimatter15's WebGL viewer
(github.com/antimatter15/splat), which many web viewers open.

No header: 32 bytes a Gaussian, little endian, in the PLY's axes (no conversion):

  position  float32 x 3
  scale     float32 x 3, linear (exp of the log scale)
  colour    uint8 x 4: R, G, B = round(255 (0.5 + SH_C0 dc)), A = round(255 sigmoid(opacity)),
            each clipped to 0..255
  rotation  uint8 x 4: the unit quaternion w, x, y, z as round(128 q + 128), clipped to 0..255

Gaussians are sorted by size times opacity (exp of the summed log scales times the opacity),
largest first, as antimatter15's converter does (the viewer draws the first ones while the rest
load); read back, they come in that order.

Lost on the way: every SH band above degree 0 (view-dependent colour; the file is degree 0),
colours outside 0..1 (0.5 + SH_C0 dc clipped: dc within +-1.77) in steps of
1 / (255 SH_C0) of dc, opacities in steps of 1/255 (0 and 1 read back as 1/510 and 1 - 1/510,
finite logits), quaternion components in steps of 1/128 (+1 becomes 127/128). Positions and
scales keep float32. A zero quaternion (a Gaussian clrf culls) is written as zero and read
back as zero. The reader returns the rotation bytes as decoded, (b - 128) / 128, not
renormalised (clrf normalises quaternions itself).

>>> write_antimatter("scene.splat", means, log_scales, quats, opacity_logits, sh)
>>> read_antimatter("scene.splat")   # read_splat_ply's dict, sh [n, 1, 3]
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

from ..runtime.atomicfile import write_bytes
from .ply import SplatFileError, file_bytes, splat_arrays

SH_C0 = 0.28209479177387814        # the degree-0 SH basis constant
RECORD = np.dtype([("position", "<f4", 3), ("scale", "<f4", 3), ("rgba", "u1", 4),
                   ("rotation", "u1", 4)])
assert RECORD.itemsize == 32
ALPHA_EDGE = 0.5 / 255             # opacities read at least this far from 0 and 1
FIX = "export it again with `clrf export --splats FILE.splat`, or pass a .ply or .spz"


def _sigmoid(x):
    return 0.5 * (1.0 + np.tanh(0.5 * x))


def size_order(log_scales, opacity_logits) -> np.ndarray:
    """[n] indices of the Gaussians by size times opacity, largest first (ties in index
    order): the order the file keeps, compared in log space so that nothing overflows."""
    s = np.asarray(log_scales, np.float64).reshape(-1, 3).sum(1)
    key = s - np.logaddexp(0.0, -np.asarray(opacity_logits, np.float64).reshape(-1))
    return np.argsort(-key, kind="stable")


def records(a: dict) -> np.ndarray:
    """The [n] RECORD array of splat_arrays ``a``, in file order (size_order)."""
    order = size_order(a["log_scales"], a["opacity_logits"])
    n = len(order)
    r = np.zeros(n, RECORD)
    r["position"] = a["means"][order]
    r["scale"] = np.exp(a["log_scales"][order])
    rgb = 255.0 * (0.5 + SH_C0 * a["sh"][order, 0])
    alpha = 255.0 * _sigmoid(a["opacity_logits"][order])
    r["rgba"] = np.clip(np.round(np.concatenate([rgb, alpha[:, None]], 1)), 0, 255)
    q = a["quats"][order]
    norm = np.linalg.norm(q, axis=1, keepdims=True)
    q = np.where(norm > 0, q / np.where(norm > 0, norm, 1), 0.0)
    r["rotation"] = np.clip(np.round(128.0 * q + 128.0), 0, 255)
    return r


def write_antimatter(path, means, log_scales, quats, opacity_logits, sh) -> int:
    """Write n splats to ``path`` as a .splat file, atomically: means [n, 3], log_scales
    [n, 3], quats [n, 4] (w, x, y, z), opacity_logits [n], sh [n, B, 3] (only the DC
    coefficient, sh[:, 0], is kept). Returns n."""
    a = splat_arrays(means, log_scales, quats, opacity_logits, sh)
    r = records(a)
    write_bytes(path, r.tobytes())
    return len(r)


def read_antimatter(path) -> dict:
    """The splats of .splat file ``path`` in file order: read_splat_ply's dict (means,
    log_scales, quats (w, x, y, z, as decoded), opacity_logits, sh [n, 1, 3], names: the
    record's fields). A size that is not a whole number of records, a non-finite value or a
    scale that is not positive raises SplatFileError naming the file and the Gaussian."""
    path = Path(path)
    data = file_bytes(path, "a .splat file")
    if len(data) % RECORD.itemsize:
        raise SplatFileError(f"{path}: cut short or not a .splat file: {len(data)} bytes is "
                             f"not a whole number of {RECORD.itemsize}-byte Gaussians "
                             f"({len(data) // RECORD.itemsize} and {len(data) % RECORD.itemsize}"
                             f" bytes over); {FIX}")
    r = np.frombuffer(data, RECORD)
    for field in ("position", "scale"):
        bad = np.flatnonzero(~np.all(np.isfinite(r[field]), 1))
        if bad.size:
            raise SplatFileError(f"{path}: the {field} of Gaussian {int(bad[0])} is "
                                 f"{r[field][bad[0]].tolist()} ({bad.size} such Gaussians): "
                                 f"every value must be finite; {FIX}")
    bad = np.flatnonzero(~np.all(r["scale"] > 0, 1))
    if bad.size:
        raise SplatFileError(f"{path}: the scale of Gaussian {int(bad[0])} is "
                             f"{r['scale'][bad[0]].tolist()} ({bad.size} such Gaussians): "
                             f"scales must be positive; {FIX}")
    rgba = r["rgba"].astype(np.float64) / 255.0
    alpha = np.clip(rgba[:, 3], ALPHA_EDGE, 1.0 - ALPHA_EDGE)
    f32 = np.float32
    return {"means": np.array(r["position"], f32),
            "log_scales": np.log(r["scale"].astype(np.float64)).astype(f32),
            "quats": ((r["rotation"].astype(np.float64) - 128.0) / 128.0).astype(f32),
            "opacity_logits": np.log(alpha / (1.0 - alpha)).astype(f32),
            "sh": ((rgba[:, None, :3] - 0.5) / SH_C0).astype(f32),
            "names": list(RECORD.names)}
