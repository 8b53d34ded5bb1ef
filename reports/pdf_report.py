"""The comparison report: one multi-page A4-landscape PDF (matplotlib ``PdfPages``).

Pages, in order (Arizpe 2006 compares images, difference images and timings; this adds
measured errors):

1. title page: scene, device, date and a summary generated from the numbers: first the
   distance of every model to the path-traced reference and the thesis's verdicts
   (:func:`dermis.reports.truth_pages.title_lines`), or why there is no reference;
2. the caller's opening pages (``opening_pages``): the distance to ground truth per lighting
   condition (:func:`dermis.reports.truth_pages.opening_pages`);
3. per geometry: images, rows models x columns lights, ONE exposure per light shared by all
   models and geometries (:func:`dermis.reports.tonemap.shared_exposure`), seconds under each;
4. per geometry with reference renders: difference images vs the reference (BSSRDF), one
   symmetric colour scale per light (the scales of :func:`reports.diff.write_differences`),
   relative RMSE and SSIM under each;
5. timing table (seconds per image; BSSRDF plus its irradiance pass) beside the thesis's
   table (docs/science.md §7);
6. error vs time scatter plot -- users trade speed for accuracy;
7. geometry page: relative RMSE of the low mesh + bump maps vs the ~1M-triangle mesh;
8. pages the caller adds (``extra_pages``): the report node's layer-profile page
   (:mod:`dermis.reports.profile_pages`) and the ground truth's detail pages.
"""
from __future__ import annotations

import datetime as _dt
import textwrap
from pathlib import Path

import numpy as np

from dermis.models import catalog
from dermis.models.catalog import THESIS_MODELS
from dermis.pipeline.errors import DermisError
from dermis.reports.diff import (GEOMETRY_COMPARED, GEOMETRY_REFERENCE, difference, difference_image,
                          image_labels)

__all__ = ["write_report", "THESIS_TIMES", "report_page_count", "summary_text", "page_table"]

A4_LANDSCAPE_IN = (11.69, 8.27)
FONT_PT = 8          # body text; nothing in the report is set below MIN_FONT_PT
MIN_FONT_PT = 7

# Thesis render times, 800x800, pbrt on a dual-core Xeon 2.4 GHz (2006), m:ss or h:mm:ss
# (Arizpe 2006, transcribed in docs/science.md §7).  mesh -> light type -> model -> time.
THESIS_LIGHTS = ("directional", "point", "area", "environment")
THESIS_TIMES = {
    "1M": {
        "directional": ("4:03", "3:46", "6:05", "10:42"),
        "point": ("3:01", "2:55", "4:03", "10:32"),
        "area": ("28:56", "19:45", "1:08:13", "19:17"),
        "environment": ("40:14", "34:19", "1:12:27", "28:38"),
    },
    "16,750": {
        "directional": ("4:33", "4:17", "6:31", "9:49"),
        "point": ("3:53", "3:45", "4:52", "9:40"),
        "area": ("23:01", "13:29", "1:02:14", "16:08"),
        "environment": ("30:48", "23:54", "1:11:41", "22:51"),
    },
}
THESIS_SHORT = {"directional": "dir", "point": "point", "area": "area", "environment": "env"}
THESIS_HARDWARE = "pbrt on a dual-core Intel Xeon 2.4 GHz (2006)"

# Two numbers closer than this (relative) are reported as "about equal" in the summary:
# single renders, and timings from one run on a shared machine, do not support finer claims.
ERROR_TIE_FRACTION = 0.10
TIME_TIE_FRACTION = 0.25


def _seconds(image) -> float | None:
    t = (getattr(image, "timings", {}) or {}).get("total")
    return float(t) if t is not None else None


def _index(images: dict) -> dict:
    """(model, light, geometry) -> RenderedImage (last node id wins on duplicates)."""
    return {image_labels(images[nid]): images[nid] for nid in sorted(images)}


