"""Shared fixtures: one device per test session, chosen by CLRF_DEVICE (default: the fastest
working device by its cached probe figure)."""
import os
from pathlib import Path

import pytest

import clrf


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
