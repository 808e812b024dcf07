"""Fused NeRF MLP benchmark: GFLOP/s next to numpy's float32 matmul on the same layer shapes and
the device's FMA peak, for one or more register tiles, all timed in one run; JSON output.

    PYTHONPATH=. python tools/nerf_bench.py [--samples 8192] [--repeats 7] [--out bench.json]
        [--tilings device,wide] [--configs nerf-8x256-skip4,small-4x64]

Every case (numpy forward / forward+backward, the fused MLP with each tiling, its backward and
weight-gradient phases, the FMA peak at 16 lanes and at the device's native float width) runs
once per round, the rounds interleaved, after one warm-up each; each figure is the median over
--repeats rounds, with min and max. The host is shared: interleaving spreads the contention
over all cases alike, and GFLOP per CPU-second (CPU time of this process, PoCL's threads
included) does not count the time other processes hold the cores.
FLOPs are counted on the logical (unpadded) layer sizes, 2 per MAC; forward + backward counts
3 products per layer (forward, input gradient, weight gradient) and so includes the
input-gradient product of layer 0, which the training step skips. The phases: "bwd" is the
whole backward (input gradients + weight gradients + reduce), "wgrad" the weight gradient and
its reduce alone; input gradient = bwd - wgrad.

Tilings: "device" (what an MLP picks here: tuned cache, else the device default), "default"
(the device default, ignoring the cache), "wide" (8 rows x 32 columns, weight gradient 8 x 32:
the former AVX-512 default), or rows:cols:dw_rows:dw_cols[:dw_chunk].

GPU sizes (``--gpu-sizes``): the fused MLP alone, forward and forward + backward, at batches of
``--gpu-samples`` (default 2^16, 2^18, 2^20) for ``--gpu-configs`` (NeRF's 8 x 256, 4 x 64, the
hash model's networks), each reported as samples/s, GFLOP/s and the fraction of the FP32 FMA
peak measured in the same run (cl/bench.cl's bench_fma; on a GPU launched as tools/bench.py's
peak/fma, 2,048 work-items per compute unit). No numpy peer there (a 2^20 batch of 8 x 256
takes seconds on a CPU). Tilings there: "device" (the MLP's own choice: the GPU tiling on GPUs),
"gpu" (the GPU tiling forced), "cpu" (the CPU register tiles, also on a GPU).
``--force-gpu-kernels`` runs the whole tool with the GPU tiling on any device (as
``CLRF_FORCE_GPU_KERNELS=1``; the CPU tilings named by --tilings then build the GPU tiling too).

    python tools/nerf_bench.py --gpu-sizes --out gpu.json            # on a GPU
    python tools/nerf_bench.py --gpu-sizes --force-gpu-kernels --gpu-samples 256 --repeats 1 \
        --gpu-configs hash-1x64-c2                                     # a smoke run on a CPU
"""
from __future__ import annotations

import argparse
import json
import os
import platform
import resource
import sys
import time
from dataclasses import asdict, replace
from pathlib import Path

import numpy as np

import pyopencl.array as cla

sys.path.append(str(Path(__file__).resolve().parent.parent))   # the checkout's clrf where none is installed (PYTHONPATH=. for the checkout's)

import clrf  # noqa: E402
from clrf.mlp.tiling import CHUNK_TILES, MLPTiling, device_default, tile_fields  # noqa: E402
from clrf.mlp.mlp import MLP, MLPSpec  # noqa: E402

CONFIGS = {   # name -> MLPSpec; in/dir dims from the usual frequencies (3 + 6 L)
    "nerf-8x256-skip4": MLPSpec(width=256, depth=8, skip=4, color_width=128, in_dim=63, dir_dim=27),
    "small-4x64": MLPSpec(width=64, depth=4, skip=-1, color_width=32, in_dim=51, dir_dim=15),
    "small-2x128": MLPSpec(width=128, depth=2, skip=-1, color_width=64, in_dim=51, dir_dim=15),
}
WIDE = MLPTiling(8, 32, 8, 32, 512)
GPU_CONFIGS = {   # --gpu-sizes: the shapes the trainers build (hash: 16 x 2 features, SH degree 4)
    "nerf-8x256-skip4": CONFIGS["nerf-8x256-skip4"],
    "small-4x64": CONFIGS["small-4x64"],
    "hash-1x64-c2": MLPSpec(width=64, depth=1, skip=-1, color_width=64, in_dim=32, dir_dim=16,
                            sigma_act="trunc_exp", color_depth=2, features=16),
}
GPU_SAMPLES = (1 << 16, 1 << 18, 1 << 20)
GPU_FMA_ITERS = 2048      # the GPU peak kernel's iterations (2,048 items per compute unit)


