"""Build the OpenCL C sources in ``cl/`` with ``-D`` specialisation.

``Device.program`` caches the built programs per (source file, defines, options); across
processes pyopencl's binary cache (keyed on source, included headers, options and driver) and
PoCL's own kernel cache make a rebuild cost tens of milliseconds. A failed build raises
``BuildError`` carrying the compiler log. A successful build prints the compiler's diagnostics
(warnings, with their notes and source excerpts) to stderr, and nothing else: the progress lines
some implementations write into every log ("Compilation started" ...) are dropped by
clrf/runtime/buildlog.py. With the device tuning's ``verbose_build`` (``CLRF_VERBOSE_BUILD=1``) the raw
log is shown instead, whenever it is non-empty. The kernels build without diagnostics on every
implementation tested (tests/test_build_log.py).
"""
from __future__ import annotations

import os
import sys
import threading
import time
import warnings
from contextlib import contextmanager, nullcontext
from pathlib import Path

import numpy as np
import pyopencl as cl
import pyopencl.array as cla
import pyopencl.cltypes as cltypes

from .buildlog import diagnostics
from .devmem import counted
from .tuning import implementation


class BuildError(RuntimeError):
    pass


# ---- one-off costs: program builds and first launches ----------------------------------------
# Seconds this process has spent on one-off work that a caller timing its own work leaves out
# (Trainer's steps and evaluations: a cold first run would otherwise spend seconds of a short
# budget on it and shift its PSNR-against-time curve): every pyopencl program build, clrf's
# and those pyopencl makes for its own kernels (the reductions behind cla.sum, the scans of
# grid pruning: seconds each on PoCL), and the first launch of each kernel at each work-group
# size, where PoCL compiles the kernel for that size (with that launch's own work), and the first
# run of each of pyopencl's own kernels that clrf calls (``first_run``).
_one_off = {"seconds": 0.0}
_one_off_lock = threading.Lock()
_one_off_depth = threading.local()   # per thread: blocks nest (a build inside a build)


def one_off_seconds() -> float:
    """Wall seconds of one-off work so far in this process (see above)."""
    return _one_off["seconds"]


@contextmanager
def one_off(queue=None):
    """Counts the block's wall time as one-off work (``queue``: finished before and after, so
    that the device's work of the block is in it and earlier work is not); blocks nest."""
    if queue is not None:
        queue.finish()
    t0 = time.perf_counter()
    depth = getattr(_one_off_depth, "n", 0)
    _one_off_depth.n = depth + 1
    try:
        yield
        if queue is not None:
            queue.finish()
    finally:
        _one_off_depth.n = depth
        if depth == 0:
            with _one_off_lock:
                _one_off["seconds"] += time.perf_counter() - t0


def _install_build_timer():
    """Every pyopencl Program.build in this process counts as one-off work (installed once)."""
    build = cl.Program.build
    if getattr(build, "_clrf_timed", False):
        return

    def timed_build(self, *args, **kwargs):
        with one_off():
            return build(self, *args, **kwargs)
    timed_build._clrf_timed = True
    cl.Program.build = timed_build


_install_build_timer()


def cl_dir() -> Path:
    """Where the kernel sources live: ``clrf/cl`` in an installed wheel, ``cl/`` in a checkout."""
    here = Path(__file__).resolve().parent.parent      # the clrf package (this is clrf/runtime)
    for cand in (here / "cl", here.parent / "cl"):
        if (cand / "common.h").is_file():
            return cand
    raise BuildError(f"OpenCL sources not found next to {here} (looked for cl/common.h)")


def build_options(device) -> dict:
    """Defines that follow from the device's capabilities (never from the scene):
    CLRF_BUILTIN_PREFETCH where the compiler takes clang's ``__builtin_prefetch`` on global
    pointers (PoCL's CPU targets; NVIDIA's compiler rejects the address-space change, SPIR
    targets get OpenCL C's ``prefetch()``), CLRF_PTX_ATOMICS where float atomic adds go
    through inline PTX (NVIDIA, ``ptx_atomics``)."""
    return capability_defines(device.caps, ptx_atomics(device))


def capability_defines(caps, ptx: bool = False) -> dict:
    """build_options from a device's Capabilities alone, ``ptx`` standing for the PTX probe's
    answer (tools/gpu_builds.py builds for GPUs that are not here with it)."""
    return {
        "CLRF_NATIVE_FLOAT_ATOMICS": int(caps.float_atomics),
        "CLRF_HAS_FP64": int(caps.fp64),
        "CLRF_BUILTIN_PREFETCH": int(implementation(caps.platform) == "pocl"),
        "CLRF_PTX_ATOMICS": int(ptx),
    }


