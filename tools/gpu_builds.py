"""Build every kernel of cl/ offline for AMD, Intel and NVIDIA GPUs, with the defines clrf
uses, and report per kernel the registers, spills, local memory and occupancy each compiler
gives. No GPU is needed.

    python tools/gpu_builds.py                         # every target, every shape; a summary
    python tools/gpu_builds.py --targets gfx1100,tgllp --shapes gpu --markdown
    python tools/gpu_builds.py --json gpu-builds.json  # everything, per kernel
    python tools/gpu_builds.py --update-table          # the tests' builds: tools/gpu_builds_table.json

Compilers (``bash tools/setup.sh gpucc`` installs them on Debian/Ubuntu):
  AMD     clang-19 for amdgcn-mesa-mesa3d with libclc-19's bitcode, which reports per kernel
          SGPRs, VGPRs (AGPRs), scratch bytes per lane, spilled registers, LDS bytes and
          occupancy in waves per SIMD (-Rpass-analysis=kernel-resource-usage)
  Intel   ocloc (Intel's offline compiler, the same IGC as its OpenCL driver; Debian's
          intel-opencl-icd), zebin format: per kernel the SIMD width IGC chose, GRF count,
          spill/fill and private memory per thread and SLM bytes (the .ze_info section)
  NVIDIA  clang-19 for nvptx64-nvidia (libclc-19's nvidiacl bitcode) to PTX, then ptxas -v (the
          CUDA toolkit, when present) for registers, spill stores, stack frame and shared
          memory; without ptxas the PTX only (it built)
Found as clang-19 / ocloc / ptxas on PATH (or $CLRF_CLANG, $CLRF_OCLOC, $CLRF_PTXAS) and
libclc's bitcode in $CLRF_LIBCLC, else .gpucc/libclc/usr/lib/clc in the checkout (where the
setup script unpacks it: installing libclc-19 would remove Mesa's OpenCL, which needs
libclc-15). NVIDIA's own OpenCL compiler is not clang: the nvptx figures are clang's, a
stand-in.

What is built: clrf/training/catalog.py lists every (kernel file, defines) pair the library asks
a device for, through the model kinds' own functions, for every scene preset and section
preset. For each target it is asked for three shapes:
  gpu      the target's own tuning (clrf/runtime/tuning.py Tuning.for_device of the target's
           capabilities below): the GPU-shaped kernels (fused MLP with MLP_GPU=1 in local
           memory, the splat rasteriser's work-group per tile, float-atomic gradients)
  gpu-cpu  the same GPU with CLRF_FORCE_GPU_KERNELS=0 (the CPU tiles and shapes on a GPU)
  cpu      a CPU device's tuning (2 compute units, AVX-512, OpenCL 3.0 acquire/release: the
           gradient slots with block locks and per-sample records, sorted rays, software
           prefetch, the AVX-512 MLP tiles): the same sources as CPUs build them
and every program gets the capability defines the target's device would add
(clrf/runtime/programs.py capability_defines, caps_build_flags: no CLRF_HAS_FP64 on Intel,
CLRF_PTX_ATOMICS on NVIDIA, ...). Builds are OpenCL C 3.0 (-cl-std=CL3.0), and OpenCL C 1.2
again for the --cl12 targets (default gfx1100; programs that need 3.0's acquire/release atomics
are skipped there).

The targets' capabilities are assumptions (no device is queried): see TARGETS.

Exit status 1 when a build fails (each failing file, defines and target is listed), else 0.
--check adds the checks of tests/test_gpu_builds.py: no GPU-shape kernel (GPU_SHAPE_KERNELS)
spills on the --no-spill targets (default gfx1100, tgllp), and no kernel's local memory
exceeds its target's (LOCAL_LIMIT).
"""
from __future__ import annotations

import argparse
import hashlib
import json
import os
import re
import shutil
import struct
import subprocess
import sys
import tempfile
import time
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

from clrf.runtime.atomicfile import write_text  # noqa: E402
from clrf.training.catalog import library_programs  # noqa: E402
from clrf.runtime.device import Capabilities  # noqa: E402
from clrf.runtime.programs import caps_build_flags, capability_defines, cl_dir  # noqa: E402
from clrf.runtime.tuning import Tuning, implementation  # noqa: E402

LIBCLC_IN_CHECKOUT = ROOT / ".gpucc" / "libclc" / "usr" / "lib" / "clc"
FIX = "bash tools/setup.sh gpucc"


def _caps(name, platform, version, cu, wg, local, fp64, float_atomics, acq_rel, kind="gpu",
          width=1) -> Capabilities:
    return Capabilities(name=name, platform=platform, platform_version=version,
                        driver_version="offline", type=kind, compute_units=cu,
                        max_work_group_size=wg, local_mem_size=local,
                        global_mem_size=16 << 30, max_alloc_size=4 << 30, fp64=fp64,
                        float_atomics=float_atomics, int64_atomics=True,
                        native_float_width=width, cr_divide_sqrt=kind == "gpu",
                        acq_rel=acq_rel)


AMD, INTEL, NV = ("AMD Accelerated Parallel Processing", "Intel(R) OpenCL Graphics",
                  "NVIDIA CUDA")


@dataclass(frozen=True)
class Target:
    """A GPU built for: its vendor ("amd", "intel", "nvidia"), the compiler's name for it
    (-mcpu, ocloc -device, ptxas --gpu-name), and the capabilities clrf would probe there:
    ROCm's OpenCL for AMD (OpenCL 2.x devices: no acquire/release atomics, no
    cl_ext_float_atomics; 256 work-items per group, 64 KiB LDS, fp64), Intel's compute runtime
    (OpenCL 3.0 with acquire/release; no fp64 on Gen12LP or Xe-HPG; cl_ext_float_atomics on
    both, as ocloc's __opencl_c_ext_fp32_global_atomic_add for tgllp shows: on Xe-LP, which
    has no float atomic add, IGC emulates it with an atomic read and a compare-and-swap loop;
    64 KiB SLM), NVIDIA's driver (no float atomics: inline PTX; 48 KiB of static
    shared memory per block, fp64)."""
    name: str
    vendor: str
    device: str
    what: str
    caps: Capabilities
    wave64: bool = False      # AMD: build wave64 (-mwavefrontsize64; gfx9 always is)


