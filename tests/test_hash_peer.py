"""The Taichi peer of the hash encoding (tools/peers/taichi_hash.py) agrees with clrf at a tiny
size, and the hash benchmarks run in smoke mode. Skipped with the reason when taichi is not
installed (extra ``peers``: pip install 'clrf[peers]' or bash tools/setup.sh test,peers)."""
import sys
from pathlib import Path

import numpy as np
import pyopencl.array as cla
import pytest

from clrf.hash.encoding import HashEncoding
from clrf.testing import tolerances as tol

ROOT = Path(__file__).resolve().parents[1]


def _taichi_hash():
    pytest.importorskip("taichi", reason="taichi is not installed (extra 'peers')")
    sys.path.insert(0, str(ROOT / "tools"))
    from peers import taichi_hash
    return taichi_hash


@pytest.mark.parametrize("log2_t", [4, 12])
def test_taichi_peer_matches_clrf(device, log2_t):
    th = _taichi_hash()
    rng = np.random.default_rng(log2_t)
    box = ((-1.0, -2.0, 0.0), (1.0, 2.0, 3.0))
    table = rng.uniform(-1, 1, (5, 1 << log2_t, 2)).astype(np.float32)
    enc = HashEncoding(device.with_tuning(grad_slots=0), 5, 2, log2_t, 4, 128, box,
                       table=table)
    x = rng.uniform(-2.5, 3.5, (257, 3)).astype(np.float32)
    genc = rng.uniform(-1, 1, (257, enc.dim)).astype(np.float32)
    peer = th.TaichiHash(x, table, enc.res_host, enc.lo, enc.inv_ext, genc)
    q = device.queue
    xd = cla.to_device(q, x)
    np.testing.assert_allclose(peer.forward(), enc.forward(xd).get(), rtol=0,
                               atol=tol.HASH_ATOL)
    enc.backward(xd, cla.to_device(q, genc))
    g = enc.grad.get()
    np.testing.assert_allclose(peer.forward_backward(), g, rtol=0,
                               atol=tol.HASH_GRAD_ATOL + tol.HASH_GRAD_RTOL * np.abs(g).max())
