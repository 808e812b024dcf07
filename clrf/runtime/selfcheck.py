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

Only wrong numbers from a kernel (or a driver error, or a driver crash) are a verdict on a
driver. A check runs in a child process (clrf/runtime/isolate.py), so a driver that crashes is
refused with that reason instead of taking clrf down. An exception raised by clrf's own code
while checking (an import that fails in a broken install, a bug) is no verdict: it is raised
as ``InstallError`` or ``ClrfBug`` with its traceback and clrf's version, and never cached. A
cached verdict carries clrf's version and a hash of the checking code beside the kernel
sources' hash, so a new clrf checks again.
"""
from __future__ import annotations

import dataclasses
import hashlib
import inspect
import sys
import traceback
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

import pyopencl as cl

from .device_probe import cache_path, device_key
from .jsonfile import read_dict, write_dict
from .programs import BuildError, cl_dir

CHECK_TIMEOUT_S = 900     # a self-check child that runs longer is taken as hung
ISOLATE = True            # run checks in a child process (tests of in-process fakes set False)


class SelfCheckError(RuntimeError):
    """A self-check could not reach a verdict because of clrf itself (never cached)."""


class InstallError(SelfCheckError):
    """clrf's installation is incomplete: one of its own modules cannot be imported."""


class ClrfBug(SelfCheckError):
    """clrf's own code raised an exception while checking a device: a bug to report."""


def clrf_version() -> str:
    from .version import VERSION
    return VERSION


def own_error(exc: BaseException, what: str) -> SelfCheckError:
    """The error to raise for an exception of clrf's own code while running ``what``."""
    tb = "".join(traceback.format_exception(type(exc), exc, exc.__traceback__)).rstrip()
    return own_error_text(f"{type(exc).__name__}: {exc}", tb, what,
                           getattr(exc, "name", None) if isinstance(exc, ImportError) else None)


def own_error_text(line: str, tb: str, what: str, missing: str | None) -> SelfCheckError:
    where = Path(__file__).resolve().parent.parent      # the clrf package (this is runtime/)
    if missing and (missing == "clrf" or missing.startswith("clrf.")):
        return InstallError(
            f"clrf {clrf_version()} is installed incompletely: module '{missing}' is missing "
            f"from {where} (needed by {what}). This is not the OpenCL driver's fault. Reinstall "
            f"clrf (`bash tools/setup.sh`, or `pip install --force-reinstall .` in its "
            f"folder)\n{tb}")
    return ClrfBug(
        f"clrf {clrf_version()} ({where}) raised {line} while running {what}: a bug in clrf, "
        f"not a verdict on the OpenCL driver (nothing was cached). Please report it with this "
        f"traceback\n{tb}")


def is_driver_error(exc: BaseException) -> bool:
    """Whether ``exc`` comes from the OpenCL driver (a call it failed, a build it refused)
    rather than from clrf's own code."""
    return isinstance(exc, (cl.Error, BuildError))


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


def code_hash(check: GradientCheck) -> str:
    """Hash of the Python module that defines ``check.run`` (the checking code itself)."""
    h = hashlib.sha256()
    try:
        h.update(Path(inspect.getsourcefile(check.run)).read_bytes())
    except (TypeError, OSError):
        h.update(check.run.__module__.encode())
    return h.hexdigest()[:12]


def _tail(check: GradientCheck) -> str:
    """What a verdict of ``check`` is valid for besides the device and path: the kernel
    sources, the check's version, clrf's version and the checking code."""
    return "|".join([sources_hash(check.sources), f"v{check.version}",
                     f"clrf{clrf_version()}", code_hash(check)])


def check_key(device, check: GradientCheck) -> str:
    t = device.tuning
    return "|".join([device_key(device.cl_device), path_name(t), f"rec{int(t.sample_record)}",
                     _tail(check)])


def _load() -> dict:
    return read_dict(_cache_file())


def _store(key: str, res: CheckResult) -> None:
    d = _load()
    d[key] = {"ok": res.ok, "detail": res.detail, "path": res.path}
    write_dict(_cache_file(), d)


def run_check(device, check: GradientCheck) -> CheckResult:
    """Run ``check`` on ``device`` with its own tuning now, in this process (no cache). A
    driver error is a failing verdict; an exception of clrf's own code raises InstallError
    or ClrfBug (module doc)."""
    try:
        why = check.run(device)
    except Exception as e:  # noqa: BLE001 - sorted into driver verdicts and clrf's own errors
        if not is_driver_error(e):
            raise own_error(e, f"the self-check of {check.what}") from e
        why = f"{type(e).__name__}: {str(e).splitlines()[0] if str(e) else ''}"
    return CheckResult(not why, why, path_name(device.tuning))


