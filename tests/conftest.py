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


ASSETS = REPO / "scenes" / "assets"


@pytest.fixture(scope="session")
def assets() -> Path:
    """The assets that ship with the package (scan + sunset): present on every clone."""
    return ASSETS


@pytest.fixture(scope="session")
def wheel(tmp_path_factory) -> Path:
    """A wheel built from a clean copy of the repository (no stale build/ folder can leak in)."""
    import shutil
    import subprocess
    import sys
    tmp = tmp_path_factory.mktemp("wheel")
    src = tmp / "src"
    shutil.copytree(REPO, src, ignore=shutil.ignore_patterns(
        ".git", "build", "dist", "out", ".dermis-cache", "*.egg-info", "__pycache__"))
    subprocess.run([sys.executable, "-m", "pip", "wheel", "--no-deps", "--no-build-isolation",
                    "-q", "-w", str(tmp), str(src)], check=True, capture_output=True)
    found, = tmp.glob("dermis-*.whl")
    return found
