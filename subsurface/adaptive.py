"""The adaptive BSSRDF: the exact part of the exitance at every shading point, the smooth
rest from the gather sampled on a coarse grid of pixels and interpolated, and each of the two
gathered only where a predictor says the image would otherwise miss the target
(docs/science.md §4 "Adaptive gather").

Split.  The full BSSRDF (``subsurface/exitance.py``) is, for point and directional lights,
the exact near field C(x) [Rd_near V(x) - edge terms] at the shading point plus the far part
gathered from the points; for other light, the whole profile gathered.  The adaptive model
takes

* the exact part, Rd_near C(x) V(x) (``subsurface/local.py``: the light's entering
  irradiance at the shading point and its shadow ray), what the near field is wherever no
  shadow edge lies within its window: evaluated at every shading point, as a BRDF is;
* the smooth part, exitance()'s "smooth" terms: the points' irradiance reconstructed at
  width sigma and convolved with the profile (its far part, beyond 2 sigma, for point and
  directional light): gathered at the centre pixel of every cell of about sigma on the
  image and interpolated bilinearly between them (``subsurface/sparse_gather.py``).

On a flat, uniformly lit plate the smooth part is constant and the model equals the gather
to its own approximation error (tests/test_bssrdf_adaptive.py).

Predictor.  Per pixel, the relative change of the pixel each gather would make:

* interpolation: the samples' second differences along both image axes (bilinear
  interpolation's error, ``sparse_gather.interpolation_error``), the largest of the four
  samples the pixel is interpolated from; inf where one is missing (the head's outline);
* occlusion: the profile's energy beyond the distance to a depth discontinuity of the image
  (a surface the camera does not see may lie within reach);
* irradiance: the shadow V convolved with the near part of the profile on the image (per
  channel, radial, at the image's median pixel footprint; normalised over the pixels that
  hit) minus V, times Rd_near C(x), over the pixel's exitance (screen-space diffusion,
  Jimenez et al. 2009, used here only to predict): the edge terms the exact part leaves out.

The first two say where the smooth part is gathered (once per pixel, at the mean position of
its shading points, or at each of them where they spread over more than CENTROID_SPREAD
sigma: an outline or grazing pixel); the third where the near field's edge terms are added
at the pixel's shading points (exitance()'s "near" terms less the exact part).

Budget.  A pixel is gathered whole where its prediction reaches a threshold tau and blended
from half of it, w = smoothstep((p / tau - BLEND_LOW) / (1 - BLEND_LOW)), so no pixel
switches model abruptly; tau is the largest in [target, PIXEL_CAP target] whose predicted
residual, summed over the image, stays within BUDGET x the target's relative RMSE
(:func:`threshold`).  Every gather shares the run's octree and shadow edges with the full
BSSRDF's image of the same lighting condition.
"""
from __future__ import annotations

import math
import time
from dataclasses import dataclass

import numpy as np

from dermis.subsurface.exitance import ExitanceOptions, ShadingPoints, exitance
from dermis.subsurface.local import pixel_representatives, sharp_irradiance
from dermis.subsurface.sparse_gather import (interpolate, interpolation_error, sample_grid,
                                             sample_spacing)
from dermis.subsurface.near_field import SHARP_LIGHTS, split_profile

__all__ = ["KERNELS", "TARGET", "BLEND_LOW", "PREDICTORS", "AdaptiveOptions", "PixelFrame",
           "pixel_frame", "adaptive_exitance", "exact_exitance", "energy_beyond",
           "blend_weight"]

KERNELS = ("point_interpolation.cl",)