def cpu_seconds() -> float:
    """CPU time of this process, all threads (PoCL's workers included)."""
    r = resource.getrusage(resource.RUSAGE_SELF)
    return r.ru_utime + r.ru_stime


def fma_peak_case(dev, vec):
    """(run, flop): FMA_CHAINS = 8 chains of float<vec> FMAs (cl/bench.cl bench_fma)."""
    n_items, iters = 64 * dev.caps.compute_units, 20000
    prg = dev.program("bench.cl", {"FMA_CHAINS": 8, "FMA_ITERS": iters, "FMA_VEC": vec})
    k = prg.kernel("bench_fma")
    out = cla.empty(dev.queue, n_items, np.float32)

    def run():
        k(dev.queue, (n_items,), (1,), out.data, np.float32(0.999), np.float32(1e-3))
        dev.queue.finish()
    return run, n_items * iters * 8 * vec * 2


def gpu_fma_peak_case(dev):
    """(run, flop): the FMA peak as tools/bench.py's peak/fma measures it on a GPU: float<the
    device's vector width> chains, 2,048 work-items per compute unit, the driver's local size.
    On a CPU device the CPU-shaped fma_peak_case."""
    if dev.caps.type == "cpu":
        return fma_peak_case(dev, dev.caps.vector_width)
    vec, iters = dev.caps.vector_width, GPU_FMA_ITERS
    n_items = 2048 * dev.caps.compute_units
    prg = dev.program("bench.cl", {"FMA_CHAINS": 8, "FMA_ITERS": iters, "FMA_VEC": vec})
    k = prg.kernel("bench_fma")
    out = cla.empty(dev.queue, n_items, np.float32)

    def run():
        k(dev.queue, (n_items,), None, out.data, np.float32(0.999), np.float32(1e-3))
        dev.queue.finish()
    return run, n_items * iters * 8 * vec * 2


def layer_shapes(spec):
    """(fan_in, fan_out) of every logical layer, in order."""
    W, D = spec.width, spec.depth
    shapes = [(spec.in_dim, W)]
    for l in range(1, D):
        shapes.append((W + (spec.in_dim if l == spec.skip + 1 else 0), W))
    shapes += [(W, W + 1), (W + spec.dir_dim, spec.color_width), (spec.color_width, 3)]
    return shapes


def _matmul_runs(spec, n):
    """(forward, forward+backward) callables: numpy float32 matmuls with the MLP's shapes."""
    rng = np.random.default_rng(0)
    mats = [(rng.random((n, a), np.float32), rng.random((a, b), np.float32),
             rng.random((n, b), np.float32)) for a, b in layer_shapes(spec)]

    def fwd():
        for X, Wm, _ in mats:
            X @ Wm

    def fwdbwd():
        for X, Wm, G in mats:
            X @ Wm
            G @ Wm.T
            X.T @ G
    return fwd, fwdbwd


def fused_runs(dev, spec, n, net=None):
    """The MLP (``net``, or a new one) and its cases: forward, forward+backward, backward alone
    and weight gradient (+ reduce) alone; the last two reuse the activations of one forward
    made here."""
    q = dev.queue
    net = net or MLP(dev, spec)
    rng = np.random.default_rng(0)
    x = cla.to_device(q, rng.random((n, spec.in_dim), np.float32))
    d = cla.to_device(q, rng.random((n, spec.dir_dim), np.float32))
    ds = cla.to_device(q, rng.random(n, np.float32))
    dr = cla.to_device(q, rng.random((n, 3), np.float32))

    def fwd():
        net.forward(x, d)
        q.finish()

    def fwdbwd():
        net.forward(x, d)
        net.backward(ds, dr)
        q.finish()

    def bwd():
        net.backward(ds, dr)
        q.finish()

    def wgrad():
        net.weight_grad(net.grad)
        q.finish()
    fwd()
    return net, {"fwd": fwd, "fwdbwd": fwdbwd, "bwd": bwd, "wgrad": wgrad}


