"""Distance to ground truth: every model against the Mitsuba 3 path-traced reference.

Both the reference (:mod:`dermis.stages.reference`) and a model image are Monte Carlo
estimates, so every distance here is reported with the noise of both at the scale it is
measured (docs/ground-truth.md; the error-bar algebra is :mod:`dermis.reports.truth_noise`;
a model image without a ``noise`` field counts as noise-free and is said to be so):

* **Blocks.**  A model image (camera size) is averaged over the block of camera pixels
  each reference pixel covers (the reference's box filter), then both are averaged further
  over f x f blocks, f in :data:`dermis.groundtruth.noise.NOISE_FACTORS`.  Only blocks whose
  every camera pixel hits the mesh count.  At each f: the relative RMSE e (the report's
  ``rel_rmse`` definition), the reference's noise sigma_ref and the model's own sigma_model
  at f, sigma = sqrt(sigma_ref^2 + sigma_model^2) (what noise alone gives), and
  e_true = sqrt(e^2 - sigma^2) (errors and noises independent, so their squares add).  A
  difference counts as **resolved** when e > ``RESOLVE_K`` x sigma.
* **Regions** (:mod:`dermis.geometry.regions`): the relative difference of the model's mean
  over the region's pixels from the reference's, per channel and in luminance, with both
  means' standard errors and the albedo tint's calibration error (the flat-slab Rd's
  standard error) in quadrature; resolved beyond ``RESOLVE_K`` standard errors.
* **FLIP** (HDR-FLIP, the ``flip-evaluator`` package; Andersson et al. 2021) and **SSIM**
  (:func:`dermis.reports.diff.difference`) on the reference-grid images.  Both are
  computed against a noisy reference and are floored by its noise: they rank models, they
  do not measure them below that floor.
* **Cost.**  The reference's noise falls as c / sqrt(spp) (``info["noise_fit"]``, measured
  over its uniform passes), so the path tracer reaches a relative error
  e at scale f after (c_f / e)^2 samples per pixel, i.e. after (c_f / e)^2 x
  seconds-per-spp.  The speed-up of a model is that time over the model's own time, at
  e = its e_true (an unresolved e_true is replaced by sigma: the speed-up is then a lower
  bound, written with ">=").
* **Ranking** per light at f = ``RANK_FACTOR`` by s = e^2 - sigma_model^2 (the reference's
  share of E[e^2] is the same for every model); every pair is compared on its common blocks
  (:func:`dermis.reports.truth_noise.pair_test`) and counts as resolved beyond
  ``RESOLVE_K`` standard errors of s_a - s_b; neighbours not resolved are marked tied, and
  each model gets the range of ranks the comparisons allow.

:func:`ground_truth_metrics` computes all of it (pure), :func:`metrics_ground_truth` the
``ground_truth`` object of ``metrics.json``, :func:`write_ground_truth` writes error maps
and ``ground_truth.json``, :func:`ground_truth_pages` adds the detail pages to an open
matplotlib ``PdfPages`` (the opening pages: :mod:`dermis.reports.truth_pages`).
"""
from __future__ import annotations

import json
import math
import textwrap
from pathlib import Path

import numpy as np

from dermis.models import catalog
from dermis.models.catalog import THESIS_MODELS
from dermis.pipeline.registry import MODEL_NAMES
from dermis.pipeline.config import CameraConfig
from dermis.rendering.color import LUMINANCE
from dermis.geometry.regions import REGION_LABELS, REGIONS, block_mean, face_regions
from dermis.groundtruth.noise import NOISE_FACTORS
from dermis.reports.causes import causes_pages, causes_table
from dermis.reports.truth_noise import (RESOLVE_K, compare, mean_se, model_noise_on, pair_test,
                                        rank_ranges, ref_scale_noise, ref_var_map,
                                        region_difference, scale_noise)
from dermis.reports.truth_verdicts import thesis_checks

__all__ = ["RegionLabeller", "region_labels_for", "ground_truth_metrics", "metrics_ground_truth",
           "write_ground_truth", "ground_truth_pages", "ground_truth_section", "thesis_checks",
           "RESOLVE_K", "GEOMETRY"]

GEOMETRY = "high"        # the references are rendered on the high mesh
# Models are ranked on 4x4 blocks of reference pixels: at single pixels a CPU reference's
# noise (~50 % at 128 spp) buries the differences between models (measured, docs/ground-truth.md)
RANK_FACTOR = 4
MODEL_ORDER = MODEL_NAMES      # the tables; the ranking is of the thesis's four (THESIS_MODELS)


