"""Host side of cl/hash_march.cl: the hash model's packed samples (stratified bins kept only in
occupied cells) and their compositing (math and layouts in the kernel file's header).

>>> pk = march(dev, occ, origins_d, dirs_d, S=128, near=2.0, far=6.0)   # all bins, no jitter
>>> pk.m, pk.offsets_host[:3], pk.t, pk.dt, pk.xyz, pk.vdir             # device t [M], ...
>>> g = packed_backward(dev, pk, sigma_d, rgb_d, bg, target_d, loss_scale)
>>> kept, (xe,) = keep_front(dev, pk, sigma_d, 1e-4, (xe_d,))   # what lies before T < 1e-4
>>> g_od = ray_grad(dev, pk, origins_d, dirs_d, gp_d, gsh_d)    # dL/d(o, d) [n, 6] device
>>> pk = march(dev, occ, origins_d, dirs_d, 256, 0.02, 1e3, contract=Contraction(box))
>>> pk = march(dev, occ, origins_d, dirs_d, 128, 2.0, 6.0, cap=1 << 18)   # bounded: nothing
>>> pk.m, pk.count, pk.total          # read back; m = 2^18 rows, count/total on the device
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import pyopencl as cl
import pyopencl.array as cla

from ..runtime.programs import device_zeros, float4, launch, scratch
from ..runtime.scan import capped_offsets, row_offsets

STATE = 8   # floats of per-ray state of packed_forward (cl/hash_march.cl ST)


@dataclass
class Packed:
    """The live samples of a batch of n rays: ray i's rows offsets[i] .. offsets[i+1]-1.
    Bounded (``count`` set): the arrays have m rows, a fixed capacity, of which the first
    count[0] (on the device) are live; no size was read back."""
    n: int
    m: int
    offsets: cla.Array        # int32 [n + 1] (device)
    t: cla.Array              # [M]
    dt: cla.Array             # [M] the segment each sample stands for (its bin's length)
    xyz: cla.Array            # [M, 3] the encoding's points (contracted under a Contraction)
    vdir: cla.Array           # [M, 3]
    count: cla.Array | None = None   # bounded: int32 [1] live rows (device), else None
    total: cla.Array | None = None   # bounded: int64 [1] live samples before the cap (device)

    @property
    def offsets_host(self) -> np.ndarray:
        """The offsets as int64 numpy [n + 1] (a download: for tests and tools, not the step)."""
        return self.offsets.get()[:self.n + 1].astype(np.int64)


class Contraction:
    """The scene contraction of unbounded scenes about an inner box (cl/hash_march.cl): the box
    maps to [-1, 1]^3 and all of space to [-2, 2]^3, the box of the encoding and the occupancy
    grid. Samples are spaced evenly in log t."""

    BOX = np.array([[-2.0] * 3, [2.0] * 3])   # the contracted space

    def __init__(self, inner_box):
        b = np.asarray(inner_box, np.float64)
        self.centre = (b[0] + b[1]) / 2
        self.half = (b[1] - b[0]) / 2
        if not np.all(self.half > 0):
            raise ValueError(f"contraction: the inner box {b.tolist()} needs positive extents")
        self.centre4 = float4(*self.centre, 0.0)
        self.inv_half4 = float4(*(1.0 / self.half), 0.0)


def program(device, contract: bool = False, pose: bool = False):
    """cl/hash_march.cl; ``pose``: the build with packed_ray_grad (HASH_POSE_GRAD), a program
    of its own so that the default one is what it was."""
    defines = {"HASH_CONTRACT": int(bool(contract))}
    if pose:
        defines["HASH_POSE_GRAD"] = 1
    return device.program("hash_march.cl", defines)


def contract_points(device, contraction: Contraction, xyz):
    """The encoding's points [m, 3] (device) of world points xyz [m, 3] (device)."""
    m = int(xyz.shape[0])
    out = scratch(device, (max(m, 1), 3))
    if m:
        launch(device, program(device, True).kernel("contract_points"), m,
               (np.int32(m), contraction.centre4, contraction.inv_half4, xyz.data, out.data),
               device.tuning.elementwise_local_size)
    return out[:m]


