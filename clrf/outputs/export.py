"""What a trained scene exports: a coloured triangle mesh and a coloured point cloud.

Mesh (``extract_mesh``): density is sampled at the centres of a regular ``reso`` grid over a box
(Plenoxels: trilinear interpolation of the sparse grid on the device, cl/export.cl; NeRF: the
density head of the fine MLP on the device), in blocks of at most ``BLOCK`` points so device
memory stays bounded. scikit-image's marching cubes extracts the ``level`` isosurface of that
volume, padded with one empty cell per side so the surface closes at the box. Vertex colours
are the view-independent colour: the SH degree-0 band (the direction-averaged colour) for a
grid, the colour head looking at the vertex along its inward normal for NeRF.

Default level: ``ln 2 / h`` with ``h`` the model's own sampling length (the grid's voxel edge;
NeRF's mean spacing ``(far - near) / (n_coarse + n_fine)`` of its render samples), i.e. the
density at which one of the renderer's steps absorbs half the light: the surface is where the
model's rendering turns opaque.

Point cloud (``point_cloud``): each ray's expected termination point
``o + (sum_k w_k t_k / sum_k w_k) d/|d|`` (opacity-weighted mean depth, w the rendering weights),
kept where the accumulated opacity ``sum_k w_k`` reaches ``min_opacity``; its colour is the
rendered colour with the background removed, ``(rgb - (1 - acc) bg) / acc``.

NDC scenes (forward-facing, ``ndc`` in the checkpoint) live in normalised device coordinates:
both exports are computed there and mapped back to world space with :func:`ndc_to_world`.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import pyopencl.array as cla

from ..runtime.programs import launch, upload

BLOCK = 1 << 20          # points per device evaluation (12 MB of coordinates)
NDC_MAX_DEPTH = 0.99     # NDC z' beyond this (world depth > 200 x near) is "at infinity": dropped


class ExportError(ValueError):
    pass


@dataclass
class Mesh:
    verts: np.ndarray    # [V, 3] float32, world space
    faces: np.ndarray    # [F, 3] int32 vertex indices
    colors: np.ndarray   # [V, 3] uint8
    level: float         # the isosurface density


# ---- fields at points ---------------------------------------------------------------------------
def sample_fields(model, points, dirs=None, block=BLOCK, progress=None):
    """Density sigma [n] and view-independent colour rgb [n, 3] (float32) at points [n, 3].

    The model's ``export_fields`` (clrf/interface.py): a voxel grid's raw interpolated density
    and the constant term of its colour; a network's fields looking along ``dirs`` [n, 3]
    (unit; default -z, which does not change sigma) where the model is ``view_dependent``.
    Points go to the device in blocks of at most ``model.export_block(block)`` (a network keeps
    its activations: bounded as its render bounds them); ``progress`` (optional) is called with
    the number of points done after each block.
    """
    p = np.ascontiguousarray(np.asarray(points, np.float32).reshape(-1, 3))
    n = p.shape[0]
    sigma = np.empty(n, np.float32)
    rgb = np.empty((n, 3), np.float32)
    q = model.device.queue
    block = model.export_block(block)
    for s in range(0, n, block):
        e = min(n, s + block)
        pd = upload(q, p[s:e])
        dd = None
        if model.view_dependent:
            d = (np.tile(np.float32([0, 0, -1]), (e - s, 1)) if dirs is None
                 else np.ascontiguousarray(dirs[s:e], np.float32))
            dd = upload(q, d)
        sd, cd = model.export_fields(pd, dd)
        sigma[s:e], rgb[s:e] = sd.get(), cd.get()
        if progress:
            progress(e - s)
    return sigma, rgb


# ---- mesh ---------------------------------------------------------------------------------------
def model_cell(model) -> float:
    """The model's own sampling length h (model units) that sets the default level."""
    return float(model.sample_length)


def default_level(model) -> float:
    """ln 2 / h: the density at which one step of the model's renderer absorbs half the light."""
    return math.log(2.0) / model_cell(model)


def default_reso(model, bbox) -> tuple:
    """The model's own resolution over ``bbox`` where it has one (a voxel grid over its own
    box); else 256 cells along the longest side of the box, proportionally fewer along the
    others."""
    bbox = np.asarray(bbox, np.float64)
    own = model.native_reso(bbox)
    if own is not None:
        return tuple(own)
    ext = bbox[1] - bbox[0]
    return tuple(int(max(2, round(256 * e / ext.max()))) for e in ext)


