"""The representations clrf knows, in ``--model`` order (the first is the default).

Each entry is a package under clrf/ whose ``kind`` module defines ``KIND``, a
clrf.interface.Kind. This is the one module outside those packages that names them: training,
outputs, the viewer and the command line ask it (``kinds()``, ``get(name)``). A new
representation adds its package and its name here.
"""
from __future__ import annotations

import importlib

PACKAGES = ("grid", "nerf", "hash", "splat")   # clrf.<name>.kind.KIND, each
DEFAULT = PACKAGES[0]

_KINDS: dict = {}


def kinds() -> list:
    """Every registered Kind, in PACKAGES order (each package imported on first use)."""
    if not _KINDS:
        for name in PACKAGES:
            kind = importlib.import_module(f"clrf.{name}.kind").KIND
            if kind.name != name:
                raise RuntimeError(f"clrf.{name}.kind.KIND is named {kind.name!r}")
            _KINDS[name] = kind
    return list(_KINDS.values())


def names() -> list:
    return [k.name for k in kinds()]


def get(name: str):
    """The Kind called ``name``; KeyError naming the known ones otherwise."""
    for k in kinds():
        if k.name == name:
            return k
    raise KeyError(f"unknown model kind {name!r}; known: {', '.join(names())}")


def exports() -> dict:
    """{flag name: (Export, [kind names that offer it])} over every kind's own exports."""
    out = {}
    for k in kinds():
        for name, exp in k.exports.items():
            out.setdefault(name, (exp, []))[1].append(k.name)
    return out


def help_text() -> str:
    """'grid (Plenoxels ...), nerf (...) or hash (...)' for --model's help."""
    parts = [f"{k.name} ({k.title})" for k in kinds()]
    return ", ".join(parts[:-1]) + (" or " if len(parts) > 1 else "") + parts[-1]
