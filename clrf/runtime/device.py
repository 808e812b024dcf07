"""OpenCL device selection, capability probes and the command queue.

``Device(spec)`` or the ``CLRF_DEVICE`` variable take:

- nothing (or ``"auto"``): the fastest working device of any type;
- ``"cpu"`` / ``"gpu"``: the fastest working device of that type;
- ``"P:D"``: platform index P, device index D, as listed by ``clrf devices``;
- an implementation's name (``"pocl"``, ``"intel"``, ``"rusticl"``, ``"oclgrind"``,
  ``"nvidia"``, ``"amd"``, ...: clrf/runtime/tuning.py ``implementation``), optionally with a
  type (``"intel:cpu"``, ``"pocl:cpu"``): the fastest working device of that implementation.
  Unlike P:D it does not move when another platform appears (``RUSTICL_ENABLE`` lists rusticl
  before the platforms registered after it, which shifts their indices).

"Working" and "fastest" come from a probe run once per device and driver version and cached on
disk (clrf/runtime/device_probe.py: build and run a kernel, then a calibrated fp32 FMA throughput
figure); figures within 10% count as equal and then platform order decides. A machine can carry
two PoCL platforms at once (pip's and the distribution's) that differ tenfold on the same CPU;
a driver that cannot compile is skipped with the reason, and a slow one gets a one-line warning
naming the fix when it is used.
"""
from __future__ import annotations

import copy
import os
import sys
from dataclasses import dataclass, field

import pyopencl as cl
import pyopencl.tools as cl_tools

from .devmem import DeviceMemory, register as register_ledger
from .device_probe import (INSTALL_HINT, TIE, Candidate, Probe, cache_path, choice_reason,
                           cpu_flags, probe, rank, slow_reasons, slow_warning, warn_once)
from .selfcheck import known_wrong
from .tuning import Tuning, implementation


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
    cr_divide_sqrt: bool = False  # CL_FP_CORRECTLY_ROUNDED_DIVIDE_SQRT: builds may ask for it
    acq_rel: bool = False      # OpenCL C 3.0 with __opencl_c_atomic_order_acq_rel and
    #                            __opencl_c_atomic_scope_device: locks that order plain memory
    #                            between work-groups (cl/common.h lock_try, CLRF_ACQ_REL)
    host_unified_memory: bool = False  # CL_DEVICE_HOST_UNIFIED_MEMORY: the device's memory is
    #                            the host's (CPU runtimes, integrated GPUs)

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


ACQ_REL_FEATURES = ("__opencl_c_atomic_order_acq_rel", "__opencl_c_atomic_scope_device")


def _opencl_c_features(dev: "cl.Device") -> frozenset:
    """The OpenCL C 3.0 optional features the device compiles (empty before OpenCL 3.0, which
    has no such query: asking a 1.2 device is an API error, which Oclgrind reports)."""
    if not dev.version.startswith("OpenCL 3."):
        return frozenset()
    try:
        return frozenset(f.name for f in dev.opencl_c_features)
    except (cl.Error, AttributeError):
        return frozenset()


def has_acq_rel(dev: "cl.Device") -> bool:
    """Whether ``-cl-std=CL3.0`` builds may use acquire/release atomics at device scope."""
    feats = _opencl_c_features(dev)
    return all(f in feats for f in ACQ_REL_FEATURES)


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
        acq_rel=has_acq_rel(dev),
        cr_divide_sqrt=bool(getattr(dev, "single_fp_config", 0)
                            & cl.device_fp_config.CORRECTLY_ROUNDED_DIVIDE_SQRT),
        host_unified_memory=_host_unified(dev),
    )


def _host_unified(dev: "cl.Device") -> bool:
    """CL_DEVICE_HOST_UNIFIED_MEMORY, False where the runtime does not answer it (the query is
    deprecated since OpenCL 2.0)."""
    try:
        return bool(dev.host_unified_memory)
    except (cl.Error, AttributeError):
        return False


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


def _candidate(pi: int, di: int, d: "cl.Device", pr: Probe) -> Candidate:
    return Candidate(pi, di, _type_name(d.type), d.name.strip(), d.platform.name.strip(),
                     d.platform.version.strip(), d.vendor.strip(), int(d.max_compute_units),
                     int(d.max_clock_frequency), pr)


