"""Fused-MLP tiles per device (clrf/mlp/tiling.py, clrf/mlp/autotune.py): defaults, the tuner's cache, the choice order,
and a smoke run of the tuner and of tools/nerf_bench.py at tiny sizes."""
import json
import sys
from dataclasses import replace
from pathlib import Path

import pytest

from clrf.mlp import autotune as tuner
from clrf.nerf import autotune as tuner_cli
from clrf.mlp import tiling as at
from clrf.runtime.device import Capabilities
from clrf.mlp.mlp import MLP, MLPSpec

sys.path.insert(0, str(Path(__file__).resolve().parent.parent / "tools"))
import nerf_bench  # noqa: E402

SPEC = MLPSpec(width=32, depth=2, skip=-1, color_width=16, in_dim=9, dir_dim=5)


def caps(type_="cpu", width=8, name="fake", driver="1.0"):
    return Capabilities(name=name, platform="FakeCL", platform_version="FakeCL 1", type=type_,
                        driver_version=driver, compute_units=2, max_work_group_size=1024,
                        local_mem_size=65536, global_mem_size=1 << 30, max_alloc_size=1 << 28,
                        fp64=True, float_atomics=False, int64_atomics=True,
                        native_float_width=width)


class FakeDevice:
    def __init__(self, c):
        self.caps = c


@pytest.fixture
def cache(tmp_path, monkeypatch):
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path))
    return tmp_path / "clrf" / "mlp_tiling.json"


def test_device_defaults_by_vector_width():
    wide = at.device_default(caps(width=16))
    assert (wide.rows, wide.cols, wide.dw_rows, wide.dw_cols) == (12, 16, 8, 32)
    assert wide.dw_chunk == at.CHUNK_TILES * 12
    # AVX-512 and an MLP no wider than NARROW_WIDTH (the tiny preset's 4x64): 8 x 16, 8 x 16
    big = MLPSpec(width=256, depth=8, skip=4, color_width=128, in_dim=63, dir_dim=27)
    assert at.device_default(caps(width=16), big) == wide
    assert at.device_default(caps(width=16), replace(big, width=at.NARROW_WIDTH + 16,
                                                     color_width=16)) == wide
    for spec in (SPEC, replace(big, width=64, color_width=32),
                 replace(big, width=at.NARROW_WIDTH, color_width=at.NARROW_WIDTH)):
        n = at.device_default(caps(width=16), spec)
        assert (n.rows, n.cols, n.dw_rows, n.dw_cols, n.dw_chunk) == (8, 16, 8, 16,
                                                                      at.CHUNK_TILES * 8)
        assert at.device_default(caps(width=8), spec) == at.device_default(caps(width=8))
    avx2 = at.device_default(caps(width=8))
    assert (avx2.rows, avx2.cols) == (6, 16) and avx2.dw_chunk == at.CHUNK_TILES * 6
    assert at.device_default(caps(width=4)).rows == 2
    gpu = at.device_default(caps(type_="gpu", width=1))
    assert (gpu.rows, gpu.cols) == (4, 16)
    assert caps(width=8).vector_width == 8 and caps(width=32).vector_width == 16
    assert caps(type_="gpu", width=1).vector_width == 4


def test_cache_round_trip_and_keys(cache):
    c = caps()
    assert at.cached_tiling(c, SPEC) is None
    t = at.MLPTiling(4, 16, 2, 32, 256)
    at.store_tiling(c, SPEC, t, {"fwdbwd_s": 0.5})
    assert at.cache_path() == cache and cache.is_file()
    assert at.cached_tiling(c, SPEC) == t
    # other driver, device or shape: not this entry; tile fields are not part of the shape
    assert at.cached_tiling(caps(driver="2.0"), SPEC) is None
    assert at.cached_tiling(caps(name="other"), SPEC) is None
    assert at.cached_tiling(c, replace(SPEC, width=48)) is None
    assert at.cached_tiling(c, replace(SPEC, rows=8)) == t
    # a second entry keeps the first; no temporary files are left behind
    at.store_tiling(c, replace(SPEC, width=48), at.MLPTiling(), {})
    assert at.cached_tiling(c, SPEC) == t
    assert [p.name for p in cache.parent.iterdir()] == [cache.name]


