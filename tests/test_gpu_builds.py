"""Every kernel builds offline for AMD, Intel and NVIDIA GPUs (tools/gpu_builds.py), with the
defines clrf uses there: no build fails on any target, no GPU-shape kernel (the fused MLP's GPU
tiling, the hash encoding, the grid render forward / backward, the splat rasteriser forward /
backward) spills registers on gfx1100 (RDNA3) or tgllp (Xe-LP), nothing needs fp64 (Intel's
Xe-LP and Xe-HPG have none: their compiler rejects any double), every file builds as OpenCL C
1.2 too, and local memory fits every target's.

The compilers come with ``bash tools/setup.sh gpucc`` (clang-19, libclc-19's bitcode in
.gpucc/, Intel's ocloc; NVIDIA's ptxas from the CUDA toolkit when present); without them the
build tests skip, saying so. The catalog tests (clrf/training/catalog.py lists every program:
each kernel file, each define the kernels read) need no compiler.

The builds (gb.TEST_PLAN): on gfx1100 every program of the three shapes (the GPU's own tuning,
the same GPU with CLRF_FORCE_GPU_KERNELS=0, a CPU device's tuning), as OpenCL C 3.0 and 1.2;
on tgllp every program of the GPU shape; on gfx1103, gfx90a, gfx942, dg2 and sm_90 the first
GPU-shape program of each kernel file. Each is paid once: their results are committed in
tools/gpu_builds_table.json, keyed by the kernel file with its headers, the flags, the target
and the OpenCL C version, and stored with the compiler that made them. The module takes an entry
whose key and compiler match as built and builds the rest (two compiler processes at a time):
nothing where the table is current, about 5 minutes on 2 cores from nothing. A test fails when
the table misses a build's key (a kernel changed): ``python tools/gpu_builds.py --update-table``
rebuilds what changed and rewrites it. ``python tools/gpu_builds.py --check`` builds every
program everywhere, with no table.
"""
import re
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT / "tools"))

import gpu_builds as gb  # noqa: E402

CL = ROOT / "cl"
CL12_TARGETS = gb.TEST_CL12
NO_FP64_TARGETS = ("tgllp", "dg2")

# Knobs (defines read with a default) that no program of the library sets, and why.
LEFT_AT_DEFAULT = {
    "CLRF_INLINE": "how helpers are inlined (common.h); set only by hand, for comparison",
    "DW_PREFETCH_AHEAD": "a constant of the CPU weight gradient's prefetch (mlp.cl)",
    "PDF_PAD": "NeRF's weight padding, a constant of sample.cl",
    "HASH_T_STOP": "the hash render's termination, a constant of hash_march.cl",
    "SIGMA_EXP_MAX": "trunc_exp's clamp, a constant of mlp_net.h (the host mirrors it)",
    "GPU_TM": "the GPU tiling's tile fields are set only by the tuner's candidates "
              "(clrf/mlp/tiling.py gpu_candidates) and its cache",
    "GPU_TN": "ditto", "GPU_NC": "ditto", "GPU_BK": "ditto", "GPU_DW_BJ": "ditto",
    "GPU_DW_BS": "ditto", "GPU_DW_TJ": "ditto (not a tuned field)",
    "GPU_DW_TK": "ditto (not a tuned field)",
    "REDUCE_FP64": "reduce.h's switch, set by the pyopencl reductions' preambles "
                   "(clrf/training/metrics.py, clrf/splat/loss.py), not by a cl/*.cl program",
}


def kernel_defines() -> set:
    """The names the kernels of cl/ read from the host: those tested in #if / #ifdef /
    #ifndef / #elif that the sources never #define, and those they #define only inside an
    ``#ifndef NAME`` block (a knob with its default). Header guards, names the sources define
    for themselves and the compilers' own (__SPIR__ ...) are left out."""
    tested, knobs, internal = set(), set(), set()
    for f in sorted(CL.iterdir()):
        if f.suffix not in (".cl", ".h"):
            continue
        stack = []                                  # the names each open #ifndef tests
        for line in f.read_text().splitlines():
            m = re.match(r"\s*#\s*(ifdef|ifndef|if|elif|else|endif|define)\b\s*(.*)", line)
            if not m:
                continue
            what, rest = m.group(1), re.sub(r"/\*.*?(\*/|$)|//.*", "", m.group(2))
            if what in ("ifdef", "ifndef", "if", "elif"):
                names = set(re.findall(r"\b[A-Za-z_]\w*\b", rest)) - {"defined"}
                # (names starting with __ are the compiler's: __SPIR__, __opencl_c_...)
                tested |= {n for n in names if n.isupper() and not n.startswith("__")}
                if what != "elif":
                    stack.append(rest.strip() if what == "ifndef" else None)
            elif what == "endif" and stack:
                stack.pop()
            elif what == "define":
                d = re.match(r"(\w+)(\(?)\s*(.*)", rest)
                name, value = d.group(1), d.group(3).strip()
                if name in stack and not value:
                    internal.add(name)              # a header guard
                    continue
                (knobs if name in stack else internal).add(name)
    return (tested - internal) | knobs


