"""The published evaluation protocols: which views, at which resolution, on which background.

- ``blender``: NeRF's synthetic scenes, the test split (200 views) at 800 x 800, RGBA
  composited on white.
- ``llff``: forward-facing LLFF captures, every 8th view held out (i % 8 == 0, NeRF's
  llffhold), at 1/4 of the 4032 x 3024 captures, i.e. 1008 x 756 (NeRF's, Plenoxels' tables).
- ``mipnerf360``: unbounded captures, every 8th view held out, outdoor scenes at 1/4 and
  indoor scenes at 1/2 of the captured resolution (mip-NeRF 360's images_4 / images_2). Indoor
  or outdoor comes from the scene's name (INDOOR_360 / OUTDOOR_360) or ``scene_type``.

The captured resolution of LLFF-layout scenes is the (H, W) column of poses_bounds.npy. Data
that cannot give the protocol's resolution is refused with a message saying what is missing;
``allow_downscaled=True`` evaluates the same views at the data's own resolution instead and
the result says it is NOT the protocol (``standard`` False, ``note``).
"""
from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from . import detect_layout
from .base import Dataset, DataError
from .io import IMAGE_EXTS, image_header

PROTOCOLS = {
    "blender": "NeRF synthetic: the test split at 800x800, RGBA composited on white",
    "llff": "LLFF: every 8th view held out (i % 8 == 0), at 1/4 of the 4032x3024 captures "
            "(1008x756)",
    "mipnerf360": "mip-NeRF 360: every 8th view held out (i % 8 == 0), outdoor scenes at 1/4 "
                  "and indoor scenes at 1/2 of the captured resolution",
}
BLENDER_HW = (800, 800)
HOLDOUT = 8
LLFF_FACTOR = 4
M360_FACTOR = {"outdoor": 4, "indoor": 2}
INDOOR_360 = ("bonsai", "counter", "kitchen", "room")
OUTDOOR_360 = ("bicycle", "garden", "stump", "flowers", "treehill")
SIZE_TOL = 1   # pixels: images_N of odd-sized captures are rounded either way


class ProtocolError(DataError):
    """The data cannot be evaluated under the protocol; the message says what is missing."""


@dataclass
class ProtocolData:
    """The held-out views of a scene, loaded for one protocol."""

    protocol: str
    dataset: Dataset              # only the evaluated views, at the evaluated resolution
    views: np.ndarray             # indices into dataset.images
    protocol_hw: tuple            # (H, W) the protocol asks for
    standard: bool                # True: evaluated as published; False: at the data's resolution
    note: str = ""
    background: tuple | None = None   # render background the protocol fixes (blender: white)
    detail: dict = field(default_factory=dict)

    @property
    def hw(self):
        return tuple(int(x) for x in self.dataset.hw)


def scene_type_of(root: Path, scene_type=None) -> str:
    """'indoor' or 'outdoor' for a mip-NeRF 360 scene: ``scene_type`` if given, else its folder
    name (or the part before the first '_' / '-': bonsai_800 -> bonsai)."""
    if scene_type is not None:
        if scene_type not in M360_FACTOR:
            raise ProtocolError(f"--scene-type: expected 'indoor' or 'outdoor', got "
                                f"{scene_type!r}")
        return scene_type
    name = root.name.lower()
    for n in (name, name.split("_")[0], name.split("-")[0]):
        if n in INDOOR_360:
            return "indoor"
        if n in OUTDOOR_360:
            return "outdoor"
    raise ProtocolError(f"{root}: the mipnerf360 protocol evaluates indoor scenes at 1/2 and "
                        f"outdoor scenes at 1/4, and '{root.name}' is not one of the published "
                        f"scenes (indoor: {', '.join(INDOOR_360)}; outdoor: "
                        f"{', '.join(OUTDOOR_360)}); pass --scene-type indoor or outdoor")


def _close(hw, want):
    return all(abs(int(a) - int(b)) <= SIZE_TOL for a, b in zip(hw, want))


def _first_image_hw(folder: Path):
    files = sorted(f for f in folder.iterdir() if f.suffix in IMAGE_EXTS)
    if not files:
        return None
    w, h, _ = image_header(files[0])
    return h, w


def _prepare_blender(root, allow_downscaled):
    from .blender import load_blender
    ds = load_blender(root, splits=("test",), background="white")
    hw = tuple(int(x) for x in ds.hw)
    pd = ProtocolData("blender", ds, np.asarray(ds.split["test"]), BLENDER_HW, True,
                      background=(1.0, 1.0, 1.0))
    if hw != BLENDER_HW:
        if not allow_downscaled:
            raise ProtocolError(
                f"{root}: the test images are {hw[1]}x{hw[0]}, and the blender protocol "
                f"evaluates at {BLENDER_HW[1]}x{BLENDER_HW[0]} (the original nerf_synthetic "
                f"scenes); point --data at the full-resolution scene, or pass "
                f"--allow-downscaled to evaluate at {hw[1]}x{hw[0]} (then NOT the protocol)")
        pd.standard = False
        pd.note = (f"NOT the blender protocol: evaluated at the data's {hw[1]}x{hw[0]}, not "
                   f"{BLENDER_HW[1]}x{BLENDER_HW[0]}")
    return pd


