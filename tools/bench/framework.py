"""What a benchmark is: Spec (data), Case (one repetition and its work), the factory registry,
the Context shared by the cases of a run, and the helpers they share. External suites
(tools/nerf_bench.py bench_suite(api)) get this module as ``api``."""
from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

import numpy as np
import clrf
import bench_scenes as scenes


TOOLS = Path(__file__).resolve().parents[1]
ROOT = TOOLS.parent
EXTERNAL_SUITES = ["nerf_bench"]   # modules in tools/ that may define bench_suite(api)


class Skip(Exception):
    """A case that cannot run here (missing peer, memory, kernel not landed): the reason."""


@dataclass
class Spec:
    name: str                 # unique; used by --only
    kind: str                 # factory key in FACTORIES
    params: dict              # passed to the factory
    metric: str = "samples/s" # headline metric for tables
    quick: dict = field(default_factory=dict)      # parameter overrides in --quick mode
    requires: tuple = ()      # ("module", "attribute") pairs that must exist, else skipped
    min_repeats: int | None = None  # overrides --min-repeats (slow peers: at least 3)


@dataclass
class Case:
    run: Callable[[], None]   # one repetition; returns when the device work is finished
    work: dict                # per repetition: samples, rays, segments, bytes, flop (any subset)
    info: dict = field(default_factory=dict)       # recorded as is (sizes, notes)
    check: dict | None = None # result of the correctness check made before timing


FACTORIES: dict[str, Callable] = {}


def factory(kind: str):
    def deco(fn):
        FACTORIES[kind] = fn
        return fn
    return deco


# ---- context shared by the cases of one run ----------------------------------------------
class Context:
    def __init__(self, dev, quick: bool):
        self.dev = dev
        self.quick = quick
        self._grid_key = None
        self._grid = None

    def grid(self, reso, degree, occupancy):
        """(links, density_rows, sh_rows, SparseGrid): the last one is kept for the next case."""
        key = (reso, degree, occupancy)
        if key != self._grid_key:
            self._grid = None
            C = 3 * (degree + 1) ** 2
            n_est = reso ** 3 * (1.0 if occupancy >= 1 else occupancy)
            need = n_est * (C + 1) * 4
            caps = self.dev.caps
            if n_est * C * 4 > caps.max_alloc_size:
                raise Skip(f"sh rows {n_est * C * 4 / 1e9:.2f} GB exceed the device's max "
                           f"allocation {caps.max_alloc_size / 1e9:.2f} GB")
            if need > 0.45 * caps.global_mem_size:
                raise Skip(f"grid {need / 1e9:.2f} GB leaves no room for gradients in "
                           f"{caps.global_mem_size / 1e9:.2f} GB of device memory")
            links, dens, sh = scenes.make_grid_rows(reso, degree, occupancy)
            g = clrf.SparseGrid.from_arrays(self.dev, links, dens, sh, scenes.BBOX)
            self._grid_key = key
            self._grid = (links, dens, sh, g)
        return self._grid


def _rays(p):
    return scenes.make_rays(p["rays"], p["n_rays"])


grid_bytes_per_sample = scenes.grid_bytes_per_sample
grid_flop_per_sample = scenes.grid_flop_per_sample


def _grid_work(p, links, o, d):
    seg, smp = scenes.count_samples(links, o, d, scenes.BBOX, p["step"])
    bwd = p.get("mode", "fwd") != "fwd"
    return {"rays": o.shape[0], "segments": seg, "samples": smp,
            "bytes": smp * grid_bytes_per_sample(p["degree"], bwd),
            "flop": smp * grid_flop_per_sample(p["degree"], bwd)}


def _compare(a, b, atol, rtol):
    a = np.asarray(a, np.float64)
    b = np.asarray(b, np.float64)
    err = np.abs(a - b)
    ok = bool(np.all(err <= atol + rtol * np.abs(b)))
    return {"max_abs_err": float(err.max(initial=0.0)), "ok": ok}
