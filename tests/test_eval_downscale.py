"""Periodic evaluation on downscaled views: the rays are the centres of f x f pixel blocks and
the reference images are the box-averaged ones."""
import numpy as np

from clrf.data.io import downscale_image
from clrf.data.synthetic import load_procedural
from clrf.training.metrics import image_metrics
from clrf.data.cameras import view_rays
from clrf.training.trainer import evaluate
from clrf.testing.tolerances import CAMERA_ATOL


class _Flat:
    """A stand-in model rendering colour = a linear function of the ray direction."""

    def render(self, o, d):
        d = d / -d[:, 2:3]
        return {"rgb": np.clip(0.5 + 0.3 * d[:, :3] * [1.0, -1.0, 0.0], 0, 1)}


def test_view_rays_downscaled_are_block_centres():
    ds = load_procedural(size=16, max_images=1)
    pose = ds.poses[:1]
    o1, d1 = view_rays(ds, pose)
    o2, d2 = view_rays(ds, pose, downscale=2)
    assert d2.shape == (64, 3)
    # camera-space directions (z = -1) are linear in the pixel position: a 2x2 block's mean
    # is the direction through the block centre
    block = d1.reshape(8, 2, 8, 2, 3).mean((1, 3)).reshape(-1, 3)
    np.testing.assert_allclose(d2, block, atol=CAMERA_ATOL)
    np.testing.assert_allclose(o2, o1[:64], atol=CAMERA_ATOL)


def test_evaluate_downscaled_compares_with_box_averaged_images():
    ds = load_procedural(size=32, max_images=2)
    views = ds.split["test"]
    ev = evaluate(_Flat(), ds, views, keep_images=True, downscale=4)
    assert ev["images"][0].shape == (8, 8, 3)
    for v, img, m in zip(views, ev["images"], ev["views"]):
        want = image_metrics(img, downscale_image(ds.images[v], 4))["psnr"]
        assert abs(m["psnr"] - want) < 1e-9
    full = evaluate(_Flat(), ds, views)
    assert full["views"][0]["psnr"] != ev["views"][0]["psnr"]
