"""Host side of cl/splat_project.cl and cl/splat_raster.cl: 3D Gaussian splatting's projection,
tile binning and tile rasteriser, forward and backward, over pyopencl arrays. The math, the
layouts and the conventions (OpenCV camera, pixel centres at +0.5) are in the kernel files'
headers and cl/splat.h.

A frame is four steps, all on the device; the one host read is the number of (tile, Gaussian)
pairs after the scan, to size the sort's buffers (``bin``):

>>> r = SplatRasterizer(dev, sh_degree=3)
>>> params = r.upload(gaussians)             # dict of device arrays (PARAM_NAMES)
>>> proj = r.project(params, camera)         # Projected: xy, conic, radius, depth, ...
>>> bins = r.bin(proj, camera)               # Binned: sorted ids, per-tile ranges
>>> ras = r.rasterize(proj, bins, camera)    # Raster: rgb [H, W, 3], T [H, W], n_contrib
>>> g2d = r.rasterize_backward(proj, bins, ras, camera, grad_rgb_d)
>>> grads = r.project_backward(params, camera, g2d)   # dict of device arrays (PARAM_NAMES)
>>> grads = r.project_backward(params, camera, g2d, camera_grad=True)
>>> dR, dt = camera_gradient(grads["camera"])  # dL/d(R, t) of camera.viewmat (splat.pose_opt)

``SplatRasterizer(dev, 3, antialiased=True)`` projects with Mip-Splatting's 3D and 2D filters
(splat.antialiased; cl/splat_project.cl): its params carry "filter3d" [n], each Gaussian's 3D
filter variance, from ``r.filter3d(params["means"], training_cameras)``; the 2D filter of
``filter2d`` px^2 (default AA_FILTER2D, splat.aa_filter2d) replaces the 0.3 px^2 dilation.

``render(gaussians, camera)`` and ``render_backward(gaussians, camera, grad_rgb)`` do the same
from and to numpy.
"""
from __future__ import annotations

import warnings
from dataclasses import dataclass

import numpy as np
import pyopencl as cl
import pyopencl.array as cla
from pyopencl.algorithm import RadixSort
from pyopencl.elementwise import ElementwiseKernel
from pyopencl.tools import context_dependent_memoize

from ..runtime.programs import device_empty, device_zeros, float4, launch, scratch, upload
from ..runtime.scan import row_offsets
from ..runtime import sort as keysort
from ..runtime.validate import check_array

TILE = 16                 # tile side in pixels (cl/splat.h TILE); 8 where 256 work-items fail
ALPHA_MAX = 0.99          # opacity clamp of one Gaussian at one pixel
ALPHA_MIN = 1.0 / 255.0   # weaker contributions are skipped
T_MIN = 1e-4              # a pixel stops before its transmittance would fall below this
COV_DILATION = 0.3        # low-pass filter added to the 2D covariance's diagonal (px^2)
FRUSTUM_GUARD = 1.3       # x/z, y/z clamped to this times the half-frustum's tangent
SIGMA_RADIUS = 3.0        # screen radius in standard deviations
AA_FILTER2D = 0.1         # the anti-aliased projection's 2D filter instead (px^2)
FILTER3D_VAR = 0.2        # the 3D filter's variance in the finest sampling interval squared
FILTER3D_MARGIN = 0.15    # a training camera sees a mean within this share outside its image
CAM_FLOATS = 20           # cl/splat.h camera buffer
PARAM_NAMES = ("means", "log_scales", "quats", "opacity_logits", "sh")
GRAD2D_NAMES = ("xy", "conic", "opacity", "color")
PAIRS = "(tile, Gaussian) pairs"   # what an int32 overflow of the binning names
CHUNK_CELLS = 1 << 22    # the rows shape's binning: at most this many (chunk, tile) counters
BACKWARD_COPIES = 64     # the rows shape's backward: at most this many gradient copies
BACKWARD_FLOATS = 9 + 2  # a Gaussian's floats in one copy (GRAD2D_NAMES, ABSGRAD's two more)


def backward_copies(caps) -> int:
    """The rows shape's gradient copies on a device of capabilities ``caps``
    (splat_raster_backward_rows): one per compute unit, so that every core adds, at most
    BACKWARD_COPIES."""
    return max(1, min(BACKWARD_COPIES, int(caps.compute_units)))


def defines(sh_degree: int, tile: int = TILE) -> dict:
    """The -D defines of both splat programs (the constants above, the SH degree, the tile)."""
    return {"SH_DEGREE": int(sh_degree), "TILE": int(tile), "ALPHA_MAX": ALPHA_MAX,
            "ALPHA_MIN": ALPHA_MIN, "T_MIN": T_MIN, "COV_DILATION": COV_DILATION,
            "FRUSTUM_GUARD": FRUSTUM_GUARD, "SIGMA_RADIUS": SIGMA_RADIUS}


