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
pixel by pixel (:func:`dermis.cycles.scene_build.add_world`).  The split is the renderer's
own (lighting/sun.py :func:`~dermis.lighting.sun.split_sun`), so both light the face with the
same sun and the same sky.
"""
from __future__ import annotations

import numpy as np

from dermis.lighting.environment import environment_map
from dermis.lighting.sun import SUN_CONTRAST, SUN_FRACTION, SUN_RADIUS_DEG
from dermis.lighting.sun import split_sun as split_map

__all__ = ["split_sun", "SUN_FRACTION", "SUN_RADIUS_DEG", "SUN_CONTRAST"]


def split_sun(light) -> tuple[np.ndarray, dict | None]:
    """(H, W, 3) float32 radiance without the sun, and the sun as a light dict
    (``type`` "directional", ``direction`` towards the sun, ``intensity`` its irradiance at
    normal incidence, ``angle_deg`` its angular diameter), or None when the map has no
    pixel standing out (a sky without a sun is left whole)."""
    env = environment_map(light)
    split = split_map(env)
    if split is None:
        return np.asarray(env.radiance, np.float32), None
    sun = split.sun
    return split.sky.radiance, {
        "type": "directional", "name": f"{light.name}_sun", "direction": sun.direction.tolist(),
        "intensity": sun.irradiance.tolist(), "angle_deg": sun.angle_deg,
        "pixels": int(len(sun.rows))}
