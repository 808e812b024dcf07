"""LLFF layout (forward-facing captures) and the Mip-NeRF 360 variant of it.

``poses_bounds.npy`` is [N, 17]: per view a 3x5 matrix flattened row-major (a 3x4
camera-to-world [R | t] whose rotation columns are LLFF's (down, right, back) axes, plus a
column (H, W, focal) of the original capture), then (near, far) depth bounds. Row i belongs to
the i-th image in sorted file-name order.

Processing (as NeRF's load_llff_data):

1. axes (down, right, back) -> OpenGL (right, up, back): columns [c1, -c0, c2];
2. focal rescaled to the loaded images: focal * W_loaded / W_original; principal point at the
   image centre;
3. forward-facing: scale translations and bounds by 1 / (0.75 min(bounds)), then recentre on
   the average camera (its pose becomes the identity). Rays go to NDC with near plane 1
   (``clrf.data.cameras.to_ndc``); ``near``, ``far`` are 0, 1 in NDC; bbox is [-1, 1] in NDC z and
   in x, y the extent of every view's frustum (``scene_extent``), ~1.3-1.5 on fern. The
   rescaled bounds stay with the dataset (``depth_bounds``): models that need world-space
   cameras (the splat model) take the capture without NDC (``clrf.data.world``);
4. real 360 (Mip-NeRF 360): the bounds are not used (bonsai's are placeholders); the world is
   re-centred on the focus point (the point closest to all optical axes) with z along the mean
   camera up, and scaled so the farthest camera is at distance 1. bbox = [-1, 1]^3, the cube
   enclosing the sphere through the farthest camera; near 0.02, far = its diagonal. The
   voxel grid fills that box (the central region, as svox2's unit cube) and the real360
   preset's MSI background (clrf/grid/background.py) starts at the box's circumscribed
   sphere, radius sqrt(3), so the room beyond the cameras lives in the background.

Every ``holdout``-th view (0, 8, 16, ...) is the test split (NeRF's llffhold = 8).
"""
from __future__ import annotations

import re
from pathlib import Path

import numpy as np

from .cameras import average_pose, ndc_extent
from .base import Dataset, DataError
from .io import (IMAGE_EXTS, check_downscale, check_poses, check_splits, holdout_split,
                 inside, limit_split, load_images, parse_background, require_dir, require_file,
                 warn)

BD_FACTOR = 0.75          # NeRF: scale so the nearest bound becomes 1 / 0.75 (NDC near plane 1)
NDC_BOX_MARGIN = 1.01     # forward-facing box: the views' NDC extent in x, y times this
FACING_THRESHOLD = 0.7    # |mean viewing axis| above this: forward-facing (all cameras alike)
ASPECT_TOL = 0.02         # images may be cropped by a pixel when resized; more means a mismatch
FOCUS_COND_MAX = 1e8     # condition number beyond which the optical axes count as parallel
REAL360_NEAR = 0.02       # in units of the farthest camera's distance


def _image_folder(root: Path, factor):
    """(folder, extra box-downscale factor to apply to its images)."""
    if factor is not None:
        if (root / f"images_{factor}").is_dir():
            return root / f"images_{factor}", 1
        if (root / "images").is_dir():
            return root / "images", factor
        raise DataError(f"{root}: neither images_{factor}/ nor images/ exists; add one of them")
    if (root / "images").is_dir():
        return root / "images", 1
    found = sorted((int(m.group(1)), d) for d in root.iterdir()
                   if d.is_dir() and (m := re.fullmatch(r"images_(\d+)", d.name)))
    if not found:
        raise DataError(f"{root}: no images/ or images_<factor>/ folder; add the images")
    return found[0][1], 1


def _focus_point(origins, axes, path):
    """The least-squares point closest to all lines origin + s * axis (axes unit)."""
    a = np.eye(3) - axes[:, :, None] * axes[:, None, :]          # projectors orthogonal to axes
    m = a.sum(0)
    if np.linalg.cond(m) > FOCUS_COND_MAX:
        raise DataError(f"{path}: the cameras' optical axes are (nearly) parallel, so they have no "
                        f"focus point for a 360 scene; pass kind='forward_facing'")
    return np.linalg.solve(m, np.einsum("nij,nj->i", a, origins))


