"""Shared fixtures: one device per test session, chosen by CLRF_DEVICE (default: first working)."""
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
def data_dir():
    """$CLRF_DATA (the shared real scenes); tests that need it skip with the reason if unset."""
    p = os.environ.get("CLRF_DATA")
    if not p or not Path(p).is_dir():
        pytest.skip("CLRF_DATA is not set to the shared data folder (see ../shared/data/README.md)")
    return Path(p)
