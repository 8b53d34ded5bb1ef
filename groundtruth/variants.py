"""Controlled variants of the ground truth: what one change to the path tracer's scene does.

Every model is darker than the Mitsuba reference (docs/ground-truth.md).  Two candidate
causes are properties of the reference's scene that the models do not share; each is
measured here by rendering the exported head (:func:`dermis.groundtruth.scene_export.
head_scene`, the reference's own export) twice with that one thing changed, at the
reference's resolution and camera:

* **Interreflection.**  The models shade with direct light only; the path tracer follows
  light from one part of the face to another.  A diffuse head whose reflectance is the albedo
  texture's linear albedo (the skin's total diffuse reflectance, every model's reading of the
  texture) is rendered with direct light only (``path``, ``max_depth = 2``) and with every
  bounce (``max_depth = -1``), with the same random numbers: the first bounce draws the same
  samples in both, so all - direct is exactly the interreflected light (>= 0 in every pixel,
  and 0 on a convex shape).  Gain g = all / direct - 1 per region: how much brighter the
  interreflections make a region (a diffuse stand-in for skin's far field).
* **Boundary.**  The reference's skin boundary is a rough GGX dielectric (alpha 0.3), the
  models' a smooth Fresnel one.  The skin head is rendered with the rough boundary and with
  Mitsuba's smooth ``dielectric`` (or a small alpha), each with the albedo tint normalised by
  its own flat-slab Rd (:func:`dermis.groundtruth.slab.slab_reflectance`), so that both read the texture as total diffuse
  reflectance on flat skin: effect b = smooth / rough - 1 per region, what remains of the
  boundary after the normalisation (angles of entry and exit, curvature).  A path leaving
  skin through a smooth boundary reaches a light only by hitting it: the variant is defined
  for disc and environment lights (:func:`boundary_lights_problem`), and is much noisier
  than the rough render (measured: 9x the variance per sample under the default area light,
  bench/results/causes.json), so it gets more samples.

Noise.  Each image is rendered as two independent half-buffers A and B (seeds 2 seed and
2 seed + 1; :func:`dermis.groundtruth.passes.render_passes`).  Per pixel ((A - B) / 2)^2
estimates the variance of the mean (A + B) / 2, a region mean's variance is the sum of that
over its pixels / N^2 (independent pixels), and a ratio's standard error follows by the delta
method with the covariance of numerator and denominator (the sum of the products of their
half-differences, which the direct and all-bounce renders share through their common random
numbers).

Regions are :mod:`dermis.geometry.regions`'s plus ``face``: every pixel that sees the head.
Pure library functions; the stage is :mod:`dermis.stages.causes`.
"""
from __future__ import annotations

import math
import time
from dataclasses import dataclass, field
from typing import Callable

import numpy as np

from dermis.geometry.regions import REGION_LABELS, REGIONS, face_regions
from dermis.groundtruth.passes import pixel_hits, render_passes
from dermis.groundtruth.scene_export import HeadSceneOptions, head_scene, release
from dermis.groundtruth.slab import slab_reflectance
from dermis.pipeline.errors import ConfigError
from dermis.rendering.color import LUMINANCE

__all__ = ["VariantOptions", "Halves", "WHOLE_FACE", "VARIANT_REGIONS",
           "render_halves", "region_labels", "ratio_stats", "interreflection_variant",
           "boundary_variant", "boundary_lights_problem", "CAUSE_EFFECTS", "MIN_LIT_PIXELS"]

# The region of every pixel that sees the head (the whole-face flux).
WHOLE_FACE = "face"
VARIANT_REGIONS = REGIONS + (WHOLE_FACE,)
# Fewest lit pixels (in each half-buffer) for which a region's standard error is given: the
# variance estimate then has at least this many independent terms (ratio_stats).
MIN_LIT_PIXELS = 8
# What each variant's effect is, for the records.
CAUSE_EFFECTS = {
    "interreflection": "all bounces / direct light only - 1, diffuse head of the texture's "
                       "linear albedo",
    "boundary": "smooth / rough (GGX) boundary - 1, skin head, each tint normalised by its "
                "own flat-slab Rd",
}