TARGETS = {t.name: t for t in (
    Target("gfx1100", "amd", "gfx1100", "AMD RDNA3 (Radeon RX 7900)",
           _caps("gfx1100", AMD, "OpenCL 2.1 AMD-APP", 48, 256, 65536, True, False, False)),
    Target("gfx1103", "amd", "gfx1103", "AMD RDNA3 APU (Radeon 780M)",
           _caps("gfx1103", AMD, "OpenCL 2.1 AMD-APP", 6, 256, 65536, True, False, False)),
    Target("gfx90a", "amd", "gfx90a", "AMD CDNA2 (Instinct MI210/MI250)",
           _caps("gfx90a", AMD, "OpenCL 2.1 AMD-APP", 104, 256, 65536, True, False, False)),
    Target("gfx942", "amd", "gfx942", "AMD CDNA3 (Instinct MI300)",
           _caps("gfx942", AMD, "OpenCL 2.1 AMD-APP", 304, 256, 65536, True, False, False)),
    Target("tgllp", "intel", "tgllp", "Intel Xe-LP (Tiger Lake Iris Xe)",
           _caps("tgllp", INTEL, "OpenCL 3.0 NEO", 96, 512, 65536, False, True, True)),
    Target("dg2", "intel", "dg2", "Intel Xe-HPG (Arc A770)",
           _caps("dg2", INTEL, "OpenCL 3.0 NEO", 512, 1024, 65536, False, True, True)),
    Target("sm_90", "nvidia", "sm_90", "NVIDIA Hopper (H100)",
           _caps("sm_90", NV, "OpenCL 3.0 CUDA", 132, 1024, 49152, True, False, False)),
)}
# not in the default list: RDNA3 in wave64 (the occupancy figures of the other wave size)
EXTRA_TARGETS = {"gfx1100-w64": Target(
    "gfx1100-w64", "amd", "gfx1100", "AMD RDNA3, wave64",
    TARGETS["gfx1100"].caps, wave64=True)}
DEFAULT_TARGETS = tuple(TARGETS)

# the CPU device whose tuning the "cpu" shape builds (PoCL on 2 cores of an AVX-512 CPU)
CPU_CAPS = _caps("cpu", "Portable Computing Language", "OpenCL 3.0 PoCL", 2, 4096, 1 << 20,
                 True, False, True, kind="cpu", width=16)
SHAPES = ("gpu", "gpu-cpu", "cpu")

# The kernels that run on GPUs in their GPU shape (tuning.gpu_kernels): no spills allowed.
GPU_SHAPE_KERNELS = {
    "mlp.cl": ("mlp_forward", "mlp_density", "mlp_backward", "mlp_weight_grad"),
    "hash.cl": ("hash_forward", "hash_backward"),
    "grid_render.cl": ("render_forward", "render_backward"),
    "splat_raster.cl": ("splat_raster_forward", "splat_raster_backward"),
}
NO_SPILL_TARGETS = ("gfx1100", "tgllp")
LOCAL_LIMIT = {"amd": 65536, "intel": 65536, "nvidia": 49152}   # bytes per work-group


# ---- compilers -------------------------------------------------------------------------------
@dataclass
class Tools:
    clang: str | None
    libclc: Path | None
    ocloc: str | None
    ptxas: str | None
    versions: dict = field(default_factory=dict)

    def missing(self, vendor: str) -> str:
        """'' when ``vendor``'s targets can be built, else what is missing."""
        need = {"amd": [("clang-19", self.clang), ("libclc-19 bitcode", self.libclc)],
                "nvidia": [("clang-19", self.clang), ("libclc-19 bitcode", self.libclc)],
                "intel": [("ocloc", self.ocloc)]}[vendor]
        gone = [n for n, v in need if not v]
        return ", ".join(gone)


def _first_line(cmd) -> str:
    try:
        out = subprocess.run(cmd, capture_output=True, text=True, timeout=60)
    except (OSError, subprocess.SubprocessError):
        return ""
    lines = [ln.strip() for ln in (out.stdout + out.stderr).splitlines() if ln.strip()]
    return lines[0] if lines else ""


def find_tools() -> Tools:
    clang = shutil.which(os.environ.get("CLRF_CLANG") or "clang-19")
    libclc = None
    for cand in (os.environ.get("CLRF_LIBCLC"), LIBCLC_IN_CHECKOUT):
        if cand and (Path(cand) / "gfx1100-amdgcn-mesa-mesa3d.bc").is_file():
            libclc = Path(cand)
            break
    ocloc = shutil.which(os.environ.get("CLRF_OCLOC") or "ocloc")
    ptxas = shutil.which(os.environ.get("CLRF_PTXAS") or "ptxas")
    t = Tools(clang, libclc, ocloc, ptxas)
    if clang:
        t.versions["clang"] = _first_line([clang, "--version"])
    if libclc:
        t.versions["libclc"] = str(libclc)
    if ocloc:
        with tempfile.TemporaryDirectory(prefix="clrf-ocloc-") as tmp:   # it writes a file
            subprocess.run([ocloc, "query", "OCL_DRIVER_VERSION"], capture_output=True,
                           cwd=tmp)
            f = Path(tmp) / "OCL_DRIVER_VERSION"
            v = f.read_text(errors="replace").strip("\0 \n") if f.is_file() else "?"
        t.versions["ocloc"] = f"ocloc of Intel's compute runtime {v}"
    if ptxas:
        out = subprocess.run([ptxas, "--version"], capture_output=True, text=True).stdout
        m = re.search(r"release [\d.]+, V[\d.]+", out)
        t.versions["ptxas"] = f"ptxas {m.group(0) if m else out.strip()}"
    return t


