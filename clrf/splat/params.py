"""The splat model's one parameter table: each per-Gaussian parameter's name, shape and learning
rate, which the device parameters, both Adam moments, the density edits, the checkpoint and
the PLY share (the SH coefficients are an ordinary entry: their rate is a pair, degree 0 and
the higher bands).

Every structural edit of the Gaussians (clone, split, prune, relocate, add) goes through
``edit_rows``, which edits the parameters and both moments of every entry together, so a
Gaussian's moments cannot be left behind or given to another.

>>> host, moments = edit_rows(host, moments, keep=alive, append=children)
>>> host, moments = edit_rows(host, moments, assign=(idx, {"opacity_logits": new_o}))
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class Param:
    """One per-Gaussian parameter: ``tail`` its shape after the Gaussian axis ("B": the SH
    basis count), ``lr`` the SplatConfig field(s) of its Adam learning rate."""
    name: str
    tail: tuple
    lr: tuple


TABLE = (
    Param("means", (3,), ("lr_position",)),             # times the extent, decayed (model.py)
    Param("log_scales", (3,), ("lr_scaling",)),
    Param("quats", (4,), ("lr_rotation",)),              # (w, x, y, z), normalised when used
    Param("opacity_logits", (), ("lr_opacity",)),
    Param("sh", ("B", 3), ("lr_feature_dc", "lr_feature_rest")),   # basis 0, the others
)
NAMES = tuple(p.name for p in TABLE)
MOMENTS = ("m", "v")        # Adam's first and second moments: "{name}_m", "{name}_v"


def shapes(n: int, n_basis: int) -> dict:
    """{name: shape} for n Gaussians with ``n_basis`` SH coefficients per channel."""
    return {p.name: (int(n),) + tuple(n_basis if d == "B" else d for d in p.tail) for p in TABLE}


def moment_keys(name: str) -> tuple:
    return tuple(f"{name}_{m}" for m in MOMENTS)


def learning_rates(config, lr_means: float) -> dict:
    """{name: rate} of SplatConfig ``config`` (the means' rate as scheduled now, ``lr_means``;
    the SH coefficients' a pair (degree 0, the higher bands))."""
    out = {}
    for p in TABLE:
        rates = tuple(float(getattr(config, f)) for f in p.lr)
        out[p.name] = rates if len(rates) > 1 else rates[0]
    out["means"] = float(lr_means)
    return out


def zero_moments(host: dict) -> dict:
    return {k: np.zeros_like(host[p], np.float32) for p in NAMES for k in moment_keys(p)}


def edit_rows(host: dict, moments: dict, keep=None, assign=None, append=None) -> tuple:
    """(host, moments) after one structural edit, on numpy arrays (host: NAMES, moments: each
    name's "_m" and "_v"), in this order:
    ``assign`` (idx, {name: rows}): rows idx of the named parameters overwritten, the moments
    of rows idx zeroed in every entry (a changed Gaussian starts its Adam afresh);
    ``keep`` a boolean mask [n]: the rows kept (with their moments);
    ``append`` {name: rows} for every name: new Gaussians at the end, moments zero.
    The inputs are not modified."""
    n = int(host[NAMES[0]].shape[0])
    host = {k: np.array(host[k], np.float32, copy=True) for k in NAMES}
    moments = {k: np.array(moments[k], np.float32, copy=True)
               for p in NAMES for k in moment_keys(p)}
    for k, a in list(host.items()) + list(moments.items()):
        if a.shape[0] != n:
            raise ValueError(f"edit_rows: {k} has {a.shape[0]} rows, {NAMES[0]} {n}")
    if assign is not None:
        idx, rows = assign
        idx = np.asarray(idx, np.int64)
        for k, v in rows.items():
            if k not in host:
                raise KeyError(f"edit_rows: unknown parameter {k!r} (one of {NAMES})")
            host[k][idx] = v
        for k in moments:
            moments[k][idx] = 0
    if keep is not None:
        keep = np.asarray(keep, bool)
        if keep.shape != (n,):
            raise ValueError(f"edit_rows: keep has shape {keep.shape}, expected ({n},)")
        host = {k: a[keep] for k, a in host.items()}
        moments = {k: a[keep] for k, a in moments.items()}
    if append is not None:
        missing = [k for k in NAMES if k not in append]
        if missing:
            raise KeyError(f"edit_rows: appended rows lack {missing}")
        k_new = int(np.shape(append[NAMES[0]])[0])
        for k in NAMES:
            rows = np.asarray(append[k], np.float32).reshape((k_new,) + host[k].shape[1:])
            host[k] = np.concatenate([host[k], rows])
            for mk in moment_keys(k):
                moments[mk] = np.concatenate([moments[mk], np.zeros_like(rows)])
    return host, moments
