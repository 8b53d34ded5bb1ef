"""The causes table: every model's distance to the reference, split into its measured causes.

A model's distance to the path-traced reference in a face region is d = model / truth - 1
(:func:`dermis.reports.ground_truth.ground_truth_metrics`, ``rel_rgb`` / ``rel_lum``).  Each
cause k is a factor f_k by which it changes the ratio model / truth:

* ``geometry`` (model side): the model rendered on the low mesh with the sharp bump map
  instead of the high mesh, f = mean(low_bump) / mean(high) over the region's pixels --
  only on the ``low_bump`` rows (the reference is of the high mesh, so a high-mesh model
  shares its geometry: 0);
* ``profile`` (model side, the BSSRDF): the multipole profile instead of the Monte Carlo
  table, f = (1 + d_bssrdf) / (1 + d_bssrdf_mc) -- the truth's noise cancels in it;
* ``convention`` (a number the caller gives): the albedo convention's relative change of
  model / truth, f = 1 + c;
* ``interreflection`` (truth side): the truth has it, the models do not; the variant's gain
  g (all bounces / direct - 1, :mod:`dermis.groundtruth.variants`) gives f = 1 / (1 + g);
* ``boundary`` (truth side): the truth's rough boundary instead of the models' smooth one;
  the variant's effect b (smooth / rough - 1) gives f = 1 + b.

The parts telescope: d_0 = d, d_k = (1 + d_(k-1)) / f_k - 1 (the distance once causes 1..k
are removed), part_k = d_(k-1) - d_k, and the remainder is the last d_k, so the parts and
the remainder sum to d exactly (first-order in each cause, so the order above matters only
at second order).  A cause not measured for a row (no variant for its light, no bssrdf_mc
image) has part None and stays in the remainder.  Standard errors: a part's is
(1 + d_(k-1)) se(f_k) / f_k^2 (the variants' half-buffers; model-side factors carry only
the models' own noise, not estimated here: None); the remainder's adds the distance's sigma
and the parts' errors in quadrature.

Rows are per lighting condition, model, geometry (``high``; ``low_bump`` where both images
exist) and region (:data:`dermis.geometry.regions.REGIONS` and ``face``, every pixel: its
distance is the metrics' whole-image flux bias, whose luminance weights the channels by the
reference's mean colour over the regions; no sigma).  Luminance and each RGB channel are
split alike.  :func:`causes_table` returns plain dicts; :func:`causes_pages` draws them.
"""
from __future__ import annotations

import math

import numpy as np

from dermis.geometry.regions import REGION_LABELS, REGIONS, block_mean
from dermis.groundtruth.variants import WHOLE_FACE
from dermis.rendering.color import LUMINANCE

__all__ = ["CAUSES", "causes_table", "geometry_factors", "causes_pages", "TABLE_REGIONS"]

CAUSES = ("geometry", "profile", "convention", "interreflection", "boundary")
TABLE_REGIONS = REGIONS + (WHOLE_FACE,)
PROFILE_MODEL, PROFILE_EXACT = "bssrdf", "bssrdf_mc"
BUMP_GEOMETRY = "low_bump"


def _info(v) -> dict:
    """A variants entry: the causes stage's artifact, its ``info``, or its ``causes`` dict."""
    info = getattr(v, "info", v) or {}
    return info.get("causes", info)


def _channels(rec: dict, key_rgb: str, key_lum: str) -> list:
    """[lum, r, g, b] of a record (None where missing)."""
    rgb = rec.get(key_rgb) or [None] * 3
    return [rec.get(key_lum)] + list(rgb)


def _face_distance(rec: dict, ref_regions: dict) -> dict | None:
    """The whole-face row of a metrics record: its flux bias (module docstring)."""
    if WHOLE_FACE in rec.get("regions", {}):
        return rec["regions"][WHOLE_FACE]
    bias = rec.get("bias_rgb")
    if bias is None:
        return None
    w = np.zeros(3)
    for r in ref_regions.values():
        w += np.asarray(r.get("mean_rgb", [0, 0, 0]), np.float64) * r.get("pixels", 0)
    w = w * LUMINANCE
    lum = float(w @ (1.0 + np.asarray(bias)) / w.sum() - 1.0) if w.sum() > 0 else None
    return {"rel_rgb": [float(b) for b in bias], "rel_lum": lum, "sigma_rgb": None,
            "sigma_lum": None}


