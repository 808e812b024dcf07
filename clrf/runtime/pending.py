"""A number the device is still computing: a non-blocking copy of a one-item device array that
the host reads only when it needs the value. A training step that returns its loss this way
does not wait for the device; the trainer reads the losses when it reports them.

>>> v = Pending(queue, loss_d, scale=1 / (3 * B))   # loss_d: a one-item device array
>>> v.ready                                         # copied already? (never waits)
>>> float(v)                                        # waits for the copy, then the value
"""
from __future__ import annotations

import numpy as np
import pyopencl as cl


class Pending:
    """float(self) is scale times the single item of the device array ``arr`` as it is once
    the commands queued before this copy have run."""

    def __init__(self, queue, arr, scale: float = 1.0):
        if int(arr.size) != 1:
            raise ValueError(f"Pending: needs a one-item device array, got shape {arr.shape}")
        self._host = np.empty(1, arr.dtype)
        self._arr = arr           # the device buffer stays alive until the copy has run
        # base_data and offset: a one-item slice of a larger array works too
        self._event = cl.enqueue_copy(queue, self._host, arr.base_data, src_offset=arr.offset,
                                      is_blocking=False)
        self._scale = float(scale)
        self._value = None

    @property
    def ready(self) -> bool:
        """True once the copy has run (float() then does not wait)."""
        if self._value is not None:
            return True
        status = self._event.get_info(cl.event_info.COMMAND_EXECUTION_STATUS)
        if status < 0:            # the copy (or a command before it) failed: float() raises
            return True
        return status == cl.command_execution_status.COMPLETE

    def __float__(self) -> float:
        if self._value is None:
            self._event.wait()
            self._value = float(self._host[0]) * self._scale
            self._arr = None
        return self._value

    def __int__(self) -> int:
        return int(round(float(self)))

    def __repr__(self) -> str:
        return f"Pending({float(self)!r})" if self._value is not None else "Pending(...)"


__all__ = ["Pending"]