def _irradiance_seconds(timings_extra: dict | None, light: str, geom: str) -> float | None:
    """Irradiance-pass seconds for (light, mesh of ``geom``) from ``timings_extra``."""
    if not timings_extra:
        return None
    mesh = "high" if geom == GEOMETRY_REFERENCE else "low"
    for key in ((light, f"mesh_{mesh}"), (light, mesh), (light, geom)):
        if key in timings_extra:
            return float(timings_extra[key])
    return None


def _fmt_s(s: float | None) -> str:
    if s is None:
        return "-"
    return f"{s:.2f} s" if s < 10 else f"{s:.1f} s"


def _ordered_models(models) -> list[str]:
    """Thesis order first (Lafortune, asperity, HK, BSSRDF), then the BSSRDF with the Monte
    Carlo profile, then anything else."""
    models = set(models)
    return catalog.ordered(models)


def _ordered_geoms(geoms) -> list[str]:
    order = ("high", "low_bump", "low_bump_blur", "low")
    geoms = set(geoms)
    return [g for g in order if g in geoms] + sorted(geoms - set(order))


def summary_text(images: dict, metrics: dict, *, timings_extra: dict | None = None) -> str:
    """A short summary from the numbers, one sentence per line: closest model to the reference
    and fastest model per light, and the geometry errors.  Near-ties
    (``ERROR_TIE_FRACTION``, ``TIME_TIE_FRACTION``) are called ties rather than ranked."""
    ref = metrics.get("reference_model", "bssrdf")
    mvr = metrics.get("model_vs_reference", {})
    idx = _index(images)
    geoms = _ordered_geoms({r["geometry"] for r in mvr.values()})
    lines = []
    if mvr:
        geom = geoms[0]
        lines.append(f"Distances are measured from the {ref} render (the reference, not ground "
                     f"truth), on the {geom} geometry; times are seconds per image"
                     + (f", the {ref}'s including its irradiance pass." if timings_extra else "."))
        for light in sorted({r["light"] for r in mvr.values()}):
            recs = sorted((r for r in mvr.values()   # the BSSRDF's own variants: below
                           if r["light"] == light and r["geometry"] == geom
                           and not catalog.is_bssrdf(r["model"])),
                          key=lambda r: r["rel_rmse"])
            if not recs:
                continue
            best = recs[0]
            if len(recs) > 1 and recs[1]["rel_rmse"] <= best["rel_rmse"] * (1 + ERROR_TIE_FRACTION):
                close = (f"{best['model']} and {recs[1]['model']} about equally close to {ref} "
                         f"(relative RMSE {best['rel_rmse']:.3f}, {recs[1]['rel_rmse']:.3f})")
            else:
                close = (f"{best['model']} closest to {ref} (relative RMSE {best['rel_rmse']:.3f}, "
                         f"SSIM {best['ssim']:.2f})")
            if len(recs) > 2 or (len(recs) == 2 and close.startswith(f"{best['model']} closest")):
                close += f", {recs[-1]['model']} farthest ({recs[-1]['rel_rmse']:.3f})"
            times = []
            for (m, l, g), im in idx.items():
                if l == light and g == geom and _seconds(im) is not None:
                    t = _seconds(im)
                    if m == ref or catalog.is_bssrdf(m):   # every BSSRDF: its irradiance pass
                        t += _irradiance_seconds(timings_extra, l, g) or 0.0
                    times.append((t, m))
            times.sort()
            if len(times) > 1 and times[1][0] <= times[0][0] * (1 + TIME_TIE_FRACTION):
                fast = (f"{times[0][1]} and {times[1][1]} about equally fast "
                        f"({times[0][0]:.2f} s, {times[1][0]:.2f} s)")
            elif times:
                fast = f"{times[0][1]} fastest ({times[0][0]:.2f} s)"
            else:
                fast = "no timings recorded"
            ref_t = [t for t, m in times if m == ref]
            if ref_t and times and times[0][1] != ref:
                fast += f"; {ref} {ref_t[0]:.2f} s ({ref_t[0] / times[0][0]:.1f}x the fastest)"
            lines.append(f"{light}: {close}; {fast}.")
        variants = sorted({r["model"] for r in mvr.values() if catalog.is_bssrdf(r["model"])})
        for m in variants:   # the same BSSRDF with another layer profile (bssrdf_mc)
            vals = [r["rel_rmse"] for r in mvr.values() if r["model"] == m and r["geometry"] == geom]
            lines.append(f"{catalog.label(m)} vs {ref}, {geom} geometry: relative RMSE "
                         f"{min(vals):.2g}-{max(vals):.2g} over {len(vals)} lights (what the "
                         "diffusion profile changes on the face; the profile page compares the "
                         "profiles themselves).")
    gvh = metrics.get("geometry_vs_high", {})
    for g in GEOMETRY_COMPARED:
        vals = [r["rel_rmse"] for r in gvh.values() if r["geometry"] == g]
        if vals:
            lines.append(f"{g} vs the {GEOMETRY_REFERENCE} mesh (same model and light): median "
                         f"relative RMSE {np.median(vals):.3f}, range {min(vals):.3f}-"
                         f"{max(vals):.3f} over {len(vals)} model/light pairs.")
    lines.append("Timings are single runs on one machine; treat time differences below about "
                 f"{TIME_TIE_FRACTION:.0%} as noise.")
    return "\n".join(lines)


