"""Device choice by measurement: ranking, cache, slow-driver detection, `clrf devices`.

Everything but the last test uses fake devices and fake probe figures; the last probes the real
devices once into a temporary cache.
"""
import json
from types import SimpleNamespace

import numpy as np
import pyopencl as cl
import pytest

import clrf.runtime.device as device
import clrf.runtime.device_probe as dp
from clrf.cli.main import main as cli_main
from clrf.runtime.device_probe import Candidate, Probe

DEBIAN = "OpenCL 3.0 PoCL 3.1+debian  Linux, None+Asserts, RELOC, SPIR, LLVM 15.0.6"
PIP = "OpenCL 3.0 PoCL 3.0-rc2  Linux, Release, RELOC, LLVM 14.0.6"
POCL = "Portable Computing Language"


def cand(pi, gflops, type_="cpu", name="pthread-haswell-AMD EPYC", error=None, di=0,
         version=DEBIAN, cus=2, mhz=2445):
    return Candidate(pi, di, type_, name, POCL if type_ == "cpu" else "NVIDIA CUDA", version,
                     "AuthenticAMD" if type_ == "cpu" else "NVIDIA", cus, mhz,
                     Probe(error, gflops if error is None else 0.0))


def specs(cands):
    return [c.spec for c in cands]


# ---- ranking -----------------------------------------------------------------------------------

def test_rank_faster_platform_wins_over_icd_order():
    # the two-PoCL machine: pip's generic-target PoCL listed first, the distribution's second
    cands = [cand(0, 5.3, name="pthread-AMD EPYC", version=PIP), cand(1, 65.0)]
    assert specs(dp.rank(cands)) == ["1:0", "0:0"]
    assert "fastest measured, 12.3x the next (0:0, 5.3 GFLOP/s)" == dp.choice_reason(
        dp.rank(cands))


def test_rank_gpu_only_when_faster():
    assert specs(dp.rank([cand(0, 60.0), cand(1, 900.0, "gpu")])) == ["1:0", "0:0"]
    # an emulated or weak GPU that measures slower than the CPU ranks below it
    assert specs(dp.rank([cand(0, 60.0), cand(1, 20.0, "gpu")])) == ["0:0", "1:0"]


def test_rank_ties_go_to_icd_order_and_unusable_are_dropped():
    cands = [cand(2, 100.0), cand(0, 95.0), cand(1, 0, error="unknown target CPU")]
    ranked = dp.rank(cands)
    assert specs(ranked) == ["0:0", "2:0"]          # 95 is within 10% of 100: platform order
    assert dp.choice_reason(ranked).startswith("within 10% of 2:0 (100.0 GFLOP/s)")
    assert dp.choice_reason(ranked[1:]) == "the only working device"
    assert dp.rank([cand(0, 0, error="x")]) == []
    # outside the tie band the figure decides
    assert specs(dp.rank([cand(0, 80.0), cand(1, 100.0)])) == ["1:0", "0:0"]


# ---- fake devices behind select_device ---------------------------------------------------------

def fake_dev(name, version, type_="cpu", mhz=2445):
    plat = SimpleNamespace(name=POCL if type_ == "cpu" else "NVIDIA CUDA", version=version)
    return SimpleNamespace(
        name=name, platform=plat, version=version, driver_version=version.split()[3],
        type=cl.device_type.CPU if type_ == "cpu" else cl.device_type.GPU,
        vendor="AuthenticAMD" if type_ == "cpu" else "NVIDIA", max_compute_units=2,
        max_clock_frequency=mhz, extensions="cl_khr_fp64 cl_khr_int64_base_atomics",
        max_work_group_size=4096, local_mem_size=512 * 1024, global_mem_size=2 ** 34,
        max_mem_alloc_size=2 ** 33, native_vector_width_float=8 if type_ == "cpu" else 1)


@pytest.fixture
def machine(monkeypatch):
    """Fake platforms: set ``m.devs`` to [(cl-like device, Probe)] in ICD order (one per platform)."""
    m = SimpleNamespace(devs=[], measured=[])

    def fake_list():
        return [(pi, 0, d) for pi, (d, _) in enumerate(m.devs)]

    def fake_probe(dev, refresh=False, measure_missing=True):
        m.measured.append(dev.name)
        return next(p for d, p in m.devs if d is dev)

    monkeypatch.setattr(device, "list_devices", fake_list)
    monkeypatch.setattr(device, "probe", fake_probe)
    monkeypatch.setattr(device, "cpu_flags", lambda: frozenset())
    monkeypatch.setattr(dp, "_warned", set())
    monkeypatch.delenv("CLRF_DEVICE", raising=False)
    return m


