"""What each splat file format costs a trained scene: bytes and PSNR / SSIM on its test views.

    python tools/splat_formats.py runs/lego --data $CLRF_DATA/lego_400 --out /tmp/formats

Writes the run's splats once in every format ``clrf export --splats`` knows (.ply, .glb,
.gltf, .compressed.ply, .spz, .splat), then scores each file as ``clrf eval --ckpt FILE``
does (the file read back by clrf, rendered by clrf on the dataset's test views), and the run's
own checkpoint beside them. Prints a table (bytes a Gaussian, the size against the PLY, PSNR
and SSIM and their changes from the checkpoint) and writes it to OUT/formats.json with each
file's eval JSON beside it. Every command runs as a user would type it (the installed
``clrf`` on PATH, or ``python -m clrf.cli``), one after the other.
"""
from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
from pathlib import Path

ENDINGS = (".ply", ".glb", ".gltf", ".compressed.ply", ".spz", ".splat")


def clrf(*args) -> None:
    """Runs ``clrf ARGS`` (this interpreter's clrf), stopping on failure."""
    cmd = [sys.executable, "-m", "clrf.cli", *map(str, args)]
    print("+ clrf " + " ".join(map(str, args)), file=sys.stderr, flush=True)
    subprocess.run(cmd, check=True)


def score(ckpt, data, out: Path, max_views: int | None) -> dict:
    """``clrf eval`` of ``ckpt`` on ``data``'s test views: its JSON."""
    args = ["eval", "--ckpt", ckpt, "--data", data, "--out", out, "--lpips", "none"]
    if max_views:
        args += ["--max-views", max_views]
    clrf(*args)
    return json.loads(out.read_text())


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("run", help="a splat run's folder (or its checkpoint)")
    ap.add_argument("--data", required=True, help="the dataset whose test views score it")
    ap.add_argument("--out", required=True, type=Path, help="folder for the files and JSON")
    ap.add_argument("--max-views", type=int, default=None)
    a = ap.parse_args(argv)
    a.out.mkdir(parents=True, exist_ok=True)
    rows = []
    base = score(a.run, a.data, a.out / "eval_ckpt.json", a.max_views)
    for ending in ENDINGS:
        path = a.out / f"scene{ending}"
        if not path.exists():
            clrf("export", "--ckpt", a.run, "--splats", path)
        ev = score(path, a.data, a.out / f"eval{ending.replace('.', '_')}.json", a.max_views)
        rows.append({"ending": ending, "bytes": os.path.getsize(path),
                     "psnr": ev["psnr"], "ssim": ev["ssim"]})
    n = _count(a.out / "scene.ply")
    ply = rows[0]["bytes"]
    print(f"{n} Gaussians; the checkpoint: {base['psnr']:.3f} dB / {base['ssim']:.4f} "
          f"over {len(base['views'])} test views")
    print("| ending | bytes a Gaussian | against the PLY | PSNR (dB) | change | SSIM | change |")
    print("| --- | --- | --- | --- | --- | --- | --- |")
    for r in rows:
        r["bytes_per_gaussian"] = r["bytes"] / n
        r["size_vs_ply"] = r["bytes"] / ply
        r["dpsnr"] = r["psnr"] - base["psnr"]
        r["dssim"] = r["ssim"] - base["ssim"]
        print(f"| `{r['ending']}` | {r['bytes_per_gaussian']:.1f} | {r['size_vs_ply']:.3f} | "
              f"{r['psnr']:.3f} | {r['dpsnr']:+.3f} | {r['ssim']:.4f} | {r['dssim']:+.4f} |")
    out = {"run": str(a.run), "data": str(a.data), "gaussians": n,
           "checkpoint": {"psnr": base["psnr"], "ssim": base["ssim"],
                          "views": len(base["views"])}, "formats": rows}
    (a.out / "formats.json").write_text(json.dumps(out, indent=2) + "\n")
    return 0


def _count(ply: Path) -> int:
    """The vertex count a PLY's header declares."""
    with open(ply, "rb") as f:
        for line in f:
            if line.startswith(b"element vertex"):
                return int(line.split()[2])
            if line.strip() == b"end_header":
                break
    raise ValueError(f"{ply}: no vertex element")


if __name__ == "__main__":
    sys.exit(main())
