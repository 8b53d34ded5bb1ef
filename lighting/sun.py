"""The sun of an environment map: found, taken out of the map and sampled as the small disc
of directions it is (docs/science.md §6).

A sunset map's sun is a few pixels (the Venice map's: 4 pixels, peak radiance 2090 against a
median sky of ~1) that carry a large share of the light on the surfaces facing it.  Sampled
as part of the map, a hit's few samples reach the sun or not by chance: its light is the
largest part of the environment-lit images' noise (bench/results/env_noise.json "split").
Taken out, it is lit like a directional light - a fixed number of samples per point, all on
the disc, each with its shadow ray - and the sky that remains is sampled on its own, without
the sun's spike in its distributions.

* :func:`sun_mask` - the map's sun: the pixels within SUN_RADIUS_DEG of its brightest pixel
  that are at least SUN_FRACTION of it, when that pixel is SUN_CONTRAST times the map's
  median luminance or more (a smooth sky has no sun and is left whole).
* :func:`split_sun` - the :class:`SunSplit` of a map: the sky (the map with the sun's pixels
  black, an :class:`~dermis.lighting.environment.EnvironmentMap` of its own) and the
  :class:`Sun`, cached on the map.  The Cycles scenes take the same split
  (cycles/environment.py: the sun becomes a Cycles sun lamp).
* :meth:`Sun.sample` - directions on the sun's pixels and their weights L / pdf: the pixel by
  its share of the sun's sampling mass (the map's own brightness x sin(theta), lighting/
  environment.py), the direction uniform in the pixel's (u, v), so the estimate is the
  integral of the map's own (piecewise constant) sun pixels, unbiased: sun + sky = the whole
  map, exactly in expectation (tests/test_env_sun.py).

Guarded by tests/test_env_sun.py and tests/test_cycles.py (the Cycles lamp).
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from dermis.pipeline.reuse import built_once
from dermis.rendering.color import LUMINANCE

__all__ = ["Sun", "SunSplit", "sun_mask", "split_sun", "SUN_FRACTION", "SUN_RADIUS_DEG",
           "SUN_CONTRAST"]

# The sun's pixels: those within SUN_RADIUS_DEG of the brightest pixel and at least
# SUN_FRACTION of its luminance (the disc and its limb), when that pixel is SUN_CONTRAST times
# the map's median luminance or more.  The solar disc is 0.27 deg in radius; 2 deg leaves room
# for a blurred or coarsely sampled one.  The Venice sunset's sun: 4 pixels, 2.2 % of the
# map's power (docs/cycles.md).
SUN_FRACTION = 0.05
SUN_RADIUS_DEG = 2.0
SUN_CONTRAST = 100.0
# A sun's solid angle at most (sr): a larger bright patch is sky, not a sun.
SUN_MAX_SOLID_ANGLE = 1e-3


def _pixel_geometry(env) -> tuple[np.ndarray, np.ndarray]:
    """(H, W, 3) float64 directions of the map's pixel centres and (H, W) their solid angles."""
    h, w = env.height, env.width
    u = (np.arange(w) + 0.5) / w
    s = (np.arange(h) + 0.5) / h
    uu, ss = np.meshgrid(u, s)
    dirs, sin_t = env._dirs(uu, ss)
    return dirs, sin_t * (2.0 * math.pi / w) * (math.pi / h)


def sun_mask(env) -> np.ndarray | None:
    """(H, W) bool the sun's pixels of an EnvironmentMap (module docstring), or None when the
    map has no pixel standing out (a sky without a sun)."""
    rad = np.asarray(env.radiance, np.float64)
    lum = rad @ np.asarray(LUMINANCE, np.float64)
    peak = np.unravel_index(int(np.argmax(lum)), lum.shape)
    dirs, omega = _pixel_geometry(env)
    near = dirs @ dirs[peak] >= math.cos(math.radians(SUN_RADIUS_DEG))
    sun = near & (lum >= SUN_FRACTION * lum[peak])
    # a sun is a small patch far brighter than the sky; a smooth sky is not one
    if (not sun.any() or omega[sun].sum() > SUN_MAX_SOLID_ANGLE
            or lum[peak] < SUN_CONTRAST * float(np.median(lum))):
        return None
    return sun


