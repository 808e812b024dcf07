"""Memory estimate of a Gaussian-splatting run: per Gaussian its parameters with gradient and
two Adam moments, the projected splats and their gradients, the CPU backward's gradient copies,
the (tile, Gaussian) pairs and the sort's copies of them; per pixel of a view the image, its
gradient, the rasteriser's per-pixel state and the device loss's planes; per training pixel its
target where the training images live on the device (as uint8 or float16), or only one view's
where they are streamed from the host (splat.images_on_device: clrf/splat/targets.py).
"""
from __future__ import annotations

from ..runtime.memory import StageEstimate
from .raster import BACKWARD_COPIES, BACKWARD_FLOATS, backward_copies
from .targets import resident

PARAM_FLOATS_WITHOUT_SH = 3 + 3 + 4 + 1      # means, log scales, quaternion, opacity logit
PROJECTED_BYTES = 4 * (2 + 3 + 1 + 1 + 3 + 1) + 16   # xy, conic, radius, depth, colour,
#                                                      opacity, int4 rect
GRAD2D_BYTES = 4 * (2 + 3 + 1 + 3)
PAIRS_PER_GAUSSIAN = 16     # tiles a Gaussian covers on average (a guess on the safe side)
PAIR_BYTES = 8 + 4          # uint64 key + int32 id
SORT_COPIES = 3             # the pairs, the radix sort's output and its scratch
DENSIFY_FLOATS = 4          # a strategy's statistics (the default's three: summed gradient
#                             norm, view count, largest screen radius) and a spare
LOSS_PLANE_BYTES = 10 * 12  # clrf/splat/loss.py: 9 scratch planes and the gradient, float3
PIXEL_BYTES = 4 * (3 + 3 + 1 + 1 + 3) + LOSS_PLANE_BYTES   # rgb, its gradient, T, n_contrib,
#                                                           the step's target widened, loss
TARGET_BYTES = 2 * 3        # a training pixel on the device: uint8 or float16 resident;
#                             streamed, one view's (its uint8 staging: targets.py)


def bytes_per_gaussian(sh_degree: int, copies: int = 0) -> int:
    """Bytes a Gaussian takes, with ``copies`` gradient copies of the CPU backward."""
    floats = PARAM_FLOATS_WITHOUT_SH + 3 * (sh_degree + 1) ** 2
    return (4 * floats * 4 + PROJECTED_BYTES + GRAD2D_BYTES + 4 * DENSIFY_FLOATS
            + 4 * BACKWARD_FLOATS * int(copies)
            + SORT_COPIES * PAIRS_PER_GAUSSIAN * PAIR_BYTES)


def copies_on(caps) -> int:
    """The CPU backward's gradient copies on a device of ``caps`` (none on a GPU, which adds
    with atomics; the most where the device is not known)."""
    if caps is None:
        return BACKWARD_COPIES
    return backward_copies(caps) if getattr(caps, "type", "cpu") == "cpu" else 0


def target_pixels(sc, caps, n_pixels: int, train_pixels: int) -> int:
    """Pixels of training images the device holds: all ``train_pixels`` where they are
    resident, one view's ``n_pixels`` (the staging buffer) where they are streamed."""
    return int(train_pixels) if resident(sc.images_on_device, caps) else int(n_pixels)


def splat_stage(sc, n_gaussians: int, n_pixels: int, train_pixels: int = 0,
                copies: int = 0) -> StageEstimate:
    """StageEstimate of a splatting run of SplatConfig ``sc`` at ``n_gaussians`` Gaussians,
    views of ``n_pixels`` pixels, ``train_pixels`` pixels of training images and ``copies``
    gradient copies of the CPU backward."""
    n = int(n_gaussians)
    total = (n * bytes_per_gaussian(sc.sh_degree, copies) + PIXEL_BYTES * int(n_pixels)
             + TARGET_BYTES * int(train_pixels))
    sh = 4 * n * 3 * (sc.sh_degree + 1) ** 2
    pairs = n * PAIRS_PER_GAUSSIAN * PAIR_BYTES
    largest, what = max((sh, "SH coefficients"), (pairs, "sorted (tile, Gaussian) pairs"))
    return StageEstimate(f"splat training ({n} Gaussians, SH degree {sc.sh_degree})", total,
                         largest, what)


def fitting_gaussians(sc, caps, n_pixels: int, share: float = 0.5, train_pixels: int = 0) -> int:
    """How many Gaussians fit in ``share`` of the device's memory (and its largest buffer)
    beside views of ``n_pixels`` pixels and ``train_pixels`` pixels of training images (those
    the device holds: ``target_pixels``)."""
    per = bytes_per_gaussian(sc.sh_degree, copies_on(caps))
    room = (int(share * caps.global_mem_size) - PIXEL_BYTES * int(n_pixels)
            - TARGET_BYTES * target_pixels(sc, caps, n_pixels, train_pixels))
    by_total = max(1, room // per)
    by_alloc = max(1, int(caps.max_alloc_size) // (PAIRS_PER_GAUSSIAN * PAIR_BYTES))
    return int(min(by_total, by_alloc))


SPLAT_FIX = "lower splat.max_gaussians (and splat.init_points), or train on smaller images " \
            "with train.downscale"


def memory(cfg, n_rays: int, caps, tuning=None, is_cpu: bool = True):
    """(stages, fix) of cfg.splat's run: the cap of Gaussians, views of the dataset's size
    (``n_rays`` over all training views bounds one view's pixels)."""
    sc = cfg.splat
    view = min(int(n_rays), 1 << 22)
    n = min(sc.max_gaussians, fitting_gaussians(sc, caps, view, train_pixels=n_rays)) \
        if caps is not None else sc.max_gaussians
    # n_rays (every training pixel) bounds a view's pixels, and so does a 2048 x 2048 view here
    return [splat_stage(sc, n, view, target_pixels(sc, caps, view, n_rays),
                        copies_on(caps) if is_cpu else 0)], SPLAT_FIX
