"""lego_exp with each training image divided by its drawn gain (the clipped pixels stay as
clipped): what a grid reaches with perfect transforms that know nothing of the clip."""
import json, shutil, sys
from pathlib import Path
import imageio.v3 as iio
import numpy as np
src, out = Path(sys.argv[1]), Path(sys.argv[2])
shutil.copytree(src, out)
pert = json.loads((src / "perturbation.json").read_text())
for fr in pert["frames"]:
    if "gain" not in fr:
        continue
    p = out / (fr["file_path"] + ".png")
    img = iio.imread(p).astype(np.float64) / 255.0
    f = fr["gain"] * np.asarray(fr["channel"])
    img[..., :3] = np.clip(img[..., :3] / f, 0, 1)
    iio.imwrite(p, np.round(img * 255).astype(np.uint8))
print("undone", len(pert["frames"]))
