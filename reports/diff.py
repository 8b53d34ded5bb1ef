"""Difference images and error metrics against a reference render (the BSSRDF by default).

The thesis (Arizpe 2006) compares each model with the multi-layer BSSRDF by eye; here the
comparison is also measured: per image RMSE, relative RMSE, per-channel bias, the 95th
percentile of the per-pixel relative error, and SSIM on luminance.  The same functions
compare geometries (low mesh + bump map vs the ~1M-triangle mesh, docs/science.md §7), the
thesis's second question.

Everything here is pure except :func:`write_differences`, which is the report writer.
Conventions: images are linear RGB (H, W, 3); a pixel counts only where *both* images have
a camera hit (``RenderedImage.mask``), intersected with an optional caller mask.
"""
from __future__ import annotations

import functools
import json
import math
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from dermis.pipeline.errors import DermisError
from dermis.rendering.color import LUMINANCE

__all__ = ["DiffResult", "difference", "difference_image", "difference_indices",
           "difference_palette", "DIFF_LEVELS", "diverging_lut", "diverging_colormap",
           "write_differences", "image_labels", "REL_FLOOR_FRACTION", "SSIM_SIGMA_PX",
           "DIFF_SCALE_PERCENTILE"]


# Relative error = (image - reference) / max(reference, floor), floor per channel =
# REL_FLOOR_FRACTION x the mean reference value over the mask.  Without a floor, shadowed
# pixels (reference ~ 0) make the ratio infinite; 5 % of the mean keeps ordinary lit skin
# (almost always > 5 % of the mean) exactly relative, and turns errors in deep shadow into
# "absolute error in units of 5 % of the typical brightness".  Our choice, not a standard.
REL_FLOOR_FRACTION = 0.05

# SSIM (Wang, Bovik, Sheikh, Simoncelli 2004, IEEE TIP 13(4)): Gaussian window sigma 1.5 px
# truncated to 11x11, K1 = 0.01, K2 = 0.03 -- the paper's values.
SSIM_SIGMA_PX = 1.5
SSIM_K1, SSIM_K2 = 0.01, 0.03
# SSIM needs a dynamic range L; linear HDR renders have none, so both luminances are divided
# by this percentile of the reference's luminance over the mask and L = 1 (the render
# stage's tone mapping also maps a high percentile to white).
SSIM_RANGE_PERCENTILE = 99.0

# Colours of a difference image: an even number (symmetric about 0) that leaves one entry
# of a 256-colour PNG palette for black outside the mask.
DIFF_LEVELS = 254

# Default symmetric scale of a difference image: this percentile of |luminance difference|
# over the mask, so a few outlier pixels (silhouette edges) do not wash out the rest.
DIFF_SCALE_PERCENTILE = 99.0


@dataclass
class DiffResult:
    """Difference of an image against a reference.

    diff : (H, W, 3) float32, image - reference (0 outside ``mask``)
    relative : (H, W, 3) float32, diff / max(reference, floor) (0 outside ``mask``)
    mask : (H, W) bool, pixels that count (both images cover them)
    metrics : dict of floats/lists -- rmse, rel_rmse, bias_rgb, flux_ratio_rgb, max_abs,
        ssim, rel_p95, pixels, rel_floor_rgb (see :func:`difference`)
    """

    diff: np.ndarray
    relative: np.ndarray
    mask: np.ndarray
    metrics: dict = field(default_factory=dict)


def _as_arrays(obj, what: str) -> tuple[np.ndarray, np.ndarray | None]:
    """(linear (H,W,3) float32, mask or None) from a RenderedImage or an array."""
    lin = getattr(obj, "linear", obj)
    arr = np.asarray(lin, dtype=np.float32)
    if arr.ndim != 3 or arr.shape[2] != 3:
        raise DermisError(f"{what}: shape {arr.shape}; expected (H, W, 3) linear RGB")
    mask = getattr(obj, "mask", None)
    return arr, (None if mask is None else np.asarray(mask, dtype=bool))


def _percentile(values: np.ndarray, q: float) -> float:
    """``np.percentile(values, q)`` (linear interpolation) through one partition."""
    n = len(values)
    pos = (n - 1) * q / 100.0
    lo = int(math.floor(pos))
    hi = min(lo + 1, n - 1)
    part = np.partition(values, [lo, hi])
    return float(part[lo] + (pos - lo) * (float(part[hi]) - float(part[lo])))