def _recentre_360(poses, path):
    """Rigidly move and uniformly scale the world: focus point at the origin, mean up along +z,
    farthest camera at distance 1."""
    focus = _focus_point(poses[:, :3, 3], -poses[:, :3, 2], path)
    z = poses[:, :3, 1].mean(0)
    z /= np.linalg.norm(z)
    x0 = poses[0, :3, 0] - z * (poses[0, :3, 0] @ z)
    x = x0 / np.linalg.norm(x0)
    y = np.cross(z, x)
    world = np.stack([x, y, z])                                   # rows: new axes in old coords
    out = poses.copy()
    out[:, :3, :3] = world @ poses[:, :3, :3]
    out[:, :3, 3] = (poses[:, :3, 3] - focus) @ world.T
    out[:, :3, 3] /= np.linalg.norm(out[:, :3, 3], axis=-1).max()
    return out


def normalize_capture(poses, bounds, kind, path, bounds_name="bounds (columns 15, 16)"):
    """Steps 3-4 above on OpenGL camera-to-world ``poses`` [N, 4, 4] with per-view depth
    ``bounds`` [N, 2] (near, far): returns (normalised poses, kind), deciding kind when "auto"
    (real360 when the cameras' mean viewing axis is shorter than FACING_THRESHOLD).
    ``bounds_name`` names where the bounds come from in error messages."""
    poses = np.array(poses, np.float64)
    if kind == "auto":
        spread = np.linalg.norm(poses[:, :3, 2].mean(0))
        kind = "real360" if spread < FACING_THRESHOLD else "forward_facing"
    if len(poses) > 1 and np.all(bounds == bounds[0]) and kind == "forward_facing":
        warn(f"{path}: the {bounds_name} are constant ({bounds[0].tolist()}); they look like "
             f"placeholders but are used for the forward-facing rescale")
    if kind == "forward_facing":
        if not np.all(bounds > 0):
            raise DataError(f"{path}: {bounds_name} must be positive for a forward-facing "
                            f"scene; regenerate them or pass kind='real360'")
        poses[:, :3, 3] *= forward_facing_scale(bounds)
        poses = np.linalg.inv(average_pose(poses)) @ poses
        poses[:, 3] = [0.0, 0.0, 0.0, 1.0]
    else:
        poses = _recentre_360(poses, path)
    return poses, kind


def forward_facing_scale(bounds) -> float:
    """Step 3's scale of a forward-facing capture with depth ``bounds`` [N, 2]: the nearest
    bound becomes 1 / BD_FACTOR."""
    return 1.0 / (float(np.min(bounds)) * BD_FACTOR)


def depth_bounds(kind, bounds, keep):
    """The Dataset's ``depth_bounds`` [len(keep), 2] of the kept views: a forward-facing
    capture's bounds in the units of its normalised poses; None for a 360 capture (whose
    bounds are not used)."""
    if kind != "forward_facing":
        return None
    b = np.asarray(bounds, np.float64)
    return b[keep] * forward_facing_scale(b)


def scene_extent(kind, poses, intrinsics, hw, distortion=None) -> dict:
    """Dataset fields (bbox, near, far, ndc, preset) of a normalised LLFF-style scene.

    Forward-facing: the NDC box is [-1, 1] in z and, in x and y, wide enough for every view's
    frustum (``clrf.data.cameras.ndc_extent`` of all ``poses``, test views included, plus
    NDC_BOX_MARGIN), never narrower than [-1, 1]: the cube itself holds only the average
    camera's frustum, and rays leaving the box sideways could not be fitted."""
    if kind == "forward_facing":
        ex, ey = ndc_extent(poses, intrinsics, hw[0], hw[1], distortion)
        ex, ey = max(1.0, ex * NDC_BOX_MARGIN), max(1.0, ey * NDC_BOX_MARGIN)
        return dict(bbox=np.array([[-ex, -ey, -1.0], [ex, ey, 1.0]]), near=0.0, far=1.0,
                    ndc=True, preset="forward_facing")
    return dict(bbox=np.array([[-1.0] * 3, [1.0] * 3]), near=REAL360_NEAR,
                far=2.0 * np.sqrt(3.0), ndc=False, preset="real360")


