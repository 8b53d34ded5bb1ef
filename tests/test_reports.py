"""Difference images, error metrics and the PDF report (reports/diff.py, reports/pdf_report.py).

Synthetic RenderedImages only: a shaded disc on black, so every expected number is known in
closed form (a scaled copy has relative error exactly the scale - 1, and so on).
"""
from __future__ import annotations

import json
import math
import re
import shutil
import subprocess

import numpy as np
import pytest

from dermis.pipeline.artifacts import RenderedImage
from dermis.pipeline.errors import DermisError
from dermis.reports.diff import (REL_FLOOR_FRACTION, difference, difference_image, diverging_lut,
                          write_differences)

# Metrics are computed in float64 from float32 images: 1e-6 covers float32 rounding of
# the inputs (relative 6e-8) with a wide margin, and is far below any real error.
EXACT = 1e-6
SIZE = 48


def _disc(seed: int = 0, size: int = SIZE) -> tuple[np.ndarray, np.ndarray]:
    """A Lambert-shaded sphere-like disc (values in [0.2, 1] inside) and its mask."""
    rng = np.random.default_rng(seed)
    y, x = np.mgrid[0:size, 0:size]
    r = np.hypot(x - size / 2 + 0.5, y - size / 2 + 0.5) / (size * 0.42)
    mask = r < 1.0
    shade = 0.2 + 0.8 * np.sqrt(np.clip(1.0 - r * r, 0.0, 1.0))
    tint = np.array([1.0, 0.7, 0.55])
    img = shade[..., None] * tint * (1.0 + 0.05 * rng.standard_normal((size, size, 1)))
    img = np.clip(img, 0.05, None) * mask[..., None]
    return img.astype(np.float32), mask


def _rendered(model: str, light: str, geom: str, *, scale: float = 1.0, seed: int = 0,
              seconds: float = 1.0) -> RenderedImage:
    img, mask = _disc(seed)
    return RenderedImage(linear=(img * np.float32(scale)), mask=mask,
                         timings={"total": seconds, "shading": seconds / 2},
                         info={"model": model, "light": light, "geometry": geom})


def _all_finite(metrics: dict) -> bool:
    vals = []
    for v in metrics.values():
        vals.extend(v if isinstance(v, list) else [v])
    return all(math.isfinite(float(v)) for v in vals)


def test_identical_images_have_zero_difference_and_ssim_one():
    ref = _rendered("bssrdf", "point", "high")
    res = difference(ref, ref)
    assert np.all(res.diff == 0) and np.all(res.relative == 0)
    m = res.metrics
    assert m["rmse"] == 0 and m["rel_rmse"] == 0 and m["max_abs"] == 0 and m["rel_p95"] == 0
    assert m["bias_rgb"] == [0.0, 0.0, 0.0]
    assert m["ssim"] == pytest.approx(1.0, abs=EXACT)
    assert m["pixels"] == int(ref.mask.sum())


def test_known_bias_gives_relative_error_of_the_scale():
    ref = _rendered("bssrdf", "point", "high")
    img = _rendered("lafortune", "point", "high", scale=1.1)
    m = difference(img, ref).metrics
    # The disc's values (>= 0.05) all exceed the floor (5 % of the mean, ~0.02), so the
    # relative error is exactly 0.1 at every pixel.
    assert np.allclose(m["bias_rgb"], 0.1, atol=EXACT)
    assert np.allclose(m["flux_ratio_rgb"], 0.1, atol=EXACT)
    assert m["rel_rmse"] == pytest.approx(0.1, abs=EXACT)
    assert m["rel_p95"] == pytest.approx(0.1, abs=EXACT)
    assert m["max_abs"] == pytest.approx(0.1 * float(ref.linear.max()), rel=EXACT)
    # A uniform gain keeps structure: SSIM stays high but below 1 (the luminance term).
    assert 0.95 < m["ssim"] < 1.0


def test_constant_offset_gives_rmse_of_the_offset():
    ref = _rendered("bssrdf", "point", "high")
    img = RenderedImage(linear=ref.linear + np.float32(0.05) * ref.mask[..., None],
                        mask=ref.mask, info=dict(ref.info))
    m = difference(img, ref).metrics
    assert m["rmse"] == pytest.approx(0.05, rel=EXACT)
    assert m["max_abs"] == pytest.approx(0.05, rel=EXACT)
    assert m["bias_rgb"][0] > 0


