"""Host wrappers of cl/grid_render.cl: the public ``render_rays`` / ``render_rays_backward``.

Both take numpy float32 rays and return numpy results; the device-side variants (``*_device``)
take and return pyopencl arrays and are what training uses (no host copies per batch).
"""
from __future__ import annotations

import numpy as np
import pyopencl.array as cla

from ..runtime.device import DeviceError
from ..runtime.programs import device_empty, device_zeros, float4, int4, launch, upload
from ..runtime.tuning import slots_order_memory
from ..runtime.validate import check_array, check_positive, check_rays

T_STOP = 1e-4          # early-termination transmittance (cl/grid_render.cl T_STOP)
BETA_EPS = 1e-3        # guard inside the beta prior's logs (cl/grid_render.cl BETA_EPS)
# Rays that can have more samples than this get compensated (Kahan) accumulators (COMPENSATED_SUMS
# in cl/march.h): plain float32 sums drift like n * 6e-8, 5e-4 relative at 8192 samples.
LONG_RAY_SAMPLES = 8192
REDUCE_ROWS = 16       # rows per work-item of grad_slots_reduce (cl/grid_render.cl)
# The kernels count samples in int; a step that would need more than this per ray is rejected.
MAX_SAMPLES_PER_RAY = 2.0 ** 30
# Work-group sizes, prefetch, block skipping and the gradient path come from grid.device.tuning
# (clrf/runtime/tuning.py).


def check_step(grid, step) -> float:
    step = check_positive("step", step)
    if max_samples_per_ray(grid.reso, step) > MAX_SAMPLES_PER_RAY:
        raise ValueError(f"step: {step} voxels gives up to {max_samples_per_ray(grid.reso, step):.3g} "
                         f"samples per ray through this {grid.reso} grid; the limit is "
                         f"{MAX_SAMPLES_PER_RAY:.3g}. Use a step >= "
                         f"{np.linalg.norm(grid.reso) / MAX_SAMPLES_PER_RAY:.3g}")
    return step


def grid_program(grid, grad_mode: int = 0, track_touched: bool = False, t_stop: float = T_STOP,
                 slots: int = 0, step: float = 0.5, record: bool = False,
                 bg_per_ray: bool = False, brick: bool = False, ray_order: bool = False,
                 pose_grad: bool = False, exposure: int = 0):
    """cl/grid_render.cl built for this grid and the device's tuning (slots: GRAD_SLOTS;
    record: the backward reads the forward's per-sample record, needs slots > 0; bg_per_ray:
    a background colour per ray, BG_PER_RAY; brick: the BRICK variant for one brick of a
    distributed grid, clrf/grid/bricks.py, built with t_stop 0; ray_order: the render kernels
    take a ray permutation, RAY_ORDER; pose_grad: also render_ray_grad, each ray's
    dL/d(origin, direction), GRID_POSE_GRAD, for grid.pose_opt; exposure: 1, or 2 clamped,
    the backward's loss through each ray's image transform, RAY_EXPOSURE, for grid.exposure).
    The constant-background build has no BG_PER_RAY define at all, so it is the same program
    as before per-ray backgrounds; likewise RAY_ORDER, GRID_POSE_GRAD and RAY_EXPOSURE."""
    t = grid.device.tuning
    extra = {"BG_PER_RAY": 1} if bg_per_ray else {}
    if exposure:
        extra["RAY_EXPOSURE"] = int(exposure)
    if ray_order:
        extra["RAY_ORDER"] = 1
    if pose_grad:
        extra["GRID_POSE_GRAD"] = 1
    if not t.grad_merge and slots <= 0:
        extra["GRAD_MERGE"] = 0   # each sample's gradients added as it is met (Intel GPUs)
    reso = getattr(grid, "march_reso", grid.reso)
    return grid.device.program("grid_render.cl", {
        **extra,
        "SH_DEGREE": grid.sh_degree, "T_STOP": float(t_stop), "GRAD_MODE": int(grad_mode),
        "TRACK_TOUCHED": int(track_touched), "GRAD_SLOTS": int(slots),
        "GRAD_LOCKS": int(t.grad_locks) if slots > 0 else 0,
        "SAMPLE_RECORD": int(bool(record) and slots > 0),
        "COMPENSATED_SUMS": int(max_samples_per_ray(reso, step) > LONG_RAY_SAMPLES),
        "CLRF_PREFETCH": int(t.prefetch), "PREFETCH_AHEAD": t.prefetch_ahead,
        "PREFETCH_LINKS_AHEAD": t.prefetch_links_ahead, "BLOCK": t.block,
        "BLOCK_FINE": t.block_fine if t.block > 0 else 0,
        "BRICK": int(bool(brick)), "BETA_EPS": BETA_EPS,
        # the GPU shape: colours per corner, 3 floats of colour gradient per corner (march.h)
        "SH_PER_CORNER": int(bool(getattr(t, "gpu_kernels", False)))})


