"""The gather sampled on a coarse grid of pixels and interpolated between them, with the
interpolation's error estimated from the samples (``subsurface/adaptive.py``; docs/science.md
§4 "Adaptive gather").

What is interpolated is the smooth part of the exitance (``exitance(terms="smooth")``): all
but the near field of point and directional lights, which the adaptive model evaluates at
every shading point.  That part is the points' irradiance reconstructed
with the gather's Gaussian of width sigma and convolved with the profile (its far part,
beyond 2 sigma, for point and directional light; all of it for disc, environment and
indirect light), so it varies over sigma and more: sampled every ``SAMPLE_SIGMAS`` sigma on the
image, it is interpolated bilinearly between the samples (the centre pixels of square cells;
Ward, Rubinstein & Clear 1988 interpolate irradiance between sparse samples the same way).

Error estimate.  Bilinear interpolation of a function with second difference d2 between
samples (d2 = f'' h^2) is off by at most |d2| / 8 midway between them; the estimate takes
|d2| / 4 (twice that: the cross term and the higher orders), per channel, along both image
axes, relative to the whole exitance at the sample, and a pixel takes the largest of the
four cells it is interpolated from.  Where a sample's neighbour is missing (the head's outline, a depth step,
the image border) the one-sided first difference takes the second difference's place:
large where the exitance varies, so such pixels are gathered.
"""
from __future__ import annotations

import numpy as np

__all__ = ["SAMPLE_SIGMAS", "sample_spacing", "SampleGrid", "sample_grid", "interpolate",
           "interpolation_error", "INTERPOLATION_FACTOR"]

# Samples every SAMPLE_SIGMAS sigma on the image: 3 pixels of the default view (sigma
# 1.24 mm, 0.37 mm a pixel), 9 of a close-up at 8 px/mm (cut to MAX_SPACING).  At 1.5
# sigma the interpolation estimate gathered more (one run each at load 10: point light 21 %
# of the pixels against 16 %, disc 68 % against 53 %, lips close-up 99 % against 96 %) and
# the point light's image cost 1.14 of the full BSSRDF's CPU seconds against 0.93.
SAMPLE_SIGMAS = 1.0
# At most this many pixels between samples (0.5 mm at 8 px/mm): in a close-up sigma spans
# ~10 pixels, and the surface folds within it.  With samples a sigma apart (9 pixels) the
# lips close-up left a band below the lower lip ungathered, several per cent from the full
# BSSRDF, and gathered 93 % of the pixels; at 4, 52 % and no band (at 3, 30 %).
MAX_SPACING = 4
# The error estimate per unit second difference: twice bilinear interpolation's midpoint
# error of a quadratic, 1/8 (module docstring); with 1/8 the lips close-up (disc light)
# came out 2.8 % rRMSE from the full BSSRDF, with 1/4 0.85 % (bench/bench_bssrdf_adaptive.py).
INTERPOLATION_FACTOR = 0.25


def sample_spacing(sigma: float, footprint: float) -> int:
    """Pixels between samples: SAMPLE_SIGMAS sigma on the image at ``footprint`` mm a pixel,
    at least 2 and at most MAX_SPACING."""
    return max(2, min(MAX_SPACING, int(SAMPLE_SIGMAS * sigma / max(footprint, 1e-12))))


class SampleGrid:
    """Samples at the centre pixel (row i s + s // 2, column j s + s // 2) of each s x s cell:
    ``shape`` (hc, wc) cells, ``cells`` (S,) flat cell index of each sample, ``points`` (S,)
    the shading point (one of the centre pixel's) it is taken at."""

    def __init__(self, spacing: int, shape: tuple, cells: np.ndarray, points: np.ndarray):
        self.spacing, self.shape, self.cells, self.points = spacing, shape, cells, points


