"""Shared fixtures: one device per test session, chosen by CLRF_DEVICE (default: the fastest
working device by its cached probe figure)."""
import os
from pathlib import Path

import pytest

import clrf


@pytest.fixture(scope="session", autouse=True)
def _own_tuning_cache(tmp_path_factory):
    """Tests never read the user's tuned tiles (clrf/autotune.py): an empty cache folder."""
    old = os.environ.get("XDG_CACHE_HOME")
    os.environ["XDG_CACHE_HOME"] = str(tmp_path_factory.mktemp("xdg_cache"))
    yield
    if old is None:
        del os.environ["XDG_CACHE_HOME"]
    else:
        os.environ["XDG_CACHE_HOME"] = old


@pytest.fixture(scope="session")
def device():
    return clrf.Device()


@pytest.fixture(scope="session")
def device_gpu_path(device):
    """The session device running the GPU code path of the grid backward on any device: float
    atomics into the gradient buffers (grad_slots 0), no per-sample record."""
    return device.with_tuning(grad_slots=0, sample_record=False)


@pytest.fixture(scope="session", params=["default_path", "gpu_path"])
def render_device(request, device, device_gpu_path):
    """Both code paths of the grid backward: the device's own tuning (on CPU devices private
    gradient copies + the per-sample record) and the GPU path."""
    return device if request.param == "default_path" else device_gpu_path


@pytest.fixture(scope="session")
def data_dir():
    """$CLRF_DATA (the shared real scenes); tests that need it skip with the reason if unset."""
    p = os.environ.get("CLRF_DATA")
    if not p or not Path(p).is_dir():
        pytest.skip("CLRF_DATA is not set to the shared data folder (see ../shared/data/README.md)")
    return Path(p)