def project_defines(sh_degree: int, tile: int = TILE, antialiased: bool = False,
                    filter2d: float = AA_FILTER2D) -> dict:
    """cl/splat_project.cl's defines: the shared ones, the 3D filter's constants and, for the
    anti-aliased projection, ANTIALIASED=1 with the 2D filter ``filter2d`` (px^2) as
    COV_DILATION."""
    d = dict(defines(sh_degree, tile), FILTER3D_VAR=FILTER3D_VAR,
             FILTER3D_MARGIN=FILTER3D_MARGIN)
    if antialiased:
        d.update(ANTIALIASED=1, COV_DILATION=float(filter2d))
    return d


def pose_program(device, sh_degree: int, tile: int = TILE, antialiased: bool = False,
                 filter2d: float = AA_FILTER2D):
    """cl/splat_project.cl with POSE_GRAD=1: its backward also writes the camera's gradient."""
    return device.program("splat_project.cl", dict(
        project_defines(sh_degree, tile, antialiased, filter2d), POSE_GRAD=1))


def camera_gradient(d_cam) -> tuple:
    """(dL/dR [3, 3], dL/dt [3]) float64 of the camera's world-to-camera [R t] from the
    backward's per-Gaussian shares ``d_cam`` [12, n] (a device array): twelve sums on the device,
    one read of twelve numbers."""
    n = int(d_cam.shape[1])
    if n == 0:
        return np.zeros((3, 3)), np.zeros(3)
    sums = [cla.sum(d_cam[k]) for k in range(12)]
    g = np.array([float(x.get()) for x in sums], np.float64)
    return g[:9].reshape(3, 3), g[9:]


def programs(device, sh_degree: int, tile: int = TILE, antialiased: bool = False,
             filter2d: float = AA_FILTER2D) -> tuple:
    """(cl/splat_project.cl, cl/splat_raster.cl) for SH degree ``sh_degree`` and tiles of
    ``tile`` pixels on ``device`` (both shapes' kernels are in the second)."""
    return (device.program("splat_project.cl",
                           project_defines(sh_degree, tile, antialiased, filter2d)),
            raster_program(device, sh_degree, tile))


def raster_program(device, sh_degree: int, tile: int = TILE, depth: bool = False,
                   absgrad: bool = False):
    """cl/splat_raster.cl, with RENDER_DEPTH=1 (the forwards also composite each splat's
    camera depth) and / or ABSGRAD=1 (the backwards also sum |dL/dxy| per pixel)."""
    d = defines(sh_degree, tile)
    if depth:
        d["RENDER_DEPTH"] = 1
    if absgrad:
        d["ABSGRAD"] = 1
    return device.program("splat_raster.cl", d)


