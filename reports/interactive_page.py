"""The interactive comparison page written beside ``report.pdf``: ``report.html``, one
self-contained file (docs/report-page.md).

The page is static: the HTML, CSS and JavaScript are this package's ``reports/page/`` files
inlined into one document with a JSON *manifest* of the study (every image's keys, numbers
and thumbnail), followed by every image's linear data as a compressed half-float block
(:mod:`dermis.reports.page_data`) that the page decodes when it first shows the image at
full size.  So it opens from the file system in any current browser with no server and no
network, and shows its grid before the data blocks are read (the default scene's size and
load time: docs/report-page.md).

Nothing here names a model, light, view or geometry: the manifest lists every image of the
run with the (view, lighting condition, geometry) its ``info`` gives (a lighting label
``<condition>@<view>`` belongs to the close-up view ``<view>``,
:data:`dermis.pipeline.schema.VIEW_MARK`),
its label from :mod:`dermis.models.catalog`, its time and its distances from ``metrics.json``,
and the page builds its selectors, grids and tables from that list.
"""
from __future__ import annotations

import base64
import html
import io
import json
import math
from concurrent.futures import ThreadPoolExecutor
from importlib import resources
from pathlib import Path

import numpy as np
from PIL import Image

from dermis.pipeline.config import condition_of, view_name_of
from dermis.geometry.regions import REGION_COLOURS, REGIONS, block_mean
from dermis.models import catalog
from dermis.pipeline.schema import MAIN_VIEW
from dermis.reports import page_data
from dermis.reports.diff import diverging_lut
from dermis.reports.ground_truth import GEOMETRY, region_labels_for
from dermis.reports.pdf_report import THESIS_LIGHTS, THESIS_TIMES
from dermis.reports.truth_noise import FAILS, HOLDS, UNRESOLVED
from dermis.reports.tonemap import encode_srgb8, shared_exposure

__all__ = ["PAGE", "write_page", "image_entries"]

PAGE = "report.html"
# the page's own files, inlined into every page (their bytes enter the report's cache key,
# pipeline/codehash.py)
DATA_FILES = ("page/page.html", "page/page.css", "page/page.js")
THUMB_PX = 200           # grid thumbnails: at most this many pixels across (block means)
GEOMETRY_ORDER = ("high", "low_bump", "low_bump_blur", "low")


def _split_label(light: str) -> tuple[str, str]:
    return condition_of(str(light)), view_name_of(str(light))


def _seconds(image) -> float | None:
    t = (getattr(image, "timings", {}) or {}).get("total")
    return float(t) if t is not None else None


def _irradiance(extra: dict, light: str, geometry: str) -> float | None:
    mesh = "mesh_high" if geometry == GEOMETRY else "mesh_low"
    for key in ((light, mesh), (_split_label(light)[0], mesh)):
        if key in (extra or {}):
            return float(extra[key])
    return None


def _noise_sigma(a, b) -> float | None:
    """Relative RMSE that the two images' own noise alone gives (their ``noise`` fields:
    per pixel variance estimates; an image without one counts as noise-free, as in
    :mod:`dermis.reports.ground_truth`) over the pixels both cover, relative to ``b``'s RMS
    as :func:`dermis.reports.diff.difference` measures ``rel_rmse``; None when neither
    image has a noise estimate."""
    if (a.noise is None and b.noise is None) or a.linear.shape != b.linear.shape:
        return None
    m = a.mask & b.mask
    if not m.any():
        return None
    var = sum((im.noise[m].astype(np.float64) ** 2).mean() for im in (a, b)
              if im.noise is not None)
    rms = math.sqrt(float((b.linear[m].astype(np.float64) ** 2).mean()))
    return math.sqrt(float(var)) / rms if rms > 0 else None


