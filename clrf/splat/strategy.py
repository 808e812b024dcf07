"""How the splat model's Gaussians are added, moved and removed during training: a density
strategy, chosen with ``splat.strategy``.

- ``default``: the published adaptive density control (Kerbl et al. 2023). Each step adds the
  screen-space gradient norm of every seen Gaussian's mean to running statistics; every
  ``densify_every`` of the budget the Gaussians whose mean norm reaches
  ``densify_grad_threshold`` are cloned (small) or split in two (large), transparent ones (and
  after an opacity reset, huge ones) pruned, never above the cap.
- ``mcmc``: 3D Gaussian splatting as Markov chain Monte Carlo (Kheradmand et al., NeurIPS
  2024). The Gaussians are samples under a hard cap from the start: at each refinement the
  dead ones (opacity <= ``prune_opacity``) are moved onto live ones drawn in proportion to
  opacity, and the count grows by ``mcmc_growth`` up to the cap, with the opacity and scale of
  every sampled Gaussian and its copies chosen so that together they render as it did
  (``relocation``), each copy starting ``mcmc_spread`` times a draw from that covariance away
  from it (published: in place, where a copy and its original take the same gradients until
  the noise parts them); after each Adam step the means take noise shaped by their
  covariance, large for transparent Gaussians and vanishing for opaque ones; L1 regularisers
  on opacity and scale keep unused Gaussians transparent and small. No opacity resets, no
  gradient statistics.

A strategy has its settings (a frozen dataclass built from the SplatConfig), keeps its running
state in a separate record (``RefineState``, saved with the checkpoint), and has hooks that
the model calls around each step: ``after_backward`` (statistics, regularisers' gradients),
``after_step`` (noise) and ``on_iteration`` (the schedule: refinement, opacity resets). The
decisions themselves (``refine``) work on numpy arrays, so each strategy is tested on arrays
without a device or a dataset; every edit goes through ``params.edit_rows``. An edit that keeps
the count may also run in place on the device (``refine_in_place``, mcmc's relocation at the
cap: the same decisions, with no copy of every parameter; tested against ``refine``).
"""
from __future__ import annotations

from dataclasses import dataclass, fields

import numpy as np
from scipy.special import comb

from ..references.reference_strategy import quat_rot, sigmoid
from ..runtime.programs import launch
from .config import STRATEGIES
from .params import edit_rows

RESET_OPACITY = 0.01            # opacities above it are lowered to it by a reset
MCMC_MAX_COPIES = 51            # relocation: at most this many copies of one Gaussian at once
OPACITY_EPS = 1.1920929e-07     # float32's epsilon: relocated opacities stay below 1 - eps


def logit(p):
    return np.log(p / (1.0 - p))