# The target: a pixel is gathered where the gather is predicted to change it by more than
# 1 % (the relative RMSE the adaptive model is to stay within of the full BSSRDF).
TARGET = 0.01
# The blend starts at half the target (w = 0 below) and is complete at the target.
BLEND_LOW = 0.5
# Depth steps between neighbouring pixels larger than this many times a footprint x (1 +
# the surface's slope) are occlusions (a continuous surface steps footprint x slope).
DEPTH_JUMP_FOOTPRINTS = 4.0
# A pixel has the profile's whole support on the image when the pixels that hit hold all but
# this fraction of the profile's weight about it.
FULL_SUPPORT = 0.02
# Pixels whose local exitance is below this fraction of the image's mean are measured
# against it (relative change of a near-black pixel is not the image's error).
DARK_FLOOR = 0.05
# The image-space predictors work on bins of PREDICTOR_BIN x PREDICTOR_BIN pixels (4x less
# work; each pixel takes its bin's prediction).
PREDICTOR_BIN = 2
# The smooth part is gathered once per pixel, at the mean position of its shading points,
# where they lie within this many sigma of it (else at each of them: a grazing or outline
# pixel).  Main view, disc light, centroid against the mean of the shading points' gathers:
# 92 % of the squared difference came from the 2.3 % of pixels spread over more than sigma,
# a median 0.07 % below 0.5 sigma.
CENTROID_SPREAD = 0.5
# The predictors a pixel's blend weight takes the largest of (module docstring).
PREDICTORS = ("irradiance", "occlusion", "interpolation")


# No pixel is left with a predicted change above this many targets, whatever the budget
# allows: the image's error is spread, not put into a few pixels.  With 3 the near field's
# edge terms left a smooth band of ~1.5 % beside the gathered shadow edges of the nose and
# eyelid close-ups; with 2 it is under 1 %, for 0.3-0.4 % rRMSE against the full BSSRDF
# instead of 0.55 % (bench/results/bssrdf_adaptive.json, bssrdf_adaptive/*-diff.png).
PIXEL_CAP = 2.0
# The predicted residual is held to this fraction of the target: the predictors are
# estimates (bench/results/bssrdf_adaptive.json: with the whole target the disc light's
# image came out 1.05 % from the full BSSRDF).
BUDGET = 0.5


@dataclass(frozen=True)
class AdaptiveOptions:
    """target : the relative RMSE of the image against the full BSSRDF the predicted
    changes are held to (:func:`threshold`);
    blend_low : fraction of the threshold where the blend starts (w = 0 below);
    pixel_cap : the largest threshold, in targets."""

    target: float = TARGET
    blend_low: float = BLEND_LOW
    pixel_cap: float = PIXEL_CAP


@dataclass
class PixelFrame:
    """Where the shading points lie in the image: ``pixel`` (Q,) flat pixel index,
    ``width``, ``height``, ``depth`` (Q,) distance along the view, mm, and
    ``footprint`` (Q,) a pixel's width at that depth, mm; ``slope`` (Q,) the depth step
    per unit of image distance of the surface there, tan of its normal's angle to the
    view (capped at 20)."""

    pixel: np.ndarray
    width: int
    height: int
    depth: np.ndarray
    footprint: np.ndarray
    slope: np.ndarray


def pixel_frame(camera, pixel: np.ndarray, positions: np.ndarray,
                normals: np.ndarray) -> PixelFrame:
    """The PixelFrame of shading points at ``positions`` (unit geometric ``normals``) seen
    through pixels ``pixel``."""
    from dermis.rendering.camera import camera_vectors
    pos, fwd, _, _ = camera_vectors(camera)
    d = np.asarray(pos, np.float32)[None, :] - np.asarray(positions, np.float32)
    depth = -(d @ np.asarray(fwd, np.float32)).astype(np.float64)
    size = 2.0 * math.tan(math.radians(camera.fov_deg) / 2.0) / min(camera.width, camera.height)
    n = np.asarray(normals, np.float32)
    c = np.abs(np.einsum("ij,ij->i", d, n)) / np.maximum(
        np.sqrt(np.einsum("ij,ij->i", d, d) * np.einsum("ij,ij->i", n, n)), np.float32(1e-30))
    c = np.clip(c, 0.05, 1.0).astype(np.float64)
    return PixelFrame(np.asarray(pixel, np.int64), int(camera.width), int(camera.height),
                      depth, depth * size, np.sqrt(1.0 - c * c) / c)