# NVIDIA's OpenCL reports no float atomics (cl_ext_float_atomics), so atomic_add_f falls back to
# a compare-and-swap loop; its compiler takes inline PTX (cl/ptx_probe.cl). Whether it builds and
# adds right is measured once per device (a wrong or failed probe keeps the loop).
_ptx_checked: dict = {}


def ptx_atomics(device) -> bool:
    """Whether float atomic adds use inline PTX on ``device``: NVIDIA devices without native
    float atomics, where a probe kernel built and added 0.5 from 2^16 work-items into 8 floats
    exactly. ``CLRF_PTX_ATOMICS=0`` keeps the compare-and-swap loop (for A/B runs)."""
    caps = device.caps
    if (caps.float_atomics or implementation(caps.platform) != "nvidia"
            or os.environ.get("CLRF_PTX_ATOMICS", "").strip() == "0"):
        return False
    key = device.cl_device.int_ptr
    if key not in _ptx_checked:
        ok = False
        try:
            n = 1 << 16
            prg = cl.Program(device.context, (cl_dir() / "ptx_probe.cl").read_text()).build()
            out = cla.zeros(device.queue, 8, np.float32)
            prg.ptx_probe(device.queue, (n,), None, out.data, np.int32(n))
            ok = bool(np.all(out.get() == n / 16))
        except (cl.Error, cl.RuntimeError):
            ok = False
        if not ok:
            print("clrf: inline PTX float atomics did not build or add right here; "
                  "float atomic adds use compare-and-swap", file=sys.stderr)
        _ptx_checked[key] = ok
    return _ptx_checked[key]


def _fmt(v) -> str:
    if isinstance(v, bool):
        return str(int(v))
    if isinstance(v, float):
        return repr(float(np.float32(v))) + "f"
    return str(v)


def build_flags(device, defines: dict, fast_math: bool = False) -> list:
    """The build options ``build`` passes for ``defines`` on ``device``: ``-I cl/``, then
    ``-DNAME=value`` for the capability defines of build_options updated by ``defines``
    (sorted by name; floats as float literals), ``-cl-std=CL3.0`` where the gradient slots'
    locks use acquire/release atomics (CLRF_ACQ_REL), then ``-cl-fast-relaxed-math`` if
    asked."""
    return caps_build_flags(device.caps, build_options(device), defines, fast_math)


def caps_build_flags(caps, capability: dict, defines: dict, fast_math: bool = False) -> list:
    """build_flags for a device's Capabilities and its capability defines (build_options or
    capability_defines)."""
    allopts = dict(capability)
    allopts.update(defines)
    if int(allopts.get("GRAD_SLOTS", 0)) > 0 and caps.acq_rel:
        allopts["CLRF_ACQ_REL"] = 1      # the slot and block locks order plain memory
    opts = [f"-I{cl_dir()}"] + [f"-D{k}={_fmt(v)}" for k, v in sorted(allopts.items())]
    if allopts.get("CLRF_ACQ_REL"):
        opts.append("-cl-std=CL3.0")     # C11-style atomics with memory order and scope
    if caps.type != "cpu" and getattr(caps, "cr_divide_sqrt", False):
        # GPUs divide to 2.5 ulp by default; correctly rounded, a voxel centre (x + 0.5) * r / r
        # lands exactly on x + 0.5 as on CPUs and in the float64 references (grid resampling
        # decides allocation by "weight > 0" there)
        opts.append("-cl-fp32-correctly-rounded-divide-sqrt")
    if fast_math:
        opts.append("-cl-fast-relaxed-math")
    return opts


def build(device, source: str, defines: dict, fast_math: bool = False, verbose: bool = False,
          binary_cache: bool = True):
    """The program for ``cl/<source>`` built for ``device`` with ``defines`` (the capability
    defines of build_options added), not cached: callers use ``Device.program``. The compiler's
    diagnostics go to stderr; verbose: the whole log instead, when non-empty.
    ``binary_cache=False`` compiles the source even where pyopencl's binary cache holds the
    program (whose log is then the loader's, not the compiler's)."""
    path = cl_dir() / source
    try:
        src = path.read_text()
    except OSError as e:
        raise BuildError(f"cannot read kernel source {path}: {e}") from e
    opts = build_flags(device, defines, fast_math)
    try:
        with warnings.catch_warnings():
            # pyopencl warns on any non-empty log, chatter included; what matters is shown
            # below.
            warnings.simplefilter("ignore", cl.CompilerWarning)
            prg = cl.Program(device.context, src).build(
                options=opts, cache_dir=None if binary_cache else False)
    except cl.RuntimeError as e:
        raise BuildError(f"building {path} with {' '.join(opts)} failed:\n{e}") from e
    log = build_log(prg, device)
    shown = log if verbose else "\n".join(d.text for d in diagnostics(log))
    if shown:
        what = "build log" if verbose else "compiler diagnostics"
        print(f"clrf: {what} of {source} ({' '.join(opts[1:])}):\n{shown}", file=sys.stderr)
    return Program(prg)


