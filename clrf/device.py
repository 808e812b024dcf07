"""OpenCL device selection, capability probes and the command queue.

Selection is explicit and deterministic. ``Device(spec)`` or the ``CLRF_DEVICE`` variable take:

- ``"cpu"`` / ``"gpu"``: the first device of that type (platforms in ICD order) that can build
  and run a probe kernel;
- ``"P:D"``: platform index P, device index D, as listed by ``clrf devices``;
- nothing: the first working GPU, else the first working CPU.

A machine can carry two PoCL platforms at once (pip's and Debian's); a driver that is listed
but cannot compile for this CPU is skipped with the reason, never chosen silently.
"""
from __future__ import annotations

import os
import sys
from dataclasses import dataclass, field

import numpy as np
import pyopencl as cl



class DeviceError(RuntimeError):
    """No OpenCL device matches the request, or the requested one does not work."""


@dataclass(frozen=True)
class Capabilities:
    """What the kernels need to know about a device, probed once."""

    name: str
    platform: str
    platform_version: str
    driver_version: str
    type: str                  # "cpu", "gpu" or "accelerator"
    compute_units: int
    max_work_group_size: int
    local_mem_size: int
    global_mem_size: int
    max_alloc_size: int
    fp64: bool                 # cl_khr_fp64: float64 accumulation available
    float_atomics: bool        # cl_ext_float_atomics: native float atomic add
    int64_atomics: bool
    native_float_width: int = 1  # native float vector width: 4 SSE/NEON, 8 AVX2, 16 AVX-512
    extensions: tuple = field(default=(), repr=False)

    @property
    def vector_width(self) -> int:
        """Float vector width for explicitly vectorised kernels (the peak kernels): the native
        width rounded to 4, 8 or 16 (GPUs report 1; float4 keeps their FMA pipes busy too)."""
        return 16 if self.native_float_width >= 16 else 8 if self.native_float_width >= 8 else 4


def _type_name(t: int) -> str:
    if t & cl.device_type.GPU:
        return "gpu"
    if t & cl.device_type.ACCELERATOR:
        return "accelerator"
    return "cpu"


def probe_capabilities(dev: "cl.Device") -> Capabilities:
    ext = tuple(sorted(dev.extensions.split()))
    return Capabilities(
        name=dev.name.strip(),
        platform=dev.platform.name.strip(),
        platform_version=dev.platform.version.strip(),
        driver_version=dev.driver_version.strip(),
        type=_type_name(dev.type),
        compute_units=int(dev.max_compute_units),
        max_work_group_size=int(dev.max_work_group_size),
        local_mem_size=int(dev.local_mem_size),
        global_mem_size=int(dev.global_mem_size),
        max_alloc_size=int(dev.max_mem_alloc_size),
        fp64="cl_khr_fp64" in ext,
        float_atomics="cl_ext_float_atomics" in ext,
        int64_atomics="cl_khr_int64_base_atomics" in ext,
        native_float_width=max(1, int(dev.native_vector_width_float)),
        extensions=ext,
    )


def list_devices():
    """All OpenCL devices as ``[(platform_index, device_index, cl.Device)]`` in ICD order."""
    out = []
    try:
        platforms = cl.get_platforms()
    except cl.Error:
        platforms = []
    for pi, p in enumerate(platforms):
        try:
            devs = p.get_devices()
        except cl.Error:
            continue
        for di, d in enumerate(devs):
            out.append((pi, di, d))
    return out


def _probe_works(dev: "cl.Device") -> str | None:
    """Build and run a one-line kernel; None if it works, else the reason."""
    try:
        ctx = cl.Context([dev])
        q = cl.CommandQueue(ctx)
        from .programs import cl_dir
        prg = cl.Program(ctx, (cl_dir() / "probe.cl").read_text()).build()
        a = np.zeros(4, np.float32)
        buf = cl.Buffer(ctx, cl.mem_flags.READ_WRITE | cl.mem_flags.COPY_HOST_PTR, hostbuf=a)
        prg.clrf_probe(q, (4,), None, buf)
        cl.enqueue_copy(q, a, buf)
        q.finish()
        if not np.all(a == 1.0):
            return "probe kernel gave wrong results"
    except Exception as e:  # noqa: BLE001 - any driver failure disqualifies the device
        lines = [m.strip() for m in str(e).splitlines() if m.strip()]
        errors = [m for m in lines if m.lower().startswith("error")]
        return (errors[0] if errors else " ".join(lines)[-200:]) or type(e).__name__
    return None


_probe_cache: dict = {}


def _works(pi, di, dev):
    key = (pi, di)
    if key not in _probe_cache:
        _probe_cache[key] = _probe_works(dev)
    return _probe_cache[key]


def _describe(pi, di, dev) -> str:
    return f"{pi}:{di} {_type_name(dev.type)} '{dev.name.strip()}' on '{dev.platform.version.strip()}'"