def _llff_source(root, factor, captured):
    """How load_llff reaches 1/factor of the capture: ('images_F', hw), ('images', hw) or the
    reason it cannot (a string)."""
    want = (round(captured[0] / factor), round(captured[1] / factor))
    sub = root / f"images_{factor}"
    found = []
    if sub.is_dir():
        hw = _first_image_hw(sub)
        if hw is not None and _close(hw, want):
            return None
        found.append(f"images_{factor}/ is {hw[1]}x{hw[0]}" if hw else
                     f"images_{factor}/ has no images")
    full = root / "images"
    if full.is_dir():
        hw = _first_image_hw(full)
        if hw is not None and _close(hw, captured) and not sub.is_dir():
            return None
        if hw is not None:
            found.append(f"images/ is {hw[1]}x{hw[0]}")
    for d in sorted(root.glob("images_*")):
        if d.is_dir() and d != sub and (hw := _first_image_hw(d)):
            found.append(f"{d.name}/ is {hw[1]}x{hw[0]}")
    return (f"needs images_{factor}/ at {want[1]}x{want[0]} (1/{factor} of the "
            f"{captured[1]}x{captured[0]} capture in poses_bounds.npy) or the full-resolution "
            f"images/ at {captured[1]}x{captured[0]}; found "
            f"{'; '.join(found) if found else 'neither'}")


def _capture_kind(pb, path):
    """'forward_facing' or 'real360' for poses_bounds rows, as load_llff(kind="auto") decides."""
    from .llff import normalize_capture
    n = pb.shape[0]
    p35 = pb[:, :15].reshape(n, 3, 5).astype(np.float64)
    poses = np.tile(np.eye(4), (n, 1, 1))
    poses[:, :3, :4] = np.concatenate([p35[:, :, 1:2], -p35[:, :, 0:1], p35[:, :, 2:4]], -1)
    return normalize_capture(poses, pb[:, 15:17].astype(np.float64), "auto", path)[1]


def _prepare_llff_like(protocol, root, allow_downscaled, scene_type):
    from .llff import load_llff
    try:
        pb = np.load(root / "poses_bounds.npy", allow_pickle=False)
    except Exception:  # noqa: BLE001 - the loader names the problem
        pb = None
    if pb is None or pb.ndim != 2 or pb.shape[1] != 17 or not len(pb) \
            or not np.all(np.isfinite(pb)):
        load_llff(root)           # raises a DataError naming the file and the fix
    captured = (int(round(pb[0, 4])), int(round(pb[0, 9])))      # (H, W) of column 4
    detail = {}
    factor = LLFF_FACTOR
    want_kind = "forward_facing" if protocol == "llff" else "real360"
    kind = _capture_kind(pb, root / "poses_bounds.npy")
    if kind != want_kind:
        other = "mipnerf360" if protocol == "llff" else "llff"
        raise ProtocolError(f"{root}: reads as a {kind} scene, and the {protocol} protocol is "
                            f"for {want_kind} captures; use --protocol {other}")
    if protocol == "mipnerf360":
        st = scene_type_of(root, scene_type)
        factor = M360_FACTOR[st]
        detail["scene_type"] = st
    detail["factor"] = factor
    want = (round(captured[0] / factor), round(captured[1] / factor))
    why = _llff_source(root, factor, captured)
    if why is not None and not allow_downscaled:
        raise ProtocolError(f"{root}: the {protocol} protocol {why}; add them, or pass "
                            f"--allow-downscaled to evaluate at the data's resolution (then NOT "
                            f"the protocol)")
    ds = load_llff(root, downscale=factor if why is None else None, holdout=HOLDOUT,
                   only_split="test")
    pd = ProtocolData(protocol, ds, np.asarray(ds.split["test"]), want, why is None,
                      detail=detail)
    if why is not None:
        hw = pd.hw
        pd.note = (f"NOT the {protocol} protocol: evaluated at the data's {hw[1]}x{hw[0]}, not "
                   f"{want[1]}x{want[0]} (the protocol {why})")
    return pd


def prepare(protocol: str, path, allow_downscaled: bool = False, scene_type=None) -> ProtocolData:
    """Load the held-out views of the scene at ``path`` as ``protocol`` evaluates them.

    Raises ProtocolError naming what is missing (wrong layout, too small images, unknown
    indoor/outdoor) unless ``allow_downscaled`` lets a too-small resolution through, labelled."""
    if protocol not in PROTOCOLS:
        raise ProtocolError(f"--protocol: expected one of {sorted(PROTOCOLS)}, got {protocol!r}")
    if not path:
        raise ProtocolError(f"the {protocol} protocol needs the scene on disk: pass --data (the "
                            f"run's data is the built-in procedural scene)")
    layout = detect_layout(path)
    root = Path(path)
    if protocol == "blender":
        if layout != "blender":
            raise ProtocolError(f"{root}: is a {layout} dataset; the blender protocol needs the "
                                f"NeRF synthetic layout (transforms_test.json and RGBA PNGs, "
                                f"800x800)")
        return _prepare_blender(root, allow_downscaled)
    if layout != "llff":
        raise ProtocolError(f"{root}: is a {layout} dataset; the {protocol} protocol needs the "
                            f"LLFF layout (poses_bounds.npy with images/ or images_N/)")
    return _prepare_llff_like(protocol, root, allow_downscaled, scene_type)
