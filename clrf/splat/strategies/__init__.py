"""The splat model's density strategies (``splat.strategy``): how its Gaussians are added,
moved and removed during training. The interface is ``base.Strategy`` (its text says what the
model calls and when); each strategy is one module here and one line of ``REGISTRY``:

- ``default`` (default.py): the published adaptive density control (Kerbl et al. 2023);
- ``mcmc`` (mcmc.py): 3DGS as Markov chain Monte Carlo (Kheradmand et al. 2024).

>>> strategy = make_strategy(splat_config, device, seed)   # its Settings from the config
>>> strategy.step_post_backward(params, grads, moments, step, render)
"""
from __future__ import annotations

from .base import RefineState, RenderInfo, Schedule, Strategy, logit
from .default import DefaultStrategy
from .mcmc import MCMCStrategy, relocation

REGISTRY = {
    "default": DefaultStrategy,
    "mcmc": MCMCStrategy,
}


def register(cls) -> type:
    """Add strategy class ``cls`` (a Strategy subclass) under ``cls.name``; returns it (so it
    also serves as a class decorator)."""
    if not (isinstance(cls, type) and issubclass(cls, Strategy)):
        raise TypeError(f"register: {cls!r} is not a Strategy subclass")
    if getattr(cls, "name", "") in ("", None):
        raise ValueError(f"register: {cls.__name__} has no name")
    REGISTRY[cls.name] = cls
    return cls


def strategy_class(name: str) -> type:
    """The class splat.strategy ``name`` registers."""
    if name not in REGISTRY:
        raise ValueError(f"splat.strategy: {name!r}; use one of {list(REGISTRY)}")
    return REGISTRY[name]


def make_strategy(config, device=None, seed: int = 0) -> Strategy:
    """The strategy splat.strategy names, with its settings from SplatConfig ``config``."""
    return strategy_class(config.strategy).of(config, device, seed)


__all__ = ["DefaultStrategy", "MCMCStrategy", "REGISTRY", "RefineState", "RenderInfo",
           "Schedule", "Strategy", "logit", "make_strategy", "register", "relocation",
           "strategy_class"]