def two_pocl(m):
    m.devs = [(fake_dev("pthread-AMD EPYC", PIP), Probe(None, 5.3)),
              (fake_dev("pthread-haswell-AMD EPYC", DEBIAN), Probe(None, 65.0))]


def test_select_picks_faster_pocl_and_env_overrides(machine, monkeypatch, capsys):
    two_pocl(machine)
    assert device.select_device()[:2] == (1, 0)
    assert capsys.readouterr().err == ""            # the chosen device is fine: no warning
    monkeypatch.setenv("CLRF_DEVICE", "0:0")
    assert device.select_device()[:2] == (0, 0)     # CLRF_DEVICE beats the measurement
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "generic CPU target" in err
    assert "CLRF_DEVICE=1:0" in err and "apt-get install pocl-opencl-icd" in err
    device.select_device()
    assert capsys.readouterr().err == ""            # once per process
    assert device.select_device("cpu")[:2] == (1, 0)   # an explicit argument beats CLRF_DEVICE


def test_select_by_type(machine, monkeypatch):
    machine.devs = [(fake_dev("pthread-haswell-AMD EPYC", DEBIAN), Probe(None, 65.0)),
                    (fake_dev("NVIDIA T4", "OpenCL 3.0 CUDA 12.2.1", "gpu"), Probe(None, 30.0))]
    assert device.select_device()[:2] == (0, 0)          # the GPU measures slower
    assert device.select_device("gpu")[:2] == (1, 0)     # asked for by type
    machine.measured.clear()
    monkeypatch.setenv("CLRF_DEVICE", "cpu")
    assert device.select_device()[:2] == (0, 0)
    assert machine.measured == ["pthread-haswell-AMD EPYC"]   # the GPU is not probed


def test_select_errors(machine):
    machine.devs = [(fake_dev("pthread-AMD EPYC", PIP), Probe("error: unknown target CPU 'znver5'")),
                    (fake_dev("pthread-haswell-AMD EPYC", DEBIAN), Probe(None, 65.0))]
    with pytest.raises(device.DeviceError, match="is unusable.*znver5"):
        device.select_device("0:0")
    with pytest.raises(device.DeviceError, match="no device 3:0"):
        device.select_device("3:0")
    with pytest.raises(device.DeviceError, match="no working gpu"):
        device.select_device("gpu")
    assert device.select_device()[:2] == (1, 0)
    machine.devs = machine.devs[:1]
    with pytest.raises(device.DeviceError, match="(?s)Rejected.*znver5.*pocl-opencl-icd"):
        device.select_device()


ZEN4 = ("AuthenticAMD", 25, 17)     # the AMD EPYC (Genoa) where pip's PoCL crashed clrf


def test_pips_pocl_is_refused_on_zen4_without_being_run(machine, monkeypatch):
    """pip's PoCL 3.0 compiling for a generic target passed its self-check on a Zen 4 and then
    died with SIGSEGV in the grid renderer: there it is refused with the reason, never run."""
    monkeypatch.setattr(dp, "cpu_id", lambda: ZEN4)
    monkeypatch.setattr(dp, "measure", lambda dev: pytest.fail("a known crash was probed"))
    pr = dp.probe(fake_dev("pthread-AMD EPYC", PIP))
    assert not pr.ok
    assert "Zen 4" in pr.error and "model 17" in pr.error and "SIGSEGV" in pr.error
    assert "pocl-opencl-icd" in pr.error                     # the fix
    # the same driver compiling for a named CPU, another PoCL, other CPUs: not refused
    assert dp.known_crash(PIP, "pthread-haswell-AMD EPYC", ZEN4) is None
    assert dp.known_crash(DEBIAN, "pthread-AMD EPYC", ZEN4) is None
    for cpu in [("AuthenticAMD", 25, 1), ("AuthenticAMD", 25, 0x21), ("AuthenticAMD", 26, 2),
                ("GenuineIntel", 6, 85), ("", -1, -1)]:
        assert dp.known_crash(PIP, "pthread-AMD EPYC", cpu) is None, cpu
    for model in (0x11, 0x61, 0x74, 0xa0):
        assert dp.known_crash(PIP, "pthread-AMD EPYC", ("AuthenticAMD", 25, model))
    # asked for by its index: one error naming the reason; never the default
    machine.devs = [(fake_dev("pthread-AMD EPYC", PIP), pr),
                    (fake_dev("pthread-haswell-AMD EPYC", DEBIAN), Probe(None, 65.0))]
    with pytest.raises(device.DeviceError, match="0:0 is unusable .known to crash here.*Zen 4"):
        device.select_device("0:0")
    assert device.select_device()[:2] == (1, 0)