def parse_tiling(dev, name, spec) -> MLPTiling | None:
    """None for "device" (the MLP's own choice), else the tiling named (see module doc)."""
    if name == "device":
        return None
    if name == "default":
        return device_default(dev.caps, spec)
    if name == "wide":
        return WIDE
    v = [int(x) for x in name.split(":")]
    return MLPTiling(*v[:4], v[4] if len(v) > 4 else CHUNK_TILES * v[0])


SETTLE_S = 0.1   # pause before each timed case: BLAS worker threads spin on after a call
MIN_SAMPLE_S = 0.05   # a timed sample repeats its case back to back for at least this long


def interleaved(cases, repeats, min_sample_s=None):
    """{label: (median s, min s, max s, median CPU s)} per call, over `repeats` rounds of all
    cases. Each case starts after a SETTLE_S pause, so that the threads numpy's BLAS leaves
    spinning after a call neither slow the next case down nor add to its CPU time. A sample
    runs its case back to back as many times as fill min_sample_s (from the warm-up's time), so
    that a short case (a 4x64 batch takes ~4 ms) is not timed on the wake-up of the thread
    pools after the pause: numpy's and PoCL's alike."""
    min_sample_s = MIN_SAMPLE_S if min_sample_s is None else min_sample_s
    calls = {}
    for k, (run, _) in cases.items():
        run()
        t0 = time.perf_counter()
        run()
        calls[k] = max(1, int(np.ceil(min_sample_s / max(time.perf_counter() - t0, 1e-6))))
    wall = {k: [] for k in cases}
    cpu = {k: [] for k in cases}
    for _ in range(repeats):
        for k, (run, _) in cases.items():
            time.sleep(SETTLE_S)
            c0 = cpu_seconds()
            t0 = time.perf_counter()
            for _ in range(calls[k]):
                run()
            wall[k].append((time.perf_counter() - t0) / calls[k])
            cpu[k].append((cpu_seconds() - c0) / calls[k])
    return {k: (float(np.median(wall[k])), float(np.min(wall[k])), float(np.max(wall[k])),
                float(np.median(cpu[k]))) for k in cases}