# --------------------------------------------------------------------------- the profile
def _energy_within(profile):
    """(r, m (M, 3)): the profile's energy within r as the gather integrates it (linear in
    r, zero beyond each cut-off, scaled to Rd)."""
    r0, R0 = np.asarray(profile.r_mm, np.float64), np.asarray(profile.R, np.float64)
    cut, rd = np.asarray(profile.cutoff_mm, np.float64), np.asarray(profile.Rd, np.float64)
    h = float(np.min(np.diff(r0))) / 4.0
    r = np.arange(0.0, float(cut.max()) + 2 * h, h)
    R = np.stack([np.interp(r, r0, R0[:, c], right=0.0) for c in range(3)], axis=1)
    R[r[:, None] > cut[None, :]] = 0.0
    ring = 2.0 * np.pi * r[:, None] * R
    m = np.vstack([np.zeros((1, 3)), np.cumsum(0.5 * (ring[1:] + ring[:-1]) * h, axis=0)])
    m *= np.where(m[-1] > 0, rd / np.where(m[-1] > 0, m[-1], 1.0), 0.0)
    return r, m


def energy_beyond(profile, d) -> np.ndarray:
    """The largest over channels of the profile's energy beyond distance ``d`` (mm), as a
    fraction of its Rd: (len(d),) in [0, 1]."""
    r, m = _energy_within(profile)
    rd = np.asarray(profile.Rd, np.float64)
    d = np.asarray(d, np.float64)
    out = np.zeros(d.shape)
    for c in range(3):
        if rd[c] > 0:
            out = np.maximum(out, 1.0 - np.interp(d, r, m[:, c]) / rd[c])
    return out


def _profile_kernel(profile, footprint: float, channel: int) -> np.ndarray:
    """The profile on the pixel grid (pixels ``footprint`` mm wide), each pixel holding the
    energy of its ring of radii, normalised to sum 1."""
    r, m = _energy_within(profile)
    reach = float(np.asarray(profile.cutoff_mm).max())
    n = max(1, int(math.ceil(reach / footprint)))
    y, x = np.mgrid[-n:n + 1, -n:n + 1]
    d = np.hypot(x, y) * footprint
    # a pixel at distance d holds the ring's energy density times its area
    within = np.interp(np.array([d.ravel() - 0.5 * footprint, d.ravel() + 0.5 * footprint]),
                       r, m[:, channel])
    ring_area = np.pi * ((d.ravel() + 0.5 * footprint) ** 2
                         - np.maximum(d.ravel() - 0.5 * footprint, 0.0) ** 2)
    k = (within[1] - within[0]) / ring_area * footprint ** 2
    k[d.ravel() == 0] = np.interp(footprint / math.sqrt(math.pi), r, m[:, channel])
    k = np.maximum(k, 0.0).reshape(d.shape)
    return k / max(float(k.sum()), 1e-300)


def smoothstep(x: np.ndarray) -> np.ndarray:
    t = np.clip(x, 0.0, 1.0)
    return t * t * (3.0 - 2.0 * t)


def blend_weight(predicted: np.ndarray, options: AdaptiveOptions,
                 tau: float | None = None) -> np.ndarray:
    """w from the predicted relative change: 0 below blend_low x ``tau``, 1 at ``tau``
    (default the target)."""
    p = np.asarray(predicted, np.float64) / (options.target if tau is None else tau)
    return smoothstep((p - options.blend_low) / (1.0 - options.blend_low))