def test_cpu_id_reads_this_host():
    vendor, family, model = dp.cpu_id()
    assert isinstance(family, int) and isinstance(model, int)
    assert (family >= 0) == bool(vendor)


INTEL = "Intel(R) OpenCL"
RUSTICL = "rusticl"


def named(platform, name, version, gflops, type_="cpu"):
    d = fake_dev(name, version, type_)
    d.platform = SimpleNamespace(name=platform, version=version)
    return d, Probe(None, gflops)


def test_select_by_implementation_name(machine, monkeypatch):
    # rusticl listed first (RUSTICL_ENABLE), then Intel, then two PoCLs: the name finds the
    # implementation wherever it sits, and the fastest of its devices
    machine.devs = [named(RUSTICL, "llvmpipe", "OpenCL 3.0 Mesa 22.3.6 x", 40.0),
                    named(INTEL, "AMD EPYC", "OpenCL 3.1 LINUX 2026.22", 230.0),
                    (fake_dev("pthread-AMD EPYC", PIP), Probe(None, 5.3)),
                    (fake_dev("pthread-haswell-AMD EPYC", DEBIAN), Probe(None, 234.0))]
    assert device.select_device("intel")[:2] == (1, 0)
    assert device.select_device("INTEL:cpu")[:2] == (1, 0)
    assert device.select_device("rusticl")[:2] == (0, 0)
    assert device.select_device("pocl")[:2] == (3, 0)        # the faster of the two PoCLs
    assert device.choose_device("intel").reason == "requested as intel"
    assert device.choose_device("pocl").reason.startswith("requested as pocl; fastest")
    monkeypatch.setenv("CLRF_DEVICE", "intel")
    assert device.select_device()[:2] == (1, 0)
    with pytest.raises(device.DeviceError, match="(?s)'nvidia'.*here: intel, pocl, rusticl"):
        device.select_device("nvidia")
    with pytest.raises(device.DeviceError, match="'intel:gpu'.*no such device"):
        device.select_device("intel:gpu")
    with pytest.raises(device.DeviceError, match="after ':' must be one of cpu, gpu"):
        device.select_device("intel:fast")


def test_clrf_devices_shows_figures_default_and_reason(machine, capsys):
    two_pocl(machine)
    assert cli_main(["devices"]) == 0
    out = capsys.readouterr().out
    assert "5.3 GFLOP/s fp32 FMA" in out and "65.0 GFLOP/s fp32 FMA" in out
    assert ("default (CLRF_DEVICE=unset): 1:0 'pthread-haswell-AMD EPYC' (PoCL 3.1+debian), "
            "65.0 GFLOP/s: fastest measured, 12.3x the next (0:0, 5.3 GFLOP/s)") in out
    slow = [ln for ln in out.splitlines() if "SLOW" in ln]
    assert len(slow) == 2 and "generic CPU target" in slow[0] and "12x slower than 1:0" in slow[1]
    assert "advice" not in out                      # the default is not the slow one


def test_clrf_devices_check_exit_status(machine, capsys):
    two_pocl(machine)
    assert cli_main(["devices", "--check"]) == 0
    assert "default device 1:0" in capsys.readouterr().out
    machine.devs = machine.devs[:1]                 # only pip's generic-target PoCL
    assert cli_main(["devices", "--check"]) == 3
    assert "apt-get install pocl-opencl-icd" in capsys.readouterr().err
    machine.devs = [(fake_dev("pthread-AMD EPYC", PIP), Probe("error: unknown target CPU"))]
    assert cli_main(["devices", "--check"]) == 1


def test_clrf_devices_check_slow_pocl_beside_a_faster_driver(machine, capsys):
    # pip's generic-target PoCL beside Intel's runtime: Intel is the (fine) default, but the
    # check still asks for the distribution's PoCL, which runs the grid kernels fastest
    intel = fake_dev("AMD EPYC", "OpenCL 3.0 LINUX 2026.22.10.0.01_160000")
    machine.devs = [(intel, Probe(None, 128.0)),
                    (fake_dev("pthread-AMD EPYC", PIP), Probe(None, 22.0))]
    assert cli_main(["devices", "--check"]) == 3
    out, err = capsys.readouterr()
    assert "default device 0:0 'AMD EPYC'" in out
    assert "1:0 'pthread-AMD EPYC'" in err and "apt-get install pocl-opencl-icd" in err
    machine.devs.append((fake_dev("pthread-haswell-AMD EPYC", DEBIAN), Probe(None, 65.0)))
    assert cli_main(["devices", "--check"]) == 0    # a PoCL that compiles for this CPU is there


