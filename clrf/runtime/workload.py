"""Device choice by what clrf will run: a short timed run of each model kind's hot kernels.

The runs themselves belong to the model kinds (``Workload``: clrf/grid/workload.py,
clrf/nerf/workload.py); the caller passes the one to choose by (clrf/training/models.py
WORKLOADS), and this module times, caches and compares.

The FMA probe (clrf/runtime/device_probe.py) says which devices work and what their arithmetic peak is,
but not which runs clrf's kernels faster: on one CPU, Intel's runtime and PoCL measure the
same peak while Intel runs the grid march at half PoCL's speed and the fused MLP faster. So
for the default device of a model kind, every working candidate (simulators and devices known
to compute wrong gradients left out) runs that kind's workload once, cached like the probe in
``$XDG_CACHE_HOME/clrf/workloads.json`` by device key, workload and kernel-source hash:

- ``grid`` (clrf/grid/workload.py): a training step's fused forward + backward (float32
  gradients, the device's own tuning) of a batch of incoherent rays through a dense
  SH-degree-2 grid, in rays/s;
- ``nerf`` (clrf/nerf/workload.py): the fused MLP forward + backward of the tiny NeRF shape
  (4 x 64) on WORK_SAMPLES samples, in samples/s.

Each figure is the best of WORK_REPEATS runs after a warm-up (about a second per device and
kind on a 2-core CPU, build included). Figures within TIE of the best count as equal, and then
the probe's order decides, so the choice does not flip on noise.
"""
from __future__ import annotations

import hashlib
import os
from dataclasses import dataclass
from typing import Callable

from . import measure
from .device_probe import TIE, cache_path, device_key
from .jsonfile import read_dict, write_dict
from .programs import cl_dir

WORKLOAD_VERSION = 2   # 2: the grid's fused training step (2026-11-25)
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
    return read_dict(_file())


def _store(key: str, value: float) -> None:
    d = _load()
    d[key] = value
    write_dict(_file(), d)


def best_time(step) -> float:
    """The best of WORK_REPEATS timed runs of ``step()`` after a warm-up."""
    return measure.best_time(step, WORK_REPEATS)


@dataclass(frozen=True)
class Workload:
    """A model kind's timed run: ``rate(device)`` runs it and returns its throughput in
    ``unit``; ``name`` (the model kind) keys its cached figures."""
    name: str
    rate: Callable
    unit: str


def rate(device, work: Workload, refresh: bool = False, measure: bool = True) -> float | None:
    """The cached (else measured, unless ``measure`` is False) figure of Workload ``work`` on
    ``device`` (a clrf Device); 0.0 when the workload fails there."""
    key = _key(device.cl_device, work.name)
    if not refresh:
        v = _load().get(key)
        if isinstance(v, (int, float)):
            return float(v)
    if not measure:
        return None
    try:
        v = float(work.rate(device))
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


def device_for(work: Workload | None, spec: str | None = None, measure: bool = True):
    """The Device to run Workload ``work``'s model kind on: the one ``spec`` (or CLRF_DEVICE)
    names when it names one ("P:D"), else, among the devices the spec allows ("auto", "cpu",
    "gpu"), the one where ``work`` runs fastest (module doc); the probe's choice when ``work``
    is None (a kind without a workload). ``device.choice`` says why."""
    from . import device as devmod
    s = (spec if spec is not None else os.environ.get("CLRF_DEVICE", "")).strip().lower()
    if ":" in s or work is None:
        return devmod.Device(spec)
    Device = devmod.Device
    choice = devmod.choose_device(s or None)
    cands = _contenders(choice)
    if len(cands) <= 1:
        return Device(spec)
    devs = [Device(c.spec) for c in cands]
    figs = [rate(d, work, measure=measure) or 0.0 for d in devs]
    if not any(figs):
        return Device(spec)
    i = pick(figs)
    dev = devs[i]
    others = ", ".join(f"{c.spec} {f:,.0f}" for j, (c, f) in enumerate(zip(cands, figs)) if j != i)
    kind, unit = work.name, work.unit
    dev.choice = (f"fastest {kind} workload: {figs[i]:,.0f} {unit} (others: {others})"
                  if figs[i] > max(f for j, f in enumerate(figs) if j != i) * (1 + TIE) else
                  f"{kind} workload within {TIE:.0%} of the best ({figs[i]:,.0f} "
                  f"{unit}; others: {others}), first by probe")
    return dev


def format_choices(workloads, measure: bool = False) -> list:
    """Lines for ``clrf devices``: the default device of each Workload of ``workloads`` (a
    model kind's, in order) and the figures behind it (cached figures; ``measure`` runs the
    missing workloads)."""
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
    for work in workloads:
        kind, unit = work.name, work.unit
        figs = [rate(d, work, measure=measure) for d in devs]
        shown = ", ".join(f"{c.spec} {'?' if f is None else f'{f:,.0f}'}"
                          for c, f in zip(cands, figs))
        if any(f is None for f in figs):
            lines.append(f"default for --model {kind}: by workload once measured "
                         f"({unit}: {shown}; `clrf devices --workloads` measures)")
            continue
        i = pick(figs)
        lines.append(f"default for --model {kind}: {cands[i].short()}: fastest {kind} "
                     f"workload ({unit}: {shown})")
    return lines
