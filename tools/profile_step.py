"""Where a training step's time goes: steps of a trained run, every kernel launch waited for and
timed by name, the rest of the step (pyopencl's own kernels, transfers, host work) as one line.

Start from a run's checkpoint, so the profile is that of the state the run reached (the
occupancy grid pruned, the batch adapted), not of a fresh model:

    python tools/profile_step.py --ckpt runs/lego400 --steps 40
    python tools/profile_step.py --ckpt runs/lego400 --steps 40 --json profile.json
    python tools/profile_step.py --ckpt runs/lego400 --set hash.train_t_stop=0   # without
    python tools/profile_step.py --ckpt runs/lego400 --bounded on   # sizes kept on the device
    python tools/profile_step.py --ckpt runs/grid_exp --exposure-two-pass   # grid.exposure's
                                                                 # step before its one march

Each clrf launch (``pyopencl.enqueue_nd_range_kernel``) is followed by ``queue.finish()``,
which serialises what an in-order queue does anyway; on a CPU device the per-launch wait adds a few microseconds. The step total is timed
separately, without the waits, so the share of each kernel is its time over the timed steps.
Prints the CPU, the OpenCL implementation and the device beside the figures.
"""
from __future__ import annotations

import argparse
import json
import platform
import sys
import time
from collections import defaultdict
from pathlib import Path

sys.path.append(str(Path(__file__).resolve().parents[1]))   # the checkout's clrf only where none is installed



def cpu_model() -> str:
    try:
        for line in open("/proc/cpuinfo"):
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or "unknown CPU"


def changed_config(model, assignments):
    """The hash model's config with hash.FIELD=VALUE assignments applied (values parsed as
    JSON, else taken as strings); other models or unknown fields are an error."""
    import dataclasses
    from clrf.hash.config import HashConfig
    if not isinstance(model.config, HashConfig):
        raise SystemExit("--set: only a hash model's options can be changed here")
    names = {f.name for f in dataclasses.fields(HashConfig)}
    over = {}
    for item in assignments:
        key, sep, val = item.partition("=")
        field = key[len("hash."):] if key.startswith("hash.") else None
        if not sep or field not in names:
            raise SystemExit(f"--set {item!r}: expected hash.FIELD=VALUE with FIELD one of "
                             f"{sorted(names)}")
        try:
            over[field] = json.loads(val)
        except json.JSONDecodeError:
            over[field] = val
    return dataclasses.replace(model.config, **over)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--ckpt", required=True, help="run directory written by clrf train --out")
    ap.add_argument("--data", default=None, help="dataset folder (default: the run's)")
    ap.add_argument("--steps", type=int, default=40, help="timed steps (default 40)")
    ap.add_argument("--device", default=None, help="CLRF_DEVICE-style spec")
    ap.add_argument("--json", default=None, help="write the figures here too")
    ap.add_argument("--bounded", choices=("auto", "on", "off"), default="auto",
                    help="a hash model's steps with their sizes on the device (on; the GPU "
                         "default) or read back (off; the CPU default); auto: the device's")
    ap.add_argument("--set", action="append", default=[], metavar="hash.FIELD=VALUE",
                    help="profile with a hash model option changed (e.g. hash.train_t_stop=0 "
                         "or hash.batch_samples=262144); repeatable")
    ap.add_argument("--exposure-two-pass", action="store_true",
                    help="a grid model with grid.exposure: render each batch first and run "
                         "the backward on the transformed target (the step a camera step "
                         "takes) instead of the transform inside the backward's one march")
    a = ap.parse_args(argv)

    from clrf.runtime.device import Device
    from clrf.training.models import checkpoint_dataset, load_model
    from clrf.training.trainer import train_on_batch, training_rays

    dev = Device(a.device)
    model, state, cfg = load_model(dev, a.ckpt)
    ds = checkpoint_dataset(state, a.data)
    from clrf import registry
    if registry.get(model.kind).batches == "views":   # the model draws its own views
        model.attach(ds, cfg.train.max_train_images)
        rays = None
    else:
        rays = training_rays(dev, ds, cfg.train.max_train_images,
                             alpha=getattr(model, "random_background", False))
    it0 = int(state.get("iteration", 0))
    if a.set:                    # the untimed steps below adapt the batch to it
        model.config = changed_config(model, a.set)
    if a.exposure_two_pass:
        if not hasattr(model, "colour_in_backward"):
            raise SystemExit(f"--exposure-two-pass: the {model.kind} model has no such step")
        model.colour_in_backward = False
    if a.bounded != "auto":
        if not hasattr(model, "bounded"):
            raise SystemExit(f"--bounded: the {model.kind} model has no bounded step")
        model.bounded = a.bounded == "on"

    def step(i):
        n = model.batch_size
        train_on_batch(model, rays, cfg.train.seed, it0 + i, n)
        return n

    for i in range(3):                              # builds, first allocations
        step(i)
    dev.queue.finish()
    t = time.perf_counter()
    rays_done = sum(step(3 + i) for i in range(a.steps))
    dev.queue.finish()
    total = time.perf_counter() - t

    import pyopencl as cl
    per = defaultdict(float)
    calls = defaultdict(int)
    enqueue = cl.enqueue_nd_range_kernel

    def timed(queue, kernel, *args, **kw):       # every clrf launch goes through this name
        queue.finish()
        t0 = time.perf_counter()
        ev = enqueue(queue, kernel, *args, **kw)
        queue.finish()
        per[kernel.function_name] += time.perf_counter() - t0
        calls[kernel.function_name] += 1
        return ev

    cl.enqueue_nd_range_kernel = timed
    try:
        t = time.perf_counter()
        for i in range(a.steps):
            step(3 + a.steps + i)
        dev.queue.finish()
        total_waited = time.perf_counter() - t
    finally:
        cl.enqueue_nd_range_kernel = enqueue

    caps = dev.caps
    print(f"CPU: {cpu_model()}; OpenCL: {caps.platform_version}; device {caps.name}")
    print(f"model: {model.describe()}"
          + (f"; bounded step: {model.bounded}" if hasattr(model, "bounded") else ""))
    print(f"{a.steps} steps, {rays_done / a.steps:,.0f} rays per step: {total / a.steps * 1e3:.1f} "
          f"ms per step ({rays_done / total:,.0f} rays/s); with a wait after each launch "
          f"{total_waited / a.steps * 1e3:.1f} ms")
    rows = sorted(per.items(), key=lambda kv: -kv[1])
    kern = sum(per.values())
    print(f"{'kernel':32s} {'ms/step':>9s} {'share':>7s} {'calls/step':>10s}")
    for name, s in rows:
        print(f"{name:32s} {s / a.steps * 1e3:9.2f} {s / total_waited:7.1%} "
              f"{calls[name] / a.steps:10.1f}")
    rest = total_waited - kern
    print(f"{'(rest: pyopencl ops, transfers, host)':32s} {rest / a.steps * 1e3:9.2f} "
          f"{rest / total_waited:7.1%}")
    if a.json:
        Path(a.json).write_text(json.dumps({
            "cpu": cpu_model(), "platform": caps.platform_version, "device": caps.name,
            "model": model.describe(), "bounded": getattr(model, "bounded", None),
            "steps": a.steps, "rays_per_step": rays_done / a.steps,
            "ms_per_step": total / a.steps * 1e3,
            "ms_per_step_waited": total_waited / a.steps * 1e3,
            "kernels_ms_per_step": {k: v / a.steps * 1e3 for k, v in rows},
            "calls_per_step": {k: calls[k] / a.steps for k, _ in rows},
            "rest_ms_per_step": rest / a.steps * 1e3}, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
