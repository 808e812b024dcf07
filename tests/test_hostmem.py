"""The host-memory readers (clrf.runtime.hostmem) on fixture text, and the guard refusing a run that
would not fit the host instead of letting the kernel's OOM killer end it."""
import os
import platform
import subprocess
import sys
from pathlib import Path

import pytest

from clrf.runtime import hostmem
from clrf.runtime.hostmem import (
    HostBudget, address_space_headroom, cgroup_headroom, cgroup_v1_headroom, cgroup_v2_headroom,
    host_budget, meminfo_available, parse_cgroup_mounts, parse_kib_fields, parse_proc_cgroup)
from clrf.testing import impls

ROOT = Path(__file__).resolve().parents[1]
KiB, MiB, GiB = 1024, 1 << 20, 1 << 30

MEMINFO = """MemTotal:       24684084 kB
MemFree:        22454464 kB
MemAvailable:   23933940 kB
Buffers:           12332 kB
Cached:          1630012 kB
HugePages_Total:       0
"""
MEMINFO_OLD = """MemTotal:        8000000 kB
MemFree:         1000000 kB
Buffers:          100000 kB
Cached:           500000 kB
"""
PROC_CGROUP_V1 = """9:name=systemd:/
4:memory:/process_api/908f
3:cpuset:/
0::/
"""
PROC_CGROUP_V2 = "0::/user.slice/session-3.scope\n"
MOUNTINFO = """31 23 0:28 / /sys/fs/cgroup rw,relatime - tmpfs tmpfs rw,mode=755
35 31 0:32 / /sys/fs/cgroup/memory rw,relatime - cgroup cgroup rw,memory
36 31 0:33 / /sys/fs/cgroup/devices rw,relatime - cgroup cgroup rw,devices
41 31 0:38 / /sys/fs/cgroup/unified rw,relatime - cgroup2 cgroup2 rw
"""
MOUNTINFO_V2 = "30 23 0:26 / /sys/fs/cgroup rw,nosuid - cgroup2 cgroup2 rw,nsdelegate\n"


def test_meminfo_reads_available_and_the_old_kernel_fallback():
    assert parse_kib_fields(MEMINFO)["MemTotal"] == 24684084 * KiB
    assert "HugePages_Total" not in parse_kib_fields(MEMINFO)   # a count, not kB
    assert meminfo_available(MEMINFO) == 23933940 * KiB
    assert meminfo_available(MEMINFO_OLD) == (1000000 + 100000 + 500000) * KiB
    assert meminfo_available("garbage\n") is None


def test_cgroup_headrooms():
    assert cgroup_v2_headroom("max\n", "123\n") is None
    assert cgroup_v2_headroom(f"{4 * GiB}\n", f"{GiB}\n") == 3 * GiB
    assert cgroup_v2_headroom(f"{GiB}\n", f"{2 * GiB}\n") == 0       # over the limit: none
    assert cgroup_v2_headroom(None, None) is None
    assert cgroup_v1_headroom("9223372036854771712\n", "7458816\n") is None   # no limit
    assert cgroup_v1_headroom(f"{2 * GiB}\n", f"{GiB // 2}\n") == GiB + GiB // 2


def test_proc_cgroup_and_mountinfo():
    assert parse_proc_cgroup(PROC_CGROUP_V1) == {"memory": "/process_api/908f", "v2": "/"}
    assert parse_proc_cgroup(PROC_CGROUP_V2) == {"v2": "/user.slice/session-3.scope"}
    assert parse_cgroup_mounts(MOUNTINFO) == {"memory": ("/", "/sys/fs/cgroup/memory"),
                                              "v2": ("/", "/sys/fs/cgroup/unified")}


def _tree(tmp_path, files: dict):
    for rel, text in files.items():
        p = tmp_path / rel
        p.parent.mkdir(parents=True, exist_ok=True)
        p.write_text(text)
    return str(tmp_path)


def test_v1_limit_of_an_ancestor_is_the_tightest(tmp_path):
    mem = "sys/fs/cgroup/memory"
    root = _tree(tmp_path, {
        "proc/self/cgroup": PROC_CGROUP_V1, "proc/self/mountinfo": MOUNTINFO,
        "proc/meminfo": MEMINFO, "proc/self/status": "VmRSS:\t  1024 kB\nVmHWM:\t 2048 kB\n",
        f"{mem}/memory.limit_in_bytes": "9223372036854771712\n",
        f"{mem}/memory.usage_in_bytes": f"{10 * GiB}\n",
        f"{mem}/process_api/memory.limit_in_bytes": f"{6 * GiB}\n",
        f"{mem}/process_api/memory.usage_in_bytes": f"{4 * GiB}\n",
        f"{mem}/process_api/908f/memory.limit_in_bytes": f"{8 * GiB}\n",
        f"{mem}/process_api/908f/memory.usage_in_bytes": f"{GiB}\n"})
    h, where = cgroup_headroom(root)
    assert h == 2 * GiB and where.endswith("process_api")
    b = host_budget(root)
    assert b.available == 2 * GiB and "process_api" in b.source
    assert (b.rss, b.peak) == (MiB, 2 * MiB)