def _describe(pi, di, dev) -> str:
    return f"{pi}:{di} {_type_name(dev.type)} '{dev.name.strip()}' on '{dev.platform.version.strip()}'"


@dataclass(frozen=True)
class Choice:
    """The device a spec resolves to, with what the decision was based on."""

    platform_index: int
    device_index: int
    cl_device: "cl.Device"
    candidate: Candidate    # the chosen device with its probe figure
    reason: str             # why it was chosen, in words
    candidates: tuple       # every device whose figure was looked at (slow-driver checks)
    ranked: tuple = ()      # the usable wanted devices, best probe first (auto/cpu/gpu specs)


def choose_device(spec: str | None = None, refresh: bool = False) -> Choice:
    """Resolve a device spec (module doc) by probing the candidates; ``refresh`` re-measures."""
    spec = (spec if spec is not None else os.environ.get("CLRF_DEVICE", "")).strip().lower()
    devs = list_devices()
    if not devs:
        raise DeviceError(
            "no OpenCL platform found. Install a driver: `pip install \"clrf[pocl]\"` or, on "
            "Debian/Ubuntu, `apt-get install pocl-opencl-icd`.")
    listing = "\n".join("  " + _describe(*d) for d in devs)
    impl, _, kind = spec.partition(":")
    if impl and not impl.isdigit():
        return _choose_by_name(spec, impl, kind, devs, listing, refresh)
    if spec and ":" in spec:
        try:
            pi, di = (int(x) for x in spec.split(":"))
        except ValueError:
            raise DeviceError(f"CLRF_DEVICE/device '{spec}' is not {SPEC_FORMS}. "
                              f"Devices:\n{listing}") from None
        for d in devs:
            if d[0] == pi and d[1] == di:
                c = _candidate(*d, probe(d[2], refresh))
                if not c.probe.ok:
                    raise DeviceError(f"device {pi}:{di} is unusable ({c.probe.error}). "
                                      f"Choose another:\n{listing}")
                known = [_candidate(*o, p) for o in devs if o is not d
                         for p in [probe(o[2], measure_missing=False)] if p is not None]
                return Choice(pi, di, d[2], c, f"requested as {spec}", (c, *known))
        raise DeviceError(f"no device {pi}:{di}. Devices:\n{listing}")
    return _choose_by_name("auto", "auto", "", devs, listing, refresh)


SPEC_FORMS = "'auto', 'cpu', 'gpu', 'P:D' or an implementation name ('pocl', 'intel', ...)"
TYPES = ("cpu", "gpu", "accelerator")


def _choose_by_name(spec, impl, kind, devs, listing, refresh) -> Choice:
    """Spec ``"cpu"``/``"gpu"``/``"accelerator"``/``"auto"`` or ``"<implementation>[:type]"``."""
    if impl in TYPES + ("auto",) and not kind:
        wanted = ("gpu", "accelerator", "cpu") if impl == "auto" else (impl,)
        return _choose_ranked(devs, [d for d in devs if _type_name(d[2].type) in wanted],
                              "/".join(wanted), listing, refresh)
    if kind and kind not in TYPES:
        raise DeviceError(f"device '{spec}': the part after ':' must be one of "
                          f"{', '.join(TYPES)}. Devices:\n{listing}")
    present = sorted({implementation(d[2].platform.name) for d in devs})
    match = [d for d in devs if implementation(d[2].platform.name) == impl
             and (not kind or _type_name(d[2].type) == kind)]
    if not match:
        raise DeviceError(f"device '{spec}' is not {SPEC_FORMS}, or no such device is "
                          f"installed (implementations here: {', '.join(present)}). "
                          f"Devices:\n{listing}")
    return _choose_ranked(devs, match, spec, listing, refresh, requested=True)


