"""Copy a Blender-layout capture with the faults of a phone capture put into its training
split, to measure what splat.exposure (and pose refinement) recover:

    python tools/perturb_capture.py $CLRF_DATA/lego_400 /tmp/lego_exposure --exposure
    python tools/perturb_capture.py $CLRF_DATA/lego_400 /tmp/lego_poses --poses

--exposure  each training image (RGB, alpha kept) times a gain drawn from [0.6, 1.5] and each
            channel times one from [0.9, 1.1], clipped to [0, 1] as a camera would;
--no-clip   (with --exposure) the same draws, every gain divided by 1.65 (the largest
            gain times the largest channel factor), so that no channel clips: what the clip
            costs, apart from the changes themselves (the scene then trains darker than the
            untouched test views, so compare scores that fit a colour transform);
--poses     each training pose turned by --degrees (1) about a random axis through the camera
            and moved by --move (1 %) of the camera's distance to the origin, in a random
            direction.
Test and validation views are copied untouched. The draws are seeded (--seed) and written to
OUT/perturbation.json, so a run can be compared with what was done to it.
"""
from __future__ import annotations

import argparse
import json
import shutil
from pathlib import Path

import imageio.v3 as iio
import numpy as np


NO_CLIP = 1.5 * 1.1    # --no-clip: the largest gain times the largest channel factor


def rotation(axis: np.ndarray, degrees: float) -> np.ndarray:
    """3 x 3 rotation by ``degrees`` about the unit vector ``axis`` (Rodrigues)."""
    a = np.radians(degrees)
    k = axis / np.linalg.norm(axis)
    K = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
    return np.eye(3) + np.sin(a) * K + (1 - np.cos(a)) * K @ K


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("src", type=Path)
    ap.add_argument("out", type=Path)
    ap.add_argument("--exposure", action="store_true")
    ap.add_argument("--no-clip", action="store_true")
    ap.add_argument("--poses", action="store_true")
    ap.add_argument("--degrees", type=float, default=1.0)
    ap.add_argument("--move", type=float, default=0.01)
    ap.add_argument("--seed", type=int, default=0)
    a = ap.parse_args(argv)
    if not (a.src / "transforms_train.json").is_file():
        ap.error(f"{a.src}: no transforms_train.json (a Blender-layout capture)")
    if a.no_clip and not a.exposure:
        ap.error("--no-clip goes with --exposure")
    if a.out.exists():
        ap.error(f"{a.out} exists; pick a new folder")
    shutil.copytree(a.src, a.out)
    meta = json.loads((a.src / "transforms_train.json").read_text())
    rng = np.random.default_rng(a.seed)
    record = []
    for f in meta["frames"]:
        entry = {"file_path": f["file_path"]}
        if a.exposure:
            path = a.out / (f["file_path"].lstrip("./") + ".png")
            img = iio.imread(path).astype(np.float64) / 255.0
            gain = rng.uniform(0.6, 1.5) / (NO_CLIP if a.no_clip else 1.0)
            channel = rng.uniform(0.9, 1.1, 3)
            img[..., :3] = np.clip(img[..., :3] * gain * channel, 0.0, 1.0)
            iio.imwrite(path, np.round(img * 255.0).astype(np.uint8))
            entry.update(gain=gain, channel=channel.tolist())
        if a.poses:
            c2w = np.asarray(f["transform_matrix"], np.float64)
            R = rotation(rng.normal(size=3), a.degrees)
            step = rng.normal(size=3)
            step *= a.move * np.linalg.norm(c2w[:3, 3]) / np.linalg.norm(step)
            c2w[:3, :3] = R @ c2w[:3, :3]
            c2w[:3, 3] += step
            f["transform_matrix"] = c2w.tolist()
            entry.update(degrees=a.degrees, move=step.tolist())
        record.append(entry)
    (a.out / "transforms_train.json").write_text(json.dumps(meta, indent=2))
    (a.out / "perturbation.json").write_text(json.dumps(
        {"source": str(a.src), "seed": a.seed, "exposure": a.exposure, "no_clip": a.no_clip,
         "poses": a.poses,
         "frames": record}, indent=2))
    for extra in ("MANIFEST.sha256",):     # the copy no longer matches the source's manifest
        (a.out / extra).unlink(missing_ok=True)
    print(f"wrote {a.out} ({len(record)} training views perturbed)")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
