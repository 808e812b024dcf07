"""Per-device tuning: the work-group sizes, code-path switches and prefetch distances the kernel
wrappers pass to the kernels as ``-D`` defines or launch sizes.

The Device builds one ``Tuning`` (``dev.tuning``) from its capabilities with
``Tuning.for_device``; the wrappers read it and nothing else. Environment overrides are read
in one place, ``Tuning.from_env`` (called by the Device), and only these variables:

  CLRF_GRAD_SLOTS            grad_slots (0 = float atomics, the GPU path)
  CLRF_SAMPLE_RECORD         sample_record (0 / 1)
  CLRF_GRAD_LOCKS            grad_locks (0 = private gradient copies per slot)
  CLRF_GRAD_MERGE            grad_merge (0 = each sample's grid gradients added as it is met)
  CLRF_PREFETCH              prefetch (0 / 1)
  CLRF_MLP_PREFETCH          mlp_prefetch (0 / 1)
  CLRF_PREFETCH_AHEAD        prefetch_ahead
  CLRF_PREFETCH_LINKS_AHEAD  prefetch_links_ahead
  CLRF_BLOCK                 block (0 = no empty-block skipping)
  CLRF_BLOCK_FINE            block_fine (0 = no second, finer level)
  CLRF_RAY_ORDER             ray_order (0 = render rays in the order given)
  CLRF_FAST_MATH             fast_math (0 / 1: -cl-fast-relaxed-math; changes results)
  CLRF_VERBOSE_BUILD         verbose_build (0 / 1: print the raw compiler logs)
  CLRF_FORCE_GPU_KERNELS     gpu_kernels (1: the GPU-shaped kernels on any device, e.g. to test
                             them on PoCL or Oclgrind: the fused MLP's GPU tiling, the splat
                             rasteriser's work-group per tile, steps that keep their sizes and
                             losses on the device and one Adam launch a step; 0: the CPU
                             shapes, also on a GPU)

>>> t = Tuning.for_device(dev.caps)
>>> gpu_path = t.replace(grad_slots=0, sample_record=False)
"""
from __future__ import annotations

import dataclasses
import os
from dataclasses import dataclass

# CPU devices sort batches of at least this many rays (the keys kernel, the host round trip
# and the argsort took ~0.6 ms for 4,096 rays on a Zen 4; a dense-grid ray costs ~25 us).
RAY_ORDER_MIN_RAYS = 256

# CPU devices add gradients under locks of 16^3-voxel blocks (grad_locks 4). In-process A/B on
# the Zen 4 (2 compute units), 128^3 SH2, 4,096 camera rays, fused forward + backward, against
# private copies per slot: dense 7-14 % faster (the copies' reduction took 12-15 ms of ~115),
# 5 %-occupied 6-7 % faster; 8 of 1.67 M touched rows found their lock taken (2^5: 40; 2^3
# was slower, more locks per cell).
GRAD_LOCKS_LOG2 = 4

def implementation(platform_name: str) -> str:
    """Short name of the OpenCL implementation behind a platform name: "pocl", "intel"
    (Intel's oneAPI CPU runtime), "intel-gpu", "rusticl", "oclgrind", "clover", "nvidia",
    "amd", else the name's first word."""
    p = platform_name.strip().lower()
    for key, name in (("portable computing language", "pocl"),
                      ("intel(r) opencl hd", "intel-gpu"),
                      ("intel(r) opencl graphics", "intel-gpu"),
                      ("intel(r) opencl", "intel"),
                      ("rusticl", "rusticl"), ("oclgrind", "oclgrind"), ("clover", "clover"),
                      ("nvidia", "nvidia"), ("amd accelerated", "amd")):
        if key in p:
            return name
    return p.split()[0] if p else "unknown"


# Per-implementation entries over the capability defaults, each set by measurement: in-process
# interleaved runs of the same cases (tools/impl_bench.py for the grid, tools/nerf_bench.py
# for the MLP), 2 vCPUs of an AMD EPYC Zen 4 (AVX-512), PoCL 3.1 (Debian, LLVM 15) beside
# Intel's CPU runtime 2026.22.10; docs/implementations.md has the tables.
#  - PoCL vectorises what is written as vectors and compiles __builtin_prefetch: prefetch in
#    the march and in the MLP.
#  - Intel's runtime: 8 rays per work-group (the forward ran 1.4-2x faster than with 32:
#    more groups to balance over its threads), prefetch in the march with OpenCL C's
#    prefetch() (grid forward + backward 0.65x -> 0.76-0.90x PoCL dense, 0.82x -> 0.94-1.00x
#    5 %-occupied), none in the MLP (its weight gradient took twice as long with it).
IMPLEMENTATIONS = {   # CPU devices only
    "pocl": {"prefetch": True, "mlp_prefetch": True},
    "intel": {"grid_local_size": 8, "prefetch": True, "mlp_prefetch": False},
}

