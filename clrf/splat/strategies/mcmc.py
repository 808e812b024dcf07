"""``splat.strategy=mcmc``: 3D Gaussian splatting as Markov chain Monte Carlo (Kheradmand et
al., NeurIPS 2024).

The Gaussians are samples under a hard cap from the start: at each refinement the dead ones
(opacity <= ``prune_opacity``) are moved onto live ones drawn in proportion to opacity, and
the count grows by ``mcmc_growth`` up to the cap, with the opacity and scale of every sampled
Gaussian and its copies chosen so that together they render as it did (``relocation``), each
copy starting ``mcmc_spread`` times a draw from that covariance away from it (published: in
place, where a copy and its original take the same gradients until the noise parts them);
after each Adam step the means take noise shaped by their covariance, large for transparent
Gaussians and vanishing for opaque ones; L1 regularisers on opacity and scale keep unused
Gaussians transparent and small. No opacity resets, no per-Gaussian statistics. Where the
count stays (at the cap) a refinement runs in place on the device (``refine_in_place``).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.special import comb

from ...runtime.programs import launch
from ..params import edit_rows
from .base import Schedule, Strategy, logit

MCMC_MAX_COPIES = 51            # relocation: at most this many copies of one Gaussian at once
OPACITY_EPS = 1.1920929e-07     # float32's epsilon: relocated opacities stay below 1 - eps


def _twin():
    """The float64 helpers of clrf/references/reference_strategy.py (sigmoid, quat_rot),
    imported when a strategy first edits rows: nothing the command line imports before the
    device's self-check may import the references (tests/test_install.py)."""
    from ...references import reference_strategy
    return reference_strategy


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
class MCMCSettings:
    """The MCMC strategy's settings (from the splat section: ``of``)."""
    schedule: Schedule          # densify_from, mcmc_until, densify_every, densify_min_steps
    min_opacity: float          # prune_opacity: at or below it a Gaussian is dead
    growth: float               # mcmc_growth
    noise_lr: float             # mcmc_noise_lr
    opacity_reg: float          # mcmc_opacity_reg
    scale_reg: float            # mcmc_scale_reg
    spread: float               # mcmc_spread

    @classmethod
    def of(cls, c) -> "MCMCSettings":
        return cls(Schedule(c.densify_from, c.mcmc_until, c.densify_every, c.densify_min_steps),
                   c.prune_opacity, c.mcmc_growth, c.mcmc_noise_lr, c.mcmc_opacity_reg,
                   c.mcmc_scale_reg, c.mcmc_spread)


class MCMCStrategy(Strategy):
    """3DGS as MCMC (see the module's text)."""
    name = "mcmc"
    Settings = MCMCSettings
    FIRST_OPACITY = 0.5
    FIRST_SCALE = 0.1
    UNSHARDED = "MCMC's regularisers and relocation (weighted by the whole count)"

    def step_post_backward(self, params, grads, moments, step, render):
        """The regularisers' gradients added to the step's (splat_mcmc_reg)."""
        s = self.settings
        if s.opacity_reg == 0 and s.scale_reg == 0:
            return
        n = int(params["means"].shape[0])
        prg = self.device.program("splat_train.cl")
        launch(self.device, prg.kernel("splat_mcmc_reg"), n,
               (np.int32(n), params["opacity_logits"].data, params["log_scales"].data,
                grads["opacity_logits"].data, grads["log_scales"].data,
                np.float32(s.opacity_reg / max(n, 1)),
                np.float32(s.scale_reg / max(3 * n, 1))))

    def step_post_update(self, params, moments, step, lr):
        """Noise on the means, after the Adam step (splat_mcmc_noise), ``noise_lr`` times the
        means' rate ``lr``."""
        scale = self.settings.noise_lr * lr
        if scale <= 0:
            return
        n = int(params["means"].shape[0])
        prg = self.device.program("splat_train.cl")
        launch(self.device, prg.kernel("splat_mcmc_noise"), n,
               (np.int32(n), params["means"].data, params["log_scales"].data,
                params["quats"].data, params["opacity_logits"].data, np.float32(scale),
                np.uint32(self.seed & 0xFFFFFFFF), np.uint32(step & 0xFFFFFFFF)))

    def refine(self, host, moments, rows=None, *, extent=1.0, cap, rng):
        """(host, moments, log line) after relocating the dead Gaussians and growing toward
        the cap, on numpy arrays."""
        mo = self.settings.min_opacity
        o = _twin().sigmoid(host["opacity_logits"])
        dead = np.flatnonzero(o <= mo)
        alive = np.flatnonzero(o > mo)
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
        g = self.settings.growth
        return min(int(cap), int(g * n0) if g > 1 else n0)

    def _draw(self, opacity_logits, log_scales, pool, k: int, rng) -> tuple:
        """(picked [k], opacity logits [k], log scales [k, 3]): k Gaussians of ``pool`` drawn in
        proportion to opacity (with replacement), and the relocated opacity and scale that each
        drawn one and its copies take."""
        o = _twin().sigmoid(opacity_logits)[pool]
        p = o / o.sum() if o.sum() > 0 else None
        picked = pool[rng.choice(len(pool), size=k, replace=True, p=p)]
        copies = np.bincount(picked, minlength=len(opacity_logits))[picked] + 1
        o_new, s_new = relocation(_twin().sigmoid(opacity_logits[picked]),
                                  np.exp(np.asarray(log_scales, np.float64)[picked]), copies)
        o_new = np.clip(o_new, self.settings.min_opacity, 1.0 - OPACITY_EPS)
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
        spread = self.settings.spread
        if spread <= 0 or len(means) == 0:
            return means
        z = rng.spawn(1)[0].standard_normal(means.shape)
        z *= np.exp(np.asarray(rows["log_scales"], np.float64))
        off = np.einsum("nij,nj->ni", _twin().quat_rot(np.asarray(rows["quats"], np.float64)), z)
        return (means + spread * off).astype(np.float32)

    def refine_in_place(self, table, cap, rng):
        """The refinement of ``refine`` on the table's device arrays, where the count stays
        (at the cap, the most of a run): only the opacities and scales come down, the drawn
        rows' other parameters are gathered on the device and the changed rows written back
        there (``table.put_rows``), so no copy of every parameter and moment is made. The same
        draws and values as ``refine`` on the downloaded arrays. None where the count would
        grow (``refine`` then)."""
        n0 = table.n
        if self._grown(n0, cap) > n0:
            return None
        mo = self.settings.min_opacity
        lo_all = table.get_rows("opacity_logits")
        o = _twin().sigmoid(lo_all)
        dead = np.flatnonzero(o <= mo)
        alive = np.flatnonzero(o > mo)
        moved = 0
        if len(dead) and len(alive):
            ls_all = table.get_rows("log_scales")
            picked, lo, ls = self._draw(lo_all, ls_all, alive, len(dead), rng)
            rows = {k: table.get_rows(k, picked) for k in table.params}
            rows.update(opacity_logits=lo, log_scales=ls)
            copies = dict(rows, means=self._spread(rows, rng))
            table.put_rows(np.concatenate([picked, dead]),
                           {k: np.concatenate([v, copies[k]]) for k, v in rows.items()})
            moved = len(dead)
        return f"relocated {moved} of {n0} Gaussians, added 0 (-> {n0}, cap {cap})"