def report_page_count(images: dict, metrics: dict) -> int:
    """Pages :func:`write_report` writes for these inputs."""
    geoms = {g for _, _, g in _index(images)}
    diff_geoms = {r["geometry"] for r in metrics.get("model_vs_reference", {}).values()}
    return 1 + len(geoms) + len(diff_geoms) + 3


def _new_page(plt, title: str):
    fig = plt.figure(figsize=A4_LANDSCAPE_IN)
    fig.suptitle(title, fontsize=12, y=0.975)
    return fig


def _grid_axes(fig, nrows: int, ncols: int, *, top=0.91, bottom=0.02, left=0.02, right=0.98,
               hspace=0.22, wspace=0.04):
    gs = fig.add_gridspec(nrows, ncols, top=top, bottom=bottom, left=left, right=right,
                          hspace=hspace, wspace=wspace)
    axes = np.array([[fig.add_subplot(gs[r, c]) for c in range(ncols)] for r in range(nrows)])
    for ax in axes.flat:
        ax.axis("off")
    return axes


def _truth_text(truth: dict) -> str:
    """The title page's ground-truth block, wrapped."""
    wrap = lambda s: textwrap.fill(s, 150, initial_indent="- ", subsequent_indent="  ")
    lines = [textwrap.fill(truth["note"], 155)]
    lines += [wrap(s) for s in truth.get("lines", [])]
    if truth.get("thesis"):
        lines.append("The thesis's conclusions against the reference:")
        lines += [wrap(f"{claim}: {verdict}") for claim, verdict in truth["thesis"]]
    return "\n".join(lines)