def catalog(targets=gb.DEFAULT_TARGETS, shapes=gb.SHAPES) -> list:
    """(target, entry, flags) over the targets and shapes."""
    out = []
    for name in targets:
        t = gb.TARGETS[name]
        for shape in shapes:
            for e in gb.library_programs(*gb.shape_device(t, shape)):
                out.append((name, e, gb.target_flags(t, e)))
    return out


def test_catalog_lists_every_kernel_file():
    files = {e.source for _, e, _ in catalog()}
    want = {p.name for p in CL.glob("*.cl")}
    assert want <= files, f"no program of the library builds {sorted(want - files)}"


def test_catalog_sets_every_define_the_kernels_read():
    knobs = kernel_defines()
    assert {"SH_DEGREE", "MLP_GPU", "GRAD_SLOTS", "HASH_GRAD_OWNED", "TILE",
            "CLRF_HAS_FP64", "SSIM_W0"} <= knobs           # the scan finds knobs
    assert not knobs & {"CLRF_COMMON_H", "ACT_RELU", "GPU_LOCAL_BYTES"}
    set_by = set()
    for _, e, flags in catalog():
        set_by |= {f[2:].split("=")[0] for f in flags if f.startswith("-D")}
    missing = knobs - set_by - set(LEFT_AT_DEFAULT)
    assert not missing, (f"defines the kernels read that no program of the catalog sets: "
                         f"{sorted(missing)} (clrf/training/catalog.py, Kind.programs; or add "
                         f"them to LEFT_AT_DEFAULT with the reason)")
    stale = set(LEFT_AT_DEFAULT) - knobs
    assert not stale, f"LEFT_AT_DEFAULT names what no kernel reads: {sorted(stale)}"


def test_catalog_follows_the_device():
    """GPU targets get the GPU shapes and their own capabilities; no fp64 on Intel, and the
    grid backward without its per-cell merge there."""
    for name, e, flags in catalog(shapes=("gpu",)):
        d = e.defines_dict()
        if e.source == "mlp.cl":
            assert d.get("MLP_GPU") == 1
            assert d["GPU_LOCAL_MAX"] == gb.TARGETS[name].caps.local_mem_size
        if e.source == "hash.cl":
            assert d["HASH_GRAD_OWNED"] == 0
        if e.source == "grid_render.cl":
            assert d["GRAD_SLOTS"] == 0
            # Intel GPUs add each sample's gradients (Tuning.grad_merge off); the rest merge
            assert d.get("GRAD_MERGE", 1) == (0 if gb.TARGETS[name].vendor == "intel" else 1)
        if not e.raw:
            fp64 = "-DCLRF_HAS_FP64=1" in flags
            assert fp64 == (name not in NO_FP64_TARGETS), (name, e.source)
    cpu = [e for _, e, _ in catalog(("gfx1100",), ("cpu",))]
    assert any(e.defines_dict().get("GRAD_SLOTS", 0) > 0 for e in cpu)


# ---- the builds ------------------------------------------------------------------------------
@pytest.fixture(scope="module")
def builds():
    tools = gb.find_tools()
    gone = {v: tools.missing(v) for v in ("amd", "intel", "nvidia")}
    if any(gone.values()):
        pytest.skip("offline GPU compilers missing ("
                    + "; ".join(f"{v}: {g}" for v, g in gone.items() if g)
                    + "): run `bash tools/setup.sh gpucc`")
    jobs, todo = gb.test_plan()
    found = gb.apply_table(todo, gb.load_table(), tools)
    built = [b for b in todo if not b.cached]
    gb.run_all(built, tools, jobs_n=2)
    print(f"gpu builds: {found['reused']} of {len(todo)} from {gb.TABLE.name}, {len(built)} "
          f"built ({len(found['other_compiler'])} by another compiler there)")
    return jobs


