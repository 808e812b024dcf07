"""The terms of a distributed splat step (clrf/splat/distributed.py) and the scaling model
docs/scaling.md builds on them: per step the compute each phase takes, the records and
gradients each rank sends, and the time in the two all-to-alls.

    mpirun --bind-to core -n 1 python tools/mpi_splat_bench.py runs/bonsai   # the terms
    mpirun --bind-to core -n 2 python tools/mpi_splat_bench.py runs/bonsai   # measured
    python tools/mpi_splat_bench.py --predict tools/results/X/terms.json     # the model

RUN is a splat run (a single-process or a distributed checkpoint) and its dataset: the
Gaussians are frozen at the checkpoint's (density control off), each rank keeps its shard and
trains --steps timed steps of the run's views after --warmup. Rank 0 prints one JSON record:
the median step and, summed over a step on the slowest rank, each phase's seconds (every
phase ends with the queue finished, so the phases' sum is the step):

  project      the shard projected into the P cameras (kernels) and the records read back
  exchange     the records' Alltoallv (after a barrier: the wait for the slowest is apart)
  render       the owner's records uploaded, binning, raster and raster backward
  loss         the owner's loss and its gradient (L1 and D-SSIM of the view)
  return       the gradients' Alltoallv and their scatter to the shard's rows (host)
  backward     the projection backward of the shard for the P cameras
  stats        the strategy's statistics of each camera (after the backward and the update)
  adam         the shard's Adam step
  host         the rest: the gradients uploaded, the loss read, the 3D filter's update
               (every 100 steps, over every training camera)

with the records (15 floats) and gradients (9 floats) each rank sent, the splats its view
saw, and the Gaussians. ``--predict`` reads records of 1 rank (the terms) and prints the
step time the model gives for P ranks of this machine's cores and for nodes on 10, 25 and 100
Gb/s networks (docs/scaling.md has the model and its figures).
"""
from __future__ import annotations

import argparse
import json
import platform
import sys
import time
from pathlib import Path

import numpy as np

sys.path.append(str(Path(__file__).resolve().parent.parent))  # an installed clrf comes first

PHASES = ("project", "exchange", "render", "loss", "return", "backward", "stats", "adam",
          "host")
RECORD_BYTES, GRAD_BYTES = 15 * 4, 9 * 4
SHM_LATENCY = 2e-5      # seconds a message between ranks of one machine (Open MPI, shared memory)


def cpu_name() -> str:
    for line in Path("/proc/cpuinfo").read_text().splitlines():
        if line.startswith("model name"):
            return line.split(":", 1)[1].strip()
    return platform.processor()


class Clock:
    """Seconds per phase of the current step; ``run(name, f, ...)`` times f with the queue
    finished before and after (so each phase holds its own kernels)."""

    def __init__(self, queue):
        self.queue, self.t = queue, dict.fromkeys(PHASES, 0.0)

    def run(self, name, f, *args, **kw):
        self.queue.finish()
        t0 = time.perf_counter()
        out = f(*args, **kw)
        self.queue.finish()
        self.t[name] += time.perf_counter() - t0
        return out


def instrument(model, clock: Clock, sent: dict):
    """Wraps the step's pieces of ``model`` (a DistSplatModel) and its module's exchanges in
    ``clock``; ``sent`` gathers a step's bytes sent to other ranks and its view's splats."""
    from clrf.splat import distributed as D
    rast = model.rast
    records, a2a, pof, rg = D._records, D._alltoallv, D.projected_of, D.return_grads
    D._records = lambda proj: clock.run("project", records, proj)

    def _alltoallv(comm, parts):
        mine = sum(p.shape[0] for k, p in enumerate(parts) if k != comm.Get_rank())
        if parts[0].shape[1] != D.RECORD:       # the gradients: inside return_grads' time
            sent["return"] = sent.get("return", 0) + mine * parts[0].shape[1] * 4
            return a2a(comm, parts)
        sent["exchange"] = sent.get("exchange", 0) + mine * D.RECORD * 4
        comm.Barrier()      # the wait for the slowest rank is not the exchange's
        return clock.run("exchange", a2a, comm, parts)
    D._alltoallv = _alltoallv

    def projected_of(dev, rec):
        sent["view_splats"] = len(rec)
        return clock.run("render", pof, dev, rec)
    D.projected_of = projected_of

    def return_grads(comm, *a, **k):
        comm.Barrier()
        return clock.run("return", rg, comm, *a, **k)
    D.return_grads = return_grads
    adam = model._adam
    model._adam = lambda *a, **k: clock.run("adam", adam, *a, **k)
    for hook in ("step_post_backward", "step_post_update"):
        f = getattr(model.strategy, hook)
        setattr(model.strategy, hook, (lambda f: lambda *a, **k: clock.run("stats", f, *a, **k))(f))
    loss = model._loss()
    lg = loss.loss_and_grad
    loss.loss_and_grad = lambda *a, **k: clock.run("loss", lg, *a, **k)
    for name, phase in (("project", "project"), ("bin", "render"), ("rasterize", "render"),
                        ("rasterize_backward", "render"), ("project_backward", "backward")):
        f = getattr(rast, name)
        setattr(rast, name, (lambda f, phase: lambda *a, **k: clock.run(phase, f, *a, **k))(
            f, phase))


