"""What a scene requires: per view, lighting condition and face region, which effects are
visible at the view's resolution and which model is the cheapest that meets the user's
accuracy (docs/science.md, "What a scene requires").

**Effects.**  An effect is a pair of images that differ in one modelling choice and nothing
else (same view, light and camera rays): the profile's shape (the BSSRDF with the Monte
Carlo table against the multipole), the layering (the BSSRDF over the skin stack against
one layer of the same total reflectance, optics/single_layer.py), the scan's geometric detail (the BSSRDF on the
1M-triangle mesh against the low mesh with its bump map), subsurface transport at all (the
BSSRDF against the local model carrying the profile's total reflectance), asperity
scattering (the asperity model against its base BRDF).  Its size in a region is the relative
difference of the two images' region means, with the standard error of both images' noise
(:func:`dermis.reports.truth_noise.region_difference`); it is *visible* when it exceeds the
threshold (``[report] effect_threshold``, default 1 % of the region's mean) by more than
``RESOLVE_K`` standard errors, and *absent* when it is below the threshold by as much.  An
effect whose pair the run did not render is listed as not measured, with the model to add.

**Cheapest adequate model.**  Per region, against the path-traced reference where it is
rendered (its region errors, :mod:`dermis.reports.ground_truth`), else against the most
complete model rendered (the BSSRDF with the Monte Carlo table, else the BSSRDF): a model
*meets* ``[report] accuracy`` when ``|error| + RESOLVE_K sigma <= accuracy`` and *fails*
when ``|error| - RESOLVE_K sigma > accuracy``; the cheapest model that meets it (seconds per
image, a BSSRDF with its irradiance pass) is the answer, else none does.

Pure functions over rendered images; numpy.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from dermis.models import catalog
from dermis.geometry.regions import REGION_LABELS, REGIONS
from dermis.pipeline.config import condition_of, view_name_of
from dermis.reports.truth_noise import RESOLVE_K, region_difference
from dermis.rendering.color import LUMINANCE

__all__ = ["Effect", "EFFECTS", "scene_requirements", "requirements_of", "auto_verdicts",
           "COMPLETE_MODELS"]


@dataclass(frozen=True)
class Effect:
    """A modelling choice and the two images that differ in it alone: (model, geometry) with
    the effect, and without it."""

    name: str
    with_: tuple
    without: tuple
    meaning: str


EFFECTS = (
    Effect("profile shape", ("bssrdf_mc", "high"), ("bssrdf", "high"),
           "Monte Carlo profile table vs the multipole"),
    Effect("layering", ("bssrdf", "high"), ("bssrdf_single", "high"),
           "skin stack vs one layer of the same total reflectance"),
    Effect("mesh detail", ("bssrdf", "high"), ("bssrdf", "low_bump"),
           "1M-triangle scan vs low mesh + bump map"),
    Effect("subsurface transport", ("bssrdf", "high"), ("bssrdf_local", "high"),
           "BSSRDF gather vs a local model of the same total reflectance"),
    Effect("asperity", ("asperity", "high"), ("lambert", "high"),
           "asperity term over its Lambert base vs the base alone"),
)
# the most complete models, best first: the answer where no reference is rendered
COMPLETE_MODELS = ("bssrdf_mc", "bssrdf")


def _verdict(size: float, sigma: float, limit: float, above: str, below: str) -> str:
    if size - RESOLVE_K * sigma > limit:
        return above
    if size + RESOLVE_K * sigma <= limit:
        return below
    return "unresolved"


def _region_masks(labels: np.ndarray, mask: np.ndarray) -> dict:
    out = {"all": mask}
    for name in REGIONS:
        sel = mask & (labels == REGION_LABELS[name])
        if sel.sum() >= 4:
            out[name] = sel
    return out


def _pair(a, b, sel) -> dict:
    """The effect's size in a region, a with it over b without.  Where both images carry
    their noise, it enters as one half-difference h = n_a - (a / b) n_b (a / b their
    luminance ratio over the region): the first-order noise of the ratio whether the two
    share their samples (the same rays, the same points: their noise then cancels in part)
    or not (then E[h^2] is the two variances' sum, as taken apart)."""
    A, B = np.asarray(a.linear, np.float64), np.asarray(b.linear, np.float64)
    model_hd, ref_hd = a.noise, b.noise
    if model_hd is not None and ref_hd is not None:
        q = float(B[sel].mean(axis=0) @ LUMINANCE)
        ratio = float(A[sel].mean(axis=0) @ LUMINANCE) / q if q > 0 else 1.0
        model_hd = np.asarray(model_hd, np.float64) - ratio * np.asarray(ref_hd, np.float64)
        ref_hd = None
    d = region_difference(A, B, sel, model_hd=model_hd, ref_var=None, ref_hd=ref_hd,
                          ref_region=None, calib=np.zeros(3))
    if not (np.asarray(d["ref_rgb"]) > 0).any():
        # the region is black without the effect: 0 if black with it too (a hard shadow in
        # both), else all its light is the effect's (+100 % of what it shows)
        lit = (np.asarray(d["model_rgb"]) > 0).any()
        return {"size": float(lit), "signed": float(lit), "stderr": 0.0}
    return {"size": abs(d["rel_lum"]), "signed": d["rel_lum"], "stderr": d["sigma_lum"]}


def _seconds(image, extra: dict) -> float:
    """An image's seconds, a BSSRDF's with its irradiance pass (as the timing table)."""
    sec = float((image.timings or {}).get("total", 0.0) or 0.0)
    info = image.info
    if catalog.is_bssrdf(info["model"]) and info["geometry"] == "high":
        sec += float(extra.get((info["light"], "mesh_high"), 0.0))
    return sec


def scene_requirements(images: dict, labels_of, *, accuracy: float, threshold: float,
                       truth: dict | None = None, extra_seconds: dict | None = None) -> dict:
    """``views.<view>.requires`` of metrics.json.

    images : id -> RenderedImage (info model / light / geometry)
    labels_of : lighting label -> (H, W) region labels of that label's camera at its image
        size (:func:`dermis.reports.ground_truth.region_labels_for`)
    accuracy, threshold : relative (``[report] accuracy`` and ``effect_threshold``)
    truth : metrics.json's ``ground_truth`` (lighting label -> its models' region errors and
        seconds), when references exist
    extra_seconds : (light, mesh node) -> seconds of a BSSRDF's irradiance pass
    """
    extra = extra_seconds or {}
    by = {(im.info["model"], im.info["light"], im.info["geometry"]): im for im in images.values()}
    out: dict = {}
    for label in sorted({k[1] for k in by}):
        labels = labels_of(label)
        masks = {g: np.asarray(im.mask, bool) for (m, l, g), im in by.items() if l == label}
        mask = masks.get("high", next(iter(masks.values())))
        regions = _region_masks(labels, mask)
        rows = {}
        for region, sel in regions.items():
            effects = {}
            for e in EFFECTS:
                a, b = by.get((e.with_[0], label, e.with_[1])), by.get(
                    (e.without[0], label, e.without[1]))
                if a is None or b is None:
                    need = [f"{m} on {g}" for (m, g), im in ((e.with_, a), (e.without, b))
                            if im is None]
                    effects[e.name] = {"measured": False, "needs": need}
                    continue
                both = sel & np.asarray(a.mask, bool) & np.asarray(b.mask, bool)
                if both.sum() < 4:
                    continue
                p = _pair(a, b, both)
                p.update(measured=True, verdict=_verdict(p["size"], p["stderr"], threshold,
                                                         "visible", "absent"))
                effects[e.name] = p
            rows[region] = {"effects": effects,
                            **_cheapest(by, label, region, sel, accuracy, truth, extra)}
        out.setdefault(view_name_of(label), {})[condition_of(label)] = {
            "regions": rows, "cheapest_everywhere": _everywhere(rows)}
    return out


def _everywhere(rows: dict) -> str | None:
    """The cheapest model that meets the accuracy in every region where it was measured."""
    seen: dict = {}
    for row in rows.values():
        for m, v in row["models"].items():
            ok, t = seen.get(m, (True, 0.0))
            seen[m] = (ok and v["verdict"] == "meets", max(t, v["seconds"]))
    ok = sorted((t, m) for m, (good, t) in seen.items() if good)
    return ok[0][1] if ok else None




def _cheapest(by, label, region, sel, accuracy, truth, extra) -> dict:
    """The models' errors in ``region`` against the truth (or the most complete model) and the
    cheapest that meets ``accuracy``."""
    cands = {}
    against = None
    if truth and label in truth:
        against = "reference"
        for m, rec in truth[label].get("models", {}).items():
            g = rec["regions"].get(region)
            if g is not None and rec.get("seconds") is not None:
                cands[m] = (g["rel_diff"], g["stderr"], rec["seconds"])
    else:
        best = next((m for m in COMPLETE_MODELS if (m, label, "high") in by), None)
        if best is not None:
            against = best
            ref = by[(best, label, "high")]
            cands[best] = (0.0, 0.0, _seconds(ref, extra))   # adequate by definition
            for (m, l, g), im in by.items():
                if l != label or g != "high" or m == best:
                    continue
                both = sel & np.asarray(im.mask, bool) & np.asarray(ref.mask, bool)
                if both.sum() >= 4:
                    p = _pair(im, ref, both)
                    cands[m] = (p["signed"], p["stderr"], _seconds(im, extra))
    errors = {m: {"error": e, "stderr": s, "seconds": t,
                  "verdict": _verdict(abs(e), s, accuracy, "fails", "meets")}
              for m, (e, s, t) in cands.items()}
    meets = sorted((v["seconds"], m) for m, v in errors.items() if v["verdict"] == "meets")
    return {"against": against, "models": errors,
            "cheapest": meets[0][1] if meets else None}


def requirements_of(images: dict, mesh, settings: dict, truth: dict | None,
                    extra_seconds: dict) -> dict:
    """:func:`scene_requirements` of the report stage's images: ``settings`` holds
    ``[report]`` and the camera of every lighting label (``cameras``); region labels come
    from the high ``mesh`` through each label's camera at its images' size."""
    from dermis.pipeline.config import CameraConfig
    from dermis.reports.ground_truth import region_labels_for
    sizes = {im.info["light"]: im.linear.shape[:2] for im in images.values()}
    cache: dict = {}

    def labels_of(label):
        if label not in cache:
            h, w = sizes[label]
            cam = CameraConfig(**settings["cameras"][label])
            cache[label] = region_labels_for(mesh, cam, width=w, height=h)
        return cache[label]
    return scene_requirements(images, labels_of, accuracy=settings["accuracy"],
                              threshold=settings["effect_threshold"], truth=truth,
                              extra_seconds=extra_seconds)


def auto_verdicts(requires: dict, chosen: dict, accuracy: float) -> dict:
    """``views.<view>.auto``: for each lighting label whose model ``["auto"]`` chose
    (``chosen``: label -> model), whether the accuracy held against the truth in every
    region ("held"), failed somewhere ("missed"), or cannot be told from the noise or
    without a reference ("unresolved" / "unverified")."""
    out: dict = {}
    for label, model in chosen.items():
        rows = requires.get(view_name_of(label), {}).get(condition_of(label), {}).get(
            "regions", {})
        verdicts = {r: row["models"][model]["verdict"] for r, row in rows.items()
                    if row.get("against") == "reference" and model in row["models"]}
        held = ("unverified" if not verdicts else "missed" if "fails" in verdicts.values()
                else "held" if set(verdicts.values()) == {"meets"} else "unresolved")
        out.setdefault(view_name_of(label), {})[condition_of(label)] = {
            "model": model, "accuracy": accuracy, "target": held, "regions": verdicts}
    return out