def _bg4(background):
    bg = np.broadcast_to(np.asarray(background, np.float64), (3,))
    if not np.all(np.isfinite(bg)):
        raise ValueError("background: must be finite")
    return float4(bg[0], bg[1], bg[2], 0.0)


def _per_ray(background, n) -> bool:
    """True when ``background`` is a device array of per-ray colours [n, 3] (BG_PER_RAY), False
    for a constant colour (three numbers)."""
    if not isinstance(background, cla.Array):
        return False
    if background.dtype != np.float32 or background.shape != (n, 3) or not background.flags.c_contiguous:
        raise ValueError(f"background: a per-ray background must be a contiguous float32 device "
                         f"array of shape ({n}, 3), got {background.dtype} {background.shape}")
    return True


def _bg_arg(background, n):
    """The kernels' background argument: the per-ray buffer or the constant float4."""
    return background.data if _per_ray(background, n) else _bg4(background)


def grad_slots(grid) -> int:
    """Slots of render_backward (GRAD_SLOTS): ``tuning.grad_slots`` (one per compute unit on
    CPU devices, where PoCL runs one work-item at a time per compute unit so no atomics are
    needed; 0, float atomics, elsewhere), 0 when the scratch copies (tuning.scratch_copies) would
    not fit in a quarter of the device memory."""
    caps = grid.device.caps
    s = max(0, int(grid.device.tuning.grad_slots))
    if s > 0 and not slots_order_memory(caps):
        raise DeviceError(
            f"grad_slots {s} (gradient copies under locks) on {caps.type} '{caps.name}', which "
            "has no OpenCL C 3.0 acquire/release atomics: its locks would order nothing between "
            "work-groups and the gradients would be wrong. Use the float-atomic path: "
            "CLRF_GRAD_SLOTS=0 (the default on GPUs)")
    row_bytes = 4 * (1 + grid.sh_dim) + 1
    scratch = grid.device.tuning.scratch_copies(s) * grid.density.shape[0] * row_bytes
    if s > 0 and scratch > caps.global_mem_size // 4:
        s = 0
    return s


def _lock_count(reso, lock_log2) -> int:
    """Ints of the block-lock buffer (cl/grid_render.cl lock_of: one per 64-byte line)."""
    return 16 * int(np.prod([(r >> lock_log2) + 1 for r in reso]))


def _slot_buffers(grid, slots):
    """Zeroed slot buffers: scratch density, SH and marks (tuning.scratch_copies), the slot
    locks and, with tuning.grad_locks, the block locks over the whole grid's voxels (allocated
    once per grid and row count; the kernels leave them all zero)."""
    n = grid.density.shape[0]
    e = grid.device.tuning.scratch_copies(slots)
    locks = grid.device.tuning.grad_locks
    key = (slots, e, locks, n, grid.sh_dim)
    cache = grid.scratch.setdefault("grad_slot_buffers", {})
    if key not in cache:
        cache.clear()
        q = grid.device.queue
        reso = getattr(grid, "march_reso", grid.reso)   # a brick locks in the whole grid
        cache[key] = (device_zeros(q, e * n, np.float32),
                      device_zeros(q, e * n * grid.sh_dim, np.float32),
                      device_zeros(q, e * n, np.uint8), device_zeros(q, slots, np.int32),
                      device_zeros(q, _lock_count(reso, locks), np.int32) if locks > 0 else None)
    return cache[key]


