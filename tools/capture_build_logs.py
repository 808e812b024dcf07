"""Capture real OpenCL build logs as fixtures for tests/test_build_log.py.

For each OpenCL device the ICD loader lists (or each ``--device P:D``) this builds

  clean           cl/grid_render.cl with the defines the library uses there (backward with
                  per-sample record and gradient slots, the device's own prefetch setting)
  clean_cached    the same through pyopencl's binary cache, built twice: the log a later run
                  sees (only where pyopencl caches binaries; PoCL caches by itself)
  warning         kernels/warning.cl: three warnings clang gives with no -W option
  werror          kernels/warning.cl with the standard -Werror: the same three as errors
  header_warning  kernels/header_warning.cl: a warning inside an #included header
  error           kernels/error.cl: a syntax error (the build fails)

and writes ``<impl>_<case>.txt`` (the log as the driver returned it) and ``<impl>_<case>.json``
(implementation, platform, device and driver versions, kernel file, defines, options, whether
the build succeeded) into tests/fixtures/build_logs/. ``<impl>`` is e.g. ``pocl-3.1-debian``,
``rusticl-22.3.6``, ``intel-2026.22.10``, ``oclgrind-21.10``.

The builds bypass pyopencl's cache (PYOPENCL_NO_CACHE, set before importing pyopencl) so that
each log is the compiler's, and the log of a failed build can be read back.

    OCL_ICD_VENDORS=/tmp/ocl-vendors RUSTICL_ENABLE=llvmpipe python tools/capture_build_logs.py
    OCL_ICD_VENDORS=/tmp/ocl-vendors-grind python tools/capture_build_logs.py --device 0:0

A new implementation: run the tool under its ICD, read the new .txt files, add the progress
lines it writes to CHATTER in clrf/runtime/buildlog.py, and run tests/test_build_log.py.
"""
from __future__ import annotations

import argparse
import datetime
import json
import os
import re
import sys
import tempfile
import warnings
from pathlib import Path
from types import SimpleNamespace

os.environ["PYOPENCL_NO_CACHE"] = "1"

import pyopencl as cl  # noqa: E402
from pyopencl.cache import create_built_program_from_source_cached  # noqa: E402
from pyopencl.characterize import has_src_build_cache  # noqa: E402

ROOT = Path(__file__).resolve().parent.parent
sys.path.append(str(ROOT))   # the checkout's clrf only where none is installed

from clrf.runtime.device import probe_capabilities  # noqa: E402
from clrf.runtime.programs import build_flags  # noqa: E402
from clrf.runtime.tuning import Tuning  # noqa: E402

OUT = ROOT / "tests" / "fixtures" / "build_logs"
KERNELS = OUT / "kernels"


def impl_name(dev) -> str:
    """A file-name-safe implementation name with its version, e.g. ``pocl-3.1-debian``."""
    plat, pver = dev.platform.name.strip(), dev.platform.version.strip()
    drv = dev.driver_version.strip()
    m = re.search(r"PoCL (\S+)", pver)
    if m:
        name, ver = "pocl", m.group(1)
    elif "intel" in plat.lower():
        m = re.match(r"\d+(\.\d+){0,2}", drv)
        name, ver = "intel", m.group(0) if m else drv
    else:
        name = plat.split()[0].lower()
        m = re.search(r"\d+(\.\d+)+\S*", drv)
        ver = m.group(0) if m else drv
    return re.sub(r"[^A-Za-z0-9._-]+", "-", f"{name}-{ver}").strip("-")


def clean_defines(caps) -> dict:
    """grid_render.cl's backward as the library builds it on a device with ``caps``."""
    t = Tuning.for_device(caps)
    slots = max(t.grad_slots, 2)
    return {"SH_DEGREE": 2, "GRAD_MODE": 1, "GRAD_SLOTS": slots, "SAMPLE_RECORD": 1,
            "GRAD_LOCKS": t.grad_locks, "TRACK_TOUCHED": 1, "COMPENSATED_SUMS": 0,
            "CLRF_PREFETCH": int(t.prefetch), "T_STOP": 1e-4, "BLOCK": 8}