class RegionLabeller:
    """The face region of every pixel any camera sees of one mesh: the mesh's ray scene and
    face regions are built once (on the 1.1M-triangle scan they took most of a cast's
    seconds) and each camera and size is cast once, for every page that asks."""

    def __init__(self, mesh):
        self.mesh = mesh
        self._scene = None
        self._regions = None
        self._cast: dict = {}

    def __call__(self, camera, *, width: int, height: int, with_faces: bool = False):
        from dataclasses import replace
        cam = replace(camera, width=int(width), height=int(height))
        key = repr(cam)
        if key not in self._cast:
            from dermis.lighting.visibility import Visibility
            from dermis.rendering.camera import camera_rays
            if self._scene is None:
                self._scene = Visibility(self.mesh.vertices, self.mesh.faces)
                self._regions = face_regions(self.mesh.vertices, self.mesh.faces)
            o, d = camera_rays(cam)
            hits = self._scene.intersect(o, d)
            tri = np.where(hits.hit, hits.tri, -1).astype(np.int64)
            lab = np.zeros(len(o), np.int8)
            lab[hits.hit] = self._regions[tri[hits.hit]]
            self._cast[key] = (lab.reshape(cam.height, cam.width),
                               tri.reshape(cam.height, cam.width))
        lab, tri = self._cast[key]
        return (lab, tri) if with_faces else lab


def region_labels_for(mesh, camera, *, width: int, height: int, with_faces: bool = False):
    """(H, W) int8 region labels of the pixel-centre hits of ``camera`` at width x height,
    through dermis's own camera rays and Embree (and the (H, W) face index, -1 = miss);
    ``mesh`` a Mesh or a :class:`RegionLabeller` of one (its casts are kept)."""
    labeller = mesh if isinstance(mesh, RegionLabeller) else RegionLabeller(mesh)
    return labeller(camera, width=width, height=height, with_faces=with_faces)


def _labels(image) -> tuple[str, str, str]:
    info = getattr(image, "info", {}) or {}
    return str(info.get("model", "?")), str(info.get("light", "?")), str(info.get("geometry", "?"))


def _rel_rmse(a: np.ndarray, b: np.ndarray) -> float:
    rms = math.sqrt(float((b * b).mean())) if b.size else 0.0
    return math.sqrt(float(((a - b) ** 2).mean())) / rms if rms > 0 else 0.0


def _flip(ref: np.ndarray, test: np.ndarray, mask: np.ndarray) -> tuple[float, np.ndarray]:
    """Mean HDR-FLIP over ``mask`` and the error map (NaN where flip-evaluator is missing)."""
    try:
        import flip_evaluator as flip
    except ImportError:
        return float("nan"), np.zeros(mask.shape, np.float32)
    r = np.ascontiguousarray(np.where(mask[..., None], ref, 0.0), np.float32)
    t = np.ascontiguousarray(np.where(mask[..., None], test, 0.0), np.float32)
    # HDR-FLIP's exposure range from the compared (head) pixels alone: over the whole frame
    # the black background's median set the stop exposure to 24 stops, 23 exposures, ~4 s
    # an image at 80^2 (against 2-6 from the head's pixels)
    skin = np.ascontiguousarray(r[mask][None], np.float32)
    _, _, exposure = flip.evaluate(skin, skin, "HDR", applyMagma=False, computeMeanError=False)
    err, _, _ = flip.evaluate(r, t, "HDR", applyMagma=False, computeMeanError=False,
                              parameters={k: exposure[k] for k in ("startExposure",
                                                                   "stopExposure",
                                                                   "numExposures")})
    err = np.asarray(err, np.float32).reshape(mask.shape[0], mask.shape[1], -1)[..., 0]
    return float(err[mask].mean()) if mask.any() else 0.0, err


def _downsample_to(image: np.ndarray, mask: np.ndarray, shape) -> tuple[np.ndarray, np.ndarray]:
    h, w = shape
    f = image.shape[0] // h
    if f * h != image.shape[0] or f * w != image.shape[1]:
        raise ValueError(f"ground truth: image {image.shape[:2]} is not a multiple of the "
                         f"reference's {shape}")
    return block_mean(image, mask, f)


def _block_error(D, M, valid, floor) -> np.ndarray:
    """Signed relative luminance error on RANK_FACTOR blocks (where the reference's noise is
    ~3x below the single-pixel one), shown at reference-pixel size (NaN outside)."""
    f = RANK_FACTOR
    Db, mb = block_mean(D, valid, f)
    Mb, _ = block_mean(M, valid, f)
    lr = Mb @ LUMINANCE
    e = np.where(mb, (Db @ LUMINANCE - lr) / np.maximum(lr, floor), np.nan)
    out = np.full(valid.shape, np.nan)
    big = np.kron(e, np.ones((f, f)))
    out[:big.shape[0], :big.shape[1]] = big
    return np.where(valid, out, np.nan)


def _contrast(lum: np.ndarray, var: np.ndarray | None = None) -> tuple[float, float]:
    """Relative standard deviation C = sqrt(V) / m of luminance over blocks, each block's
    noise variance ``var`` removed from V, and C's standard error from that noise (first
    order in the noise n_i of each block, Gaussian): C (dV / 2V - dm / m) with
    dV = 2/N sum (x_i - m) n_i + 1/N sum (n_i^2 - v_i) and dm = 1/N sum n_i, so
    var C = C^2 / N^2 (sum v_i ((x_i - m) / V - 1 / m)^2 + sum v_i^2 / (2 V^2))."""
    n = lum.size
    m = float(lum.mean()) if n else 0.0
    if n == 0 or m <= 0:
        return 0.0, 0.0
    v = np.zeros(n) if var is None else np.asarray(var, np.float64)
    V = float(lum.var()) - float(v.mean())
    if V > 0:
        c = math.sqrt(V) / m
        w = (lum - m) / V - 1.0 / m
        return c, c / n * math.sqrt(float((v * w * w).sum() + (v * v).sum() / (2 * V * V)))
    # no variance left above the noise: the bound from the noise of V alone
    sd_v = math.sqrt(float(4 * ((lum - m) ** 2 * v).sum() + 2 * (v * v).sum())) / n
    return 0.0, math.sqrt(sd_v) / m


