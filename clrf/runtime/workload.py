"""Device choice by what clrf will run: a short timed run of each model kind's hot kernels.

The FMA probe (clrf/device_probe.py) says which devices work and what their arithmetic peak is,
but not which runs clrf's kernels faster: on one CPU, Intel's runtime and PoCL measure the
same peak while Intel runs the grid march at half PoCL's speed and the fused MLP faster. So
for the default device of a model kind, every working candidate (simulators and devices known
to compute wrong gradients left out) runs that kind's workload once, cached like the probe in
``$XDG_CACHE_HOME/clrf/workloads.json`` by device key, workload and kernel-source hash:

- ``grid``: forward + backward (float32 gradients, the device's own tuning) of WORK_RAYS
  random rays through a dense WORK_RESO^3 SH-degree-2 grid, in rays/s;
- ``nerf``: the fused MLP forward + backward of the tiny NeRF shape (4 x 64) on WORK_SAMPLES
  samples, in samples/s.

Each figure is the best of WORK_REPEATS runs after a warm-up (about a second per device and
kind on a 2-core CPU, build included). Figures within TIE of the best count as equal, and then
the probe's order decides, so the choice does not flip on noise.
"""
from __future__ import annotations

import hashlib
import json
import os
import tempfile
import time

import numpy as np

from .device_probe import TIE, cache_path, device_key
from .programs import cl_dir

WORKLOAD_VERSION = 1
KINDS = ("grid", "nerf")
WORK_RESO = 48
WORK_RAYS = 4096
WORK_SAMPLES = 8192
WORK_REPEATS = 3


def _sources_hash() -> str:
    h = hashlib.sha256()
    for p in sorted(cl_dir().glob("*")):
        if p.suffix in (".cl", ".h"):
            h.update(p.name.encode() + p.read_bytes())
    return h.hexdigest()[:16]


def _file():
    return cache_path().with_name("workloads.json")


def _key(cl_device, kind: str) -> str:
    return "|".join([device_key(cl_device), kind, _sources_hash(), f"v{WORKLOAD_VERSION}"])


def _load() -> dict:
    try:
        d = json.loads(_file().read_text())
        return d if isinstance(d, dict) else {}
    except (OSError, ValueError):
        return {}


def _store(key: str, value: float) -> None:
    d = _load()
    d[key] = value
    path = _file()
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        fd, tmp = tempfile.mkstemp(prefix=".workloads.", suffix=".tmp", dir=path.parent)
        with os.fdopen(fd, "w") as f:
            json.dump(d, f, indent=1, sort_keys=True)
        os.replace(tmp, path)
    except OSError:
        pass


def _best_time(step) -> float:
    step()                                     # warm-up: builds, first-touch of buffers
    best = float("inf")
    for _ in range(WORK_REPEATS):
        t0 = time.perf_counter()
        step()
        best = min(best, time.perf_counter() - t0)
    return best


def _grid_rate(device) -> float:
    import pyopencl.array as cla

    from ..grid.grid import SparseGrid
    from ..grid.render import render_backward_device, render_forward_device
    from .programs import upload
    rng = np.random.default_rng(3)
    r = WORK_RESO
    dens = rng.uniform(0.0, 0.3, (r, r, r)).astype(np.float32)
    sh = rng.normal(0.0, 0.3, (r, r, r, 27)).astype(np.float32)
    grid = SparseGrid.from_dense(device, dens, sh, np.array([[-1.0] * 3, [1.0] * 3]))
    o = rng.uniform(-0.5, 0.5, (WORK_RAYS, 3)) + np.array([0.0, 0.0, -3.0])
    d = rng.uniform(-0.4, 0.4, (WORK_RAYS, 3)) + np.array([0.0, 0.0, 1.0])   # towards the box
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    q = device.queue
    od, dd = upload(q, o.astype(np.float32)), upload(q, d.astype(np.float32))
    g = upload(q, rng.normal(size=(WORK_RAYS, 3)).astype(np.float32))
    gd = cla.zeros(q, grid.density.shape[0], np.float32)
    gs = cla.zeros(q, grid.sh.shape, np.float32)

    def step():
        render_forward_device(grid, od, dd, 0.5, (1.0, 1.0, 1.0))
        render_backward_device(grid, od, dd, g, 0.5, (1.0, 1.0, 1.0), gd, gs)
        q.finish()
    return WORK_RAYS / _best_time(step)


