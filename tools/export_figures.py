"""The export pictures of docs/guide.md from a trained run: the exported mesh drawn with
matplotlib, and the first frame of the orbit video.

    python tools/export_figures.py RUN_DIR [--out tools/results/export]

Runs ``clrf export --mesh`` and ``clrf render --views orbit --video --scale 4`` on RUN_DIR
(outputs in RUN_DIR/export), then writes OUT/mesh.png (the mesh's triangles with their vertex colours,
flat-shaded by the angle to a light, painter's-algorithm order) and OUT/orbit_frame0.png (frame 0
of orbit.mp4 as read back by imageio).
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np


def draw_mesh(ply, png, elev=30.0, azim=-60.0, max_faces=60_000):
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from mpl_toolkits.mplot3d.art3d import Poly3DCollection

    from clrf.outputs.ply import read_ply

    m = read_ply(ply)
    v, f = m["verts"].astype(np.float64), m["faces"]
    if len(f) > max_faces:                       # keep the PNG small: an even subset
        f = f[np.linspace(0, len(f) - 1, max_faces).astype(int)]
    tri = v[f]
    n = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    n /= np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-12)
    light = np.array([0.4, -0.3, 0.87])
    shade = 0.35 + 0.65 * np.clip(n @ (light / np.linalg.norm(light)), 0, 1)
    col = m["colors"][f].mean(1) / 255.0 * shade[:, None]
    fig = plt.figure(figsize=(4, 4), dpi=100)
    ax = fig.add_subplot(projection="3d")
    ax.add_collection3d(Poly3DCollection(tri, facecolors=np.clip(col, 0, 1), linewidths=0))
    lo, hi = v.min(0), v.max(0)
    c, r = (lo + hi) / 2, (hi - lo).max() / 2
    for setlim, ci in zip((ax.set_xlim, ax.set_ylim, ax.set_zlim), c):
        setlim(ci - r, ci + r)
    ax.set_box_aspect((1, 1, 1))
    ax.view_init(elev=elev, azim=azim)
    ax.set_axis_off()
    fig.subplots_adjust(0, 0, 1, 1)
    fig.savefig(png)
    plt.close(fig)


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("run", help="a run directory written by clrf train")
    p.add_argument("--out", default="tools/results/export", help="folder for the two PNGs")
    a = p.parse_args(argv)
    import imageio.v3 as iio

    from clrf.cli.main import main as cli

    run, out = Path(a.run), Path(a.out)
    work = run / "export"
    out.mkdir(parents=True, exist_ok=True)
    if cli(["--quiet", "export", "--ckpt", str(run), "--mesh", str(work / "mesh.ply")]) != 0:
        return 1
    if cli(["--quiet", "render", "--ckpt", str(run), "--views", "orbit", "--frames", "48",
            "--scale", "4", "--video", "--out", str(work)]) != 0:
        return 1
    draw_mesh(work / "mesh.ply", out / "mesh.png")
    frame0 = iio.imread(work / "orbit.mp4", index=0)
    iio.imwrite(out / "orbit_frame0.png", frame0)
    print(f"saved {out / 'mesh.png'} and {out / 'orbit_frame0.png'}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
