"""Timing helpers shared by the device choice (workload.py) and the tuners of the
representations (e.g. the fused MLP's tiles, clrf/mlp/autotune.py): the best of a few timed
runs after a warm-up, and medians of candidates timed in interleaved rounds so a slow moment
of the machine hits every candidate alike."""
from __future__ import annotations

import time

import numpy as np


def best_time(step, repeats: int = 3) -> float:
    """The shortest wall time of ``repeats`` calls of ``step()``, after one warm-up call
    (builds, first touch of buffers)."""
    step()
    best = float("inf")
    for _ in range(repeats):
        t0 = time.perf_counter()
        step()
        best = min(best, time.perf_counter() - t0)
    return best


def interleaved_medians(steps, rounds: int = 5) -> list:
    """Median wall seconds of each of ``steps`` (callables), after one warm-up call each,
    timed in ``rounds`` rounds that call every step once."""
    for step in steps:
        step()
    times = [[] for _ in steps]
    for _ in range(rounds):
        for i, step in enumerate(steps):
            t0 = time.perf_counter()
            step()
            times[i].append(time.perf_counter() - t0)
    return [float(np.median(t)) for t in times]
