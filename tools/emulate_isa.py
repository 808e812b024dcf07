"""Run a clrf tool with PoCL compiling for an older x86 vector ISA than the host's.

    python tools/emulate_isa.py avx2 tools/nerf_bench.py --out avx2.json
    python tools/emulate_isa.py avx2 tools/bench.py --only 'grid/fwdbwd/128/sh2/*/camera'
    python tools/emulate_isa.py avx2 -m clrf.nerf.autotune --preset original

What changes, for the tool's process only:
- PoCL compiles the kernels for the ISA's LLVM CPU (POCL_LLVM_CPU_NAME, e.g. haswell: the
  device is then named ``pthread-haswell-...``) and links its builtin library for that ISA
  (POCL_KERNELLIB_NAME), into a kernel cache of its own (POCL_CACHE_DIR), with pyopencl's
  binary cache off (PYOPENCL_NO_CACHE), so no binary of the host's ISA is reused;
- clrf sees the ISA's native float vector width (PoCL reports the host's), so its per-device
  defaults (the fused MLP's register tile, clrf/mlp/tiling.py) are those of such a CPU, and the
  tuner's cache goes to a directory of its own (XDG_CACHE_HOME);
- numpy's OpenBLAS uses its kernels for the ISA (OPENBLAS_CORETYPE), so ratios to numpy
  compare like with like.

What it cannot change: the caches, memory system and execution units stay the host's (on a
Zen 4, 512-bit FMAs run as two 256-bit halves, so AVX2 code has the same FLOP peak but needs
twice the instructions), and peers that compile for the host themselves (Taichi) keep the
host's ISA. Figures are "the ISA's code on this CPU", not another CPU's.
"""
from __future__ import annotations

import dataclasses
import os
import runpy
import sys
import tempfile

# ISA -> (PoCL LLVM CPU, PoCL builtin library, native float width, OpenBLAS core type)
ISAS = {
    "avx2": ("haswell", "avx2", 8, "Haswell"),
    "avx": ("sandybridge", "avx", 8, "Sandybridge"),
    "sse4": ("nehalem", "sse41", 4, "Nehalem"),
}


def main(argv=None) -> None:
    argv = list(sys.argv[1:] if argv is None else argv)
    if len(argv) < 2 or argv[0] not in ISAS:
        sys.exit(f"usage: python tools/emulate_isa.py {{{','.join(ISAS)}}} TOOL.py|-m MODULE "
                 f"[ARGS...]")
    isa, rest = argv[0], argv[1:]
    cpu, lib, width, blas = ISAS[isa]
    scratch = os.path.join(tempfile.gettempdir(), f"clrf-emulate-{isa}")
    os.environ.update({"POCL_LLVM_CPU_NAME": cpu, "POCL_KERNELLIB_NAME": lib,
                       "POCL_CACHE_DIR": os.path.join(scratch, "pocl"),
                       "PYOPENCL_NO_CACHE": "1", "OPENBLAS_CORETYPE": blas,
                       "XDG_CACHE_HOME": os.path.join(scratch, "cache")})
    here = os.path.dirname(os.path.abspath(__file__))
    sys.path[:0] = [here]
    sys.path.append(os.path.dirname(here))   # the checkout's clrf only where none is installed
    import clrf.runtime.device as device

    probe = device.probe_capabilities
    device.probe_capabilities = lambda d: dataclasses.replace(probe(d), native_float_width=width)
    print(f"emulate_isa: PoCL compiles for {cpu} ({lib} builtins), clrf sees float width "
          f"{width}, OpenBLAS core {blas}", file=sys.stderr)
    if rest[0] == "-m":
        sys.argv = rest[1:]
        runpy.run_module(rest[1], run_name="__main__", alter_sys=True)
    else:
        sys.argv = rest
        runpy.run_path(rest[0], run_name="__main__")


if __name__ == "__main__":
    main()