def threshold(predicted: list, scale: np.ndarray, options: AdaptiveOptions) -> float:
    """The per-pixel threshold tau (relative change where a pixel is gathered whole) in
    [target, pixel_cap x target] whose residual meets the error budget: the predicted
    changes ``predicted`` (each (P,), relative to ``scale`` (P,) the pixel's exitance) left
    after the blend, sum_i (sum_k (1 - w_ik) p_ik)^2 scale_i^2 <= (BUDGET target)^2 sum_i
    scale_i^2 (the image's relative RMSE); the largest such tau, by bisection (the residual grows
    with tau)."""
    lo, hi = options.target, options.pixel_cap * options.target
    s2 = np.asarray(scale, np.float64) ** 2
    budget = (BUDGET * options.target) ** 2 * float(s2.sum())
    fin = [np.where(np.isfinite(p), p, 0.0) for p in predicted]
    # pixels below the blend at the lowest threshold keep their whole predicted change
    moves = np.maximum.reduce(fin) >= options.blend_low * lo
    still = sum(p[~moves] for p in fin)
    budget -= float(np.sum(still * still * s2[~moves]))
    fin = [p[moves] for p in fin]
    s2 = s2[moves]

    def residual(tau):
        r = sum((1.0 - blend_weight(p, options, tau)) * p for p in fin)
        return float(np.sum(r * r * s2))
    if residual(hi) <= budget:
        return hi
    if residual(lo) > budget:
        return lo
    for _ in range(24):
        mid = 0.5 * (lo + hi)
        lo, hi = (mid, hi) if residual(mid) <= budget else (lo, mid)
    return lo


# --------------------------------------------------------------------------- local model
def _resolved(options: ExitanceOptions, sigma: float, lights) -> bool:
    """Whether :func:`exitance` resolves the near field at the shading points (its test)."""
    return bool(options.near_field and options.normalisation == "energy" and sigma > 0
                and any(l.type in SHARP_LIGHTS for l in lights)
                and options.tuning.kernel_sigma_mm is None)


def exact_exitance(profile, shading: ShadingPoints, *, lights, visibility,
                   options: ExitanceOptions, sigma: float, parts: list | None = None):
    """The part of the exitance (Q, 3) the adaptive model evaluates at every shading point:
    for point and directional lights, where the near field is resolved, Rd_near C(x) V(x)
    (``subsurface/local.py``), the exact near field wherever no shadow edge lies within its
    window; zero otherwise.  ``parts``: if given, a list that gets the terms the gather
    would blur, for the predictor: (values (Q,) or (Q, 3), the profile part that blurs them,
    a factor (Q, 3) applied after)."""
    lights = list(lights)
    parts = [] if parts is None else parts
    M = np.zeros((len(shading.positions), 3))
    if not _resolved(options, sigma, lights):
        return M
    split = split_profile(profile, sigma, cutoff_mm=options.tuning.cutoff_mm)
    rd_near = np.asarray(split.rd_near, np.float64)
    for k, light in enumerate(l for l in lights if l.type in SHARP_LIGHTS):
        c, v = sharp_irradiance(shading, light, k, visibility, options.transmittance)
        rc = rd_near.astype(np.float32)[None, :] * c
        M += rc * v[:, None]
        # the exact near field blurs only the shadow: C(x) [Rd_near V - edge terms]
        parts.append((v, split.near, rc))
    return M


def _spacing(points) -> float:
    return float(points.info.get("spacing_mm") or math.sqrt(
        float(np.sum(points.areas)) / max(len(points.areas), 1)))
# --------------------------------------------------------------------------- predictor
def _image(values: np.ndarray, pixel: np.ndarray, size: int) -> tuple[np.ndarray, np.ndarray]:
    """Per-pixel mean of per-sample values (Q, k) -> (size, k), and the hit count."""
    count = np.bincount(pixel, minlength=size).astype(np.float64)
    out = np.stack([np.bincount(pixel, weights=values[:, c], minlength=size)
                    for c in range(values.shape[1])], axis=1)
    return out / np.maximum(count, 1.0)[:, None], count


