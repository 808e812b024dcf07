"""Distributed Plenoxels over MPI (clrf/distributed.py): `mpirun -n 2|3` runs of
tests/mpi_script.py compared with the single-device results in this process. Skips when mpirun
or mpi4py is missing (install: `bash tools/setup.sh test,mpi`)."""
import importlib.util
import os
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pyopencl.array as cla
import pytest

from clrf.grid.grid import SparseGrid
from clrf.grid.render import render_backward_device, render_forward_device
from clrf.testing.tolerances import (BRICK_COMPOSE_ATOL, BRICK_DEPTH_ATOL, GRAD_ATOL,
                                     GRAD_RTOL)

from mpi_script import BACKGROUND, BBOX, STEP, scene

HERE = Path(__file__).resolve().parent
MPIRUN = shutil.which("mpirun")
HAVE_MPI4PY = importlib.util.find_spec("mpi4py") is not None
pytestmark = pytest.mark.skipif(
    MPIRUN is None or not HAVE_MPI4PY,
    reason=f"needs mpirun ({'found' if MPIRUN else 'missing'}) and mpi4py "
           f"({'found' if HAVE_MPI4PY else 'missing'}): bash tools/setup.sh test,mpi")
MPI_TIMEOUT = 120   # seconds; a hung collective fails the test instead of the suite


def mpirun(n, *args, timeout=MPI_TIMEOUT, env=None, check=True):
    """Run `mpirun -n n python args...` from the repository root; returns the CompletedProcess."""
    cmd = [MPIRUN, "--oversubscribe", "--allow-run-as-root", "-n", str(n), sys.executable, *args]
    e = dict(os.environ, **(env or {}))
    e.setdefault("OMPI_MCA_rmaps_base_oversubscribe", "1")
    p = subprocess.run(cmd, cwd=HERE.parent, capture_output=True, text=True, timeout=timeout,
                       env=e)
    if check and p.returncode != 0:
        raise AssertionError(f"{' '.join(cmd)} exited {p.returncode}:\n{p.stdout}\n{p.stderr}")
    return p


@pytest.fixture(scope="module")
def single(device):
    """Single-device render and gradient without early termination (the distributed setting)."""
    dens, sh, o, d, g = scene()
    q = device.queue
    grid = SparseGrid.from_dense(device, dens, sh, BBOX)
    od, dd = cla.to_device(q, o), cla.to_device(q, d)
    out = {k: v.get() for k, v in
           render_forward_device(grid, od, dd, STEP, BACKGROUND, t_stop=0.0).items()}
    gd = cla.zeros(q, grid.density.shape[0], np.float32)
    gs = cla.zeros(q, grid.sh.shape, np.float32)
    render_backward_device(grid, od, dd, cla.to_device(q, g), STEP, BACKGROUND, gd, gs,
                           t_stop=0.0)
    out["gd"], out["gs"] = grid.rows_to_dense(gd.get(), gs.get())
    return out


@pytest.mark.parametrize("ranks", [2, 3])
def test_render_and_gradients_equal_single_device(single, tmp_path, ranks):
    out = tmp_path / "r.npz"
    mpirun(ranks, "tests/mpi_script.py", "render", str(out))
    r = np.load(out)
    np.testing.assert_allclose(r["rgb"], single["rgb"], rtol=0, atol=BRICK_COMPOSE_ATOL)
    np.testing.assert_allclose(r["acc"], single["acc"], rtol=0, atol=BRICK_COMPOSE_ATOL)
    np.testing.assert_allclose(r["depth"], single["depth"], rtol=0, atol=BRICK_DEPTH_ATOL)
    seen = np.zeros(single["gd"].shape, bool)
    for i in range(ranks):
        s = tuple(slice(a, b) for a, b in zip(r[f"lo{i}"], r[f"hi{i}"]))
        # every voxel a rank holds (its own and its halo replicas) has the full gradient
        np.testing.assert_allclose(r[f"gd{i}"], single["gd"][s], atol=GRAD_ATOL, rtol=GRAD_RTOL)
        np.testing.assert_allclose(r[f"gs{i}"], single["gs"][s], atol=GRAD_ATOL, rtol=GRAD_RTOL)
        seen[s] = True
    assert seen.all()
    # replicas of a halo voxel are bit-identical (summed in rank order on every holder), so the
    # optimiser keeps them equal
    for i in range(ranks):
        for j in range(i + 1, ranks):
            lo = np.maximum(r[f"lo{i}"], r[f"lo{j}"])
            hi = np.minimum(r[f"hi{i}"], r[f"hi{j}"])
            if np.any(hi <= lo):
                continue
            si = tuple(slice(a - o, b - o) for a, b, o in zip(lo, hi, r[f"lo{i}"]))
            sj = tuple(slice(a - o, b - o) for a, b, o in zip(lo, hi, r[f"lo{j}"]))
            np.testing.assert_array_equal(r[f"gd{i}"][si], r[f"gd{j}"][sj])
            np.testing.assert_array_equal(r[f"gs{i}"][si], r[f"gs{j}"][sj])
