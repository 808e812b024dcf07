"""The child process of clrf/runtime/isolate.py: ``python -m clrf.runtime.child`` reads one
JSON request on standard input, does the work its ``task`` names (``probe``: the device probe,
clrf/runtime/device_probe.py; ``selfcheck``: a gradient self-check, clrf/runtime/selfcheck.py)
and prints the JSON answer on one line after ``isolate.RESULT_MARK``."""
from __future__ import annotations

import faulthandler
import importlib
import json
import sys

import pyopencl as cl

from . import selfcheck
from .device import Device, DeviceError
from .isolate import RESULT_MARK
from .tuning import Tuning


def main() -> None:
    faulthandler.enable()   # a crash in the driver leaves the Python stack on stderr
    request = json.loads(sys.stdin.read() or "{}")
    task = request.get("task")
    if task == "probe":
        from .device_probe import child_probe as work
    elif task == "selfcheck":
        work = child_check
    else:
        raise SystemExit(f"clrf.runtime.child: unknown task {task!r}")
    answer = work(request)
    sys.stdout.write(RESULT_MARK + json.dumps(answer) + "\n")
    sys.stdout.flush()


def child_check(request: dict) -> dict:
    """The self-check child's work: the check
    ``request['module'].request['check']`` on device P:D with the parent's tuning."""
    try:
        check = getattr(importlib.import_module(request["module"]), request["check"])
        tuning = Tuning(**request["tuning"])
    except Exception as e:  # noqa: BLE001 - clrf's own failure, reported to the parent
        name = f"{request.get('module')}.{request.get('check')}"
        err = selfcheck.own_error(e, f"the self-check {name}")
        return {"own_error": "install" if isinstance(err, selfcheck.InstallError) else "bug",
                "detail": str(err)}
    path = selfcheck.path_name(tuning)
    try:
        device = Device(f"{request['platform']}:{request['device']}", tuning=tuning)
    except (DeviceError, cl.Error) as e:
        return {"name": request["name"], "ok": False, "path": path,
                "detail": f"cannot open the device: {str(e).splitlines()[0]}"}
    if device.cl_device.name != request["name"]:
        return {"name": device.cl_device.name}
    try:
        res = selfcheck.run_check(device, check)
    except selfcheck.SelfCheckError as e:
        return {"own_error": "install" if isinstance(e, selfcheck.InstallError) else "bug",
                "detail": str(e)}
    return {"name": device.cl_device.name, "ok": res.ok, "detail": res.detail,
            "path": res.path}


if __name__ == "__main__":
    main()