def geometry_factors(images: dict, labels: np.ndarray) -> dict:
    """mean(low_bump) / mean(high) per (model, light) and region, [lum, r, g, b]: the model
    images block-averaged to the reference grid of ``labels`` ((H, W) region labels, 0 none;
    only blocks both images cover whole count; ``face`` = every such block)."""
    idx = {}
    for im in images.values():
        info = getattr(im, "info", {}) or {}
        idx[(info.get("model"), info.get("light"), info.get("geometry"))] = im
    h, w = labels.shape
    out = {}
    for (model, light, geom), hi in idx.items():
        lo = idx.get((model, light, BUMP_GEOMETRY))
        if geom != "high" or lo is None:
            continue
        f = hi.linear.shape[0] // h
        if f < 1 or f * h != hi.linear.shape[0] or lo.linear.shape != hi.linear.shape:
            continue
        H, mh = block_mean(np.asarray(hi.linear, np.float64), np.asarray(hi.mask, bool), f)
        L, ml = block_mean(np.asarray(lo.linear, np.float64), np.asarray(lo.mask, bool), f)
        valid = mh & ml
        rec = {}
        for name in TABLE_REGIONS:
            sel = valid if name == WHOLE_FACE else valid & (labels == REGION_LABELS[name])
            if not sel.any():
                continue
            sh, sl = H[sel].sum(axis=0), L[sel].sum(axis=0)
            lh, ll = float(sh @ LUMINANCE), float(sl @ LUMINANCE)
            rec[name] = [ll / lh if lh > 0 else None] + [float(a / b) if b > 0 else None
                                                       for a, b in zip(sl, sh)]
        out[(model, light)] = rec
    return out


def _telescope(d: list, factors: list) -> tuple[dict, list]:
    """Parts and remainder for one channel: ``factors`` = [(cause, f, se_f | None) or
    (cause, None, None)] in order."""
    parts, cur = {}, d
    for cause, f, se_f in factors:
        if f is None or cur is None or not f > 0:
            parts[cause] = (None, None)
            continue
        nxt = cur if f == 1.0 else (1.0 + cur) / f - 1.0
        se = None if se_f is None else (1.0 + cur) * se_f / (f * f)
        parts[cause] = (cur - nxt, se)
        cur = nxt
    return parts, cur


def causes_table(metrics: dict, variants: dict, *, convention=0.0, images: dict | None = None,
                 labels: np.ndarray | None = None) -> dict:
    """Every model's distance per light and region, split into causes (module docstring).

    Parameters
    ----------
    metrics : dict
        :func:`dermis.reports.ground_truth.ground_truth_metrics`'s output (read only).
    variants : dict light -> the causes stage's artifact (or its ``info``)
    convention : float or (3,) sequence
        The albedo convention's relative change of model / truth (negative: it makes the
        models darker), per channel; a float applies to all three and luminance.
    images : dict id -> RenderedImage, optional
        The model renders; with ``labels`` (the reference grid's (H, W) region labels) they
        give the ``low_bump`` rows and their geometry part.

    Returns
    -------
    dict: ``causes`` (the order), ``convention``, ``rows`` (a list of dicts: light, model,
    geometry, region, ``distance`` and ``sigma`` ([lum, r, g, b]), ``parts`` (cause ->
    {"value": [lum, r, g, b], "se": [...]}, None where not measured), ``remainder``
    ({"value", "se"})).
    """
    conv = np.broadcast_to(np.asarray(convention, np.float64), (3,))
    conv4 = [float(conv @ LUMINANCE / LUMINANCE.sum())] + [float(c) for c in conv]
    geom = geometry_factors(images, labels) if images and labels is not None else {}
    recs = metrics.get("models", {})
    rows = []
    for key in sorted(recs):
        rec = recs[key]
        model, light = rec.get("model"), rec.get("light")
        var = _info(variants.get(light, {}))
        inter, bound = var.get("interreflection", {}), var.get("boundary", {})
        ref_regions = metrics.get("references", {}).get(light, {}).get("regions", {})
        exact = recs.get(f"{PROFILE_EXACT}-{light}")
        for region in TABLE_REGIONS:
            dist = (_face_distance(rec, ref_regions) if region == WHOLE_FACE
                    else rec.get("regions", {}).get(region))
            if not dist:
                continue
            d_high = _channels(dist, "rel_rgb", "rel_lum")
            sigma = _channels(dist, "sigma_rgb", "sigma_lum")
            prof = None
            if model == PROFILE_MODEL and exact:
                e = (_face_distance(exact, ref_regions) if region == WHOLE_FACE
                     else exact.get("regions", {}).get(region))
                if e:
                    de = _channels(e, "rel_rgb", "rel_lum")
                    prof = [None if a is None or b is None else (1 + a) / (1 + b)
                            for a, b in zip(d_high, de)]
            g = geom.get((model, light), {}).get(region)
            for geometry in ("high", BUMP_GEOMETRY):
                if geometry == BUMP_GEOMETRY and g is None:
                    continue
                if geometry == "high":
                    d, fg = d_high, [1.0] * 4
                else:
                    d = [None if a is None or b is None else (1 + a) * b - 1
                         for a, b in zip(d_high, g)]
                    fg = g
                rows.append(_row(light, model, geometry, region, d, sigma, fg, prof, conv4,
                                 inter.get(region), bound.get(region)))
    return {"causes": list(CAUSES), "convention": conv4, "rows": rows}


# A variant's effect enters the table only when its standard error is known and at most this
# (10 percentage points): the default budget's boundary variant read -2106 % (no standard
# error: under 8 lit pixels) or +83 +- 57 % in small regions, noise that would swamp every
# other part; such an effect stays in the remainder, shown as not measured.
MAX_EFFECT_SE = 0.10