def _thumbnail(linear: np.ndarray, exposure: float) -> str:
    f = max(1, max(linear.shape[:2]) // THUMB_PX)
    h, w = (linear.shape[0] // f) * f, (linear.shape[1] // f) * f
    # rows of blocks first, then columns: contiguous sums, 5x faster than one mean over (1, 3)
    rows = np.asarray(linear[:h, :w], np.float32).reshape(h // f, f, w, 3).sum(axis=1)
    small = rows.reshape(h // f, w // f, f, 3).sum(axis=2) / (f * f)
    buf = io.BytesIO()
    Image.fromarray(encode_srgb8(small, exposure)).save(buf, "JPEG", quality=90)
    return "data:image/jpeg;base64," + base64.b64encode(buf.getvalue()).decode("ascii")


def _truth(metrics: dict, light: str, model: str, geometry: str) -> dict | None:
    if geometry != GEOMETRY:
        return None
    rec = (metrics.get("ground_truth") or {}).get(light, {}).get("models", {}).get(model)
    if not rec:
        return None
    keep = ("distance", "stderr", "resolved", "distance_true", "scale", "rank", "rank_range",
            "ref_noise", "model_noise")
    out = {k: rec.get(k) for k in keep}
    out["regions"] = {n: {k: g.get(k) for k in ("rel_diff", "stderr", "resolved",
                                                  "rel_diff_rgb", "stderr_rgb")}
                      for n, g in rec.get("regions", {}).items()}
    return out


def image_entries(images: dict, refs: dict, metrics: dict, extra: dict | None = None
                  ) -> list[dict]:
    """The manifest's image list (no data): every model image, then every reference, with
    its grouping keys, label, time and distances."""
    baseline = metrics.get("reference_model")
    by_key = {(im.info.get("model"), im.info.get("light"), im.info.get("geometry")): im
              for im in images.values()}
    out = []
    models = catalog.ordered({im.info.get("model", "?") for im in images.values()})
    geoms = {im.info.get("geometry", "?") for im in images.values()}
    geoms = [g for g in GEOMETRY_ORDER if g in geoms] + sorted(geoms - set(GEOMETRY_ORDER))
    for nid in sorted(images, key=lambda n: (models.index(images[n].info.get("model", "?")),
                                             geoms.index(images[n].info.get("geometry", "?")),
                                             images[n].info.get("light", "?"))):
        im = images[nid]
        model, light, geom = (str(im.info.get(k, "?")) for k in ("model", "light", "geometry"))
        cond, view = _split_label(light)
        h, w = im.linear.shape[:2]
        irr = _irradiance(extra, light, geom) if catalog.is_bssrdf(model) else None
        entry = {"kind": "model", "model": model, "label": catalog.label(model),
                 "light": light, "condition": cond, "view": view, "geometry": geom,
                 "width": w, "height": h, "seconds": _seconds(im), "irradiance_seconds": irr,
                 "file": f"{model}-{light}-{geom}.exr",
                 "truth": _truth(metrics, light, model, geom)}
        vs = (metrics.get("model_vs_reference") or {}).get(f"{model}-{light}-{geom}")
        base = by_key.get((baseline, light, geom))
        if vs and base is not None:
            entry["baseline"] = {"model": baseline, "label": catalog.label(baseline),
                                 "rel_rmse": vs.get("rel_rmse"), "ssim": vs.get("ssim"),
                                 "noise": _noise_sigma(im, base)}
        out.append(entry)
    for light in sorted(refs):
        ref = refs[light]
        cond, view = _split_label(light)
        h, w = ref.linear.shape[:2]
        gt = (metrics.get("ground_truth") or {}).get(light, {})
        reached = gt.get("noise_reached", {})
        out.append({"kind": "reference", "model": "reference", "label": "Reference (Mitsuba 3)",
                    "light": light, "condition": cond, "view": view, "geometry": GEOMETRY,
                    "width": w, "height": h, "seconds": reached.get("seconds"),
                    "spp": reached.get("spp"), "file": f"reference-{light}.exr",
                    "regions": gt.get("regions", {}), "ranking": gt.get("ranking", [])})
    return out


def _flip_maps(pairs: list) -> list:
    """HDR-FLIP (Andersson et al. 2021, ``flip-evaluator``) of each (model image, reference)
    pair, the model block-averaged to the reference's grid, over the blocks both cover, as
    :mod:`dermis.reports.ground_truth` measures it: the exposure range from the reference's
    compared pixels alone (computed once per reference and mask).  Returns per pair None
    (no FLIP: flip-evaluator missing, or grids that do not divide) or (mean, uint8 map =
    FLIP x 255, 0 outside the compared blocks)."""
    try:
        import flip_evaluator as flip
    except ImportError:
        return [None] * len(pairs)
    keys = ("startExposure", "stopExposure", "numExposures")
    ranges: dict = {}

    def one(pair):
        image, ref = pair
        f = image.linear.shape[0] // ref.linear.shape[0]
        if f < 1 or f * ref.linear.shape[0] != image.linear.shape[0]:
            return None
        down, valid = block_mean(image.linear, image.mask, f)
        if down.shape[:2] != ref.linear.shape[:2]:
            return None
        valid &= np.asarray(ref.mask, bool)
        if not valid.any():
            return None
        r = np.ascontiguousarray(np.where(valid[..., None], ref.linear, 0.0), np.float32)
        t = np.ascontiguousarray(np.where(valid[..., None], down, 0.0), np.float32)
        key = (id(ref), valid.tobytes())
        if key not in ranges:
            skin = np.ascontiguousarray(r[valid][None], np.float32)
            _, _, exposure = flip.evaluate(skin, skin, "HDR", applyMagma=False,
                                           computeMeanError=False)
            ranges[key] = {k: exposure[k] for k in keys}
        err, _, _ = flip.evaluate(r, t, "HDR", applyMagma=False, computeMeanError=False,
                                  parameters=ranges[key])
        err = np.asarray(err, np.float32).reshape(valid.shape[0], valid.shape[1], -1)[..., 0]
        return (float(err[valid].mean()),
                np.where(valid, np.round(np.clip(err, 0, 1) * 255), 0).astype(np.uint8))
    # on 2 threads (a race for one exposure range computes the same range twice): 6 calls took
    # 0.9 s there against 6.1 s one after another on the shared 2-core machine of
    # bench/results/report_page.json
    with ThreadPoolExecutor(2) as pool:
        return list(pool.map(one, pairs))


def _assets() -> dict:
    folder = resources.files("dermis.reports")
    return {Path(n).name: (folder / n).read_text(encoding="utf-8") for n in DATA_FILES}


def _magma() -> list:
    from matplotlib import colormaps
    return np.round(colormaps["magma"](np.linspace(0, 1, 256))[:, :3] * 255).astype(int).tolist()


def write_page(out_dir, images: dict, refs: dict, metrics: dict, *, scene_name: str,
               device: str = "", timings_extra: dict | None = None, mesh=None,
               cameras: dict | None = None) -> Path:
    """Write ``out_dir/report.html`` and return its path.

    images : node id -> RenderedImage (the models'); refs : lighting label -> the reference
    RenderedImage; metrics : the report's ``metrics.json`` object; timings_extra : (lighting
    label, mesh node) -> seconds of the BSSRDF's irradiance pass; mesh, cameras : the high
    mesh and {lighting label: the CameraConfig of its view}, for the face region of every
    pixel of each view (without them the page shows no regions).
    """
    entries = image_entries(images, refs, metrics, timings_extra)
    by_key = {(im.info.get("model"), im.info.get("light"), im.info.get("geometry")): im
              for im in images.values()}
    arrays = [by_key[(e["model"], e["light"], e["geometry"])] if e["kind"] == "model"
              else refs[e["light"]] for e in entries]
    exposures = {}
    for light in sorted({e["light"] for e in entries}):
        # the images stage's exposure: over the models' images of the condition (the
        # reference's noisy pixels would move the percentile), else over what there is
        here = [(e, a) for e, a in zip(entries, arrays) if e["light"] == light]
        group = [a.linear for e, a in here if e["kind"] == "model"] or [a.linear for _, a in here]
        exposures[light] = math.log2(shared_exposure(group))
    with ThreadPoolExecutor(2) as pool:   # numpy and zlib release the GIL: ~1.8x on 2 cores
        encoded = pool.map(lambda im: page_data.encode_linear(im.linear), arrays)
        blocks = []
        for k, (e, im, blob) in enumerate(zip(entries, arrays, encoded)):
            e["id"] = e["key"] = f"i{k}"
            blocks.append(page_data.data_block(e["key"], blob))
            e["thumb"] = _thumbnail(im.linear, 2.0 ** exposures[e["light"]])
    refs_by_light = {e["light"]: e for e in entries if e["kind"] == "reference"}
    measured = [(e, im) for e, im in zip(entries, arrays) if e["kind"] == "model"
                and e["geometry"] == GEOMETRY and e["light"] in refs_by_light]
    flips = _flip_maps([(im, refs[e["light"]]) for e, im in measured])
    for (e, _), got in zip(measured, flips):
        ref = refs_by_light[e["light"]]
        if got is not None:
            key = f"f{e['id']}"
            blocks.append(page_data.data_block(key, page_data.encode_u8(got[1])))
            e["flip"] = {"key": key, "against": ref["id"], "mean": got[0],
                         "width": ref["width"], "height": ref["height"]}
    regions = {}
    views = {_split_label(label)[1]: cam for label, cam in sorted((cameras or {}).items())}
    for view, camera in sorted(views.items()) if mesh is not None else ():
        labels = region_labels_for(mesh, camera, width=camera.width, height=camera.height)
        key = f"r{len(regions)}"
        blocks.append(page_data.data_block(key, page_data.encode_u8(labels)))
        regions[view] = {"key": key, "width": camera.width, "height": camera.height}
    manifest = {
        "scene": scene_name, "device": device, "images": entries, "main_view": MAIN_VIEW,
        "exposure_stops": exposures, "regions": {"names": list(REGIONS),
                                                 "colours": [list(c) for c in REGION_COLOURS],
                                                 "views": regions},
        "baseline": metrics.get("reference_model"),
        "thesis": metrics.get("thesis", []),
        "verdicts": {"holds": HOLDS, "fails": FAILS, "unresolved": UNRESOLVED},
        "truth_skipped": metrics.get("ground_truth_skipped"),
        "thesis_times": {"lights": list(THESIS_LIGHTS), "models": list(catalog.THESIS_MODELS),
                         "labels": [catalog.label(m) for m in catalog.THESIS_MODELS],
                         "times": THESIS_TIMES},
        "luts": {"diverging": np.round(diverging_lut(256) * 255).astype(int).tolist(),
                 "magma": _magma()},
        "encoding": {"linear": "zlib(byte-shuffled little-endian binary16 planes R, G, B)",
                     "maps": "zlib(uint8 per pixel)", "type": page_data.DATA_TYPE,
                     "half_rel_precision": page_data.HALF_REL_PRECISION},
        "data_chars": sum(len(b) for b in blocks),
    }
    page = Path(out_dir) / PAGE
    page.write_text(_render(manifest, "".join(blocks)), encoding="utf-8")
    return page


def _finite(x):
    """``x`` with numpy scalars as Python numbers, tuples as lists and NaN / inf as None
    (JSON has no NaN; the page shows None as a dash)."""
    if isinstance(x, dict):
        return {str(k): _finite(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [_finite(v) for v in x]
    if isinstance(x, (np.floating, float)):
        return float(x) if math.isfinite(x) else None
    if isinstance(x, (np.integer,)):
        return int(x)
    if isinstance(x, np.bool_):
        return bool(x)
    return x


def _render(manifest: dict, blocks: str) -> str:
    a = _assets()
    text = json.dumps(_finite(manifest), separators=(",", ":"), allow_nan=False)
    text = text.replace("</", "<\\/")     # no "</script>" inside the JSON block
    title = html.escape(f"dermis: {manifest['scene']}")
    return (a["page.html"].replace("{{TITLE}}", title).replace("/*CSS*/", a["page.css"])
            .replace("/*JS*/", a["page.js"]).replace("<!--DATA-->", blocks).replace("/*MANIFEST*/", text))
