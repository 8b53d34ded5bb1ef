"""The report's adaptive-BSSRDF pages (reports/adaptive_pages.py) and the blend weight the
images carry (pipeline/artifacts.py RenderedImage.blend)."""
from __future__ import annotations

import numpy as np

from dermis.pipeline.artifacts import RenderedImage, load, save
from dermis.reports.adaptive_pages import ROWS, adaptive_pages, adaptive_rows


def image(model, light, geometry="high", value=1.0, blend=None):
    lin = np.full((16, 16, 3), value, np.float32)
    mask = np.ones((16, 16), bool)
    mask[:2] = False
    lin[~mask] = 0.0
    return RenderedImage(lin, mask, {"total": 1.0, "gather": 2.0 if model == "bssrdf" else 1.0},
                         {"model": model, "light": light, "geometry": geometry,
                          "gather": {"gathered_pixel_fraction": 0.25}}, blend=blend)


def test01_a_row_per_lighting_with_both_images_on_the_high_mesh():
    w = np.zeros((16, 16), np.float32)
    w[8:] = 1.0
    images = {}
    for light in ("point", "area", "sunset", "dir", "point@nose"):
        images[f"f-{light}"] = image("bssrdf", light)
        images[f"a-{light}"] = image("bssrdf_adaptive", light, value=1.01, blend=w)
    images["a-low"] = image("bssrdf_adaptive", "point", geometry="low_bump", blend=w)
    images["f-only"] = image("bssrdf", "lonely")       # no adaptive image: no row
    images["a-only"] = image("bssrdf_adaptive", "orphan", blend=w)   # no full image: no row
    rows = adaptive_rows(images)
    assert sorted(r[0] for r in rows) == ["area", "dir", "point", "point@nose", "sunset"]
    assert all(full.info["model"] == "bssrdf" and ad.info["geometry"] == "high"
               for _, full, ad in rows)


def test02_pages_hold_rows_rows_and_none_without_an_adaptive_image(tmp_path):
    from matplotlib.backends.backend_pdf import PdfPages
    w = np.linspace(0, 1, 256, dtype=np.float32).reshape(16, 16)
    images = {}
    for k in range(ROWS + 1):
        images[f"f{k}"] = image("bssrdf", f"l{k}")
        images[f"a{k}"] = image("bssrdf_adaptive", f"l{k}", value=1.0 + 0.001 * k, blend=w)
    with PdfPages(tmp_path / "r.pdf") as pdf:
        n = adaptive_pages(pdf, images)
        assert n == 2 and pdf.get_pagecount() == 2
    with PdfPages(tmp_path / "none.pdf") as pdf:
        assert adaptive_pages(pdf, {"f": image("bssrdf", "point")}) == 0


def test03_the_blend_weight_survives_the_cache(tmp_path):
    w = np.random.default_rng(0).random((16, 16)).astype(np.float32)
    save(image("bssrdf_adaptive", "point", blend=w), tmp_path / "a")
    np.testing.assert_array_equal(load(tmp_path / "a").blend, w)
    save(image("bssrdf", "point"), tmp_path / "b")
    assert load(tmp_path / "b").blend is None
