"""The report's opening pages: every model's distance to the path-traced reference, with error bars.

Right after the title page, one page per lighting condition
(:func:`opening_pages`): the relative difference of every model's mean from the reference's in
each face region with error bars of both images' noise (:mod:`dermis.reports.truth_noise`),
the relative RMSE at the ranking scale with the noise that alone would give it, the
ranking with what is and is not resolved, each model's seconds, the noise the reference
reached, and the difference images against the reference beside the ones against the
BSSRDF.  :func:`title_lines` gives the title page its summary: the ranking per light and
the thesis's verdicts, or why there is no reference.

The PDF's fonts are the 14 standard ones (Latin-1): no Greek letters or math signs beyond
"±" and "×" in the text.
"""
from __future__ import annotations

import textwrap
from types import SimpleNamespace

import numpy as np

from dermis.geometry.regions import REGIONS, block_mean
from dermis.pipeline.registry import MODEL_NAMES
from dermis.reports.truth_noise import RESOLVE_K

__all__ = ["opening_pages", "title_lines", "ranking_text", "noise_reached_text", "OPENING_TITLE"]

OPENING_TITLE = "Distance to ground truth"
GEOMETRY = "high"


def _labels(image) -> tuple[str, str, str]:
    info = getattr(image, "info", {}) or {}
    return str(info.get("model", "?")), str(info.get("light", "?")), str(info.get("geometry", "?"))


def _pct(x) -> str:
    return "-" if x is None else f"{100 * x:.1f}"


def ranking_text(gt: dict, light: str) -> str:
    """"a 9.1 ~ b 9.3 < c 12.0" (relative RMSE %, closest first; "<": resolved apart,
    "~": not)."""
    rows = gt.get("ranking", {}).get(light, [])
    out = ""
    for k, r in enumerate(rows):
        if k:
            out += " ~ " if r["tied_with_previous"] else " < "
        out += f"{r['model']} {_pct(r['rel_rmse'])}"
    return out


def noise_reached_text(ref: dict) -> str:
    """What noise the reference reached (its passes, samples, stopping rule, worst region)."""
    spp, passes, stopped = ref.get("spp"), ref.get("passes"), ref.get("stopped")
    target, budget = ref.get("target_rel_se"), ref.get("budget_s")
    rel = ref.get("region_rel_se") or {}
    if not rel:   # from the region standard errors (channels independent)
        from dermis.reports.ground_truth import _rel_se_lum
        rel = {k: _rel_se_lum(v["mean_rgb"], v["stderr_rgb"])
               for k, v in (ref.get("regions") or {}).items()
               if "stderr_rgb" in v and "mean_rgb" in v}
        rel = {k: v for k, v in rel.items() if v is not None}
    worst = max(rel.items(), key=lambda kv: kv[1]) if rel else None
    spp_txt = f"{spp:.0f}" if isinstance(spp, (int, float)) else f"{spp}"
    parts = [f"{ref.get('width')}×{ref.get('height')} px, {spp_txt} samples per pixel "
             "(mean; more where the regions needed them)"]
    if passes is not None:
        parts.append(f"{passes} passes")
    if stopped == "target":
        parts.append("stopped at its target" + (f" (region means to {_pct(target)} % relative "
                                                 "standard error)" if target else ""))
    elif stopped == "budget":
        parts.append("stopped by its time budget" + (f" ({budget:.0f} s)" if budget else "")
                     + (f" before its target of {_pct(target)} %" if target else ""))
    elif stopped == "max_passes":
        parts.append("stopped at its maximum of passes" + (
            f" before its target of {_pct(target)} %" if target else ""))
    elif stopped:
        parts.append(f"stopped: {stopped}")
    else:
        parts.append("a fixed sample count (no stopping rule recorded)")
    parts.append(f"{ref.get('seconds', 0.0):.0f} s")
    text = "Reference noise reached: " + ", ".join(parts) + "."
    if worst:
        text += (f"  Worst region: {worst[0]}, {_pct(worst[1])} % relative standard error of its "
                 f"mean; at 4×4 blocks the image's noise is "
                 f"{_pct((ref.get('noise', {}).get('4') or {}).get('rel'))} % (relative RMSE).")
    calib = ref.get("calibration_rel_rgb")
    if calib and any(calib):
        text += (f"  Albedo-tint calibration: {', '.join(_pct(c) for c in calib)} % (R, G, B; "
                 "in the region error bars).")
    return text