def run_isolated(device, check: GradientCheck) -> CheckResult:
    """``run_check`` in a child process (clrf/runtime/isolate.py): a driver that crashes
    gives a failing verdict that says so."""
    from .device_probe import locate
    from .isolate import run_child
    what = f"the self-check of {check.what}"
    try:
        pi, di = locate(device.cl_device)
    except (LookupError, cl.Error):
        return run_check(device, check)
    module = sys.modules.get(check.run.__module__)
    name = next((n for n, v in vars(module).items() if v is check), None) if module else None
    if name is None:     # not a module-level check: the child could not find it
        return run_check(device, check)
    out = run_child({"task": "selfcheck", "platform": pi, "device": di,
                     "name": device.cl_device.name, "module": module.__name__, "check": name,
                     "tuning": dataclasses.asdict(device.tuning)}, CHECK_TIMEOUT_S)
    if out.crash:
        return CheckResult(False, f"the driver crashed during the check ({out.crash})",
                           path_name(device.tuning))
    r = out.result
    if r is None:    # the child gave no answer: clrf's problem (it could not import, say)
        missing = None
        for line in out.failure.splitlines():
            if "No module named" in line and "'" in line:
                missing = line.split("'")[1]
        last = (out.failure.strip().splitlines() or ["no output"])[-1]
        raise own_error_text(last, out.failure.rstrip(), what + " (in a child process)",
                              missing)
    if "own_error" in r:
        raise (InstallError if r["own_error"] == "install" else ClrfBug)(r["detail"])
    if r.get("name") != device.cl_device.name:     # the child's listing differs from ours
        return run_check(device, check)
    return CheckResult(bool(r["ok"]), str(r["detail"]), str(r["path"]))


def gradient_check(device, check: GradientCheck, refresh: bool = False,
                   run=None) -> CheckResult:
    """The cached verdict of ``check`` on ``device``'s gradient path, measured when missing
    (with ``run(device)``, default: in a child process, ``run_isolated``) and then cached.
    InstallError / ClrfBug pass through uncached."""
    key = check_key(device, check)
    if not refresh:
        e = _load().get(key)
        if isinstance(e, dict) and isinstance(e.get("ok"), bool):
            return CheckResult(e["ok"], str(e.get("detail", "")), str(e.get("path", "")))
    if run is not None:
        res = run(device)
    else:
        res = run_isolated(device, check) if ISOLATE else run_check(device, check)
    _store(key, res)
    return res


def cached_verdict(cl_device, tuning, check: GradientCheck) -> CheckResult | None:
    """The cached verdict of ``check`` on ``cl_device`` with ``tuning``, or None (nothing is
    run)."""
    key = "|".join([device_key(cl_device), path_name(tuning), f"rec{int(tuning.sample_record)}",
                    _tail(check)])
    e = _load().get(key)
    if isinstance(e, dict) and isinstance(e.get("ok"), bool):
        return CheckResult(e["ok"], str(e.get("detail", "")), str(e.get("path", "")))
    return None


def checks() -> list:
    """The registered checks."""
    return list(_CHECKS)


def verdicts_for(cl_device, check: GradientCheck) -> list:
    """Every cached verdict of ``check`` on ``cl_device`` with the current kernels and clrf,
    one per gradient path (nothing is run)."""
    head, tail = device_key(cl_device) + "|", "|" + _tail(check)
    return [CheckResult(e["ok"], str(e.get("detail", "")), str(e.get("path", "")))
            for k, e in _load().items()
            if k.startswith(head) and k.endswith(tail) and isinstance(e, dict)
            and isinstance(e.get("ok"), bool)]


def known_wrong(cl_device, checks=None) -> str | None:
    """Why ``cl_device`` is known (from the cache only; nothing is run) to compute wrong
    gradients (or to crash) on its float-atomic path with the current kernels and clrf under
    one of ``checks`` (default: the registered ones), or None."""
    head = device_key(cl_device) + "|atomics|"
    entries = _load()
    for check in (_CHECKS if checks is None else checks):
        tail = "|" + _tail(check)
        for k, e in entries.items():
            if (k.startswith(head) and k.endswith(tail) and isinstance(e, dict)
                    and e.get("ok") is False):
                return str(e.get("detail", "wrong gradients"))
    return None
