"""tools/mpi_splat_bench.py's scaling model of a distributed splat step (docs/scaling.md): the
terms one rank measured, stretched and divided as the model says."""
import importlib.util
from pathlib import Path

import pytest

pytestmark = pytest.mark.quick


def _bench():
    path = Path(__file__).resolve().parents[1] / "tools" / "mpi_splat_bench.py"
    spec = importlib.util.spec_from_file_location("mpi_splat_bench", path)
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


TERMS = {"phases_s": {"project": 0.010, "exchange": 0.0, "render": 0.012, "loss": 0.008,
                      "return": 0.004, "backward": 0.008, "stats": 0.0, "adam": 0.006,
                      "host": 0.002}}


def test_one_rank_is_its_own_terms():
    b = _bench()
    one = b.predict(TERMS, 1, cores=2, bandwidth_gbps=None, latency_s=1e-5,
                    splats_per_view=1e5)
    assert one["step_s"] == pytest.approx(0.050) and one["comm_s"] == 0
    assert one["bytes_per_rank"] == 0 and one["views_per_s"] == pytest.approx(20.0)


def test_ranks_share_adam_and_pay_the_exchange():
    """Two ranks: Adam on half the rows, the rest of the compute per rank as one camera's
    whole; half the view's splats cross, 60 + 36 bytes each, at 10 Gb/s, and two messages
    to the other rank. Past the cores, the compute stretches."""
    b = _bench()
    two = b.predict(TERMS, 2, cores=2, bandwidth_gbps=10, latency_s=1e-5, splats_per_view=1e5)
    assert two["compute_s"] == pytest.approx(0.047)
    assert two["bytes_per_rank"] == pytest.approx(0.5 * 1e5 * 96)
    assert two["comm_s"] == pytest.approx(2e-5 + 0.5 * 1e5 * 96 * 8 / 1e10)
    three = b.predict(TERMS, 3, cores=2, bandwidth_gbps=None, latency_s=0.0,
                      splats_per_view=1e5)
    assert three["compute_s"] == pytest.approx(1.5 * (0.044 + 0.002))
