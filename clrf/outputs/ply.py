"""Binary little-endian PLY files: coloured vertices and optional triangles.

A PLY file is an ASCII header followed by packed records, so numpy structured arrays write it
directly (one ``tobytes`` per element); that keeps a dependency out of the install for ~40 lines.
Layout: vertex ``x y z`` float32, ``red green blue`` uint8; face ``vertex_indices`` as a list
with a uchar count and int32 indices (the common layout of mesh tools).

>>> write_ply("mesh.ply", verts, colors, faces)  # [V,3] float, [V,3] uint8, [F,3] int
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

from ..runtime.atomicfile import atomic_path

VERTEX = np.dtype([("x", "<f4"), ("y", "<f4"), ("z", "<f4"),
                   ("red", "u1"), ("green", "u1"), ("blue", "u1")])
FACE = np.dtype([("n", "u1"), ("v", "<i4", (3,))])


def write_ply(path, verts, colors, faces=None):
    """Write vertices [V, 3] (float), colours [V, 3] (uint8) and optional triangles [F, 3]
    (vertex indices) to ``path`` atomically (temporary file, then rename)."""
    verts = np.asarray(verts, np.float32).reshape(-1, 3)
    colors = np.asarray(colors, np.uint8).reshape(-1, 3)
    if colors.shape[0] != verts.shape[0]:
        raise ValueError(f"colors: {colors.shape[0]} rows for {verts.shape[0]} vertices")
    v = np.empty(len(verts), VERTEX)
    v["x"], v["y"], v["z"] = verts.T
    v["red"], v["green"], v["blue"] = colors.T
    header = ["ply", "format binary_little_endian 1.0", "comment written by clrf",
              f"element vertex {len(v)}", "property float x", "property float y",
              "property float z", "property uchar red", "property uchar green",
              "property uchar blue"]
    f = None
    if faces is not None:
        faces = np.asarray(faces, np.int64).reshape(-1, 3)
        f = np.empty(len(faces), FACE)
        f["n"] = 3
        f["v"] = faces
        header += [f"element face {len(f)}", "property list uchar int vertex_indices"]
    header.append("end_header")
    path = Path(path)
    with atomic_path(path) as tmp, open(tmp, "wb") as fh:
        fh.write(("\n".join(header) + "\n").encode("ascii"))
        fh.write(v.tobytes())
        if f is not None:
            fh.write(f.tobytes())


def read_ply(path) -> dict:
    """Read a file written by :func:`write_ply`: verts [V,3] float32, colors [V,3] uint8,
    faces [F,3] int32 (empty without a face element)."""
    data = Path(path).read_bytes()
    end = data.index(b"end_header\n") + len(b"end_header\n")
    counts = {}
    for line in data[:end].decode("ascii").splitlines():
        parts = line.split()
        if parts[:1] == ["element"]:
            counts[parts[1]] = int(parts[2])
    nv, nf = counts.get("vertex", 0), counts.get("face", 0)
    v = np.frombuffer(data, VERTEX, nv, end)
    f = np.frombuffer(data, FACE, nf, end + nv * VERTEX.itemsize)
    return {"verts": np.stack([v["x"], v["y"], v["z"]], -1),
            "colors": np.stack([v["red"], v["green"], v["blue"]], -1),
            "faces": f["v"].astype(np.int32).reshape(-1, 3)}