@pytest.mark.parametrize("text", ["{not json", "[]", '{"version": 99, "entries": {}}',
                                  '{"version": %d, "entries": {"d": 3}}' % at.CACHE_VERSION,
                                  '{"version": %d, "entries": {}}' % (at.CACHE_VERSION - 1), ""])
def test_corrupt_cache_is_ignored_and_replaced(cache, text):
    cache.parent.mkdir(parents=True)
    cache.write_text(text)
    c = caps()
    assert at.load_cache() == {} and at.cached_tiling(c, SPEC) is None
    assert at.mlp_tiling_for(FakeDevice(c), SPEC) == at.device_default(c)
    at.store_tiling(c, SPEC, at.MLPTiling(4, 16, 2, 32, 256), {})
    assert at.cached_tiling(c, SPEC).rows == 4


def test_malformed_entry_is_ignored(cache):
    c = caps()
    at.store_tiling(c, SPEC, at.MLPTiling(), {})
    data = json.loads(cache.read_text())
    entry = data["entries"][at.device_key(c)][at.shape_key(SPEC)]
    entry["rows"] = "eight"
    cache.write_text(json.dumps(data))
    assert at.cached_tiling(c, SPEC) is None


def test_choice_order_spec_then_cache_then_default(cache):
    c = caps(width=8)
    dev = FakeDevice(c)
    assert at.mlp_tiling_for(dev, SPEC) == at.device_default(c)
    tuned = at.MLPTiling(4, 32, 2, 16, 256)
    at.store_tiling(c, SPEC, tuned, {})
    assert at.mlp_tiling_for(dev, SPEC) == tuned
    got = at.mlp_tiling_for(dev, replace(SPEC, cols=16, dw_rows=8))
    assert got == replace(tuned, cols=16, dw_rows=8)
    # rows set alone: the chunk follows it (64 tiles), unless set too
    assert at.mlp_tiling_for(dev, replace(SPEC, rows=8)).dw_chunk == 8 * at.CHUNK_TILES
    assert at.mlp_tiling_for(dev, replace(SPEC, rows=8, dw_chunk=40)).dw_chunk == 40


@pytest.mark.slow
def test_tuner_times_candidates_and_the_mlp_uses_its_choice(device, cache):
    best, res = tuner.tune(device, SPEC, n=64, rounds=1)
    assert [t for t, _ in res] == at.candidates(device.caps, SPEC)
    assert all(s > 0 for _, s in res) and best == min(res, key=lambda r: r[1])[0]
    assert at.cached_tiling(device.caps, SPEC) == best
    # the CPU tiles are what it tunes: a GPU's MLP runs its GPU tiling (CLRF_FORCE_GPU_KERNELS)
    assert MLP(device.with_tuning(gpu_kernels=False), SPEC).tiling == best


