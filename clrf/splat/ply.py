"""Gaussian splats as the PLY file the 3D Gaussian Splatting tools read and write.

One ``vertex`` element, binary little endian, every property float32, in this order:
``x y z`` (mean), ``nx ny nz`` (zeros, unused), ``f_dc_0..2`` (the degree-0 SH coefficient of
R, G, B), ``f_rest_0..`` (the higher coefficients, channel-major: every coefficient of R, then
of G, then of B), ``opacity`` (the logit), ``scale_0..2`` (log scales), ``rot_0..3`` (the
quaternion w, x, y, z, not necessarily normalised). clrf/outputs/ply.py writes uint8 colours
only, so the splats have their own writer (numpy structured arrays, one ``tobytes``).

>>> write_splat_ply("scene.ply", means, log_scales, quats, opacity_logits, sh)   # sh [n, B, 3]
>>> read_splat_ply("scene.ply")   # the same arrays back
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

from ..interface import InputFileError
from ..runtime.atomicfile import atomic_path


def property_names(n_basis: int) -> list:
    """The vertex properties, in file order, of splats with ``n_basis`` SH coefficients."""
    rest = 3 * (n_basis - 1)
    return (["x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2"]
            + [f"f_rest_{i}" for i in range(rest)]
            + ["opacity", "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3"])


def write_splat_ply(path, means, log_scales, quats, opacity_logits, sh):
    """Write n splats to ``path`` atomically (a temporary file beside it, then a rename):
    means [n, 3], log_scales [n, 3], quats [n, 4] (w, x, y, z), opacity_logits [n],
    sh [n, B, 3] (basis, channel; B = (degree + 1)^2). Returns the number written."""
    means = np.asarray(means, np.float32).reshape(-1, 3)
    n = means.shape[0]
    sh = np.asarray(sh, np.float32)
    if sh.ndim != 3 or sh.shape[0] != n or sh.shape[2] != 3 or sh.shape[1] not in (1, 4, 9, 16):
        raise ValueError(f"sh: expected [{n}, 1|4|9|16, 3], got {sh.shape}")
    names = property_names(sh.shape[1])
    v = np.zeros(n, np.dtype([(k, "<f4") for k in names]))
    v["x"], v["y"], v["z"] = means.T
    for c in range(3):
        v[f"f_dc_{c}"] = sh[:, 0, c]
    # channel-major: f_rest_{c * (B - 1) + (b - 1)} is basis b of channel c
    rest = np.transpose(sh[:, 1:, :], (0, 2, 1)).reshape(n, 3 * (sh.shape[1] - 1))
    for i in range(rest.shape[1]):
        v[f"f_rest_{i}"] = rest[:, i]
    v["opacity"] = np.asarray(opacity_logits, np.float32).reshape(n)
    s = np.asarray(log_scales, np.float32).reshape(n, 3)
    q = np.asarray(quats, np.float32).reshape(n, 4)
    for k in range(3):
        v[f"scale_{k}"] = s[:, k]
    for k in range(4):
        v[f"rot_{k}"] = q[:, k]
    header = ["ply", "format binary_little_endian 1.0", f"element vertex {n}"]
    header += [f"property float {k}" for k in names]
    header.append("end_header")
    path = Path(path)
    with atomic_path(path) as tmp, open(tmp, "wb") as fh:
        fh.write(("\n".join(header) + "\n").encode("ascii"))
        fh.write(v.tobytes())
    return n


REQUIRED = ["x", "y", "z", "f_dc_0", "f_dc_1", "f_dc_2", "opacity", "scale_0", "scale_1",
            "scale_2", "rot_0", "rot_1", "rot_2", "rot_3"]
PLY_FIX = ("re-export it with `clrf export --splats FILE.ply`, or use the point_cloud.ply the 3D "
           "Gaussian Splatting tools write")


class SplatFileError(InputFileError):
    """A splat file (any format files.py reads) that cannot be read: the message names the
    file, what is wrong and the fix."""


def file_bytes(path, what: str) -> bytes:
    """The bytes of ``path``; an unreadable file raises SplatFileError naming it (``what``: the
    kind of file expected, for the fix)."""
    try:
        return Path(path).read_bytes()
    except OSError as e:
        raise SplatFileError(f"{path}: cannot read the splat file ({e.strerror or e}); pass "
                             f"the path of {what}") from None


def splat_arrays(means, log_scales, quats, opacity_logits, sh) -> dict:
    """The five arrays of n splats checked and as float64, for the quantising writers (SPZ,
    .splat): means [n, 3], log_scales [n, 3], quats [n, 4] (w, x, y, z), opacity_logits [n],
    sh [n, B, 3]. A wrong shape or a non-finite value raises ValueError naming the array."""
    means = np.asarray(means, np.float64).reshape(-1, 3)
    n = len(means)
    sh = np.asarray(sh, np.float64)
    if sh.ndim != 3 or sh.shape[0] != n or sh.shape[2] != 3 or sh.shape[1] not in (1, 4, 9, 16):
        raise ValueError(f"sh: expected [{n}, 1|4|9|16, 3], got {sh.shape}")
    out = {"means": means, "sh": sh}
    for k, v, shape in (("log_scales", log_scales, (n, 3)), ("quats", quats, (n, 4)),
                        ("opacity_logits", opacity_logits, (n,))):
        v = np.asarray(v, np.float64)
        if v.size != int(np.prod(shape)):
            raise ValueError(f"{k}: expected {list(shape)} values, got shape {v.shape}")
        out[k] = v.reshape(shape)
    for k, v in out.items():
        if not np.all(np.isfinite(v)):
            raise ValueError(f"{k}: {int(np.sum(~np.isfinite(v)))} values are not finite")
    return out


def read_splat_ply(path) -> dict:
    """The arrays of a splat PLY (float32 vertex properties in any order, as
    :func:`write_splat_ply` and the 3DGS tools write them): means, log_scales, quats,
    opacity_logits, sh [n, B, 3], and ``names`` (the properties in file order). Other float
    properties (normals) are ignored; a missing property, another format or property type, a
    truncated file, a non-square number of SH coefficients or a non-finite value raise
    SplatFileError naming the file and the property."""
    path = Path(path)
    data = file_bytes(path, "a splat PLY")
    if not data.startswith(b"ply\n") or b"end_header\n" not in data[:1 << 16]:
        raise SplatFileError(f"{path}: not a PLY file (no 'ply' ... 'end_header' header); "
                             f"{PLY_FIX}")
    end = data.index(b"end_header\n") + len(b"end_header\n")
    n, names, element = 0, [], None
    for line in data[:end].decode("ascii", "replace").splitlines():
        parts = line.split()
        if not parts or parts[0] in ("ply", "comment", "obj_info", "end_header"):
            continue
        if parts[0] == "format":
            if parts[1:2] != ["binary_little_endian"]:
                raise SplatFileError(f"{path}: format {' '.join(parts[1:])}: only "
                                     f"binary_little_endian splat files are read; {PLY_FIX}")
        elif parts[0] == "element":
            element = parts[1] if len(parts) > 1 else None
            if element != "vertex":
                raise SplatFileError(f"{path}: element {element!r}: a splat file has one "
                                     f"'vertex' element; {PLY_FIX}")
            try:
                n = int(parts[2])
            except (IndexError, ValueError):
                raise SplatFileError(f"{path}: bad line {line!r}: expected 'element vertex "
                                     f"COUNT'") from None
        elif parts[0] == "property":
            if len(parts) != 3 or parts[1] != "float":
                raise SplatFileError(f"{path}: property {parts[-1]} is "
                                     f"{' '.join(parts[1:-1])}, expected float; {PLY_FIX}")
            names.append(parts[2])
    missing = [k for k in REQUIRED if k not in names]
    if missing:
        raise SplatFileError(f"{path}: vertex properties {', '.join(missing)} missing (a splat "
                             f"needs x y z, f_dc_0..2, opacity, scale_0..2, rot_0..3); "
                             f"{PLY_FIX}")
    dtype = np.dtype([(k, "<f4") for k in names])
    if len(data) - end < n * dtype.itemsize:
        raise SplatFileError(f"{path}: truncated: {n} vertices of {dtype.itemsize} bytes need "
                             f"{n * dtype.itemsize} bytes after the header, the file has "
                             f"{len(data) - end}; {PLY_FIX}")
    v = np.frombuffer(data, dtype, n, end)
    n_rest = sum(k.startswith("f_rest_") for k in names)
    B = 1 + n_rest // 3
    if n_rest % 3 or B not in (1, 4, 9, 16):
        raise SplatFileError(f"{path}: {n_rest} f_rest_* properties: expected 0, 9, 24 or 45 "
                             f"(SH degree 0..3); {PLY_FIX}")
    want = [f"f_rest_{i}" for i in range(n_rest)]
    gaps = [k for k in want if k not in names]
    if gaps:
        raise SplatFileError(f"{path}: vertex properties {', '.join(gaps[:5])} missing; "
                             f"{PLY_FIX}")
    for k in REQUIRED + want:
        bad = np.flatnonzero(~np.isfinite(v[k]))
        if bad.size:
            raise SplatFileError(f"{path}: property {k} of vertex {int(bad[0])} is "
                                 f"{float(v[k][bad[0]])} ({bad.size} such vertices): every "
                                 f"value must be finite; {PLY_FIX}")
    sh = np.zeros((n, B, 3), np.float32)
    for c in range(3):
        sh[:, 0, c] = v[f"f_dc_{c}"]
        for b in range(1, B):
            sh[:, b, c] = v[f"f_rest_{c * (B - 1) + b - 1}"]
    return {"means": np.stack([v["x"], v["y"], v["z"]], -1),
            "log_scales": np.stack([v[f"scale_{k}"] for k in range(3)], -1),
            "quats": np.stack([v[f"rot_{k}"] for k in range(4)], -1),
            "opacity_logits": np.array(v["opacity"]), "sh": sh, "names": names}