def cases(caps):
    """(case, kernel path, defines, extra options) for one device."""
    grid = ROOT / "cl" / "grid_render.cl"
    return [("clean", grid, clean_defines(caps), []),
            ("clean_cached", grid, clean_defines(caps), []),
            ("warning", KERNELS / "warning.cl", {}, []),
            ("werror", KERNELS / "warning.cl", {}, ["-Werror"]),
            ("header_warning", KERNELS / "header_warning.cl", {}, [f"-I{KERNELS}"]),
            ("error", KERNELS / "error.cl", {}, [])]


def build_log(ctx, dev, src: str, opts: list, cached: bool) -> tuple:
    """(log, built) of building ``src`` with ``opts`` on ``dev``; cached: through pyopencl's
    binary cache in a fresh folder, twice, the second log."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        if cached:
            with tempfile.TemporaryDirectory() as tmp:
                for _ in range(2):
                    prg, _was_cached = create_built_program_from_source_cached(
                        ctx, src, " ".join(opts).encode(), [dev], cache_dir=tmp)
            return prg.get_build_info(dev, cl.program_build_info.LOG), True
        prg = cl.Program(ctx, src)
        try:
            prg.build(options=opts, devices=[dev])
            built = True
        except cl.RuntimeError:
            built = False
        return prg.get_build_info(dev, cl.program_build_info.LOG), built


def capture(pi: int, di: int, dev, out: Path, name: str | None) -> list:
    caps = probe_capabilities(dev)
    impl = name or impl_name(dev)
    ctx = cl.Context([dev])
    # what build_flags reads of a clrf Device (the PTX probe builds and runs a kernel)
    shim = SimpleNamespace(caps=caps, cl_device=dev, context=ctx, queue=cl.CommandQueue(ctx))
    written = []
    for case, path, defines, extra in cases(caps):
        if case == "clean_cached" and has_src_build_cache(dev):
            continue
        opts = (build_flags(shim, defines) if path.parent.name == "cl" else []) + extra
        log, built = build_log(ctx, dev, path.read_text(), opts, case == "clean_cached")
        stem = f"{impl}_{case}"
        (out / f"{stem}.txt").write_text(log)
        meta = {"implementation": impl, "case": case, "platform": caps.platform,
                "platform_version": caps.platform_version, "device": caps.name,
                "device_index": f"{pi}:{di}", "driver_version": caps.driver_version,
                "kernel": str(path.relative_to(ROOT)), "defines": defines, "options": opts,
                "built": built, "pyopencl": cl.VERSION_TEXT,
                "captured": datetime.date.today().isoformat(),
                "how": ("pyopencl binary cache, second build" if case == "clean_cached"
                        else "source build")}
        (out / f"{stem}.json").write_text(json.dumps(meta, indent=1) + "\n")
        written.append(f"{stem}: {'built' if built else 'failed'}, {len(log)} chars")
    return written


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--device", action="append", default=[],
                    help="P:D as pyopencl lists them under the current ICD setting (repeatable;"
                         " default: every device)")
    ap.add_argument("--name", help="implementation name for the files (one --device only)")
    ap.add_argument("--out", type=Path, default=OUT, help="fixture folder (default: %(default)s)")
    args = ap.parse_args(argv)
    devs = [(pi, di, d) for pi, p in enumerate(cl.get_platforms())
            for di, d in enumerate(p.get_devices())]
    if args.device:
        want = {tuple(int(x) for x in s.split(":")) for s in args.device}
        devs = [x for x in devs if (x[0], x[1]) in want]
        if len(devs) != len(want):
            ap.error(f"--device {args.device}: not all listed ({[f'{p}:{d}' for p, d, _ in devs]})")
    if args.name and len(devs) != 1:
        ap.error("--name needs exactly one device")
    args.out.mkdir(parents=True, exist_ok=True)
    for pi, di, d in devs:
        print(f"{pi}:{di} {d.platform.name.strip()} / {d.name.strip()}", flush=True)
        for line in capture(pi, di, d, args.out, args.name):
            print("  " + line, flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