def _ref_block_var(ref_var, ref_hd, valid, f: int, Mb, mb, sigma: float) -> np.ndarray:
    """Per block (f x f reference pixels) and channel, the variance of the reference's block
    mean: (block-mean half-difference)^2 when the reference has one; else its per-pixel
    variances / f^2, scaled so that their sum matches the block noise the reference measured
    at f (``sigma``: its pixels are not independent where its noise is heavy-tailed)."""
    if ref_hd is not None:
        return block_mean(ref_hd, valid, f)[0] ** 2
    vb = block_mean(ref_var, valid, f)[0] / (f * f)
    have, want = float(vb[mb].sum()), sigma * sigma * float((Mb[mb] ** 2).sum())
    return vb * (want / have) if have > 0 and want > 0 else vb


def reference_camera(ref, camera):
    """The camera a reference was rendered through (its own, else ``camera``)."""
    own = ref.info.get("camera")
    return CameraConfig(**{k: tuple(v) if isinstance(v, list) else v for k, v in own.items()}
                        ) if own else camera


def reference_labels(ref, mesh, camera, cache: dict):
    """The region labels of reference ``ref``'s pixels (``cache``: by size and camera; a
    cache given as {(height, width): labels} serves references without a camera of their
    own)."""
    h, w = ref.linear.shape[:2]
    cam = reference_camera(ref, camera)
    key = (h, w) if cam is camera else (h, w, repr(cam))
    if key not in cache:
        cache[key] = region_labels_for(mesh, cam, width=w, height=h)
    return cache[key]