def load_llff(path, kind="auto", downscale=None, holdout=8, max_images=None,
              background="white", only_split=None) -> Dataset:
    """Load an LLFF / Mip-NeRF 360 folder (poses_bounds.npy + images).

    kind: "forward_facing", "real360" or "auto" (real360 when the cameras' mean viewing axis is
    shorter than FACING_THRESHOLD, i.e. they look in many directions: fern 0.99, bonsai 0.50).
    downscale: None -> images/ at full size if present, else the images_<k>/ with the smallest k;
    d -> images_<d>/ if present, else images/ box-downscaled by d.
    holdout: every holdout-th view is test. max_images: first this-many views of each split.
    background: only used to composite RGBA images.
    only_split: "train" or "test" to read only that split's images (the others' views are
    dropped; the poses are normalised over all views as usual).
    """
    root = require_dir(path, "LLFF scene", "pass the folder holding poses_bounds.npy")
    pb_path = require_file(root / "poses_bounds.npy", "LLFF poses file",
                           "generate it with LLFF's imgs2poses.py")
    factor = check_downscale(downscale) if downscale is not None else None
    if kind not in ("auto", "forward_facing", "real360"):
        raise DataError(f"kind: expected 'auto', 'forward_facing' or 'real360', got {kind!r}")
    try:
        arr = np.load(pb_path, allow_pickle=False)
    except Exception as e:  # noqa: BLE001 - any numpy read failure means an unusable file
        raise DataError(f"{pb_path}: unreadable ({type(e).__name__}: {e}); regenerate it") from None
    if arr.ndim != 2 or arr.shape[1] != 17 or arr.shape[0] == 0:
        raise DataError(f"{pb_path}: expected shape (N, 17) (3x5 pose + 2 bounds per view), got "
                        f"{arr.shape}")
    if not np.all(np.isfinite(arr)):
        raise DataError(f"{pb_path}: contains NaN or Inf; regenerate it")
    n = arr.shape[0]
    p35 = arr[:, :15].reshape(n, 3, 5).astype(np.float64)
    hwf = p35[0, :, 4]
    if not np.all(hwf > 0):
        raise DataError(f"{pb_path}: column 4 (H, W, focal) of row 0 must be positive, got "
                        f"{hwf.tolist()}; regenerate the file with LLFF's imgs2poses.py")
    bounds = arr[:, 15:17].astype(np.float64)
    poses = np.tile(np.eye(4), (n, 1, 1))
    poses[:, :3, :4] = np.concatenate([p35[:, :, 1:2], -p35[:, :, 0:1], p35[:, :, 2:4]], -1)
    check_poses(poses, pb_path, "row {} (3x4 pose part)")

    folder, extra = _image_folder(root, factor)
    files = [inside(root, str(f.relative_to(root)), folder, f.name)
             for f in sorted(folder.iterdir()) if f.suffix in IMAGE_EXTS]
    if len(files) != n:
        raise DataError(f"{folder}: {len(files)} images but {pb_path.name} has {n} rows; one "
                        f"image per pose row is required (remove extra images or re-run COLMAP)")

    poses, kind = normalize_capture(poses, bounds, kind, pb_path)

    split = holdout_split(n, holdout)
    check_splits(split, pb_path, f"use a holdout between 2 and {n}")
    keep, split = limit_split(split, max_images)
    check_splits(split, pb_path, "pass max_images >= 1")
    if only_split is not None:
        if only_split not in split:
            raise DataError(f"only_split: expected one of {sorted(split)}, got {only_split!r}")
        keep, split = keep[split[only_split]], {only_split: np.arange(len(split[only_split]))}
    bg = parse_background(background)
    images, _, (H0, W0) = load_images([files[i] for i in keep], downscale=extra, background=bg)
    if abs((H0 / W0) / (hwf[0] / hwf[1]) - 1.0) > ASPECT_TOL:
        raise DataError(f"{folder}: images are {W0}x{H0} (WxH) but {pb_path.name} says "
                        f"{hwf[1]:.0f}x{hwf[0]:.0f}; the aspect ratios differ, so these are not "
                        f"the images the poses were computed for: use those (or re-run COLMAP)")
    focal = hwf[2] * W0 / hwf[1] / extra
    intr = np.array([focal, focal, W0 / 2.0 / extra, H0 / 2.0 / extra])
    poses = poses[keep].astype(np.float32)
    return Dataset(name=root.name, images=images, poses=poses, intrinsics=intr, split=split,
                   background=bg, depth_bounds=depth_bounds(kind, bounds, keep),
                   **scene_extent(kind, poses, intr, images.shape[1:3]))