@pytest.mark.slow
def test_tuner_cli(device, cache, capsys):
    assert tuner_cli.main(["--samples", "0"]) == 2
    assert "clrf: error: --samples" in capsys.readouterr().err
    assert tuner_cli.main(["--width", "40", "--depth", "2", "--skip", "-1", "--samples", "8",
                    "--rounds", "1"]) == 2
    assert "clrf: error: --width must be" in capsys.readouterr().err and not cache.exists()
    # the tiny preset's shape with NeRF's skip (layer 4 of 4): rejected by name, not a build error
    assert tuner_cli.main(["--preset", "tiny", "--skip", "4", "--samples", "8", "--rounds", "1"]) == 2
    assert "clrf: error: --skip must be" in capsys.readouterr().err and not cache.exists()
    # tune the session's device (the tuner's own default is the probe's choice, which can
    # differ from the session's workload-chosen device when two drivers measure alike)
    dev = ["--device", f"{device.platform_index}:{device.device_index}"]
    assert tuner_cli.main(["--width", "32", "--depth", "2", "--skip", "-1", "--color-width", "16",
                       "--in-dim", "9", "--dir-dim", "5", "--samples", "16", "--rounds", "1",
                       *dev]) == 0
    out = capsys.readouterr().out
    assert out.count("GFLOP/s") == len(at.candidates(device.caps, SPEC)) and cache.is_file()
    # --preset tiny tunes the shape `clrf train --model nerf` builds (its cache entry)
    from clrf.nerf.config import NerfConfig
    tiny = NerfConfig.from_preset("tiny").mlp_spec()
    assert at.cached_tiling(device.caps, tiny) is None
    assert tuner_cli.main(["--preset", "tiny", "--samples", "8", "--rounds", "1", *dev]) == 0
    assert at.cached_tiling(device.caps, tiny) is not None


def test_gpu_candidates_start_at_the_default_and_differ():
    c = caps(type_="gpu", width=1)
    cands = at.gpu_candidates(c)
    assert cands[0] == at.gpu_default(c) and len(set(cands)) == len(cands) > 8
    assert all(g.wg >= 32 and g.local_max == c.local_mem_size for g in cands)
    assert {g.tm for g in cands} >= {None, 2, 4} and {g.wg for g in cands} == {256, 128, 64}
    small = replace(c, max_work_group_size=64)   # no group under 32 work-items
    assert {g.wg for g in at.gpu_candidates(small)} == {64, 32}


def test_gpu_default_samples_per_work_item_on_intel_gpus():
    """Intel GPUs get INTEL_GPU_TM samples per work-item (the kernel's choice spilled there,
    tools/gpu_builds.py); other GPUs leave it to the kernel."""
    intel = replace(caps(type_="gpu", width=1), platform="Intel(R) OpenCL Graphics")
    assert at.gpu_default(intel).tm == at.INTEL_GPU_TM == 2
    assert at.gpu_default(intel).defines()["GPU_TM"] == 2
    assert at.gpu_default(caps(type_="gpu", width=1)).tm is None
    assert at.gpu_candidates(intel)[0].tm == 2 and {g.tm for g in at.gpu_candidates(intel)} >= {2, 4}


def test_gpu_cache_round_trip_and_choice(cache):
    """A tuned GPU tiling is its own entry beside the CPU tile, read back with the device's
    local memory, and chosen where the device runs the GPU tiling (its chunk from MLPSpec)."""
    from types import SimpleNamespace
    c = caps(type_="gpu", width=1)
    gpu_dev, cpu_dev = FakeDevice(c), FakeDevice(c)
    gpu_dev.tuning = SimpleNamespace(gpu_kernels=True)
    assert at.cached_gpu_tiling(c, SPEC) is None
    assert at.mlp_tiling_for(gpu_dev, SPEC).gpu == at.gpu_default(c)
    tuned = at.GPUTiling(wg=128, local_max=1, tm=4, bk=8)
    at.store_tiling(c, SPEC, at.MLPTiling(gpu=tuned), {"fwdbwd_s": 0.1})
    assert at.cached_gpu_tiling(c, SPEC) == replace(tuned, local_max=c.local_mem_size)
    assert at.cached_tiling(c, SPEC) is None               # no CPU tile was stored
    assert at.mlp_tiling_for(gpu_dev, SPEC).gpu == replace(tuned, local_max=c.local_mem_size)
    assert at.mlp_tiling_for(gpu_dev, replace(SPEC, dw_chunk=96)).gpu.chunk == 96
    assert at.mlp_tiling_for(cpu_dev, SPEC) == at.device_default(c)
    at.store_tiling(c, SPEC, at.MLPTiling(4, 32, 2, 16, 256), {})   # keeps the GPU entry
    assert at.cached_gpu_tiling(c, SPEC) is not None
    data = json.loads(cache.read_text())
    data["entries"][at.device_key(c)][at.GPU_KEY + at.shape_key(SPEC)]["tm"] = "four"
    cache.write_text(json.dumps(data))
    assert at.cached_gpu_tiling(c, SPEC) is None