# ---- one build -------------------------------------------------------------------------------
@dataclass
class Build:
    """One compile: ``source`` with ``flags`` for ``target`` as OpenCL C ``std``."""
    source: str
    flags: tuple
    target: str
    std: str
    raw: bool = False
    ok: bool = False
    log: str = ""
    seconds: float = 0.0
    kernels: dict = field(default_factory=dict)   # name -> figures
    cached: bool = False                          # filled from the resource table (TABLE)

    def key(self):
        return (self.source, self.flags, self.target, self.std)


# a kernel's name: after its qualifier at the start of a line, spelt with or without the
# underscores
KERNEL_RE = re.compile(r"^[ \t]*(?:__)?kernel\b.{0,200}?\bvoid\s+(\w+)\s*\(", re.S | re.M)


def kernel_names(source: str, _seen=None) -> set:
    """Names declared as kernels in cl/<source> and the headers it includes (whatever the
    defines)."""
    seen = set() if _seen is None else _seen
    if source in seen or not (cl_dir() / source).is_file():
        return set()
    seen.add(source)
    text = (cl_dir() / source).read_text()
    names = set(KERNEL_RE.findall(text))
    for inc in re.findall(r'^\s*#\s*include\s+"([^"]+)"', text, re.M):
        names |= kernel_names(inc, seen)
    return names


def _run(cmd, cwd=None, timeout=600):
    p = subprocess.run(cmd, capture_output=True, text=True, cwd=cwd, timeout=timeout)
    return p.returncode, p.stdout + p.stderr


def _amd(b: Build, t: Target, tools: Tools) -> None:
    bc = tools.libclc / f"{t.device}-amdgcn-mesa-mesa3d.bc"
    cmd = [tools.clang, "-x", "cl", f"-cl-std={b.std}", "-target", "amdgcn-mesa-mesa3d",
           f"-mcpu={t.device}", "-nogpulib", "-Xclang", "-finclude-default-header",
           "-Xclang", "-mlink-builtin-bitcode", "-Xclang", str(bc), "-O3",
           "-Rpass-analysis=kernel-resource-usage", *b.flags, "-c", str(cl_dir() / b.source),
           "-o", os.devnull]
    if t.wave64:
        cmd.insert(cmd.index("-nogpulib"), "-mwavefrontsize64")
    rc, out = _run(cmd)
    b.ok = rc == 0
    b.log = _diagnostics(out)
    kernels, cur = {}, None
    names = kernel_names(b.source)
    fields = {"SGPRs": "sgpr", "VGPRs": "vgpr", "AGPRs": "agpr",
              "ScratchSize [bytes/lane]": "scratch", "Occupancy [waves/SIMD]": "occupancy",
              "SGPRs Spill": "sgpr_spill", "VGPRs Spill": "vgpr_spill",
              "LDS Size [bytes/block]": "local"}
    for m in re.finditer(r"remark: +(Function Name|[A-Za-z][^:]*?): (\S+) \[-Rpass-analysis", out):
        k, v = m.group(1).strip(), m.group(2)
        if k == "Function Name":
            cur = v if v in names else None
            if cur:
                kernels[cur] = {}
        elif cur and k in fields:
            kernels[cur][fields[k]] = int(v) if v.isdigit() else v
    wave = 64 if t.wave64 or re.match(r"gfx[6-9]", t.device) else 32   # gfx9: wave64 only
    for fig in kernels.values():
        fig["spill"] = int(fig.get("vgpr_spill", 0) > 0 or fig.get("sgpr_spill", 0) > 0)
        fig["regs"] = fig.get("vgpr")
        fig["wave"] = wave
    b.kernels = kernels


def _elf_section(data: bytes, want: str) -> bytes:
    """The bytes of section ``want`` of a 64-bit little-endian ELF file."""
    shoff, = struct.unpack_from("<Q", data, 0x28)
    entsize, num, strndx = struct.unpack_from("<HHH", data, 0x3A)
    secs = [struct.unpack_from("<IIQQQQ", data, shoff + i * entsize) for i in range(num)]
    stroff = secs[strndx][4]
    for name, _typ, _flags, _addr, off, size in secs:
        end = data.index(b"\0", stroff + name)
        if data[stroff + name:end].decode() == want:
            return data[off:off + size]
    raise ValueError(f"no section {want}")


def parse_zeinfo(text: str) -> dict:
    """{kernel: figures} from a zebin's .ze_info (YAML; only the keys used here are read):
    execution_env's simd_size, grf_count and slm_size ("local"), and the per-thread memory
    buffers: "scratch" their total bytes per thread, split into "spill_bytes" and "private"
    where the buffers say (spill_fill_space, private_space); a single_space buffer holds both
    ("split" False: _intel_split reads IGC's assembly for the split)."""
    kernels, top, cur, section, buf = {}, None, None, None, None
    for line in text.splitlines():
        if re.match(r"^\S", line):             # a top-level key (kernels, kernels_misc_info ...)
            top, cur = line.split(":")[0], None
            continue
        m = re.match(r"^  - name:\s+(\S+)", line)
        if m and top == "kernels":
            cur = kernels[m.group(1)] = {"simd": None, "grf": None, "local": 0, "scratch": 0,
                                         "spill_bytes": 0, "private": 0, "split": True}
            section = None
            continue
        if cur is None:
            continue
        m = re.match(r"^    (\w+):\s*$", line)
        if m:
            section = m.group(1)
            continue
        m = re.match(r"^      (?:- |  )?(\w+):\s+(\S+)", line)
        if not m:
            continue
        k, v = m.group(1), m.group(2)
        if section == "execution_env":
            if k == "simd_size":
                cur["simd"] = int(v)
            elif k == "grf_count":
                cur["grf"] = int(v)
            elif k == "slm_size":
                cur["local"] = int(v)
        elif section == "per_thread_memory_buffers":
            if line.lstrip().startswith("- "):
                buf = {}
            if buf is not None:
                buf[k] = v
                if "usage" in buf and "size" in buf:
                    size = int(buf["size"])
                    cur["scratch"] += size
                    if buf["usage"] == "spill_fill_space":
                        cur["spill_bytes"] += size
                    elif buf["usage"] == "private_space":
                        cur["private"] += size
                    else:                       # single_space: spills and private together
                        cur["split"] = False
                    buf = None
    return kernels


