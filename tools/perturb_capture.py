"""Copy a Blender-layout capture with the faults of a phone capture put into its training
split, to measure what splat.exposure, splat.bilateral_grid (and pose refinement) recover:

    python tools/perturb_capture.py $CLRF_DATA/lego_400 /tmp/lego_exposure --exposure
    python tools/perturb_capture.py $CLRF_DATA/lego_400 /tmp/lego_poses --poses
    python tools/perturb_capture.py $CLRF_DATA/lego_400 /tmp/lego_vignette --vignette 0.4

--exposure  each training image (RGB, alpha kept) times a gain drawn from [0.6, 1.5] and each
            channel times one from [0.9, 1.1], clipped to [0, 1] as a camera would;
--no-clip   (with --exposure) the same draws, every gain divided by 1.65 (the largest
            gain times the largest channel factor), so that no channel clips: what the clip
            costs, apart from the changes themselves (the scene then trains darker than the
            untouched test views, so compare scores that fit a colour transform);
--poses     each training pose turned by --degrees (1) about a random axis through the camera
            and moved by --move (1 %) of the camera's distance to the origin, in a random
            direction;
--vignette S  each training image (RGB, alpha kept) times a smooth radial falloff, as a lens
            darkens toward its corners: f = clip(1 - s r^2, 0, 1), r the distance of a pixel's
            centre from the falloff's centre over half the image's diagonal, s drawn from
            [S / 2, S] per image and the centre moved from the image's by up to 10 % of its
            width and height (uniform; the draws from a stream of their own, so that the
            other draws of a seed stay as they were); with --exposure, the pixel is the
            source times both, clipped once. What a bilateral grid per image
            (splat.bilateral_grid) can absorb and a colour transform (splat.exposure) cannot.
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
VIGNETTE_SHIFT = 0.1   # --vignette: the centre's largest move, a fraction of width and height
VIGNETTE_STREAM = 1    # --vignette: its draws' stream, default_rng((seed, VIGNETTE_STREAM))


def vignette(h: int, w: int, strength: float, centre) -> np.ndarray:
    """The falloff [h, w] of --vignette: clip(1 - strength r^2, 0, 1), r the distance of each
    pixel's centre (x + 1/2, y + 1/2) from ``centre`` (x, y in pixels) over half the diagonal.

    >>> float(vignette(2, 2, 0.5, (1.0, 1.0))[0, 0])     # r^2 = 0.5 / 2: 1 - 0.5 * 0.25
    0.875
    """
    y, x = np.mgrid[0:h, 0:w] + 0.5
    r2 = ((x - centre[0]) ** 2 + (y - centre[1]) ** 2) / ((w / 2) ** 2 + (h / 2) ** 2)
    return np.clip(1.0 - strength * r2, 0.0, 1.0)


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
    ap.add_argument("--vignette", type=float, default=None, metavar="S")
    ap.add_argument("--seed", type=int, default=0)
    a = ap.parse_args(argv)
    if not (a.src / "transforms_train.json").is_file():
        ap.error(f"{a.src}: no transforms_train.json (a Blender-layout capture)")
    if a.no_clip and not a.exposure:
        ap.error("--no-clip goes with --exposure")
    if a.vignette is not None and not 0 < a.vignette <= 1:
        ap.error(f"--vignette {a.vignette}: the largest strength must be in (0, 1]")
    if a.out.exists():
        ap.error(f"{a.out} exists; pick a new folder")
    shutil.copytree(a.src, a.out)
    meta = json.loads((a.src / "transforms_train.json").read_text())
    rng = np.random.default_rng(a.seed)
    rng_vignette = np.random.default_rng((a.seed, VIGNETTE_STREAM))
    record = []
    for f in meta["frames"]:
        entry = {"file_path": f["file_path"]}
        if a.exposure or a.vignette:
            path = a.out / (f["file_path"].lstrip("./") + ".png")
            img = iio.imread(path).astype(np.float64) / 255.0
            factor = np.ones(img.shape[:2] + (1,))
            if a.exposure:
                gain = rng.uniform(0.6, 1.5) / (NO_CLIP if a.no_clip else 1.0)
                channel = rng.uniform(0.9, 1.1, 3)
                factor = factor * gain * channel
                entry.update(gain=gain, channel=channel.tolist())
            if a.vignette:
                h, w = img.shape[:2]
                s = rng_vignette.uniform(a.vignette / 2, a.vignette)
                centre = np.array([w, h]) * (0.5 + rng_vignette.uniform(
                    -VIGNETTE_SHIFT, VIGNETTE_SHIFT, 2))
                factor = factor * vignette(h, w, s, centre)[..., None]
                entry.update(vignette={"strength": s, "centre": centre.tolist()})
            img[..., :3] = np.clip(img[..., :3] * factor, 0.0, 1.0)
            iio.imwrite(path, np.round(img * 255.0).astype(np.uint8))
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
         "poses": a.poses, "vignette": a.vignette or 0.0,
         "frames": record}, indent=2))
    for extra in ("MANIFEST.sha256",):     # the copy no longer matches the source's manifest
        (a.out / extra).unlink(missing_ok=True)
    print(f"wrote {a.out} ({len(record)} training views perturbed)")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
