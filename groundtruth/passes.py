"""Rendering the exported head: sample passes of bounded size, and the pixels' first hits.

A Mitsuba render of many samples per pixel is split into calls of at most :data:`MAX_LANES`
samples (a wavefront of that many paths), each with its own seed (the reference's variants,
:mod:`dermis.groundtruth.variants`; the reference itself traces its pixels in passes,
:mod:`dermis.groundtruth.progressive`).  :func:`pixel_hits` casts Mitsuba's own pixel-centre
camera rays, the same rays as dermis's (tests/test_reference.py), to find the face every
reference pixel sees.
"""
from __future__ import annotations

import time
from typing import Callable

import numpy as np


__all__ = ["MAX_LANES", "render_passes", "pixel_hits"]

# Samples traced by one render call (wavefront size): bounds the LLVM variant's memory at a
# few GB (measured ~0.5 kB per lane for volpathmis in skin).
MAX_LANES = 1 << 21


def render_passes(mi, scene, *, spp: int, seed: int,
                  progress: Callable[[int], None] | None = None, integrator=None
                  ) -> tuple[np.ndarray, float]:
    """Render ``spp`` samples per pixel in calls of at most :data:`MAX_LANES` samples.

    Returns the (H, W, 3) float64 mean image and the seconds spent.  Call k uses seed
    ``seed * 65536 + k`` (independent streams; seeds < 65536).
    ``progress(samples_done)`` is called after every call.  ``integrator``: a loaded Mitsuba
    integrator replacing the scene's own (None: the scene's).
    """
    film = scene.sensors()[0].film()
    w, h = (int(c) for c in film.crop_size())
    per_call = max(1, min(int(spp), MAX_LANES // max(w * h, 1)))
    acc = np.zeros((h, w, 3), np.float64)
    done, k = 0, 0
    t0 = time.perf_counter()
    while done < spp:
        n = min(per_call, int(spp) - done)
        img = np.asarray(mi.render(scene, spp=n, seed=int(seed) * 65536 + k,
                                   integrator=integrator), dtype=np.float64)
        acc += img[..., :3] * n
        done += n
        k += 1
        if progress is not None:
            progress(done)
    return acc / max(done, 1), time.perf_counter() - t0


def pixel_hits(mi, scene, *, width: int, height: int, sensor=None
               ) -> tuple[np.ndarray, np.ndarray]:
    """Mitsuba's camera rays through the pixel centres of ``sensor`` (None: the scene's
    first): (H, W) hit mask and (H, W) int64 primitive (face) index of the first shape hit
    (-1 where none)."""
    sensor = scene.sensors()[0] if sensor is None else sensor
    j, i = np.meshgrid(np.arange(width), np.arange(height))
    pos = mi.Point2f(((j + 0.5) / width).ravel().astype(np.float32),
                     ((i + 0.5) / height).ravel().astype(np.float32))
    ray, _ = sensor.sample_ray(0.0, 0.0, pos, mi.Point2f(0.5, 0.5))
    si = scene.ray_intersect(ray)
    valid = np.asarray(si.is_valid(), bool).reshape(height, width)
    prim = np.asarray(si.prim_index, np.int64).reshape(height, width)
    return valid, np.where(valid, prim, -1)