# Work-group sizes of GPUs (none measured on one yet), chosen from the hardware's limits: the
# CPU sizes (the grid renderer's 32 rays, the per-ray kernels' 16, the encoding's 8) fill a
# half, a quarter or an eighth of a 64-wide wave on AMD's GCN and CDNA (ROCm's gfx6xx to gfx9xx:
# Instinct MI100 to MI300 are gfx908, gfx90a, gfx942; tools/gpu_builds.py builds them wave64),
# 16 and 8 fill half or a quarter of a 32-wide warp (NVIDIA), wave32 (RDNA) or SIMD32 thread
# (the width Intel's compiler picks for the per-ray kernels), and NVIDIA keeps at most 32 groups
# resident per SM (sm_70, sm_80, sm_90; 16 on sm_75 and sm_86), so groups of 32 would cap a
# Hopper SM at 1,024 of its 2,048 threads. Groups of 64 are one wave64, two warps or wave32s,
# two to four Intel hardware threads, and let an sm_90 fill (sm_86: 1,024 of 1,536).
GPU_GROUPS = {"grid_local_size": 64, "per_ray_local_size": 64, "encode_local_size": 64}


# Intel GPUs: the grid backward adds each sample's gradients as it meets them (grad_merge off).
# No Intel GPU has been measured; the choice is from the offline builds (tools/gpu_builds.py,
# ocloc of compute runtime 22.43): with the per-cell sums held across the march,
# render_backward spilled 1.0-1.8 KB per hardware thread on Xe-LP (tgllp, every program of the
# GPU shape), and 0 B with the sums gone, at every SH degree and mode. Xe-HPG (dg2) did not
# spill either way; it takes the same path, one Intel build.
INTEL_GPU = {"grad_merge": False}

ENV = {
    "CLRF_GRAD_SLOTS": ("grad_slots", int),
    "CLRF_SAMPLE_RECORD": ("sample_record", lambda v: v != "0"),
    "CLRF_GRAD_LOCKS": ("grad_locks", int),
    "CLRF_GRAD_MERGE": ("grad_merge", lambda v: v != "0"),
    "CLRF_PREFETCH": ("prefetch", lambda v: v != "0"),
    "CLRF_MLP_PREFETCH": ("mlp_prefetch", lambda v: v != "0"),
    "CLRF_PREFETCH_AHEAD": ("prefetch_ahead", int),
    "CLRF_PREFETCH_LINKS_AHEAD": ("prefetch_links_ahead", int),
    "CLRF_BLOCK": ("block", int),
    "CLRF_BLOCK_FINE": ("block_fine", int),
    "CLRF_RAY_ORDER": ("ray_order", int),
    "CLRF_FAST_MATH": ("fast_math", lambda v: v != "0"),
    "CLRF_VERBOSE_BUILD": ("verbose_build", lambda v: v != "0"),
    "CLRF_FORCE_GPU_KERNELS": ("gpu_kernels", lambda v: v != "0"),
}


def slots_order_memory(caps) -> bool:
    """Whether the grid backward's gradient slots and block locks (GRAD_SLOTS > 0) give right
    gradients on a device with ``caps``: with acquire/release atomics (by the OpenCL memory
    model), or on a CPU device, whose compute units run one work-item at a time (what a user
    who forces them there relies on). A GPU without them runs many work-groups at once, and
    OpenCL 1.2 fences order nothing between them: on NVIDIA's driver (no acquire/release)
    half the gradient entries of the slot tests came out wrong, some by 0.5 on values near 1."""
    return caps.type == "cpu" or bool(getattr(caps, "acq_rel", False))