def title_lines(gt: dict | None, skip_reason: str | None) -> dict:
    """The title page's summary: ``truth`` (whether a reference exists), ``lines`` (per light,
    the ranking against it), ``thesis`` [(claim, verdict)], ``note`` (why there is none)."""
    if not gt:
        why = skip_reason or "[reference] enabled = false"
        return {"truth": False, "lines": [], "thesis": [],
                "note": f"No path-traced reference in this run ({why.rstrip('.')}). Every "
                        "distance in this report is to the BSSRDF, a model, not the truth."}
    lines = [f"{l}: {ranking_text(gt, l)}" for l in sorted(gt.get("ranking", {}))]
    thesis = [(c["claim"], c["verdict"]) for c in gt.get("thesis", [])]
    return {"truth": True, "lines": lines, "thesis": thesis,
            "note": "Distance to the Mitsuba 3 path-traced reference: relative RMSE (%) on 4×4 "
                    "blocks of its pixels, closest first; '<' resolved apart, '~' not resolved "
                    f"at this noise ({RESOLVE_K:g} standard errors of both images' noise)."}


def _models(gt: dict, light: str) -> list[str]:
    have = {r["model"] for r in gt["models"].values() if r["light"] == light}
    return [m for m in MODEL_NAMES if m in have] + sorted(have - set(MODEL_NAMES))


def _region_axes(fig, rect, gt, light, models):
    ax = fig.add_axes(rect)
    regions = [n for n in REGIONS if any(n in gt["models"][f"{m}-{light}"]["regions"]
                                         for m in models)]
    width = 0.8 / max(len(models), 1)
    spans = []
    import matplotlib.pyplot as plt
    cmap = plt.get_cmap("tab10")
    for k, m in enumerate(models):
        rec = gt["models"][f"{m}-{light}"]
        for i, name in enumerate(regions):
            g = rec["regions"].get(name)
            if not g:
                continue
            x = i + (k - (len(models) - 1) / 2) * width
            y, e = 100 * g["rel_lum"], 100 * RESOLVE_K * g["sigma_lum"]
            spans.append((y, e))
            ax.errorbar([x], [y], yerr=[e], fmt="o", ms=4.5, capsize=2, color=cmap(k % 10),
                        mfc=cmap(k % 10) if g["resolved"] else "white", lw=1.0,
                        label=m if i == 0 else None)
    ax.axhline(0.0, color="0.3", lw=0.8)
    # a region of few pixels can have bars of several hundred percent: the frame keeps the
    # others readable (bars beyond it are cut at the frame)
    ext = np.array([abs(y) + e for y, e in spans]) if spans else np.array([5.0])
    lim = max(min(float(ext.max()), 2.5 * float(np.median(ext))),
              1.15 * max((abs(y) for y, _ in spans), default=0.0), 5.0) * 1.08
    ax.set_ylim(-lim, lim)
    ax.set_xticks(np.arange(len(regions)), [n.replace("_", " ") for n in regions], fontsize=8)
    ax.tick_params(axis="y", labelsize=8)
    ax.set_ylabel("model / reference - 1, luminance (%)", fontsize=8)
    ax.set_title(f"Region means: bars ± {RESOLVE_K:g} standard errors (both images' noise and "
                 "the tint calibration);\nfilled = resolved, hollow = not resolved at this "
                 "noise", fontsize=8)
    ax.grid(True, axis="y", alpha=0.3)
    ax.legend(fontsize=7, ncol=min(len(models), 5), loc="upper center",
              bbox_to_anchor=(0.5, -0.09), frameon=False)
    return ax