def gpu_main(dev, args) -> dict:
    """--gpu-sizes: the fused MLP at GPU batch sizes beside the FMA peak of the same run."""
    sizes = [int(v) for v in args.gpu_samples.split(",")]
    tnames = (args.tilings or "device").split(",")
    res = {"device": repr(dev), "driver": dev.caps.driver_version, "host": platform.node(),
           "mode": "gpu-sizes", "compute_units": dev.caps.compute_units,
           "local_mem_size": dev.caps.local_mem_size, "samples": sizes,
           "repeats": args.repeats, "min_sample_s": args.min_sample_s, "configs": {}}
    cases = {"fma_peak": gpu_fma_peak_case(dev)}
    tilings = {}
    for name in args.gpu_configs.split(","):
        spec = GPU_CONFIGS[name]
        fwd_flop, fwdbwd_flop = spec.flops_per_sample()
        for tname in tnames:
            d = {"device": dev, "gpu": dev.with_tuning(gpu_kernels=True),
                 "cpu": dev.with_tuning(gpu_kernels=False)}.get(tname)
            if d is None:
                raise SystemExit(f"nerf_bench: --tilings with --gpu-sizes: device, gpu or cpu, "
                                 f"got {tname!r}")
            net = MLP(d, spec)     # one per shape and tiling: its scratch grows to the largest n
            for n in sizes:
                net, runs = fused_runs(d, spec, n, net)
                tilings[f"{name}/{tname}"] = {**asdict(net.tiling), "layout_gpu": net.layout.gpu,
                                              "block": net.layout.rows}
                for mode, flop in (("fwd", fwd_flop), ("fwdbwd", fwdbwd_flop)):
                    cases[f"{name}/{tname}/{n}/{mode}"] = (runs[mode], flop * n)
    times = interleaved(cases, args.repeats, args.min_sample_s)
    peak = cases["fma_peak"][1] / times["fma_peak"][0] / 1e9
    res["fma_peak_gflops"] = peak
    res["tilings"] = tilings
    figs = res["cases"] = {}
    print(f"FP32 FMA peak (same run): {peak:.1f} GFLOP/s", flush=True)
    for k, (_, f) in cases.items():
        if k == "fma_peak":
            continue
        n = int(k.split("/")[2])
        med, lo, hi, _ = times[k]
        g = f / med / 1e9
        figs[k] = {"median_s": med, "min_s": lo, "max_s": hi, "samples_per_s": n / med,
                   "gflops": g, "fraction_of_fma_peak": g / peak}
        print(f"{k:44s} {n / med / 1e6:9.3f} M samples/s {g:9.1f} GFLOP/s "
              f"{100 * g / peak:6.2f} % of peak", flush=True)
    return res


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--samples", type=int, default=8192, help="samples per batch")
    ap.add_argument("--repeats", type=int, default=7, help="interleaved rounds")
    ap.add_argument("--configs", default=",".join(CONFIGS))
    ap.add_argument("--tilings", default=None,
                    help="comma list, see module doc (default device,wide; with --gpu-sizes "
                         "device)")
    ap.add_argument("--min-sample-s", type=float, default=MIN_SAMPLE_S,
                    help="a timed sample repeats its case back to back at least this long")
    ap.add_argument("--out", default=None, help="write the JSON here too")
    ap.add_argument("--gpu-sizes", action="store_true",
                    help="time the fused MLP alone at GPU batch sizes (--gpu-samples), with "
                         "samples/s and the fraction of the FMA peak of the same run")
    ap.add_argument("--gpu-samples", default=",".join(str(v) for v in GPU_SAMPLES),
                    help="comma list of batch sizes for --gpu-sizes (default 2^16,2^18,2^20)")
    ap.add_argument("--gpu-configs", default=",".join(GPU_CONFIGS),
                    help="comma list of MLP shapes for --gpu-sizes")
    ap.add_argument("--force-gpu-kernels", action="store_true",
                    help="the fused MLP's GPU tiling on any device (CLRF_FORCE_GPU_KERNELS=1)")
    args = ap.parse_args(argv)
    dev = clrf.Device()
    if args.force_gpu_kernels:
        dev = dev.with_tuning(gpu_kernels=True)
    if args.gpu_sizes:
        res = gpu_main(dev, args)
        if args.out:
            with open(args.out, "w") as fh:
                fh.write(json.dumps(res, indent=1) + "\n")
        return
    args.tilings = args.tilings or "device,wide"
    n = args.samples
    res = {"device": repr(dev), "driver": dev.caps.driver_version, "host": platform.node(),
           "native_float_width": dev.caps.native_float_width, "cpu_count": os.cpu_count(),
           "load1_before": os.getloadavg()[0], "samples": n, "repeats": args.repeats,
           "min_sample_s": args.min_sample_s,
           "configs": {}}
    cases, tilings = {}, {}
    for vec in sorted({16, dev.caps.vector_width}):
        cases[f"fma_peak/vec{vec}"] = fma_peak_case(dev, vec)
    for name in args.configs.split(","):
        spec = CONFIGS[name]
        macs = sum(a * b for a, b in layer_shapes(spec)) * n
        fwd, fwdbwd = _matmul_runs(spec, n)
        cases[f"{name}/numpy/fwd"] = (fwd, 2 * macs)
        cases[f"{name}/numpy/fwdbwd"] = (fwdbwd, 6 * macs)
        for tname in args.tilings.split(","):
            t = parse_tiling(dev, tname, spec)
            net, runs = fused_runs(dev, spec if t is None else replace(spec, **tile_fields(t)),
                                   n)
            tilings[f"{name}/{tname}"] = asdict(net.tiling)
            for mode, flop in (("fwd", 2), ("fwdbwd", 6), ("bwd", 4), ("wgrad", 2)):
                cases[f"{name}/{tname}/{mode}"] = (runs[mode], flop * macs)
    times = interleaved(cases, args.repeats, args.min_sample_s)
    figs = {k: {"gflops": f / times[k][0] / 1e9, "gflops_min": f / times[k][2] / 1e9,
                "gflops_max": f / times[k][1] / 1e9, "gflop_per_cpu_s": f / times[k][3] / 1e9,
                "median_s": times[k][0]} for k, (_, f) in cases.items()}
    res["cases"] = figs
    res["tilings"] = tilings
    res["load1_after"] = os.getloadavg()[0]
    for k, v in figs.items():
        if k.startswith("fma_peak"):
            print(f"{k:34s} {v['gflops']:7.1f} GFLOP/s  {v['gflop_per_cpu_s']:7.1f} per CPU-s")
    for name in args.configs.split(","):
        npm = {m: figs[f"{name}/numpy/{m}"] for m in ("fwd", "fwdbwd")}
        print(f"{name}: numpy fwd {npm['fwd']['gflops']:.1f}, fwd+bwd "
              f"{npm['fwdbwd']['gflops']:.1f} GFLOP/s ({npm['fwd']['gflop_per_cpu_s']:.1f} / "
              f"{npm['fwdbwd']['gflop_per_cpu_s']:.1f} per CPU-s)")
        ratios = res["configs"][name] = {}
        for tname in args.tilings.split(","):
            f = {m: figs[f"{name}/{tname}/{m}"] for m in ("fwd", "fwdbwd", "bwd", "wgrad")}
            t = tilings[f"{name}/{tname}"]
            r = ratios[tname] = {
                "tiling": t,
                "fwd_ratio_to_numpy": f["fwd"]["gflops"] / npm["fwd"]["gflops"],
                "fwdbwd_ratio_to_numpy": f["fwdbwd"]["gflops"] / npm["fwdbwd"]["gflops"],
                "fwd_cpu_ratio_to_numpy":
                    f["fwd"]["gflop_per_cpu_s"] / npm["fwd"]["gflop_per_cpu_s"],
                "fwdbwd_cpu_ratio_to_numpy":
                    f["fwdbwd"]["gflop_per_cpu_s"] / npm["fwdbwd"]["gflop_per_cpu_s"],
                "seconds": {m: f[m]["median_s"] for m in f}}
            s = r["seconds"]
            print(f"  {tname:8s} tile {t['rows']}x{t['cols']} dw {t['dw_rows']}x{t['dw_cols']} "
                  f"chunk {t['dw_chunk']}: fwd {f['fwd']['gflops']:6.1f} fwd+bwd "
                  f"{f['fwdbwd']['gflops']:6.1f} GFLOP/s | /numpy {r['fwd_ratio_to_numpy']:.2f} / "
                  f"{r['fwdbwd_ratio_to_numpy']:.2f} (per CPU-s {r['fwd_cpu_ratio_to_numpy']:.2f}"
                  f" / {r['fwdbwd_cpu_ratio_to_numpy']:.2f}) | ms: fwd {1e3 * s['fwd']:.1f} "
                  f"input-grad {1e3 * (s['bwd'] - s['wgrad']):.1f} wgrad+reduce "
                  f"{1e3 * s['wgrad']:.1f}", flush=True)
    txt = json.dumps(res, indent=1)
    if args.out:
        with open(args.out, "w") as fh:
            fh.write(txt + "\n")