def _blur(v: np.ndarray) -> np.ndarray:
    from scipy.ndimage import gaussian_filter
    return gaussian_filter(v, SSIM_SIGMA_PX, truncate=3.5, mode="constant")  # 11x11 window


def _ssim_reference(b: np.ndarray, mask: np.ndarray) -> dict:
    """The reference's part of SSIM over ``mask``: its bounding box, scale and local moments
    (computed once per reference and mask, reused by every image compared with it)."""
    ref_vals = b[mask]
    top = float(np.percentile(ref_vals, SSIM_RANGE_PERCENTILE)) if ref_vals.size else 0.0
    # Work on the mask's bounding box plus the window radius: identical result, faster
    # (a face fills ~40 % of the frame).
    rows, cols = np.nonzero(mask.any(axis=1))[0], np.nonzero(mask.any(axis=0))[0]
    pad = 6
    sl = (slice(max(rows[0] - pad, 0), rows[-1] + pad + 1),
          slice(max(cols[0] - pad, 0), cols[-1] + pad + 1))
    m = mask[sl]
    out = {"top": top, "sl": sl, "mask": m}
    if top > 0:
        y = np.where(m, b[sl], 0.0).astype(np.float32) / np.float32(top)
        my = _blur(y)
        out.update(y=y, my=my, syy=_blur(y * y) - my * my)
    return out


def _ssim_luminance(a: np.ndarray, b: np.ndarray, mask: np.ndarray, *,
                    ref_stats: dict | None = None) -> float:
    """Mean SSIM over ``mask`` of two (H, W) luminance images, both zeroed outside the mask.

    ``ref_stats`` : :func:`_ssim_reference` of ``b`` and ``mask`` when already computed.
    Computed in float32 (SSIM is reported to 3 decimals; float32 moments of values normalised
    to ~1 are good to ~1e-4).
    """
    st = ref_stats if ref_stats is not None else _ssim_reference(b, mask)
    sl, m, top = st["sl"], st["mask"], st["top"]
    if not top > 0:
        top = float(max(np.abs(a[mask]).max(initial=0.0), 1.0))
        st = {**st, "top": top}
        y = np.where(m, b[sl], 0.0).astype(np.float32) / np.float32(top)
        my = _blur(y)
        st.update(y=y, my=my, syy=_blur(y * y) - my * my)
    y, my, syy = st["y"], st["my"], st["syy"]
    x = np.where(m, a[sl], 0.0).astype(np.float32) / np.float32(top)
    c1, c2 = SSIM_K1 ** 2, SSIM_K2 ** 2  # L = 1 after the normalisation above
    mx = _blur(x)
    sxx = _blur(x * x) - mx * mx
    sxy = _blur(x * y) - mx * my
    s = ((2 * mx * my + c1) * (2 * sxy + c2)) / ((mx * mx + my * my + c1) * (sxx + syy + c2))
    return float(s[m].mean(dtype=np.float64))


