"""How far a run's training cameras are from the true ones, before and after splat.pose_opt:

    python tools/perturb_capture.py $CLRF_DATA/lego_400 /tmp/lego_poses --poses
    clrf train --model splat --data /tmp/lego_poses --out runs/poses --set splat.pose_opt=true
    python tools/pose_error.py runs/poses $CLRF_DATA/lego_400

Reads the run's checkpoint (its data folder, the given poses, the corrections), loads the true
poses from TRUE (the capture before perturbation, the same views in the same order) and prints
the mean rotation error (degrees) and camera-centre error (scene units and % of the mean camera
distance to the origin) of the training views as given and as corrected, with --json the same
as one JSON object. A run without pose_opt reports the given poses' errors only.

Both are also reported after the similarity (scale, rotation, shift of the world) that best
maps each set's camera centres onto the true ones (Umeyama's least squares), as BARF and its
successors report pose errors: images alone cannot tell a scene and its cameras from the same
scene and cameras moved together, so a refinement may settle in a frame a little off the true
one, and only what is left after that common part blurs the scene.
"""
from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

sys.path.append(str(Path(__file__).resolve().parents[1]))   # an installed clrf comes first

from clrf.data import load_dataset  # noqa: E402
from clrf.outputs import checkpoint  # noqa: E402
from clrf.splat.model import viewmat_of  # noqa: E402
from clrf.corrections.pose import PoseCorrection, rotation_angle  # noqa: E402


def errors(views, true) -> dict:
    """Mean rotation (degrees) and centre errors of world-to-camera ``views`` against ``true``
    ([n, 4, 4] each)."""
    rot = [np.degrees(rotation_angle(V[:3, :3] @ T[:3, :3].T)) for V, T in zip(views, true)]
    centre = [np.linalg.norm(-V[:3, :3].T @ V[:3, 3] + T[:3, :3].T @ T[:3, 3])
              for V, T in zip(views, true)]
    return {"rotation_deg": float(np.mean(rot)), "centre": float(np.mean(centre))}


def centres(views) -> np.ndarray:
    return np.array([-V[:3, :3].T @ V[:3, 3] for V in views])


def aligned(views, true) -> list:
    """``views`` moved by the world similarity x -> s Q x + b that best maps their camera
    centres onto ``true``'s (Umeyama): world-to-camera [R t] becomes [R Q^T, s t - R Q^T b]."""
    x, y = centres(views), centres(true)
    mx, my = x.mean(0), y.mean(0)
    cov = (y - my).T @ (x - mx) / len(x)
    U, D, Vt = np.linalg.svd(cov)
    S = np.diag([1.0, 1.0, np.sign(np.linalg.det(U) * np.linalg.det(Vt))])
    Q = U @ S @ Vt
    s = float(np.trace(np.diag(D) @ S) / np.mean(np.sum((x - mx) ** 2, axis=1)))
    b = my - s * Q @ mx
    out = []
    for V in views:
        W = np.eye(4)
        W[:3, :3] = V[:3, :3] @ Q.T
        W[:3, 3] = s * V[:3, 3] - V[:3, :3] @ Q.T @ b
        out.append(W)
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("run", type=Path, help="the run's folder (its ckpt.npz)")
    ap.add_argument("true", type=Path, help="the capture with the true poses")
    ap.add_argument("--json", action="store_true")
    a = ap.parse_args(argv)
    st = checkpoint.load(a.run)
    given_ds = load_dataset(st["run_config"]["train"]["data"])
    true_ds = load_dataset(str(a.true))
    train = np.asarray(given_ds.split["train"])
    if len(true_ds.poses) != len(given_ds.poses) or \
            not np.array_equal(np.asarray(true_ds.split["train"]), train):
        ap.error(f"{a.true}: not the same views as the run's data "
                 f"({st['run_config']['train']['data']})")
    given = [viewmat_of(given_ds.poses[v]) for v in train]
    true = [viewmat_of(true_ds.poses[v]) for v in train]
    dist = float(np.mean([np.linalg.norm(-T[:3, :3].T @ T[:3, 3]) for T in true]))
    out = {"views": int(len(train)), "camera_distance": dist, "given": errors(given, true),
           "given_aligned": errors(aligned(given, true), true)}
    if "pose" in st:
        pc = PoseCorrection(len(st["pose"]), 1e-3, 0.0, 1.0, state=st)
        corrected = [pc.viewmat(V, v) for V, v in zip(given, train)]
        out["corrected"] = errors(corrected, true)
        out["corrected_aligned"] = errors(aligned(corrected, true), true)
        for k in ("", "_aligned"):
            out[f"rotation_error_reduction{k}"] = 1.0 - (
                out[f"corrected{k}"]["rotation_deg"] / max(out[f"given{k}"]["rotation_deg"],
                                                           1e-12))
    if a.json:
        print(json.dumps(out, indent=2))
        return 0
    for k in ("given", "corrected", "given_aligned", "corrected_aligned"):
        if k in out:
            e = out[k]
            print(f"{k:17s} rotation error {e['rotation_deg']:.4f} deg, centre error "
                  f"{e['centre']:.4g} ({100 * e['centre'] / dist:.3f} % of the camera "
                  f"distance), mean over {out['views']} training views")
    if "corrected" in out:
        print(f"rotation error down by {100 * out['rotation_error_reduction']:.1f} % "
              f"({100 * out['rotation_error_reduction_aligned']:.1f} % after the alignment)")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