@dataclass(frozen=True)
class SplatCamera:
    """A pinhole camera: ``viewmat`` [4, 4] world-to-camera (x right, y down, z forward),
    intrinsics in pixels, the image size and the near plane (> 0; Gaussians with camera depth
    <= near are culled)."""
    viewmat: np.ndarray
    fx: float
    fy: float
    cx: float
    cy: float
    width: int
    height: int
    near: float = 0.01

    def __post_init__(self):
        v = check_array("viewmat", self.viewmat, ndim=2, dtype=np.float64)
        if v.shape != (4, 4):
            raise ValueError(f"viewmat: expected shape (4, 4), got {v.shape}")
        object.__setattr__(self, "viewmat", v)
        for name in ("fx", "fy", "near"):
            x = float(getattr(self, name))
            if not (np.isfinite(x) and x > 0):
                raise ValueError(f"{name}: must be a finite number > 0, got {x}")
        for name in ("cx", "cy"):
            if not np.isfinite(float(getattr(self, name))):
                raise ValueError(f"{name}: must be finite")
        for name in ("width", "height"):
            x = getattr(self, name)
            if int(x) != x or not 1 <= int(x) <= 1 << 15:
                raise ValueError(f"{name}: must be an integer in 1..32768, got {x}")

    def tiles(self, tile: int = TILE) -> tuple[int, int]:
        """(ntx, nty): tiles across and down."""
        return -(-int(self.width) // tile), -(-int(self.height) // tile)

    def buffer(self) -> np.ndarray:
        """The float32 camera buffer of cl/splat.h (R, t, centre, fx, fy, cx, cy, near)."""
        R, t = self.viewmat[:3, :3], self.viewmat[:3, 3]
        out = np.concatenate([R.ravel(), t, -R.T @ t,
                              [self.fx, self.fy, self.cx, self.cy, self.near]])
        return out.astype(np.float32)


@dataclass
class Projected:
    """Per-Gaussian screen-space splats on the device (splat_project's outputs; Gaussian i):
    xy [n, 2] pixels, conic [n, 3] (A, B, C) of Sigma2^-1, radius [n] (0: culled), depth [n]
    (camera z), color [n, 3], opacity [n], rect [n, 4] int32 tiles (x0, y0, x1, y1)."""
    n: int
    xy: cla.Array
    conic: cla.Array
    radius: cla.Array
    depth: cla.Array
    color: cla.Array
    opacity: cla.Array
    rect: cla.Array


@dataclass
class Binned:
    """The sorted (tile, Gaussian) pairs: ids [n_pairs] int32 front to back within each tile,
    keys [n_pairs] uint64 (tile << 32 | depth bits), ranges [ntiles, 2] int32 [start, end)."""
    n_pairs: int
    keys: cla.Array
    ids: cla.Array
    ranges: cla.Array
    ntx: int
    nty: int


@dataclass
class Raster:
    """The forward's image: rgb [H, W, 3], final transmittance T [H, W], n_contrib [H, W] int32
    (list entries the backward walks); for the rows shape also the splats' records the forward
    used (splat_pack_rows), which the backward reuses; where asked (``depth=True``) depth
    [H, W], sum_k T_k alpha_k z_k of the same pass (divide by 1 - T for the mean depth)."""
    rgb: cla.Array
    T: cla.Array
    n_contrib: cla.Array
    records: cla.Array | None = None
    depth: cla.Array | None = None


def _check_device_array(name: str, a, shape: tuple, dtype=np.float32):
    if not isinstance(a, cla.Array):
        raise TypeError(f"{name}: expected a pyopencl array, got {type(a).__name__}")
    if a.dtype != np.dtype(dtype):
        raise TypeError(f"{name}: expected dtype {np.dtype(dtype)}, got {a.dtype}")
    if tuple(a.shape) != tuple(shape):
        raise ValueError(f"{name}: expected shape {tuple(shape)}, got {tuple(a.shape)}")
    if not a.flags.c_contiguous:
        raise ValueError(f"{name}: must be C-contiguous")


@context_dependent_memoize
def _fill_unseen(context):
    """f2[i] < 0 (no training camera sees Gaussian i) -> the largest f2, max(0, top[0])."""
    return ElementwiseKernel(context, "float *f2, __global const float *top",
                             "if (f2[i] < 0.0f) f2[i] = fmax(top[0], 0.0f)", "splat_fill_unseen")


@context_dependent_memoize
def _pair_sort(context):
    """pyopencl's radix sort of the pairs' (uint64 keys, ids) for ``context``, built once."""
    with warnings.catch_warnings():
        # pyopencl warns on any non-empty build log, chatter included (programs.build)
        warnings.simplefilter("ignore", cl.CompilerWarning)
        return RadixSort(context, "__global ulong *keys, __global int *ids", key_expr="keys[i]",
                         sort_arg_names=["keys", "ids"], key_dtype=np.uint64)


SHAPES = ("rows", "group")


def default_shape(device, tile: int = TILE) -> str:
    """The rasteriser's shape for ``device``: "group" (a work-group of tile x tile work-items
    per tile, splat_raster_forward / _backward) on GPUs and wherever the tuning forces the GPU
    kernels (CLRF_FORCE_GPU_KERNELS=1); else "rows" (one work-item per tile, a row of pixels
    one float vector: splat_raster_forward_rows / _backward_rows), for tiles of 4, 8 or 16."""
    if getattr(device.tuning, "gpu_kernels", False) or int(tile) not in (4, 8, 16):
        return "group"
    return "rows"


CPU_TILE = 8   # the rows shape's tile where the model picks it (default_tile)


def default_tile(device) -> int:
    """The tile a model's rasteriser uses on ``device``: TILE (16) for the work-group shape,
    CPU_TILE (8) for the rows shape. With 8-pixel rows (one float8) a small splat wastes fewer
    lanes than with 16: on a lego_400 checkpoint of 174k Gaussians (2 vCPUs of a Xeon with
    AVX-512, PoCL 3.1) a 400x400 frame took 123 ms against 140, forward + backward 190-211 ms
    against 232."""
    return CPU_TILE if default_shape(device, CPU_TILE) == "rows" else TILE


class SplatRasterizer:
    """Gaussian splatting kernels on ``device`` for SH degree ``sh_degree`` (0..3) and square
    tiles of ``tile`` pixels. ``shape`` (default: ``default_shape(device, tile)``) picks the
    rasteriser's kernels: "group" (one work-group of tile x tile work-items per tile, the GPU
    shape) or "rows" (one work-item per tile, the CPU shape; tiles of 4, 8 or 16); both compute
    the same images and gradients to float32 rounding."""

    def __init__(self, device, sh_degree: int = 3, tile: int = TILE, shape: str | None = None,
                 antialiased: bool = False, filter2d: float = AA_FILTER2D):
        if int(sh_degree) not in (0, 1, 2, 3):
            raise ValueError(f"sh_degree: must be 0, 1, 2 or 3, got {sh_degree}")
        if int(tile) not in (4, 8, 16, 32):
            raise ValueError(f"tile: must be 4, 8, 16 or 32, got {tile}")
        self.device = device
        self.sh_degree = int(sh_degree)
        self.n_basis = (self.sh_degree + 1) ** 2
        self.tile = int(tile)
        self.shape = default_shape(device, self.tile) if shape is None else shape
        if self.shape not in SHAPES:
            raise ValueError(f"shape: must be one of {SHAPES}, got {shape!r}")
        if self.shape == "rows" and self.tile not in (4, 8, 16):
            raise ValueError(f"shape 'rows': tiles of 4, 8 or 16 pixels, got {self.tile}")
        if self.shape == "group" and self.tile * self.tile > device.caps.max_work_group_size:
            raise ValueError(f"tile {self.tile}: {self.tile ** 2} work-items exceed this "
                             f"device's work-group limit {device.caps.max_work_group_size}; "
                             f"use a smaller tile")
        self.antialiased = bool(antialiased)
        if not 0 < filter2d <= 1:
            raise ValueError(f"filter2d: the 2D filter's variance must be in (0, 1] px^2, got "
                             f"{filter2d}")
        self.filter2d = float(filter2d) if self.antialiased else COV_DILATION   # px^2
        self.proj_program, self.raster_program = programs(device, self.sh_degree, self.tile,
                                                          self.antialiased, self.filter2d)
        # The kernels' own CL_KERNEL_WORK_GROUP_SIZE is not consulted: Mesa's rusticl reports
        # 32 for every kernel and then runs 16 x 16 groups correctly. A device that really
        # cannot fails the launch with CL_INVALID_WORK_GROUP_SIZE (_tiles_launch says why).
        self.sort = _pair_sort(device.context)

    # ---- parameters ---------------------------------------------------------------------------
    def shapes(self, n: int) -> dict:
        """The parameter shapes for n Gaussians."""
        return {"means": (n, 3), "log_scales": (n, 3), "quats": (n, 4), "opacity_logits": (n,),
                "sh": (n, self.n_basis, 3)}

    def _count(self, params: dict) -> int:
        missing = [k for k in PARAM_NAMES if k not in params]
        if missing:
            raise KeyError(f"gaussians: missing {missing} (need {list(PARAM_NAMES)})")
        return int(np.shape(params["means"])[0]) if np.ndim(params["means"]) else -1

    def check_params(self, params: dict) -> int:
        """Checks device parameters (dtype float32, shapes, contiguity; "filter3d" [n] too when
        anti-aliased); returns n."""
        n = self._count(params)
        for name, shape in self.shapes(n).items():
            _check_device_array(name, params[name], shape)
        if self.antialiased:
            if params.get("filter3d") is None:
                raise KeyError("gaussians: the anti-aliased rasteriser needs 'filter3d' [n] "
                               "(SplatRasterizer.filter3d)")
            _check_device_array("filter3d", params["filter3d"], (n,))
        return n

    def filter3d(self, means, cameras) -> cla.Array:
        """Each Gaussian's 3D filter variance f2 [n] (splat_filter3d) over ``cameras`` (the
        training views' SplatCameras, all of one size); a mean no camera sees gets the largest
        f2 of the others (0 when none is seen)."""
        n = int(means.shape[0])
        dev = self.device
        f2 = scratch(dev, (n,))
        if n == 0:
            return f2
        cams = list(cameras)
        if not cams:
            raise ValueError("filter3d: no training cameras")
        if len({(int(c.width), int(c.height)) for c in cams}) != 1:
            raise ValueError("filter3d: the training cameras differ in image size")
        buf = upload(dev.queue, np.stack([c.buffer() for c in cams]))
        launch(dev, self.proj_program.kernel("splat_filter3d"), n,
               (np.int32(n), means.data, buf.data, np.int32(len(cams)),
                np.int32(cams[0].width), np.int32(cams[0].height), f2.data),
               dev.tuning.elementwise_local_size)
        _fill_unseen(dev.context)(f2, cla.max(f2))
        return f2

    def upload(self, gaussians: dict) -> dict:
        """Host arrays (any float dtype, finite) -> validated float32 device arrays."""
        n = self._count(gaussians)
        out = {}
        for name, shape in self.shapes(max(n, 0)).items():
            a = check_array(name, gaussians[name], ndim=len(shape))
            if a.shape != shape:
                raise ValueError(f"{name}: expected shape {shape}, got {a.shape}")
            out[name] = upload(self.device.queue, a)
        return out

    # ---- forward --------------------------------------------------------------------------------
    def _camera(self, camera: SplatCamera):
        if not isinstance(camera, SplatCamera):
            raise TypeError(f"camera: expected a SplatCamera, got {type(camera).__name__}")
        return upload(self.device.queue, camera.buffer())

    def project(self, params: dict, camera: SplatCamera) -> Projected:
        """splat_project over the n Gaussians of ``params`` (device arrays, PARAM_NAMES)."""
        n = self.check_params(params)
        cam = self._camera(camera)
        ntx, nty = camera.tiles(self.tile)
        dev = self.device
        proj = Projected(n, scratch(dev, (n, 2)), scratch(dev, (n, 3)), scratch(dev, (n,)),
                         scratch(dev, (n,)), scratch(dev, (n, 3)), scratch(dev, (n,)),
                         scratch(dev, (n, 4), np.int32))
        p = params
        args = (np.int32(n), p["means"].data, p["log_scales"].data, p["quats"].data,
                p["opacity_logits"].data, p["sh"].data, cam.data, np.int32(camera.width),
                np.int32(camera.height), np.int32(ntx), np.int32(nty), proj.xy.data,
                proj.conic.data, proj.radius.data, proj.depth.data, proj.color.data,
                proj.opacity.data, proj.rect.data)
        if self.antialiased:
            args += (p["filter3d"].data,)
        launch(dev, self.proj_program.kernel("splat_project"), n, args,
               dev.tuning.elementwise_local_size)
        return proj

    def check_projected(self, proj: Projected):
        n = int(proj.n)
        for name, shape, dt in (("xy", (n, 2), np.float32), ("conic", (n, 3), np.float32),
                                ("radius", (n,), np.float32), ("depth", (n,), np.float32),
                                ("color", (n, 3), np.float32), ("opacity", (n,), np.float32),
                                ("rect", (n, 4), np.int32)):
            _check_device_array(name, getattr(proj, name), shape, dt)

    def bin(self, proj: Projected, camera: SplatCamera) -> Binned:
        """The per-tile lists of (tile, Gaussian) pairs, front to back. Shape "group": count,
        scan, emit, sort the pairs, range them. Shape "rows": sort the Gaussians by depth and
        count-sort that order into the tiles (splat_chunk_*; Binned.keys is then empty). Both
        read one int64 (the pair count) back to the host to size the ids and the sort's
        buffers, and give the same ids and ranges."""
        self.check_projected(proj)
        dev, q, n = self.device, self.device.queue, int(proj.n)
        ntx, nty = camera.tiles(self.tile)
        empty_keys = device_empty(q, 0, np.uint64)
        empty_ids = device_empty(q, 0, np.int32)
        if self.shape == "rows":
            return self._bin_rows(proj, n, ntx, nty, empty_keys, empty_ids)
        ranges = cla.zeros(q, (ntx * nty, 2), np.int32, allocator=dev.pool)
        if n == 0:
            return Binned(0, empty_keys, empty_ids, ranges, ntx, nty)
        ls = dev.tuning.elementwise_local_size
        counts = scratch(dev, (n,), np.int32)
        launch(dev, self.raster_program.kernel("splat_count"), n,
               (np.int32(n), proj.rect.data, counts.data), ls)
        # the one host read of a forward: the pair total
        offsets, n_pairs = row_offsets(dev, counts, n, PAIRS)
        if n_pairs == 0:
            return Binned(0, empty_keys, empty_ids, ranges, ntx, nty)
        keys = scratch(dev, (n_pairs,), np.uint64)
        ids = scratch(dev, (n_pairs,), np.int32)
        launch(dev, self.raster_program.kernel("splat_emit"), n,
               (np.int32(n), proj.rect.data, proj.depth.data, offsets.data, np.int32(ntx),
                keys.data, ids.data), ls)
        key_bits = 32 + max(1, int(ntx * nty - 1).bit_length())
        (keys, ids), _ = self.sort(keys, ids, key_bits=key_bits, queue=q, allocator=dev.pool)
        launch(dev, self.raster_program.kernel("splat_ranges"), n_pairs,
               (np.int32(n_pairs), keys.data, ranges.data), ls)
        return Binned(n_pairs, keys, ids, ranges, ntx, nty)

    def _bin_rows(self, proj: Projected, n: int, ntx: int, nty: int, empty_keys, empty_ids):
        """bin() for the rows shape (see there): the Gaussians' stable depth order
        (clrf/runtime/sort.py), then one counting sort of it into the tiles' lists, a chunk of
        that order a work-item (splat_chunk_*)."""
        dev, q = self.device, self.device.queue
        ntiles = ntx * nty
        if n == 0:
            return Binned(0, empty_keys, empty_ids,
                          cla.zeros(q, (ntiles, 2), np.int32, allocator=dev.pool), ntx, nty)
        prg = self.raster_program
        ls = dev.tuning.elementwise_local_size
        # depth > near > 0 wherever a rect is not empty, so its bits order like the depths
        order = keysort.key_order(dev, proj.depth.view(np.uint32), n)
        most = max(1, min(keysort.MAX_CHUNKS, CHUNK_CELLS // ntiles))
        chunk, nchunks = keysort.chunking(n, most)
        cc = scratch(dev, (nchunks, ntiles), np.int32)
        head = (np.int32(n), np.int32(chunk), np.int32(nchunks), order.data, proj.rect.data,
                np.int32(ntx), np.int32(ntiles), cc.data)
        launch(dev, prg.kernel("splat_chunk_count"), nchunks, head, 1)
        counts = scratch(dev, (ntiles,), np.int32)
        launch(dev, prg.kernel("splat_chunk_totals"), ntiles,
               (np.int32(ntiles), np.int32(nchunks), cc.data, counts.data), ls)
        # the one host read of a forward: the pair total
        offsets, n_pairs = row_offsets(dev, counts, ntiles, PAIRS)
        ranges = scratch(dev, (ntiles, 2), np.int32)
        if n_pairs == 0:
            ranges.fill(0)
            return Binned(0, empty_keys, empty_ids, ranges, ntx, nty)
        launch(dev, prg.kernel("splat_chunk_cursors"), ntiles,
               (np.int32(ntiles), np.int32(nchunks), cc.data, offsets.data, ranges.data), ls)
        ids = scratch(dev, (n_pairs,), np.int32)
        launch(dev, prg.kernel("splat_chunk_fill"), nchunks, head + (ids.data,), 1)
        return Binned(n_pairs, empty_keys, ids, ranges, ntx, nty)

    def _records(self, proj: Projected) -> cla.Array:
        """The rows shape's per-splat records [n, 16] (splat_pack_rows: the splat and the
        bounds of its reach, one 64-byte line a list entry loads)."""
        n = int(proj.n)
        rec = scratch(self.device, (max(n, 1), 16))
        if n:
            launch(self.device, self.raster_program.kernel("splat_pack_rows"), n,
                   (np.int32(n), proj.xy.data, proj.conic.data, proj.opacity.data,
                    proj.color.data, proj.depth.data, rec.data),
                   self.device.tuning.elementwise_local_size)
        return rec

    def _backward_records(self, proj: Projected, raster: Raster):
        """The records for the backward (rows shape): the forward's, when it kept them for
        these splats, else packed anew."""
        if self.shape != "rows":
            return None
        rec = raster.records
        if rec is None or rec.shape[0] != max(int(proj.n), 1):
            rec = self._records(proj)
        return rec

    def _tiles_launch(self, name: str, bins: Binned, args, rec=None, program=None,
                      group_tail=(), rows_tail=()):
        """Kernel ``name`` of the rasteriser's shape (of ``program``, default the plain
        build) with ``args`` (width, height, ntx, ranges, ids, xy, conic, opacity, color, then
        the kernel's own) and a variant's trailing arguments: one work-group of tile x tile
        work-items per tile ("group", + ``group_tail``), or one work-item per tile ("rows",
        name + "_rows", which takes the tile count after ntx and the splats' records ``rec``
        instead of xy .. color, + ``rows_tail``)."""
        t = self.tile
        program = program or self.raster_program
        if self.shape == "rows":
            ntiles = bins.ntx * bins.nty
            kernel = program.kernel(name + "_rows")
            launch(self.device, kernel, ntiles,
                   args[:3] + (np.int32(ntiles),) + args[3:5] + (rec.data,) + args[9:]
                   + tuple(rows_tail), 1)
            return
        args = tuple(args) + tuple(group_tail)
        kernel = program.kernel(name)
        kernel.set_args(*args)
        try:
            cl.enqueue_nd_range_kernel(self.device.queue, kernel,
                                       (bins.ntx * t, bins.nty * t), (t, t))
        except cl.LogicError as e:
            if e.code != cl.status_code.INVALID_WORK_GROUP_SIZE:
                raise
            raise RuntimeError(f"{kernel.function_name}: this device refuses work-groups of "
                               f"{t} x {t}; build SplatRasterizer with a smaller tile") from e

    @staticmethod
    def _bg(background) -> np.ndarray:
        bg = check_array("background", background, ndim=1, dtype=np.float32)
        if bg.shape != (3,):
            raise ValueError(f"background: expected 3 values, got shape {bg.shape}")
        return float4(*bg, 0.0)

    def rasterize(self, proj: Projected, bins: Binned, camera: SplatCamera,
                  background=(0.0, 0.0, 0.0), depth: bool = False) -> Raster:
        """splat_raster_forward: the image of the binned splats over ``background``; with
        ``depth`` also their composited camera depth, in the same pass (RENDER_DEPTH)."""
        self.check_projected(proj)
        dev = self.device
        H, W = int(camera.height), int(camera.width)
        out = Raster(scratch(dev, (H, W, 3)), scratch(dev, (H, W)),
                     scratch(dev, (H, W), np.int32),
                     self._records(proj) if self.shape == "rows" else None,
                     scratch(dev, (H, W)) if depth else None)
        program, group_tail, rows_tail = None, (), ()
        if depth:
            program = raster_program(dev, self.sh_degree, self.tile, depth=True)
            group_tail, rows_tail = (proj.depth.data, out.depth.data), (out.depth.data,)
        self._tiles_launch(
            "splat_raster_forward", bins,
            (np.int32(W), np.int32(H), np.int32(bins.ntx), bins.ranges.data, bins.ids.data,
             proj.xy.data, proj.conic.data, proj.opacity.data, proj.color.data,
             self._bg(background), out.rgb.data, out.T.data, out.n_contrib.data), out.records,
            program, group_tail, rows_tail)
        return out

    # ---- backward -------------------------------------------------------------------------------
    def rasterize_backward(self, proj: Projected, bins: Binned, raster: Raster,
                           camera: SplatCamera, grad_rgb: cla.Array,
                           background=(0.0, 0.0, 0.0), absgrad: bool = False) -> dict:
        """dL/d(xy, conic, opacity, color) [n, ...] (device, GRAD2D_NAMES) for dL/drgb
        ``grad_rgb`` [H, W, 3] (device float32), from the forward's ``raster``; with
        ``absgrad`` also "xy_abs" [n, 2], the per-pixel terms of dL/dxy summed in absolute
        value (ABSGRAD)."""
        self.check_projected(proj)
        H, W = int(camera.height), int(camera.width)
        _check_device_array("grad_rgb", grad_rgb, (H, W, 3))
        _check_device_array("T", raster.T, (H, W))
        _check_device_array("n_contrib", raster.n_contrib, (H, W), np.int32)
        q, n = self.device.queue, int(proj.n)
        # _backward_rows writes every row; elsewhere the atomics add into zeros
        alloc = device_empty if self.shape == "rows" and bins.n_pairs else device_zeros
        g = {k: alloc(q, shape, np.float32)
             for k, shape in (("xy", (n, 2)), ("conic", (n, 3)), ("opacity", (n,)),
                              ("color", (n, 3)))}
        program, tail = None, ()
        if absgrad:
            g["xy_abs"] = alloc(q, (n, 2), np.float32)
            program = raster_program(self.device, self.sh_degree, self.tile, absgrad=True)
            tail = (g["xy_abs"].data,)
        if bins.n_pairs == 0:
            return g
        if self.shape == "rows":
            return self._backward_rows(proj, bins, raster, W, H, grad_rgb, background, g,
                                       program or self.raster_program)
        self._tiles_launch(
            "splat_raster_backward", bins,
            (np.int32(W), np.int32(H), np.int32(bins.ntx), bins.ranges.data, bins.ids.data,
             proj.xy.data, proj.conic.data, proj.opacity.data, proj.color.data,
             self._bg(background), raster.T.data, raster.n_contrib.data, grad_rgb.data,
             g["xy"].data, g["conic"].data, g["opacity"].data, g["color"].data),
            self._backward_records(proj, raster), program, tail, tail)
        return g

    def backward_copies(self) -> int:
        """The rows shape's gradient copies on this device (module backward_copies)."""
        return backward_copies(self.device.caps)

    def _backward_rows(self, proj, bins, raster, W, H, grad_rgb, background, g, program):
        """rasterize_backward for the rows shape: the tiles into per-work-item copies of the
        gradients, then their sum into ``g`` (no atomics; the same result every run)."""
        dev, n, copies = self.device, int(proj.n), self.backward_copies()
        ntiles = bins.ntx * bins.nty
        acc = scratch(dev, (copies, n, BACKWARD_FLOATS - 2 * int("xy_abs" not in g)))
        launch(dev, program.kernel("splat_raster_backward_rows"), copies,
               (np.int32(W), np.int32(H), np.int32(bins.ntx), np.int32(ntiles),
                bins.ranges.data, bins.ids.data, self._backward_records(proj, raster).data,
                self._bg(background), raster.T.data, raster.n_contrib.data, grad_rgb.data,
                np.int32(n), np.int32(copies), acc.data), 1)
        outs = tuple(g[k].data for k in GRAD2D_NAMES + (("xy_abs",) if "xy_abs" in g else ()))
        launch(dev, program.kernel("splat_backward_rows_sum"), n,
               (np.int32(n), np.int32(copies), acc.data) + outs,
               dev.tuning.elementwise_local_size)
        return g

    def project_backward(self, params: dict, camera: SplatCamera, grads2d: dict,
                         camera_grad: bool = False) -> dict:
        """dL/d(PARAM_NAMES) (device arrays) from the projected outputs' gradients ``grads2d``
        (GRAD2D_NAMES, e.g. rasterize_backward's); with ``camera_grad`` also "camera": each
        Gaussian's share of dL/d(R, t) of the camera, [12, n] (``camera_gradient`` sums it)."""
        n = self.check_params(params)
        for name, shape in (("xy", (n, 2)), ("conic", (n, 3)), ("opacity", (n,)),
                            ("color", (n, 3))):
            _check_device_array(f"grads2d[{name!r}]", grads2d[name], shape)
        dev = self.device
        out = {name: scratch(dev, shape) for name, shape in self.shapes(n).items()}
        cam = self._camera(camera)
        p = params
        args = (np.int32(n), p["means"].data, p["log_scales"].data, p["quats"].data,
                p["opacity_logits"].data, p["sh"].data, cam.data, np.int32(camera.width),
                np.int32(camera.height), grads2d["xy"].data, grads2d["conic"].data,
                grads2d["color"].data, grads2d["opacity"].data, out["means"].data,
                out["log_scales"].data, out["quats"].data, out["opacity_logits"].data,
                out["sh"].data)
        if self.antialiased:
            args += (p["filter3d"].data,)
        prg = self.proj_program
        if camera_grad:
            prg = pose_program(dev, self.sh_degree, self.tile, self.antialiased, self.filter2d)
            out["camera"] = scratch(dev, (12, n))
            args += (out["camera"].data,)
        launch(dev, prg.kernel("splat_project_backward"), n, args,
               dev.tuning.elementwise_local_size)
        return out

    # ---- numpy conveniences ---------------------------------------------------------------------
    def forward(self, params: dict, camera: SplatCamera, background=(0.0, 0.0, 0.0),
                depth: bool = False):
        """(Projected, Binned, Raster) of device parameters (``depth``: Raster.depth too)."""
        proj = self.project(params, camera)
        bins = self.bin(proj, camera)
        return proj, bins, self.rasterize(proj, bins, camera, background, depth)

    def render(self, gaussians: dict, camera: SplatCamera,
               background=(0.0, 0.0, 0.0)) -> dict:
        """dict(rgb [H, W, 3], T [H, W], n_contrib [H, W], depth [H, W] (sum_k T_k alpha_k
        z_k)) as numpy arrays."""
        _, _, ras = self.forward(self.upload(gaussians), camera, background, depth=True)
        return {"rgb": ras.rgb.get(), "T": ras.T.get(), "n_contrib": ras.n_contrib.get(),
                "depth": ras.depth.get()}

    def render_backward(self, gaussians: dict, camera: SplatCamera, grad_rgb,
                        background=(0.0, 0.0, 0.0), absgrad: bool = False) -> dict:
        """dL/d(PARAM_NAMES) as numpy arrays for dL/drgb ``grad_rgb`` [H, W, 3], plus the
        screen-space gradients under "grad2d" (a dict of GRAD2D_NAMES, and "xy_abs" with
        ``absgrad``)."""
        params = self.upload(gaussians)
        g = check_array("grad_rgb", grad_rgb, ndim=3)
        proj, bins, ras = self.forward(params, camera, background)
        g2d = self.rasterize_backward(proj, bins, ras, camera,
                                      upload(self.device.queue, g), background, absgrad)
        out = {k: v.get() for k, v in self.project_backward(params, camera, g2d).items()}
        out["grad2d"] = {k: v.get() for k, v in g2d.items()}
        return out