@pytest.mark.slow
def test_gpu_tuner_times_what_builds_and_the_mlp_uses_its_choice(device, cache, monkeypatch):
    """The GPU tiling's tuner on the session device (forced): tilings that do not build are
    left out, the fastest is cached, and an MLP built there afterwards runs it. One of the
    neighbours only: each GPU build takes seconds on a CPU."""
    monkeypatch.setattr(at, "GPU_NEIGHBOURS", ({"tm": 2},))
    dev = device.with_tuning(gpu_kernels=True)
    bad = at.GPUTiling(wg=64, local_max=int(device.caps.local_mem_size), tm=3)   # #error
    timed = tuner.time_gpu_candidates(dev, SPEC, [bad, at.gpu_default(dev.caps)], n=96,
                                      rounds=1)
    assert len(timed) == 1 and timed[0][0].gpu.tm is None and timed[0][1] > 0
    best, res = tuner.tune(dev, SPEC, n=96, rounds=1)
    assert best.gpu is not None and best == min(res, key=lambda r: r[1])[0] and len(res) == 2
    assert at.cached_gpu_tiling(dev.caps, SPEC) == best.gpu
    assert MLP(dev, SPEC).tiling.gpu == best.gpu
    assert at.cached_tiling(dev.caps, SPEC) is None     # the CPU tiles were not tuned


def test_hash_tuner_cli(device, cache, capsys, monkeypatch):
    """python -m clrf.hash.autotune tunes the networks a hash preset builds (the GPU tiling
    with CLRF_FORCE_GPU_KERNELS=1; one neighbour of the default only)."""
    monkeypatch.setattr(at, "GPU_NEIGHBOURS", ({"tm": 2},))
    from clrf.hash import autotune as hash_cli
    from clrf.hash.config import HashConfig
    from clrf.hash.model import mlp_spec
    dev = ["--device", f"{device.platform_index}:{device.device_index}"]
    spec = mlp_spec(HashConfig.from_preset("tiny"))
    assert hash_cli.main(["--preset", "tiny", "--rounds", "0", *dev]) == 2
    assert "clrf: error: --samples and --rounds" in capsys.readouterr().err
    monkeypatch.setenv("CLRF_FORCE_GPU_KERNELS", "1")
    assert hash_cli.main(["--preset", "tiny", "--samples", "64", "--rounds", "1", *dev]) == 0
    out = capsys.readouterr().out
    assert "GPU tiling, 64 samples" in out and out.count("*") == 1 and out.count("GFLOP/s") == 2
    assert at.cached_gpu_tiling(device.caps, spec) is not None


@pytest.mark.slow
def test_nerf_bench_runs_and_reports_tilings(device, cache, tmp_path, capsys):
    out = tmp_path / "b.json"
    nerf_bench.main(["--samples", "16", "--repeats", "1", "--configs", "small-4x64",
                     "--tilings", "device,wide,6:16:8:16", "--out", str(out)])
    res = json.loads(out.read_text())
    t = res["configs"]["small-4x64"]
    assert t["wide"]["tiling"]["cols"] == 32 and t["6:16:8:16"]["tiling"]["dw_cols"] == 16
    assert t["device"]["tiling"]["rows"] == at.device_default(device.caps,
                                                              nerf_bench.CONFIGS["small-4x64"]).rows
    assert f"fma_peak/vec{device.caps.vector_width}" in res["cases"]
    assert all(v["gflops"] > 0 for v in res["cases"].values())