def block_occupancy(grid):
    """(occ uint8 device array, oreso int4): which BLOCK^3-cell blocks have an allocated corner
    and, from entry oreso.w on, which BLOCK_FINE^3-cell blocks (cl/grid_render.cl
    block_occupancy). Built once per links buffer and cached on the grid; a grid whose links
    are rewritten in place must drop ``grid.scratch["block_occupancy"]``."""
    t = grid.device.tuning
    block, fine = t.block, t.block_fine if t.block > 0 else 0
    r = grid.reso   # the links array's own shape (a brick's, for bricks)
    ob = [max(1, -(-x // block)) if block > 0 else 1 for x in r]
    of = [max(1, -(-x // fine)) if fine > 0 else 0 for x in r]
    key = (grid.links.data.int_ptr, block, fine, tuple(r))
    cached = grid.scratch.get("block_occupancy")
    if cached is None or cached[0] != key:
        n_coarse = int(np.prod(ob))
        occ = device_zeros(grid.device.queue, n_coarse + int(np.prod(of)), np.uint8)
        oreso = int4(ob[0], ob[1], ob[2], n_coarse)
        k = grid_program(grid).kernel("block_occupancy")
        r4 = int4(r[0], r[1], r[2], 0)
        for nb, shape, off in ((block, ob, 0), (fine, of, n_coarse)):
            if nb > 0:
                launch(grid.device, k, int(np.prod(shape)),
                       (r4, int4(*shape, 0), np.int32(nb), np.int32(off),
                        grid.links.data, occ.data), 64)
        cached = (key, occ, oreso)
        grid.scratch["block_occupancy"] = cached
    return cached[1], cached[2]


def max_samples_per_ray(reso, step) -> int:
    """Upper bound of the segments of one ray: the box diagonal in voxels over the step, + 2."""
    return int(np.ceil(np.sqrt(float(sum(r * r for r in reso))) / float(step))) + 2


def _record_buffer(grid, slots, rec_max):
    """Per-slot sample records of the backward march: float [slots, rec_max, 8] (march.h)."""
    key = (slots, rec_max)
    cache = grid.scratch.setdefault("grad_record_buffers", {})
    if key not in cache:
        cache.clear()
        cache[key] = device_empty(grid.device.queue, slots * rec_max * 8, np.float32)
    return cache[key]


# Sort rays (tuning.ray_order) only on grids with at least this fraction of cells allocated:
# in-process A/B on the Zen 4, 128^3 SH2, 4,096 camera rays, forward + backward: dense 9-10 %
# faster, 5 %-occupied 13 % slower (the sort's ~0.6 ms, and that order was slower there).
RAY_ORDER_MIN_OCCUPANCY = 0.25


def ray_order(grid, origins_d, dirs_d, step):
    """A permutation of the n rays (int32 device array) that sorts them by the Morton code of
    the block (1/32 of the grid per axis) that holds the midpoint of their path through the
    grid box (cl/grid_render.cl ray_order_keys), or None when the device's
    ``tuning.ray_order`` does not ask for one at this n or the grid is sparse
    (RAY_ORDER_MIN_OCCUPANCY). Rendering in that order gives the same per-ray results; it only
    changes which rays run one after another. The keys are read back and argsorted on the
    host, so the call waits for the queue."""
    dev = grid.device
    n = origins_d.shape[0]
    if dev.tuning.ray_order <= 0 or n < dev.tuning.ray_order:
        return None
    if grid.n_rows < RAY_ORDER_MIN_OCCUPANCY * float(np.prod(grid.reso)):
        return None
    keys = device_empty(dev.queue, n, np.uint32)
    shift = max(0, int(np.ceil(np.log2(max(grid.reso)))) - 5)
    launch(dev, grid_program(grid, step=step).kernel("ray_order_keys"), n,
           (np.int32(n), origins_d.data, dirs_d.data, *grid.geometry_args(), np.float32(step),
            np.int32(shift), keys.data), dev.tuning.elementwise_local_size)
    order = np.argsort(keys.get(), kind="stable").astype(np.int32)
    return upload(dev.queue, order)


def render_forward_device(grid, origins_d, dirs_d, step, background, out=None, t_stop=T_STOP):
    """Forward render of device rays; returns dict of device arrays rgb [n,3], depth, acc [n].
    background: three numbers, or a float32 device array [n, 3] of per-ray colours. t_stop:
    early-termination transmittance (0: none, as distributed rendering)."""
    dev = grid.device
    n = origins_d.shape[0]
    q = dev.queue
    if out is None:
        out = {"rgb": device_empty(q, (n, 3), np.float32), "depth": device_empty(q, n, np.float32),
               "acc": device_empty(q, n, np.float32)}
    order = ray_order(grid, origins_d, dirs_d, step)
    k = grid_program(grid, step=step, t_stop=t_stop, bg_per_ray=_per_ray(background, n),
                     ray_order=order is not None).kernel("render_forward")
    occ, oreso = block_occupancy(grid)
    launch(dev, k, n, (np.int32(n), origins_d.data, dirs_d.data, grid.links.data,
                       grid.density.data, grid.sh.data, *grid.geometry_args(),
                       np.float32(step), _bg_arg(background, n), out["rgb"].data,
                       out["depth"].data, out["acc"].data, occ.data, oreso,
                       *([] if order is None else [order.data])),
           dev.tuning.grid_local_size)
    return out


def ray_exit_device(grid, origins_d, dirs_d, step, out=None):
    """t_exit [n] (device float32): where each ray leaves the grid box, as a world distance
    along its unit direction; 0 for rays that miss the box. The start of a background model
    behind the grid (cl/grid_render.cl ray_exit)."""
    dev = grid.device
    n = origins_d.shape[0]
    if out is None:
        out = device_empty(dev.queue, max(n, 1), np.float32)
    k = grid_program(grid, step=step, bg_per_ray=True).kernel("ray_exit")
    launch(dev, k, n, (np.int32(n), origins_d.data, dirs_d.data, *grid.geometry_args(),
                       np.float32(step), out.data), dev.tuning.grid_local_size)
    return out


def render_backward_device(grid, origins_d, dirs_d, ray_in_d, step, background, grad_density,
                           grad_sh, grad_mode=0, loss_scale=1.0, ray_out=None, touched=None,
                           beta_scale=0.0, grad_bg=None, t_stop=T_STOP, ray_grad=None,
                           exposure=None):
    """Add the gradients of one batch into grad_density [N] / grad_sh [N, C] (device arrays).

    grad_mode 0: ray_in_d holds dL/drgb. grad_mode 1: ray_in_d holds target colours, the loss
    is ``loss_scale * sum |rgb - target|^2 + beta_scale * sum [log(T + 1e-3) + log(1 - T + 1e-3)]``
    (T the ray's final transmittance: the beta prior) and ray_out receives the per-ray squared
    error.
    touched (uint8 [N]) gets 1 for every row that received a gradient, if given.
    background: three numbers, or a float32 device array [n, 3] of per-ray colours; then
    grad_bg (float32 device [n, 3], overwritten) receives dL/d background = T_end dL/dpixel
    per ray (allocated if None). Returns grad_bg (None for a constant background).
    ray_grad (float32 device [n, 6], overwritten, or None): each ray's dL/d(origin,
    direction) of the same loss, sample distances held (cl/grid_render.cl render_ray_grad, in
    the GRID_POSE_GRAD build, launched after the backward).
    exposure (grad_mode 1, no ray_grad): a ``RayTransform`` (clrf/corrections/exposure.py
    ``RayExposure.in_backward``): the loss compares each ray's pixel under its image's
    transform, A rgb + b (clamped to [0, 1] with its clip), with the target; ray_out gets that
    loss's terms, and its state and resid what the rows' gradient reads (cl/grid_render.cl
    RAY_EXPOSURE).
    """
    dev = grid.device
    n = origins_d.shape[0]
    per_ray = _per_ray(background, n)
    if n == 0:
        return grad_bg
    slots = grad_slots(grid)
    record = slots > 0 and dev.tuning.sample_record
    order = ray_order(grid, origins_d, dirs_d, step)
    if ray_grad is not None and (ray_grad.dtype != np.float32 or ray_grad.shape != (n, 6)
                                 or not ray_grad.flags.c_contiguous):
        raise ValueError(f"ray_grad: a contiguous float32 device array of shape ({n}, 6), got "
                         f"{ray_grad.dtype} {ray_grad.shape}")
    if exposure is not None and (grad_mode != 1 or ray_grad is not None):
        raise ValueError("exposure: the transform in the backward needs grad_mode 1 and no "
                         "ray_grad")
    prg = grid_program(grid, grad_mode, touched is not None, t_stop=t_stop, slots=slots,
                       step=step, record=record, bg_per_ray=per_ray,
                       ray_order=order is not None,
                       exposure=0 if exposure is None else 1 + bool(exposure.clip))
    args = [np.int32(n), origins_d.data, dirs_d.data, grid.links.data, grid.density.data,
            grid.sh.data, *grid.geometry_args(), np.float32(step), _bg_arg(background, n),
            ray_in_d.data]
    if grad_mode == 1:
        # the per-ray loss: never aliased onto ray_in (the targets), which other work-items
        # may still be reading
        if ray_out is None:
            ray_out = device_empty(dev.queue, max(n, 1), np.float32)
        args += [ray_out.data, np.float32(loss_scale), np.float32(beta_scale)]
    if exposure is not None:
        args += [exposure.index.data, np.int32(exposure.pixels), exposure.rows.data,
                 exposure.state.data, exposure.resid.data]
    args += [grad_density.data, grad_sh.data]
    if per_ray:
        if grad_bg is None:
            grad_bg = device_empty(dev.queue, (n, 3), np.float32)
        args.append(grad_bg.data)
    launch_backward(grid, prg, n, args, grad_density, grad_sh, touched, slots, record,
                    grid.reso, step, () if order is None else (order.data,))
    if ray_grad is not None:   # render_ray_grad: the same loss's camera gradient per ray
        _launch_ray_grad(grid, origins_d, dirs_d, ray_in_d, step, background, grad_mode,
                         loss_scale, beta_scale, t_stop, ray_grad, order)
    return grad_bg


def render_ray_grad_device(grid, origins_d, dirs_d, ray_in_d, step, background, grad_mode=0,
                           loss_scale=1.0, beta_scale=0.0, t_stop=T_STOP, ray_grad=None):
    """Each ray's dL/d(origin, direction) [n, 6] (float32 device, ``ray_grad`` overwritten or a
    new array) of the loss ``render_backward_device`` takes with the same arguments (sample
    distances held: cl/grid_render.cl render_ray_grad, the GRID_POSE_GRAD build, built when
    first asked for), with nothing else formed: no gradient of the grid's values, no touched
    rows, no per-ray loss. The grid is only read (test-time camera refinement)."""
    n = int(origins_d.shape[0])
    q = grid.device.queue
    if ray_grad is None:
        ray_grad = device_empty(q, (max(n, 1), 6), np.float32)[:n]
    elif (ray_grad.dtype != np.float32 or ray_grad.shape != (n, 6)
          or not ray_grad.flags.c_contiguous):
        raise ValueError(f"ray_grad: a contiguous float32 device array of shape ({n}, 6), got "
                         f"{ray_grad.dtype} {ray_grad.shape}")
    if n:
        _launch_ray_grad(grid, origins_d, dirs_d, ray_in_d, step, background, grad_mode,
                         loss_scale, beta_scale, t_stop, ray_grad,
                         ray_order(grid, origins_d, dirs_d, step))
    return ray_grad


def _launch_ray_grad(grid, origins_d, dirs_d, ray_in_d, step, background, grad_mode,
                     loss_scale, beta_scale, t_stop, ray_grad, order):
    """render_ray_grad over the n rays into ``ray_grad`` [n, 6], in the ray permutation
    ``order`` (or None)."""
    dev = grid.device
    n = int(origins_d.shape[0])
    pose = grid_program(grid, grad_mode, t_stop=t_stop, step=step,
                        bg_per_ray=_per_ray(background, n), ray_order=order is not None,
                        pose_grad=True)
    occ, oreso = block_occupancy(grid)
    rargs = [np.int32(n), origins_d.data, dirs_d.data, grid.links.data, grid.density.data,
             grid.sh.data, *grid.geometry_args(), np.float32(step), _bg_arg(background, n),
             ray_in_d.data]
    if grad_mode == 1:
        rargs += [np.float32(loss_scale), np.float32(beta_scale)]
    launch(dev, pose.kernel("render_ray_grad"), n,
           rargs + [ray_grad.data, occ.data, oreso] + ([] if order is None else [order.data]),
           dev.tuning.grid_local_size)


def launch_backward(grid, prg, n, args, grad_density, grad_sh, touched, slots, record,
                    march_reso, step, extra_args=()):
    """The tail every render_backward launch shares (single grid and bricks): ``args`` up to
    the gradient buffers, then touched, the slot buffers and sample records, the block
    occupancy and ``extra_args``; launch, and reduce the slots into the gradients."""
    dev = grid.device
    args = list(args)
    if touched is not None:
        args.append(touched.data)
    n_rows = grid.density.shape[0]
    if slots:
        sd, ss, st, lock, block_locks = _slot_buffers(grid, slots)
        args += [np.int32(n_rows), sd.data, ss.data, st.data, lock.data]
        if block_locks is not None:
            args.append(block_locks.data)
        if record:
            rec_max = max_samples_per_ray(march_reso, step)
            args += [_record_buffer(grid, slots, rec_max).data, np.int32(rec_max)]
    occ, oreso = block_occupancy(grid)
    args += [occ.data, oreso, *extra_args]
    launch(dev, prg.kernel("render_backward"), n, args, dev.tuning.grid_local_size)
    if slots:
        tch = touched if touched is not None else st   # not read without TRACK_TOUCHED
        launch(dev, prg.kernel("grad_slots_reduce"), -(-n_rows // REDUCE_ROWS),
               (np.int32(n_rows), sd.data, ss.data, st.data, grad_density.data, grad_sh.data,
                tch.data), dev.tuning.reduce_local_size)


def _host_background(background, n, q):
    """A numpy per-ray background [n, 3] goes to the device; three numbers stay as they are."""
    if np.ndim(background) < 2:
        return background
    bg = check_array("background", background, ndim=2, shape_tail=(3,))
    if bg.shape[0] != n:
        raise ValueError(f"background has {bg.shape[0]} rows for {n} rays")
    return upload(q, bg)


def render_rays(grid, origins, dirs, step=0.5, background=(1.0, 1.0, 1.0)):
    """Render rays through a SparseGrid.

    origins, dirs: float32 [n, 3] (dirs need not be unit length). step: voxels per sample.
    background: three numbers, or [n, 3] colours, one per ray.
    Returns numpy ``rgb`` [n,3], ``depth`` [n] (sum of weight x distance, background at 0) and
    ``acc`` [n] (opacity, sum of weights); rgb includes ``T_end * background`` (T_end the
    ray's final transmittance, ~ 1 - acc).

    >>> out = clrf.render_rays(grid, np.zeros((1, 3)), np.array([[0, 0, 1.0]]))
    >>> sorted(out)
    ['acc', 'depth', 'rgb']
    """
    o, d = check_rays(origins, dirs)
    step = check_step(grid, step)
    q = grid.device.queue
    n = o.shape[0]
    if n == 0:
        return {"rgb": np.zeros((0, 3), np.float32), "depth": np.zeros(0, np.float32),
                "acc": np.zeros(0, np.float32)}
    bg = _host_background(background, n, q)
    out = render_forward_device(grid, upload(q, o), upload(q, d), step, bg)
    return {k: v.get() for k, v in out.items()}


def render_rays_backward(grid, origins, dirs, grad_rgb, step=0.5, background=(1.0, 1.0, 1.0),
                         ray_grad=False):
    """Gradient of ``sum(grad_rgb * rgb)`` with respect to the grid's values.

    Returns dense numpy ``density`` [X,Y,Z] and ``sh`` [X,Y,Z,C] (zeros at empty voxels); with
    a per-ray ``background`` [n, 3] also ``background`` [n, 3] = T_end * grad_rgb, its gradient;
    with ``ray_grad`` also ``ray_grad`` [n, 6], each ray's gradient with respect to its origin
    and direction (sample distances held: cl/grid_render.cl, GRID_POSE_GRAD).
    """
    o, d = check_rays(origins, dirs)
    g = check_array("grad_rgb", grad_rgb, ndim=2, shape_tail=(3,))
    if g.shape[0] != o.shape[0]:
        raise ValueError(f"grad_rgb has {g.shape[0]} rows for {o.shape[0]} rays")
    step = check_step(grid, step)
    q = grid.device.queue
    n = o.shape[0]
    bg = _host_background(background, n, q)
    gd = device_zeros(q, grid.density.shape[0], np.float32)
    gs = device_zeros(q, grid.sh.shape, np.float32)
    gbg = None
    rg = device_empty(q, (n, 6), np.float32) if ray_grad and n else None
    if n:
        gbg = render_backward_device(grid, upload(q, o), upload(q, d),
                                     upload(q, g), step, bg, gd, gs, ray_grad=rg)
    dens, sh = grid.rows_to_dense(gd.get(), gs.get())
    out = {"density": dens, "sh": sh}
    if ray_grad:
        out["ray_grad"] = rg.get() if rg is not None else np.zeros((0, 6), np.float32)
    if np.ndim(background) == 2:
        out["background"] = gbg.get() if gbg is not None else np.zeros((0, 3), np.float32)
    return out


def render_max_weight_device(grid, origins_d, dirs_d, step, maxw):
    """maxw[k] = max(maxw[k], max over samples of w_sample * w_corner) for rows k (device)."""
    dev = grid.device
    n = origins_d.shape[0]
    occ, oreso = block_occupancy(grid)
    launch(dev, grid_program(grid, step=step).kernel("render_max_weight"), n,
           (np.int32(n), origins_d.data, dirs_d.data, grid.links.data, grid.density.data,
            *grid.geometry_args(), np.float32(step), maxw.data, occ.data, oreso),
           dev.tuning.grid_local_size)