@dataclass(frozen=True)
class VariantOptions:
    """How the variants are rendered.

    width, height : the reference's size (pixels)
    seed : half-buffers use seeds 2 seed and 2 seed + 1
    diffuse_spp : samples per pixel of each half of the diffuse head (both depths)
    rough_spp, smooth_spp : samples per pixel of each half of the skin head, rough / smooth
    roughness : GGX alpha of the reference's boundary
    smooth_roughness : the smooth variant's alpha (0: Mitsuba's smooth ``dielectric``)
    slab_samples : paths of each flat-slab Rd (:func:`dermis.groundtruth.slab.slab_reflectance`)
    max_depth, rr_depth, env_clamp : the reference's skin integrator and environment clamp
    """

    width: int
    height: int
    seed: int = 1
    diffuse_spp: int = 64
    rough_spp: int = 8
    smooth_spp: int = 32
    roughness: float = 0.3
    smooth_roughness: float = 0.0
    slab_samples: int = 1 << 16
    max_depth: int = -1
    rr_depth: int = 1024
    env_clamp: float = 0.0


@dataclass
class Halves:
    """Two independent half-buffer renders of one scene: (H, W, 3) float64 ``a``, ``b``;
    their mean is the image, (a - b) / 2 its per-pixel error."""

    a: np.ndarray
    b: np.ndarray
    spp: int
    seconds: float
    info: dict = field(default_factory=dict)

    @property
    def mean(self) -> np.ndarray:
        return (self.a + self.b) / 2.0

    @property
    def half_diff(self) -> np.ndarray:
        return (self.a - self.b) / 2.0


# --------------------------------------------------------------------------- flat slab
# --------------------------------------------------------------------------- rendering
def render_halves(mi, scene, *, spp: int, seed: int, integrator=None,
                  progress: Callable[[int], None] | None = None) -> Halves:
    """``scene`` rendered twice with ``spp`` samples per pixel, seeds 2 ``seed`` and
    2 ``seed`` + 1 (:func:`dermis.groundtruth.passes.render_passes`); ``progress(samples
    done of both)``."""
    a, ta = render_passes(mi, scene, spp=spp, seed=2 * seed, integrator=integrator,
                             progress=progress)
    b, tb = render_passes(mi, scene, spp=spp, seed=2 * seed + 1, integrator=integrator,
                             progress=(lambda n: progress(spp + n)) if progress else None)
    return Halves(a, b, int(spp), ta + tb)


def region_labels(mi, scene, mesh, *, width: int, height: int) -> tuple[np.ndarray, np.ndarray]:
    """(H, W) bool hit mask and (H, W) int8 region labels (0: none) of the pixel centres of
    ``scene``'s camera, from Mitsuba's own rays (the reference's pixels)."""
    hit, prim = pixel_hits(mi, scene, width=width, height=height)
    labels = np.where(hit, face_regions(mesh.vertices, mesh.faces)[np.maximum(prim, 0)], 0)
    return hit, labels.astype(np.int8)


def _region_masks(hit: np.ndarray, labels: np.ndarray) -> dict:
    out = {name: hit & (labels == REGION_LABELS[name]) for name in REGIONS}
    out[WHOLE_FACE] = hit.copy()
    return out


