"""What a run holds in device memory: clrf's buffers and its memory pool, with their
peaks.

On a GPU this is the card's memory that the run takes (the figure gsplat's benchmarks report
as "Mem", torch's peak of allocated memory), and what decides whether a Gaussian budget or a
hash table fits there. On a CPU device it is the part of the process's host memory that
grows with the model; the rest (the interpreter, the OpenCL runtime and its compiled kernels,
the host's copy of the dataset) is the resident peak that ``tools/memory_peak.py`` reads.

Two kinds of allocation are counted, on the device's context:
- **buffers**: arrays of their own buffer (parameters, optimiser moments, training images,
  the ray store, a grid's arrays), made by ``programs.upload``, ``device_empty`` and
  ``device_zeros`` through ``DeviceMemory.buffer`` (``counted``), and the arrays pyopencl
  derives from them (arithmetic, ``zeros_like``: they take the operand's allocator); each is
  counted from its creation until pyopencl releases it (the last array or view on it dropped);
- **the pool**: per-step arrays (``programs.scratch`` and every ``allocator=device.pool``)
  come from a pyopencl MemoryPool, which keeps freed blocks for reuse. ``held`` counts what
  the pool holds (its blocks in use and those kept for reuse: memory the runtime has given
  it), ``in_use`` only the blocks in use.

A peak can only be reached at an allocation, so both are updated there. Arrays made without
an allocator are not counted: the splat model's index arrays for editing rows, the device
probes' and benchmarks' buffers, and what pyopencl allocates for itself where it is given no
allocator.

>>> mem = dev.memory
>>> mem.reset_peaks(); ...; mem.summary()
{'held_bytes': ..., 'peak_held_bytes': ..., 'peak_in_use_bytes': ...}
"""
from __future__ import annotations

import threading
import weakref

import pyopencl as cl

GiB = 1024 ** 3


class CountedBuffer(cl.Buffer):
    """A cl.Buffer that ``DeviceMemory`` sees released (pyopencl's own Buffer takes no weak
    reference; a Python subclass does)."""


class DeviceMemory:
    """The ledger of one context's buffers and pool (module doc). Called with a byte count
    it is the pool's allocator (``allocator=device.pool``)."""

    def __init__(self, context, pool):
        self.context, self._pool = context, pool
        self._lock = threading.RLock()   # release callbacks run on the thread that drops
        self.buffer_bytes = 0            # bytes of live counted buffers
        self.peak_held = self.peak_in_use = 0

    # ---- allocators ----
    def buffer(self, nbytes: int) -> CountedBuffer:
        """A long-lived buffer of ``nbytes``, counted until it is released (an allocator:
        ``cla.to_device(queue, ary, allocator=memory.buffer)``)."""
        n = max(int(nbytes), 1)
        buf = CountedBuffer(self.context, cl.mem_flags.READ_WRITE, n)
        with self._lock:
            self.buffer_bytes += n
            weakref.finalize(buf, self._released, n)
            self._note()
        return buf

    def __call__(self, nbytes: int):
        """A block of the pool (a per-step array's buffer)."""
        block = self._pool.allocate(int(nbytes))
        with self._lock:
            self._note()
        return block

    def _released(self, n: int):
        with self._lock:
            self.buffer_bytes -= n

    def _note(self):
        self.peak_held = max(self.peak_held, self.held_bytes)
        self.peak_in_use = max(self.peak_in_use, self.in_use_bytes)

    # ---- the pool's own accounting ----
    def free_held(self):
        """Return the pool's kept blocks to the runtime (MemoryPool.free_held)."""
        self._pool.free_held()

    @property
    def held_blocks(self) -> int:
        return self._pool.held_blocks

    @property
    def active_blocks(self) -> int:
        return self._pool.active_blocks

    # ---- figures ----
    @property
    def held_bytes(self) -> int:
        """Counted buffers plus every block the pool holds (in use or kept)."""
        return self.buffer_bytes + int(self._pool.managed_bytes)

    @property
    def in_use_bytes(self) -> int:
        """Counted buffers plus the pool's blocks in use."""
        return self.buffer_bytes + int(self._pool.active_bytes)

    def reset_peaks(self):
        """Peaks from what is held now (a run's peak leaves out what came before it)."""
        with self._lock:
            self.peak_held, self.peak_in_use = self.held_bytes, self.in_use_bytes

    def summary(self) -> dict:
        """The figures now and at their peaks, in bytes."""
        with self._lock:
            return {"held_bytes": self.held_bytes, "in_use_bytes": self.in_use_bytes,
                    "peak_held_bytes": self.peak_held, "peak_in_use_bytes": self.peak_in_use}

    def describe(self) -> str:
        """'device memory: peak 0.21 GiB held (0.18 GiB in use)'."""
        s = self.summary()
        return (f"device memory: peak {s['peak_held_bytes'] / GiB:.3f} GiB held by clrf's "
                f"buffers and pool ({s['peak_in_use_bytes'] / GiB:.3f} GiB in use)")


_LEDGERS: dict = {}   # queue.int_ptr -> DeviceMemory: the allocators take a queue, not a Device


def register(queue, memory: DeviceMemory, owner) -> None:
    """Make ``memory`` the ledger of ``queue`` until ``owner`` (the Device) is collected."""
    key = queue.int_ptr
    _LEDGERS[key] = memory
    weakref.finalize(owner, _LEDGERS.pop, key, None)


def counted(queue):
    """The allocator that counts an array in ``queue``'s ledger (``DeviceMemory.buffer``), or
    None (pyopencl's own) for a queue that no Device made: ``cla.empty(q, n, np.float32,
    allocator=counted(q))``."""
    memory = _LEDGERS.get(queue.int_ptr)
    return memory.buffer if memory is not None else None
