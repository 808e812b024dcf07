"""Self-checks that misbehave on purpose, for the tests of clrf/runtime/selfcheck.py: a
driver that crashes, one that computes wrongly, and clrf's own failures (a bug, a module
missing from the install). They are module-level GradientChecks, so the self-check child
process finds them as it finds the grid's; none is registered for the device choice."""
from __future__ import annotations

import ctypes
import importlib

from ..runtime.selfcheck import GradientCheck

SOURCES = ("common.h",)


def _crash(device) -> str:
    """Dereferences a null pointer, as a driver that segfaults would."""
    ctypes.string_at(0)
    return ""


def _wrong(device) -> str:
    return "every gradient is zero (a fault made on purpose)"


def _bug(device) -> str:
    raise TypeError("a fault made on purpose in clrf's own code")


def _missing(device) -> str:
    importlib.import_module("clrf.no_such_module_on_purpose")
    return ""


CRASH = GradientCheck(SOURCES, 1, _crash, "a crashing check")
WRONG = GradientCheck(SOURCES, 1, _wrong, "a wrong check")
BUG = GradientCheck(SOURCES, 1, _bug, "a buggy check")
MISSING = GradientCheck(SOURCES, 1, _missing, "a check that imports a missing module")