@dataclass(frozen=True)
class Tuning:
    """How the kernels run on one device. Results do not depend on it (except fast_math)."""

    grid_local_size: int = 32      # rays per work-group of the grid render kernels
    grad_slots: int = 0            # render_backward: N > 0 private gradient copies (one per
    #                                compute unit: the CPU path, no atomics); 0 float atomics
    #                                into the gradient buffers (the GPU path)
    grad_locks: int = 0            # with grad_slots > 0: n > 0 every work-item adds into the
    #                                caller's gradient buffers under try-locks of 2^n-voxel
    #                                blocks (one scratch copy takes what finds a lock taken);
    #                                0: a private copy per slot, all reduced afterwards
    grad_merge: bool = True        # with grad_slots 0: render_backward sums a cell's corner
    #                                gradients over its samples and adds them with atomics when
    #                                the march leaves the cell (GRAD_MERGE 1); False: each
    #                                sample's as it is met (more atomics, fewer live registers;
    #                                Intel GPUs, INTEL_GPU)
    sample_record: bool = False    # backward reads the forward march's per-sample record
    #                                (needs grad_slots > 0: the record lives in the slot)
    prefetch: bool = False         # software prefetch in the grid march (__builtin_prefetch
    #                                on clang targets, OpenCL C's prefetch() on SPIR ones)
    mlp_prefetch: bool = False     # the same in the fused MLP's backward and weight gradient
    prefetch_ahead: int = 3        # samples ahead for a cell's rows (~1.5 voxels at step 0.5)
    prefetch_links_ahead: int = 6  # samples ahead for a cell's links
    block: int = 8                 # empty-space skipping over block^3-cell blocks (0: off)
    block_fine: int = 2            # then over block_fine^3-cell blocks inside occupied ones
    #                                (0: off)
    ray_order: int = 0             # render_forward / render_backward of >= ray_order rays
    #                                (0: never) run them sorted by the block that holds their
    #                                path's midpoint (RAY_ORDER; dense grids only), so
    #                                consecutive rays share cached rows
    reduce_local_size: int = 64    # work-items (of 16 rows each) per group of grad_slots_reduce
    mlp_fused_local_size: int = 1  # work-items per group of the fused MLP kernels (big tiles)
    gpu_kernels: bool = False      # the GPU shapes instead of the CPU ones (default: GPU
    #                                devices): the fused MLP's work-groups of samples in local
    #                                memory (cl/mlp_gpu.h, clrf/mlp/tiling.py) instead of its
    #                                register tiles; the splat rasteriser's TILE x TILE
    #                                work-group per tile instead of one vectorised work-item per
    #                                tile (cl/splat_raster.cl); training steps that read nothing
    #                                back (the hash model's bounded step, losses as Pending) and
    #                                one Adam launch for all parameter buffers (AdamSet)
    elementwise_local_size: int = 64   # loop-free kernels: PoCL vectorises across the group
    per_ray_local_size: int = 16   # one ray per work-item with a loop over its samples
    encode_local_size: int = 8     # encode_forward: explicitly vectorised items (16 points)
    fast_math: bool = False        # -cl-fast-relaxed-math (off: results follow the references)
    verbose_build: bool = False    # print the raw compiler log (else only its diagnostics)

    @classmethod
    def for_device(cls, caps) -> "Tuning":
        """Defaults from capabilities: CPU devices get one slot (with its per-sample record)
        per compute unit, block-locked gradient adds (GRAD_LOCKS_LOG2) and sorted rays from
        RAY_ORDER_MIN_RAYS on, GPU devices the fused MLP's GPU tiling and groups of 64
        (GPU_GROUPS); then, for CPU devices, each implementation's entry (IMPLEMENTATIONS)."""
        cpu = caps.type == "cpu"
        # the slots and block locks need locks that order plain memory between work-groups,
        # which OpenCL 1.2 atomics do not promise: without acquire/release atomics a CPU
        # device takes the float-atomic path, correct by the specification alone
        slots = cpu and getattr(caps, "acq_rel", False)
        t = cls(grad_slots=caps.compute_units if slots else 0, sample_record=slots,
                grad_locks=GRAD_LOCKS_LOG2 if slots else 0,
                ray_order=RAY_ORDER_MIN_RAYS if cpu else 0, gpu_kernels=caps.type == "gpu")
        impl = implementation(getattr(caps, "platform", ""))
        if not cpu and caps.type == "gpu":
            return t.replace(**GPU_GROUPS, **(INTEL_GPU if impl == "intel-gpu" else {}))
        return t.replace(**(IMPLEMENTATIONS.get(impl, {}) if cpu else {}))

    @classmethod
    def from_env(cls, caps, environ=None) -> "Tuning":
        """for_device, then the CLRF_* overrides listed in the module docstring."""
        environ = os.environ if environ is None else environ
        t, kw = cls.for_device(caps), {}
        for var, (field, conv) in ENV.items():
            v = environ.get(var, "").strip()
            if v:
                try:
                    kw[field] = conv(v)
                except ValueError:
                    raise ValueError(f"{var}={v!r}: expected an integer") from None
        if "prefetch_ahead" in kw and "prefetch_links_ahead" not in kw:
            kw["prefetch_links_ahead"] = 2 * kw["prefetch_ahead"]
        return t.replace(**kw)

    def scratch_copies(self, slots: int) -> int:
        """Scratch gradient copies the grid backward holds with ``slots`` slots: none on the
        atomic path (0 slots), one shared by the work-items that find a block lock taken
        (grad_locks), else one per slot."""
        if slots <= 0:
            return 0
        return 1 if self.grad_locks > 0 else int(slots)

    def replace(self, **kw) -> "Tuning":
        """A copy with the given fields changed."""
        return dataclasses.replace(self, **kw)