def _effect(rec: dict | None, c: int):
    if not rec or rec.get("effect_lum") is None:
        return None, None
    v = _channels(rec, "effect_rgb", "effect_lum")[c]
    s = _channels(rec, "se_rgb", "se_lum")[c]
    if v is None or s is None or not s <= MAX_EFFECT_SE:
        return None, None
    return v, s


def _row(light, model, geometry, region, d, sigma, fg, prof, conv4, inter, bound) -> dict:
    parts = {k: {"value": [None] * 4, "se": [None] * 4} for k in CAUSES}
    rem, rem_se = [None] * 4, [None] * 4
    for c in range(4):
        g, gse = _effect(inter, c)
        b, bse = _effect(bound, c)
        factors = [
            ("geometry", fg[c], None if geometry == BUMP_GEOMETRY else 0.0),
            ("profile", prof[c] if prof else None, None),
            ("convention", 1.0 + conv4[c], 0.0),
            ("interreflection", None if g is None else 1.0 / (1.0 + g),
             None if gse is None else gse / (1.0 + g) ** 2),
            ("boundary", None if b is None else 1.0 + b, bse),
        ]
        p, r = _telescope(d[c], factors)
        for k, (v, s) in p.items():
            parts[k]["value"][c], parts[k]["se"][c] = v, s
        rem[c] = r
        terms = [sigma[c]] + [s for v, s in p.values() if v is not None]
        known = [t for t in terms if t is not None]
        rem_se[c] = math.sqrt(sum(t * t for t in known)) if known else None
    for k in CAUSES:
        if all(v is None for v in parts[k]["value"]):
            parts[k] = None
    return {"light": light, "model": model, "geometry": geometry, "region": region,
            "distance": d, "sigma": sigma, "parts": parts,
            "remainder": {"value": rem, "se": rem_se}}


# --------------------------------------------------------------------------- the page
def _pct(v, se=None) -> str:
    if v is None:
        return "–"
    s = f"{100 * v:+.1f}"
    return s + (f" ± {100 * se:.1f}" if se is not None and se > 0 else "")


def causes_pages(pdf, table: dict, *, figsize=(11.69, 8.27), max_rows: int = 36) -> int:
    """Add the causes table to an open ``PdfPages``: per lighting condition, rows model x
    region (high mesh; luminance, %), columns the distance, each cause's part, the remainder
    and, where low+bump images exist, that row's distance and geometry part.  Returns the
    number of pages."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from dermis.reports.pdf_report import MIN_FONT_PT, page_table

    rows = table.get("rows", [])
    lights = sorted({r["light"] for r in rows})
    bump = {(r["light"], r["model"], r["region"]): r for r in rows
            if r["geometry"] == BUMP_GEOMETRY}
    shown = [k for k in CAUSES if k != "geometry"]
    header = (["model / region", "distance"] + shown + ["remainder", "low+bump", "geometry"])
    pages = 0
    for light in lights:
        high = [r for r in rows if r["light"] == light and r["geometry"] == "high"]
        for start in range(0, max(len(high), 1), max_rows):
            chunk = high[start:start + max_rows]
            cells = []
            for r in chunk:
                b = bump.get((light, r["model"], r["region"]))
                cell = [f"{r['model']} / {r['region']}", _pct(r["distance"][0], r["sigma"][0])]
                for k in shown:
                    p = r["parts"].get(k)
                    cell.append(_pct(p["value"][0], p["se"][0]) if p else "–")
                cell.append(_pct(r["remainder"]["value"][0], r["remainder"]["se"][0]))
                gp = b["parts"].get("geometry") if b else None
                cell += [_pct(b["distance"][0]) if b else "–",
                         _pct(gp["value"][0]) if gp else "–"]
                cells.append(cell)
            fig = plt.figure(figsize=figsize)
            fig.suptitle(f"Causes of the distance to ground truth: {light} (luminance, %, "
                         "± 1 s.e.)", fontsize=12, y=0.975)
            ax = fig.add_axes([0.02, 0.1, 0.96, 0.83])
            ax.axis("off")
            if cells:
                n = len(header)
                page_table(ax, cells, header, widths=[0.2] + [0.8 / (n - 1)] * (n - 1),
                           row_height=0.027, fontsize=MIN_FONT_PT)
            conv = table.get("convention", [0.0])[0]
            fig.text(0.02, 0.04, "distance = model / reference - 1 over the region's pixels. "
                     "Parts telescope (they and the remainder sum to the distance): profile = "
                     "multipole vs Monte Carlo table (BSSRDF); convention = "
                     f"{100 * conv:+.1f} % (given); interreflection and boundary = the "
                     "reference's controlled variants (diffuse head all/direct bounces; smooth "
                     "vs rough boundary). low+bump: the same model on the low mesh with the "
                     "sharp bump, its geometry part. – = not measured, or a variant's standard "
                     f"error above {100 * MAX_EFFECT_SE:.0f} points (left in the remainder).",
                     fontsize=MIN_FONT_PT,
                     wrap=True)
            pdf.savefig(fig)
            plt.close(fig)
            pages += 1
    return pages