def parse_igc_asm(folder: Path) -> dict:
    """{kernel: (spill bytes, private bytes)} per thread from the assembly IGC dumps
    (IGC_ShaderDumpEnable): the "//.spill size" and "//.private memory size" lines of each
    kernel's final compile (retries, named *_N_simdW_*, are left out)."""
    out = {}
    for f in sorted(folder.rglob("*.asm")):
        if re.search(r"_\d+_simd\d+_", f.name):
            continue
        head = f.read_text(errors="replace")[:200000]
        name = re.search(r"^//\.kernel (\S+)", head, re.M)
        if not name:
            continue
        sp = re.search(r"^//\.spill size (\d+)", head, re.M)
        pr = re.search(r"^//\.private memory size (\d+)", head, re.M)
        out[name.group(1)] = (int(sp.group(1)) if sp else 0, int(pr.group(1)) if pr else 0)
    return out


def _ocloc(b: Build, t: Target, tools: Tools, tmp: str, env=None):
    opts = list(b.flags) + [f"-cl-std={b.std}"]
    cmd = [tools.ocloc, "compile", "-file", str(cl_dir() / b.source), "-device", t.device,
           "--format", "zebin", "-output_no_suffix", "-output", "k", "-out_dir", tmp,
           "-options", " ".join(opts)]
    p = subprocess.run(cmd, capture_output=True, text=True, cwd=tmp, timeout=600,
                       env=None if env is None else {**os.environ, **env})
    return p.returncode, p.stdout + p.stderr, Path(tmp) / "k"


def _intel(b: Build, t: Target, tools: Tools) -> None:
    with tempfile.TemporaryDirectory(prefix="clrf-ocloc-") as tmp:
        rc, out, binary = _ocloc(b, t, tools, tmp)
        b.ok = rc == 0 and binary.is_file()
        b.log = _diagnostics(out)
        if not b.ok:
            return
        b.kernels = parse_zeinfo(_elf_section(binary.read_bytes(), ".ze_info").decode())
        if any(not f["split"] for f in b.kernels.values()):
            # scratch holds spills and private arrays together: compile again with IGC's
            # assembly dumped, which gives each kernel's spill and private sizes
            dump = Path(tmp) / "dump"
            rc, _, _ = _ocloc(b, t, tools, tmp, {"IGC_ShaderDumpEnable": "1",
                                                  "IGC_DumpToCustomDir": str(dump)})
            sizes = parse_igc_asm(dump) if rc == 0 else {}
            for k, f in b.kernels.items():
                if not f["split"] and k in sizes:
                    f["spill_bytes"], f["private"] = sizes[k]
                    f["split"] = True
    for fig in b.kernels.values():
        # unsplit scratch counts as spills (it may be private arrays: the asm was not read)
        fig["spill"] = int(fig["spill_bytes"] > 0 or not fig["split"])
        fig["regs"] = fig["grf"]
        fig["occupancy"] = fig["simd"]


def _nvidia(b: Build, t: Target, tools: Tools) -> None:
    bc = tools.libclc / "nvptx64--nvidiacl.bc"
    with tempfile.TemporaryDirectory(prefix="clrf-ptx-") as tmp:
        ptx = Path(tmp) / "k.ptx"
        cmd = [tools.clang, "-x", "cl", f"-cl-std={b.std}", "-target", "nvptx64-unknown-nvidiacl",
               f"-march={t.device}", "-nogpulib", "-fgnu-keywords",   # NVIDIA's takes asm
               "-Xclang", "-finclude-default-header",
               "-Xclang", "-mlink-builtin-bitcode", "-Xclang", str(bc), "-O3", *b.flags,
               "-S", str(cl_dir() / b.source), "-o", str(ptx)]
        rc, out = _run(cmd)
        b.ok = rc == 0
        b.log = _diagnostics(out)
        if not b.ok:
            return
        names = kernel_names(b.source)
        if not tools.ptxas:
            text = ptx.read_text()
            b.kernels = {k: {"regs": None, "spill": None}
                         for k in re.findall(r"\.entry\s+(\w+)", text) if k in names}
            return
        rc, out = _run([tools.ptxas, "-v", "--gpu-name", t.device, str(ptx), "-o", os.devnull])
    if rc != 0:
        b.ok = False
        b.log = (b.log + "\n" + out).strip()
        return
    kernels, cur = {}, None
    for line in out.splitlines():
        m = re.search(r"Function properties for (\w+)", line)
        if m:
            cur = m.group(1) if m.group(1) in names else None
            if cur:
                kernels.setdefault(cur, {"regs": None, "spill_bytes": 0, "stack": 0,
                                         "local": 0})
            continue
        if cur is None:
            continue
        m = re.search(r"(\d+) bytes stack frame, (\d+) bytes spill stores", line)
        if m:
            kernels[cur]["stack"], kernels[cur]["spill_bytes"] = int(m.group(1)), int(m.group(2))
        m = re.search(r"Used (\d+) registers", line)
        if m:
            kernels[cur]["regs"] = int(m.group(1))
            s = re.search(r"(\d+) bytes smem", line)
            kernels[cur]["local"] = int(s.group(1)) if s else 0
    for fig in kernels.values():
        fig["spill"] = int(fig["spill_bytes"] > 0)
    b.kernels = kernels


