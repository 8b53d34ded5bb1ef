"""The BSSRDF's local limit: the profile's total reflectance applied where the light enters,
M(x) = Rd E(x), no transport along the surface (docs/science.md §4 "Local limit").

Where the irradiance is uniform over the profile's reach on a flat surface thicker than the
reach, the gather returns exactly this: the "energy" table integrates to Rd
(``subsurface/profile_table.py``).  Everywhere else the difference between the full BSSRDF
and this limit is what subsurface transport does to the image (the requirement table's
"subsurface transport" effect, reports/requirements.py); it is the BSSRDF as a Lambertian
BRDF of albedo Rd, behind the same Fresnel exit and surface term.

E(x) is the irradiance the pixel's own light evaluation gives, taken as the full BSSRDF's
near field takes it (``subsurface/near_field.py``):

* point and directional lights: C(x) V(x), the light's entering irradiance at the shading
  point (shading normal, entry transmittance) and its shadow ray (``ShadingPoints.visible``,
  the shared visibility's; traced where absent);
* disc and environment lights, and indirect light: the points' irradiance of those lights
  interpolated at the shading point with the gather's Gaussian (normalised: Shepard 1968,
  ``subsurface/interpolation.py``), one query per pixel (the interpolation varies over sigma,
  several pixels).

Bound against the smoothed irradiance.  The gather reconstructs the points' irradiance with a
Gaussian of width sigma; on a region where the irradiance is uniform over the profile's reach
the two agree, and where it varies the pixel's own C(x) differs from the reconstruction by
at most the variation of C over the reach: |Rd C(x) - gather| <= Rd max_{|y - x| < reach}
|C(y) - C(x)| (the profile is non-negative and integrates to Rd).  That variation is what
``subsurface/adaptive.py``'s predictor estimates.
"""
from __future__ import annotations

import time

import numpy as np

from dermis.subsurface.exitance import ExitanceOptions, ShadingPoints
from dermis.subsurface.interpolation import interpolate_points
from dermis.subsurface.near_field import SHARP_LIGHTS

__all__ = ["sharp_irradiance", "soft_irradiance", "pixel_representatives",
           "local_limit_exitance"]


def sharp_irradiance(shading: ShadingPoints, light, k: int, visibility, transmittance):
    """C(x) (Q, 3) float32 and V(x) (Q,) of one point or directional light (the ``k``-th of
    the condition's) at the shading points, as ``shadow_edges.sharp_near_field`` takes them.
    In float32, with the horizon as a factor (not a selection): a pass over the camera
    samples' arrays costs what a BRDF evaluation's does."""
    from dermis.lighting.emitters import sample_lights
    x = np.asarray(shading.positions, np.float32)
    ns = np.asarray(shading.shading_normals, np.float32)
    ng = np.asarray(shading.geo_normals, np.float32)
    ls = sample_lights(light, x, ng)
    wi, wt, dist = ls.directions[:, 0], ls.weights[:, 0], ls.distance[:, 0]
    norm = np.sqrt(np.einsum("ij,ij->i", ns, ns))
    cos = np.einsum("ij,ij->i", wi, ns) / np.maximum(norm, np.float32(1e-30))
    live = (cos > 0) & (wt.max(axis=1) > 0)
    if not live.any():
        return np.zeros((len(x), 3), np.float32), np.zeros(len(x))
    c = wt * (cos * live)[:, None]
    if transmittance is not None:
        c *= np.asarray(transmittance(np.where(live, cos, np.float32(1.0))), np.float32)
    if shading.visible is not None:
        seen = np.asarray(shading.visible[:, k], bool) & live
    else:
        seen = np.zeros(len(x), bool)
        seen[live] = ~visibility.occluded(x[live], ng[live], wi[live], dist[live])
    return c, seen


