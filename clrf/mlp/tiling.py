"""Register tiles of the fused MLP (cl/mlp.cl) per device: defaults from the device's vector
width, and the cache of the tuner's results (clrf/mlp/autotune.py) per device and MLP shape.

Choice order for each tile field (``MLPTiling``): a value set in ``MLPSpec`` > the tuned cache
entry for (platform, device, driver, MLP shape) > ``device_default(caps)``.

Defaults by device class (``device_default``; accumulators = rows x cols / 16 float16):

=====================================  ====  ====  =======  =======  ===============================
device                                 rows  cols  dw_rows  dw_cols  why
=====================================  ====  ====  =======  =======  ===============================
CPU, native float width >= 16 (AVX-512)  12    16        8       32  12 of 32 zmm (see below)
  the same, every layer <= NARROW_WIDTH     8    16        8       16  more, smaller tiles
CPU, native float width 8 (AVX2)          6    16        8       16  12 of 16 ymm (+ weight row)
CPU, native float width <= 4 (SSE, NEON)  2    16        2       16  8 xmm-sized registers
GPU / accelerator                         4    16        4       16  64 scalar registers per item
=====================================  ====  ====  =======  =======  ===============================

On AVX-512, 12 rows x 16 columns (12 float16 accumulators) beat the former 8 x 32 (16) in
interleaved tools/nerf_bench.py runs on a Zen 4 (forward + backward against numpy at 8,192
samples; two runs before the MLP's software prefetch, 8x256 skip 4: 1.06x / 0.97x against
0.99x / 0.91x, 4x64: 0.81x / 0.99x against 0.64x / 0.71x; two with it, 8x256: 1.09x / 1.08x
against 1.03x / 1.04x, 4x64: 0.99x / 1.01x against 0.93x / 1.00x): each weight row loaded
serves 12 samples instead of 8, and the tile count (work-groups) falls by a third. 16 x 16
measured the same as 12 x 16 within noise.
Narrow MLPs (every layer at most NARROW_WIDTH = 128 wide: the tiny preset's 4 x 64) have too
few tiles for that: a 64 x 64 weight gradient in 8 x 32 tiles is 16 tiles a chunk. There 8 x 16
with an 8 x 16 weight-gradient tile (chunk 512) was the fastest in three interleaved
tools/nerf_bench.py runs on the Zen 4 (4x64 at 8,192 samples, forward + backward against
numpy: 1.13x / 1.13x / 1.04x against 0.98x / 0.95x / 0.96x for 12 x 16 / 8 x 32; the tuner
picked it, or 6 x 16 with the same weight-gradient tile, on its own), and 2x128 1.22x against
1.12x; for 8x256 skip 4 it was slower (1.04x / 1.06x against 1.06x / 1.09x), so wide MLPs keep
12 x 16 / 8 x 32.
On AVX2 a float16 takes two ymm registers, so the AVX-512 tiles spill. The AVX2
weight-gradient tile was the fastest of 2x32, 4x16, 4x32 and 8x16 on a Zen 3 (its CPU time,
interleaved rounds). The GPU row is a register-budget guess (one work-item per tile, no local
memory), not a measurement; GPUs run the GPU tiling (below) and use it only with
``CLRF_FORCE_GPU_KERNELS=0``. ``dw_chunk`` (rows per partial weight
gradient) defaults to 64 tiles of ``rows`` samples.

    python -m clrf.nerf.autotune --width 256 --depth 8 --skip 4 --color-width 128 --in-dim 63 \\
        --dir-dim 27     # times the candidates, prints them, caches the best

The cache is JSON at ``$XDG_CACHE_HOME/clrf/mlp_tiling.json`` (default ``~/.cache/clrf``),
written atomically; an unreadable or malformed file is ignored (and replaced on the next tune).

GPU tiling. The register tiles above are CPU-shaped: one work-item per tile, no local memory.
On an NVIDIA H100 they reached 0.8 % of the FP32 FMA peak. Devices whose tuning has
``gpu_kernels`` (clrf/runtime/tuning.py: GPU devices, or any device with
``CLRF_FORCE_GPU_KERNELS=1``; ``=0`` keeps the CPU tiles on a GPU) build cl/mlp.cl with
``MLP_GPU=1`` instead (cl/mlp_gpu.h): a work-group of ``GPUTiling.wg`` work-items runs a block
of samples through every layer with the block's activations in local memory. ``gpu_default``
gives the work-group size (256, clamped to the device's maximum; the MLP halves it where a
built kernel allows fewer) and the local memory the kernel may use (the device's); the kernel
then picks its samples per work-item and K-slice rows as the largest that fit (mlp_gpu.h),
except on Intel GPUs, whose samples per work-item are INTEL_GPU_TM (register spills). The
weight gradient's chunk (rows per partial gradient) is chosen per batch so that its work-groups
fill the device (``GPU_GROUPS_PER_CU`` per compute unit, chunks of at least ``GPU_MIN_CHUNK``
rows), unless ``MLPSpec.dw_chunk`` sets it. The defaults were chosen from the device limits
(48 KiB of local memory on NVIDIA), not measured; the tuner (clrf/mlp/autotune.py) times
``gpu_candidates`` (work-group size, samples and columns per work-item, K-slice rows, the
weight gradient's tile) at batches that fill a GPU (2^18 samples by default) and caches the
fastest per device and MLP shape beside the CPU tiles, which ``mlp_tiling_for`` then prefers
to ``gpu_default``.
"""
from __future__ import annotations