def select_device(spec: str | None = None):
    """Resolve a device spec to ``(platform_index, device_index, cl.Device)``; see module doc."""
    spec = (spec if spec is not None else os.environ.get("CLRF_DEVICE", "")).strip().lower()
    devs = list_devices()
    if not devs:
        raise DeviceError(
            "no OpenCL platform found. Install a driver: `pip install \"clrf[pocl]\"` or, on "
            "Debian/Ubuntu, `apt-get install pocl-opencl-icd`.")
    listing = "\n".join("  " + _describe(*d) for d in devs)
    if spec and ":" in spec:
        try:
            pi, di = (int(x) for x in spec.split(":"))
        except ValueError:
            raise DeviceError(f"CLRF_DEVICE/device '{spec}' is not 'cpu', 'gpu' or 'P:D'. "
                              f"Devices:\n{listing}") from None
        for d in devs:
            if d[0] == pi and d[1] == di:
                why = _works(*d)
                if why:
                    raise DeviceError(f"device {pi}:{di} cannot build kernels ({why}). "
                                      f"Choose another:\n{listing}")
                return d
        raise DeviceError(f"no device {pi}:{di}. Devices:\n{listing}")
    if spec in ("", "auto"):
        wanted = ["gpu", "accelerator", "cpu"]
    elif spec in ("cpu", "gpu", "accelerator"):
        wanted = [spec]
    else:
        raise DeviceError(f"device '{spec}' is not 'cpu', 'gpu' or 'P:D'. Devices:\n{listing}")
    rejected = []
    for t in wanted:
        for d in devs:
            if _type_name(d[2].type) != t:
                continue
            why = _works(*d)
            if why is None:
                return d
            rejected.append(f"  {_describe(*d)}: {why}")
    msg = f"no working {'/'.join(wanted)} OpenCL device. Devices:\n{listing}"
    if rejected:
        msg += "\nRejected:\n" + "\n".join(rejected)
    if "cpu" in wanted:
        msg += ("\nOn Debian/Ubuntu `apt-get install pocl-opencl-icd` gives a CPU driver that "
                "works on current CPUs.")
    raise DeviceError(msg)


class Device:
    """An OpenCL device with its context, in-order queue and probed capabilities.

    >>> dev = clrf.Device("cpu")        # or Device() to honour CLRF_DEVICE
    >>> dev.caps.fp64
    True
    """

    def __init__(self, spec: str | None = None, verbose: bool = False):
        self.platform_index, self.device_index, self.cl_device = select_device(spec)
        self.context = cl.Context([self.cl_device])
        self.queue = cl.CommandQueue(self.context)
        self.caps = probe_capabilities(self.cl_device)
        self._programs = {}
        if verbose:
            print(f"clrf: device {self}", file=sys.stderr)

    def __repr__(self):
        return (f"{self.platform_index}:{self.device_index} {self.caps.type} "
                f"'{self.caps.name}' ({self.caps.platform_version})")

    @property
    def is_cpu(self) -> bool:
        return self.caps.type == "cpu"

    def program(self, source: str, defines: dict | None = None):
        """The built program for ``cl/<source>`` with ``defines``; see programs.build."""
        from .programs import build
        return build(self, source, defines or {})

    def finish(self):
        self.queue.finish()


def format_devices() -> str:
    """Text for ``clrf devices``: every device, whether it works, and its capabilities."""
    lines = []
    for pi, di, d in list_devices():
        why = _works(pi, di, d)
        c = probe_capabilities(d)
        state = "ok" if why is None else f"UNUSABLE: {why}"
        lines.append(f"{pi}:{di}  {c.type:4s} {c.name}  [{state}]")
        lines.append(f"      platform      {c.platform_version}")
        lines.append(f"      driver        {c.driver_version}")
        lines.append(f"      compute units {c.compute_units}, max work-group {c.max_work_group_size}, "
                     f"local mem {c.local_mem_size // 1024} KiB")
        lines.append(f"      global mem    {c.global_mem_size / 2**30:.2f} GiB "
                     f"(max alloc {c.max_alloc_size / 2**30:.2f} GiB)")
        lines.append(f"      fp64 {'yes' if c.fp64 else 'no'}, float atomics "
                     f"{'native' if c.float_atomics else 'emulated (CAS)'}, int64 atomics "
                     f"{'yes' if c.int64_atomics else 'no'}, native float vector width "
                     f"{c.native_float_width}")
    if not lines:
        return "no OpenCL devices found"
    try:
        pi, di, _ = select_device()
        lines.append(f"default (CLRF_DEVICE={os.environ.get('CLRF_DEVICE', '') or 'unset'}): {pi}:{di}")
    except DeviceError as e:
        lines.append(f"default: none ({str(e).splitlines()[0]})")
    return "\n".join(lines)