def _nerf_rate(device) -> float:
    import pyopencl.array as cla

    from ..nerf.mlp import MLP, MLPSpec
    spec = MLPSpec(width=64, depth=4, skip=-1, color_width=32, in_dim=51, dir_dim=15)
    net = MLP(device, spec)
    q = device.queue
    rng = np.random.default_rng(4)
    n = WORK_SAMPLES
    x = cla.to_device(q, rng.random((n, spec.in_dim), np.float32))
    d = cla.to_device(q, rng.random((n, spec.dir_dim), np.float32))
    ds = cla.to_device(q, rng.random(n, np.float32))
    dr = cla.to_device(q, rng.random((n, 3), np.float32))

    def step():
        net.forward(x, d)
        net.backward(ds, dr)
        q.finish()
    return n / _best_time(step)


RATES = {"grid": _grid_rate, "nerf": _nerf_rate}
UNITS = {"grid": "rays/s", "nerf": "samples/s"}


def rate(device, kind: str, refresh: bool = False, measure: bool = True) -> float | None:
    """The cached (else measured, unless ``measure`` is False) workload figure of ``kind`` on
    ``device`` (a clrf Device); 0.0 when the workload fails there."""
    key = _key(device.cl_device, kind)
    if not refresh:
        v = _load().get(key)
        if isinstance(v, (int, float)):
            return float(v)
    if not measure:
        return None
    try:
        v = float(RATES[kind](device))
    except Exception:  # noqa: BLE001 - a device that cannot run the workload is not chosen
        v = 0.0
    _store(key, v)
    return v


def pick(figures: list) -> int:
    """Index of the winner among ``figures`` (in probe order): the first within TIE of the
    best, so near-equal figures keep the probe's order."""
    top = max(figures)
    return next(i for i, f in enumerate(figures) if f >= top * (1 - TIE))


def _contenders(choice) -> list:
    """The ranked candidates worth a workload run: no simulator, no flagged slow driver."""
    from .device_probe import cpu_flags, slow_reasons
    flags = cpu_flags()
    cands = list(choice.candidates)
    return [c for c in choice.ranked if "oclgrind" not in c.platform.lower()
            and not slow_reasons(c, cands, flags)]


def device_for(kind: str, spec: str | None = None, measure: bool = True):
    """The Device to run model kind ``kind`` on: the one ``spec`` (or CLRF_DEVICE) names when
    it names one ("P:D"), else, among the devices the spec allows ("auto", "cpu", "gpu"), the
    one whose ``kind`` workload is fastest (module doc). ``device.choice`` says why."""
    from .device import Device, choose_device
    s = (spec if spec is not None else os.environ.get("CLRF_DEVICE", "")).strip().lower()
    if ":" in s or kind not in RATES:
        return Device(spec)
    choice = choose_device(s or None)
    cands = _contenders(choice)
    if len(cands) <= 1:
        return Device(spec)
    devs = [Device(c.spec) for c in cands]
    figs = [rate(d, kind, measure=measure) or 0.0 for d in devs]
    if not any(figs):
        return Device(spec)
    i = pick(figs)
    dev = devs[i]
    others = ", ".join(f"{c.spec} {f:,.0f}" for j, (c, f) in enumerate(zip(cands, figs)) if j != i)
    dev.choice = (f"fastest {kind} workload: {figs[i]:,.0f} {UNITS[kind]} (others: {others})"
                  if figs[i] > max(f for j, f in enumerate(figs) if j != i) * (1 + TIE) else
                  f"{kind} workload within {TIE:.0%} of the best ({figs[i]:,.0f} "
                  f"{UNITS[kind]}; others: {others}), first by probe")
    return dev


def format_choices(measure: bool = False) -> list:
    """Lines for ``clrf devices``: each model kind's default device and the figures behind it
    (cached figures; ``measure`` runs the missing workloads)."""
    from .device import DeviceError, choose_device
    lines = []
    try:
        choice = choose_device()
    except DeviceError:
        return lines
    cands = _contenders(choice)
    if len(cands) <= 1:
        return lines
    from .device import Device
    devs = [Device(c.spec) for c in cands]
    for kind in KINDS:
        figs = [rate(d, kind, measure=measure) for d in devs]
        shown = ", ".join(f"{c.spec} {'?' if f is None else f'{f:,.0f}'}"
                          for c, f in zip(cands, figs))
        if any(f is None for f in figs):
            lines.append(f"default for --model {kind}: by workload once measured "
                         f"({UNITS[kind]}: {shown}; `clrf devices --workloads` measures)")
            continue
        i = pick(figs)
        lines.append(f"default for --model {kind}: {cands[i].short()}: fastest {kind} "
                     f"workload ({UNITS[kind]}: {shown})")
    return lines