def _choose_ranked(devs, pool, what, listing, refresh, requested=False) -> Choice:
    """The best-probing working device of ``pool``; ``requested``: the user named the pool
    (an implementation), so a device only known to compute wrong gradients is still taken."""
    wanted = tuple(what.split("/"))
    entries = {(d[0], d[1]): d for d in pool}
    cands = tuple(_candidate(*d, probe(d[2], refresh)) for d in entries.values())
    # a device known to compute wrong gradients (a registered self-check, clrf/runtime/
    # selfcheck.py, e.g. the grid's) is never the default
    wrong = {} if requested else {
        (c.platform_index, c.device_index): why for c in cands if c.probe.ok
        for why in [known_wrong(entries[(c.platform_index, c.device_index)][2])] if why}
    ranked = [c for c in rank(list(cands)) if (c.platform_index, c.device_index) not in wrong]
    if not requested:
        # a slow driver (pip's PoCL compiling for a generic CPU, 3-10x slower in clrf's
        # kernels than its FMA probe shows) is never the default over one that is not
        flags = cpu_flags()
        ranked.sort(key=lambda c: bool(slow_reasons(c, list(cands), flags)))
    if ranked:
        best = ranked[0]
        d = entries[(best.platform_index, best.device_index)]
        reason = (f"requested as {what}" + (f"; {choice_reason(ranked)}" if len(ranked) > 1
                                             else "")) if requested else choice_reason(ranked)
        faster = [c for c in ranked[1:] if c.probe.gflops > best.probe.gflops * (1 + TIE)]
        whys = slow_reasons(faster[0], list(cands), cpu_flags()) \
            if faster and not requested else []
        if whys:   # (a faster device ranked lower for another reason has none)
            reason = (f"{faster[0].spec} measures {faster[0].probe.gflops:.1f} GFLOP/s but "
                      f"{whys[0]}")
        if requested:
            known = [_candidate(*o, p) for o in devs if (o[0], o[1]) not in entries
                     for p in [probe(o[2], measure_missing=False)] if p is not None]
            cands = (*cands, *known)
        return Choice(d[0], d[1], d[2], best, reason, cands, tuple(ranked))
    msg = f"no working {what} OpenCL device. Devices:\n{listing}"
    if cands:
        msg += "\nRejected:\n" + "\n".join(
            f"  {_describe(*entries[(c.platform_index, c.device_index)])}: "
            f"{c.probe.error or wrong.get((c.platform_index, c.device_index)) or 'unusable'}"
            for c in cands)
    if "cpu" in wanted:
        msg += ("\nOn Debian/Ubuntu `apt-get install pocl-opencl-icd` gives a CPU driver that "
                "works on current CPUs.")
    raise DeviceError(msg)


def select_device(spec: str | None = None):
    """Resolve a device spec to ``(platform_index, device_index, cl.Device)``; see module doc.

    Warns once per process (stderr, one line) when the device is a slow driver for its CPU.
    """
    c = choose_device(spec)
    warn_once(slow_warning(c.candidate, list(c.candidates), cpu_flags()))
    return c.platform_index, c.device_index, c.cl_device


def quiet_library_builds():
    """Silence pyopencl's "Non-empty compiler output encountered" warning for the kernels that
    pyopencl itself builds (array fill, reductions, scans). Some implementations (Intel's CPU
    runtime) write progress chatter into every build log, so the warning would fire on every
    fresh build while saying nothing; clrf's own builds report real diagnostics
    (clrf/runtime/programs.py, buildlog.py)."""
    import warnings
    warnings.filterwarnings("ignore", category=cl.CompilerWarning)


