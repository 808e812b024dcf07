"""The interface of a density strategy (clrf/splat/strategies/): what the splat model gives it
and asks of it, and what every strategy shares (its running state and its checkpoint keys).

A strategy is made from the ``splat`` section in one place (``Strategy.of``: its own frozen
``Settings`` record) and owns its running state: the schedule's counters (``RefineState``)
and per-Gaussian statistics, float32 device arrays [n] named by ``ROWS``, which follow the
rows of the parameter table (``allocate`` after an edit of the count: zeros, or given rows;
``zero_rows`` where rows are overwritten in place; ``host_rows`` to move them between MPI
shards) and are saved as ``strategy_row_{name}`` in the checkpoint (``state_dict``).

A training step calls, in this order:

- forward, loss, backward (with ``absgrad``: the render record carries the per-pixel
  absolute screen gradients);
- ``step_post_backward(params, grads, moments, step, render)``: the parameters and their
  gradients (device arrays by name), their Adam moments ({name: (first, second)}), the step
  and the render record (``RenderInfo``: screen radii, screen gradients, image size) before
  the update;
- the Adam update;
- ``step_post_update(params, moments, step, lr)``: after it (``lr``: the means' rate);

and between steps the budget fraction f drives ``refine_due`` (the model then edits the rows:
``refine_in_place`` on the device where the count stays, else ``refine`` on numpy arrays) and
``step_schedule`` (the strategy's own edits of the parameters, e.g. opacity resets).
"""
from __future__ import annotations

from dataclasses import dataclass, fields
from typing import ClassVar

import numpy as np

from ...runtime.programs import device_zeros, download, upload

ROW_PREFIX = "strategy_row_"     # checkpoint key of a per-Gaussian statistic
OLD_STATS = "adam_stats"         # checkpoints before strategies owned them: [3, n] on the model


def logit(p):
    return np.log(p / (1.0 - p))


@dataclass(frozen=True)
class RenderInfo:
    """What a training step's render tells the strategy: each Gaussian's screen radius [n]
    (0: not seen) and the loss's gradient on its screen position [n, 2] (device arrays; with
    the strategy's absgrad the per-pixel terms summed in absolute value), and the image size
    in pixels."""
    radius: object
    grad_xy: object
    width: int
    height: int


@dataclass
class RefineState:
    """A strategy's schedule counters between steps (checkpointed): the iteration and budget
    fraction of the last refinement, and the opacity resets so far (default strategy)."""
    last_refine: int = 0        # iteration of the last refinement (0: none yet)
    refine_frac: float = 0.0    # budget fraction at it
    resets: int = 0             # opacity resets so far (the schedule's count)
    last_reset: int = 0         # the step of the last reset (0: none yet)

    def state_dict(self) -> dict:
        return {f"strategy_{f.name}": getattr(self, f.name) for f in fields(self)}

    @classmethod
    def from_state(cls, state: dict) -> "RefineState":
        """From a checkpoint (also one written before strategies: its own key names)."""
        old = {"last_refine": "last_densify", "refine_frac": "densify_frac"}
        out = cls()
        for f in fields(cls):
            key = f"strategy_{f.name}"
            v = state.get(key, state.get(old.get(f.name, f.name)))
            if v is not None:
                setattr(out, f.name, type(getattr(out, f.name))(np.asarray(v).item()))
        return out


@dataclass(frozen=True)
class Schedule:
    """When a strategy refines: between budget fractions ``start`` and ``stop``, every
    ``every`` of the budget and at least ``min_steps`` iterations apart."""
    start: float
    stop: float
    every: float
    min_steps: int

    def due(self, st: RefineState, it: int, f: float, step: int) -> bool:
        return (self.start <= f < self.stop and step > 0
                and it - st.last_refine >= self.min_steps
                and int(f / self.every) > int(st.refine_frac / self.every))