def ground_truth_metrics(images: dict, references: dict, *, mesh, camera,
                         extra_seconds: dict | None = None,
                         region_labels: dict | None = None) -> dict:
    """Distances of every model image to the reference of its light (module docstring).

    Parameters
    ----------
    images : dict id -> RenderedImage
        Model renders (``info`` model / light / geometry); only ``geometry = "high"``
        images of a light that has a reference are compared.  Their ``noise`` (when set)
        enters every error bar (:mod:`dermis.reports.truth_noise`).
    references : dict light label -> RenderedImage
        The reference stage's artifacts.
    mesh : Mesh
        The high mesh (region labels of the models' pixels).
    camera : CameraConfig
        The scene camera (the models' camera; the reference's at its own size), where a
        reference does not name its own (``info["camera"]``: a close-up view's).
    extra_seconds : dict (light, mesh node) -> seconds, optional
        Time to add to a BSSRDF image's own (its irradiance pass), as the report does.
    region_labels : dict (height, width) -> (H, W) int labels, optional
        The region labels at a reference's size, instead of casting ``camera``'s rays at
        ``mesh`` (:func:`region_labels_for`).

    Returns
    -------
    dict (JSON-able): ``references`` (per light: size, spp, seconds, noise, noise_fit, slab,
    passes, stopped), ``models`` (per "model-light": errors per factor with both noises,
    regions, flip, ssim, seconds, speed-up), ``ranking`` and ``comparisons`` (per light),
    ``thesis`` (:func:`dermis.reports.truth_verdicts.thesis_checks`).
    """
    from dermis.reports.diff import difference
    extra_seconds = extra_seconds or {}
    out = {"resolve_k": RESOLVE_K, "rank_factor": RANK_FACTOR, "references": {}, "models": {},
           "ranking": {}, "comparisons": {}}
    labels_cache: dict = dict(region_labels or {})
    for light, ref in sorted(references.items()):
        info = ref.info
        h, w = ref.linear.shape[:2]
        labels = reference_labels(ref, mesh, camera, labels_cache)
        M = np.asarray(ref.linear, np.float64)
        ref_var, ref_hd = ref_var_map(ref, labels)
        # highlights are picked on the models' mean image: picking them on the noisy
        # reference would select its positive noise (regression to the mean)
        mine = [_downsample_to(np.asarray(im.linear, np.float64), np.asarray(im.mask, bool),
                               (h, w))[0] for im in images.values()
                if _labels(im)[1] == light and _labels(im)[2] == GEOMETRY
                and _labels(im)[0] in THESIS_MODELS]
        highlight_basis = np.mean(mine, axis=0) if mine else M
        blocks_for_rank: dict = {}
        rmask = np.asarray(ref.mask, bool)
        slab = info.get("slab", {})
        calib = np.asarray(slab.get("Rd_stderr", [0, 0, 0]), np.float64) / np.maximum(
            np.asarray(slab.get("Rd", [1, 1, 1]), np.float64), 1e-30)
        rel_se = info.get("region_rel_se") or {}
        t_spp = float(ref.timings.get("seconds_per_spp", 0.0) or 0.0)
        out["references"][light] = {
            "width": w, "height": h, "spp": info.get("spp"), "variant": info.get("variant"),
            "seconds": float(ref.timings.get("render", 0.0) or 0.0),
            "seconds_per_spp": t_spp, "noise": info.get("noise", {}),
            "noise_fit": info.get("noise_fit", {}), "slab": slab,
            "calibration_rel_rgb": [float(c) for c in calib],
            "regions": info.get("regions", {}), "region_rel_se": rel_se,
            "passes": info.get("passes"), "stopped": info.get("stopped"),
            "target_rel_se": info.get("target_rel_se"), "budget_s": info.get("budget_s"),
            "half_difference": ref_hd is not None, "env_clamp": info.get("env_clamp", 0.0)}
        for nid, im in sorted(images.items()):
            model, l, geom = _labels(im)
            if l != light or geom != GEOMETRY or model == "reference":
                continue
            D, full = _downsample_to(np.asarray(im.linear, np.float64),
                                     np.asarray(im.mask, bool), (h, w))
            fcam = im.linear.shape[0] // h
            N = model_noise_on(im, (h, w), fcam)
            valid = full & rmask
            rec = {"model": model, "light": light, "factor_to_reference": fcam,
                   "pixels": int(valid.sum()), "own_noise": N is not None, "scales": {},
                   "regions": {}}
            for f in NOISE_FACTORS:
                Db, mb = block_mean(D, valid, f)
                Mb, _ = block_mean(M, valid, f)
                if not mb.any():
                    continue
                e = _rel_rmse(Db[mb], Mb[mb])
                s_ref = ref_scale_noise(ref, ref_hd, Mb, mb, f, valid)
                s_mod = scale_noise(N, Mb, mb, f, valid)
                sigma = math.hypot(s_ref, s_mod or 0.0)
                true = math.sqrt(max(e * e - sigma * sigma, 0.0))
                c = float(info.get("noise_fit", {}).get(str(f), 0.0))
                resolved = e > RESOLVE_K * sigma
                e_eff = true if resolved else max(sigma, true)
                spp_eq = (c / e_eff) ** 2 if e_eff > 0 and c > 0 else float("nan")
                rec["scales"][str(f)] = {"rel_rmse": e, "ref_noise": s_ref, "model_noise": s_mod,
                                         "noise": sigma, "rel_rmse_true": true,
                                         "resolved": bool(resolved), "blocks": int(mb.sum()),
                                         "pt_seconds_same_error": spp_eq * t_spp,
                                         "pt_spp_same_error": spp_eq}
                if f == RANK_FACTOR:
                    vD = (block_mean(N, valid, f)[0] ** 2 if N is not None
                          else np.zeros_like(Db))
                    blocks_for_rank[model] = (Db, mb, vD)
            # regions: same pixel set for model and reference
            for name in REGIONS:
                sel = valid & (labels == REGION_LABELS[name])
                rr = info.get("regions", {}).get(name, {})
                if not sel.any() or not rr:
                    continue
                rec["regions"][name] = region_difference(
                    D, M, sel, model_hd=N, ref_var=ref_var, ref_hd=ref_hd,
                    ref_region=dict(rr, rel_se=rel_se.get(name)), calib=calib)
            dr = difference(np.where(valid[..., None], D, 0.0), np.where(valid[..., None], M, 0.0),
                            mask=valid)
            rec["ssim"] = dr.metrics["ssim"]
            rec["bias_rgb"] = dr.metrics["flux_ratio_rgb"]
            rec["flip"], _ = _flip(M, D, valid)
            if valid.any():
                _thesis_numbers(rec, D, M, valid, highlight_basis, N, ref_var, ref_hd, info)
            sec = float((getattr(im, "timings", {}) or {}).get("total", 0.0) or 0.0)
            if catalog.is_bssrdf(model):   # every BSSRDF: with its irradiance pass
                sec += float(extra_seconds.get((light, "mesh_high"), 0.0))
            rec["seconds"] = sec
            for f in ("1", "4", "8"):
                s = rec["scales"].get(f)
                if s and sec > 0:
                    s["speedup"] = s["pt_seconds_same_error"] / sec
                    s["speedup_is_lower_bound"] = not s["resolved"]
            out["models"][f"{model}-{light}"] = rec
        ranking, comparisons = _rank(out["models"], blocks_for_rank, light, M, rmask, ref_var,
                                     ref_hd, info)
        out["ranking"][light] = ranking
        out["comparisons"][light] = comparisons
    out["thesis"] = thesis_checks(out)
    return out


