"""Fill gpu-data/ with what tools/gpu/run.sh's training plans read on a GPU machine, which has no
package registry and no copy of the scenes: each plan's scene, cut to fit the device tool's
carry (64 MiB with the wheels), and for splat_bonsai the initial Gaussians made here (the
points triangulated from the training views need pycolmap, the `process` extra, which the GPU
machine lacks).

    python tools/gpu/pack.py splat_bonsai     # gpu-data/bonsai_800, gpu-data/bonsai_init.ply
    python tools/gpu/pack.py hash_lego --test-views 200

Plans and what they take (sizes on disk):
  hash_lego, grid_lego   lego_400: the 100 training views, the first validation view (the
                         loader reads all three splits), --test-views of the 200 test views
                         (evenly spaced; their RGB PNGs only, not the depth and normal ones):
                         13 MB + 0.1 MB + 25 MB for all 200
  hash_bonsai            bonsai_800 (images and poses_bounds.npy, 18 MB)
  splat_bonsai           the same, and bonsai_init.ply: the Gaussians a splat run starts from
                         with train.points=triangulate (points triangulated at a quarter of the
                         resolution: world points, the same at full size; about 1 MB)
Prints the folder's size; pass `gpu-data` to the device tool in carry (it is git-ignored).
"""
from __future__ import annotations

import argparse
import json
import os
import shutil
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[2]
sys.path.append(str(ROOT))   # the checkout's clrf only where none is installed

SCENE = {"hash_lego": "lego_400", "grid_lego": "lego_400", "hash_bonsai": "bonsai_800",
         "splat_bonsai": "bonsai_800"}
INIT_PLY = "bonsai_init.ply"


def _frames_json(src: Path, dst: Path, keep) -> list:
    """Copy a transforms_<split>.json keeping the frames at indices ``keep``; their files."""
    meta = json.loads(src.read_text())
    frames = [meta["frames"][i] for i in keep]
    dst.write_text(json.dumps(dict(meta, frames=frames), indent=1))
    return [f["file_path"] for f in frames]


def pack_lego(src: Path, dst: Path, test_views: int):
    dst.mkdir(parents=True, exist_ok=True)
    for split, n_all in (("train", None), ("val", 1), ("test", test_views)):
        meta = json.loads((src / f"transforms_{split}.json").read_text())
        total = len(meta["frames"])
        n = total if n_all is None else max(1, min(n_all, total))
        keep = np.unique(np.linspace(0, total - 1, n).round().astype(int))
        for fp in _frames_json(src / f"transforms_{split}.json",
                               dst / f"transforms_{split}.json", keep):
            name = fp if Path(fp).suffix else fp + ".png"
            (dst / name).parent.mkdir(parents=True, exist_ok=True)
            shutil.copyfile(src / name, dst / name)


def pack_bonsai(src: Path, dst: Path):
    dst.mkdir(parents=True, exist_ok=True)
    shutil.copyfile(src / "poses_bounds.npy", dst / "poses_bounds.npy")
    shutil.copytree(src / "images", dst / "images", dirs_exist_ok=True)


def splat_init(src: Path, out: Path):
    """The initial Gaussians of `clrf train --model splat --set train.points=triangulate` on
    bonsai at a quarter of the resolution, written as a splat PLY."""
    from clrf.data import load_dataset
    from clrf.data.triangulate import with_points
    from clrf.splat.model import initial_host
    from clrf.splat.ply import write_splat_ply
    from clrf.training.config import build_config
    ds = with_points(load_dataset(str(src), downscale=4), "triangulate")
    cfg = build_config("", None, {"train": {"model": "splat", "downscale": 4,
                                            "points": "triangulate"}}, ds.preset)
    host, where = initial_host(cfg.splat, ds, cfg.splat.max_gaussians, cfg.train.seed)
    write_splat_ply(out, host["means"], host["log_scales"], host["quats"],
                    host["opacity_logits"], host["sh"])
    print(f"{out}: {where}")


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("plans", nargs="+", choices=sorted(SCENE))
    ap.add_argument("--data", default=os.environ.get("CLRF_DATA", str(ROOT.parent / "shared"
                                                                          / "data")),
                    help="the scenes (default $CLRF_DATA, else ../shared/data)")
    ap.add_argument("--out", default=str(ROOT / "gpu-data"))
    ap.add_argument("--test-views", type=int, default=200,
                    help="lego_400 test views to take, evenly spaced (default all 200)")
    a = ap.parse_args(argv)
    data, out = Path(a.data), Path(a.out)
    for plan in a.plans:
        scene = SCENE[plan]
        if scene == "lego_400":
            pack_lego(data / scene, out / scene, a.test_views)
        else:
            pack_bonsai(data / scene, out / scene)
        if plan == "splat_bonsai":
            splat_init(data / scene, out / INIT_PLY)
    size = sum(p.stat().st_size for p in out.rglob("*") if p.is_file())
    print(f"{out}: {size / 2**20:.1f} MiB; carry it with the wheels (64 MiB in all)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
