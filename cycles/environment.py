"""An environment map for Cycles: its sun as a lamp, the rest as the world.

Cycles samples the world from an importance map it builds by point-sampling the world
shader on a lat-long grid; a sun a few map pixels wide is mostly missed, and then reached
only by BSDF samples: at a few hundred samples per pixel, practically never.  Measured on a
Lambert plate facing the procedural sunset's sun (0.534 deg wide), Cycles gave 0.2416 /
0.2645 / 0.2774 of the exact 0.2884 (red radiance) at importance maps 2048 / 4096 / 8192
wide, the last at 18 s a render (docs/cycles.md).  So the map's sun, the pixels within
``SUN_RADIUS_DEG`` of its brightest pixel that are at least ``SUN_FRACTION`` of it (when
that pixel is ``SUN_CONTRAST`` times the median or more), leaves
the map and becomes a Cycles sun lamp of the same irradiance (sum over its pixels of
radiance x solid angle), direction (their power-weighted mean) and angular diameter (that
of a disc of their solid angle).  A small disc's irradiance on any surface it lights
entirely is that of its pixels to within the cosine's change across it (< 1e-4 for a
0.5 deg sun); its shadows are a disc's.  The rest of the map stays in the world, looked up
pixel by pixel (:func:`dermis.cycles.scene_build.add_world`).
"""
from __future__ import annotations

import math

import numpy as np

from dermis.lighting.environment import environment_map
from dermis.rendering.color import LUMINANCE

__all__ = ["split_sun", "SUN_FRACTION", "SUN_RADIUS_DEG", "SUN_CONTRAST"]

SUN_FRACTION = 0.05     # of the brightest pixel's luminance (the sun's disc and limb)
SUN_RADIUS_DEG = 2.0    # around the brightest pixel (the solar disc is 0.27 deg in radius)
SUN_CONTRAST = 100.0    # its peak over the map's median luminance, at least


def split_sun(light) -> tuple[np.ndarray, dict | None]:
    """(H, W, 3) float32 radiance without the sun, and the sun as a light dict
    (``type`` "directional", ``direction`` towards the sun, ``intensity`` its irradiance at
    normal incidence, ``angle_deg`` its angular diameter), or None when the map has no
    pixel standing out (a sky without a sun is left whole)."""
    env = environment_map(light)
    rad = np.asarray(env.radiance, np.float64)
    h, w = rad.shape[:2]
    lum = rad @ np.asarray(LUMINANCE, np.float64)
    peak = np.unravel_index(int(np.argmax(lum)), lum.shape)
    u = (np.arange(w) + 0.5) / w
    s = (np.arange(h) + 0.5) / h
    uu, ss = np.meshgrid(u, s)
    dirs, sin_t = env._dirs(uu, ss)
    omega = sin_t * (2.0 * math.pi / w) * (math.pi / h)          # solid angle per pixel
    near = dirs @ dirs[peak] >= math.cos(math.radians(SUN_RADIUS_DEG))
    sun = near & (lum >= SUN_FRACTION * lum[peak])
    # a sun is a small patch far brighter than the sky (the Venice map's: 4 pixels, peak
    # 2090 against a median sky of ~1, 2.2 % of the map's power); a smooth sky is not one
    if (not sun.any() or omega[sun].sum() > 1e-3
            or lum[peak] < SUN_CONTRAST * float(np.median(lum))):
        return rad.astype(np.float32), None
    irradiance = (rad * omega[..., None])[sun].sum(axis=0)
    d = ((lum * omega)[..., None] * dirs)[sun].sum(axis=0)
    d /= np.linalg.norm(d)
    angle = 2.0 * math.degrees(math.acos(1.0 - omega[sun].sum() / (2.0 * math.pi)))
    rest = rad.copy()
    rest[sun] = 0.0
    return rest.astype(np.float32), {
        "type": "directional", "name": f"{light.name}_sun", "direction": d.tolist(),
        "intensity": irradiance.tolist(), "angle_deg": angle, "pixels": int(sun.sum())}