def _thesis_numbers(rec, D, M, valid, basis, N, ref_var, ref_hd, info) -> None:
    """The thesis's diagnostics with their standard errors: highlight excess (shininess) and
    luminance contrast on 4x4 blocks (softness)."""
    lum_m, lum_r = D[valid] @ LUMINANCE, M[valid] @ LUMINANCE
    lum_s = basis[valid] @ LUMINANCE
    top = np.zeros_like(valid)
    top[valid] = lum_s >= np.percentile(lum_s, 95.0)
    means = [(float(lum_m[top[valid]].mean()), mean_se(top, hd=N)[1] if N is not None else 0.0),
             (float(lum_r[top[valid]].mean()), mean_se(top, var=ref_var, hd=ref_hd)[1]),
             (float(lum_m.mean()), mean_se(valid, hd=N)[1] if N is not None else 0.0),
             (float(lum_r.mean()), mean_se(valid, var=ref_var, hd=ref_hd)[1])]
    (dt, _), (rt, _), (da, _), (ra, _) = means
    if min(dt, rt, da, ra) <= 0:
        return
    h = dt / rt / (da / ra)
    rec["highlight_excess"] = float(h - 1)
    rec["highlight_excess_stderr"] = float(h * math.sqrt(sum((s / m) ** 2 for m, s in means)))
    f = 4
    D4, m4 = block_mean(D, valid, f)
    M4, _ = block_mean(M, valid, f)
    if not m4.any():
        return
    vm = (block_mean(N, valid, f)[0] @ LUMINANCE) ** 2 if N is not None else None
    if ref_hd is not None:   # the luminance of the half-difference, not per channel
        vr = (block_mean(ref_hd, valid, f)[0] @ LUMINANCE) ** 2
    else:
        sig = float(info.get("noise", {}).get(str(f), {}).get("rel", 0.0))
        vr = _ref_block_var(ref_var, None, valid, f, M4, m4, sig) @ (LUMINANCE * LUMINANCE)
    rec["contrast"], rec["contrast_stderr"] = _contrast(D4[m4] @ LUMINANCE,
                                                        None if vm is None else vm[m4])
    rec["ref_contrast"], rec["ref_contrast_stderr"] = _contrast(M4[m4] @ LUMINANCE, vr[m4])


def _rank(models: dict, blocks: dict, light: str, M, rmask, ref_var, ref_hd, info):
    """The light's ranking of the thesis's models on RANK_FACTOR blocks and every pair's
    comparison (:func:`dermis.reports.truth_noise.pair_test`)."""
    fk = str(RANK_FACTOR)
    # the thesis's four are ranked, and Cycles' models (catalog.ranked); bssrdf_mc (the same
    # BSSRDF, another profile) has its rows in the tables but would tie with bssrdf
    recs = [r for r in models.values() if r["light"] == light and fk in r["scales"]
            and catalog.ranked(r["model"]) and r["model"] in blocks]

    def score(r):
        s = r["scales"][fk]
        return s["rel_rmse"] ** 2 - (s["model_noise"] or 0.0) ** 2
    recs.sort(key=score)
    sigma = float(info.get("noise", {}).get(fk, {}).get("rel", 0.0))
    Mb, mref = block_mean(M, rmask, RANK_FACTOR)
    vM = _ref_block_var(ref_var, ref_hd, rmask, RANK_FACTOR, Mb, mref, sigma)
    pairs, comparisons = {}, {}
    for i, ra in enumerate(recs):
        for rb in recs[i + 1:]:
            a, b = ra["model"], rb["model"]
            (Da, ma, va), (Db, mb, vb) = blocks[a], blocks[b]
            m2 = ma & mb
            d, se, n = pair_test(Da[m2], va[m2], Db[m2], vb[m2], Mb[m2], vM[m2])
            pairs[(a, b)], pairs[(b, a)] = compare(d, se), compare(-d, se)
            comparisons[f"{a} vs {b}"] = {"score_difference": d, "stderr": se, "elements": n,
                                          "result": pairs[(a, b)]}
    order = [r["model"] for r in recs]
    ranges = rank_ranges(order, pairs)
    ranking = []
    for k, r in enumerate(recs):
        s = r["scales"][fk]
        ranking.append({"model": r["model"], "rel_rmse": s["rel_rmse"],
                        "rel_rmse_true": s["rel_rmse_true"], "noise": s["noise"],
                        "score": score(r), "factor": RANK_FACTOR,
                        "rank_best": ranges[r["model"]][0], "rank_worst": ranges[r["model"]][1],
                        "tied_with_previous": bool(k and pairs[(r["model"], order[k - 1])]
                                                   == "tied")})
    return ranking, comparisons


# --------------------------------------------------------------------------- outputs
def _tonemap_pair(images: list, exposure=None):
    from dermis.reports.tonemap import tonemap
    return tonemap(images, exposure=exposure)


def write_ground_truth(metrics: dict, images: dict, references: dict, out_dir) -> list[Path]:
    """Write ``ground_truth.json``, per light a PNG sheet (reference, models and signed
    relative-error maps on the reference grid) and return the paths."""
    from dermis.pipeline.imageio import write_png
    from dermis.reports.diff import difference_image
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    files = []
    for light, ref in sorted(references.items()):
        h, w = ref.linear.shape[:2]
        M = np.asarray(ref.linear, np.float64)
        for nid, im in sorted(images.items()):
            model, l, geom = _labels(im)
            if l != light or geom != GEOMETRY:
                continue
            D, full = _downsample_to(np.asarray(im.linear, np.float64),
                                     np.asarray(im.mask, bool), (h, w))
            valid = full & np.asarray(ref.mask, bool)
            # signed relative error on RANK_FACTOR blocks, luminance, full scale = +-50 %
            lum_r = M @ LUMINANCE
            floor = 0.05 * lum_r[valid].mean() if valid.any() else 1.0
            rel = np.nan_to_num(_block_error(D, M, valid, floor))
            tile = difference_image(np.repeat(rel[..., None], 3, axis=2) / LUMINANCE.sum(),
                                    scale=0.5)
            tile[~valid] = 0
            files.append(write_png(out_dir / f"gt-error-{model}-{light}.png", tile))
    p = out_dir / "ground_truth.json"
    p.write_text(json.dumps(metrics, indent=1, sort_keys=True, default=float))
    files.append(p)
    return files


