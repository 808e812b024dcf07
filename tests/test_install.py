"""The wheel carries the kernels: build it, install it into a fresh target, render from there."""
import os
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent


@pytest.mark.slow
def test_wheel_installs_and_renders(tmp_path):
    wheels = tmp_path / "wheels"
    r = subprocess.run([sys.executable, "-m", "pip", "wheel", "--no-deps", "--no-build-isolation",
                        "-w", str(wheels), str(ROOT)], capture_output=True, text=True)
    if r.returncode != 0 and "No module named" in r.stderr and "setuptools" in r.stderr:
        pytest.fail("setuptools missing from the test environment (it is in the 'test' extra)")
    assert r.returncode == 0, r.stderr[-2000:]
    (whl,) = wheels.glob("clrf-*.whl")
    target = tmp_path / "site"
    r = subprocess.run([sys.executable, "-m", "pip", "install", "--no-deps", "--target",
                        str(target), str(whl)], capture_output=True, text=True)
    assert r.returncode == 0, r.stderr[-2000:]
    assert (target / "clrf" / "cl" / "grid_render.cl").is_file()
    assert (target / "clrf" / "viewer" / "page.html").is_file()   # the viewer's page
    for part in ("cl/hash.cl", "cl/hash_occ.h", "cl/hash_march.cl", "hash/model.py"):
        assert (target / "clrf" / part).is_file(), part     # the hash model is packaged
    # every package of the layout (docs/architecture.md), the CLI's entry point among them
    for pkg in ("runtime", "grid", "nerf", "hash", "data", "outputs", "training", "viewer", "cli",
                "testing"):
        assert (target / "clrf" / pkg / "__init__.py").is_file(), pkg
    assert (target / "clrf" / "cli" / "__main__.py").is_file()
    script = (
        "import numpy as np, clrf, clrf.runtime.programs as p, clrf.cli\n"
        "assert callable(clrf.cli.main)\n"
        "assert 'site' in str(p.cl_dir()), p.cl_dir()\n"
        "dev = clrf.Device()\n"
        "g = clrf.SparseGrid.from_dense(dev, np.ones((2,2,2)), np.zeros((2,2,2,3)), [[0,0,0],[1,1,1]])\n"
        "out = clrf.render_rays(g, np.array([[0.5,0.5,-1.0]]), np.array([[0,0,1.0]]))\n"
        "print(float(out['acc'][0]))\n")
    env = dict(os.environ, PYTHONPATH=str(target))
    r = subprocess.run([sys.executable, "-c", script], cwd=str(tmp_path), env=env,
                       capture_output=True, text=True)
    assert r.returncode == 0, r.stderr[-2000:]
    assert abs(float(r.stdout.strip()) - (1 - __import__("math").exp(-1.0))) < 1e-4
