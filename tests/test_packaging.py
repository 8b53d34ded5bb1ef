"""Kernels and scene presets ship in the wheel: package data covers every file they need."""
import fnmatch
import tomllib
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]


def test01_package_data_covers_every_kernel_and_header():
    cfg = tomllib.loads((REPO / "pyproject.toml").read_text())["tool"]["setuptools"]
    patterns = cfg["package-data"]["dermis.cl"]
    assert "dermis.cl" in cfg["packages"]
    files = [p.name for p in (REPO / "cl").iterdir() if p.suffix in (".cl", ".h")]
    assert files, "no kernels found"
    missing = [f for f in files if not any(fnmatch.fnmatch(f, pat) for pat in patterns)]
    assert not missing, f"not shipped in a wheel: {missing}"


def test02_kernels_are_found_through_the_installed_package():
    from dermis.pipeline.cl import CL_DIR
    from dermis import cl
    assert CL_DIR == Path(cl.__file__).parent
    assert (CL_DIR / "common.h").is_file()


def test03_default_scene_ships_with_the_package():
    cfg = tomllib.loads((REPO / "pyproject.toml").read_text())["tool"]["setuptools"]
    assert "dermis.scenes" in cfg["packages"] and "*.toml" in cfg["package-data"]["dermis.scenes"]
    from dermis.pipeline.config import default_scene_path
    assert default_scene_path().is_file()


def test04_report_page_assets_ship_with_the_package():
    """The interactive page's HTML, CSS and JavaScript (reports/page/) are package data."""
    cfg = tomllib.loads((REPO / "pyproject.toml").read_text())["tool"]["setuptools"]
    patterns = cfg["package-data"]["dermis.reports"]
    files = [f"page/{p.name}" for p in (REPO / "reports" / "page").iterdir() if p.is_file()]
    assert len(files) >= 3
    missing = [f for f in files if not any(fnmatch.fnmatch(f, pat) for pat in patterns)]
    assert not missing, f"not shipped in a wheel: {missing}"
    from importlib import resources
    assert (resources.files("dermis.reports") / "page" / "page.js").is_file()