def _rel_se_lum(mean_rgb, se_rgb) -> float | None:
    """Relative standard error of a mean's luminance from per-channel ones (channels
    independent), None without a mean."""
    lum = float(np.asarray(mean_rgb, np.float64) @ LUMINANCE)
    if lum <= 0:
        return None
    se = np.asarray(se_rgb, np.float64) * LUMINANCE
    return math.sqrt(float(se @ se)) / lum


def metrics_ground_truth(gt: dict) -> dict:
    """The ``ground_truth`` object of ``metrics.json``, keyed by lighting condition
    (docs/ground-truth.md "In metrics.json"): the reference's region means and their
    relative standard errors, every model's distance at the ranking scale and per region with
    the standard error of both images' noise, whether it is resolved, its rank range and
    seconds, and the noise the reference reached."""
    out = {}
    fk = str(gt.get("rank_factor", RANK_FACTOR))
    for light, ref in sorted(gt.get("references", {}).items()):
        rel_se = ref.get("region_rel_se") or {}
        regions = {}
        for name in REGIONS:
            rr = (ref.get("regions") or {}).get(name)
            if not rr:
                continue
            mean = rr.get("mean_rgb", [0.0, 0.0, 0.0])
            se = rr.get("stderr_rgb")
            regions[name] = {
                "pixels": rr.get("pixels"), "ref_mean_rgb": mean,
                "ref_rel_se": (float(rel_se[name]) if rel_se.get(name) is not None
                               else _rel_se_lum(mean, se) if se is not None else None),
                "ref_rel_se_rgb": ([float(s) / m if m > 0 else None for s, m in zip(se, mean)]
                                   if se is not None else None)}
        order = [r["model"] for r in gt.get("ranking", {}).get(light, [])]
        rows = {r["model"]: r for r in gt.get("ranking", {}).get(light, [])}
        models = {}
        for rec in gt.get("models", {}).values():
            s = rec["scales"].get(fk)
            if rec["light"] != light or not s:
                continue
            m = rec["model"]
            row = rows.get(m)
            models[m] = {
                "distance": s["rel_rmse"], "stderr": s["noise"], "resolved": s["resolved"],
                "distance_true": s["rel_rmse_true"], "ref_noise": s["ref_noise"],
                "model_noise": s["model_noise"], "own_noise": rec["own_noise"],
                "scale": int(fk), "seconds": rec.get("seconds"),
                "rank": order.index(m) + 1 if row else None,
                "rank_range": [row["rank_best"], row["rank_worst"]] if row else None,
                "regions": {name: {"rel_diff": g["rel_lum"], "stderr": g["sigma_lum"],
                                   "resolved": g["resolved"], "rel_diff_rgb": g["rel_rgb"],
                                   "stderr_rgb": g["sigma_rgb"], "ref_se": g["ref_se_lum"],
                                   "model_se": g["model_se_lum"],
                                   "calibration": g["calibration_lum"]}
                            for name, g in rec["regions"].items()}}
        worst = max(((v["ref_rel_se"], k) for k, v in regions.items()
                     if v["ref_rel_se"] is not None), default=(None, None))
        out[light] = {"regions": regions, "models": models, "ranking": order,
                      "noise_reached": {"passes": ref.get("passes"), "spp": ref.get("spp"),
                                        "stopped": ref.get("stopped"),
                                        "target_rel_se": ref.get("target_rel_se"),
                                        "budget_s": ref.get("budget_s"),
                                        "seconds": ref.get("seconds"),
                                        "worst_region": worst[1],
                                        "worst_region_rel_se": worst[0],
                                        "calibration_rel_rgb": ref.get("calibration_rel_rgb")}}
    return out


def _fmt_e(s: dict | None) -> str:
    if not s:
        return "-"
    mark = "" if s["resolved"] else " (n.r.)"
    return f"{100 * s['rel_rmse']:.1f} ± {100 * s['noise']:.1f}{mark}"


def _fmt_speed(s: dict | None) -> str:
    if not s or "speedup" not in s or not math.isfinite(s["speedup"]):
        return "-"
    return (">= " if s.get("speedup_is_lower_bound") else "") + f"{s['speedup']:.3g}×"


