"""clrf benchmark runner: benchmarks declared as data, device peaks measured in the same run.

    python tools/bench.py                       # everything; JSON to bench-results/bench-<time>.json
    python tools/bench.py --only 'grid.*128*'   # fnmatch pattern(s) on the benchmark names
    python tools/bench.py --quick               # smoke mode: tiny sizes, one repeat, checks only
    python tools/bench.py --list                # names and parameters, nothing run
    python tools/bench.py --only 'grid/fwdbwd/*' --only 'peer.taichi/fwdbwd/*' --interleave 9
    python tools/report.py bench-results/bench-*.json   # Markdown table + plots

Every benchmark is a ``Spec`` (name, kind, parameters, metric) in ``SPECS`` (specs.py); ``kind`` names a
factory in ``FACTORIES`` that builds the inputs and returns a ``Case``: a callable doing one
repetition (device work finished when it returns), the work it does (samples, rays, bytes,
flop) and an optional check against a reference. The runner warms each case up once (JIT),
then repeats until the timing is stable (relative inter-quartile range below ``--tol`` after
``--min-repeats``) or a cap (``--max-repeats``, ``--max-seconds``), and records the median and
the min-max. With ``--interleave ROUNDS`` every selected case is set up first and then timed in
ROUNDS rounds that run each case once, so that a ratio between two cases (clrf against a peer)
is measured over the same minutes. The device peaks (copy and triad bandwidth, FMA throughput at the device's native
float vector width, cl/bench.cl) are measured at the start and at the end of the run; every
throughput is also given as a ratio to them, because this class of machine sometimes halves
everything at once.

Adding benchmarks: append Specs (and, for a new kind, a factory registered with
``@factory("kind")``, cases.py). Kernels that have not landed are left out by name: a Spec whose
``requires`` names a missing module attribute is reported as skipped, with the reason.
Other suites plug in through ``EXTERNAL_SUITES``: a module there (e.g. tools/nerf_bench.py)
that defines ``bench_suite(api)`` returning Specs (``api`` is framework.py, for ``Spec``,
``Case`` and ``factory``) has them run and reported with the rest.

Peers (optional dependencies, skipped with the reason when not importable) run on identical
inputs after their outputs were checked against clrf's: the float64 numpy reference
(clrf.references.reference, small sizes), tools/peers/torch_grid.py (PyTorch CPU, autograd backward)
and tools/peers/taichi_grid.py (Taichi CPU).

Layout: framework.py (Spec, Case, factory, Context), cases.py (the factories), specs.py (the
list), runner.py (timing, metrics, JSON, command line); tools/bench.py is the entry script.
"""
import os

# A dense 256^3 SH-2 grid is 1.9 GB: raise PoCL's default 4.3 GB / 2.15 GB-per-buffer limits.
# Must be set before the OpenCL platform is loaded.
os.environ.setdefault("POCL_MEMORY_LIMIT", "16")

from .framework import Case, Context, Skip, Spec, factory  # noqa: E402
from .runner import main, run_interleaved, run_spec  # noqa: E402
from .specs import SPECS, _peak_specs, external_specs  # noqa: E402

__all__ = ["Case", "Context", "SPECS", "Skip", "Spec", "external_specs", "factory", "main",
           "run_interleaved", "run_spec", "_peak_specs"]