def sample_grid(pixel: np.ndarray, width: int, height: int, spacing: int) -> SampleGrid:
    """The SampleGrid of shading points seen through flat pixel indices ``pixel`` (Q,)."""
    s = int(spacing)
    pixel = np.asarray(pixel, np.int64)
    row, col = pixel // width, pixel % width
    centre = (row % s == s // 2) & (col % s == s // 2)
    idx = np.flatnonzero(centre)
    hc, wc = -(-height // s), -(-width // s)
    cell = (row[idx] // s) * wc + col[idx] // s
    cells, first = np.unique(cell, return_index=True)
    return SampleGrid(s, (hc, wc), cells, idx[first])


def _coords(pixels: np.ndarray, width: int, spacing: int, n: int):
    """Grid coordinates of pixels along one axis: (lower sample index (P,), fraction (P,) in
    [0, 1]).  Past the outermost samples the fraction is held at 0 or 1 (the nearest
    sample's value, whose error the one-sided first difference of
    :func:`interpolation_error` bounds): an extrapolated exitance can be negative, an
    interpolated one cannot."""
    u = (pixels - spacing // 2) / spacing
    i0 = np.clip(np.floor(u).astype(np.int64), 0, max(n - 2, 0))
    return i0, np.clip(u - i0, 0.0, 1.0)


def interpolate(grid: SampleGrid, values: np.ndarray, pixels: np.ndarray, width: int):
    """Bilinear interpolation of per-sample ``values`` (S, k) at flat pixel indices
    ``pixels`` (P,): ((P, k) values, each a convex combination of its four samples, (P,)
    bool whether all four samples exist, (P, 4) their flat cell indices)."""
    hc, wc = grid.shape
    v = np.zeros((hc * wc, values.shape[1]))
    have = np.zeros(hc * wc, bool)
    v[grid.cells] = values
    have[grid.cells] = True
    pixels = np.asarray(pixels, np.int64)
    r0, fr = _coords(pixels // width, width, grid.spacing, hc)
    c0, fc = _coords(pixels % width, width, grid.spacing, wc)
    r1, c1 = np.minimum(r0 + 1, hc - 1), np.minimum(c0 + 1, wc - 1)
    corners = np.stack([r0 * wc + c0, r0 * wc + c1, r1 * wc + c0, r1 * wc + c1], axis=1)
    wts = np.stack([(1 - fr) * (1 - fc), (1 - fr) * fc, fr * (1 - fc), fr * fc], axis=1)
    out = np.einsum("pk,pkc->pc", wts, v[corners])
    ok = have[corners].all(axis=1) & (hc > 1) & (wc > 1)
    return out, ok, corners


def interpolation_error(grid: SampleGrid, values: np.ndarray, scale: np.ndarray,
                        floor: np.ndarray) -> np.ndarray:
    """(hc * wc,) the relative error estimate of interpolating ``values`` (S, 3) from each
    cell's sample (module docstring; inf where a cell has no sample), relative to ``scale``
    (S, 3) there (the whole exitance) floored at ``floor`` (3,)."""
    hc, wc = grid.shape
    g = np.zeros((hc, wc, 3))
    ref = np.zeros((hc, wc, 3))
    have = np.zeros((hc, wc), bool)
    g.reshape(-1, 3)[grid.cells] = values
    ref.reshape(-1, 3)[grid.cells] = np.abs(scale)
    have.reshape(-1)[grid.cells] = True
    err = np.zeros((hc, wc))
    for axis in (0, 1):
        gp = np.pad(g, [(1, 1) if a == axis else (0, 0) for a in range(2)] + [(0, 0)])
        hp = np.pad(have, [(1, 1) if a == axis else (0, 0) for a in range(2)])
        lo = [slice(None)] * 2
        hi = [slice(None)] * 2
        lo[axis], hi[axis] = slice(0, -2), slice(2, None)
        a, b = gp[tuple(lo)], gp[tuple(hi)]
        ha, hb = hp[tuple(lo)], hp[tuple(hi)]
        d2 = np.where((ha & hb)[..., None], a + b - 2.0 * g, 0.0)
        one = np.where(ha[..., None], np.abs(a - g), 0.0)
        one = np.maximum(one, np.where(hb[..., None], np.abs(b - g), 0.0))
        d = np.where((ha & hb)[..., None], np.abs(d2), one)
        if (~(ha | hb)).any() and min(hc, wc) > 1:
            d = np.where((~(ha | hb))[..., None], np.inf, d)
        err = np.maximum(err, (INTERPOLATION_FACTOR * d / np.maximum(
            ref, floor[None, None, :])).max(axis=2))
    err[~have] = np.inf
    return err.ravel()