def test_pixels_outside_the_mask_do_not_count():
    ref = _rendered("bssrdf", "point", "high")
    base = difference(_rendered("hk93", "point", "high", scale=1.2), ref).metrics

    # 1) garbage outside both masks (where a renderer writes 0) changes nothing
    img = _rendered("hk93", "point", "high", scale=1.2)
    img.linear[~img.mask] = 50.0
    assert difference(img, ref).metrics == base

    # 2) a region the image does not cover is excluded even though the reference covers it
    img2 = _rendered("hk93", "point", "high", scale=1.2)
    hole = np.zeros_like(img2.mask)
    hole[: SIZE // 2] = True
    img2.mask = img2.mask & ~hole
    img2.linear[hole] = 1e3  # would dominate every metric if it counted
    res = difference(img2, ref)
    assert res.metrics["pixels"] == int((ref.mask & ~hole).sum())
    assert res.metrics["rel_rmse"] == pytest.approx(0.2, abs=EXACT)
    assert np.all(res.diff[hole] == 0)

    # 3) an explicit mask restricts further
    res3 = difference(_rendered("hk93", "point", "high", scale=1.2), ref, mask=~hole)
    assert res3.metrics["pixels"] == res.metrics["pixels"]
    assert res3.metrics["rel_rmse"] == pytest.approx(0.2, abs=EXACT)


def test_black_pixels_give_no_nan():
    ref = _rendered("bssrdf", "point", "high")
    img = _rendered("lafortune", "point", "high")
    ref.linear[: SIZE // 2] = 0.0      # reference in shadow, image lit there
    img.linear[:, : SIZE // 3] = 0.0   # image in shadow, reference lit there
    res = difference(img, ref)
    assert np.all(np.isfinite(res.relative)) and _all_finite(res.metrics)
    # Where the reference is black, relative error = image / floor, floor = 5 % of the mean.
    floor = np.array(res.metrics["rel_floor_rgb"])
    mean_ref = ref.linear[ref.mask].mean(axis=0)
    assert np.allclose(floor, REL_FLOOR_FRACTION * mean_ref, rtol=EXACT)
    i, j = SIZE // 4, SIZE // 2
    assert ref.mask[i, j]
    assert np.allclose(res.relative[i, j], img.linear[i, j] / floor, rtol=1e-5)

    # Entirely black images, and a black reference with a lit image: still finite.
    black = RenderedImage(linear=np.zeros((SIZE, SIZE, 3), np.float32), mask=ref.mask,
                          info=dict(ref.info))
    assert _all_finite(difference(black, black).metrics)
    assert difference(black, black).metrics["ssim"] == pytest.approx(1.0)
    m = difference(img, black).metrics
    assert _all_finite(m) and m["rel_rmse"] > 0
    # An empty mask: zeros, not NaN.
    m0 = difference(img, ref, mask=np.zeros((SIZE, SIZE), bool)).metrics
    assert _all_finite(m0) and m0["pixels"] == 0


def test_ssim_drops_with_structure_loss():
    ref = _rendered("bssrdf", "point", "high")
    rng = np.random.default_rng(3)
    noisy = RenderedImage(linear=ref.linear * (1 + 0.5 * rng.standard_normal(ref.linear.shape))
                          .astype(np.float32) * ref.mask[..., None], mask=ref.mask)
    assert difference(noisy, ref).metrics["ssim"] < 0.9


def test_diverging_colour_map_is_symmetric():
    lut = diverging_lut()
    assert np.allclose(lut[::-1], lut[:, ::-1])  # entry n-1-k = entry k with R and B swapped

    d = np.zeros((4, 5, 3), np.float32)
    levels = [0.1, 0.35, 0.5, 0.9, 2.0]  # the last one is clipped at the scale
    for j, v in enumerate(levels):
        d[0, j] = v     # brighter than the reference
        d[1, j] = -v    # darker by the same amount
    mask = np.ones((4, 5), bool)
    mask[3] = False
    from dermis.reports.diff import DiffResult
    img = difference_image(DiffResult(diff=d, relative=d, mask=mask), scale=1.0)
    assert img.dtype == np.uint8 and img.shape == (4, 5, 3)
    assert np.array_equal(img[0], img[1][:, ::-1])           # mirrored colours
    assert np.all(img[0, :, 0] > img[0, :, 2])               # positive = red
    assert np.all(img[1, :, 2] > img[1, :, 0])               # negative = blue
    zero = img[2, 0].astype(int)
    assert zero.min() > 200 and zero.max() - zero.min() < 8  # zero = light neutral grey
    assert np.all(img[3] == 0)                               # black outside the mask
    # Stronger differences are farther from the neutral colour of "no difference".
    dist = np.linalg.norm(img[0].astype(float) - zero, axis=1)
    assert np.all(np.diff(dist[:4]) > 0) and dist[4] >= dist[3]


def _scene_images(models=("bssrdf", "lafortune", "hk93"), lights=("point", "sun"),
                  geoms=("high", "low_bump")) -> dict:
    images, k = {}, 0
    for m in models:
        for l in lights:
            for g in geoms:
                scale = {"bssrdf": 1.0, "lafortune": 1.05, "hk93": 0.8}.get(m, 1.0)
                scale *= 1.0 if g == "high" else 1.02
                scale *= 1.0 if l == "point" else 3.0
                k += 1
                images[f"render-{m}-{l}-{g}"] = _rendered(m, l, g, scale=scale, seed=k,
                                                          seconds=0.1 * k)
    return images


def test_write_differences_files_and_metrics(tmp_path):
    images = _scene_images()
    files, metrics = write_differences(images, tmp_path)
    names = {p.name for p in files}
    expected = {f"diff-{m}-{l}-{g}.png" for m in ("lafortune", "hk93") for l in ("point", "sun")
                for g in ("high", "low_bump")}
    expected |= {f"geomdiff-{m}-{l}-low_bump.png" for m in ("bssrdf", "lafortune", "hk93")
                 for l in ("point", "sun")}
    expected |= {"diffgrid-high.png", "diffgrid-low_bump.png", "geomgrid-low_bump.png",
                 "metrics.json"}
    assert names == expected
    assert all(p.is_file() and p.stat().st_size > 0 for p in files)

    on_disk = json.loads((tmp_path / "metrics.json").read_text())
    assert on_disk["reference_model"] == "bssrdf"
    assert set(on_disk["scales"]["model"]) == {"point", "sun"}  # one shared scale per light
    mvr = on_disk["model_vs_reference"]
    assert len(mvr) == 8 and len(on_disk["geometry_vs_high"]) == 6
    rec = mvr["hk93-point-high"]
    for key in ("rmse", "rel_rmse", "bias_rgb", "max_abs", "ssim", "rel_p95", "seconds",
                "reference_seconds", "model", "light", "geometry", "file"):
        assert key in rec, key
    assert rec["seconds"] == pytest.approx(images["render-hk93-point-high"].timings["total"])
    # hk93 is 0.8 x the reference (different noise seed, so only approximately)
    assert np.allclose(rec["flux_ratio_rgb"], -0.2, atol=0.02)
    assert on_disk["geometry_vs_high"]["lafortune-point-low_bump"]["rel_rmse"] < 0.1
    assert metrics == on_disk


def test_missing_reference_raises_clear_error(tmp_path):
    images = _scene_images(models=("lafortune", "hk93"))
    with pytest.raises(DermisError, match=r"bssrdf.*models present: hk93, lafortune"):
        write_differences(images, tmp_path)
    assert not (tmp_path / "metrics.json").exists()


def _pdf_pages(path) -> int:
    """Page count: pdfinfo (poppler) if installed, else count the page objects."""
    if shutil.which("pdfinfo"):
        out = subprocess.run(["pdfinfo", str(path)], capture_output=True, text=True,
                             check=True).stdout
        return int(re.search(r"Pages:\s+(\d+)", out).group(1))
    return len(re.findall(rb"/Type\s*/Page\b", path.read_bytes()))


def test_write_report_page_count(tmp_path):
    from dermis.reports.pdf_report import report_page_count, summary_text, write_report

    images = _scene_images()
    _, metrics = write_differences(images, tmp_path / "diff")
    extra = {("point", "mesh_high"): 0.5, ("point", "mesh_low"): 0.2}
    pdf = write_report(images, metrics, tmp_path / "report.pdf", scene_name="synthetic",
                       device="test device", timings_extra=extra)
    # title + images per geometry (2) + differences per geometry (2) + timing + scatter
    # + geometry page
    assert report_page_count(images, metrics) == 8
    assert _pdf_pages(pdf) == 8

    text = summary_text(images, metrics, timings_extra=extra)
    # lafortune (1.05 x) is closer to the reference than hk93 (0.8 x) under both lights
    assert "point: lafortune closest to bssrdf" in text
    assert "sun: lafortune closest to bssrdf" in text


def test_write_report_without_geometry_comparison(tmp_path):
    from dermis.reports.pdf_report import write_report

    images = _scene_images(lights=("point",), geoms=("low_bump",))
    _, metrics = write_differences(images, tmp_path / "diff")
    assert metrics["geometry_vs_high"] == {}
    pdf = write_report(images, metrics, tmp_path / "r.pdf", scene_name="s", device="d")
    assert _pdf_pages(pdf) == 1 + 1 + 1 + 3


# ---- the BSSRDF with the Monte Carlo profile -----------------------------------------------
def _mc_like(prof, noise=0.01, seed=0):
    """A Monte Carlo-shaped LayerProfile from a multipole one: its ring energy on geometric
    rings, each ring scaled by 1 + noise x N(0, 1), with that noise as the stated error."""
    import dataclasses
    from dermis.optics.profile_command import ring_energy
    edges = np.concatenate([[0.0], np.geomspace(0.02, 8.0, 60)])
    area = np.pi * np.diff(edges**2)[:, None]
    R = ring_energy(prof, edges) / area
    R = R * (1 + noise * np.random.default_rng(seed).standard_normal(R.shape))
    mid = 0.5 * (edges[1:] + edges[:-1])
    mid[0] = 0.0
    info = {"model": "monte_carlo", "r_edges": edges.tolist(), "R_err": (noise * R).tolist(),
            "T_err": np.zeros_like(R).tolist(), "Rd_err": [1e-4] * 3, "Tt_err": [0.0] * 3,
            "photons": 1000, "seed": seed, "seconds": 0.0, "noise_max_rel": [noise] * 3}
    return dataclasses.replace(prof, r_mm=mid, R=R, T=np.zeros_like(R), info=info)


def test_bssrdf_mc_in_sheets_differences_and_report(tmp_path):
    """bssrdf_mc renders are compared against the multipole bssrdf like any model, named
    "BSSRDF (Monte Carlo profile)" in the sheets and the PDF, kept out of the summary's
    closest/farthest ranking (it is the same model) and given a line of its own; the report
    node's profile page adds one page."""
    from dermis.optics.layers import PRESETS
    from dermis.reports.comparison_images import contact_sheet_image
    from dermis.reports.sheets import caption
    from dermis.reports.pdf_report import report_page_count, summary_text, write_report
    from dermis.reports.profile_pages import PAGES, profile_pages
    from dermis.optics.layer_profiles import build_profiles

    images = _scene_images(models=("bssrdf", "lafortune", "hk93", "bssrdf_mc"))
    _, metrics = write_differences(images, tmp_path / "diff")
    mvr = metrics["model_vs_reference"]
    assert {k for k in mvr if k.startswith("bssrdf_mc-")} == {
        f"bssrdf_mc-{l}-{g}" for l in ("point", "sun") for g in ("high", "low_bump")}
    assert all(r["reference"] == "bssrdf" for r in mvr.values())
    assert (tmp_path / "diff" / "diff-bssrdf_mc-point-high.png").is_file()
    assert caption("bssrdf_mc", "point") == "BSSRDF (Monte Carlo profile) / point"
    assert caption("bssrdf_mc", "dir_left+dir_right") == \
        "BSSRDF (Monte Carlo profile)\ndir_left+dir_right"
    sel = {k: v for k, v in images.items() if v.info["geometry"] == "high"}
    mapped = {k: (np.clip(v.linear, 0, 1) * 255).astype(np.uint8) for k, v in sel.items()}
    sheet = contact_sheet_image(sel, mapped)
    assert sheet.ndim == 3 and sheet.shape[0] > 4 * 256       # four model rows
    text = summary_text(images, metrics)
    assert "point: lafortune closest to bssrdf" in text          # not the bssrdf variant
    assert "BSSRDF (Monte Carlo profile) vs bssrdf, high geometry: relative RMSE" in text

    mp = build_profiles(PRESETS["skin2"])
    profiles = {"profiles": mp, "profiles-monte_carlo": _mc_like(mp)}
    added = {}
    pdf = write_report(images, metrics, tmp_path / "report.pdf", scene_name="s", device="d",
                       extra_pages=lambda p: added.setdefault("n", profile_pages(p, profiles)))
    assert added["n"] == PAGES == 1
    assert _pdf_pages(pdf) == report_page_count(images, metrics) + 1
    if shutil.which("pdftotext"):
        out = subprocess.run(["pdftotext", str(pdf), "-"], capture_output=True, text=True,
                             check=True).stdout
        assert "BSSRDF (Monte Carlo profile)" in out and "Layer profiles" in out
        assert "Monte Carlo table (1,000 photons/channel" in out