@dataclass
class Sun:
    """The sun's pixels of a map and how they are sampled (module docstring).

    rows, cols : (P,) int64 its pixels; radiance : (P, 3) float32 theirs; cdf : (P,) float64
    the cumulative share of each pixel in the sun's sampling mass; pmf : (P,) float64 the
    map's sampling pmf of each pixel (lighting/environment.py); irradiance : (3,) float64 the
    sun's irradiance on a surface facing it (sum of radiance x solid angle); direction : (3,)
    float64 unit, towards the sun (the luminance-power-weighted mean of its pixels);
    angle_deg : the angular diameter of a disc of its solid angle; share : its share of the
    whole map's irradiance (luminance) on a surface facing it
    """

    rows: np.ndarray
    cols: np.ndarray
    radiance: np.ndarray
    cdf: np.ndarray
    pmf: np.ndarray
    irradiance: np.ndarray
    direction: np.ndarray
    angle_deg: float
    env: object
    share: float = 1.0

    def sample(self, u: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Directions and weights L / pdf for uniform numbers ``u`` (..., 3) in [0, 1): u[..., 0]
        picks the pixel through the sun's CDF, u[..., 1:] the point in it (row, column
        fractions).  Returns (..., 3) float32 unit directions and (..., 3) float32 weights
        (radiance x sr); E[weight x g(direction)] = the integral of g L over the sun's pixels."""
        env = self.env
        shape = np.shape(u)[:-1]
        u = np.asarray(u, np.float64).reshape(-1, 3)
        i = np.minimum(np.searchsorted(self.cdf, u[:, 0] * self.cdf[-1], side="right"),
                       len(self.cdf) - 1)
        row, col = self.rows.take(i), self.cols.take(i)
        d, sin_t = env._dirs((col + u[:, 2]) / env.width, (row + u[:, 1]) / env.height)
        # pdf over solid angle: q H W / (2 pi^2 sin theta), q the pixel's share of the sun
        q = self.pmf.take(i) / self.cdf[-1]
        inv_pdf = 2.0 * math.pi * math.pi * sin_t / (q * env.height * env.width)
        w = self.radiance.take(i, axis=0) * inv_pdf[:, None]
        return (d.astype(np.float32).reshape(shape + (3,)),
                w.astype(np.float32).reshape(shape + (3,)))


@dataclass
class SunSplit:
    """A map split into its ``sky`` (EnvironmentMap, the sun's pixels black) and its ``sun``
    (:class:`Sun`)."""

    sky: object
    sun: Sun


def split_sun(env) -> SunSplit | None:
    """The sun and the sky of an EnvironmentMap (module docstring), or None when the map has no
    sun (:func:`sun_mask`); built once per map."""
    return built_once(env, "_sun_split", lambda: _split_sun(env))


def _split_sun(env) -> SunSplit | None:
    from dermis.lighting.environment import EnvironmentMap
    split = None
    sun = sun_mask(env) if not env.black else None
    if sun is not None:
        rad = np.asarray(env.radiance, np.float64)
        lum = rad @ np.asarray(LUMINANCE, np.float64)
        dirs, omega = _pixel_geometry(env)
        irradiance = (rad * omega[..., None])[sun].sum(axis=0)
        d = ((lum * omega)[..., None] * dirs)[sun].sum(axis=0)
        d /= np.linalg.norm(d)
        angle = 2.0 * math.degrees(math.acos(1.0 - omega[sun].sum() / (2.0 * math.pi)))
        rest = rad.copy()
        rest[sun] = 0.0
        sky = EnvironmentMap(rest.astype(np.float32), name=f"{env.name} (sky)")
        sky.rotation = env.rotation
        rows, cols = np.nonzero(sun)
        pmf = env.pmf.reshape(env.height, env.width)[rows, cols].astype(np.float64)
        whole = (lum * omega * np.maximum(dirs @ d, 0.0)).sum()
        share = float(irradiance @ np.asarray(LUMINANCE, np.float64) / whole) if whole > 0 \
            else 1.0
        if pmf.sum() > 0:
            split = SunSplit(sky, Sun(rows.astype(np.int64), cols.astype(np.int64),
                                      env.radiance[rows, cols], np.cumsum(pmf), pmf,
                                      irradiance, d, angle, env, share))
    return split