def _diagnostics(out: str) -> str:
    """The compiler's errors and warnings (remarks, with the include chains and source
    excerpts that go with them, and progress lines dropped)."""
    keep, skip, chain = [], False, []
    for line in out.splitlines():
        if line.startswith("In file included from") or (chain and line.startswith("    ")
                                                          and "included from" in line):
            chain.append(line)
            continue
        if "remark:" in line or "[-Rpass-analysis" in line:
            skip, chain = True, []
            continue
        if skip and (line.startswith(" ") or re.match(r"^\s*\d+ \|", line)):
            continue
        skip = False
        if not line.strip() or line.startswith(("Build succeeded", "Command was:")):
            continue
        keep += chain + [line]
        chain = []
    return "\n".join(keep)


BACKENDS = {"amd": _amd, "intel": _intel, "nvidia": _nvidia}


def run_build(b: Build, t: Target, tools: Tools) -> Build:
    t0 = time.perf_counter()
    try:
        BACKENDS[t.vendor](b, t, tools)
    except (OSError, subprocess.SubprocessError, ValueError) as e:
        b.ok, b.log = False, f"{type(e).__name__}: {e}"
    b.seconds = time.perf_counter() - t0
    return b


# ---- what to build ---------------------------------------------------------------------------
def shape_device(target: Target, shape: str):
    """(caps, tuning) a program list is recorded with for ``shape`` on ``target``."""
    if shape == "gpu":
        return target.caps, Tuning.for_device(target.caps)
    if shape == "gpu-cpu":
        return target.caps, Tuning.for_device(target.caps).replace(gpu_kernels=False)
    return CPU_CAPS, Tuning.for_device(CPU_CAPS)


def target_flags(target: Target, entry) -> tuple:
    """The -D / -I / -cl options clrf would pass for ``entry`` on ``target``'s device, less
    -cl-std (the builder sets it)."""
    caps = target.caps
    if entry.raw:
        flags = [f"-D{k}={v}" for k, v in entry.defines]
    else:
        ptx = implementation(caps.platform) == "nvidia" and not caps.float_atomics
        flags = caps_build_flags(caps, capability_defines(caps, ptx), entry.defines_dict())
    return tuple(f for f in flags if not f.startswith("-cl-std="))


@dataclass
class Job:
    """A program of one shape on one target, and the build that serves it (shared by the
    shapes that ask for the same flags)."""
    target: str
    shape: str
    entry: object
    build: Build


def plan(targets, shapes, cl12, only_sources=None, per_source=None, builds=None) -> tuple:
    """(jobs, builds): a Job per (target, shape, program), a Build per distinct compile.
    per_source: at most this many programs per (target, shape, kernel file), the first asked;
    builds: a {key: Build} to share compiles with (and add to)."""
    builds, jobs = ({} if builds is None else builds), []
    for name in targets:
        t = TARGETS.get(name) or EXTRA_TARGETS[name]
        stds = ["CL3.0"] + (["CL1.2"] if name in cl12 else [])
        for shape in shapes:
            caps, tuning = shape_device(t, shape)
            count = {}
            for e in library_programs(caps, tuning):
                if e.only and implementation(t.caps.platform) not in e.only:
                    continue
                if only_sources and e.source not in only_sources:
                    continue
                count[e.source] = count.get(e.source, 0) + 1
                if per_source and count[e.source] > per_source:
                    continue
                flags = target_flags(t, e)
                for std in stds:
                    if std == "CL1.2" and "-DCLRF_ACQ_REL=1" in flags:
                        continue       # acquire/release atomics are OpenCL C 3.0
                    b = Build(e.source, flags, name, std, e.raw)
                    b = builds.setdefault(b.key(), b)
                    jobs.append(Job(name, shape if std == "CL3.0" else f"{shape} CL1.2", e, b))
    return jobs, list(builds.values())


def run_all(builds, tools: Tools, jobs_n: int = 2, progress=None) -> None:
    by_name = {**TARGETS, **EXTRA_TARGETS}
    # the slow ones first, so that the workers finish together
    order = sorted(builds, key=lambda b: (by_name[b.target].vendor != "intel",
                                          b.source != "mlp.cl"))
    with ThreadPoolExecutor(max_workers=max(1, jobs_n)) as ex:
        for i, b in enumerate(ex.map(lambda b: run_build(b, by_name[b.target], tools), order)):
            if progress:
                progress(i + 1, len(order), b)


# ---- the resource table: builds paid once -----------------------------------------------------
# tests/test_gpu_builds.py builds TEST_PLAN. Its results are committed in TABLE, keyed by each
# build's inputs (the kernel file and every header it includes, the flags, the target and the
# OpenCL C version: ``source_key``) and stored with the compiler that built it
# (``compiler_of``). The tests take an entry whose key and compiler both match as built, and
# build the rest: on the machine that wrote the table nothing; after a kernel change the
# programs of the files it touched. ``--update-table`` rebuilds what is stale and rewrites
# the table; without ``--table`` this tool builds everything.
TABLE = ROOT / "tools" / "gpu_builds_table.json"
TABLE_FORMAT = 1
# (targets, shapes, programs per kernel file): every program of every shape on gfx1100 (clang:
# quick), every GPU-shape program on the no-spill targets and NVIDIA, and on the other targets
# the first GPU-shape program of each kernel file (every kernel builds there)
TEST_PLAN = ((("gfx1100",), SHAPES, None), (("tgllp",), ("gpu",), None),
             (("gfx1103", "gfx90a", "gfx942", "dg2", "sm_90"), ("gpu",), 1))
TEST_CL12 = ("gfx1100",)
LOG_CHARS = 4000            # a build log kept in the table is cut to this


def test_plan() -> tuple:
    """(jobs, builds) of TEST_PLAN."""
    jobs, todo = [], {}
    for targets, shapes, per_source in TEST_PLAN:
        jobs += plan(targets, shapes, set(TEST_CL12), per_source=per_source, builds=todo)[0]
    return jobs, list(todo.values())


def _source_text(source: str, seen=None) -> bytes:
    """cl/<source> and every header it includes (recursively, each once, in include order)."""
    seen = set() if seen is None else seen
    path = cl_dir() / source
    if source in seen or not path.is_file():
        return b""
    seen.add(source)
    text = path.read_bytes()
    out = [source.encode(), b"\0", text]
    for inc in re.findall(rb'^\s*#\s*include\s+"([^"]+)"', text, re.M):
        out.append(_source_text(inc.decode(), seen))
    return b"".join(out)


