"""The child process of clrf/runtime/isolate.py: ``python -m clrf.runtime.child`` reads one
JSON request on standard input, does the work its ``task`` names (``probe``: the device probe,
clrf/runtime/device_probe.py; ``selfcheck``: a gradient self-check, clrf/runtime/selfcheck.py)
and prints the JSON answer on one line after ``isolate.RESULT_MARK``."""
from __future__ import annotations

import faulthandler
import json
import sys

from .isolate import RESULT_MARK


def main() -> None:
    faulthandler.enable()   # a crash in the driver leaves the Python stack on stderr
    request = json.loads(sys.stdin.read() or "{}")
    task = request.get("task")
    if task == "probe":
        from .device_probe import child_probe as work
    elif task == "selfcheck":
        from .selfcheck import child_check as work
    else:
        raise SystemExit(f"clrf.runtime.child: unknown task {task!r}")
    answer = work(request)
    sys.stdout.write(RESULT_MARK + json.dumps(answer) + "\n")
    sys.stdout.flush()


if __name__ == "__main__":
    main()
