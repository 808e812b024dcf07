"""``splat.strategy=default``: the published adaptive density control (Kerbl et al. 2023).

Each step adds the screen-space gradient norm of every seen Gaussian's mean to running
statistics (``grad_accum``, ``grad_count``, ``max_radius``: cl/splat_train.cl
splat_densify_stats); every ``densify_every`` of the budget the Gaussians whose mean norm
reaches ``densify_grad_threshold`` are cloned (small) or split in two (large), transparent
ones (and after an opacity reset, huge ones) pruned, never above the cap; the statistics then
start again from zero. Every ``opacity_reset_every`` of the budget the opacities are lowered
to RESET_OPACITY.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ...runtime.programs import download, launch
from ..params import edit_rows
from .base import Schedule, Strategy, logit

RESET_OPACITY = 0.01            # opacities above it are lowered to it by a reset


def _twin():
    """The float64 helpers of clrf/references/reference_strategy.py (sigmoid, quat_rot),
    imported when a strategy first edits rows: nothing the command line imports before the
    device's self-check may import the references (tests/test_install.py)."""
    from ...references import reference_strategy
    return reference_strategy


@dataclass(frozen=True)
class DefaultSettings:
    """The default strategy's settings (from the splat section: ``of``)."""
    schedule: Schedule          # densify_from, densify_until, densify_every, densify_min_steps
    grad_threshold: float       # densify_grad_threshold (densify_absgrad_threshold: absgrad)
    percent_dense: float        # clone at or below this fraction of the extent, else split
    prune_opacity: float
    prune_screen_size: float    # pixels (after the first reset)
    prune_world_size: float     # fraction of the extent (after the first reset)
    reset_every: float          # opacity_reset_every (0: never)
    reset_min_steps: int
    absgrad: bool = False       # the statistics from |dL/dxy| per pixel

    @classmethod
    def of(cls, c) -> "DefaultSettings":
        return cls(Schedule(c.densify_from, c.densify_until, c.densify_every,
                            c.densify_min_steps),
                   c.densify_absgrad_threshold if c.absgrad else c.densify_grad_threshold,
                   c.percent_dense, c.prune_opacity, c.prune_screen_size, c.prune_world_size,
                   c.opacity_reset_every, c.opacity_reset_min_steps, bool(c.absgrad))


class DefaultStrategy(Strategy):
    """The published adaptive density control (see the module's text)."""
    name = "default"
    Settings = DefaultSettings
    ROWS = ("grad_accum", "grad_count", "max_radius")   # summed norms, views, largest radius
    FIRST_OPACITY = 0.1
    FIRST_SCALE = 1.0

    @property
    def absgrad(self) -> bool:
        return self.settings.absgrad

    def step_post_backward(self, params, grads, moments, step, render):
        """The step's densification statistics (splat_densify_stats; of the absolute screen
        gradients with absgrad: ``render.grad_xy`` is then those)."""
        n = int(params["means"].shape[0])
        r = self.rows
        prg = self.device.program("splat_train.cl")
        launch(self.device, prg.kernel("splat_densify_stats"), n,
               (np.int32(n), render.grad_xy.data, render.radius.data,
                np.float32(0.5 * render.width), np.float32(0.5 * render.height),
                r["grad_accum"].data, r["grad_count"].data, r["max_radius"].data))

    def step_schedule(self, params, moments, f, step):
        """The opacity reset when one is due: opacities above RESET_OPACITY lowered to it,
        their Adam moments zeroed."""
        s, st = self.settings, self.state
        if not (s.reset_every > 0 and f < s.schedule.stop):
            return []
        k = int(f / s.reset_every)
        if k <= st.resets or step - st.last_reset < s.reset_min_steps:
            return []
        st.resets, st.last_reset = k, step
        lo = logit(RESET_OPACITY)
        p = download(params["opacity_logits"])
        params["opacity_logits"].set(np.minimum(p, np.float32(lo)).astype(np.float32))
        for a in moments["opacity_logits"]:
            a.fill(0)
        return [f"opacities reset to {RESET_OPACITY}"]

    def refine(self, host, moments, rows, *, extent, cap, rng):
        """(host, moments, log line) after cloning, splitting and pruning, on numpy arrays;
        ``rows``: the statistics (summed gradient norms, view counts, largest screen radii)."""
        s = self.settings
        accum, count, max_radius = (np.asarray(rows[k], np.float64) for k in self.ROWS)
        grad = np.where(count > 0, accum / np.maximum(count, 1), 0.0)
        scale = np.exp(np.asarray(host["log_scales"], np.float64)).max(axis=1)
        big = s.percent_dense * extent
        # prune first: the room it frees is the room for new Gaussians
        prune = _twin().sigmoid(host["opacity_logits"]) < s.prune_opacity
        if self.state.resets > 0:
            prune |= (max_radius > s.prune_screen_size) | (scale > s.prune_world_size * extent)
        keep = ~prune
        if not keep.any():   # never remove every Gaussian
            keep[np.argmax(host["opacity_logits"])] = True
        room = max(int(cap) - int(keep.sum()), 0)
        idx = np.flatnonzero((grad >= s.grad_threshold) & keep)
        if len(idx) > room:   # the highest gradients first when the cap leaves too little room
            idx = idx[np.argsort(-grad[idx], kind="stable")[:room]]
        clone, split = idx[scale[idx] <= big], idx[scale[idx] > big]
        new = {k: [np.asarray(host[k])[clone]] for k in host}
        if len(split):   # two samples of each split Gaussian, scales / 1.6, replace it
            sc = np.exp(np.asarray(host["log_scales"], np.float64)[split])
            R = _twin().quat_rot(host["quats"][split])
            for _ in range(2):
                z = rng.standard_normal((len(split), 3)) * sc
                new["means"].append(host["means"][split] + np.einsum("nij,nj->ni", R, z))
                new["log_scales"].append(np.log(sc / 1.6))
                for k in ("quats", "opacity_logits", "sh"):
                    new[k].append(np.asarray(host[k])[split])
        pruned = int((~keep).sum())
        keep[split] = False
        n0 = len(keep)
        host, moments = edit_rows(host, moments, keep=keep,
                                  append={k: np.concatenate(v) for k, v in new.items()})
        msg = (f"densified: {n0} -> {len(host['means'])} Gaussians ({len(clone)} cloned, "
               f"{len(split)} split, {pruned} pruned)")
        return host, moments, msg