# ---- slow-driver detection ---------------------------------------------------------------------

@pytest.mark.parametrize("name, target", [
    ("pthread-haswell-AMD EPYC", "haswell"),
    ("pthread-skylake-avx512-AMD EPYC", "skylake-avx512"),
    ("cpu-znver3-AMD Ryzen 9 5900X 12-Core Processor", "znver3"),
    ("cpu-x86-64-v3-Intel(R) Xeon(R) CPU", "x86-64-v3"),
    ("pthread-AMD EPYC", ""),
    ("pthread-Intel(R) Xeon(R) Platinum 8375C CPU @ 2.90GHz", ""),
    ("NVIDIA GeForce RTX 3090", None),
    ("Intel(R) Xeon(R) CPU E5-2680", None),
])
def test_pocl_cpu_target(name, target):
    assert dp.pocl_cpu_target(name) == target


def test_slow_reasons():
    good, generic = cand(0, 65.0), cand(1, 5.3, name="pthread-AMD EPYC", version=PIP)
    avx2 = frozenset({"sse2", "avx", "avx2", "fma"})
    # 2 units x 2.445 GHz x 8 lanes x 2 pipes x 2 flop = 156 GFLOP/s
    assert dp.estimated_peak_gflops(good, avx2) == pytest.approx(156.48)
    assert dp.estimated_peak_gflops(cand(0, 1.0, "gpu"), avx2) is None
    assert dp.slow_reasons(good, [good, generic], avx2) == []
    why = dp.slow_reasons(generic, [good, generic], avx2)
    assert len(why) == 3 and "generic" in why[0] and "peak of 156" in why[1] and "12x" in why[2]
    # a CPU-specific target that still measures far below the CPU's peak is flagged too
    odd = cand(0, 8.0, name="pthread-znver3-AMD EPYC")
    assert dp.slow_reasons(odd, [odd], avx2) == [
        "measures 8.0 GFLOP/s, under 8% of this CPU's estimated peak of 156"]
    assert dp.slow_warning(odd, [odd], frozenset()) is None      # no flags: peak unknown
    # a different CPU model is not a sibling
    other = cand(1, 200.0, name="pthread-znver3-AMD EPYC 9B14")
    assert dp.faster_sibling(good, [good, other]) is None
    assert dp.slow_warning(generic, [generic], frozenset()) == (
        "clrf: warning: device 1:0 'pthread-AMD EPYC' (PoCL 3.0-rc2) compiles for a generic CPU "
        "target (no LLVM CPU in the device name); install the distribution's PoCL "
        "(Debian/Ubuntu: `apt-get install pocl-opencl-icd`)")


# ---- the cache ---------------------------------------------------------------------------------

@pytest.fixture
def cache(monkeypatch, tmp_path):
    """An empty cache directory and a fresh in-process memo; ``measure`` counts its calls."""
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path))
    monkeypatch.setattr(dp, "_memo", {})
    calls = []

    def fake_measure(dev):
        calls.append(dev.name)
        return Probe(None, 42.5, 0.2, "2026-11-22T21:00:00Z")

    monkeypatch.setattr(dp, "measure", fake_measure)
    return SimpleNamespace(path=tmp_path / "clrf" / "devices.json", calls=calls)


def test_cache_round_trip(cache, monkeypatch):
    dev = fake_dev("pthread-haswell-AMD EPYC", DEBIAN)
    p = dp.probe(dev)
    assert (p.gflops, p.cached, cache.calls) == (42.5, False, ["pthread-haswell-AMD EPYC"])
    assert dp.probe(dev) is p                                   # memo: no file read
    monkeypatch.setattr(dp, "_memo", {})                        # a new process
    q = dp.probe(dev)
    assert (q.gflops, q.when, q.cached, len(cache.calls)) == (42.5, p.when, True, 1)
    entry = json.loads(cache.path.read_text())["devices"][dp.device_key(dev)]
    assert entry["probe"] == dp.probe_version() and entry["error"] is None
    dp.probe(dev, refresh=True)
    assert len(cache.calls) == 2
    # another driver version is another key
    dev2 = fake_dev("pthread-haswell-AMD EPYC", DEBIAN.replace("3.1+debian", "3.2+debian"))
    assert dp.probe(dev2, measure_missing=False) is None
    assert not list(cache.path.parent.glob(".devices.*"))      # no temporaries left behind


