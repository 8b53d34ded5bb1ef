"""Shared fixtures: the PoCL OpenCL env, a seeded RNG, the shared data folder, the two-layer
skin's profiles."""
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
def two_layer_profile():
    """The layer profiles of the ``two_layer`` preset (optics/layer_profiles.py)."""
    from dermis.optics.layer_profiles import build_profiles
    from dermis.optics.layers import PRESETS
    return build_profiles(PRESETS["two_layer"])


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


# Hypothesis profiles for tests/test_stability.py (docs/hardening.md): "ci" is the default
# (derandomized: the same examples every run, a few per property, CI-sized); "thorough" is run
# with `pytest tests/test_stability.py --hypothesis-profile=thorough`.  No example database
# (nothing is written into the repository); failures print the reproducing blob.
try:
    from hypothesis import HealthCheck, Phase, settings as _hyp_settings
except ImportError:  # pragma: no cover - hypothesis is a dev extra
    pass
else:
    _common = dict(deadline=None, database=None, print_blob=True, report_multiple_bugs=False,
                   suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large,
                                          HealthCheck.function_scoped_fixture])
    _hyp_settings.register_profile("ci", max_examples=6, derandomize=True,   # no shrinking:
                                   phases=[Phase.explicit, Phase.generate], **_common)
    _hyp_settings.register_profile("thorough", max_examples=200, **_common)
    _hyp_settings.load_profile("ci")


# Tests longer than ~5 s on 2 cores (measured with `pytest --durations=60`), marked ``slow``
# so that `pytest -m "not slow"` is the edit-test loop; CI and the README's command run all.
# A module name marks the whole module (its fixtures run a whole scene); module::prefix marks
# the tests whose names start with prefix.
SLOW = (
    "test_pipeline.py",            # the quick scene built, rebuilt and compared across jobs
    "test_sweep.py",               # sweeps of the quick scene, serial and on Dask
    "test_reference.py::test08", "test_reference.py::test09",   # Mitsuba renders
    "test_report_page.py::test02", "test_report_page.py::test03",   # a tiny run + Chromium
    "test_reference_passes.py::test04", "test_reference_passes.py::test05",   # Mitsuba, Dask
    "test_convention.py",          # Mitsuba renders of a flat plate (~50 s)
    "test_hardening_config.py::test12",  # peak memory of a render measured in a subprocess
    "test_hardening.py::test15", "test_hardening.py::test16", "test_hardening.py::test19",
    "test_hardening.py::test23",
    "test_brdf_hk93.py::test13",   # single-scattering quadrature converging at |g| = 0.99
    "test_energy.py::test05c", "test_antialias.py::test04",
    "test_assets.py::test05",      # a wheel installed into a fresh environment
    "test_stability.py::test_hk93_directional_albedo_at_most_one",
    "test_stability.py::test12c",  # energy through non-scattering layers, adding-doubling
    "test_hardening_inputs.py::test08",   # every model's images over a grid of sharp shadows
    "test_profiles.py::test13", "test_profiles.py::test15",   # whole profile builds per stack
    "test_cycles.py::test04", "test_cycles.py::test05",   # Blender renders of the quick scene,
    "test_cycles.py::test07",                             # Cycles' slab; Cycles vs Mitsuba
)


def pytest_collection_modifyitems(config, items):
    slow = pytest.mark.slow
    for item in items:
        module = Path(str(item.fspath)).name
        if any(s == module or s == f"{module}::{item.name[:len(s) - len(module) - 2]}"
               for s in SLOW):
            item.add_marker(slow)


@pytest.fixture(scope="module")
def mi():
    """The Mitsuba module with a working variant (groundtruth/mitsuba.py), or the test skips
    with the reason: not installed, or installed but no variant runs here."""
    pytest.importorskip("mitsuba", reason="Mitsuba 3 is not installed (bash .ci/setup, or "
                                          "pip install mitsuba drjit): Mitsuba tests skipped")
    from dermis.groundtruth.mitsuba import MitsubaUnavailable, load_mitsuba
    try:
        return load_mitsuba()
    except MitsubaUnavailable as exc:
        pytest.skip(str(exc))