class Device:
    """An OpenCL device with its context, in-order queue and probed capabilities.

    >>> dev = clrf.Device("cpu")        # or Device() to honour CLRF_DEVICE
    >>> dev.caps.fp64
    True
    """

    def __init__(self, spec: str | None = None, verbose: bool = False,
                 tuning: Tuning | None = None):
        self.platform_index, self.device_index, self.cl_device = select_device(spec)
        self.context = cl.Context([self.cl_device])
        self.queue = cl.CommandQueue(self.context)
        # Per-step arrays whose sizes change every step (packed samples, their encodings and
        # gradients) come from this pool: freed buffers go back to size bins and are reused,
        # instead of a fresh clCreateBuffer each step that a CPU runtime serves from the C heap,
        # where buffers of ever-different sizes fragment it and resident memory creeps. Bins
        # are powers of two and their halfway points (leading_bits_in_bin_id=1), so few sizes
        # are held; free_held() returns what is held (HashModel.render does after a render).
        # The pool allocates through the device's memory ledger (clrf/runtime/devmem.py), which
        # also counts the long-lived arrays of programs.upload: ``self.memory`` is both
        self.memory = self.pool = DeviceMemory(
            self.context, cl_tools.MemoryPool(cl_tools.ImmediateAllocator(self.queue),
                                              leading_bits_in_bin_id=1))
        register_ledger(self.queue, self.memory, self)
        self.caps = probe_capabilities(self.cl_device)
        if tuning is None:
            try:
                tuning = Tuning.from_env(self.caps)
            except ValueError as e:
                raise DeviceError(str(e)) from None
        self.tuning = tuning   # how kernels run here (clrf/runtime/tuning.py); CLRF_* overrides applied
        self._programs = {}
        self.first_launches = set()   # (kernel, work-group size) launched once (programs.launch)
        quiet_library_builds()
        if verbose:
            print(f"clrf: device {self}", file=sys.stderr)

    def __repr__(self):
        return (f"{self.platform_index}:{self.device_index} {self.caps.type} "
                f"'{self.caps.name}' ({self.caps.platform_version})")

    @property
    def is_cpu(self) -> bool:
        return self.caps.type == "cpu"

    def with_tuning(self, **kw) -> "Device":
        """The same device, context and queue with ``tuning.replace(**kw)``, e.g.
        ``dev.with_tuning(grad_slots=0, sample_record=False)`` for the GPU code path."""
        other = copy.copy(self)
        other.tuning = self.tuning.replace(**kw)
        return other

    def program(self, source: str, defines: dict | None = None):
        """The program for ``cl/<source>`` with ``defines`` (programs.build), built once per
        (source, defines, fast_math) and kept for the device's lifetime."""
        from .programs import build, one_off
        key = (source, tuple(sorted((defines or {}).items())), self.tuning.fast_math)
        prg = self._programs.get(key)
        if prg is None:
            with one_off():
                prg = self._programs[key] = build(self, source, defines or {},
                                                  self.tuning.fast_math,
                                                  self.tuning.verbose_build)
        return prg

    @property
    def build_seconds(self) -> float:
        """Wall seconds this process has spent on one-off work (program builds, first kernel
        launches: programs.one_off_seconds) that a caller timing its work leaves out
        (Trainer's steps and evaluations)."""
        from .programs import one_off_seconds
        return one_off_seconds()

    def finish(self):
        self.queue.finish()


def float_atomics_text(caps) -> str:
    """How atomic_add_f adds floats on a device with ``caps`` (cl/common.h)."""
    from .tuning import implementation
    if caps.float_atomics:
        return "native"
    if implementation(caps.platform) == "nvidia":
        return "inline PTX red.add (after a probe kernel; else CAS)"
    return "emulated (CAS)"


def selfcheck_lines(cl_device, caps, checks, refresh: bool) -> list:
    """``clrf devices``' lines on the gradient self-checks of one device: the cached verdicts,
    each check run first (in a child process) with the device's own tuning when ``refresh``
    (``--reprobe``) or when none is cached yet and ``refresh`` asks."""
    from types import SimpleNamespace

    from .device_probe import is_simulator
    from .selfcheck import gradient_check, verdicts_for
    out = []
    for check in checks:
        if refresh and not is_simulator(cl_device):
            tuning = Tuning.from_env(caps)
            res = gradient_check(SimpleNamespace(cl_device=cl_device, tuning=tuning), check,
                                 refresh=True)
            if not res.ok and tuning.grad_slots > 0:    # the fallback training would take
                gradient_check(SimpleNamespace(
                    cl_device=cl_device, tuning=tuning.replace(
                        grad_slots=0, sample_record=False, grad_locks=0)), check, refresh=True)
        found = verdicts_for(cl_device, check)
        if not found:
            out.append(f"      self-check    {check.what}: not run yet (runs before the first "
                       f"training; `clrf devices --reprobe` runs it now)")
        for v in found:
            state = "passed" if v.ok else f"FAILED: {v.detail}"
            out.append(f"      self-check    {check.what} ({v.path}): {state}")
    return out