import json
import os
from dataclasses import dataclass, fields, replace
from pathlib import Path

from ..runtime.atomicfile import write_text

TILE_FIELDS = ("rows", "cols", "dw_rows", "dw_cols", "dw_chunk")
MLP_ROWS = (1, 2, 3, 4, 5, 6, 8, 12, 16)   # the register-tile heights cl/mlp.cl accepts (the
#                                            nerf and hash sections' mlp_rows)
CHUNK_TILES = 64            # default dw_chunk = CHUNK_TILES * rows
CACHE_VERSION = 3   # bumped when cl/mlp.cl's kernels change (work split, v2; software prefetch,
                    # v3): older timings do not carry over


GPU_WG = 256            # work-items per group of the GPU tiling (before the device's clamp)
INTEL_GPU_TM = 2        # GPU_TM (samples per work-item) on Intel GPUs: with the kernel's own
# choice (the most that fit in local memory: 8) IGC spilled 5.2-7.7 KB per thread of
# mlp_forward / mlp_density / mlp_backward at SIMD8 on Xe-LP (tgllp) and up to 1 KB on Xe-HPG
# (dg2); with 4 the hash model's backward still spilled (192 / 96 B); with 2 nothing spills on
# tgllp for any MLP shape the library builds, and on dg2 only the NeRF tiny forward, 256 B
# (tools/gpu_builds.py, ocloc of compute runtime 22.43). Not measured on such a GPU; the tuner
# still times 4 (GPU_NEIGHBOURS).
GPU_GROUPS_PER_CU = 4   # the GPU weight gradient: chunks enough for this many groups per unit
GPU_MIN_CHUNK = 256     # ... but no chunk under this many rows (16 staging steps of 16)


@dataclass(frozen=True)
class GPUTiling:
    """The GPU tiling of cl/mlp_gpu.h (MLP_GPU=1). Fields left None are the kernel's choice:
    the largest tiles that fit in ``local_max`` bytes of local memory (mlp_gpu.h)."""

    wg: int = GPU_WG       # GPU_WG: work-items per group, a power of two
    local_max: int = 32768  # GPU_LOCAL_MAX: local memory a group may use (the device's)
    tm: int | None = None  # GPU_TM: samples per work-item, 1, 2, 4 or 8
    tn: int | None = None  # GPU_TN: output columns per work-item, 1, 2, 4 or 8 (kernel: 4)
    nc: int | None = None  # GPU_NC: output columns per pass (kernel: the trunk width's power
    #                        of two, at most 256)
    bk: int | None = None  # GPU_BK: weight rows per K-slice staged in local memory
    dw_bj: int | None = None  # GPU_DW_BJ: output neurons per weight-gradient group (kernel: 64)
    dw_bs: int | None = None  # GPU_DW_BS: scratch rows staged per step there (kernel: 16)
    chunk: int | None = None  # rows per partial weight gradient, a kernel argument; None:
    #                           per batch (GPU_GROUPS_PER_CU, GPU_MIN_CHUNK)

    def defines(self) -> dict:
        d = {"MLP_GPU": 1, "GPU_WG": self.wg, "GPU_LOCAL_MAX": self.local_max}
        for name, key in (("tm", "GPU_TM"), ("tn", "GPU_TN"), ("nc", "GPU_NC"), ("bk", "GPU_BK"),
                          ("dw_bj", "GPU_DW_BJ"), ("dw_bs", "GPU_DW_BS")):
            if getattr(self, name) is not None:
                d[key] = getattr(self, name)
        return d