def ground_truth_pages(pdf, metrics: dict | None, images: dict, references: dict, *,
                       skip_reason: str | None = None, figsize=(11.69, 8.27)) -> int:
    """Add the "distance to ground truth" pages to an open ``PdfPages``; returns the count.

    With no references (Mitsuba missing, or ``[reference] enabled = false``) one page says
    why, so the rest of the report is unchanged.
    """
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from dermis.reports.diff import diverging_colormap

    if not references or not metrics:
        fig = plt.figure(figsize=figsize)
        fig.suptitle("Distance to ground truth", fontsize=12)
        fig.text(0.06, 0.8, skip_reason or "No path-traced reference in this run: set "
                 "[reference] enabled = true (the default; Mitsuba 3 installed by .ci/setup).",
                 fontsize=9,
                 wrap=True)
        pdf.savefig(fig)
        plt.close(fig)
        return 1
    pages = 0
    lights = sorted(references)
    models = [m for m in MODEL_ORDER if any(f"{m}-{l}" in metrics["models"] for l in lights)]

    # page 1: error table per light (rel RMSE at reference pixels and 4x4 blocks, FLIP, SSIM)
    fig = plt.figure(figsize=figsize)
    fig.suptitle("Ground truth in detail: distance at every scale, FLIP, SSIM, cost",
                 fontsize=12)
    ax = fig.add_axes([0.03, 0.08, 0.94, 0.8])
    ax.axis("off")
    header = ["light", "model", "rel RMSE % ± noise (px)", "(4×4 blocks)", "FLIP", "SSIM",
              "seconds", "speed-up (px)", "speed-up (4×4)", "rank"]
    cells = []
    for l in lights:
        rank = {r["model"]: k + 1 for k, r in enumerate(metrics["ranking"].get(l, []))}
        for m in models:
            r = metrics["models"].get(f"{m}-{l}")
            if not r:
                continue
            s1, s4 = r["scales"].get("1"), r["scales"].get("4")
            cells.append([l, m, _fmt_e(s1), _fmt_e(s4), f"{r['flip']:.3f}", f"{r['ssim']:.3f}",
                          f"{r['seconds']:.1f}", _fmt_speed(s1), _fmt_speed(s4),
                          str(rank.get(m, "-"))])
    if cells:
        t = ax.table(cellText=cells, colLabels=header, loc="upper center", cellLoc="center")
        t.auto_set_font_size(False)
        t.set_fontsize(7)
        t.scale(1, 1.25)
    ref0 = metrics["references"][lights[0]]
    notes = [f"Reference: {ref0['width']}×{ref0['height']} px, {float(ref0['spp']):.0f} "
             f"samples a pixel (mean of two half-buffers), {ref0['variant']}, "
             + ", ".join(f"{l} {metrics['references'][l]['seconds']:.0f} s" for l in lights),
             "± = the relative RMSE that noise alone gives at that scale (the reference's and "
             "the model's own, in quadrature).  n.r. = not resolved: the error is below "
             f"{RESOLVE_K:g}× that noise; speed-ups are then lower bounds.  Speed-up = "
             "path-tracer time to reach the model's error / model time."]
    fig.text(0.03, 0.03, "\n".join(textwrap.fill(n, 200) for n in notes), fontsize=7)
    pdf.savefig(fig)
    plt.close(fig)
    pages += 1

    # page 2: region table (relative luminance difference ± sigma per region)
    fig = plt.figure(figsize=figsize)
    fig.suptitle("Ground truth in detail: region means (model / reference - 1, luminance, %)",
                 fontsize=12)
    ax = fig.add_axes([0.03, 0.08, 0.94, 0.8])
    ax.axis("off")
    header = ["light", "model"] + list(REGIONS)
    cells = []
    for l in lights:
        for m in models:
            r = metrics["models"].get(f"{m}-{l}")
            if not r:
                continue
            row = [l, m]
            for name in REGIONS:
                g = r["regions"].get(name)
                row.append("-" if not g else f"{100 * g['rel_lum']:+.1f} ± "
                           f"{100 * g['sigma_lum']:.1f}{'' if g['resolved'] else ' (n.r.)'}")
            cells.append(row)
    if cells:
        t = ax.table(cellText=cells, colLabels=header, loc="upper center", cellLoc="center")
        t.auto_set_font_size(False)
        t.set_fontsize(7)
        t.scale(1, 1.25)
    fig.text(0.03, 0.03, "Regions are sets of mesh faces (dermis.geometry.regions): the same "
             "skin from any camera.  ± = one standard error: the reference's and the model's "
             "own of the region means and the albedo tint's calibration error, in quadrature.",
             fontsize=7)
    pdf.savefig(fig)
    plt.close(fig)
    pages += 1

    # page 3: images on the reference grid (tone-mapped with one exposure per light) + errors
    fig = plt.figure(figsize=figsize)
    fig.suptitle("Reference and models on the reference's pixel grid; signed relative "
                 "error on 4×4 blocks (luminance, ±50 %; red = model brighter)", fontsize=11)
    ncol = 1 + len(models)
    gs = fig.add_gridspec(2 * len(lights), ncol, top=0.92, bottom=0.02, left=0.02, right=0.98,
                          hspace=0.25, wspace=0.03)
    for i, l in enumerate(lights):
        ref = references[l]
        h, w = ref.linear.shape[:2]
        tiles = [np.asarray(ref.linear)]
        errs = [None]
        for m in models:
            im = next((x for x in images.values() if _labels(x) == (m, l, GEOMETRY)), None)
            if im is None:
                tiles.append(np.zeros_like(ref.linear))
                errs.append(None)
                continue
            D, full = _downsample_to(np.asarray(im.linear, np.float64),
                                     np.asarray(im.mask, bool), (h, w))
            tiles.append(D.astype(np.float32))
            valid = full & np.asarray(ref.mask, bool)
            lr = np.asarray(ref.linear, np.float64) @ LUMINANCE
            floor = 0.05 * lr[valid].mean() if valid.any() else 1.0
            errs.append(_block_error(D, np.asarray(ref.linear, np.float64), valid, floor))
        srgb = _tonemap_pair(tiles)
        for j, (tile, err) in enumerate(zip(srgb, errs)):
            ax = fig.add_subplot(gs[2 * i, j])
            ax.imshow(tile)
            ax.axis("off")
            ax.set_title(f"{l}: " + ("reference" if j == 0 else models[j - 1]), fontsize=7)
            if err is not None:
                ax2 = fig.add_subplot(gs[2 * i + 1, j])
                ax2.imshow(err, cmap=diverging_colormap(), vmin=-0.5, vmax=0.5)
                ax2.axis("off")
    pdf.savefig(fig)
    plt.close(fig)
    pages += 1

    # page 4: the thesis's conclusions, with numbers
    fig = plt.figure(figsize=figsize)
    fig.suptitle("Ground truth in detail: the thesis's conclusions, with their numbers",
                 fontsize=12)
    y = 0.88
    for c in metrics.get("thesis", []):
        vals = "; ".join(f"{l} ({c.get('per_light', {}).get(l, '-')}): " + _fmt_values(d)
                         for l, d in c["values"].items())
        fig.text(0.04, y, f"- {c['claim']} - {c['verdict']}", fontsize=9, weight="bold")
        fig.text(0.06, y - 0.035, f"measure: {c['measure']}", fontsize=7.5)
        fig.text(0.06, y - 0.07, vals, fontsize=7.5, wrap=True)
        y -= 0.16
    from dermis.reports.truth_pages import ranking_text
    lines = [f"{l}: {ranking_text(metrics, l)}" for l in lights]
    fig.text(0.04, max(y, 0.1), "Ranking per light (relative RMSE % on 4×4 blocks, closest "
             "first; '<' resolved apart, '~' not resolved at this noise):\n" + "\n".join(lines),
             fontsize=8)
    pdf.savefig(fig)
    plt.close(fig)
    pages += 1
    return pages