def _table(fig, rect, gt, light, models):
    ax = fig.add_axes(rect)
    ax.axis("off")
    fk = str(gt.get("rank_factor", 4))
    ranked = {r["model"]: (k + 1, r) for k, r in enumerate(gt["ranking"].get(light, []))}
    header = ["model", "rel RMSE %", "± noise %", "resolved", "rank (range)", "own noise %",
              "seconds"]
    cells = []
    for m in models:
        rec = gt["models"][f"{m}-{light}"]
        s = rec["scales"].get(fk, {})
        if m in ranked:
            k, r = ranked[m]
            rank = str(k) if r["rank_best"] == r["rank_worst"] else \
                f"{k} ({r['rank_best']}-{r['rank_worst']})"
        else:
            rank = "-"
        own = _pct(s.get("model_noise")) if rec.get("own_noise") else "not estimated"
        cells.append([m, _pct(s.get("rel_rmse")), _pct(s.get("noise")),
                      "yes" if s.get("resolved") else "no", rank, own,
                      f"{rec.get('seconds', 0.0):.2f}"])
    ref = gt["references"][light]
    cells.append(["reference", "0", _pct((ref.get("noise", {}).get(fk) or {}).get("rel")), "",
                  "", "", f"{ref.get('seconds', 0.0):.0f}"])
    widths = [0.28, 0.12, 0.11, 0.10, 0.13, 0.14, 0.12]
    rows = len(cells) + 1
    height = min(1.0, rows * 0.1)
    tab = ax.table(cellText=cells, colLabels=header, colWidths=widths, cellLoc="center",
                   bbox=[0, 1 - height, 1, height])
    tab.auto_set_font_size(False)
    tab.set_fontsize(8)
    for (r, c), cell in tab.get_celld().items():
        if r == 0:
            cell.set_text_props(weight="bold", fontsize=7)
    ax.set_title(f"Relative RMSE on {fk}×{fk} blocks of reference pixels (the ranking scale); "
                 "± = what noise alone\ngives (reference's and model's own, in quadrature); "
                 f"resolved = above {RESOLVE_K:g}× that", fontsize=8, loc="left")
    return ax


def _diff_tiles(fig, rect, gt, light, images, ref, models, differences, tiles):
    """Row 1: the reference, then every model minus the reference on its grid; row 2: the
    BSSRDF, then every model minus the BSSRDF (the report's difference images)."""
    from dermis.reports.diff import default_scale, difference, difference_image
    from dermis.reports.ground_truth import _downsample_to, _tonemap_pair
    h, w = ref.linear.shape[:2]
    M = np.asarray(ref.linear, np.float64)
    rmask = np.asarray(ref.mask, bool)
    idx = {_labels(im): im for im in images.values()}
    base = idx.get(("bssrdf", light, GEOMETRY))
    fk = int(gt.get("rank_factor", 4))
    vs_ref = {}
    for m in models:
        im = idx.get((m, light, GEOMETRY))
        D, full = _downsample_to(np.asarray(im.linear, np.float64), np.asarray(im.mask, bool),
                                 (h, w))
        # on the ranking scale's blocks: per reference pixel its noise is speckle that
        # hides every systematic difference (docs/ground-truth.md)
        d, mb = block_mean(D - M, full & rmask, fk)
        vs_ref[m] = SimpleNamespace(diff=np.where(mb[..., None], d, 0.0), mask=mb)
    scales = ((differences or {}).get("scales", {}) or {}).get("model", {})
    # one scale for both rows (the BSSRDF differences'), so their colours compare
    scale = scales.get(light) or default_scale(list(vs_ref.values()))
    scale_b = scale
    mvr = (differences or {}).get("model_vs_reference", {})
    shown = [np.asarray(ref.linear)]
    if base is not None:
        shown.append(_downsample_to(np.asarray(base.linear, np.float64),
                                    np.asarray(base.mask, bool), (h, w))[0].astype(np.float32))
    srgb = _tonemap_pair(shown)
    x0, y0, ww, hh = rect
    ncol = 1 + len(models)
    fs = 7 if ncol <= 9 else max(4.5, 63 / ncol)   # titles side by side must not overlap
    gs = fig.add_gridspec(2, ncol, left=x0, right=x0 + ww, bottom=y0, top=y0 + hh,
                          hspace=0.32, wspace=0.05)
    f = images and next(iter(images.values())).linear.shape[0] // h
    for row in range(2):
        ax = fig.add_subplot(gs[row, 0])
        ax.axis("off")
        if row == 0:
            ax.imshow(srgb[0], interpolation="nearest")
            ax.set_title("reference (Mitsuba)", fontsize=fs)
        elif base is not None:
            ax.imshow(srgb[1], interpolation="nearest")
            ax.set_title("bssrdf", fontsize=fs)
    for j, m in enumerate(models):
        rec = gt["models"][f"{m}-{light}"]
        ax = fig.add_subplot(gs[0, 1 + j])
        ax.axis("off")
        ax.imshow(difference_image(vs_ref[m], scale=scale), interpolation="nearest")
        s = rec["scales"].get(str(fk), {})
        ax.set_title(f"{m}\n- reference\nrel RMSE {_pct(s.get('rel_rmse'))} ± "
                     f"{_pct(s.get('noise'))} %", fontsize=fs)
        ax = fig.add_subplot(gs[1, 1 + j])
        ax.axis("off")
        if m == "bssrdf" or base is None:
            ax.text(0.5, 0.5, "(the BSSRDF itself)" if m == "bssrdf" else "(no BSSRDF)",
                    ha="center", va="center", fontsize=7, transform=ax.transAxes)
            continue
        tile = (tiles or {}).get((m, light, GEOMETRY))
        if tile is None:
            tile = difference_image(difference(idx[(m, light, GEOMETRY)], base), scale=scale_b)
        ax.imshow(tile, interpolation="nearest")
        r = mvr.get(f"{m}-{light}-{GEOMETRY}")
        ax.set_title(f"{m}\n- bssrdf" + (f"\nrel RMSE {_pct(r['rel_rmse'])} %" if r else ""),
                     fontsize=fs)
    return f, fk, scale


