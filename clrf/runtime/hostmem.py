"""How much memory this process may still take from the host: the memory guard's host budget.

The smallest of

- ``MemAvailable`` of /proc/meminfo (the kernel's estimate of memory that can be taken without
  swapping; ``MemFree + Buffers + Cached`` on kernels older than 3.14),
- the headroom of the process's memory cgroup and of each of its ancestors: cgroup v2
  ``memory.max - memory.current``, v1 ``memory.limit_in_bytes - memory.usage_in_bytes`` (the
  limit a container runs under; "no limit" reads as "max" in v2 and as a huge number in v1),
- the address-space limit (``ulimit -v``, RLIMIT_AS) minus the process's ``VmSize``.

Every reader takes the file text, so tests feed it fixtures; ``host_budget(root)`` reads the
files under ``root`` ("/" on a real system).
"""
from __future__ import annotations

import functools
import resource
from dataclasses import dataclass
from pathlib import Path

V1_UNLIMITED = 1 << 60   # cgroup v1 writes "no limit" as PAGE_COUNTER_MAX pages (~2^63 bytes)


@dataclass
class HostBudget:
    """Bytes this process may still allocate (``available``), what set it (``source``), and
    the process's resident set now (``rss``) and at its peak so far (``peak``)."""
    available: int
    source: str
    rss: int = 0
    peak: int = 0


def parse_kib_fields(text: str) -> dict:
    """``Name:  123 kB`` lines (/proc/meminfo, /proc/PID/status) -> {name: bytes}; lines that
    are not a number of kB are skipped."""
    out = {}
    for line in text.splitlines():
        name, _, rest = line.partition(":")
        parts = rest.split()
        if len(parts) == 2 and parts[1] == "kB" and parts[0].isdigit():
            out[name.strip()] = int(parts[0]) * 1024
    return out


def meminfo_available(text: str) -> int | None:
    """Bytes available from /proc/meminfo text: MemAvailable, else MemFree + Buffers + Cached
    (kernels before 3.14); None when neither is there."""
    f = parse_kib_fields(text)
    if "MemAvailable" in f:
        return f["MemAvailable"]
    if "MemFree" in f:
        return f["MemFree"] + f.get("Buffers", 0) + f.get("Cached", 0)
    return None


def _int_or_none(text: str | None):
    if text is None:
        return None
    t = text.strip()
    return int(t) if t.isdigit() else None


def cgroup_v2_headroom(max_text: str | None, current_text: str | None) -> int | None:
    """memory.max - memory.current of one cgroup v2 directory; None when unlimited ("max") or
    unreadable."""
    lim, cur = _int_or_none(max_text), _int_or_none(current_text)
    if lim is None:
        return None
    return max(0, lim - (cur or 0))


def cgroup_v1_headroom(limit_text: str | None, usage_text: str | None) -> int | None:
    """memory.limit_in_bytes - memory.usage_in_bytes of one cgroup v1 memory directory; None
    when unlimited (>= 2^60) or unreadable."""
    lim, use = _int_or_none(limit_text), _int_or_none(usage_text)
    if lim is None or lim >= V1_UNLIMITED:
        return None
    return max(0, lim - (use or 0))


def parse_proc_cgroup(text: str) -> dict:
    """/proc/self/cgroup -> {"v2": path} for the ``0::path`` line and {"memory": path} for a
    v1 hierarchy holding the memory controller."""
    out = {}
    for line in text.splitlines():
        parts = line.split(":", 2)
        if len(parts) != 3:
            continue
        hid, ctrls, path = parts
        if hid == "0" and ctrls == "":
            out["v2"] = path
        elif "memory" in ctrls.split(","):
            out["memory"] = path
    return out


def parse_cgroup_mounts(text: str) -> dict:
    """/proc/self/mountinfo -> {"v2": (root, mount point), "memory": (root, mount point)} of the
    cgroup2 mount and of the v1 mount with the memory controller."""
    out = {}
    for line in text.splitlines():
        left, sep, right = line.partition(" - ")
        if not sep:
            continue
        f, r = left.split(), right.split()
        if len(f) < 5 or len(r) < 3:
            continue
        root, point = f[3], f[4]
        if r[0] == "cgroup2":
            out.setdefault("v2", (root, point))
        elif r[0] == "cgroup" and "memory" in r[2].split(","):
            out.setdefault("memory", (root, point))
    return out