if __name__ == "__main__":
    main()


# ---- specs for tools/bench.py (EXTERNAL_SUITES): the NeRF kernels in the main benchmark run --
def bench_suite(api):
    """Specs for tools/bench.py: encoding, fused MLP forward and forward+backward (flop-counted,
    so bench.py reports GFLOP/s and the ratio to the FMA peak of the same run), numpy float32
    matmul on the same layer shapes, and one whole NeRF training step."""
    from clrf.nerf import ops as nerf_ops

    @api.factory("nerf.encode")
    def _encode(ctx, p):
        """Positional encoding forward of n points with L frequencies (+ the raw input)."""
        dev = ctx.dev
        n, L = p["n"], p["freqs"]
        x = cla.to_device(dev.queue, np.random.default_rng(0).uniform(-1, 1, (n, 3)).astype(np.float32))
        out = nerf_ops.encode(dev, x, L)

        def run():
            nerf_ops.encode(dev, x, L, out=out)
            dev.finish()
        return api.Case(run, {"samples": n, "bytes": n * 4 * (3 + out.shape[1])},
                        {"out_dim": int(out.shape[1])})

    @api.factory("nerf.mlp")
    def _mlp(ctx, p):
        """Fused MLP forward, or forward + backward (input, weight and bias gradients)."""
        dev = ctx.dev
        spec = CONFIGS[p["config"]]
        n = p["n"]
        q = dev.queue
        net = MLP(dev, spec)
        rng = np.random.default_rng(0)
        x = cla.to_device(q, rng.random((n, spec.in_dim), np.float32))
        d = cla.to_device(q, rng.random((n, spec.dir_dim), np.float32))
        ds = cla.to_device(q, rng.random(n, np.float32))
        dr = cla.to_device(q, rng.random((n, 3), np.float32))
        macs = sum(a * b for a, b in layer_shapes(spec)) * n

        def run():
            net.forward(x, d)
            if p["mode"] == "fwdbwd":
                net.backward(ds, dr)
            q.finish()
        return api.Case(run, {"samples": n, "flop": (6 if p["mode"] == "fwdbwd" else 2) * macs},
                        {"tiling": asdict(net.tiling)})

    @api.factory("nerf.numpy_matmul")
    def _npm(ctx, p):
        """numpy float32 matmuls with the MLP's layer shapes (the peer for the fused MLP)."""
        spec = CONFIGS[p["config"]]
        n = p["n"]
        fwd, fwdbwd = _matmul_runs(spec, n)
        run = fwdbwd if p["mode"] == "fwdbwd" else fwd
        macs = sum(a * b for a, b in layer_shapes(spec)) * n
        return api.Case(run, {"samples": n, "flop": (6 if p["mode"] == "fwdbwd" else 2) * macs})

    @api.factory("nerf.train_step")
    def _step(ctx, p):
        """One NerfModel.train_step (coarse + fine, Adam) on a batch of random rays: rays/s."""
        from clrf.nerf import NerfConfig, NerfModel
        dev = ctx.dev
        cfg = NerfConfig.from_preset(p["preset"], batch_rays=p["rays"])
        model = NerfModel(dev, cfg, 2.0, 6.0, (1, 1, 1))
        rng = np.random.default_rng(0)
        n = p["rays"]
        o = rng.normal(0, 0.1, (n, 3)) + [0, 0, 4.0]
        dd = rng.normal(0, 0.2, (n, 3)) + [0, 0, -1.0]
        q = dev.queue
        args = [cla.to_device(q, a.astype(np.float32)) for a in
                (o, dd / np.linalg.norm(dd, axis=1, keepdims=True), rng.uniform(0, 1, (n, 3)))]
        it = [0]

        def run():
            model.train_step(it[0], *args)
            it[0] += 1
        return api.Case(run, {"rays": n, "samples": n * (cfg.n_coarse + cfg.n_fine)},
                        {"preset": p["preset"]})

    specs = [api.Spec("nerf/encode/L10", "nerf.encode", {"n": 1 << 20, "freqs": 10},
                      quick={"n": 1000})]
    for cfg in CONFIGS:
        for mode in ("fwd", "fwdbwd"):
            specs.append(api.Spec(f"nerf/mlp/{cfg}/{mode}", "nerf.mlp",
                                  {"config": cfg, "mode": mode, "n": 8192}, quick={"n": 64}))
            specs.append(api.Spec(f"nerf/numpy_matmul/{cfg}/{mode}", "nerf.numpy_matmul",
                                  {"config": cfg, "mode": mode, "n": 8192}, quick={"n": 64}))
    specs.append(api.Spec("nerf/train_step/tiny", "nerf.train_step",
                          {"preset": "tiny", "rays": 1024}, metric="rays/s", quick={"rays": 16}))
    return specs
