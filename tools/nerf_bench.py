"""Fused NeRF MLP benchmark: GFLOP/s and samples/s next to numpy's float32 matmul on the same
layer shapes and the device's FMA peak, all measured in the same run; JSON output.

    PYTHONPATH=. python tools/nerf_bench.py [--samples 8192] [--repeats 5] [--out bench.json]

Each figure is the median of --repeats timed runs after a warm-up (wall clock around enqueue +
finish), with min and max. FLOPs are counted on the logical (unpadded) layer sizes, 2 per MAC;
forward + backward counts 3 products per layer (forward, input gradient, weight gradient) and
so includes the input-gradient product of layer 0, which the training step skips.
The host is shared, so read the ratios: fused/numpy and fused/FMA-peak, by wall clock and by
CPU time (GFLOP per CPU-second of this process, which does not count the time other processes
hold the cores).
"""
from __future__ import annotations

import argparse
import json
import os
import platform
import resource
import time

import numpy as np

import pyopencl.array as cla

import clrf
from clrf.nerf.mlp import MLP, MLPSpec

CONFIGS = {   # name -> MLPSpec; in/dir dims from the usual frequencies (3 + 6 L)
    "nerf-8x256-skip4": MLPSpec(width=256, depth=8, skip=4, color_width=128, in_dim=63, dir_dim=27),
    "small-4x64": MLPSpec(width=64, depth=4, skip=-1, color_width=32, in_dim=51, dir_dim=15),
    "small-2x128": MLPSpec(width=128, depth=2, skip=-1, color_width=64, in_dim=51, dir_dim=15),
}


def cpu_seconds() -> float:
    """CPU time of this process, all threads (PoCL's workers included)."""
    r = resource.getrusage(resource.RUSAGE_SELF)
    return r.ru_utime + r.ru_stime


CPU_TIMES = []   # CPU seconds of the last timed() call, per repeat


def timed(fn, repeats):
    """(median, min, max) wall seconds; the CPU seconds per repeat are left in CPU_TIMES.
    GFLOP per CPU-second is the contention-robust figure: on a shared host the wall clock
    also counts the time other processes hold our cores."""
    fn()
    ts, cs = [], []
    for _ in range(repeats):
        c0 = cpu_seconds()
        t0 = time.perf_counter()
        fn()
        ts.append(time.perf_counter() - t0)
        cs.append(cpu_seconds() - c0)
    CPU_TIMES[:] = cs
    return float(np.median(ts)), float(np.min(ts)), float(np.max(ts))


def fma_peak(dev, repeats):
    n_items, iters = 64 * dev.caps.compute_units, 20000
    prg = dev.program("bench.cl", {"FMA_CHAINS": 8, "FMA_ITERS": iters})
    k = prg.kernel("bench_fma")
    out = cla.empty(dev.queue, n_items, np.float32)

    def run():
        k(dev.queue, (n_items,), (1,), out.data, np.float32(0.999), np.float32(1e-3))
        dev.queue.finish()

    med, lo, hi = timed(run, repeats)
    flop = n_items * iters * 8 * 16 * 2
    return {"gflops": flop / med / 1e9, "gflops_min": flop / hi / 1e9,
            "gflops_max": flop / lo / 1e9,
            "gflop_per_cpu_s": flop / float(np.median(CPU_TIMES)) / 1e9}


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


def numpy_matmul(spec, n, repeats):
    """numpy float32 matmuls with the MLP's shapes: forward (X W) and forward + backward
    (X W, G W^T, X^T G) per layer, timed as one sequence each."""
    fwd, fwdbwd = _matmul_runs(spec, n)

    macs = sum(a * b for a, b in layer_shapes(spec)) * n
    f = timed(fwd, repeats)
    fc = float(np.median(CPU_TIMES))
    fb = timed(fwdbwd, repeats)
    fbc = float(np.median(CPU_TIMES))
    return {"forward_gflops": 2 * macs / f[0] / 1e9, "fwdbwd_gflops": 6 * macs / fb[0] / 1e9,
            "forward_gflop_per_cpu_s": 2 * macs / fc / 1e9,
            "fwdbwd_gflop_per_cpu_s": 6 * macs / fbc / 1e9}


