"""Build the OpenCL C sources in ``cl/`` with ``-D`` specialisation, once per process.

Programs are cached per (device, source file, defines) in the Device object; across processes
pyopencl's binary cache (keyed on source, included headers, options and driver) and PoCL's own
kernel cache make a rebuild cost tens of milliseconds. A failed build raises ``BuildError``
carrying the compiler log.
"""
from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import pyopencl as cl


class BuildError(RuntimeError):
    pass


def cl_dir() -> Path:
    """Where the kernel sources live: ``clrf/cl`` in an installed wheel, ``cl/`` in a checkout."""
    here = Path(__file__).resolve().parent
    for cand in (here / "cl", here.parent / "cl"):
        if (cand / "common.h").is_file():
            return cand
    raise BuildError(f"OpenCL sources not found next to {here} (looked for cl/common.h)")


def build_options(device) -> dict:
    """Defines that follow from the device's capabilities (never from the scene)."""
    caps = device.caps
    return {
        "CLRF_NATIVE_FLOAT_ATOMICS": int(caps.float_atomics),
        "CLRF_HAS_FP64": int(caps.fp64),
    }


def _fmt(v) -> str:
    if isinstance(v, bool):
        return str(int(v))
    if isinstance(v, float):
        return repr(float(np.float32(v))) + "f"
    return str(v)


def build(device, source: str, defines: dict):
    """The program for ``cl/<source>`` built for ``device`` with ``defines`` (cached)."""
    allopts = dict(build_options(device))
    allopts.update(defines)
    key = (source, tuple(sorted(allopts.items())))
    prg = device._programs.get(key)
    if prg is not None:
        return prg
    path = cl_dir() / source
    try:
        src = path.read_text()
    except OSError as e:
        raise BuildError(f"cannot read kernel source {path}: {e}") from e
    opts = [f"-I{cl_dir()}"] + [f"-D{k}={_fmt(v)}" for k, v in sorted(allopts.items())]
    if os.environ.get("CLRF_FAST_MATH"):
        opts.append("-cl-fast-relaxed-math")
    try:
        prg = cl.Program(device.context, src).build(options=opts)
    except cl.RuntimeError as e:
        raise BuildError(f"building {path} with {' '.join(opts)} failed:\n{e}") from e
    device._programs[key] = Program(prg)
    return device._programs[key]


class Program:
    """A built program whose kernels are looked up once."""

    def __init__(self, prg):
        self.cl_program = prg
        self._kernels = {}

    def kernel(self, name: str):
        k = self._kernels.get(name)
        if k is None:
            k = self._kernels[name] = getattr(self.cl_program, name)
        return k


def launch(device, kernel, n: int, args, local_size: int | None = None, wait_for=None):
    """Run a 1-D kernel over ``n`` items (kernels bounds-check ``gid < n``).

    Returns the event, or None when ``n == 0``. The global size is rounded up to a multiple of
    the local size, which is clamped to what the device reports.
    """
    if n <= 0:
        return None
    if local_size is None:
        local_size = 64 if device.is_cpu else 128
    local_size = max(1, min(int(local_size), device.caps.max_work_group_size))
    gsize = ((n + local_size - 1) // local_size) * local_size
    kernel.set_args(*args)
    return cl.enqueue_nd_range_kernel(device.queue, kernel, (gsize,), (local_size,),
                                      wait_for=wait_for)