class Strategy:
    """A density strategy (the module's text). A subclass sets ``name``, ``Settings`` (a
    frozen dataclass with ``of(splat_config)``), ``ROWS``, ``FIRST_OPACITY``,
    ``FIRST_SCALE`` and ``UNSHARDED``, and overrides the hooks it uses: here the step's
    hooks do nothing and ``refine_due`` follows ``settings.schedule`` where there is one."""
    name: ClassVar[str]
    Settings: ClassVar[type]
    ROWS: ClassVar[tuple] = ()        # its per-Gaussian statistics, float32 [n] each
    FIRST_OPACITY: ClassVar[float] = 0.1   # the first Gaussians' (splat.init_opacity 0)
    FIRST_SCALE: ClassVar[float] = 1.0     # their size factor (splat.init_scale 0)
    UNSHARDED: ClassVar[str] = ""   # what of it MPI shards cannot run alone ("": nothing)

    def __init__(self, settings, device=None, seed: int = 0):
        self.settings = settings
        self.device = device        # where its statistics live and its kernels run
        self.seed = int(seed)       # the run's seed (a strategy's device draws)
        self.state = RefineState()
        self.rows = {}

    @classmethod
    def of(cls, config, device=None, seed: int = 0) -> "Strategy":
        """The strategy with its settings from SplatConfig ``config``."""
        return cls(cls.Settings.of(config), device, seed)

    @classmethod
    def first(cls, config) -> tuple[float, float]:
        """(opacity, size factor) of the first Gaussians: splat.init_opacity and
        splat.init_scale, or this strategy's published values where they are 0."""
        return (config.init_opacity or cls.FIRST_OPACITY, config.init_scale or cls.FIRST_SCALE)

    @property
    def absgrad(self) -> bool:
        """Whether the render record's screen gradients are the per-pixel absolute sums."""
        return False

    # ---- the running statistics, one row per Gaussian ----------------------------------------
    def allocate(self, n: int, rows: dict | None = None):
        """Statistics of n Gaussians on the device: ``rows`` {name: [n]} where given, else
        zeros."""
        q = self.device.queue
        rows = rows or {}
        self.rows = {k: (upload(q, np.ascontiguousarray(rows[k], np.float32)) if k in rows
                         else device_zeros(q, n, np.float32)) for k in self.ROWS}

    def release(self):
        self.rows = {}

    def host_rows(self) -> dict:
        """{name: float32 [n]} of the statistics."""
        return {k: download(a) for k, a in self.rows.items()}

    def zero_rows(self, idx):
        """Rows ``idx`` (int64) of every statistic set to 0 (rows overwritten in place)."""
        from pyopencl.array import multi_put, to_device
        if self.rows and len(idx):
            q = self.device.queue
            zero = device_zeros(q, 1, np.float32)
            multi_put([zero] * len(self.rows), to_device(q, np.asarray(idx, np.int64)),
                      out=list(self.rows.values()))

    # ---- the step's hooks ------------------------------------------------------------------
    def step_post_backward(self, params: dict, grads: dict, moments: dict, step: int,
                           render: RenderInfo):
        """After the backward, before the update (``grads`` may be added to)."""

    def step_post_update(self, params: dict, moments: dict, step: int, lr: float):
        """After the Adam update of step ``step``."""

    # ---- the schedule ----------------------------------------------------------------------
    def refine_due(self, it: int, f: float, step: int) -> bool:
        """Whether iteration ``it`` at budget fraction f refines (then counted as done): by
        the settings' ``schedule`` (a Schedule; none: never)."""
        sched = getattr(self.settings, "schedule", None)
        if sched is None or not sched.due(self.state, it, f, step):
            return False
        self.state.last_refine, self.state.refine_frac = it, f
        return True

    def step_schedule(self, params: dict, moments: dict, f: float, step: int) -> list:
        """The strategy's own edits of this iteration after a refinement: log lines."""
        return []

    def refine(self, host: dict, moments: dict, rows: dict, *, extent: float, cap: int,
               rng) -> tuple:
        """(host, moments, log line) after one refinement, on numpy arrays (host: the
        parameters, moments: Adam's, rows: ``host_rows``), through ``params.edit_rows``."""
        raise NotImplementedError(f"strategy {self.name!r} refines nothing")

    def refine_in_place(self, table, cap: int, rng):
        """The refinement on the device where it keeps the count: a log line, or None where
        ``refine`` must run. ``table``: the model's rows (``n``, ``params``, ``get_rows``,
        ``put_rows``)."""
        return None

    # ---- checkpoints -----------------------------------------------------------------------
    def state_dict(self) -> dict:
        out = self.state.state_dict()
        out.update({ROW_PREFIX + k: v for k, v in self.host_rows().items()})
        return out

    def load_state_dict(self, state: dict, n: int):
        """The counters and statistics of a checkpoint of n Gaussians (one written before
        strategies owned their statistics: its ``adam_stats`` [3, n], rows in ``ROWS``
        order)."""
        self.state = RefineState.from_state(state)
        rows = {k: np.asarray(state[ROW_PREFIX + k], np.float32) for k in self.ROWS
                if ROW_PREFIX + k in state}
        if not rows and OLD_STATS in state:
            old = np.asarray(state[OLD_STATS], np.float32)
            rows = dict(zip(self.ROWS, old))
        for k, v in rows.items():
            if v.shape != (n,):
                raise ValueError(f"statistic {k!r}: shape {v.shape}, expected ({n},)")
        self.allocate(n, rows)

    @classmethod
    def row_keys(cls) -> tuple:
        """The checkpoint keys of its per-Gaussian statistics."""
        return tuple(ROW_PREFIX + k for k in cls.ROWS)