def _title_page(plt, images, metrics, *, scene_name, device, timings_extra, credits=(),
                truth=None):
    idx = _index(images)
    fig = _new_page(plt, "")
    fig.text(0.5, 0.88, "dermis: skin rendering comparison", ha="center", fontsize=20)
    fig.text(0.5, 0.82, f"scene: {scene_name}", ha="center", fontsize=12)
    date = _dt.datetime.now(_dt.timezone.utc).strftime("%Y-%m-%d %H:%M UTC")
    facts = [
        f"device: {device}",
        f"date: {date}",
        f"images: {len(idx)}   models: {', '.join(_ordered_models(m for m, _, _ in idx))}",
        f"lights: {', '.join(sorted({l for _, l, _ in idx}))}",
        f"geometries: {', '.join(_ordered_geoms(g for _, _, g in idx))}",
        f"ground truth: {'Mitsuba 3 path-traced reference' if truth and truth['truth'] else 'none'}"
        f";  model differences also against: {metrics.get('reference_model', '-')}",
    ]
    facts = [textwrap.fill(f, 110, subsequent_indent="  ") for f in facts]
    y = _place(fig, 0.77, "\n".join(facts), fontsize=9, family="monospace") - 0.035
    small = bool(truth)   # the ground truth leads: the rest is set smaller
    if truth:
        y = _place(fig, y, "Summary: distance to ground truth" if truth["truth"] else
                   "Summary: no ground truth", fontsize=11, weight="bold") - 0.01
        y = _place(fig, y, _truth_text(truth), fontsize=8.5, linespacing=1.35) - 0.03
    summary = summary_text(images, metrics, timings_extra=timings_extra)
    y = _place(fig, y, "Against the BSSRDF (a model, not the truth)" if truth and truth["truth"]
               else "Summary", fontsize=11 if small else 12, weight="bold") - 0.01
    text = "\n".join(textwrap.fill(line, 165 if small else 140, initial_indent="- ",
                                   subsequent_indent="  ") for line in summary.splitlines())
    y = _place(fig, y, text, fontsize=7.5 if small else 9,
               linespacing=1.3 if small else 1.5) - 0.025
    floor = metrics.get("rel_floor_fraction")
    howto = (
        "Relative RMSE = RMSE / RMS of the reference over the pixels both renders cover. "
        "SSIM: Wang et al. 2004 on luminance, 11x11 Gaussian window. Relative error per pixel "
        f"= (image - reference) / max(reference, {floor} x mean reference); bias and 95th "
        "percentile use it. Difference images: red = brighter than the reference, blue = "
        "darker, one symmetric scale per light. Reproduces and extends A. Arizpe, A Critical "
        "Comparison of Human Face Rendering Techniques, MIT MEng thesis, 2006.")
    y = _place(fig, min(y, 0.12), textwrap.fill(howto, 160), fontsize=7, color="0.3") - 0.01
    if credits:  # the scan's CC BY attribution goes wherever the scan appears
        _place(fig, min(y, 0.05), "\n".join(textwrap.fill(c, 160) for c in credits),
               fontsize=7, color="0.3")
    return fig


def _place(fig, y: float, text: str, **kw) -> float:
    """Draw ``text`` with its top at ``y`` (figure fraction, x = 0.08); returns its bottom."""
    t = fig.text(0.08, y, text, va="top", **kw)
    box = t.get_window_extent(renderer=fig.canvas.get_renderer())
    return y - box.height / fig.bbox.height


def _mosaic_page(plt, title: str, mosaic: np.ndarray, *, bottom: float = 0.01):
    """A page showing one labelled grid image (:mod:`dermis.reports.sheets`) at its native
    resolution: one axes, no resampling, so a page costs milliseconds, not seconds."""
    fig = _new_page(plt, title)
    ax = fig.add_axes([0.01, bottom, 0.98, 0.94 - bottom])
    ax.imshow(mosaic, interpolation="none")
    ax.axis("off")
    return fig


