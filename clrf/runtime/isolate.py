"""Run a step that touches a driver for the first time in a child process, so that a driver
that crashes (a segfault in its compiler or in a kernel) cannot take clrf down with it.

The device probe (device_probe.py) and the gradient self-checks (selfcheck.py) run this way:
the parent starts ``python -m clrf.runtime.child`` with a JSON request on standard input (its
``task`` names the work), the child does the work and prints one JSON line, prefixed with ``RESULT_MARK``, on standard output. What the
parent gets back (``Outcome``) says which of three things happened:

- the child answered: ``result`` is its JSON object;
- the child died from a signal or ran past the time limit: ``crash`` says so in words
  ("killed by signal 11 (SIGSEGV)"): a verdict on the driver;
- the child exited without an answer (it could not import clrf, say): ``failure`` holds the
  end of its standard error: a clrf problem, never a verdict on the driver.

The child imports the same clrf as the parent: it starts in the folder that holds the parent's
clrf package, which ``python -m`` puts first on the module path.
"""
from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
from dataclasses import dataclass
from pathlib import Path

RESULT_MARK = "clrf-child-result: "
STDERR_TAIL = 4000      # characters of a failed child's standard error kept for the report


@dataclass(frozen=True)
class Outcome:
    result: dict | None = None   # the child's answer
    crash: str = ""              # how it died: a driver verdict
    failure: str = ""            # why it gave no answer: a clrf problem (its stderr's end)


def signal_text(returncode: int) -> str:
    """'killed by signal 11 (SIGSEGV)' for a negative return code (a shell's 128 + N too)."""
    num = -returncode if returncode < 0 else returncode - 128
    try:
        name = signal.Signals(num).name
    except ValueError:
        name = "unknown signal"
    return f"killed by signal {num} ({name})"


def package_root() -> Path:
    """The folder that holds the clrf package this process runs (site-packages, a checkout)."""
    return Path(__file__).resolve().parent.parent.parent


CHILD_MODULE = "clrf.runtime.child"


def run_child(request: dict, timeout: float) -> Outcome:
    """Run ``python -m clrf.runtime.child`` with ``request`` on its standard input (module
    doc)."""
    try:
        p = subprocess.run([sys.executable, "-m", CHILD_MODULE], input=json.dumps(request),
                           capture_output=True, text=True, timeout=timeout,
                           cwd=str(package_root()), env=dict(os.environ))
    except subprocess.TimeoutExpired:
        return Outcome(crash=f"did not finish within {timeout:.0f} s (hung)")
    for line in reversed(p.stdout.splitlines()):
        if line.startswith(RESULT_MARK):
            try:
                res = json.loads(line[len(RESULT_MARK):])
            except ValueError:
                break
            if isinstance(res, dict):
                return Outcome(result=res)
            break
    # Python exits 1 on an uncaught exception; a signal is < 0 (or 128 + N through a shell)
    if p.returncode < 0 or p.returncode > 128:
        return Outcome(crash=signal_text(p.returncode))
    return Outcome(failure=(p.stderr or p.stdout or f"exit status {p.returncode}")[-STDERR_TAIL:])