def _portable(text: str) -> str:
    """``text`` with the kernel folder's path (which differs between a checkout and an
    install) written as ``<cl>``."""
    return text.replace(str(cl_dir()), "<cl>")


def source_key(b: Build) -> str:
    """What a build's result depends on besides the compiler: the kernel file with its
    headers, the flags, the target and the OpenCL C version."""
    h = hashlib.sha256(_source_text(b.source))
    h.update(json.dumps([[_portable(f) for f in b.flags], b.target, b.std, b.raw]).encode())
    return h.hexdigest()[:24]


def compiler_of(target: str, tools: Tools) -> str:
    """The compiler (and its bitcode library) that builds for ``target`` here, in words."""
    t = TARGETS.get(target) or EXTRA_TARGETS[target]
    if t.vendor == "intel":
        return tools.versions.get("ocloc", "no ocloc")
    parts = [tools.versions.get("clang", "no clang")]
    if tools.libclc:
        bc = tools.libclc / (f"{t.device}-amdgcn-mesa-mesa3d.bc" if t.vendor == "amd"
                             else "nvptx64--nvidiacl.bc")
        parts.append(f"libclc {bc.name} {bc.stat().st_size if bc.is_file() else 0} B")
    if t.vendor == "nvidia":
        parts.append(tools.versions.get("ptxas", "no ptxas"))
    return "; ".join(parts)


def load_table(path: Path = TABLE) -> dict:
    """{source_key: entry} of the committed table ({} when there is none)."""
    try:
        d = json.loads(Path(path).read_text())
    except (OSError, ValueError):
        return {}
    return d.get("builds", {}) if d.get("format") == TABLE_FORMAT else {}


def apply_table(builds, table: dict, tools: Tools) -> dict:
    """Fill every build whose inputs and compiler match a table entry (``cached``); returns
    {"reused": n, "stale": [builds whose inputs are not in the table], "other_compiler":
    [builds whose entry was made by another compiler]}."""
    out = {"reused": 0, "stale": [], "other_compiler": []}
    for b in builds:
        e = table.get(source_key(b))
        if e is None:
            out["stale"].append(b)
        elif e["compiler"] != compiler_of(b.target, tools):
            out["other_compiler"].append(b)
        else:
            b.ok, b.log, b.kernels, b.seconds = e["ok"], e["log"], e["kernels"], e["seconds"]
            b.cached = True
            out["reused"] += 1
    return out


def write_table(builds, tools: Tools, path: Path = TABLE) -> None:
    entries = {}
    for b in builds:
        entries[source_key(b)] = {
            "source": b.source, "target": b.target, "std": b.std, "ok": b.ok,
            "compiler": compiler_of(b.target, tools), "seconds": round(b.seconds, 2),
            "log": _portable(b.log)[:LOG_CHARS], "kernels": b.kernels,
            "defines": [f for f in b.flags if f.startswith("-D")]}
    text = json.dumps({"format": TABLE_FORMAT, "made_by": "python tools/gpu_builds.py "
                       "--update-table", "compilers": tools.versions,
                       "builds": dict(sorted(entries.items()))}, indent=1, sort_keys=True)
    write_text(path, text + "\n")


# ---- reports ---------------------------------------------------------------------------------
def failures(jobs) -> list:
    """(source, defines, target, shape, log) of every job whose build failed."""
    return [(j.entry.source, j.entry.defines_dict(), j.target, j.shape, j.build.log)
            for j in jobs if not j.build.ok]


def gpu_shape_rows(jobs) -> dict:
    """{(target, source, kernel): worst figures over the GPU shape's programs} for the
    GPU_SHAPE_KERNELS: the most registers, spills, local memory, the lowest occupancy."""
    out = {}
    for j in jobs:
        if j.shape != "gpu" or not j.build.ok or j.entry.source not in GPU_SHAPE_KERNELS:
            continue
        for k in GPU_SHAPE_KERNELS[j.entry.source]:
            fig = j.build.kernels.get(k)
            if fig is None:
                continue
            row = out.setdefault((j.target, j.entry.source, k), {"programs": 0})
            row["programs"] += 1
            for key, v in fig.items():
                if not isinstance(v, (int, float)) or isinstance(v, bool):
                    continue
                if key in ("occupancy", "simd"):
                    row[key] = min(row.get(key, v), v)
                else:
                    row[key] = max(row.get(key, v), v)
    return out


def spills(jobs, targets=NO_SPILL_TARGETS, shapes=("gpu",), kernels=GPU_SHAPE_KERNELS) -> list:
    """(target, shape, source, kernel, figures, defines) of the listed kernels that spill."""
    out = []
    for j in jobs:
        if j.target not in targets or j.shape not in shapes or not j.build.ok:
            continue
        for k, fig in j.build.kernels.items():
            if kernels is not None and k not in kernels.get(j.entry.source, ()):
                continue
            if fig.get("spill"):
                out.append((j.target, j.shape, j.entry.source, k, fig, j.entry.defines_dict()))
    return out


def local_overflows(jobs) -> list:
    """(target, source, kernel, bytes) of kernels whose static local memory exceeds the
    target's (LOCAL_LIMIT)."""
    by_name = {**TARGETS, **EXTRA_TARGETS}
    out = set()
    for j in jobs:
        lim = LOCAL_LIMIT[by_name[j.target].vendor]
        for k, fig in j.build.kernels.items():
            if (fig.get("local") or 0) > lim:
                out.add((j.target, j.entry.source, k, fig["local"]))
    return sorted(out)