def _downsample(linear: np.ndarray, px: int) -> np.ndarray:
    """Block mean of a linear image down to about ``px`` on its longer side (radiance is
    averaged before tone mapping, as a camera would)."""
    k = max(1, int(round(max(linear.shape[:2]) / px)))
    if k == 1:
        return linear
    h, w = (linear.shape[0] // k) * k, (linear.shape[1] // k) * k
    out = np.zeros((h // k, w // k, 3), np.float32)
    for a in range(k):          # k^2 strided adds: much faster than a reshaped mean
        for b in range(k):
            out += linear[a:h:k, b:w:k]
    return out / np.float32(k * k)


def _image_pages(plt, images, thumbnails=None):
    from dermis.reports.sheets import caption
    from dermis.reports.sheets import TILE_PX, grid
    from dermis.reports.tonemap import encode_srgb8, shared_exposure

    idx = _index(images)
    lights = sorted({l for _, l, _ in idx})
    models = _ordered_models(m for m, _, _ in idx)
    exposure = None
    if not thumbnails or not all(k in thumbnails for k in idx):
        thumbnails = None      # tone-map here (the images stage's exposure rule)
        exposure = {l: shared_exposure([im.linear for (_, ll, _), im in idx.items() if ll == l])
                    for l in lights}
    for geom in _ordered_geoms(g for _, _, g in idx):
        tiles, caps = {}, {}
        for (m, l, g), im in idx.items():
            if g == geom:
                tiles[(m, l)] = (thumbnails[(m, l, g)] if thumbnails is not None else
                                 encode_srgb8(_downsample(im.linear, TILE_PX), exposure[l]))
                caps[(m, l)] = f"{caption(m, l)}\n{_fmt_s(_seconds(im))}"
        yield _mosaic_page(plt, f"Images, geometry {geom}  (one exposure per light, shared by "
                                "all models and geometries)",
                           grid(tiles, models, lights, captions=caps))


def _diff_pages(plt, images, metrics, tiles=None):
    from dermis.reports.diff import _grid_image

    idx = _index(images)
    ref = metrics.get("reference_model", "bssrdf")
    mvr = metrics.get("model_vs_reference", {})
    scales = metrics.get("scales", {}).get("model", {})
    lights = sorted({r["light"] for r in mvr.values()})
    models = _ordered_models(r["model"] for r in mvr.values())
    for geom in _ordered_geoms(r["geometry"] for r in mvr.values()):
        sel, caps = {}, {}
        for rec in mvr.values():
            if rec["geometry"] != geom:
                continue
            m, l = rec["model"], rec["light"]
            tile = (tiles or {}).get((m, l, geom))
            if tile is None:   # not handed over by write_differences: recompute
                tile = difference_image(difference(idx[(m, l, geom)], idx[(ref, l, geom)]),
                                        scale=scales.get(l))
            sel[(m, l)] = tile
            caps[(m, l)] = f"rel RMSE {rec['rel_rmse']:.3f}  SSIM {rec['ssim']:.3f}"
        yield _mosaic_page(plt, f"Difference vs {ref}, geometry {geom}  (red = brighter, blue "
                                "= darker than the reference)",
                           _grid_image(sel, models, lights, scales, title="", captions=caps))


def page_table(ax, cells: list[list[str]], header: list[str], *, widths=None,
               row_height: float = 0.075, fontsize: float = MIN_FONT_PT + 0.5) -> None:
    """A table at the top of ``ax``: a bold header row, the first column (row labels)
    left-aligned and, unless ``widths`` (fractions) are given, wider than the rest;
    ``row_height`` is each row's share of the axes."""
    n = len(header)
    if widths is None:
        first = 0.32
        widths = [first] + [(1 - first) / (n - 1)] * (n - 1)
    height = min(1.0, (len(cells) + 1) * row_height)
    tab = ax.table(cellText=cells, colLabels=header, colWidths=widths, cellLoc="center",
                   bbox=[0, 1 - height, 1, height])
    tab.auto_set_font_size(False)
    tab.set_fontsize(fontsize)
    for (r, c), cell in tab.get_celld().items():
        if r == 0:
            cell.set_text_props(weight="bold")
        if c == 0:
            cell.set_text_props(ha="left")
            cell.PAD = 0.02


def _timing_page(plt, images, metrics, *, device, timings_extra):
    idx = _index(images)
    ref = metrics.get("reference_model", "bssrdf")
    lights = sorted({l for _, l, _ in idx})
    models = _ordered_models(m for m, _, _ in idx)
    geoms = _ordered_geoms(g for _, _, g in idx)
    sizes = sorted({f"{im.linear.shape[1]}x{im.linear.shape[0]}" for im in images.values()},
                   key=lambda t: -int(t.split("x")[0]))
    fig = _new_page(plt, f"Render time per {' / '.join(sizes)} image: this run vs the thesis "
                         "(800x800)")
    rows, cells = [], []
    for m in models:
        for g in geoms:
            row = []
            for l in lights:
                im = idx.get((m, l, g))
                t = _seconds(im) if im is not None else None
                cell = _fmt_s(t)
                irr = (_irradiance_seconds(timings_extra, l, g)
                       if m == ref or catalog.is_bssrdf(m) else None)
                if t is not None and irr is not None:
                    cell = f"{t:.2f} + {irr:.2f} irr"
                row.append(cell)
            if any(c != "-" for c in row):
                rows.append(f"{catalog.label(m)} / {g}")
                cells.append(row)
    ax = fig.add_axes([0.02, 0.30, 0.62, 0.58])
    ax.axis("off")
    ax.set_title(f"this run: seconds per image\n{device}", fontsize=9)
    if cells:
        page_table(ax, [[r] + c for r, c in zip(rows, cells)],
               ["model / geometry"] + [l.replace("+", "+\n") for l in lights])
    ax2 = fig.add_axes([0.67, 0.30, 0.31, 0.58])
    ax2.axis("off")
    ax2.set_title(f"thesis (docs/science.md §7), m:ss\n{THESIS_HARDWARE}", fontsize=9)
    tcells = []
    for mesh, by_light in THESIS_TIMES.items():
        for k, m in enumerate(THESIS_MODELS):
            tcells.append([f"{m} / {mesh}"] + [by_light[l][k] for l in THESIS_LIGHTS])
    page_table(ax2, tcells, ["model / triangles"] + [THESIS_SHORT[l] for l in THESIS_LIGHTS])
    note = (f"Hardware differs: the thesis rendered with {THESIS_HARDWARE}; this run used "
            f"{device}, through OpenCL. Absolute times are therefore not comparable; compare the "
            "ratios between models under one light. Thesis geometries: 1M triangles ~ 'high', "
            "16,750 triangles + bump map ~ 'low_bump'. Thesis light types: dir = the two "
            "directional lights together, env = the environment (sunset) map. Times here are wall "
            "seconds of each image's own work (shading; for the BSSRDF the gather, the exit and "
            "the surface term), without the camera and shadow rays and the surface attributes "
            "that every model of a mesh and light (geometry) shares, cast and computed once; "
            f"'+ x irr' is the {ref}'s separate irradiance pass for that light and mesh (run once, "
            "cached and shared by every geometry on that mesh).")
    fig.text(0.03, 0.22, textwrap.fill(note, 170), va="top", fontsize=8)
    return fig


def _markers(models):
    shapes = ("o", "s", "^", "D", "v", "P", "X", "*")
    return {m: shapes[i % len(shapes)] for i, m in enumerate(models)}


def _scatter_page(plt, images, metrics, *, timings_extra):
    from matplotlib.lines import Line2D

    idx = _index(images)
    ref = metrics.get("reference_model", "bssrdf")
    mvr = metrics.get("model_vs_reference", {})
    lights = sorted({r["light"] for r in mvr.values()})
    models = _ordered_models([r["model"] for r in mvr.values()] + [ref])
    colours = {l: plt.get_cmap("tab10")(i % 10) for i, l in enumerate(lights)}
    marks = _markers(models)
    fig = _new_page(plt, "Error vs time: users trade speed for accuracy")
    ax = fig.add_axes([0.08, 0.12, 0.62, 0.76])
    pts = []
    for rec in mvr.values():
        if rec.get("seconds"):
            t = rec["seconds"] + ((_irradiance_seconds(timings_extra, rec["light"],
                                                       rec["geometry"]) or 0.0)
                                  if catalog.is_bssrdf(rec["model"]) else 0.0)
            pts.append((rec["model"], rec["light"], rec["geometry"], t, rec["rel_rmse"]))
    for (m, l, g), im in idx.items():  # the reference itself: zero error, its full cost
        if m == ref and l in colours and _seconds(im):
            t = _seconds(im) + (_irradiance_seconds(timings_extra, l, g) or 0.0)
            pts.append((m, l, g, t, 0.0))
    for m, l, g, t, e in pts:
        hollow = g != GEOMETRY_REFERENCE
        ax.scatter([t], [e], marker=marks[m], s=46, linewidths=1.3,
                   facecolors="none" if hollow else colours[l], edgecolors=colours[l])
    ax.set_xscale("log")
    ax.set_xlabel("seconds per image (log)" + (f"; {ref} includes its irradiance pass"
                                                if timings_extra else ""), fontsize=9)
    ax.set_ylabel(f"relative RMSE vs {ref}", fontsize=9)
    ax.tick_params(labelsize=8)
    ax.grid(True, which="both", alpha=0.3)
    handles = [Line2D([], [], marker=marks[m], ls="", color="0.2", label=catalog.label(m))
               for m in models]
    handles += [Line2D([], [], marker="s", ls="", color=colours[l], label=l) for l in lights]
    handles += [Line2D([], [], marker="o", ls="", color="0.2", label=GEOMETRY_REFERENCE),
                Line2D([], [], marker="o", ls="", mfc="none", color="0.2",
                       label="low geometries (hollow)")]
    ax.legend(handles=handles, fontsize=8, loc="upper left", bbox_to_anchor=(1.02, 1.0),
              title="marker: model, colour: light", title_fontsize=8)
    fig.text(0.08, 0.04, f"Lower left is better. The {ref} is the reference (error 0 by "
             "definition); points to its left are faster, and the height shows what they give up.",
             fontsize=8)
    return fig


def _geometry_page(plt, metrics):
    gvh = metrics.get("geometry_vs_high", {})
    fig = _new_page(plt, f"Geometry: low mesh + bump map vs the {GEOMETRY_REFERENCE} mesh, same "
                         "model and light")
    if not gvh:
        fig.text(0.5, 0.5, f"No geometry comparison: the scene renders no "
                 f"{GEOMETRY_REFERENCE!r} geometry together with "
                 f"{' / '.join(GEOMETRY_COMPARED)}.", ha="center", fontsize=10)
        return fig
    lights = sorted({r["light"] for r in gvh.values()})
    geoms = [g for g in GEOMETRY_COMPARED if any(r["geometry"] == g for r in gvh.values())]
    ncols = min(3, len(lights))
    nrows = -(-len(lights) // ncols)
    gs = fig.add_gridspec(nrows, ncols, top=0.86, bottom=0.16, left=0.07, right=0.98,
                          hspace=0.45, wspace=0.25)
    width = 0.8 / max(len(geoms), 1)
    for i, l in enumerate(lights):
        ax = fig.add_subplot(gs[i // ncols, i % ncols])
        models = _ordered_models(r["model"] for r in gvh.values() if r["light"] == l)
        ymax = max(r["rel_rmse"] for r in gvh.values() if r["light"] == l)
        for k, g in enumerate(geoms):
            vals = [gvh.get(f"{m}-{l}-{g}", {}).get("rel_rmse", np.nan) for m in models]
            x = np.arange(len(models)) + (k - (len(geoms) - 1) / 2) * width
            ax.bar(x, vals, width, label=g, color=("tab:orange", "tab:green", "tab:purple")[k % 3])
            for xx, v in zip(x, vals):
                if np.isfinite(v):
                    ax.text(xx, v, f"{v:.3f}", ha="center", va="bottom", fontsize=MIN_FONT_PT,
                            rotation=90)
        ax.set_xticks(np.arange(len(models)), models, fontsize=8)
        ax.tick_params(axis="y", labelsize=8)
        ax.set_ylim(0, ymax * 1.35 if ymax > 0 else 1.0)  # room for the value labels
        ax.set_title(l, fontsize=9)
        ax.set_ylabel("relative RMSE vs high", fontsize=8)
        if i == 0:
            ax.legend(fontsize=8)
    fig.text(0.07, 0.06, textwrap.fill(
        "The thesis's geometry question: does a 16,750-triangle mesh with baked albedo and bump "
        "maps (sharp, or Gaussian-blurred to stand in for subsurface smoothing) look like the "
        "~1M-triangle scan? Bars: relative RMSE of the low-geometry render against the high-mesh "
        "render of the same model and light (lower = closer); each panel has its own y scale. "
        "Difference images: geomdiff-*.png.",
        170), fontsize=8, va="top")
    return fig


def _opening(pdf, opening_pages) -> list:
    if opening_pages is not None:
        opening_pages(pdf)
    return []


def write_report(images: dict, metrics: dict, out_pdf, *, scene_name: str, device: str,
                 timings_extra: dict | None = None, credits=(), tiles: dict | None = None,
                 image_tiles: dict | None = None, extra_pages=None, opening_pages=None,
                 truth: dict | None = None) -> Path:
    """Write the multi-page comparison PDF.

    Parameters
    ----------
    images : dict node id -> :class:`pipeline.artifacts.RenderedImage`
        ``info`` has "model", "light", "geometry"; ``timings["total"]`` in seconds.
    metrics : dict returned by :func:`reports.diff.write_differences` (its scales are reused
        so the PDF's difference images match the PNGs)
    out_pdf : path of the PDF to write (parent created)
    scene_name : shown on the title page
    device : OpenCL device description, shown on the title and timing pages
    credits : attribution lines of the scene's assets, printed on the title page
    tiles : the ``tiles_out`` of :func:`reports.diff.write_differences`, optional: its
        difference images are placed as they are (else recomputed)
    image_tiles : {(model, light, geometry): uint8 thumbnail}, optional: the images stage's
        tone-mapped thumbnails (:func:`reports.comparison_images.load_thumbnails`), else
        tone-mapped here
    timings_extra : dict (light, mesh) -> seconds, optional
        The BSSRDF's irradiance pass per lighting condition and mesh ("mesh_high"/"mesh_low",
        or "high"/"low"); added to the BSSRDF's time in the table, summary and scatter plot.
    extra_pages : callable(PdfPages), optional
        Adds further pages at the end (the profile page, the ground truth's details).
    opening_pages : callable(PdfPages), optional
        Adds pages right after the title page (the distance to ground truth).
    truth : dict, optional
        The title page's ground-truth summary (:func:`dermis.reports.truth_pages.title_lines`).

    Returns
    -------
    Path of the PDF; it has :func:`report_page_count` pages.
    """
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.backends.backend_pdf import PdfPages

    if not images:
        raise DermisError("report: no rendered images to report on; [render] models, lights "
                          "and geometries must select at least one image")
    out_pdf = Path(out_pdf)
    out_pdf.parent.mkdir(parents=True, exist_ok=True)
    # The PDF's 14 standard fonts (Helvetica, Courier) are referenced, not embedded: embedding
    # and subsetting DejaVu took ~1 s per font face, most of the report's time (text outside
    # Latin-1 would print as '?'; the report's own text is ASCII).
    import logging
    logging.getLogger("matplotlib.font_manager").setLevel(logging.ERROR)
    # zlib level 1 for the page images: ~3x faster than 6 for a slightly larger file.
    # ASCII minus signs on the axes: U+2212 is outside the standard fonts' Latin-1.
    # Titles at the top of their axes (axes.titley = 1, where matplotlib's automatic placement
    # puts them when no tick labels sit on top): the automatic placement measures every tick
    # label of the axes first, ~0.1 s per log-scaled axes on this report's pages.
    with plt.rc_context({"font.size": FONT_PT, "pdf.use14corefonts": True,
                         "font.family": "sans-serif", "pdf.compression": 1,
                         "axes.titley": 1.0, "axes.unicode_minus": False}), \
            PdfPages(out_pdf) as pdf:
        builders = [lambda: [_title_page(plt, images, metrics, scene_name=scene_name,
                                         device=device, timings_extra=timings_extra,
                                         credits=credits, truth=truth)],
                    lambda: _opening(pdf, opening_pages),
                    lambda: _image_pages(plt, images, image_tiles),
                    lambda: _diff_pages(plt, images, metrics, (tiles or {}).get("model")),
                    lambda: [_timing_page(plt, images, metrics, device=device,
                                          timings_extra=timings_extra)],
                    lambda: [_scatter_page(plt, images, metrics, timings_extra=timings_extra)],
                    lambda: [_geometry_page(plt, metrics)]]
        for build in builders:
            for fig in build():  # generators: one page in memory at a time
                pdf.savefig(fig)
                plt.close(fig)
        if extra_pages is not None:
            extra_pages(pdf)
        info = pdf.infodict()
        info["Title"] = f"dermis comparison: {scene_name}"
        info["Creator"] = "dermis reports.pdf_report"
    return out_pdf