@pytest.mark.parametrize("content", [
    "{not json", "[]", '{"devices": 3}',
    '{"devices": {"KEY": {"probe": "VERSION", "gflops": "fast", "error": null}}}',
    '{"devices": {"KEY": {"probe": "VERSION", "gflops": -1.0, "error": null}}}',
    '{"devices": {"KEY": {"probe": "stale", "gflops": 1.0, "error": null}}}',
])
def test_corrupt_or_stale_cache_is_ignored_and_rewritten(cache, content):
    dev = fake_dev("pthread-haswell-AMD EPYC", DEBIAN)
    cache.path.parent.mkdir(parents=True)
    cache.path.write_text(content.replace("KEY", dp.device_key(dev).replace('"', '\\"'))
                          .replace("VERSION", dp.probe_version()))
    assert dp.probe(dev).gflops == 42.5 and cache.calls == [dev.name]
    entries = json.loads(cache.path.read_text())["devices"]
    assert list(entries) == [dp.device_key(dev)] and entries[dp.device_key(dev)]["gflops"] == 42.5


def test_unwritable_cache_still_probes(cache, monkeypatch, tmp_path):
    blocker = tmp_path / "file"
    blocker.write_text("")
    monkeypatch.setenv("XDG_CACHE_HOME", str(blocker))          # clrf/ cannot be made under a file
    assert dp.probe(fake_dev("pthread-haswell-AMD EPYC", DEBIAN)).gflops == 42.5


def test_fma_reference_matches_the_iteration():
    """The closed form the probe checks the kernel against equals the float64 iteration of
    every lane of every chain of each work-item (lanes, chains and work-items all differ)."""
    c = dp.probe_coefficients().astype(np.float64)
    m, a, starts, di = c[:8], c[8:16], c[16:24], c[24]
    n = 70                                     # past 64: the per-work-item offset wraps
    base = (np.float32(di) * (np.arange(n) & 63).astype(np.float32)).astype(np.float64)
    x = starts[None, :, None] + base[:, None, None] + 0 * m[None, None, :]   # [n, chain, lane]
    for _ in range(300):
        x = x * m + a
    ref = dp.fma_reference(300, n)
    assert ref == pytest.approx(x.sum(axis=(1, 2)), rel=1e-12)
    assert len(set(np.round(ref, 9))) == 64     # no two work-items of a group compute alike
    assert len(set(m)) == 8 and len(set(a)) == 8


def test_physical_peak_refuses_an_impossible_figure(monkeypatch):
    """A CPU device's peak is compute units x clock x lanes x 2 pipes x 2 flop; the probe
    refuses a figure above OVER_PEAK times it."""
    import pyopencl as cl
    monkeypatch.setattr(dp, "cpu_flags", lambda: frozenset({"sse2", "avx2", "fma", "avx512f"}))

    class Dev:
        type = cl.device_type.CPU
        max_compute_units = 2
        max_clock_frequency = 2000
    assert dp.physical_peak_gflops(Dev()) == pytest.approx(2 * 2.0 * 16 * 2 * 2)
    Dev.type = cl.device_type.GPU
    assert dp.physical_peak_gflops(Dev()) is None


# ---- the real devices --------------------------------------------------------------------------

@pytest.mark.slow
def test_real_devices_probe_and_cache(monkeypatch, tmp_path):
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path))
    monkeypatch.setattr(dp, "_memo", {})
    devs = device.list_devices()
    if not devs:
        pytest.skip("no OpenCL device on this machine")
    first = [dp.probe(d) for _, _, d in devs]
    ok = [p for p in first if p.ok]
    assert ok, [p.error for p in first]
    assert all(p.gflops > 0 and not p.cached for p in ok)
    monkeypatch.setattr(dp, "_memo", {})
    again = [dp.probe(d) for _, _, d in devs]
    assert all(a.cached and a.gflops == p.gflops for a, p in zip(again, first))
    chosen = device.choose_device("auto")
    # the best probe of the devices that may be the default: a slow driver (pip's PoCL for a
    # generic CPU, whose FMA probe can top the others) and a device known to compute wrong
    # gradients never are, whatever they measure
    cands = list(chosen.candidates)
    cl_dev = {(pi, di): d for pi, di, d in devs}
    eligible = [c.probe.gflops for c in cands if c.probe.ok
                and not device.slow_reasons(c, cands, device.cpu_flags())
                and not device.known_wrong(cl_dev[(c.platform_index, c.device_index)])]
    assert chosen.candidate.probe.gflops >= max(eligible) * (1 - dp.TIE), cands