@dataclass(frozen=True)
class StepInfo:
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
    """A strategy's running state between steps (checkpointed): the iteration and budget
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


# ---- the refinement schedule (both strategies) ---------------------------------------------
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


# ---- default: adaptive density control ------------------------------------------------------
@dataclass(frozen=True)
class DefaultStrategy:
    """The published adaptive density control (see the module's text)."""
    schedule: Schedule
    grad_threshold: float
    percent_dense: float
    prune_opacity: float
    prune_screen_size: float
    prune_world_size: float
    reset_every: float
    reset_min_steps: int
    absgrad: bool = False       # the statistics from |dL/dxy| per pixel (ABSGRAD)
    name = "default"

    @classmethod
    def of(cls, c) -> "DefaultStrategy":
        return cls(Schedule(c.densify_from, c.densify_until, c.densify_every,
                            c.densify_min_steps),
                   c.densify_absgrad_threshold if c.absgrad else c.densify_grad_threshold,
                   c.percent_dense, c.prune_opacity, c.prune_screen_size, c.prune_world_size,
                   c.opacity_reset_every, c.opacity_reset_min_steps, bool(c.absgrad))

    def after_backward(self, model, info, grads):
        """The step's densification statistics (cl/splat_train.cl splat_densify_stats; of
        the absolute screen gradients with absgrad: StepInfo.grad_xy is then those)."""
        prg = model.device.program("splat_train.cl")
        launch(model.device, prg.kernel("splat_densify_stats"), model.n,
               (np.int32(model.n), info.grad_xy.data, info.radius.data,
                np.float32(0.5 * info.width), np.float32(0.5 * info.height),
                model.accum.data, model.count.data, model.max_radius.data))

    def after_step(self, model):
        pass

    def on_iteration(self, model, it: int, f: float) -> list:
        """The schedule's edits of this iteration: log lines."""
        st, msgs = model.refine_state, []
        if self.schedule.due(st, it, f, model.step):
            msgs.append(model.refine())
            st.last_refine, st.refine_frac = it, f
        if self.reset_every > 0 and f < self.schedule.stop:
            k = int(f / self.reset_every)
            if k > st.resets and model.step - st.last_reset >= self.reset_min_steps:
                st.resets, st.last_reset = k, model.step
                model.reset_opacity(RESET_OPACITY)
                msgs.append(f"opacities reset to {RESET_OPACITY}")
        return msgs

    def refine_in_place(self, model, rng):
        """None: cloning, splitting and pruning change the count (``refine``)."""
        return None

    def refine(self, host: dict, moments: dict, stats, *, extent: float, cap: int, resets: int,
               rng) -> tuple:
        """(host, moments, log line) after cloning, splitting and pruning, on numpy arrays;
        ``stats`` [3, n]: summed gradient norms, view counts, largest screen radii."""
        accum, count, max_radius = (np.asarray(s, np.float64) for s in stats)
        grad = np.where(count > 0, accum / np.maximum(count, 1), 0.0)
        scale = np.exp(np.asarray(host["log_scales"], np.float64)).max(axis=1)
        big = self.percent_dense * extent
        # prune first: the room it frees is the room for new Gaussians
        prune = sigmoid(host["opacity_logits"]) < self.prune_opacity
        if resets > 0:
            prune |= (max_radius > self.prune_screen_size) | \
                (scale > self.prune_world_size * extent)
        keep = ~prune
        if not keep.any():   # never remove every Gaussian
            keep[np.argmax(host["opacity_logits"])] = True
        room = max(int(cap) - int(keep.sum()), 0)
        idx = np.flatnonzero((grad >= self.grad_threshold) & keep)
        if len(idx) > room:   # the highest gradients first when the cap leaves too little room
            idx = idx[np.argsort(-grad[idx], kind="stable")[:room]]
        clone, split = idx[scale[idx] <= big], idx[scale[idx] > big]
        new = {k: [np.asarray(host[k])[clone]] for k in host}
        if len(split):   # two samples of each split Gaussian, scales / 1.6, replace it
            s = np.exp(np.asarray(host["log_scales"], np.float64)[split])
            R = quat_rot(host["quats"][split])
            for _ in range(2):
                z = rng.standard_normal((len(split), 3)) * s
                new["means"].append(host["means"][split] + np.einsum("nij,nj->ni", R, z))
                new["log_scales"].append(np.log(s / 1.6))
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


# ---- mcmc: 3DGS as Markov chain Monte Carlo -------------------------------------------------
def relocation(opacity, scale, copies):
    """(opacity', scale') [n], [n, ...] of each of ``copies`` [n] Gaussians that together
    replace one of opacity ``opacity`` and scales ``scale`` (Kheradmand et al. 2024, eq. 9):
    1 - (1 - o')^N = o (the same peak opacity), and the scales such that the N copies composited
    at one place integrate, along a line, to what the one did:
    o s = sum_{k=1..N} (-1)^(k+1) C(N, k) o'^k s' / sqrt(k). N is clipped to
    1..MCMC_MAX_COPIES; float64."""
    o = np.asarray(opacity, np.float64)
    N = np.clip(np.asarray(copies, np.int64), 1, MCMC_MAX_COPIES)
    o_new = 1.0 - np.power(1.0 - o, 1.0 / N)
    k = np.arange(1, MCMC_MAX_COPIES + 1)
    binom = comb(N[:, None], k)                                  # C(N, k), 0 for k > N
    terms = binom * (-1.0) ** (k + 1) * np.power(o_new[:, None], k) / np.sqrt(k)
    denom = terms.sum(1)
    s = np.asarray(scale, np.float64)
    factor = o / np.maximum(denom, 1e-300)
    return o_new, s * factor.reshape((-1,) + (1,) * (s.ndim - 1))


@dataclass(frozen=True)
class MCMCStrategy:
    """3DGS as MCMC (see the module's text)."""
    schedule: Schedule
    min_opacity: float
    growth: float
    noise_lr: float
    opacity_reg: float
    scale_reg: float
    spread: float
    name = "mcmc"
    absgrad = False

    @classmethod
    def of(cls, c) -> "MCMCStrategy":
        return cls(Schedule(c.densify_from, c.mcmc_until, c.densify_every, c.densify_min_steps),
                   c.prune_opacity, c.mcmc_growth, c.mcmc_noise_lr, c.mcmc_opacity_reg,
                   c.mcmc_scale_reg, c.mcmc_spread)

    def after_backward(self, model, info, grads):
        """The regularisers' gradients added to the step's (splat_mcmc_reg)."""
        if self.opacity_reg == 0 and self.scale_reg == 0:
            return
        n = model.n
        prg = model.device.program("splat_train.cl")
        p = model.params
        launch(model.device, prg.kernel("splat_mcmc_reg"), n,
               (np.int32(n), p["opacity_logits"].data, p["log_scales"].data,
                grads["opacity_logits"].data, grads["log_scales"].data,
                np.float32(self.opacity_reg / max(n, 1)),
                np.float32(self.scale_reg / max(3 * n, 1))))

    def after_step(self, model):
        """Noise on the means, after the Adam step (splat_mcmc_noise)."""
        scale = self.noise_lr * model.lr_means
        if scale <= 0:
            return
        prg = model.device.program("splat_train.cl")
        p = model.params
        launch(model.device, prg.kernel("splat_mcmc_noise"), model.n,
               (np.int32(model.n), p["means"].data, p["log_scales"].data, p["quats"].data,
                p["opacity_logits"].data, np.float32(scale), np.uint32(model.seed & 0xFFFFFFFF),
                np.uint32(model.step & 0xFFFFFFFF)))

    def on_iteration(self, model, it: int, f: float) -> list:
        st = model.refine_state
        if not self.schedule.due(st, it, f, model.step):
            return []
        st.last_refine, st.refine_frac = it, f
        return [model.refine()]

    def refine(self, host: dict, moments: dict, stats=None, *, extent: float = 1.0, cap: int,
               resets: int = 0, rng) -> tuple:
        """(host, moments, log line) after relocating the dead Gaussians and growing toward
        the cap, on numpy arrays."""
        o = sigmoid(host["opacity_logits"])
        dead = np.flatnonzero(o <= self.min_opacity)
        alive = np.flatnonzero(o > self.min_opacity)
        n0 = len(o)
        moved = 0
        if len(dead) and len(alive):
            host, moments = self._copy_onto(host, moments, alive, len(dead), rng, dead)
            moved = len(dead)
        n_add = max(0, self._grown(n0, cap) - n0)
        if n_add:
            host, moments = self._copy_onto(host, moments, np.arange(n0), n_add, rng, None)
        n1 = len(host["means"])
        return host, moments, (f"relocated {moved} of {n0} Gaussians, added {n1 - n0} "
                               f"(-> {n1}, cap {cap})")

    def _grown(self, n0: int, cap: int) -> int:
        """The count a refinement of n0 Gaussians grows toward: by ``growth``, at most
        ``cap``."""
        return min(int(cap), int(self.growth * n0) if self.growth > 1 else n0)

    def _draw(self, opacity_logits, log_scales, pool, k: int, rng) -> tuple:
        """(picked [k], opacity logits [k], log scales [k, 3]): k Gaussians of ``pool`` drawn in
        proportion to opacity (with replacement), and the relocated opacity and scale that each
        drawn one and its copies take."""
        o = sigmoid(opacity_logits)[pool]
        p = o / o.sum() if o.sum() > 0 else None
        picked = pool[rng.choice(len(pool), size=k, replace=True, p=p)]
        copies = np.bincount(picked, minlength=len(opacity_logits))[picked] + 1
        o_new, s_new = relocation(sigmoid(opacity_logits[picked]),
                                  np.exp(np.asarray(log_scales, np.float64)[picked]), copies)
        o_new = np.clip(o_new, self.min_opacity, 1.0 - OPACITY_EPS)
        return picked, logit(o_new), np.log(s_new)

    def _copy_onto(self, host, moments, pool, k: int, rng, dst):
        """Draw k Gaussians of ``pool`` (``_draw``), give each drawn one and its copies the
        relocated opacity and scale, and put the copies in rows ``dst`` (None: appended). The
        moments of every changed row start at zero."""
        picked, lo, ls = self._draw(host["opacity_logits"], host["log_scales"], pool, k, rng)
        copied = {k_: np.asarray(host[k_])[picked] for k_ in host}
        copied.update(opacity_logits=lo, log_scales=ls)
        copies = dict(copied, means=self._spread(copied, rng))
        if dst is None:   # the drawn rows changed, their copies appended: one edit
            return edit_rows(host, moments, assign=(picked, copied), append=copies)
        both = np.concatenate([picked, dst])
        return edit_rows(host, moments,
                         assign=(both, {k_: np.concatenate([v, copies[k_]])
                                        for k_, v in copied.items()}))

    def _spread(self, rows: dict, rng) -> np.ndarray:
        """The means of the copies of ``rows``: the drawn Gaussians' own (``spread`` 0, as
        published), or each moved by ``spread`` times a draw from its relocated covariance, so
        that a Gaussian and its copies do not start alike and take alike gradients. The draws
        come from a child stream spawned off ``rng`` (independent of it and of the other
        children), which leaves ``rng``'s own draws as they were: every other decision is the
        one spread 0 makes."""
        means = np.asarray(rows["means"], np.float32)
        if self.spread <= 0 or len(means) == 0:
            return means
        z = rng.spawn(1)[0].standard_normal(means.shape)
        z *= np.exp(np.asarray(rows["log_scales"], np.float64))
        off = np.einsum("nij,nj->ni", quat_rot(np.asarray(rows["quats"], np.float64)), z)
        return (means + self.spread * off).astype(np.float32)

    def refine_in_place(self, model, rng):
        """The refinement of ``refine`` on the model's device arrays, where the count stays
        (at the cap, the most of a run): only the opacities and scales come down, the drawn
        rows' other parameters are gathered on the device and the changed rows written back there
        (``model.put_rows``), so no copy of every parameter and moment is made. The same draws
        and values as ``refine`` on the downloaded arrays. None where the count would grow
        (``refine`` then)."""
        n0 = model.n
        if self._grown(n0, model.max_count) > n0:
            return None
        lo_all = model.get_rows("opacity_logits")
        o = sigmoid(lo_all)
        dead = np.flatnonzero(o <= self.min_opacity)
        alive = np.flatnonzero(o > self.min_opacity)
        moved = 0
        if len(dead) and len(alive):
            ls_all = model.get_rows("log_scales")
            picked, lo, ls = self._draw(lo_all, ls_all, alive, len(dead), rng)
            rows = {k: model.get_rows(k, picked) for k in model.params}
            rows.update(opacity_logits=lo, log_scales=ls)
            copies = dict(rows, means=self._spread(rows, rng))
            model.put_rows(np.concatenate([picked, dead]),
                           {k: np.concatenate([v, copies[k]]) for k, v in rows.items()})
            moved = len(dead)
        return f"relocated {moved} of {n0} Gaussians, added 0 (-> {n0}, cap {model.max_count})"


def make_strategy(config):
    """The strategy splat.strategy names, with its settings from SplatConfig ``config``."""
    if config.strategy == "mcmc":
        return MCMCStrategy.of(config)
    if config.strategy == "default":
        return DefaultStrategy.of(config)
    raise ValueError(f"splat.strategy: {config.strategy!r}; use one of {list(STRATEGIES)}")


__all__ = ["DefaultStrategy", "MCMCStrategy", "RefineState", "Schedule", "StepInfo",
           "make_strategy",
           "relocation", "STRATEGIES"]
