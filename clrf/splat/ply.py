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

import os
from pathlib import Path

import numpy as np


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
    rest = np.transpose(sh[:, 1:, :], (0, 2, 1)).reshape(n, -1)
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
    tmp = path.with_name(f".{path.name}.tmp{os.getpid()}")
    try:
        with open(tmp, "wb") as fh:
            fh.write(("\n".join(header) + "\n").encode("ascii"))
            fh.write(v.tobytes())
        os.replace(tmp, path)
    finally:
        if tmp.exists():
            tmp.unlink()
    return n


def read_splat_ply(path) -> dict:
    """The arrays of a splat PLY (float32 vertex properties in any order, as
    :func:`write_splat_ply` and the 3DGS tools write them): means, log_scales, quats,
    opacity_logits, sh [n, B, 3], and ``names`` (the properties in file order)."""
    data = Path(path).read_bytes()
    end = data.index(b"end_header\n") + len(b"end_header\n")
    n, names = 0, []
    for line in data[:end].decode("ascii").splitlines():
        parts = line.split()
        if parts[:2] == ["format", "binary_little_endian"]:
            continue
        if parts[:1] == ["format"]:
            raise ValueError(f"{path}: only binary_little_endian splat files are read")
        if parts[:1] == ["element"]:
            if parts[1] != "vertex":
                raise ValueError(f"{path}: unexpected element {parts[1]!r}")
            n = int(parts[2])
        elif parts[:1] == ["property"]:
            if parts[1] != "float":
                raise ValueError(f"{path}: property {parts[-1]} is {parts[1]}, expected float")
            names.append(parts[2])
    v = np.frombuffer(data, np.dtype([(k, "<f4") for k in names]), n, end)
    n_rest = sum(k.startswith("f_rest_") for k in names)
    B = 1 + n_rest // 3
    sh = np.zeros((n, B, 3), np.float32)
    for c in range(3):
        sh[:, 0, c] = v[f"f_dc_{c}"]
        for b in range(1, B):
            sh[:, b, c] = v[f"f_rest_{c * (B - 1) + b - 1}"]
    return {"means": np.stack([v["x"], v["y"], v["z"]], -1),
            "log_scales": np.stack([v[f"scale_{k}"] for k in range(3)], -1),
            "quats": np.stack([v[f"rot_{k}"] for k in range(4)], -1),
            "opacity_logits": np.array(v["opacity"]), "sh": sh, "names": names}