def test_the_resource_table_is_current():
    """Every build of the plan has an entry in the committed table (needs no compiler): a
    kernel, header or define changed without the table being rebuilt fails here, with the
    command that rebuilds what changed."""
    _, todo = gb.test_plan()
    table = gb.load_table()
    assert table, f"{gb.TABLE} is missing or unreadable"
    stale = sorted({(b.source, b.target, b.std) for b in todo
                    if gb.source_key(b) not in table})
    assert not stale, (f"{len(stale)} builds are not in {gb.TABLE.name} (first: {stale[:5]}): "
                       f"run `python tools/gpu_builds.py --update-table` and commit it")
    assert len(table) == len({gb.source_key(b) for b in todo}), \
        "the table holds builds the plan no longer has: --update-table rewrites it"


def test_a_table_entry_is_taken_only_for_the_same_inputs_and_compiler():
    _, todo = gb.test_plan()
    b = todo[0]
    tools = gb.Tools("clang-19", None, "ocloc", None, {"clang": "clang A", "ocloc": "ocloc A"})
    entry = {"ok": True, "log": "", "kernels": {"k": {"spill": 0}}, "seconds": 1.0,
             "compiler": gb.compiler_of(b.target, tools)}
    twin = gb.Build(b.source, b.flags, b.target, b.std, b.raw)
    found = gb.apply_table([twin], {gb.source_key(b): entry}, tools)
    assert found["reused"] == 1 and twin.cached and twin.kernels == {"k": {"spill": 0}}
    # another define, another OpenCL C version, another compiler: built again
    other = gb.Build(b.source, b.flags + ("-DEXTRA=1",), b.target, b.std, b.raw)
    assert gb.source_key(other) != gb.source_key(b)
    assert gb.source_key(gb.Build(b.source, b.flags, b.target, "CL1.2", b.raw)) != \
        gb.source_key(b)
    newer = gb.Tools("clang-19", None, "ocloc", None, {"clang": "clang B", "ocloc": "ocloc B"})
    again = gb.Build(b.source, b.flags, b.target, b.std, b.raw)
    found = gb.apply_table([again], {gb.source_key(b): entry}, newer)
    assert not again.cached and found["other_compiler"] == [again]


@pytest.mark.parametrize("target", gb.DEFAULT_TARGETS)
def test_every_program_builds(builds, target):
    bad = [(s, d, sh, log) for s, d, t, sh, log in gb.failures(builds) if t == target]
    assert not bad, "\n\n".join(f"{s} ({sh}) {d}:\n{log}" for s, d, sh, log in bad[:5])
    files = {j.entry.source for j in builds if j.target == target}
    want = {p.name for p in CL.glob("*.cl")} - ({"ptx_probe.cl"}
                                               if gb.TARGETS[target].vendor != "nvidia" else set())
    assert want <= files
    for j in builds:
        if j.target == target and j.build.ok:
            assert j.build.kernels, f"{j.entry.source}: no kernel figures read"


@pytest.mark.parametrize("target", gb.NO_SPILL_TARGETS)
def test_no_gpu_shape_kernel_spills(builds, target):
    rows = [r for r in gb.gpu_shape_rows(builds) if r[0] == target]
    assert {(s, k) for _, s, k in rows} == {(s, k) for s, ks in gb.GPU_SHAPE_KERNELS.items()
                                            for k in ks}
    found = gb.spills(builds, (target,))
    assert not found, "\n".join(f"{s} {k}: {f} ({d})" for _, _, s, k, f, d in found)


def test_nothing_needs_fp64(builds):
    """Intel's Xe-LP and Xe-HPG have no fp64: their compiler rejects a double (a canary
    kernel shows it does), and every program built there with CLRF_HAS_FP64=0."""
    canary = Path(__file__).parent / "fixtures" / "fp64_canary.cl"
    tools = gb.find_tools()
    b = gb.run_build(gb.Build(str(canary), (), "tgllp", "CL3.0"), gb.TARGETS["tgllp"], tools)
    assert not b.ok and "double" in b.log
    for t in NO_FP64_TARGETS:
        js = [j for j in builds if j.target == t and not j.entry.raw]
        assert js and all("-DCLRF_HAS_FP64=0" in j.build.flags for j in js)
        assert all(j.build.ok for j in js)


def test_every_file_builds_as_opencl_c_1_2(builds):
    js = [j for j in builds if j.build.std == "CL1.2"]
    assert {j.entry.source for j in js} == {p.name for p in CL.glob("*.cl")} - {"ptx_probe.cl"}
    bad = [j for j in js if not j.build.ok]
    assert not bad, "\n\n".join(f"{j.entry.source} {j.entry.defines_dict()}:\n{j.build.log}"
                                for j in bad[:5])


def test_local_memory_fits_every_target(builds):
    assert not gb.local_overflows(builds)
    biggest = max((f.get("local") or 0) for j in builds for f in j.build.kernels.values())
    assert biggest > 0                          # the figures are read