def _cgroup_dirs(proc_path: str, mount) -> list:
    """The directories of a cgroup and of its ancestors up to the mount's root, deepest first."""
    root, point = mount
    rel = proc_path
    if root != "/" and (rel == root or rel.startswith(root.rstrip("/") + "/")):
        rel = rel[len(root.rstrip("/")):]   # the mount shows the hierarchy from its own root
    parts = [p for p in rel.split("/") if p]
    return [Path(point, *parts[:k]) for k in range(len(parts), -1, -1)]


def _read(path) -> str | None:
    try:
        return Path(path).read_text()
    except OSError:
        return None


def _under(root: str, path) -> Path:
    return Path(root) / str(path).lstrip("/")


def cgroup_headroom(root: str = "/") -> tuple:
    """(bytes, directory) of the tightest memory cgroup limit over the process's cgroup and its
    ancestors, v2 and v1 alike; (None, None) when no limit is set."""
    groups = parse_proc_cgroup(_read(_under(root, "proc/self/cgroup")) or "")
    mounts = parse_cgroup_mounts(_read(_under(root, "proc/self/mountinfo")) or "")
    best = (None, None)
    for kind, files in (("v2", ("memory.max", "memory.current")),
                        ("memory", ("memory.limit_in_bytes", "memory.usage_in_bytes"))):
        if kind not in groups or kind not in mounts:
            continue
        headroom = cgroup_v2_headroom if kind == "v2" else cgroup_v1_headroom
        for d in _cgroup_dirs(groups[kind], mounts[kind]):
            h = headroom(_read(_under(root, d / files[0])), _read(_under(root, d / files[1])))
            if h is not None and (best[0] is None or h < best[0]):
                best = (h, f"cgroup {d}")
    return best


def address_space_headroom(status_text: str, limit: int) -> int | None:
    """RLIMIT_AS ``limit`` minus VmSize of /proc/self/status; None when unlimited."""
    if limit is None or limit < 0 or limit == resource.RLIM_INFINITY:
        return None
    return max(0, int(limit) - parse_kib_fields(status_text).get("VmSize", 0))


def host_budget(root: str = "/") -> HostBudget:
    """The smallest of the host's available memory, the cgroup headroom and the address-space
    headroom, with the process's resident set now and at its peak (see the module docstring).
    Without /proc (not Linux) the budget is unknown: ``available`` is -1."""
    status = _read(_under(root, "proc/self/status")) or ""
    st = parse_kib_fields(status)
    rss, peak = st.get("VmRSS", 0), st.get("VmHWM", 0)
    cands = []
    avail = meminfo_available(_read(_under(root, "proc/meminfo")) or "")
    if avail is not None:
        cands.append((avail, "MemAvailable of /proc/meminfo"))
    cg, where = cgroup_headroom(root)
    if cg is not None:
        cands.append((cg, f"the memory limit of {where}"))
    soft, _hard = resource.getrlimit(resource.RLIMIT_AS)
    asr = address_space_headroom(status, soft) if root == "/" else None
    if asr is not None:
        cands.append((asr, "the address-space limit (ulimit -v) less the process's VmSize"))
    if not cands:
        return HostBudget(-1, "unknown (no /proc/meminfo)", rss, peak)
    avail, src = min(cands)
    return HostBudget(int(avail), src, rss, peak)


def release_free_heap() -> bool:
    """Give the C heap's free pages back to the system (glibc's ``malloc_trim(0)``); False
    where there is no glibc (the call is then a no-op).

    glibc serves a freed block of a few MB from its heap the next time rather than unmapping
    it (after a large block is freed, its mmap threshold rises to up to 32 MB), so a phase that
    allocated and freed many such blocks (decoding a capture's images, a host edit of every
    Gaussian) leaves the resident set high for the rest of the run. 2 vCPUs, bonsai at 200x133:
    385 MB resident after loading, 334 MB after this call."""
    trim = _malloc_trim()
    if trim is None:
        return False
    trim(0)
    return True


@functools.cache
def _malloc_trim():
    """glibc's ``malloc_trim`` from the running process's symbols, or None (musl, macOS,
    Windows)."""
    import ctypes
    try:
        trim = ctypes.CDLL(None).malloc_trim
    except (OSError, AttributeError, TypeError):
        return None
    trim.argtypes, trim.restype = [ctypes.c_size_t], ctypes.c_int
    return trim