def fused(dev, spec, n, repeats):
    q = dev.queue
    net = MLP(dev, spec)
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

    macs = sum(a * b for a, b in layer_shapes(spec)) * n
    f = timed(fwd, repeats)
    fc = float(np.median(CPU_TIMES))
    fb = timed(fwdbwd, repeats)
    fbc = float(np.median(CPU_TIMES))
    return {"forward_gflops": 2 * macs / f[0] / 1e9, "forward_samples_per_s": n / f[0],
            "forward_s": f, "forward_gflop_per_cpu_s": 2 * macs / fc / 1e9,
            "fwdbwd_gflops": 6 * macs / fb[0] / 1e9, "fwdbwd_samples_per_s": n / fb[0],
            "fwdbwd_s": fb, "fwdbwd_gflop_per_cpu_s": 6 * macs / fbc / 1e9}


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--samples", type=int, default=8192, help="samples per batch")
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--configs", default=",".join(CONFIGS))
    ap.add_argument("--out", default=None, help="write the JSON here too")
    args = ap.parse_args(argv)
    dev = clrf.Device()
    res = {"device": repr(dev), "driver": dev.caps.driver_version, "host": platform.node(),
           "cpu_count": os.cpu_count(), "load1_before": os.getloadavg()[0],
           "samples": args.samples, "repeats": args.repeats, "results": []}
    for name in args.configs.split(","):
        spec = CONFIGS[name]
        peak_before = fma_peak(dev, args.repeats)     # bracket every measurement with the
        fu = fused(dev, spec, args.samples, args.repeats)   # reference kernel: the host is
        npm = numpy_matmul(spec, args.samples, args.repeats)  # shared and swings by 2x
        peak_after = fma_peak(dev, args.repeats)
        peak = 0.5 * (peak_before["gflops"] + peak_after["gflops"])
        peak_cpu = 0.5 * (peak_before["gflop_per_cpu_s"] + peak_after["gflop_per_cpu_s"])
        entry = {"name": name, "spec": spec.__dict__, "fused": fu, "numpy_matmul": npm,
                 "fma_peak_before": peak_before, "fma_peak_after": peak_after,
                 "fma_peak_gflops": peak, "load1": os.getloadavg()[0],
                 "fwd_ratio_to_numpy": fu["forward_gflops"] / npm["forward_gflops"],
                 "fwdbwd_ratio_to_numpy": fu["fwdbwd_gflops"] / npm["fwdbwd_gflops"],
                 "fwd_ratio_to_fma_peak": fu["forward_gflops"] / peak,
                 "fwdbwd_ratio_to_fma_peak": fu["fwdbwd_gflops"] / peak,
                 "fma_peak_gflop_per_cpu_s": peak_cpu,
                 "fwd_cpu_ratio_to_fma_peak": fu["forward_gflop_per_cpu_s"] / peak_cpu,
                 "fwdbwd_cpu_ratio_to_fma_peak": fu["fwdbwd_gflop_per_cpu_s"] / peak_cpu,
                 "fwd_cpu_ratio_to_numpy": fu["forward_gflop_per_cpu_s"]
                 / npm["forward_gflop_per_cpu_s"],
                 "fwdbwd_cpu_ratio_to_numpy": fu["fwdbwd_gflop_per_cpu_s"]
                 / npm["fwdbwd_gflop_per_cpu_s"]}
        res["results"].append(entry)
        print(f"{name:17s} fused fwd {fu['forward_gflops']:6.1f} GFLOP/s "
              f"({fu['forward_samples_per_s'] / 1e3:7.1f} k samples/s), fwd+bwd "
              f"{fu['fwdbwd_gflops']:6.1f} GFLOP/s ({fu['fwdbwd_samples_per_s'] / 1e3:6.1f} k/s)"
              f" | numpy {npm['forward_gflops']:6.1f} / {npm['fwdbwd_gflops']:6.1f} | fused/numpy "
              f"{entry['fwd_ratio_to_numpy']:.2f} / {entry['fwdbwd_ratio_to_numpy']:.2f} | "
              f"FMA peak {peak:6.1f}, fused/peak {entry['fwd_ratio_to_fma_peak']:.2f} / "
              f"{entry['fwdbwd_ratio_to_fma_peak']:.2f} | load {entry['load1']:.1f}", flush=True)
        print(f"{'':17s} per CPU-second: fused {fu['forward_gflop_per_cpu_s']:6.1f} / "
              f"{fu['fwdbwd_gflop_per_cpu_s']:6.1f}, numpy {npm['forward_gflop_per_cpu_s']:6.1f} / "
              f"{npm['fwdbwd_gflop_per_cpu_s']:6.1f}, FMA kernel {peak_cpu:6.1f} GFLOP; fused/FMA "
              f"{entry['fwd_cpu_ratio_to_fma_peak']:.2f} / "
              f"{entry['fwdbwd_cpu_ratio_to_fma_peak']:.2f}",
              flush=True)
    res["load1_after"] = os.getloadavg()[0]
    txt = json.dumps(res, indent=1)
    if args.out:
        with open(args.out, "w") as f:
            f.write(txt + "\n")



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
        return api.Case(run, {"samples": n, "flop": (6 if p["mode"] == "fwdbwd" else 2) * macs})

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
        cfg = NerfConfig.preset(p["preset"], batch_rays=p["rays"])
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