def _cell(vendor: str, f: dict) -> str:
    kib = lambda n: f"{n / 1024:.0f}K" if n else "0"   # noqa: E731
    if vendor == "amd":
        s = f"{f.get('vgpr', '?')}v {f.get('sgpr', '?')}s"
        if f.get("agpr"):
            s += f" {f['agpr']}a"
        s += f", {f.get('scratch', 0)} B scratch"
        if f.get("vgpr_spill") or f.get("sgpr_spill"):
            s += f" ({f.get('vgpr_spill', 0)}v {f.get('sgpr_spill', 0)}s spilled)"
        return s + (f", LDS {kib(f.get('local', 0))}, {f.get('occupancy', '?')} w"
                    f"{f.get('wave', '')}")
    if vendor == "intel":
        s = f"SIMD{f.get('simd', '?')} {f.get('grf', '?')} GRF"
        s += f", {f.get('spill_bytes', 0)} B spill"
        if f.get("private"):
            s += f" + {f['private']} B private"
        return s + f", SLM {kib(f.get('local', 0))}"
    if f.get("regs") is None:
        return "PTX only"
    s = f"{f['regs']} regs, {f.get('spill_bytes', 0)} B spill"
    if f.get("stack"):
        s += f" ({f['stack']} B stack)"
    return s + f", smem {kib(f.get('local', 0))}"


def markdown(jobs, targets, tools: Tools, command: str) -> str:
    by_name = {**TARGETS, **EXTRA_TARGETS}
    rows = gpu_shape_rows(jobs)
    lines = [f"Generated by `{command}`; compilers: "
             + "; ".join(f"{v}" for k, v in tools.versions.items() if k != "libclc") + ".", "",
             "GPU-shape kernels (the GPU tuning's programs; the worst figures over the "
             "programs that contain the kernel: most registers, spills and local memory, lowest "
             "occupancy). AMD: VGPRs v, SGPRs s (AGPRs a), scratch bytes per lane (spilled "
             "registers, when any, in brackets), LDS per work-group, occupancy in waves per "
             "SIMD (w32 / w64: waves of 32 or 64 work-items). Intel: the SIMD width IGC chose, "
             "GRF registers per thread, spill (and private) bytes per thread, SLM per "
             "work-group. NVIDIA (clang's PTX through ptxas): registers per thread, spill "
             "stores, shared memory per block.", ""]
    head = "| kernel | " + " | ".join(f"{n} ({by_name[n].what})" for n in targets) + " |"
    lines += [head, "|" + " --- |" * (len(targets) + 1)]
    for src, names in GPU_SHAPE_KERNELS.items():
        for k in names:
            cells = []
            for n in targets:
                f = rows.get((n, src, k))
                cells.append("-" if f is None else _cell(by_name[n].vendor, f))
            if any(c != "-" for c in cells):
                lines.append(f"| {src} {k} | " + " | ".join(cells) + " |")
    shapes = sorted({j.shape for j in jobs}, key=lambda s: (s.endswith("CL1.2"), s))
    lines += ["", f"Every program built, per target (shapes: {', '.join(shapes)}). Spilling: "
              "the GPU-shape kernels above that spill in the gpu shape / every kernel that "
              "spills in any program built (the CPU-shaped ones included).", "",
              "| target | compiles | failed | spilling | most local memory | compile s |",
              "| --- | --- | --- | --- | --- | --- |"]
    for n in targets:
        js = [j for j in jobs if j.target == n]
        bs = {id(j.build): j.build for j in js}.values()
        nf = sum(not b.ok for b in bs)
        sp_gpu = {(s, k) for _, _, s, k, _, _ in spills(js, (n,), ("gpu",))}
        sp_all = {(s, k) for _, _, s, k, _, _ in
                  spills(js, (n,), tuple({j.shape for j in js}), None)}
        loc = max(((f.get("local") or 0, f"{j.entry.source} {k}") for j in js
                   for k, f in j.build.kernels.items()), default=(0, "-"))
        secs = sum(b.seconds for b in bs)
        lines.append(f"| {n} | {len(bs)} | {nf} | {len(sp_gpu)} / {len(sp_all)} | "
                     f"{loc[0] / 1024:.1f} KiB ({loc[1]}) | {secs:.0f} |")
    return "\n".join(lines)


def as_text(md: str) -> str:
    """The markdown of ``markdown`` with its tables as aligned columns."""
    out, table = [], []

    def flush():
        if table:
            cells = [[c.strip() for c in row.strip().strip("|").split("|")] for row in table
                     if not set(row.replace("|", "").split()) <= {"---"}]
            widths = [max(len(r[i]) for r in cells if i < len(r))
                      for i in range(max(map(len, cells)))]
            out.extend("  ".join(c.ljust(w) for c, w in zip(r, widths)).rstrip() for r in cells)
            table.clear()
    for line in md.splitlines():
        if line.startswith("|"):
            table.append(line)
        else:
            flush()
            out.append(line)
    flush()
    return "\n".join(out)


def to_json(jobs, tools: Tools) -> dict:
    return {"compilers": tools.versions,
            "targets": {n: {"vendor": t.vendor, "device": t.device, "what": t.what,
                            "caps": {k: getattr(t.caps, k) for k in (
                                "platform", "type", "compute_units", "max_work_group_size",
                                "local_mem_size", "fp64", "float_atomics", "acq_rel")}}
                        for n, t in {**TARGETS, **EXTRA_TARGETS}.items()
                        if any(j.target == n for j in jobs)},
            "builds": [{"target": j.target, "shape": j.shape, "source": j.entry.source,
                        "defines": j.entry.defines_dict(), "uses": list(j.entry.uses),
                        "flags": list(j.build.flags), "std": j.build.std, "ok": j.build.ok,
                        "log": j.build.log, "seconds": round(j.build.seconds, 3),
                        "kernels": j.build.kernels} for j in jobs]}