def difference(image, reference, *, mask: np.ndarray | None = None,
               cache: dict | None = None, relative: bool = True) -> DiffResult:
    """Signed difference of ``image`` against ``reference`` and error metrics over a mask.

    Parameters
    ----------
    image, reference : RenderedImage or (H, W, 3) array
        Linear RGB radiance.  For RenderedImages, only pixels both masks cover count.
    mask : (H, W) bool array, optional
        Further restricts the pixels that count (intersected with the images' masks).
    cache : dict, optional
        Scratch space shared by calls against the same reference (its luminance and SSIM
        moments are computed once); results are the same with or without it.
    relative : bool
        False leaves ``DiffResult.relative`` None (the metrics are the same; saves an image).

    Returns
    -------
    DiffResult
        ``metrics`` (all over the mask, all channels unless stated):

        - ``rmse``: sqrt(mean (image - reference)^2), radiance units
        - ``rel_rmse``: rmse / sqrt(mean reference^2) -- energy-normalised, needs no floor
          (image = 1.1 x reference gives 0.1)
        - ``bias_rgb``: per channel, mean of the signed relative error (floored, see
          ``REL_FLOOR_FRACTION``) -- positive = brighter than the reference
        - ``flux_ratio_rgb``: per channel, sum image / sum reference - 1 (bias of the totals)
        - ``max_abs``: max |image - reference|
        - ``rel_p95``: 95th percentile of |relative error|
        - ``ssim``: mean SSIM of the luminances (Wang et al. 2004, 11x11 Gaussian window)
        - ``pixels``: number of pixels that count; ``rel_floor_rgb``: the floor used

        No metric is NaN: an empty mask gives zeros (``pixels`` = 0) and SSIM 1.
    """
    img, m_img = _as_arrays(image, "image")
    ref, m_ref = _as_arrays(reference, "reference")
    if img.shape != ref.shape:
        raise DermisError(f"difference: image shape {img.shape} != reference shape {ref.shape}; "
                          "renders must share the camera resolution")
    valid = np.ones(img.shape[:2], bool)
    for m, what in ((m_img, "image mask"), (m_ref, "reference mask"), (mask, "mask")):
        if m is None:
            continue
        m = np.asarray(m, dtype=bool)
        if m.shape != valid.shape:
            raise DermisError(f"difference: {what} shape {m.shape}; expected {valid.shape}")
        valid &= m
    # Non-finite pixels (should not happen) are excluded rather than poisoning every metric.
    # float32 per pixel, float64 sums (the metrics are exact to ~1e-7 relative).
    idx = np.flatnonzero(valid)
    i = img.reshape(-1, 3)[idx]
    r = ref.reshape(-1, 3)[idx]
    if not (np.isfinite(i.sum(dtype=np.float64)) and np.isfinite(r.sum(dtype=np.float64))):
        finite = np.isfinite(i).all(axis=1) & np.isfinite(r).all(axis=1)
        valid.ravel()[idx[~finite]] = False
        idx, i, r = idx[finite], i[finite], r[finite]
    d = i - r
    n = len(idx)
    sum_ref = r.sum(axis=0, dtype=np.float64) if n else np.zeros(3)
    mean_ref = sum_ref / max(n, 1)
    floor = REL_FLOOR_FRACTION * mean_ref
    if not np.all(floor > 0):
        # A black reference channel: fall back to 5 % of the mean of either image over all
        # channels, then to 1 (both black: the relative error is 0 anyway).
        alt = REL_FLOOR_FRACTION * float(np.maximum(r, i).mean(dtype=np.float64)) if n else 0.0
        floor = np.where(floor > 0, floor, alt if alt > 0 else 1.0)
    relv = d / np.maximum(r, floor.astype(np.float32))
    diff = np.zeros((valid.size, 3), np.float32)
    diff[idx] = d
    rel = None
    if relative:
        rel = np.zeros((valid.size, 3), np.float32)
        rel[idx] = relv

    if n:
        rms_ref = math.sqrt(float(np.einsum("ij,ij->", r, r, dtype=np.float64)) / (3 * n))
        rmse = math.sqrt(float(np.einsum("ij,ij->", d, d, dtype=np.float64)) / (3 * n))
        sum_img = i.sum(axis=0, dtype=np.float64)
        flux = np.where(sum_ref > 0, sum_img / np.where(sum_ref > 0, sum_ref, 1.0) - 1.0, 0.0)
        lum = LUMINANCE.astype(np.float32)
        cache = {} if cache is None else cache
        key = (id(ref), hash(valid.tobytes()))
        if key not in cache:   # the reference's luminance and SSIM moments, once per mask
            ref_lum = ref @ lum
            cache.clear()      # one reference at a time: memory stays bounded
            cache[key] = (ref, ref_lum, _ssim_reference(ref_lum, valid))
        _, ref_lum, stats = cache[key]
        metrics = {
            "rmse": rmse,
            "rel_rmse": rmse / rms_ref if rms_ref > 0 else (0.0 if rmse == 0 else float("inf")),
            "bias_rgb": [float(v) for v in relv.sum(axis=0, dtype=np.float64) / n],
            "flux_ratio_rgb": [float(v) for v in flux],
            "max_abs": float(max(d.max(), -d.min())),
            "rel_p95": _percentile(np.abs(relv).ravel(), 95.0),
            "ssim": _ssim_luminance(_CropLum(img, lum, stats["sl"]), ref_lum, valid,
                                    ref_stats=stats),
        }
        if not math.isfinite(metrics["rel_rmse"]):
            # Reference black over the whole mask but the image is not: report the RMSE
            # relative to the image instead of infinity (documented, never NaN).
            metrics["rel_rmse"] = rmse / math.sqrt(
                float(np.einsum("ij,ij->", i, i, dtype=np.float64)) / (3 * n))
    else:
        metrics = {"rmse": 0.0, "rel_rmse": 0.0, "bias_rgb": [0.0] * 3,
                   "flux_ratio_rgb": [0.0] * 3, "max_abs": 0.0, "rel_p95": 0.0, "ssim": 1.0}
    metrics["pixels"] = n
    metrics["rel_floor_rgb"] = [float(v) for v in floor]
    return DiffResult(diff=diff.reshape(img.shape),
                      relative=None if rel is None else rel.reshape(img.shape),
                      mask=valid, metrics=metrics)