def march(device, occ, origins, dirs, S: int, near: float, far: float, jitter: bool = False,
          key: int = 0, k0: int = 0, k1: int | None = None, alive=None,
          contract: Contraction | None = None, cap: int | None = None) -> Packed:
    """The live samples of bins k0 .. k1-1 (default all S) of the rays origins/dirs [n, 3]
    (device) through the occupancy grid ``occ`` (OccupancyGrid), for rays with alive[i] != 0
    (uchar device array [n]; None: all). ``contract``: log-spaced bins and contracted points
    (occ then covers Contraction.BOX). The per-ray counts are scanned on the device; one
    number comes back (the total, to size the sample arrays). A scratch byte per (ray, bin)
    marks the live ones. ``cap``: bounded, nothing comes back: the arrays have cap rows and
    the offsets stop at cap (a ray past it keeps the live samples that fit, later rays none;
    Packed.total says how many there were)."""
    n = int(origins.shape[0])
    k1 = S if k1 is None else int(k1)
    dev, q = device, device.queue
    prg = program(device, contract is not None)
    W = k1 - k0
    counts = scratch(dev, max(n, 1), np.int32)
    live = scratch(dev, max(n * W, 1), np.uint8)
    zero4 = float4(0, 0, 0, 0)
    centre = contract.centre4 if contract else zero4
    inv_half = contract.inv_half4 if contract else zero4
    bins = (np.int32(n), np.int32(S), np.int32(k0), np.int32(k1), np.float32(near),
            np.float32(far), np.int32(bool(jitter)), np.uint32(key), origins.data, dirs.data)
    if n and W > 0:
        kern = prg.kernel("march_live")
        kern.set_args(*bins, occ.lo4, occ.inv4, np.int32(occ.res), centre, inv_half,
                      occ.occ.data, alive.data if alive is not None else None, live.data)
        cl.enqueue_nd_range_kernel(q, kern, (-(-W // 16), n), None)   # 16 bins an item
    launch(dev, prg.kernel("march_count"), n, (np.int32(n), np.int32(W), live.data, counts.data),
           dev.tuning.per_ray_local_size)
    count = total = None
    if cap is None:
        offsets, m = row_offsets(dev, counts, n)
    else:
        m = int(cap)
        offsets, count, total = capped_offsets(dev, counts, n, m)
    t = scratch(dev, max(m, 1))
    dt = scratch(dev, max(m, 1))
    xyz = scratch(dev, (max(m, 1), 3))
    vdir = scratch(dev, (max(m, 1), 3))
    if m:
        launch(dev, prg.kernel("march_compact"), n,
               bins + (centre, inv_half, live.data, offsets.data, t.data, dt.data, xyz.data,
                       vdir.data),
               dev.tuning.per_ray_local_size)
    return Packed(n, m, offsets, *(a[:m] if m else a for a in (t, dt, xyz, vdir)), count,
                  total)


def _bg4(background):
    bg = np.broadcast_to(np.asarray(background, np.float64), (3,))
    return float4(bg[0], bg[1], bg[2], 0.0)


def packed_forward(device, pk: Packed, sigma, rgb, state, alive=None):
    """Continue the per-ray composite state [n, STATE] (device, zero at the start) over pk's
    samples with sigma [M], rgb [M, 3]; clears alive[i] once T < HASH_T_STOP."""
    launch(device, program(device).kernel("packed_forward"), pk.n,
           (np.int32(pk.n), pk.offsets.data, pk.t.data, pk.dt.data, sigma.data, rgb.data,
            state.data, alive.data if alive is not None else None),
           device.tuning.per_ray_local_size)


def finish_state(state: np.ndarray, background) -> dict:
    """numpy rgb [n, 3] (foreground + T_end bg), depth [n], acc [n] of a final state."""
    bg = np.asarray(background, np.float32)
    T = np.exp(state[:, 5])
    return {"rgb": state[:, :3] + T[:, None] * bg[None, :], "acc": state[:, 3].copy(),
            "depth": state[:, 4].copy()}


def packed_backward(device, pk: Packed, sigma, rgb, background, target,
                    loss_scale: float) -> dict:
    """dict(sigma=dL/dsigma [M], rgb=dL/drgb [M, 3], sq_err=[n]) of the MSE loss
    loss_scale * sum |rgb_ray - target|^2 (target [n, 3] device)."""
    m = max(pk.m, 1)
    out = {"sigma": scratch(device, m), "rgb": scratch(device, (m, 3)),
           "sq_err": scratch(device, max(pk.n, 1))}
    launch(device, program(device).kernel("packed_backward"), pk.n,
           (np.int32(pk.n), pk.offsets.data, pk.t.data, pk.dt.data, sigma.data, rgb.data,
            _bg4(background), target.data, np.float32(loss_scale), out["sq_err"].data,
            out["sigma"].data, out["rgb"].data), device.tuning.per_ray_local_size)
    if pk.m == 0:
        out["sigma"], out["rgb"] = out["sigma"][:0], out["rgb"][:0]
    return out


def ray_grad(device, pk: Packed, origins, dirs, gp, gsh=None,
             contract: Contraction | None = None, out=None):
    """dL/d(origin, direction) [n, 6] (device, overwritten) of pk's rays origins/dirs [n, 3]
    from their samples' gp [M, 3] = dL/dp (p the encoding's point: HashEncoding.dx) and gsh
    [M, 16] = dL/d(SH basis of the view direction) or None (math: the kernel file's header):
    dL/do = sum_k dL/dx_k, dL/dd = (I - dh dh^T) / |d| sum_k (t_k dL/dx_k + dL/dY_k dY/dv)."""
    n = pk.n
    out = out if out is not None else scratch(device, (max(n, 1), 6))
    zero4 = float4(0, 0, 0, 0)
    centre = contract.centre4 if contract else zero4
    inv_half = contract.inv_half4 if contract else zero4
    launch(device, program(device, contract is not None, True).kernel("packed_ray_grad"), n,
           (np.int32(n), pk.offsets.data, pk.t.data, origins.data, dirs.data, centre, inv_half,
            gp.data, gsh.data if gsh is not None else None, out.data),
           device.tuning.per_ray_local_size)
    return out[:n]


def keep_front(device, pk: Packed, sigma, t_stop: float, rows=(), max_fraction: float = 1.0):
    """The samples of pk in front of each ray's first point of transmittance < t_stop (see
    packed_keep in the kernel file), as a new Packed, and the same rows of each array in rows
    (device [M, ...] float32, C-contiguous); None (nothing copied) when that keeps more than
    max_fraction of the samples. The kept counts are scanned on the device; one number comes
    back (the kept total). A bounded pk (count set): nothing comes back and the samples are
    always copied (max_fraction is not checked), into arrays of pk's capacity."""
    dev, q = device, device.queue
    prg = program(device)
    ls = dev.tuning.per_ray_local_size
    n = pk.n
    keep = scratch(dev, max(n, 1), np.int32)
    if pk.m:
        launch(dev, prg.kernel("packed_keep"), n, (np.int32(n), pk.offsets.data, pk.dt.data,
                                                    sigma.data, np.float32(t_stop), keep.data), ls)
    count = None
    if pk.count is not None:
        m = pk.m
        offsets, count, _ = capped_offsets(dev, keep, n, m)
    elif pk.m:
        offsets, m = row_offsets(dev, keep, n)
    else:                        # no sample: packed_keep did not run
        offsets, m = device_zeros(q, n + 1, np.int32), 0
    if count is None and m > max_fraction * pk.m:
        return None
    out = []
    for a in (pk.t, pk.dt, pk.xyz, pk.vdir, *rows):
        if a.dtype != np.float32 or not a.flags.c_contiguous:
            raise TypeError("keep_front: rows must be C-contiguous float32 device arrays")
        width = int(np.prod(a.shape[1:], dtype=np.int64))
        b = scratch(dev, (max(m, 1),) + tuple(a.shape[1:]), a.dtype)
        if m:
            launch(dev, prg.kernel("packed_gather"), n,
                   (np.int32(n), np.int32(width), pk.offsets.data, offsets.data, a.data,
                    b.data), ls)
        out.append(b[:m] if m else b)
    return Packed(n, m, offsets, *out[:4], count, pk.total), out[4:]
