"""The scan and the sunset ship with the package: checksums, loading, the default scene, credits."""
from __future__ import annotations

import hashlib
import subprocess
import sys
import textwrap
from pathlib import Path

import numpy as np
import pytest

from dermis.pipeline.config import default_scene_path, load_scene
from dermis.pipeline.plan import build_graph

REPO = Path(__file__).resolve().parents[1]
ATTRIBUTION = '"Infinite, 3D Head Scan" by Lee Perry-Smith'


def _sums(folder: Path) -> dict[str, str]:
    return {name: digest for digest, name in
            (line.split() for line in (folder / "SHA256SUMS").read_text().splitlines())}


@pytest.mark.parametrize("folder", ["lps_head", "env_sunset"])
def test01_assets_match_their_recorded_checksums(assets, folder):
    sums = _sums(assets / folder)
    assert sums, "no checksums recorded"
    for name, digest in sums.items():
        assert hashlib.sha256((assets / folder / name).read_bytes()).hexdigest() == digest, name
    shipped = {p.name for p in (assets / folder).iterdir()}
    assert set(sums) <= shipped and shipped - set(sums) <= {"SHA256SUMS", "ATTRIBUTION.txt",
                                                             "LICENSE.txt"}


def test02_packaged_scan_loads(assets):
    from dermis.geometry.scan import load_scan
    from dermis.geometry.validation import validate
    lps = assets / "lps_head"
    mesh = load_scan(lps / "LeePerrySmith_cm.obj", units="cm", texture=lps / "Map-COL.jpg")
    mesh, report = validate(mesh, source="packaged scan")
    assert len(mesh.faces) == 17684 and report["boundary_edges"] == 0   # a closed bust
    np.testing.assert_allclose(np.ptp(mesh.vertices, axis=0), [431, 400, 261], atol=1.0)  # mm
    assert mesh.texture_srgb.shape == (1024, 1024, 3)
    assert mesh.texture_srgb[..., 0].mean() > mesh.texture_srgb[..., 2].mean()   # skin is red


def test03_default_scene_is_the_scan_under_the_real_sunset():
    scene = load_scene()
    assert Path(scene.path) == default_scene_path()
    nodes, _ = build_graph(scene)
    src = nodes["mesh_source"].params
    assert src["source"] == "scan" and src["file"].endswith("assets/lps_head/LeePerrySmith_cm.obj")
    assert src["file_sha256"] == _sums(Path(src["file"]).parent)["LeePerrySmith_cm.obj"]
    env = [l for l in scene.lights if l.type == "environment"]
    assert env and env[0].map.endswith("venice_sunset_1k.hdr")
    assert [label for label, _ in scene.light_groups("main")] == ["point", "area",
                                                            "dir_left+dir_right", "sunset"]
    assert [v.name for v in scene.views] == ["ear", "nose_shadow", "lips", "eyelid"]
    assert any(ATTRIBUTION in c for c in scene.credits())


def test04_procedural_head_stays_a_preset():
    scene = load_scene(REPO / "scenes" / "procedural.toml")
    assert scene.mesh.source == "procedural" and scene.credits() == ()


def test05_assets_load_from_a_built_wheel_in_a_fresh_environment(wheel, tmp_path):
    """Install the wheel into a new virtual environment and load the packaged assets there,
    from a folder with no repository and no ../shared beside it."""
    venv = tmp_path / "venv"
    subprocess.run([sys.executable, "-m", "venv", "--system-site-packages", str(venv)],
                   check=True)
    py = venv / "bin" / "python"
    subprocess.run([str(py), "-m", "pip", "install", "-q", "--no-deps", "--no-index", str(wheel)],
                   check=True, capture_output=True)
    probe = textwrap.dedent(f"""
        import hashlib, sys
        from pathlib import Path
        import dermis
        from dermis.pipeline.config import load_scene
        from dermis.geometry.scan import load_scan
        root = Path(dermis.__file__).parent
        assert str(root).startswith({str(venv)!r}), root
        scene = load_scene()
        path = scene.mesh_path()
        assert root in path.parents, path
        mesh = load_scan(path, units="cm", texture=scene.resolve(scene.mesh.texture))
        assert len(mesh.faces) == 17684 and mesh.texture_srgb is not None
        sums = dict(reversed(l.split()) for l in (path.parent / "SHA256SUMS").read_text().splitlines())
        for name, digest in sums.items():
            assert hashlib.sha256((path.parent / name).read_bytes()).hexdigest() == digest, name
        print("ok", "|".join(scene.credits()))
    """)
    work = tmp_path / "elsewhere"
    work.mkdir()
    res = subprocess.run([str(py), "-c", probe], cwd=work, capture_output=True, text=True,
                         env={"PATH": "/usr/bin:/bin", "HOME": str(tmp_path)})
    assert res.returncode == 0, res.stderr[-2000:]
    assert res.stdout.startswith("ok") and ATTRIBUTION in res.stdout


def test06_attribution_on_the_report_title_page(tmp_path):
    """The scan's credit is on the report's first page (read back with pdftotext)."""
    import shutil
    from dermis.pipeline.artifacts import RenderedImage
    from dermis.reports import diff, pdf_report
    if shutil.which("pdftotext") is None:
        pytest.fail("pdftotext missing: .ci/setup installs poppler-utils")
    rng = np.random.default_rng(3)
    images = {}
    for model in ("lafortune", "bssrdf"):
        lin = rng.random((16, 16, 3)).astype(np.float32)
        images[f"render-{model}-point-high"] = RenderedImage(
            lin, np.ones((16, 16), bool), {"total": 1.0},
            {"model": model, "light": "point", "geometry": "high"})
    _, metrics = diff.write_differences(images, tmp_path, reference_model="bssrdf")
    credits = load_scene().credits()
    pdf = pdf_report.write_report(images, metrics, tmp_path / "r.pdf", scene_name="default",
                                  device="test", credits=credits)
    text = subprocess.run(["pdftotext", "-f", "1", "-l", "1", str(pdf), "-"],
                          capture_output=True, text=True, check=True).stdout
    assert "Lee Perry-Smith" in text and "CC BY 3.0" in text