def update_table(jobs_n: int = 2, quiet: bool = False) -> int:
    """--update-table: TEST_PLAN built (what is current taken from the table), the table
    rewritten with exactly its builds. Exit status 2 when a vendor's compiler is missing."""
    tools = find_tools()
    gone = {v: tools.missing(v) for v in ("amd", "intel", "nvidia")}
    if any(gone.values()):
        print(f"gpu_builds: cannot update the table: {gone} missing; run `{FIX}`",
              file=sys.stderr)
        return 2
    _, builds = test_plan()
    found = apply_table(builds, load_table(), tools)
    todo = [b for b in builds if not b.cached]
    t0 = time.perf_counter()
    run_all(todo, tools, jobs_n, None if quiet else lambda i, n, b: print(
        f"[{i}/{n}] {b.target} {b.std} {b.source} {'ok' if b.ok else 'FAILED'} "
        f"{b.seconds:.1f}s", file=sys.stderr, flush=True))
    write_table(builds, tools)
    print(f"gpu_builds: {TABLE.relative_to(ROOT)}: {len(builds)} builds, {found['reused']} "
          f"kept, {len(todo)} built in {time.perf_counter() - t0:.0f} s", file=sys.stderr)
    return 0


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                 formatter_class=argparse.RawDescriptionHelpFormatter,
                                 epilog="\n\n".join(__doc__.split("\n\n")[1:]))
    ap.add_argument("--targets", default=",".join(DEFAULT_TARGETS),
                    help=f"comma-separated, of {', '.join([*TARGETS, *EXTRA_TARGETS])} "
                         "(default: %(default)s)")
    ap.add_argument("--shapes", default=",".join(SHAPES),
                    help="comma-separated, of gpu, gpu-cpu, cpu (default: %(default)s)")
    ap.add_argument("--cl12", default="gfx1100",
                    help="targets also built as OpenCL C 1.2, comma-separated ('' none; "
                         "default: %(default)s)")
    ap.add_argument("--sources", default="", help="only these cl/ files, comma-separated")
    ap.add_argument("--per-source", type=int, default=None, metavar="N",
                    help="at most N programs per kernel file, target and shape (the first "
                         "asked): every kernel on every target, fewer define sets")
    ap.add_argument("--jobs", "-j", type=int, default=2, help="compiler processes at once")
    ap.add_argument("--json", metavar="OUT", help="write every build's figures there")
    ap.add_argument("--markdown", action="store_true", help="print the tables as markdown")
    ap.add_argument("--check", action="store_true",
                    help="also fail (exit 1) on GPU-shape spills on the --no-spill targets and "
                         "on local memory over a target's")
    ap.add_argument("--no-spill", default=",".join(NO_SPILL_TARGETS),
                    help="targets where --check allows no GPU-shape spill (default: %(default)s)")
    ap.add_argument("--quiet", "-q", action="store_true", help="no progress lines")
    ap.add_argument("--table", action="store_true",
                    help=f"take the builds whose inputs and compiler match an entry of "
                         f"{TABLE.relative_to(ROOT)} from it instead of building them")
    ap.add_argument("--update-table", action="store_true",
                    help="build what the tests build (TEST_PLAN; the target, shape and source "
                         "options are ignored), taking what is current from the table, and "
                         "rewrite the table")
    a = ap.parse_args(argv)
    if a.update_table:
        return update_table(a.jobs, a.quiet)
    targets = [t for t in a.targets.split(",") if t]
    unknown = [t for t in targets if t not in TARGETS and t not in EXTRA_TARGETS]
    shapes = [s for s in a.shapes.split(",") if s]
    if unknown or not set(shapes) <= set(SHAPES):
        ap.error(f"unknown targets {unknown} or shapes {shapes}")
    tools = find_tools()
    by_name = {**TARGETS, **EXTRA_TARGETS}
    for t in list(targets):
        gone = tools.missing(by_name[t].vendor)
        if gone:
            print(f"gpu_builds: skipping {t}: {gone} not found (install: {FIX})",
                  file=sys.stderr)
            targets.remove(t)
    if not targets:
        print(f"gpu_builds: no compiler for any target; run `{FIX}`", file=sys.stderr)
        return 2
    cl12 = {t for t in a.cl12.split(",") if t}
    jobs, builds = plan(targets, shapes, cl12, set(filter(None, a.sources.split(","))),
                        a.per_source)

    def progress(i, n, b):
        if not a.quiet:
            print(f"[{i}/{n}] {b.target} {b.std} {b.source} {'ok' if b.ok else 'FAILED'} "
                  f"{b.seconds:.1f}s", file=sys.stderr, flush=True)
    t0 = time.perf_counter()
    if a.table:
        found = apply_table(builds, load_table(), tools)
        if not a.quiet:
            print(f"gpu_builds: {found['reused']} of {len(builds)} builds from the table",
                  file=sys.stderr)
    run_all([b for b in builds if not b.cached], tools, a.jobs, progress)
    if not a.quiet:
        print(f"gpu_builds: {len(builds)} compiles in {time.perf_counter() - t0:.0f} s",
              file=sys.stderr)
    if a.json:
        Path(a.json).write_text(json.dumps(to_json(jobs, tools), indent=1, default=str) + "\n")
    command = "python tools/gpu_builds.py " + " ".join(argv if argv is not None else sys.argv[1:])
    md = markdown(jobs, targets, tools, command.strip())
    print(md if a.markdown else as_text(md))
    status = 0
    bad = failures(jobs)
    seen = set()
    for src, defs, tgt, shape, log in bad:
        key = (src, tuple(sorted(defs.items())), tgt, shape)
        if key in seen:
            continue
        seen.add(key)
        print(f"\nFAILED {src} on {tgt} ({shape}) with {defs}:\n{log}", file=sys.stderr)
        status = 1
    if a.check:
        for tgt, shape, src, k, fig, defs in spills(jobs, tuple(a.no_spill.split(","))):
            print(f"SPILLS {src} {k} on {tgt} ({shape}): {fig} with {defs}", file=sys.stderr)
            status = 1
        for tgt, src, k, n in local_overflows(jobs):
            print(f"LOCAL {src} {k} on {tgt}: {n} bytes of local memory", file=sys.stderr)
            status = 1
    return status


if __name__ == "__main__":
    sys.exit(main())