def _light_page(plt, gt, light, images, ref, differences, tiles, figsize):
    fig = plt.figure(figsize=figsize)
    fig.suptitle(f"{OPENING_TITLE}, {light}: every model against the Mitsuba 3 path-traced "
                 "reference", fontsize=12, y=0.975)
    models = [m for m in _models(gt, light)
              if any(_labels(im) == (m, light, GEOMETRY) for im in images.values())]
    _region_axes(fig, [0.06, 0.63, 0.42, 0.27], gt, light, models)
    _table(fig, [0.53, 0.60, 0.45, 0.30], gt, light, models)
    missing = [m for m in models if not gt["models"][f"{m}-{light}"].get("own_noise")]
    own = ("Own noise not estimated (taken as 0, so their error bars hold the reference's "
           f"noise only): {', '.join(missing)}." if missing else
           "Every model's own noise is estimated from its two half images.")
    lines = [f"Ranking (relative RMSE % on 4×4 blocks, closest first; '<' resolved apart, '~' "
             f"not resolved at this noise): {ranking_text(gt, light)}.",
             noise_reached_text(gt["references"][light]), own]
    text = "\n".join(textwrap.fill(s, 175) for s in lines)
    fig.text(0.04, 0.535, text, va="top", fontsize=8, linespacing=1.35)
    f, fk, scale = _diff_tiles(fig, [0.02, 0.01, 0.96, 0.31], gt, light, images, ref, models,
                               differences, tiles)
    fig.text(0.04, 0.405, textwrap.fill(
        "Difference images, luminance (red = model brighter, blue = darker; one scale for both "
        f"rows, ± {scale:.3g}): top, the model minus the reference on {fk}×{fk} blocks of "
        f"reference pixels (the ranking scale; the model first averaged over each reference "
        f"pixel's {f}×{f} camera pixels); bottom, the model minus the BSSRDF on the camera "
        "grid, as on the report's difference pages.", 190), va="top", fontsize=7.5,
        color="0.25")
    return fig


def opening_pages(pdf, gt: dict | None, images: dict, references: dict, *,
               differences: dict | None = None, tiles: dict | None = None,
               figsize=(11.69, 8.27)) -> int:
    """Add one opening page per lighting condition with a reference; returns the count (0
    without references: the title page then says why)."""
    if not gt or not references:
        return 0
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    pages = 0
    for light in sorted(references):
        if not any(r["light"] == light for r in gt["models"].values()):
            continue
        fig = _light_page(plt, gt, light, images, references[light], differences, tiles,
                          figsize)
        pdf.savefig(fig)
        plt.close(fig)
        pages += 1
    return pages