def _fmt_values(d: dict) -> str:
    """"name value ± stderr" for each number of a thesis check's values."""
    parts = []
    for k, v in d.items():
        if k.endswith("_stderr"):
            continue
        se = d.get(f"{k}_stderr")
        if isinstance(v, float):
            parts.append(f"{k} {v:.3g}" + (f" ± {se:.2g}" if se is not None and
                                            math.isfinite(se) else ""))
        else:
            parts.append(f"{k} {v}")
    return ", ".join(parts)


def ground_truth_section(images: dict, references: dict, out_dir, files: list, *, mesh, camera,
                         extra_seconds: dict, skip_reason: str | None,
                         differences: dict | None = None, tiles: dict | None = None,
                         variants: dict | None = None):
    """The report's distance-to-ground-truth section: metrics and files of ``references``
    (light -> RenderedImage; ``mesh`` and ``camera`` as :func:`ground_truth_metrics`, unused
    when there are none) and two functions adding pages to the open PDF: the opening pages
    (:func:`dermis.reports.truth_pages.opening_pages`, right after the title page; with
    ``differences``, the metrics of the differences against the BSSRDF, and their ``tiles``
    {(model, light, geometry): image} beside the ones against the reference; with
    ``variants``, the causes stage's artifacts by light, the causes table after them,
    :mod:`dermis.reports.causes`) and the detail pages (:func:`ground_truth_pages`, at the
    end).

    Its files are appended to ``files``.  Returns (opening, details, info): info's ``pages``
    is filled in when the functions have run, ``metrics`` is the ``ground_truth`` object of
    ``metrics.json`` ({} without references), ``title`` the title page's lines
    (:func:`dermis.reports.truth_pages.title_lines`), ``causes`` the causes table (when
    ``variants`` are given)."""
    from dermis.reports.truth_pages import opening_pages, title_lines
    info = {"references": sorted(references), "pages": 0, "metrics": {}}
    gt = None
    if references:
        gt = ground_truth_metrics(images, references, mesh=mesh, camera=camera,
                                  extra_seconds=extra_seconds)
        files.extend(write_ground_truth(gt, images, references, out_dir))
        info["ranking"] = gt["ranking"]
        info["metrics"] = metrics_ground_truth(gt)
        info["thesis"] = [{k: c[k] for k in ("model", "claim", "verdict", "per_light")}
                          for c in gt["thesis"]]
        if variants:
            # the variants are of the main camera's conditions, whose references share one
            # grid; the albedo convention is shared by construction (docs/ground-truth.md),
            # so its part is 0; the flat-plate test keeps it so
            ref = references[next(l for l in references if l in variants)]
            info["causes"] = causes_table(gt, variants, convention=0.0, images=images,
                                          labels=reference_labels(ref, mesh, camera, {}))
    info["title"] = title_lines(gt, skip_reason)

    def opening(pdf):
        info["pages"] += opening_pages(pdf, gt, images, references, differences=differences,
                                    tiles=tiles)
        if info.get("causes"):
            info["pages"] += causes_pages(pdf, info["causes"])

    def details(pdf):
        if gt:
            info["pages"] += ground_truth_pages(pdf, gt, images, references)
    return opening, details, info