def ratio_stats(num: Halves, den: Halves, hit: np.ndarray, labels: np.ndarray, *,
                calibration_rel=None) -> dict:
    """Per region (:data:`VARIANT_REGIONS`): the ratio of region means num / den - 1, per
    channel and in luminance, with its standard error.

    Delta method on the region sums N, D: var(N / D) = (vN - 2 r cND + r^2 vD) / D^2 with
    r = N / D, vN = the sum over the pixels of num's half-difference^2, vD likewise, cND = the
    sum of the products of the two half-differences (non-zero where the renders share random
    numbers); i.e. the sum over the pixels of (num_hd - r den_hd)^2 / D^2.
    ``calibration_rel`` (3,): a relative error of the ratio's scale (the slabs' Rd) added in
    quadrature.
    """
    cal = np.zeros(3) if calibration_rel is None else np.asarray(calibration_rel, np.float64)
    nm, dm, nh, dh = num.mean, den.mean, num.half_diff, den.half_diff
    out = {}
    for name, sel in _region_masks(hit, labels).items():
        n = int(sel.sum())
        if n == 0:
            out[name] = {"pixels": 0}
            continue
        rec = {"pixels": n}
        N, D = nm[sel].sum(axis=0), dm[sel].sum(axis=0)
        vN, vD = (nh[sel] ** 2).sum(axis=0), (dh[sel] ** 2).sum(axis=0)
        cND = (nh[sel] * dh[sel]).sum(axis=0)
        # luminance: the same sums of the luminance images
        Nl, Dl = float(N @ LUMINANCE), float(D @ LUMINANCE)
        nhl, dhl = nh[sel] @ LUMINANCE, dh[sel] @ LUMINANCE
        vNl, vDl, cl = float((nhl ** 2).sum()), float((dhl ** 2).sum()), float((nhl * dhl).sum())
        cal_l = float(cal @ (LUMINANCE * D) / Dl) if Dl > 0 else 0.0

        def ratio(Nv, Dv, vn, vd, c, cal_v):
            if not Dv > 0:   # an unlit region: no ratio
                return None, None
            r = Nv / Dv
            # sum over pixels of (num_hd - r den_hd)^2 / D^2: never negative
            var = max(vn - 2.0 * r * c + r * r * vd, 0.0) / (Dv * Dv)
            return r - 1.0, math.sqrt(var + (r * cal_v) ** 2)

        # the half-difference estimate of the variance fails where few pixels have any
        # light at all (a rare-hit estimator: a region whose paths never reached the light
        # reads 0 +- 0): below MIN_LIT_PIXELS lit pixels in a half, no standard error
        lit = min(int(((im[sel] @ LUMINANCE) > 0).sum()) for im in (num.a, num.b, den.a, den.b))
        rec["lit_pixels"] = lit
        per = [ratio(float(N[c]), float(D[c]), float(vN[c]), float(vD[c]), float(cND[c]),
                     float(cal[c])) for c in range(3)]
        rec["effect_rgb"] = [p[0] for p in per]
        rec["se_rgb"] = [p[1] for p in per]
        rec["effect_lum"], rec["se_lum"] = ratio(Nl, Dl, vNl, vDl, cl, cal_l)
        if lit < MIN_LIT_PIXELS:
            rec["se_rgb"], rec["se_lum"] = [None] * 3, None
        rec["num_mean_rgb"] = [float(v) / n for v in N]
        rec["den_mean_rgb"] = [float(v) / n for v in D]
        out[name] = rec
    return out


# --------------------------------------------------------------------------- variants
def interreflection_variant(mi, mesh, camera, lights, opts: VariantOptions, *,
                            progress: Callable[[float], None] | None = None) -> dict:
    """The interreflection gain of a diffuse head (module docstring).

    Returns ``regions`` (:func:`ratio_stats` of all bounces over direct light), ``hit`` and
    ``labels`` (the reference's pixels), ``direct`` and ``all`` (:class:`Halves`),
    ``seconds``.
    """
    t0 = time.perf_counter()
    w, h = opts.width, opts.height
    head = head_scene(mi, mesh, None, camera, lights, width=w, height=h,
                      options=HeadSceneOptions(roughness=opts.roughness, material="lambert",
                                               env_clamp=opts.env_clamp))
    spp = int(opts.diffuse_spp)
    try:
        hit, labels = region_labels(mi, head.scene, mesh, width=w, height=h)
        renders = {}
        for k, (name, depth) in enumerate((("direct", 2), ("all", -1))):
            integ = mi.load_dict({"type": "path", "max_depth": depth, "hide_emitters": True})
            # the same seeds for both depths: common random numbers (module docstring)
            renders[name] = render_halves(
                mi, head.scene, spp=spp, seed=opts.seed, integrator=integ,
                progress=(lambda n, k=k: progress((k * 2 * spp + n) / (4 * spp)))
                if progress else None)
    finally:
        release(head)
    regions = ratio_stats(renders["all"], renders["direct"], hit, labels)
    return {"regions": regions, "hit": hit, "labels": labels, "direct": renders["direct"],
            "all": renders["all"], "seconds": time.perf_counter() - t0, "spp": spp,
            "textured": head.export.get("textured", False)}


