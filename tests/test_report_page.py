"""The interactive comparison page ``report.html`` (reports/interactive_page.py,
reports/page_data.py, reports/page/): written by the report stage of a tiny run with a
path-traced reference, it lists every image of the run, carries every image's linear data
to the precision of half floats, and in a real browser (Debian's Chromium driven by
Playwright, or the test skips saying why) it loads without console errors, its grid shows
every image, and its comparator's read-out at a pixel is the EXR's value there.

Tolerance of the read-out: half floats round to nearest, so a value v >= 2^-14 is held to
|v| 2^-11 and a smaller one to 2^-25 (half the subnormal spacing), page_data.py."""
from __future__ import annotations

import base64
import json
import math
import os
import re
import shutil
from pathlib import Path

import numpy as np
import pytest

from dermis.pipeline.api import load_scene, run
from dermis.pipeline.imageio import read_image
from dermis.reports import page_data
from dermis.reports.interactive_page import PAGE

QUICK = Path(__file__).resolve().parents[1] / "scenes" / "quick.toml"
CHROMIUM = shutil.which("chromium")      # Debian's package (Ubuntu's chromium-browser is a snap stub)
# The tiny study: two models (the baseline BSSRDF and Lafortune), one light, two geometries,
# an 80-pixel camera and a 40-pixel reference of 8 samples per pixel
OVER = {"camera": {"width": 80, "height": 80},
        "mesh": {"high_triangles": 20_000, "low_triangles": 1_000,
                 "procedural_texture_size": 64, "procedural_detail": False},
        "bake": {"resolution": 64},
        "render": {"models": ["lafortune", "bssrdf"], "lights": ["point"],
                   "geometries": ["high", "low_bump"]},
        "reference": {"enabled": True, "width": 40, "height": 40, "min_spp": 8, "max_spp": 8,
                      "budget_s": 0, "slab_samples": 4096},
        "causes": {"enabled": False}}


@pytest.fixture(scope="module")
def study(tmp_path_factory):
    """(report folder, {(model, light, geometry): EXR path}, {light: reference EXR path})."""
    tmp = tmp_path_factory.mktemp("page")
    over = dict(OVER, output={"previews": False, "output_dir": str(tmp / "out")})
    summary = run(load_scene(QUICK, overrides=over), cache=tmp / "cache", export=False)
    by_id = {n.id: Path(n.path) for n in summary.nodes}
    renders, refs = {}, {}
    for nid, path in by_id.items():
        for exr in path.glob("*.exr"):
            if nid.startswith(("render-", "bssrdf-")):
                model, light, geom = exr.stem.rsplit("-", 2)
                renders[(model, light, geom)] = exr
            elif nid.startswith("reference-") and re.fullmatch(r"reference-[^-]+", exr.stem):
                refs[exr.stem.split("-", 1)[1]] = exr
    return by_id["report"], renders, refs


def _manifest(html: str) -> dict:
    m = re.search(r'<script type="application/json" id="manifest">(.*?)</script>', html, re.S)
    return json.loads(m.group(1))


def _block(html: str, key: str) -> bytes:
    m = re.search(rf'<script type="{re.escape(page_data.DATA_TYPE)}" id="d-{key}">([^<]*)'
                  r"</script>", html)
    return base64.b64decode(m.group(1))


def _half_close(got, want) -> bool:
    got, want = np.asarray(got, np.float64), np.asarray(want, np.float64)
    tol = np.maximum(np.abs(want) * page_data.HALF_REL_PRECISION, page_data.HALF_ABS_PRECISION)
    return bool(np.all(np.abs(got - want) <= tol * (1 + 1e-6)))


