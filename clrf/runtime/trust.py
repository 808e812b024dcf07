"""Before training: the device must pass the registered gradient self-checks
(clrf/runtime/selfcheck.py holds the checks and their cached verdicts; the device choice in
device.py reads them)."""
from __future__ import annotations

from .device import DeviceError
from .selfcheck import gradient_check


def ensure_trusted(device, checks, log=None):
    """Before training: the device's gradient path passes every check of ``checks`` (cached
    verdicts), else the float-atomic path replaces it (``device.tuning`` is changed, with a
    warning through ``log``) when that one passes them; else DeviceError naming the device and
    its driver. Returns each check's passing CheckResult. InstallError / ClrfBug (clrf's own
    failure while checking, clrf/runtime/selfcheck.py) pass through: they say nothing about
    the device."""
    passed = []
    for check in checks:
        res = gradient_check(device, check)
        if res.ok:
            passed.append(res)
            continue
        first = res
        if device.tuning.grad_slots > 0:
            device.tuning = device.tuning.replace(grad_slots=0, sample_record=False,
                                                  grad_locks=0)
            device._programs.clear()
            res = gradient_check(device, check)
            if res.ok:
                if log is not None:
                    log(f"clrf: warning: the {first.path} gradient path computes wrong "
                        f"gradients on {device!r} ({first.detail}); using the float-atomic path")
                passed.append(res)
                continue
        raise DeviceError(
            f"device {device!r}, driver {device.caps.driver_version}: fails the gradient "
            f"self-check of {check.what} ({first.path}: {first.detail}); clrf will not train on it. Choose "
            f"another device with --device / CLRF_DEVICE (`clrf devices` lists them) or update "
            f"the OpenCL driver")
    return passed