def test_v2_limit_below_meminfo_wins_and_max_means_none(tmp_path):
    cg = "sys/fs/cgroup/user.slice/session-3.scope"
    files = {"proc/self/cgroup": PROC_CGROUP_V2, "proc/self/mountinfo": MOUNTINFO_V2,
             "proc/meminfo": MEMINFO, f"{cg}/memory.max": f"{3 * GiB}\n",
             f"{cg}/memory.current": f"{GiB}\n"}
    b = host_budget(_tree(tmp_path / "a", files))
    assert b.available == 2 * GiB and "session-3.scope" in b.source
    files[f"{cg}/memory.max"] = "max\n"
    b = host_budget(_tree(tmp_path / "b", files))
    assert b.available == 23933940 * KiB and "MemAvailable" in b.source
    assert host_budget(str(tmp_path / "nothing")).available == -1


def test_address_space_limit():
    status = "VmPeak:\t 3000000 kB\nVmSize:\t 2097152 kB\n"
    import resource
    assert address_space_headroom(status, resource.RLIM_INFINITY) is None
    assert address_space_headroom(status, 3 * GiB) == GiB
    assert address_space_headroom(status, GiB) == 0


def test_a_run_beyond_the_host_refuses_naming_the_setting(tmp_path, capsys, monkeypatch):
    """The guard compares the run's growth with the host budget: a budget of 64 MiB (the
    reader monkeypatched, as a small container's cgroup would give) refuses the procedural
    run before the trainer exists, naming the phase and the settings to lower."""
    import clrf.training.trainer
    from clrf.cli.main import main as cli
    monkeypatch.setattr(clrf.training.trainer, "Trainer", None)
    monkeypatch.setattr(hostmem, "host_budget",
                        lambda root="/": HostBudget(64 * MiB, "the memory limit of cgroup /test",
                                                    300 * MiB, 300 * MiB))
    out = tmp_path / "out"
    rc = cli(["train", "--out", str(out)])
    err = capsys.readouterr().err
    assert rc == 2, err
    assert "more device and host memory than this process holds now" in err
    assert "only 0.06 GiB is available (the memory limit of cgroup /test)" in err
    assert "lower grid.reso" in err and "train.downscale" in err
    assert not out.exists()


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="RLIMIT_AS is Linux's here")
def test_under_ulimit_v_the_run_refuses_instead_of_dying(tmp_path, device):
    """A real limit: `clrf train` under RLIMIT_AS (ulimit -v) at the process's own size + 1
    GiB, asked for a 192^3 grid (about 2.5 GiB on the host, less than the
    reported device memory): it exits 2 with the guard's
    message, not with a MemoryError, an OpenCL allocation failure or a kill."""
    code = (
        "import resource, sys\n"
        "from clrf.runtime.hostmem import parse_kib_fields\n"
        "import pyopencl\n"
        "pyopencl.get_platforms()\n"      # every driver loaded before the size is read
        "size = parse_kib_fields(open('/proc/self/status').read())['VmSize']\n"
        "lim = size + (1 << 30)\n"
        "resource.setrlimit(resource.RLIMIT_AS, (lim, lim))\n"
        "from clrf.cli import main\n"
        "sys.exit(main(sys.argv[1:]))\n")
    out = tmp_path / "out"
    p = subprocess.run([sys.executable, "-c", code, "train", "--out", str(out), "--set",
                        "grid.reso=[[192,192,192]]", "--set", "grid.upsample_at=[]"],
                       cwd=tmp_path, capture_output=True, text=True, timeout=300,
                       env={**os.environ,
                            # one device (PoCL where present): no other driver's threads
                            # under the limit
                            "CLRF_DEVICE": impls.present().get(
                                "pocl", f"{device.platform_index}:{device.device_index}")})
    assert p.returncode == 2, p.stderr[-2000:]
    assert "address-space limit (ulimit -v)" in p.stderr and "lower grid.reso" in p.stderr
    assert not (out / "ckpt.npz").exists()


@pytest.mark.skipif(platform.libc_ver()[0] != "glibc", reason="malloc_trim is glibc's")
def test_release_free_heap_returns_freed_heap_pages():
    """60 MB of 100 kB blocks (under glibc's mmap threshold: they come from the heap), all
    freed but the last (which keeps the heap's top from shrinking on its own): the resident
    set drops by most of the 60 MB only once ``release_free_heap`` runs. In a child, so that
    this process's heap does not matter."""
    code = (
        "from clrf.runtime.hostmem import parse_kib_fields, release_free_heap\n"
        "rss = lambda: parse_kib_fields(open('/proc/self/status').read())['VmRSS']\n"
        "blocks = [bytearray(100_000) for _ in range(600)]\n"
        "last = blocks[-1]\n"
        "del blocks\n"
        "before = rss()\n"
        "assert release_free_heap()\n"
        "print(before - rss())\n")
    p = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60)
    assert p.returncode == 0, p.stderr[-2000:]
    assert int(p.stdout) > 40e6, p.stdout