def test01_half_float_blocks_round_trip():
    """encode_linear / decode_linear: every value back to the nearest half float, values
    beyond the half range at its maximum; u8 maps exactly."""
    rng = np.random.default_rng(1)
    x = (rng.lognormal(-3, 3, (7, 5, 3)) * (rng.random((7, 5, 3)) > 0.2)).astype(np.float32)
    x[0, 0] = [1e6, 2.0 ** -20, 0.0]
    y = page_data.decode_linear(page_data.encode_linear(x), 5, 7)
    assert y[0, 0, 0] == page_data.HALF_MAX
    assert _half_close(y.ravel()[1:], x.ravel()[1:])
    with np.errstate(over="ignore"):
        half = x.astype(np.float16).astype(np.float32).clip(0, page_data.HALF_MAX)
    assert np.array_equal(y, half)
    m = rng.integers(0, 256, (4, 9), dtype=np.uint8)
    assert np.array_equal(page_data.decode_u8(page_data.encode_u8(m), 9, 4), m)
    with pytest.raises(ValueError, match="shape"):
        page_data.encode_linear(np.zeros((4, 4)))


def test02_page_lists_every_image_with_its_data_and_numbers(study):
    """The page beside report.pdf: one manifest entry per image of the run and per
    reference, each with its data (the EXR to half precision) and thumbnail; the models'
    distances to the truth and their FLIP as ground_truth.json has them; one inline script,
    no network reference."""
    folder, renders, refs = study
    html = (folder / PAGE).read_text()
    assert (folder / "report.pdf").is_file()
    man = _manifest(html)
    models = [e for e in man["images"] if e["kind"] == "model"]
    assert {(e["model"], e["light"], e["geometry"]) for e in models} == set(renders)
    assert {e["light"] for e in man["images"] if e["kind"] == "reference"} == set(refs)
    for e in man["images"]:
        exr = renders.get((e["model"], e["light"], e["geometry"])) or refs[e["light"]]
        want = read_image(exr, channels=3)
        got = page_data.decode_linear(_block(html, e["key"]), e["width"], e["height"])
        assert got.shape == want.shape and _half_close(got, want), e["file"]
        assert e["thumb"].startswith("data:image/jpeg;base64,")
    assert html.count("<script>") == 1 and "</" not in _script(html)
    assert not re.search(r'(src|href)="(https?:)?//', html)
    if refs:
        gt = json.loads((folder / "ground_truth.json").read_text())
        for e in models:
            if e["geometry"] == "high":
                rec = gt["models"][f"{e['model']}-{e['light']}"]
                assert e["flip"]["mean"] == pytest.approx(rec["flip"], rel=1e-6)
                assert e["truth"]["distance"] == pytest.approx(rec["scales"]["4"]["rel_rmse"])
        assert man["regions"]["views"]["main"]["width"] == 80


def _script(html: str) -> str:
    return html.split("<script>", 1)[1].split("</script>", 1)[0]


def _browser():
    if CHROMIUM is None:
        pytest.skip("no Chromium here (Debian: apt-get install chromium; bash .ci/setup "
                    "installs it where the distribution has it): browser test skipped")
    sync_api = pytest.importorskip("playwright.sync_api", reason="Playwright is not installed "
                                   "(pip install playwright; bash .ci/setup): browser test "
                                   "skipped")
    return sync_api.sync_playwright, CHROMIUM


def _launch(p, exe):
    try:   # --no-sandbox: CI runs as root, where Chromium's sandbox refuses to start
        return p.chromium.launch(executable_path=exe, args=["--no-sandbox"])
    except Exception as exc:   # Playwright's Error: the browser here cannot start
        pytest.skip(f"{exe} does not start under Playwright ({str(exc).splitlines()[0]}): "
                    "browser test skipped")