def boundary_lights_problem(lights) -> str | None:
    """Why a smooth-boundary variant cannot be rendered under ``lights`` (None if it can): a
    path leaving skin through a smooth boundary never reaches a point or directional light."""
    delta = [lt.name for lt in lights if lt.type in ("point", "directional")]
    if delta:
        return (f"light {delta[0]!r} is a {next(lt.type for lt in lights if lt.name == delta[0])}"
                " light: a path leaving skin through a smooth boundary never reaches it (use a "
                "lighting condition of disc or environment lights)")
    return None


def boundary_variant(mi, mesh, stack, camera, lights, opts: VariantOptions, *,
                     labels=None, progress: Callable[[float], None] | None = None) -> dict:
    """The smooth-vs-rough boundary effect on the skin head (module docstring).

    Returns ``regions`` (:func:`ratio_stats` of smooth over rough, with the two slabs'
    relative errors as calibration), ``slabs`` (roughness -> :class:`SlabResult`), ``rough``
    and ``smooth`` (:class:`Halves`), ``hit``, ``labels``, ``seconds``, ``normalised``
    (False for an untextured mesh: no tint, so the raw ratio).  ``labels``: (hit, labels) of
    the reference's pixels when known.
    """
    why = boundary_lights_problem(lights)
    if why:
        raise ConfigError(f"boundary variant: {why}")
    t0 = time.perf_counter()
    w, h = opts.width, opts.height
    alphas = {"rough": float(opts.roughness), "smooth": float(opts.smooth_roughness)}
    spps = {"rough": int(opts.rough_spp), "smooth": int(opts.smooth_spp)}
    total = 2 * sum(spps.values())
    slabs, renders, done = {}, {}, 0
    for name in ("rough", "smooth"):
        slab = slab_reflectance(mi, stack, roughness=alphas[name], samples=opts.slab_samples,
                                seed=opts.seed, max_depth=opts.max_depth,
                                rr_depth=opts.rr_depth)
        slabs[name] = slab
        head = head_scene(mi, mesh, stack, camera, lights, width=w, height=h,
                          options=HeadSceneOptions(roughness=alphas[name], tint_rd=slab.Rd_entered,
                                                   env_clamp=opts.env_clamp,
                                                   max_depth=opts.max_depth,
                                                   rr_depth=opts.rr_depth))
        try:
            if labels is None:
                labels = region_labels(mi, head.scene, mesh, width=w, height=h)
            renders[name] = render_halves(
                mi, head.scene, spp=spps[name], seed=opts.seed,
                progress=(lambda n, d=done: progress((d + n) / total)) if progress else None)
        finally:
            release(head)
        done += 2 * spps[name]
    normalised = bool(head.export.get("tinted", False))
    cal = None
    if normalised:
        cal = np.sqrt(sum((np.asarray(s.Rd_stderr) / np.maximum(np.asarray(s.Rd), 1e-30)) ** 2
                          for s in slabs.values()))
    hit, lab = labels
    regions = ratio_stats(renders["smooth"], renders["rough"], hit, lab, calibration_rel=cal)
    return {"regions": regions, "slabs": slabs, "rough": renders["rough"],
            "smooth": renders["smooth"], "hit": hit, "labels": lab, "alphas": alphas,
            "spp": spps, "normalised": normalised, "seconds": time.perf_counter() - t0}