def density_volume(model, bbox, reso, progress=None):
    """sigma [X, Y, Z] (float32; raw for grids, see sample_fields) at the cell centres
    bbox[0] + (i + 1/2) h of a ``reso`` grid over ``bbox``, h = (bbox[1] - bbox[0]) / reso,
    evaluated in blocks of whole x-slabs (at most BLOCK points each)."""
    bbox = np.asarray(bbox, np.float64)
    X, Y, Z = (int(r) for r in reso)
    h = (bbox[1] - bbox[0]) / np.array([X, Y, Z])
    ys = bbox[0, 1] + (np.arange(Y) + 0.5) * h[1]
    zs = bbox[0, 2] + (np.arange(Z) + 0.5) * h[2]
    yy, zz = np.meshgrid(ys, zs, indexing="ij")
    slab = np.stack([np.zeros(Y * Z), yy.ravel(), zz.ravel()], -1)
    per = max(1, BLOCK // (Y * Z))
    vol = np.empty((X, Y, Z), np.float32)
    for x0 in range(0, X, per):
        x1 = min(X, x0 + per)
        xs = bbox[0, 0] + (np.arange(x0, x1) + 0.5) * h[0]
        pts = np.tile(slab, (x1 - x0, 1))
        pts[:, 0] = np.repeat(xs, Y * Z)
        vol[x0:x1] = sample_fields(model, pts)[0].reshape(x1 - x0, Y, Z)
        if progress:
            progress(x1 - x0)
    return vol


def extract_mesh(model, bbox, reso=None, level=None, ndc=None, progress=None) -> Mesh:
    """Marching-cubes mesh of the ``level`` density isosurface inside ``bbox`` (model space).

    reso: cells per axis (default :func:`default_reso`); level: default :func:`default_level`;
    ndc: None, or (intrinsics, H, W) of an NDC scene, whose vertices are then mapped to world
    space (faces at NDC depth >= NDC_MAX_DEPTH are dropped). ``progress(k)``: k x-slabs done.
    Raises ExportError when the volume has no crossing of ``level``.
    """
    from skimage.measure import marching_cubes

    bbox = np.asarray(bbox, np.float64)
    reso = tuple(reso) if reso is not None else default_reso(model, bbox)
    level = float(level) if level is not None else default_level(model)
    vol = density_volume(model, bbox, reso, progress)
    vmax = float(vol.max(initial=0.0))
    if not (0.0 < level < vmax):
        raise ExportError(f"--level {level:.4g}: the density in the box ranges over [0, "
                          f"{vmax:.4g}], so there is no surface; pass a --level inside that range")
    h = (bbox[1] - bbox[0]) / np.array(reso)
    padded = np.pad(vol, 1)                      # empty border: the surface closes at the box
    verts, faces, normals, _ = marching_cubes(padded, level, spacing=tuple(h))
    verts = verts + bbox[0] + 0.5 * h - h        # cell centres, minus the one-cell pad
    faces = faces[:, ::-1]                       # counter-clockwise seen from outside
    nrm = -normals / np.maximum(np.linalg.norm(normals, axis=1, keepdims=True), 1e-12)
    # marching_cubes' normals point down the gradient (out of the dense inside): look inwards
    _, rgb = sample_fields(model, verts, dirs=nrm)
    colors = (np.clip(rgb, 0, 1) * 255 + 0.5).astype(np.uint8)
    if ndc is not None:
        faces = faces[np.all(verts[faces, 2] < NDC_MAX_DEPTH, axis=1)]
        used, faces = np.unique(faces, return_inverse=True)      # drop vertices left unused
        faces = faces.reshape(-1, 3)
        verts, colors = ndc_to_world(verts[used], *ndc), colors[used]
    return Mesh(verts.astype(np.float32), faces.astype(np.int32), colors, level)


# ---- point cloud ---------------------------------------------------------------------------------
def point_cloud(model, origins, dirs, background, min_opacity=0.5, ndc=None, chunk=1 << 15,
                progress=None):
    """Expected-termination points of rays origins, dirs [n, 3] (model space).

    Returns (points [m, 3] float32 world space, colors [m, 3] uint8) for the m <= n rays whose
    accumulated opacity is >= min_opacity (see the module docstring).
    """
    o = np.asarray(origins, np.float32)
    d = np.asarray(dirs, np.float32)
    pts, cols = [], []
    bg = np.asarray(background, np.float64)
    for s in range(0, len(o), chunk):
        e = min(len(o), s + chunk)
        r = model.render(o[s:e], d[s:e])
        acc = r["acc"].astype(np.float64)
        keep = acc >= min_opacity
        a = acc[keep][:, None]
        u = d[s:e][keep].astype(np.float64)
        u /= np.linalg.norm(u, axis=1, keepdims=True)
        pts.append(o[s:e][keep] + (r["depth"][keep, None] / a) * u)
        cols.append((r["rgb"][keep] - (1.0 - a) * bg) / a)
        if progress:
            progress(e - s)
    p = np.concatenate(pts) if pts else np.zeros((0, 3))
    c = np.concatenate(cols) if cols else np.zeros((0, 3))
    if ndc is not None:
        keep = p[:, 2] < NDC_MAX_DEPTH
        p, c = ndc_to_world(p[keep], *ndc), c[keep]
    return p.astype(np.float32), (np.clip(c, 0, 1) * 255 + 0.5).astype(np.uint8)


def ndc_to_world(p, intrinsics, H, W, near=1.0):
    """Inverse of the NDC map of clrf.data.cameras.to_ndc for points p [n, 3] (z' < 1)::

        z = 2 near / (z' - 1),  x = x' z / ax,  y = y' z / ay,  ax = -2 fx / W, ay = -2 fy / H
    """
    p = np.asarray(p, np.float64)
    fx, fy = float(intrinsics[0]), float(intrinsics[1])
    ax, ay = -2.0 * fx / W, -2.0 * fy / H
    z = 2.0 * near / (p[:, 2] - 1.0)
    return np.stack([p[:, 0] * z / ax, p[:, 1] * z / ay, z], -1)