@dataclass(frozen=True)
class MLPTiling:
    """The register tiles of cl/mlp.cl (its defines MLP_ROWS, MLP_COLS, DW_ROWS, DW_COLS,
    DW_CHUNK; the kernel rejects invalid values with #error), or with ``gpu`` set its GPU
    tiling (the CPU fields are then unused)."""

    rows: int = 8          # samples per work-item in forward / input gradient: 1-6, 8, 12, 16
    cols: int = 32         # columns per tile there: 32 (two float16) or 16 (one)
    dw_rows: int = 8       # output neurons per work-item in the weight gradient; divides 16
    dw_cols: int = 32      # input columns per work-item there: 32 or 16
    dw_chunk: int = 512    # scratch rows per partial weight gradient; rounded up to rows
    gpu: GPUTiling | None = None   # the GPU tiling (cl/mlp_gpu.h) instead of the tiles above

    def defines(self) -> dict:
        if self.gpu is not None:
            return self.gpu.defines()
        chunk = -(-self.dw_chunk // self.rows) * self.rows
        return {"MLP_ROWS": self.rows, "MLP_COLS": self.cols, "DW_ROWS": self.dw_rows,
                "DW_COLS": self.dw_cols, "DW_CHUNK": chunk}


def tile_fields(tiling: MLPTiling) -> dict:
    """The CPU tile fields of ``tiling`` (TILE_FIELDS), as MLPSpec takes them."""
    return {k: getattr(tiling, k) for k in TILE_FIELDS}


def gpu_default(caps, chunk: int | None = None) -> GPUTiling:
    """The GPU tiling on a device (Capabilities): GPU_WG work-items per group, clamped to the
    largest power of two the device allows, and the device's local memory; on Intel GPUs
    INTEL_GPU_TM samples per work-item (elsewhere the kernel's choice)."""
    from ..runtime.tuning import implementation
    wg = 1
    while wg * 2 <= min(GPU_WG, caps.max_work_group_size):
        wg *= 2
    intel = implementation(getattr(caps, "platform", "")) == "intel-gpu"
    return GPUTiling(wg=wg, local_max=int(caps.local_mem_size),
                     tm=INTEL_GPU_TM if intel else None, chunk=chunk)


GPU_FIELDS = ("wg", "tm", "tn", "nc", "bk", "dw_bj", "dw_bs")   # tuned, cached
GPU_KEY = "gpu "   # cache entries of the GPU tiling: this prefix and the shape key
GPU_NEIGHBOURS = ({"tm": 4}, {"tm": 2}, {"tn": 2}, {"tn": 8}, {"bk": 8}, {"bk": 4},
                  {"dw_bj": 32}, {"dw_bs": 32}, {"dw_bs": 8}, {"wg": 0.5}, {"wg": 0.5, "tm": 4},
                  {"wg": 0.25})


def gpu_candidates(caps) -> list:
    """The GPU tilings the tuner times: gpu_default first (the kernel's own choices in the
    device's local memory), then single changes of it (GPU_NEIGHBOURS; a float "wg" scales the
    work-group, kept at 32 or more). Some may not build on a device (local memory, the
    kernel's #error checks); the tuner skips those."""
    base = gpu_default(caps)
    out = [base]
    for change in GPU_NEIGHBOURS:
        c = dict(change)
        if "wg" in c:
            c["wg"] = int(base.wg * c["wg"])
            if c["wg"] < 32:
                continue
        t = replace(base, **c)
        if t not in out:
            out.append(t)
    return out


NARROW_WIDTH = 128   # AVX-512: MLPs no wider than this get the narrow tile (module docstring)


def device_default(caps, spec=None) -> MLPTiling:
    """The tile for a device class (table in the module docstring), from Capabilities; on
    AVX-512 it also depends on the widest layer of ``spec`` (None: a wide MLP)."""
    narrow = spec is not None and max(spec.width, spec.color_width) <= NARROW_WIDTH
    if caps.type != "cpu":
        rows, cols, dwr, dwc = 4, 16, 4, 16
    elif caps.native_float_width >= 16 and narrow:
        rows, cols, dwr, dwc = 8, 16, 8, 16
    elif caps.native_float_width >= 16:
        rows, cols, dwr, dwc = 12, 16, 8, 32
    elif caps.native_float_width >= 8:
        rows, cols, dwr, dwc = 6, 16, 8, 16
    else:
        rows, cols, dwr, dwc = 2, 16, 2, 16
    return MLPTiling(rows, cols, dwr, dwc, CHUNK_TILES * rows)


def candidates(caps, spec=None) -> list:
    """The tiles the tuner times: the device default first, then a few neighbours."""
    shapes = [(12, 16, 8, 32), (16, 16, 8, 32), (8, 32, 8, 32), (6, 16, 8, 16), (6, 16, 4, 32),
              (6, 16, 4, 16), (4, 16, 8, 16), (8, 16, 8, 16), (3, 32, 8, 16), (4, 32, 4, 32)]
    out = [device_default(caps, spec)]
    for r, c, dr, dc in shapes:
        t = MLPTiling(r, c, dr, dc, CHUNK_TILES * r)
        if t not in out:
            out.append(t)
    return out


# ---- cache ----------------------------------------------------------------------------------
def cache_path() -> Path:
    base = os.environ.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"), ".cache")
    return Path(base) / "clrf" / "mlp_tiling.json"


def device_key(caps) -> str:
    return f"{caps.platform} | {caps.name} | {caps.driver_version}"


def shape_key(spec) -> str:
    """The MLP shape (every MLPSpec field that is not a tile field) as a stable string; the
    fields added for the hash model (color_depth, features) only when they differ from NeRF's
    shape, so that tiles tuned before them keep their keys."""
    later = {"color_depth": 1, "features": None}
    return json.dumps({f.name: getattr(spec, f.name) for f in fields(spec)
                       if f.name not in TILE_FIELDS
                       and not (f.name in later and getattr(spec, f.name) == later[f.name])},
                      sort_keys=True)


def load_cache(path: Path | None = None) -> dict:
    """{device_key: {shape_key: entry}}; {} when missing, unreadable or malformed."""
    path = path or cache_path()
    try:
        data = json.loads(path.read_text())
    except (OSError, ValueError):
        return {}
    if not isinstance(data, dict) or data.get("version") != CACHE_VERSION:
        return {}
    entries = data.get("entries")
    if not isinstance(entries, dict) or not all(isinstance(v, dict) for v in entries.values()):
        return {}
    return entries


def cached_tiling(caps, spec, path: Path | None = None) -> MLPTiling | None:
    """The tuned tile for this device and MLP shape, or None (absent or malformed entry)."""
    e = load_cache(path).get(device_key(caps), {}).get(shape_key(spec))
    if not isinstance(e, dict):
        return None
    vals = [e.get(k) for k in TILE_FIELDS]
    if not all(isinstance(v, int) and not isinstance(v, bool) and v > 0 for v in vals):
        return None
    return MLPTiling(*vals)


def cached_gpu_tiling(caps, spec, path: Path | None = None) -> GPUTiling | None:
    """The tuned GPU tiling for this device and MLP shape (with the device's local memory), or
    None (absent or malformed entry)."""
    e = load_cache(path).get(device_key(caps), {}).get(GPU_KEY + shape_key(spec))
    if not isinstance(e, dict) or not isinstance(e.get("wg"), int):
        return None
    vals = {k: e.get(k) for k in GPU_FIELDS}
    if not all(v is None or (isinstance(v, int) and not isinstance(v, bool) and v > 0)
               for v in vals.values()):
        return None
    return GPUTiling(local_max=int(caps.local_mem_size), **vals)


def store_tiling(caps, spec, tiling: MLPTiling, info: dict, path: Path | None = None):
    """Record ``tiling`` (and ``info``: timings) for this device and shape; atomic replace.
    A tiling with ``gpu`` set records the GPU tiling's fields (a separate entry)."""
    path = path or cache_path()
    entries = load_cache(path)
    if tiling.gpu is not None:
        key = GPU_KEY + shape_key(spec)
        fields_ = {k: getattr(tiling.gpu, k) for k in GPU_FIELDS}
    else:
        key, fields_ = shape_key(spec), tile_fields(tiling)
    entries.setdefault(device_key(caps), {})[key] = {**fields_, **info}
    path.parent.mkdir(parents=True, exist_ok=True)
    write_text(path, json.dumps({"version": CACHE_VERSION, "entries": entries}, indent=1,
                                sort_keys=True), sync=False)       # a cache: tuned again


def mlp_tiling_for(device, spec, path: Path | None = None) -> MLPTiling:
    """The tile an MLP of ``spec`` uses on ``device``: MLPSpec fields that are set, then the
    tuned cache entry, then the device default. dw_chunk, when not set anywhere, is
    CHUNK_TILES * rows. Where the device's tuning asks for the GPU tiling (``gpu_kernels``), the
    result carries the tuned GPU tiling, else ``gpu_default`` (with MLPSpec.dw_chunk as its
    chunk, when set)."""
    base = cached_tiling(device.caps, spec, path) or device_default(device.caps, spec)
    chosen = {k: getattr(spec, k) for k in TILE_FIELDS if getattr(spec, k) is not None}
    if "rows" in chosen and "dw_chunk" not in chosen and base.rows != chosen["rows"]:
        chosen["dw_chunk"] = CHUNK_TILES * chosen["rows"]
    tiling = replace(base, **chosen)
    if getattr(getattr(device, "tuning", None), "gpu_kernels", False):
        gpu = cached_gpu_tiling(device.caps, spec, path) or gpu_default(device.caps)
        tiling = replace(tiling, gpu=replace(gpu, chunk=spec.dw_chunk))
    return tiling