def measure(a) -> dict:
    from mpi4py import MPI
    import clrf
    from clrf.outputs import checkpoint
    from clrf.runtime.mpi import pin_threads
    from clrf.splat.kind import Distributed
    from clrf.training.models import checkpoint_dataset
    comm = MPI.COMM_WORLD
    P, rank = comm.Get_size(), comm.Get_rank()
    pin_threads()
    dev = clrf.Device()
    state = checkpoint.load(a.run)
    cfg = state["run_config"]
    ds = checkpoint_dataset(state)
    model = Distributed(comm).from_state(dev, state, None)
    model.attach(ds)
    clock, sent = Clock(dev.queue), {}
    instrument(model, clock, sent)
    steps, phases, splats = [], [], []
    for it in range(a.warmup + a.steps):
        comm.Barrier()
        clock.t = dict.fromkeys(PHASES, 0.0)
        sent.clear()
        t0 = time.perf_counter()
        model.train_step(it)
        dev.queue.finish()
        dt = time.perf_counter() - t0
        if it >= a.warmup:
            steps.append(dt)
            t = dict(clock.t)
            t["host"] = dt - sum(t[p] for p in PHASES if p != "host")
            phases.append(t)
            splats.append(dict(sent))
    step = float(np.median(steps))
    own = {p: float(np.median([t[p] for t in phases])) for p in PHASES}
    every = comm.gather({"step": step, "phases": own, "n": int(model.n),
                         "sent": {k: float(np.median([s.get(k, 0) for s in splats]))
                                  for k in ("exchange", "return", "view_splats")}}, root=0)
    if rank != 0:
        return {}
    slowest = max(every, key=lambda e: e["step"])
    return {"run": str(a.run), "ranks": P, "gaussians": int(sum(e["n"] for e in every)),
            "view_pixels": int(np.prod(ds.hw)), "steps": a.steps,
            "step_s": float(max(e["step"] for e in every)),
            "phases_s": slowest["phases"],
            "records_bytes_sent": [e["sent"]["exchange"] for e in every],
            "grad_bytes_sent": [e["sent"]["return"] for e in every],
            "view_splats": float(np.mean([e["sent"]["view_splats"] for e in every])),
            "sh_degree": int(cfg["splat"]["sh_degree"]),
            "cpu": cpu_name(), "device": dev.caps.name, "platform": dev.caps.platform_version}


# ---- the model --------------------------------------------------------------------------------
def predict(terms: dict, P: int, cores: int, bandwidth_gbps: float | None,
            latency_s: float, splats_per_view: float) -> dict:
    """The step time of P ranks from one rank's ``terms`` (module doc; docs/scaling.md):
    per rank, the projection and its backward of N / P Gaussians into P cameras with the
    gradients' scatter and upload (P times one camera's work on N / P: the terms' 1-rank
    figures), the owner's render of one view, Adam on N / P, and the two exchanges: each rank sends (P - 1) / P of the records and
    gradients of its view's splats at ``bandwidth_gbps`` (None: the 1-rank terms have no
    exchange, and this machine's shared memory is taken as free of bandwidth cost) plus
    2 (P - 1) messages of ``latency_s``. With more ranks than ``cores`` the compute stretches
    by P / cores."""
    ph = terms["phases_s"]
    stretch = max(1.0, P / cores)
    compute = {"project": ph["project"], "backward": ph["backward"], "render": ph["render"],
               "loss": ph["loss"], "return": ph["return"], "stats": ph["stats"],
               "host": ph["host"], "adam": ph["adam"] / P}
    share = (P - 1) / P
    bytes_ = share * splats_per_view * (RECORD_BYTES + GRAD_BYTES)
    comm = 2 * (P - 1) * latency_s
    if bandwidth_gbps:
        comm += bytes_ * 8 / (bandwidth_gbps * 1e9)
    total = stretch * sum(compute.values()) + comm
    return {"ranks": P, "step_s": total, "views_per_s": P / total,
            "compute_s": stretch * sum(compute.values()), "comm_s": comm,
            "bytes_per_rank": bytes_}


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("run", nargs="?", help="a splat run folder or checkpoint")
    ap.add_argument("--warmup", type=int, default=3)
    ap.add_argument("--steps", type=int, default=10)
    ap.add_argument("--predict", type=Path, nargs="+",
                    help="print the model from a 1-rank record (the first), against the "
                         "measured step of the records of more ranks that follow")
    ap.add_argument("--cores", type=int, default=2, help="cores of this machine (--predict)")
    ap.add_argument("--latency", type=float, default=5e-6,
                    help="seconds a message on the network (--predict)")
    a = ap.parse_args()
    if a.predict:
        terms, *measured = (json.loads(p.read_text()) for p in a.predict)
        splats = terms["view_splats"]
        here = []
        for m in [terms] + measured:
            p = predict(terms, m["ranks"], a.cores, None, SHM_LATENCY, splats)
            p["measured_step_s"] = m["step_s"]
            p["error"] = p["step_s"] / m["step_s"] - 1.0
            here.append(p)
        out = {"here": here,
               "nodes": [dict(predict(terms, P, P, bw, a.latency, splats), gbps=bw)
                         for bw in (10, 25, 100) for P in (8, 16, 64)]}
        print(json.dumps(out, indent=2))
        return
    if not a.run:
        ap.error("RUN is needed to measure")
    rec = measure(a)
    if rec:
        print(json.dumps(rec))


if __name__ == "__main__":
    main()