def build_log(prg, device) -> str:
    """The compiler's log of a built pyopencl program on ``device``, stripped."""
    return prg.get_build_info(device.cl_device, cl.program_build_info.LOG).strip()


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


def upload(queue, ary):
    """``cla.to_device`` without keeping the host array alive. pyopencl's to_device leaves an
    event that holds ``ary`` in the new array's event list until that array's own finish(),
    which kernels launched on its ``.data`` never call: every uploaded grid, ray store and
    optimiser state kept a second copy in host memory for its whole life. The array is counted
    in its device's memory ledger (clrf/runtime/devmem.py) while it lives."""
    arr = cla.to_device(queue, ary, allocator=counted(queue))
    arr.finish()
    return arr


def download(arr) -> np.ndarray:
    """``arr.get()`` without leaving the host copy alive. pyopencl's get() adds its read event
    to ``arr.events``, and that event holds the new numpy array until the list is pruned (some
    events later) or ``arr.finish()``: a long-lived array downloaded for every checkpoint (a
    hash table, a grid, their Adam moments) kept several host copies of itself, and resident
    memory grew with each save (hash on bonsai: 0.2 GB a checkpoint)."""
    out = arr.get()
    arr.finish()
    return out


def float4(x, y, z, w) -> np.ndarray:
    """A ``float4`` kernel argument. pyopencl's ``cltypes.make_float4`` builds it with
    ``eval`` of a string, and CPython remembers a Ctrl-C that lands inside such an eval: a run
    under ``python -m`` that then saved its checkpoint and exited 130 died of SIGINT instead
    (one Adam step of the grid makes two of these calls)."""
    return np.array((x, y, z, w), dtype=cltypes.float4)


def int4(x, y, z, w) -> np.ndarray:
    """An ``int4`` kernel argument, without ``cltypes.make_int4``'s ``eval`` (``float4``)."""
    return np.array((x, y, z, w), dtype=cltypes.int4)


def device_empty(queue, shape, dtype=np.float32):
    """``cla.empty`` counted in the device's memory ledger (clrf/runtime/devmem.py) while it
    lives: an array that clrf makes outside the pool (``scratch``) and ``upload``."""
    return cla.empty(queue, shape, dtype, allocator=counted(queue))


def device_zeros(queue, shape, dtype=np.float32):
    """``cla.zeros`` counted as ``device_empty`` is."""
    return cla.zeros(queue, shape, dtype, allocator=counted(queue))


def scratch(device, shape, dtype=np.float32):
    """An uninitialised per-step device array from the device's memory pool (Device.pool): its
    buffer goes back to the pool when the array is dropped, so arrays whose sizes change every
    step reuse buffers instead of fragmenting a CPU runtime's heap."""
    return cla.empty(device.queue, shape, dtype, allocator=device.pool)


def count_arg(count):
    """A kernel's ``count`` argument (cl/common.h live_rows): the buffer of an int32 [1] device
    array holding a bounded buffer's live rows, or null (None: every row)."""
    return None if count is None else count.data


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
    if not _first_launch(device, kernel, local_size):
        return cl.enqueue_nd_range_kernel(device.queue, kernel, (gsize,), (local_size,),
                                          wait_for=wait_for)
    with one_off(device.queue):
        return cl.enqueue_nd_range_kernel(device.queue, kernel, (gsize,), (local_size,),
                                          wait_for=wait_for)


def first_run(device, key):
    """A context in which a pyopencl library kernel runs (an ElementwiseKernel, a
    ReductionKernel, ``cla.sum``), counted as one-off work the first time ``key`` runs on
    ``device`` (PoCL compiles it at its first launch, as it does clrf's kernels in ``launch``),
    and a no-op after that.

    >>> with first_run(dev, ("cla.sum", np.float32)):
    ...     total = cla.sum(a, queue=dev.queue)
    """
    seen = getattr(device, "first_launches", None)
    if seen is None or key in seen:
        return nullcontext()
    seen.add(key)
    return one_off(device.queue)


def _first_launch(device, kernel, local_size) -> bool:
    """Whether this is the first time ``kernel`` runs at ``local_size`` on ``device`` (PoCL
    compiles a kernel for its work-group size at that launch: one-off work)."""
    seen = getattr(device, "first_launches", None)
    key = (kernel.int_ptr, local_size)
    if seen is None or key in seen:   # (a stand-in device without the set: no accounting)
        return False
    seen.add(key)
    return True
