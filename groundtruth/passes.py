"""Rendering the exported head: sample passes of bounded size, and the pixels' first hits.

A Mitsuba render of many samples per pixel is split into calls of at most :data:`MAX_LANES`
samples (a wavefront of that many paths), each with its own seed, and the running mean is
kept at chosen sample counts (the reference's noise-vs-spp curve, docs/ground-truth.md).
:func:`pixel_hits` casts Mitsuba's own pixel-centre camera rays, the same rays as dermis's
(tests/test_reference.py), to find the face every reference pixel sees.
:func:`render_two_seeds` renders the reference twice with independent seeds, the pair its
own noise is measured on (:mod:`dermis.groundtruth.noise`).
"""
from __future__ import annotations

import time
from dataclasses import dataclass
from typing import Callable

import numpy as np

from dermis.groundtruth.noise import curve_checkpoints

__all__ = ["MAX_LANES", "render_passes", "pixel_hits", "TwoSeeds", "render_two_seeds"]

# Samples traced by one render call (wavefront size): bounds the LLVM variant's memory at a
# few GB (measured ~0.5 kB per lane for volpathmis in skin).
MAX_LANES = 1 << 21


def render_passes(mi, scene, *, spp: int, seed: int, checkpoints=(),
                  progress: Callable[[int], None] | None = None, integrator=None
                  ) -> tuple[np.ndarray, list, float]:
    """Render ``spp`` samples per pixel in calls of at most :data:`MAX_LANES` samples.

    Returns the (H, W, 3) float64 mean image, a list of (spp so far, mean image so far) at
    each of ``checkpoints`` (sample counts; the final count is always included) and the
    seconds spent.  Call k uses seed ``seed * 65536 + k`` (independent streams; seeds < 65536).
    ``progress(samples_done)`` is called after every call.  ``integrator``: a loaded Mitsuba
    integrator replacing the scene's own (None: the scene's).
    """
    film = scene.sensors()[0].film()
    w, h = (int(c) for c in film.crop_size())
    per_call = max(1, min(int(spp), MAX_LANES // max(w * h, 1)))
    marks = sorted({int(c) for c in checkpoints if 0 < int(c) < spp} | {int(spp)})
    acc = np.zeros((h, w, 3), np.float64)
    done, k, out = 0, 0, []
    t0 = time.perf_counter()
    for mark in marks:
        while done < mark:
            n = min(per_call, mark - done)
            img = np.asarray(mi.render(scene, spp=n, seed=int(seed) * 65536 + k,
                                       integrator=integrator), dtype=np.float64)
            acc += img[..., :3] * n
            done += n
            k += 1
            if progress is not None:
                progress(done)
        out.append((done, acc / done))
    return acc / max(done, 1), out, time.perf_counter() - t0


def pixel_hits(mi, scene, *, width: int, height: int) -> tuple[np.ndarray, np.ndarray]:
    """Mitsuba's camera rays through the pixel centres: (H, W) hit mask and (H, W) int64
    primitive (face) index of the first shape hit (-1 where none)."""
    sensor = scene.sensors()[0]
    j, i = np.meshgrid(np.arange(width), np.arange(height))
    pos = mi.Point2f(((j + 0.5) / width).ravel().astype(np.float32),
                     ((i + 0.5) / height).ravel().astype(np.float32))
    ray, _ = sensor.sample_ray(0.0, 0.0, pos, mi.Point2f(0.5, 0.5))
    si = scene.ray_intersect(ray)
    valid = np.asarray(si.is_valid(), bool).reshape(height, width)
    prim = np.asarray(si.prim_index, np.int64).reshape(height, width)
    return valid, np.where(valid, prim, -1)


@dataclass
class TwoSeeds:
    """Two independent renders of one scene and the pixels they cover.

    hit : (H, W) bool, a pixel-centre ray hits the head; prim : (H, W) int64 face it hits (-1)
    img_a, img_b : (H, W, 3) float64 mean images of seeds 2 seed and 2 seed + 1
    curve_a, curve_b : their (spp so far, mean image so far) at :func:`curve_checkpoints`
    seconds : time spent rendering both
    """

    hit: np.ndarray
    prim: np.ndarray
    img_a: np.ndarray
    img_b: np.ndarray
    curve_a: list
    curve_b: list
    seconds: float


def render_two_seeds(mi, scene, *, width: int, height: int, spp: int, seed: int,
                     progress: Callable[[float], None] | None = None) -> TwoSeeds:
    """Render ``scene`` with ``spp`` samples per pixel for each of the seeds 2 ``seed`` and
    2 ``seed`` + 1 (:func:`render_passes`); ``progress(fraction of both done)``."""
    hit, prim = pixel_hits(mi, scene, width=width, height=height)
    marks = curve_checkpoints(spp)
    total = 2 * spp

    def part(offset):
        return (lambda n: progress((offset + n) / total)) if progress else None

    img_a, curve_a, t_a = render_passes(mi, scene, spp=spp, seed=2 * seed,
                                        checkpoints=marks, progress=part(0))
    img_b, curve_b, t_b = render_passes(mi, scene, spp=spp, seed=2 * seed + 1,
                                        checkpoints=marks, progress=part(spp))
    return TwoSeeds(hit, prim, img_a, img_b, curve_a, curve_b, t_a + t_b)