def irradiance_change(parts: list, total: np.ndarray, mask: np.ndarray,
                      footprint: float) -> np.ndarray:
    """(H, W) predicted relative change of each pixel from the irradiance around it: for each
    term (image (H, W, 3), the profile part that blurs it, factor (H, W, 3) or None) its image
    convolved with that profile at ``footprint`` mm per pixel (normalised over ``mask``, the
    pixels that hit) minus itself, times the factor; summed, over ``total`` (H, W, 3)
    (floored at DARK_FLOOR of the image's mean), the largest channel."""
    from scipy.ndimage import distance_transform_edt
    from scipy.signal import fftconvolve
    m = mask.astype(np.float64)
    change = np.zeros(mask.shape + (3,))
    support = np.ones(mask.shape)
    for img, part, factor in parts:
        for c in range(3):
            if not (np.asarray(part.Rd)[c] > 0 and np.any(img[..., c][mask] != 0)):
                continue
            k = _profile_kernel(part, footprint, c)
            x = img[..., c] * m
            # the surface goes on past the image's border (a close-up): mirrored there, so a
            # border pixel's neighbourhood is symmetric (no first-order bias)
            n = min(k.shape[0] // 2, min(mask.shape) - 1)
            xp, mp = (np.pad(a, n, mode="reflect") for a in (x, m))
            den = fftconvolve(mp, k, mode="same")[n:-n or None, n:-n or None]
            support = np.minimum(support, den)
            num = fftconvolve(xp, k, mode="same")[n:-n or None, n:-n or None]
            conv = np.where(den > 1e-6, num / np.maximum(den, 1e-6), x)
            d = np.abs(conv - x)
            change[..., c] += d if factor is None else d * factor[..., c]
    out = np.zeros(mask.shape)
    for c in range(3):
        mean = float(total[..., c][mask].mean()) if mask.any() else 0.0
        if mean > 0:
            out = np.maximum(out, np.where(mask, change[..., c] / np.maximum(
                total[..., c], DARK_FLOOR * mean), 0.0))
    # where the profile reaches past the head's outline the one-sided mean is biased by the
    # gradient (a first-order error the gather, whose points go on round the head, does not
    # make): those pixels take the prediction of the nearest pixel with the profile's whole
    # support on the image
    full = mask & (support > 1.0 - FULL_SUPPORT)
    if full.any() and not full[mask].all():
        _, (iy, ix) = distance_transform_edt(~full, return_indices=True)
        out = np.where(mask & ~full, out[iy, ix], out)
    return out


def occlusion_change(depth_img: np.ndarray, foot_img: np.ndarray, mask: np.ndarray, profile,
                     footprint: float) -> np.ndarray:
    """(H, W) at each pixel near a depth discontinuity (neighbouring pixels that both hit,
    depths differing by more than DEPTH_JUMP_FOOTPRINTS footprints beyond what the surface's
    slope steps, ``foot_img`` (H, W) footprint x (1 + slope)): the profile's energy,
    as a fraction of Rd, beyond the larger of the distance to it on the image and the step
    across it (the two surfaces are at least that far apart, and what the image shows
    beside a pixel there is not the surface beside it)."""
    from scipy.ndimage import distance_transform_edt
    jump = np.zeros(mask.shape, bool)
    size = np.zeros(mask.shape)
    for axis in (0, 1):
        a = [slice(None)] * 2
        b = [slice(None)] * 2
        a[axis], b[axis] = slice(1, None), slice(None, -1)
        both = mask[tuple(a)] & mask[tuple(b)]
        step = np.abs(depth_img[tuple(a)] - depth_img[tuple(b)])
        # the less steep side's expectation: at an occluding edge the near side is seen
        # grazing (a large slope) and the surface behind it is not
        big = both & (step > DEPTH_JUMP_FOOTPRINTS * np.minimum(foot_img[tuple(a)],
                                                                 foot_img[tuple(b)]))
        jump[tuple(a)] |= big
        jump[tuple(b)] |= big
        size[tuple(a)] = np.maximum(size[tuple(a)], np.where(big, step, 0.0))
        size[tuple(b)] = np.maximum(size[tuple(b)], np.where(big, step, 0.0))
    if not jump.any():
        return np.zeros(mask.shape)
    dist, (iy, ix) = distance_transform_edt(~jump, return_indices=True)
    apart = np.maximum(dist * footprint, size[iy, ix])
    return np.where(mask, energy_beyond(profile, apart.ravel()).reshape(mask.shape), 0.0)


def _bin_of(pixel: np.ndarray, width: int, size: int) -> np.ndarray:
    """The bin (``size`` x ``size`` pixels, row-major) of flat pixel indices."""
    pixel = np.asarray(pixel, np.int64)
    return (pixel // width // size) * (-(-width // size)) + (pixel % width) // size


def predict(frame: PixelFrame, local: np.ndarray, parts: list, pixels: np.ndarray,
            profile, rep: np.ndarray, rep_of: np.ndarray) -> dict:
    """Per pixel of ``pixels`` (the distinct pixels of the shading points): the image-space
    predicted relative changes "irradiance" and "occlusion" (module docstring) as (P,)
    arrays.  ``local`` (P, 3) the pixels' local exitance, ``parts`` its terms per shading
    point (:func:`exact_exitance`): per pixel, the shadow's mean over its shading points
    (``rep_of`` each one's pixel row) and the factors of its first, ``rep``."""
    # on an image binned PREDICTOR_BIN x PREDICTOR_BIN: the profile spans >= 3 pixels of the
    # default scan's (sigma 1.24 mm, 0.37 mm a pixel)
    b = PREDICTOR_BIN
    hb, wb = -(-frame.height // b), -(-frame.width // b)
    binned = _bin_of(pixels, frame.width, b)
    # a shadow's coverage of the pixel, not its first sample's
    parts = [(np.repeat(_image(np.asarray(v, np.float64)[:, None], rep_of, len(pixels))[0], 3,
                        axis=1) if v.ndim == 1 else v[rep], part,
              None if f is None else f[rep]) for v, part, f in parts]
    size, shape = hb * wb, (hb, wb)
    local_img, count = _image(local, binned, size)
    mask = (count > 0).reshape(shape)
    footprint = float(np.median(frame.footprint)) * b

    def img(v):
        return _image(np.asarray(v, np.float64), binned, size)[0].reshape(shape + (3,))
    terms = [(img(v), part, None if f is None else img(f)) for v, part, f in parts]
    p_e = irradiance_change(terms, local_img.reshape(shape + (3,)), mask, footprint)
    dep, _ = _image(np.stack([frame.depth[rep], frame.footprint[rep] * b * (
        1.0 + frame.slope[rep])], 1), binned, size)
    p_occ = occlusion_change(dep[:, 0].reshape(shape), dep[:, 1].reshape(shape), mask, profile,
                             footprint)
    at = _bin_of(pixels, frame.width, b)     # back to the pixels: each takes its bin's
    return {"irradiance": p_e.ravel()[at], "occlusion": p_occ.ravel()[at]}


# --------------------------------------------------------------------------- the whole
def pixel_centroids(rows: np.ndarray, rep_of: np.ndarray, positions: np.ndarray):
    """For the pixel rows ``rows`` (``rep_of`` (Q,) each shading point's pixel row): the
    mean position of each one's shading points (len(rows), 3) and their largest distance
    from it (len(rows),), mm."""
    rows = np.asarray(rows, np.int64)
    where = np.full(int(rep_of.max()) + 1 if len(rep_of) else 0, -1, np.int64)
    where[rows] = np.arange(len(rows))
    pts = np.flatnonzero(where[rep_of] >= 0)
    g = where[rep_of[pts]]
    x = np.asarray(positions, np.float64)[pts]
    count = np.bincount(g, minlength=len(rows)).astype(np.float64)
    centre = np.stack([np.bincount(g, weights=x[:, c], minlength=len(rows)) for c in range(3)],
                      axis=1) / np.maximum(count, 1.0)[:, None]
    spread = np.zeros(len(rows))
    np.maximum.at(spread, g, np.linalg.norm(x - centre[g], axis=1))
    return centre, spread


def adaptive_exitance(points, irradiance, profile, shading: ShadingPoints, *, lights,
                      visibility, options: ExitanceOptions, camera, pixels: np.ndarray,
                      adaptive: AdaptiveOptions = AdaptiveOptions(), shared=None,
                      keys=None, noise: np.ndarray | None = None) -> tuple[np.ndarray, dict]:
    """Exitance (Q, 3) of the adaptive BSSRDF at the shading points seen by ``camera``
    (a CameraConfig) through ``pixels`` (Q,) flat pixel indices (module docstring), and
    stats: the gathers' kernel seconds, the blend weight per shading point ("blend", the
    larger of the two) and per pixel ("blend_image", (H, W)), the predicted changes per
    pixel ("predicted_images", in units of the target), the fractions of shading points and
    of pixels gathered, and the seconds of each part.

    ``visibility``: the mesh's Visibility (shadow rays where ``shading`` carries none).  The
    gathers are :func:`exitance`'s own terms, with the run's ``shared`` octree and shadow
    edges.  ``noise``: the points' irradiance noise; stats["noise"] is then the exitance's
    noise estimate (``exitance``'s ``noise``), its smooth part's noise gathered, interpolated
    and blended as the smooth part is (the exact part and the near field have none)."""
    t0 = time.perf_counter()
    lights = list(lights)
    E = np.asarray(irradiance, np.float32)
    sigma = float(points.info.get("kernel_sigma_mm") or 0.0) or _spacing(points)
    q = np.asarray(shading.positions)
    ng = np.asarray(shading.geo_normals)
    ns = np.asarray(shading.shading_normals)
    frame = pixel_frame(camera, pixels, q, ng)
    pixels, rep, rep_of = pixel_representatives(frame.pixel)
    stats: dict = {"kernel_seconds": 0.0}

    noisy = noise is not None and bool(np.any(noise))

    def term(terms, idx, at=None):
        """exitance()'s ``terms`` at the shading points ``idx`` (or at positions ``at`` with
        their normals), with the run's octree and shadow edges: (M, its noise, None where
        the points have none and for the near terms)."""
        vis_sub = None if shading.visible is None else shading.visible[idx]
        m, st = exitance(points, E, profile, ShadingPoints(q[idx] if at is None else at,
                                                            ns[idx], ng[idx], visible=vis_sub),
                         lights=lights, visibility=visibility, options=options,
                         shared=shared, keys=keys, terms=terms,
                         noise=noise if noisy else None)
        stats["kernel_seconds"] += float(st.get("kernel_seconds", 0.0))
        n = st.get("noise")
        return np.asarray(m, np.float64), None if n is None else np.asarray(n, np.float64)
    # the exact part at every shading point
    parts: list = []
    exact = exact_exitance(profile, shading, lights=lights, visibility=visibility,
                           options=options, sigma=sigma, parts=parts)
    t_local = time.perf_counter() - t0
    # the smooth part sampled on a grid of pixels and interpolated
    t1 = time.perf_counter()
    grid = sample_grid(frame.pixel, frame.width, frame.height,
                       sample_spacing(sigma, float(np.median(frame.footprint))))
    smooth_s, noise_s = term("smooth", grid.points)
    smooth, complete, corners = interpolate(grid, smooth_s, pixels, frame.width)
    smooth_noise = interpolate(grid, noise_s, pixels, frame.width)[0] if noisy else None
    t_sample = time.perf_counter() - t1
    # the predictors
    t2 = time.perf_counter()
    local = smooth + _image(exact, rep_of, len(pixels))[0]
    pred = predict(frame, local, parts, pixels, profile, rep, rep_of)
    whole_s = smooth_s + exact[grid.points]
    floor = DARK_FLOOR * np.maximum(whole_s.mean(axis=0), 1e-30) if len(whole_s) else np.ones(3)
    cell_err = interpolation_error(grid, smooth_s, whole_s, floor)
    pred["interpolation"] = np.where(complete, cell_err[corners].max(axis=1), np.inf)
    p_smooth = np.maximum(pred["interpolation"], pred["occlusion"])
    scale = np.sqrt((local * local).sum(axis=1))
    tau = threshold([p_smooth, pred["irradiance"]], scale, adaptive)
    w_smooth = blend_weight(p_smooth, adaptive, tau)
    w_near = blend_weight(pred["irradiance"], adaptive, tau)
    t_pred = time.perf_counter() - t2
    # the smooth part gathered where its interpolation is predicted to miss: at the pixel's
    # mean position (smooth over a pixel: its error is second order in the pixel's size),
    # at every shading point of a pixel that straddles a depth step
    t3 = time.perf_counter()
    smooth_rows = np.flatnonzero(w_smooth > 0)
    centre, spread = pixel_centroids(smooth_rows, rep_of, q)
    one_surface = spread <= CENTROID_SPREAD * sigma
    at_pixel = smooth_rows[one_surface]
    if len(at_pixel):
        wi = w_smooth[at_pixel, None]
        m, n = term("smooth", rep[at_pixel], at=centre[one_surface])
        smooth[at_pixel] = (1.0 - wi) * smooth[at_pixel] + wi * m
        if noisy:
            smooth_noise[at_pixel] = (1.0 - wi) * smooth_noise[at_pixel] + wi * n
    M = exact + smooth[rep_of]
    M_noise = smooth_noise[rep_of] if noisy else None
    straddle = np.zeros(len(pixels), bool)
    straddle[smooth_rows[~one_surface]] = True
    at_point = np.flatnonzero(straddle[rep_of])
    w_q = w_smooth[rep_of]
    if len(at_point):
        wi = w_q[at_point, None]
        m, n = term("smooth", at_point)
        M[at_point] += wi * (m - smooth[rep_of[at_point]])
        if noisy:
            M_noise[at_point] += wi * (n - smooth_noise[rep_of[at_point]])
    # the near field's edge terms where the shadow is predicted to change the pixel
    near = np.flatnonzero(w_near[rep_of] > 0)
    if len(near):
        M[near] += w_near[rep_of[near], None] * (term("near", near)[0] - exact[near])
    t_gather = time.perf_counter() - t3
    w_pix = np.maximum(w_smooth, w_near)
    size = frame.width * frame.height
    image = np.zeros(size, np.float32)
    image[pixels] = w_pix
    flagged = {f"flagged_{k}": float(np.mean(blend_weight(pred[k], adaptive, tau) > 0))
               for k in PREDICTORS}
    maps = {}
    for k in PREDICTORS:
        maps[k] = np.zeros(size, np.float32)
        maps[k][pixels] = np.minimum(pred[k] / tau, 1e30)
    w = w_pix[rep_of]
    stats.update({"blend": w.astype(np.float32),
                  "noise": None if M_noise is None else M_noise.astype(np.float32),
                  "predicted_images": {k: v.reshape(frame.height, frame.width)
                                       for k, v in maps.items()},
                  "blend_image": image.reshape(frame.height, frame.width),
                  "gathered_fraction": float(np.mean(w > 0)) if len(w) else 0.0,
                  "gathered_pixel_fraction": float(np.mean(w_pix > 0)) if len(w_pix) else 0.0,
                  "smooth_gathered_pixels": int(len(at_pixel)),
                  "smooth_gathered_points": int(len(at_point)),
                  "near_gathered_points": int(len(near)),
                  "threshold": tau, "sample_spacing_pixels": grid.spacing, "sampled_points": len(grid.points),
                  "local_seconds": t_local, "predictor_seconds": t_pred,
                  "sample_gather_seconds": t_sample, "adaptive_gather_seconds": t_gather,
                  **flagged, "seconds": time.perf_counter() - t0})
    return np.nan_to_num(M, nan=0.0, posinf=0.0, neginf=0.0).astype(np.float32), stats