class _CropLum:
    """Luminance of an RGB image computed only on the crop ``sl`` SSIM works on (indexing
    with ``sl`` gives it; any other index computes the full luminance first)."""

    def __init__(self, rgb: np.ndarray, lum: np.ndarray, sl):
        self.rgb, self.lum, self.sl = rgb, lum, sl

    def __getitem__(self, key):
        if key is self.sl:
            return self.rgb[self.sl] @ self.lum
        return (self.rgb @ self.lum)[key]


@functools.lru_cache(maxsize=4)
def _diverging_lut(n: int) -> np.ndarray:
    from matplotlib import colormaps

    red = colormaps["RdBu_r"](np.linspace(0.5, 1.0, n // 2))[:, :3]  # grey -> red
    blue = red[::-1, ::-1]  # reversed order, R and B swapped: blue -> grey
    return np.concatenate([blue, red])


def diverging_lut(n: int = 256) -> np.ndarray:
    """(n, 3) float RGB diverging colour table, blue (darker) -> grey -> red (brighter).

    The red half is matplotlib's ``RdBu_r`` upper half; the blue half is its mirror with the
    red and blue channels swapped, so equal and opposite differences get exactly mirrored
    colours (``lut[n-1-k] == lut[k][::-1]``) -- ColorBrewer's RdBu is close to, but not
    exactly, symmetric.
    """
    if n < 2 or n % 2:
        raise DermisError(f"diverging_lut: n = {n}; must be an even number >= 2")
    return _diverging_lut(n).copy()


def diverging_colormap():
    """The :func:`diverging_lut` as a matplotlib colormap (for colour bars)."""
    from matplotlib.colors import ListedColormap

    return ListedColormap(diverging_lut(), name="dermis_diff")


def _luminance_diff(diff) -> tuple[np.ndarray, np.ndarray]:
    """(luminance difference (H, W), mask) from a DiffResult or an (H, W, 3) array."""
    d = np.asarray(getattr(diff, "diff", diff), dtype=np.float32)
    mask = getattr(diff, "mask", None)
    mask = np.ones(d.shape[:2], bool) if mask is None else np.asarray(mask, bool)
    return d @ LUMINANCE.astype(np.float32), mask


def default_scale(diffs) -> float:
    """Symmetric scale shared by several differences: the ``DIFF_SCALE_PERCENTILE`` of
    |luminance difference| over all their masks (1.0 if they are all zero)."""
    vals = []
    for dr in diffs:
        lum, mask = _luminance_diff(dr)
        vals.append(np.abs(lum[mask]))
    vals = np.concatenate(vals) if vals else np.zeros(0)
    vals = vals[np.isfinite(vals)]
    s = float(np.percentile(vals, DIFF_SCALE_PERCENTILE)) if vals.size else 0.0
    return s if s > 0 else 1.0


def difference_indices(diff, *, scale: float | None = None) -> np.ndarray:
    """(H, W) uint8 palette indices of :func:`difference_image`: 0 .. DIFF_LEVELS - 1 from
    full blue to full red, ``DIFF_LEVELS`` (black) outside the mask (:func:`difference_palette`)."""
    lum, mask = _luminance_diff(diff)
    if scale is None:
        scale = default_scale([diff])
    if not (math.isfinite(scale) and scale > 0):
        raise DermisError(f"difference_image: scale = {scale}; must be finite and > 0")
    n = DIFF_LEVELS
    t = np.nan_to_num(lum[mask]) * np.float32((n / 2) / scale)
    # Symmetric binning: |t| picks a bin counted outward from the centre, the sign picks
    # the half, so +t and -t land on mirrored entries k and n-1-k.
    k = np.minimum(np.abs(t), np.float32(n // 2 - 1)).astype(np.int32)
    out = np.full(mask.shape, n, np.uint8)
    out[mask] = np.where(t >= 0, n // 2 + k, n // 2 - 1 - k)
    return out


@functools.lru_cache(maxsize=1)
def _palette() -> np.ndarray:
    pal = np.zeros((DIFF_LEVELS + 1, 3), np.uint8)
    pal[:DIFF_LEVELS] = np.round(_diverging_lut(DIFF_LEVELS) * 255.0).astype(np.uint8)
    return pal


def difference_palette() -> np.ndarray:
    """(DIFF_LEVELS + 1, 3) uint8: the diverging colours, then black (outside the mask)."""
    return _palette().copy()


def difference_image(diff, *, scale: float | None = None) -> np.ndarray:
    """Colour-coded luminance difference: red = brighter than the reference, blue = darker.

    Parameters
    ----------
    diff : DiffResult (or (H, W, 3) signed difference array, all pixels counting)
    scale : float, optional
        Luminance difference mapped to full red / full blue (symmetric, clipped beyond).
        Share one scale across a comparison; default :func:`default_scale` of this image.

    Returns
    -------
    (H, W, 3) uint8 RGB; black outside the mask, neutral grey where the difference is 0.
    """
    return _palette()[difference_indices(diff, scale=scale)]


def image_labels(image) -> tuple[str, str, str]:
    """(model, light, geometry) of a RenderedImage from its ``info``."""
    info = getattr(image, "info", {}) or {}
    return str(info.get("model", "?")), str(info.get("light", "?")), str(info.get("geometry", "?"))


def _seconds(image) -> float | None:
    t = (getattr(image, "timings", {}) or {}).get("total")
    return float(t) if t is not None else None


# Geometries compared with the ~1M-triangle mesh (the thesis's geometry question).
GEOMETRY_REFERENCE = "high"
GEOMETRY_COMPARED = ("low_bump", "low_bump_blur")


def _grid_image(tiles: dict, rows: list, cols: list, scales: dict, *, title: str,
                captions: dict) -> np.ndarray:
    """A labelled grid of difference images (rows x cols) with one colour bar per column
    (:mod:`dermis.reports.sheets`)."""
    from dermis.reports.sheets import caption
    from dermis.reports.sheets import TILE_PX, colorbar, grid, hstack

    lut = diverging_lut()
    bars = [colorbar(lut, -scales.get(c, 1.0), scales.get(c, 1.0), f"{c}: luminance difference",
                     width=TILE_PX - 56) for c in cols]
    return grid(tiles, rows, cols, captions={k: f"{caption(*k)}\n{v}" for k, v in captions.items()},
                title=title, footer=hstack(bars, gap=56 + 8))


def _pairs(pairs_in: dict, cache_key) -> dict:
    """DiffResults of (image, reference) pairs, computed on two threads (numpy and scipy
    release the GIL); pairs sharing a reference share its luminance and SSIM moments."""
    from concurrent.futures import ThreadPoolExecutor

    groups: dict = {}
    for k, (im, ref) in pairs_in.items():
        groups.setdefault(cache_key(k), []).append((k, im, ref))

    def run(group):
        cache: dict = {}
        out = []
        for k, im, ref in group:
            res = difference(im, ref, cache=cache, relative=False)   # not drawn
            out.append((k, res))
        return out

    with ThreadPoolExecutor(2) as pool:
        return dict(kv for part in pool.map(run, groups.values()) for kv in part)


def _record(res: DiffResult, image, ref_image, fname: str, against: dict) -> dict:
    model, light, geom = image_labels(image)
    rec = {"model": model, "light": light, "geometry": geom, **against,
           "seconds": _seconds(image), "reference_seconds": _seconds(ref_image), "file": fname}
    rec.update(res.metrics)
    return rec


# The two comparison sets: (metrics section, scale kind, grid file prefix, grid title)
SETS = (("model_vs_reference", "model", "diffgrid",
         lambda ref, geom: f"difference vs {ref}, geometry {geom} (red = brighter, blue = darker)"),
        ("geometry_vs_high", "geometry", "geomgrid",
         lambda ref, geom: f"{geom} vs {GEOMETRY_REFERENCE} mesh, same model and light (red = "
                           "brighter, blue = darker)"))


def write_grids(metrics: dict, tiles: dict, out_dir) -> list[Path]:
    """The labelled grids, one per comparison set and geometry (rows models, columns lights):
    ``diffgrid-<geometry>.png`` and ``geomgrid-<geometry>.png``, from the difference images
    ``tiles`` ({"model": {(m, l, g): image}, "geometry": {...}}, full size or thumbnails)."""
    from concurrent.futures import ThreadPoolExecutor

    from dermis.reports.sheets import ordered_models
    from dermis.reports.sheets import save_png

    out_dir = Path(out_dir)
    jobs = []
    for section, kind, prefix, title in SETS:
        recs = metrics.get(section, {})
        got = tiles.get(kind, {})
        for geom in sorted({r["geometry"] for r in recs.values()}):
            sel = {(r["model"], r["light"]): got[(r["model"], r["light"], geom)]
                   for r in recs.values() if r["geometry"] == geom
                   and (r["model"], r["light"], geom) in got}
            caps = {(m, l): _caption(recs[f"{m}-{l}-{geom}"]) for (m, l) in sel}
            jobs.append((out_dir / f"{prefix}-{geom}.png",
                         _grid_image(sel, ordered_models(m for m, _ in sel),
                                     sorted({l for _, l in sel}),
                                     metrics["scales"][kind],
                                     title=title(metrics.get("reference_model", "bssrdf"), geom),
                                     captions=caps)))
    with ThreadPoolExecutor(2) as pool:
        return list(pool.map(lambda job: save_png(*job), jobs))


def merge_metrics(parts: list) -> dict:
    """One metrics dict from several :func:`write_differences` results (e.g. one per
    lighting condition): their records and per-light scales side by side."""
    out = {"reference_model": "bssrdf", "rel_floor_fraction": REL_FLOOR_FRACTION,
           "scale_percentile": DIFF_SCALE_PERCENTILE, "scales": {"model": {}, "geometry": {}},
           "model_vs_reference": {}, "geometry_vs_high": {}}
    for part in parts:
        for key in ("reference_model", "rel_floor_fraction", "scale_percentile"):
            out[key] = part.get(key, out[key])
        for kind in ("model", "geometry"):
            out["scales"][kind].update(part.get("scales", {}).get(kind, {}))
        for section in ("model_vs_reference", "geometry_vs_high"):
            out[section].update(part.get(section, {}))
    return out


def _write_set(pairs: dict, refs: dict, by_key: dict, metrics: dict, scale_kind: str,
               section: str, prefix: str, out_dir: Path, extra: dict,
               tiles_out: dict | None = None) -> list[Path]:
    """One comparison set: a shared scale per light, a PNG and a metrics record per pair."""
    from concurrent.futures import ThreadPoolExecutor

    from dermis.reports.sheets import save_png

    for light in sorted({l for _, l, _ in pairs}):
        metrics["scales"][scale_kind][light] = default_scale(
            [d for (m, l, g), d in pairs.items() if l == light])
    tiles, jobs, pal = {}, [], _palette()
    for (m, l, g), res in sorted(pairs.items()):
        fname = f"{prefix}-{m}-{l}-{g}.png"
        idx = difference_indices(res, scale=metrics["scales"][scale_kind][l])
        tiles[(m, l, g)] = pal[idx]
        jobs.append((out_dir / fname, idx, pal))     # palette PNG: 1 byte a pixel
        metrics[section][f"{m}-{l}-{g}"] = _record(res, by_key[(m, l, g)], refs[(m, l, g)],
                                                    fname, extra)
    if tiles_out is not None:
        tiles_out.update(tiles)
    with ThreadPoolExecutor(2) as pool:
        return list(pool.map(lambda job: save_png(job[0], job[1], palette=job[2]), jobs))


def write_differences(images: dict, out_dir, *, reference_model: str = "bssrdf",
                      tiles_out: dict | None = None, grids: bool = True
                      ) -> tuple[list[Path], dict]:
    """Difference images and metrics of every model against the reference, and of the low
    geometries against the high mesh.

    Parameters
    ----------
    images : dict node id -> :class:`pipeline.artifacts.RenderedImage`
        ``info`` must carry "model", "light" and "geometry".
    out_dir : directory to write into (created)
    reference_model : model every other model is compared with (default the BSSRDF)
    tiles_out : dict, optional
        Filled with the colour-coded difference images, ``{"model": {(model, light, geom):
        uint8 image}, "geometry": {...}}``, so the PDF reuses them instead of recomputing
    grids : bool
        Also draw the labelled grids (:func:`write_grids`); False when one call sees one
        lighting condition and the grids are drawn from all of them later

    Returns
    -------
    files : list of written paths -- ``diff-<model>-<light>-<geometry>.png``,
        ``diffgrid-<geometry>.png`` (rows models, columns lights),
        ``geomdiff-<model>-<light>-<geometry>.png``, ``geomgrid-<geometry>.png`` and
        ``metrics.json``
    metrics : the content of ``metrics.json``::

        {"reference_model", "rel_floor_fraction", "scale_percentile",
         "scales": {"model": {light: s}, "geometry": {light: s}},
         "model_vs_reference": {"<model>-<light>-<geometry>": record},
         "geometry_vs_high": {"<model>-<light>-<geometry>": record}}

        record = the :func:`difference` metrics + model, light, geometry, seconds (this
        image's ``timings["total"]``), reference_seconds, file, and what it is compared with.

    Raises
    ------
    DermisError
        If no image has ``reference_model``.
    """
    out_dir = Path(out_dir)
    by_key = {}
    for nid in sorted(images):
        by_key[image_labels(images[nid])] = images[nid]
    models = sorted({m for m, _, _ in by_key})
    if reference_model not in models:
        raise DermisError(
            f"difference images: no render of the reference model {reference_model!r} among "
            f"{len(by_key)} images (models present: {', '.join(models) or 'none'}); add "
            f"{reference_model!r} to [render] models, or pick another reference_model")
    out_dir.mkdir(parents=True, exist_ok=True)
    files: list[Path] = []
    metrics: dict = {"reference_model": reference_model, "rel_floor_fraction": REL_FLOOR_FRACTION,
                     "scale_percentile": DIFF_SCALE_PERCENTILE,
                     "scales": {"model": {}, "geometry": {}},
                     "model_vs_reference": {}, "geometry_vs_high": {}}

    # --- models vs the reference, per (light, geometry) where the reference exists --------
    todo = {}  # (model, light, geom) -> (image, reference)
    for (m, l, g), im in by_key.items():
        ref = by_key.get((reference_model, l, g))
        if m == reference_model or ref is None:
            continue
        todo[(m, l, g)] = (im, ref)
    tiles = {"model": {}, "geometry": {}} if tiles_out is None else tiles_out
    tiles.setdefault("model", {})
    tiles.setdefault("geometry", {})
    pairs = _pairs(todo, lambda k: (k[1], k[2]))        # DiffResults, grouped by reference
    files += _write_set(pairs, {k: by_key[(reference_model, k[1], k[2])] for k in pairs},
                        by_key, metrics, "model", "model_vs_reference", "diff", out_dir,
                        {"reference": reference_model}, tiles["model"])
    del pairs

    # --- geometries vs the high mesh, same model and light --------------------------------
    todo = {}
    for (m, l, g), im in by_key.items():
        hi = by_key.get((m, l, GEOMETRY_REFERENCE))
        if g in GEOMETRY_COMPARED and hi is not None:
            todo[(m, l, g)] = (im, hi)
    gpairs = _pairs(todo, lambda k: (k[0], k[1]))
    files += _write_set(gpairs, {k: by_key[(k[0], k[1], GEOMETRY_REFERENCE)] for k in gpairs},
                        by_key, metrics, "geometry", "geometry_vs_high", "geomdiff", out_dir,
                        {"reference_geometry": GEOMETRY_REFERENCE}, tiles["geometry"])
    del gpairs
    if grids:
        files += write_grids(metrics, tiles, out_dir)

    (out_dir / "metrics.json").write_text(json.dumps(metrics, indent=1, sort_keys=True))
    files.append(out_dir / "metrics.json")
    return files, metrics


def _caption(rec: dict) -> str:
    """One-line caption: relative RMSE and SSIM."""
    return f"rel RMSE {rec['rel_rmse']:.3f}  SSIM {rec['ssim']:.3f}"
