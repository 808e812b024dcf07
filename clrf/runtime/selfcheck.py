"""Self-check verdicts: does a device, driver and gradient path compute correct gradients?

A driver can compile clrf's kernels and still compute wrong gradients, and training on them
runs for minutes without an error. The layer that owns a backward kernel defines a check of it
(``GradientCheck``: the kernel sources it covers, a version, the function that runs it; the
grid's is clrf/grid/selfcheck.py) and registers it here. This module keeps the verdicts: it
runs a check once per device, driver, gradient path and kernel source, caches the result next
to the probe figures (``$XDG_CACHE_HOME/clrf/selfcheck.json``, keyed by the probe's device key,
the tuning's gradient path, the sample-record switch, a hash of the check's sources and its
version), and tells the device choice (clrf/runtime/device.py) which devices are known, from
the cache alone, to compute wrong gradients on their float-atomic path: such a device is never
the default.
"""
from __future__ import annotations

import hashlib
from dataclasses import dataclass
from typing import Callable

from .device_probe import cache_path, device_key
from .jsonfile import read_dict, write_atomic
from .programs import cl_dir


@dataclass(frozen=True)
class CheckResult:
    ok: bool
    detail: str          # what failed, in words ("" when ok)
    path: str            # the gradient path checked ("atomics", "slots", "slots+locks")


@dataclass(frozen=True)
class GradientCheck:
    """A check of a backward kernel: ``run(device)`` returns '' when the device's gradients
    are right, else why not; ``sources`` (files of cl/) and ``version`` key its verdicts."""
    sources: tuple
    version: int
    run: Callable
    what: str = "the backward"   # names the kernel in messages ("the grid backward")


_CHECKS: list = []   # the registered checks (known_wrong reads their verdicts)


def register(check: GradientCheck) -> GradientCheck:
    """Make ``check``'s cached verdicts count for the device choice; returns it."""
    if check not in _CHECKS:
        _CHECKS.append(check)
    return check


def path_name(tuning) -> str:
    if tuning.grad_slots <= 0:
        return "atomics"
    return "slots+locks" if tuning.grad_locks > 0 else "slots"


def sources_hash(names) -> str:
    h = hashlib.sha256()
    for name in names:
        p = cl_dir() / name
        if p.exists():
            h.update(p.read_bytes())
    return h.hexdigest()[:16]


def _cache_file():
    return cache_path().with_name("selfcheck.json")


def check_key(device, check: GradientCheck) -> str:
    t = device.tuning
    return "|".join([device_key(device.cl_device), path_name(t), f"rec{int(t.sample_record)}",
                     sources_hash(check.sources), f"v{check.version}"])


def _load() -> dict:
    return read_dict(_cache_file())


def _store(key: str, res: CheckResult) -> None:
    d = _load()
    d[key] = {"ok": res.ok, "detail": res.detail, "path": res.path}
    write_atomic(_cache_file(), d)


def run_check(device, check: GradientCheck) -> CheckResult:
    """Run ``check`` on ``device`` with its own tuning now (no cache)."""
    try:
        why = check.run(device)
    except Exception as e:  # noqa: BLE001 - any driver failure means: not trusted
        why = f"{type(e).__name__}: {str(e).splitlines()[0] if str(e) else ''}"
    return CheckResult(not why, why, path_name(device.tuning))


def gradient_check(device, check: GradientCheck, refresh: bool = False,
                   run=None) -> CheckResult:
    """The cached verdict of ``check`` on ``device``'s gradient path, measured when missing
    (with ``run(device)``, default ``run_check(device, check)``) and then cached."""
    key = check_key(device, check)
    if not refresh:
        e = _load().get(key)
        if isinstance(e, dict) and isinstance(e.get("ok"), bool):
            return CheckResult(e["ok"], str(e.get("detail", "")), str(e.get("path", "")))
    res = run(device) if run is not None else run_check(device, check)
    _store(key, res)
    return res


def known_wrong(cl_device, checks=None) -> str | None:
    """Why ``cl_device`` is known (from the cache only; nothing is run) to compute wrong
    gradients on its float-atomic path with the current kernels under one of ``checks``
    (default: the registered ones), or None."""
    head = device_key(cl_device) + "|atomics|"
    entries = _load()
    for check in (_CHECKS if checks is None else checks):
        tail = f"|{sources_hash(check.sources)}|v{check.version}"
        for k, e in entries.items():
            if (k.startswith(head) and k.endswith(tail) and isinstance(e, dict)
                    and e.get("ok") is False):
                return str(e.get("detail", "wrong gradients"))
    return None

