"""The benchmark list: SPECS (grid, hash, splat and training), the peak specs, and external suites'
specs."""
from __future__ import annotations

import importlib

from . import framework
from .framework import EXTERNAL_SUITES, Spec, TOOLS
from .cases import _train_specs


# ---- the benchmark list ---------------------------------------------------------------------
def _grid_specs():
    base = {"step": 0.5, "n_rays": 4096}
    quick = {"reso": 16, "n_rays": 64}
    out = []

    def add(kind, prefix, min_repeats=None, **kw):
        p = dict(base, **kw)
        occ = "dense" if p["occupancy"] >= 1 else f"pruned{int(round(p['occupancy'] * 100))}"
        name = (f"{prefix}/{p.get('mode', 'fwd')}/{p['reso']}/sh{p['degree']}/{occ}/"
                f"{p['rays']}")
        out.append(Spec(name, kind, p, "samples/s", dict(quick), min_repeats=min_repeats))

    # 128^3: every SH degree, dense and pruned (5 %), coherent camera rays, fwd / fused fwd+bwd
    for deg in (0, 2, 3):
        for occ in (1.0, 0.05):
            for mode in ("fwd", "fwdbwd"):
                add("grid.render", "grid", reso=128, degree=deg, occupancy=occ, rays="camera",
                    mode=mode)
    add("grid.render", "grid", reso=128, degree=2, occupancy=1.0, rays="camera", mode="fwdbwd_g")
    for occ in (1.0, 0.05):   # incoherent rays
        for mode in ("fwd", "fwdbwd"):
            add("grid.render", "grid", reso=128, degree=2, occupancy=occ, rays="random",
                mode=mode)
    # 256^3: SH2 dense is 1.9 GB (forward only: grid + gradients + scratch would not fit in
    # device memory); fwd+bwd on SH0 dense and on a 5 % pruned SH2 grid.
    add("grid.render", "grid", reso=256, degree=2, occupancy=1.0, rays="camera", mode="fwd")
    for mode in ("fwd", "fwdbwd"):
        add("grid.render", "grid", reso=256, degree=0, occupancy=1.0, rays="camera", mode=mode)
        add("grid.render", "grid", reso=256, degree=2, occupancy=0.05, rays="camera", mode=mode)
    add("grid.render", "grid", reso=256, degree=2, occupancy=0.05, rays="random", mode="fwd")

    # GPU sizes: 2^18 rays a call, about the samples of a GPU's step (tools/gpu/run.sh runs
    # them there; on a CPU each repetition takes seconds)
    for mode in ("fwd", "fwdbwd"):
        add("grid.render", "grid.gpu", reso=256, degree=2, occupancy=0.05, rays="camera",
            mode=mode, n_rays=1 << 18)
    add("grid.render", "grid.gpu", reso=128, degree=2, occupancy=1.0, rays="camera",
        mode="fwdbwd", n_rays=1 << 18)

    # peers on the bar configuration (128^3 SH2 dense camera); taichi also on a pruned grid
    # (torch takes tens of seconds per repetition here: dense only, 3 repetitions)
    for occ in (1.0, 0.05):
        for mode in ("fwd", "fwdbwd"):
            add("peer.taichi", "peer.taichi", reso=128, degree=2, occupancy=occ, rays="camera",
                mode=mode)
    for mode in ("fwd", "fwdbwd"):
        add("peer.torch", "peer.torch", min_repeats=3, reso=128, degree=2, occupancy=1.0,
            rays="camera", mode=mode)
    # the float64 reference is slow: a small problem, with clrf on the same one
    small = dict(reso=32, degree=2, occupancy=1.0, rays="camera", n_rays=1024, mode="fwd")
    add("peer.numpy_ref", "peer.numpy_ref", **small)
    add("grid.render", "grid", **small)
    return out


def _hash_specs():
    """Hash encoding forward and forward + backward (the published sizes: L 16, F 2, T 2^19,
    16..2048, 2^18 points per call, about one training batch's live samples), clrf and the
    Taichi peer on identical inputs."""
    base = {"levels": 16, "features": 2, "log2_t": 19, "n_min": 16, "n_max": 2048,
            "n_points": 1 << 18}
    quick = {"log2_t": 12, "n_points": 1024}
    out = []
    for kind, prefix in (("hash.encode", "hash"), ("peer.taichi_hash", "peer.taichi_hash")):
        for mode in ("fwd", "fwdbwd"):
            out.append(Spec(f"{prefix}/{mode}/L16F2T19", kind, dict(base, mode=mode),
                            "samples/s", dict(quick)))
    for mode in ("fwd", "fwdbwd"):   # a GPU's size: 2^20 points a call
        out.append(Spec(f"hash.gpu/{mode}/L16F2T19", "hash.encode",
                        dict(base, mode=mode, n_points=1 << 20), "samples/s", dict(quick)))
    return out


def _splat_specs():
    """The Gaussian-splatting tile rasteriser (cl/splat_raster.cl) forward and forward +
    backward, clrf and the Taichi peer (tools/peers/taichi_splat.py) on identical inputs: 20,000
    random Gaussians, SH degree 3, projected and binned by clrf for a 400 x 400 camera (set-up,
    not timed). samples/s = (pixel, Gaussian) pairs the forward evaluates; compare the two in
    one --interleave run (``--only 'splat*'``)."""
    base = {"n": 20000, "width": 400, "height": 400, "degree": 3}
    quick = {"n": 500, "width": 64, "height": 48}
    need = (("clrf.splat", "SplatRasterizer"),)
    out = []
    for kind, prefix in (("splat.raster", "splat.raster.clrf"),
                         ("peer.taichi_splat", "splat.raster.taichi")):
        for mode in ("fwd", "fwdbwd"):
            out.append(Spec(f"{prefix}/{mode}/20k/400x400/sh3", kind, dict(base, mode=mode),
                            "samples/s", dict(quick), need))
    return out


def _peak_specs():
    return [
        Spec("peak/copy", "peak.bandwidth", {"op": "copy", "mbytes": 256}, "GB/s",
             {"mbytes": 4}),
        Spec("peak/triad", "peak.bandwidth", {"op": "triad", "mbytes": 256}, "GB/s",
             {"mbytes": 4}),
        Spec("peak/fma", "peak.fma", {"iters": 4096, "items": 4096}, "GFLOP/s",
             {"iters": 64, "items": 64}),
    ]


# Training kernels (TV, optimiser step, upsample, prune, full Plenoxels step); a spec whose
# module is missing on a branch is reported as skipped (Spec.requires).
TRAINING_SPECS: list = _train_specs()

SPECS = _grid_specs() + _hash_specs() + _splat_specs() + TRAINING_SPECS


def external_specs():
    out = []
    for modname in EXTERNAL_SUITES:
        if not (TOOLS / f"{modname}.py").is_file():
            continue
        mod = importlib.import_module(modname)
        if hasattr(mod, "bench_suite"):
            out += list(mod.bench_suite(framework))
    return out
