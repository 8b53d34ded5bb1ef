"""The report's adaptive-BSSRDF pages: where the adaptive model gathers, and what it costs.

Per view and lighting condition with both a ``bssrdf`` and a ``bssrdf_adaptive`` image of
the high mesh, one row: the full BSSRDF and the adaptive image at one exposure, the blend
weight (``RenderedImage.blend``: black = the exact part and the interpolated gather, white =
gathered, docs/science.md §4 "Adaptive gather") and the difference adaptive - full on the
difference palette with full red / blue at ``DIFF_SCALE`` of the full image's 99th-percentile
luminance (so a seam or a missed region would show at a per-cent level).  The row's title
gives the relative RMSE against the full BSSRDF, the pixels gathered and the seconds of each
image's exitance in this run (the octree and shadow edges the images of a lighting condition
share are paid by the first that needs them; bench/bench_bssrdf_adaptive.py compares them
like for like).  ``ROWS`` rows a page.
"""
from __future__ import annotations

import numpy as np

from dermis.reports.diff import difference, difference_image, image_labels
from dermis.rendering.color import LUMINANCE
from dermis.reports.tonemap import tonemap

__all__ = ["adaptive_pages", "adaptive_rows", "ROWS", "DIFF_SCALE"]

ROWS = 4
# The difference shown at full colour: 1 % of the full image's 99th-percentile luminance,
# the model's target (subsurface/adaptive.py TARGET)
DIFF_SCALE = 0.01
GEOMETRY = "high"


def adaptive_rows(images: dict) -> list[tuple[str, object, object]]:
    """(lighting label, full BSSRDF image, adaptive image) for every lighting condition (a
    close-up's "<lighting>@<view>" included) with both on the high mesh, in the images'
    order."""
    by = {image_labels(im): im for im in images.values()}
    rows = []
    for (model, light, geometry), im in by.items():
        full = by.get(("bssrdf", light, geometry))
        if model == "bssrdf_adaptive" and geometry == GEOMETRY and full is not None:
            rows.append((light, full, im))
    return rows


def adaptive_pages(pdf, images: dict) -> int:
    """Add the pages to the open ``PdfPages`` ``pdf``; returns the pages added (0 without an
    adaptive image)."""
    import matplotlib.pyplot as plt
    rows = adaptive_rows(images)
    pages = 0
    for start in range(0, len(rows), ROWS):
        fig = plt.figure(figsize=(11.69, 8.27))
        fig.suptitle("Adaptive BSSRDF: where it gathers (white), and its difference from the "
                     f"full BSSRDF (full red / blue at {100 * DIFF_SCALE:g} % of the image's "
                     "99th-percentile luminance)", fontsize=10, y=0.985)
        part = rows[start:start + ROWS]
        gs = fig.add_gridspec(ROWS, 4, left=0.03, right=0.97, bottom=0.02, top=0.90,
                              hspace=0.30, wspace=0.04)
        for r, (light, full, ad) in enumerate(part):
            _row(fig, gs, r, light, full, ad)
        pdf.savefig(fig)
        plt.close(fig)
        pages += 1
    return pages


def _row(fig, gs, r, light, full, ad) -> None:
    mask = np.asarray(full.mask, bool) & np.asarray(ad.mask, bool)
    d = difference(ad, full, relative=False)
    lum = np.asarray(full.linear, np.float32)[mask] @ LUMINANCE.astype(np.float32)
    scale = DIFF_SCALE * float(np.percentile(lum, 99)) if lum.size else None
    srgb = tonemap([np.asarray(full.linear), np.asarray(ad.linear)])
    blend = np.zeros(mask.shape, np.float32) if ad.blend is None else np.asarray(ad.blend)
    g = ad.info.get("gather", {})
    t_full, t_ad = (full.timings.get("gather"), ad.timings.get("gather"))
    # in a run the first BSSRDF image of a condition pays for what they share (octree,
    # shadow edges): a like-for-like ratio is bench/bench_bssrdf_adaptive.py's
    cost = (f"exitance {t_ad:.2f} s, full {t_full:.2f} s (shared work in the first)"
            if t_full and t_ad else "")
    titles = (f"{light}: bssrdf", "bssrdf_adaptive",
              f"blend: {100 * float(g.get('gathered_pixel_fraction', np.mean(blend[mask] > 0))):.0f} "
              "% of pixels gathered",
              f"adaptive - full: rel RMSE {100 * d.metrics['rel_rmse']:.2f} %\n{cost}")
    tiles = (srgb[0], srgb[1], np.where(mask, np.clip(blend, 0.0, 1.0), 0.0),
             difference_image(d, scale=scale))
    for c, (tile, title) in enumerate(zip(tiles, titles)):
        ax = fig.add_subplot(gs[r, c])
        ax.axis("off")
        ax.imshow(tile, cmap="gray" if c == 2 else None, vmin=0.0, vmax=1.0,
                  interpolation="nearest")
        ax.set_title(title, fontsize=7)
