"""Shared fixtures: the PoCL OpenCL env, a seeded RNG, the shared data folder."""
from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

REPO = Path(__file__).resolve().parents[1]
SHARED_DATA = REPO.parent / "shared" / "data"


@pytest.fixture(scope="session")
def cl_env():
    """The default OpenCL env (PoCL CPU); tests run on it as CI does."""
    from dermis.pipeline.cl import get_env
    return get_env()


@pytest.fixture
def rng():
    return np.random.default_rng(20061)


@pytest.fixture(scope="session")
def shared_data() -> Path:
    if not SHARED_DATA.is_dir():
        pytest.skip(f"shared assets not found at {SHARED_DATA} (they live beside the repo)")
    return SHARED_DATA