def pixel_representatives(pixels: np.ndarray):
    """(distinct pixels (P,), the first shading point of each (P,), each shading point's
    row among them (Q,)) for ``pixels`` (Q,) flat pixel indices."""
    pixels = np.asarray(pixels, np.int64)
    if len(pixels) and bool(np.all(pixels[1:] >= pixels[:-1])):   # the renderer's order
        first = np.flatnonzero(np.r_[True, pixels[1:] != pixels[:-1]])
        rep_of = np.cumsum(np.r_[False, pixels[1:] != pixels[:-1]])
        return pixels[first], first, rep_of
    order = np.argsort(pixels, kind="stable")
    distinct, first = np.unique(pixels[order], return_index=True)
    return distinct, order[first], np.searchsorted(distinct, pixels)


def soft_irradiance(points, irradiance, sharp, visibility, options: ExitanceOptions):
    """(N, 3) the points' irradiance less that of the ``sharp`` lights (what disc,
    environment and indirect light give them)."""
    E = np.asarray(irradiance, np.float64)
    if not sharp:
        return E
    from dermis.lighting.irradiance import irradiance as point_irradiance
    e_sharp = point_irradiance(points.positions, points.normals, sharp, visibility.occluded,
                               transmittance=options.transmittance)
    return np.maximum(E - e_sharp, 0.0)


def local_limit_exitance(points, irradiance, profile, shading: ShadingPoints, *, lights,
                         visibility, options: ExitanceOptions, pixels=None, camera=None,
                         shared=None, keys=None,
                         noise: np.ndarray | None = None) -> tuple[np.ndarray, dict]:
    """M = Rd E(x) (Q, 3) at the shading points (module docstring) and stats (seconds).
    ``pixels`` (Q,): the shading points' flat pixel indices (the soft lights' interpolation
    runs once per pixel); None: once per shading point.  ``noise``: the points' irradiance
    noise, interpolated as E is into stats["noise"], Rd times it (``exitance``'s
    ``noise``; the point and directional lights' part has none)."""
    t0 = time.perf_counter()
    lights = list(lights)
    rd = np.asarray(profile.Rd, np.float64)
    sharp = [l for l in lights if l.type in SHARP_LIGHTS]
    soft = [l for l in lights if l.type not in SHARP_LIGHTS]
    E = np.zeros((len(shading.positions), 3))
    for k, light in enumerate(sharp):
        c, v = sharp_irradiance(shading, light, k, visibility, options.transmittance)
        E += c * v[:, None]
    kernel = 0.0
    noise_m = None
    if soft or options.indirect:
        e_soft = soft_irradiance(points, irradiance, sharp, visibility, options)
        q = np.asarray(shading.positions)
        n = np.asarray(shading.geo_normals)
        if pixels is None:
            rep, rep_of = np.arange(len(q)), np.arange(len(q))
        else:
            _, rep, rep_of = pixel_representatives(pixels)
        sigma = float(points.info.get("kernel_sigma_mm") or 0.0) or float(np.sqrt(
            np.sum(points.areas) / max(len(points.areas), 1)))
        it = interpolate_points(points.positions, points.normals, points.areas,
                                e_soft.astype(np.float32), q[rep], n[rep], sigma,
                                env=options.env)
        E += np.asarray(it.values[:, :3], np.float64)[rep_of]
        kernel = it.seconds
        if noise is not None and np.any(noise):
            nt = interpolate_points(points.positions, points.normals, points.areas,
                                    np.asarray(noise, np.float32), q[rep], n[rep], sigma,
                                    env=options.env)
            noise_m = (rd[None, :] * np.asarray(nt.values[:, :3], np.float64)[rep_of]
                       ).astype(np.float32)
            kernel += nt.seconds
    M = np.nan_to_num(rd[None, :] * E, nan=0.0, posinf=0.0, neginf=0.0).astype(np.float32)
    return M, {"seconds": time.perf_counter() - t0, "kernel_seconds": kernel,
               "local_seconds": time.perf_counter() - t0, "noise": noise_m}