def test_probe_time_discounts_other_load():
    """A CPU probe run that waited for its cores (wall 3x its CPU time per compute unit) counts
    its CPU time; a quiet run or a spinning host thread counts wall time; a GPU always wall."""
    from clrf.runtime.device_probe import run_seconds
    assert run_seconds(0.090, 0.060, 2, gpu=False) == pytest.approx(0.030)   # contended
    assert run_seconds(0.030, 0.060, 2, gpu=False) == pytest.approx(0.030)   # quiet
    assert run_seconds(0.030, 0.090, 2, gpu=False) == pytest.approx(0.030)   # host spinning
    assert run_seconds(0.090, 0.001, 2, gpu=True) == pytest.approx(0.090)


def test_ptx_atomics_only_where_the_probe_adds_right(capsys):
    """Float atomic adds go through inline PTX only on a device named NVIDIA whose probe kernel
    built and added right (there, the real driver must pass it). A CPU device that claims to be
    NVIDIA fails the probe (its compiler has no PTX) and keeps the compare-and-swap loop, saying
    so; other devices are not probed."""
    import copy
    import dataclasses
    from clrf.runtime import programs
    from clrf.runtime.tuning import implementation
    dev = device.Device()
    if implementation(dev.caps.platform) == "nvidia":
        assert programs.ptx_atomics(dev) is True
        assert programs.build_options(dev)["CLRF_PTX_ATOMICS"] == 1
        return
    assert programs.build_options(dev)["CLRF_PTX_ATOMICS"] == 0
    fake = copy.copy(dev)
    fake.caps = dataclasses.replace(dev.caps, platform="NVIDIA CUDA", float_atomics=False)
    programs._ptx_checked.pop(fake.cl_device.int_ptr, None)
    try:
        assert programs.ptx_atomics(fake) is False
        assert "compare-and-swap" in capsys.readouterr().err
    finally:
        programs._ptx_checked.pop(fake.cl_device.int_ptr, None)


def test_float_atomics_text_names_the_path():
    import dataclasses
    caps = device.probe_capabilities(device.list_devices()[0][2])
    assert device.float_atomics_text(dataclasses.replace(caps, float_atomics=True)) == "native"
    nv = dataclasses.replace(caps, float_atomics=False, platform="NVIDIA CUDA")
    assert "PTX" in device.float_atomics_text(nv)
    other = dataclasses.replace(caps, float_atomics=False, platform="Portable Computing Language")
    assert device.float_atomics_text(other) == "emulated (CAS)"


def test_a_slow_driver_is_not_the_default_even_when_its_probe_is_higher(machine):
    """pip's generic-target PoCL can measure more FMA GFLOP/s than the distribution's PoCL and
    still run clrf's kernels several times slower: it is not the default while a driver that
    is not slow works, and the reason says so."""
    machine.devs = [(fake_dev("pthread-AMD EPYC", PIP), Probe(None, 158.0)),
                    (fake_dev("pthread-haswell-AMD EPYC", DEBIAN), Probe(None, 120.0))]
    ch = device.choose_device()
    assert (ch.platform_index, ch.device_index) == (1, 0)
    assert "0:0 measures 158.0 GFLOP/s but compiles for a generic CPU target" in ch.reason
    assert device.choose_device("0:0").platform_index == 0    # asked for: still given
    machine.devs = machine.devs[:1]                            # the only one: it is used
    assert device.choose_device().platform_index == 0


def test_rejected_devices_show_their_reason(machine, monkeypatch):
    """A device refused for a cached failing self-check is listed with that verdict, never
    with ': None'."""
    machine.devs = [(fake_dev("pthread-haswell-AMD EPYC", DEBIAN), Probe(None, 65.0))]
    monkeypatch.setattr(device, "known_wrong", lambda d: "the driver crashed during the check "
                                                         "(killed by signal 11 (SIGSEGV))")
    with pytest.raises(device.DeviceError) as e:
        device.choose_device()
    assert "SIGSEGV" in str(e.value) and ": None" not in str(e.value)