def _pick_pixel(exr_a: Path) -> tuple[int, int]:
    """A pixel on the face away from the silhouette: the brightest of the image's central
    quarter."""
    a = read_image(exr_a, channels=3)
    h, w = a.shape[:2]
    lum = a[h // 4:3 * h // 4, w // 4:3 * w // 4].sum(axis=2)
    y, x = np.unravel_index(int(np.argmax(lum)), lum.shape)
    return int(x + w // 4), int(y + h // 4)


def test03_browser_grid_and_pixel_readout(study, tmp_path):
    """In headless Chromium: no console error while loading, opening the comparator and
    switching through its modes; the grid shows every image of the run (and each
    reference) once; hovering a pixel reads A's and B's linear RGB there as in their EXRs
    (B = the reference: its pixel covering that camera pixel), within half precision."""
    sync_playwright, exe = _browser()
    folder, renders, refs = study
    man = _manifest((folder / PAGE).read_text())
    errors = []
    with sync_playwright() as p:
        browser = _launch(p, exe)
        page = browser.new_page(viewport={"width": 1400, "height": 900})
        page.on("console", lambda m: errors.append(m.text) if m.type == "error" else None)
        page.on("pageerror", lambda e: errors.append(str(e)))
        page.goto((folder / PAGE).resolve().as_uri())
        ids = page.eval_on_selector_all("#grid .card", "els => els.map(e => e.dataset.id)")
        assert sorted(ids) == sorted(e["id"] for e in man["images"])
        assert len(ids) == len(renders) + len(refs)
        page.screenshot(path=str(tmp_path / "grid.png"))
        a = next(e for e in man["images"] if e["kind"] == "model" and e["geometry"] == "high"
                 and e["model"] != man["baseline"])
        b = next((e for e in man["images"] if e["kind"] == "reference"
                  and e["light"] == a["light"]), None) or next(
            e for e in man["images"] if e["model"] == man["baseline"]
            and e["light"] == a["light"] and e["geometry"] == a["geometry"])
        page.click(f'#grid .card[data-id="{a["id"]}"]')
        page.wait_for_function("window.dermis.ready")
        assert page.evaluate("[window.dermis.state.a.id, window.dermis.state.b.id]") == [
            a["id"], b["id"]]
        exr_a = renders[(a["model"], a["light"], a["geometry"])]
        exr_b = refs.get(b["light"]) if b["kind"] == "reference" else renders[
            (b["model"], b["light"], b["geometry"])]
        x, y = _pick_pixel(exr_a)
        page.evaluate("window.dermis.zoomTo(8)")
        page.evaluate(f"window.dermis.centre({x}, {y})")
        pos = page.evaluate(f"window.dermis.clientOf({x}, {y})")
        page.mouse.move(pos["x"], pos["y"])
        assert page.inner_text("#ro-xy") == f"x {x}, y {y}"
        got_a = json.loads(page.get_attribute("#ro-a", "data-rgb"))
        got_b = json.loads(page.get_attribute("#ro-b", "data-rgb"))
        want_a = read_image(exr_a, channels=3)[y, x]
        ref = read_image(exr_b, channels=3)
        f = a["width"] // ref.shape[1]
        want_b = ref[y // f, x // f]
        assert _half_close(got_a, want_a), (got_a, want_a.tolist())
        assert _half_close(got_b, want_b), (got_b, want_b.tolist())
        assert min(want_a) > 0
        page.keyboard.press("ArrowRight")      # the read-out one pixel over
        assert page.inner_text("#ro-xy") == f"x {x + 1}, y {y}"
        assert _half_close(json.loads(page.get_attribute("#ro-a", "data-rgb")),
                           read_image(exr_a, channels=3)[y, x + 1])
        page.mouse.move(pos["x"], pos["y"])
        region = page.get_attribute("#ro-region", "data-region")
        assert region in (man["regions"]["names"] + [""])
        page.screenshot(path=str(tmp_path / "compare.png"))
        for mode in ("wipe", "flip", "diff"):
            page.click(f'#mode button[data-mode="{mode}"]')
            page.mouse.move(pos["x"], pos["y"])
            if mode == "flip":
                page.keyboard.press("f")
                assert page.evaluate("window.dermis.state.flipShowB")
        for kind in ("relative", "signed", "flip"):
            if page.is_enabled(f'#diffkind button[data-kind="{kind}"]'):
                page.click(f'#diffkind button[data-kind="{kind}"]')
        page.evaluate("window.dermis.zoomTo(1)")
        page.screenshot(path=str(tmp_path / "difference.png"))
        for tab in ("timings", "conclusions"):
            page.click(f'#tabs button[data-tab="{tab}"]')
        browser.close()
    assert not errors, errors
    shots = os.environ.get("DERMIS_PAGE_SHOTS")   # where to keep the screenshots to look at
    if shots:
        Path(shots).mkdir(parents=True, exist_ok=True)
        for png in tmp_path.glob("*.png"):
            shutil.copy(png, Path(shots) / f"test-{png.name}")
    assert math.isfinite(sum(got_a))



def _image(model: str, light: str, geometry: str, value: float, size: int = 8):
    from dermis.pipeline.artifacts import RenderedImage
    lin = np.full((size, size, 3), value, np.float32)
    lin[0] = 0.0                                   # a background row
    mask = lin[..., 0] > 0
    return RenderedImage(lin, mask, {"total": 1.5}, {"model": model, "light": light,
                                                      "geometry": geometry})


def _synthetic_page(folder: Path) -> tuple[Path, dict]:
    from dermis.reports.interactive_page import write_page
    images = {"a": _image("bssrdf", "point", "high", 0.5),
              "b": _image("plugin_model", "point", "high", 0.25),
              "c": _image("plugin_model", "point@nose", "high", 0.125),
              "d": _image("bssrdf", "point@nose", "high", 0.0625)}
    refs = {"point@nose": _image("reference", "point@nose", "high", 0.3, size=4)}
    page = write_page(folder, images, refs, {"reference_model": "bssrdf"}, scene_name="x")
    return page, images


def test05_new_models_views_and_references_need_no_change(tmp_path):
    """The page is built from the images' own keys: a model no registry knows, a close-up
    view's lighting label ``<condition>@<view>`` and a reference of that view each appear
    with their keys (the unknown model under its own name), every image's data included;
    without references or metrics the page says so and lists the images alone."""
    from dermis.reports.interactive_page import write_page
    page, images = _synthetic_page(tmp_path)
    man = _manifest(page.read_text())
    got = {(e["kind"], e["model"], e["condition"], e["view"], e["label"])
           for e in man["images"]}
    assert ("model", "plugin_model", "point", "main", "plugin_model") in got
    assert ("model", "plugin_model", "point", "nose", "plugin_model") in got
    assert ("reference", "reference", "point", "nose", "Reference (Mitsuba 3)") in got
    assert len(man["images"]) == 5
    for e in man["images"]:
        v = page_data.decode_linear(_block(page.read_text(), e["key"]), e["width"], e["height"])
        assert v.shape == (e["height"], e["width"], 3) and v[-1, -1, 0] > 0
    plugin = next(e for e in man["images"] if e["model"] == "plugin_model"
                  and e["view"] == "main")
    # no differences or ground truth in these metrics: no distances, the time all the same
    assert "baseline" not in plugin and plugin["truth"] is None and plugin["seconds"] == 1.5
    page = write_page(tmp_path, {"b": images["b"]}, {}, {"ground_truth_skipped": "no Mitsuba"},
                      scene_name="x")
    man = _manifest(page.read_text())
    assert man["truth_skipped"] == "no Mitsuba" and len(man["images"]) == 1


def test06_browser_shows_a_close_up_view_of_its_own(tmp_path):
    """In Chromium, the synthetic study of test05: a View choice appears with the main
    camera and the close-up; the close-up's grid holds its two images and its reference; its
    comparator opens (a 4-pixel reference beside 8-pixel images) and reads the reference's
    value at a pixel; no console error."""
    sync_playwright, exe = _browser()
    page_path, _ = _synthetic_page(tmp_path)
    errors = []
    with sync_playwright() as p:
        browser = _launch(p, exe)
        page = browser.new_page(viewport={"width": 1200, "height": 800})
        page.on("console", lambda m: errors.append(m.text) if m.type == "error" else None)
        page.on("pageerror", lambda e: errors.append(str(e)))
        page.goto(page_path.resolve().as_uri())
        views = page.eval_on_selector_all('button[data-filter="view"]',
                                          "els => els.map(e => e.dataset.value)")
        assert sorted(views) == ["main", "nose"]
        page.click('button[data-filter="view"][data-value="nose"]')
        cards = page.eval_on_selector_all("#grid .card", "els => els.map(e => e.title)")
        assert len(cards) == 3 and any("Reference" in c for c in cards)
        page.locator("#grid .card").first.click()
        page.wait_for_function("window.dermis.ready")
        pos = page.evaluate("window.dermis.clientOf(7, 7)")
        page.mouse.move(pos["x"], pos["y"])
        got_b = json.loads(page.get_attribute("#ro-b", "data-rgb"))
        assert _half_close(got_b, [0.3, 0.3, 0.3])
        browser.close()
    assert not errors, errors