def format_devices(refresh: bool = False, workloads: list | None = None,
                   checks: list | None = None) -> str:
    """Text for ``clrf devices``: every device, its probe figure, capabilities, the verdicts
    of the gradient self-checks ``checks`` (run again with ``refresh``) and the default;
    ``workloads``: lines on each model kind's default (clrf/runtime/workload.py format_choices)."""
    devs = list_devices()
    if not devs:
        return "no OpenCL devices found"
    cands = [_candidate(*d, probe(d[2], refresh)) for d in devs]
    flags = cpu_flags()
    lines = []
    for (pi, di, d), cand in zip(devs, cands):
        c = probe_capabilities(d)
        pr = cand.probe
        state = "ok" if pr.ok else f"UNUSABLE: {pr.error}"
        lines.append(f"{pi}:{di}  {c.type:4s} {c.name}  [{state}]")
        if pr.ok:
            lines.append(f"      probe         {pr.gflops:.1f} GFLOP/s fp32 FMA ("
                         f"{'cached, ' if pr.cached else ''}measured {pr.when})")
            for why in slow_reasons(cand, cands, flags):
                lines.append(f"      SLOW          {why}")
        lines.append(f"      platform      {c.platform_version}")
        lines.append(f"      driver        {c.driver_version}")
        lines.append(f"      compute units {c.compute_units}, max work-group {c.max_work_group_size}, "
                     f"local mem {c.local_mem_size // 1024} KiB")
        lines.append(f"      global mem    {c.global_mem_size / 2**30:.2f} GiB "
                     f"(max alloc {c.max_alloc_size / 2**30:.2f} GiB)")
        lines.append(f"      fp64 {'yes' if c.fp64 else 'no'}, float atomics "
                     f"{float_atomics_text(c)}, int64 atomics "
                     f"{'yes' if c.int64_atomics else 'no'}, native float vector width "
                     f"{c.native_float_width}")
        if pr.ok and checks:
            lines.extend(selfcheck_lines(d, c, checks, refresh))
    env = os.environ.get("CLRF_DEVICE", "") or "unset"
    try:
        ch = choose_device()
        lines.append(f"default (CLRF_DEVICE={env}): {ch.candidate.short()}, "
                     f"{ch.candidate.probe.gflops:.1f} GFLOP/s: {ch.reason}")
        warning = slow_warning(ch.candidate, cands, flags)
        if warning:
            lines.append(warning.replace("clrf: warning: ", "advice: "))
    except DeviceError as e:
        lines.append(f"default (CLRF_DEVICE={env}): none ({str(e).splitlines()[0]})")
    if workloads is not None:
        lines.extend(workloads)
    lines.append(f"probe figures and self-check verdicts are cached in {cache_path().parent}; "
                 f"`clrf devices --reprobe` measures and checks again")
    return "\n".join(lines)


def check_default(refresh: bool = False) -> int:
    """``clrf devices --check``: one line on the default device and an exit status for scripts.

    0: a working device that is not a slow driver; 3: the best working device, or any PoCL
    device, is a slow driver (the warning names the fix); 1: no device works.
    """
    try:
        ch = choose_device(refresh=refresh)
    except DeviceError as e:
        print(f"clrf: no working OpenCL device: {e}", file=sys.stderr)
        return 1
    print(f"clrf: default device {ch.candidate.short()}, {ch.candidate.probe.gflops:.1f} "
          f"GFLOP/s ({ch.reason})")
    cands, flags = list(ch.candidates), cpu_flags()
    warning = slow_warning(ch.candidate, cands, flags)
    if warning:
        print(warning, file=sys.stderr)
        return 3
    # a slow PoCL beside a faster driver (pip's generic-target PoCL next to Intel's runtime):
    # not the default, but the grid kernels run fastest on a PoCL that compiles for this CPU,
    # and the tests run every kernel on PoCL, so the distribution's PoCL is still worth having
    pocl = [c for c in cands if c.probe.ok and "pocl" in c.platform_version.lower()]
    slow = {c.spec: slow_reasons(c, cands, flags) for c in pocl}
    if pocl and all(slow.values()):
        c = pocl[0]
        print(f"clrf: device {c.short()} {slow[c.spec][0]}; {INSTALL_HINT}", file=sys.stderr)
        return 3
    return 0
