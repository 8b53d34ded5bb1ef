"""Stratified uniform numbers: per point, and spread over the sub-pixel samples of a pixel.

* :func:`stratified_2d` - (n, s, 2) points in [0, 1)^2 per point: a jittered grid when s is
  a square, Latin hypercube strata otherwise (Shirley 1991, "Discrepancy as a quality
  measure for sample distributions"); the disc light's points, the environment light's
  cosine and lobe samples (lighting/emitters.py) and the camera's sub-pixel offsets
  (lighting/visibility.py ``subpixel_offsets``).
* :class:`PixelStrata` - renderers spread a pixel's S light samples over its camera samples
  (``share``) and stratify them over the whole pixel (Kollig & Keller 2002, "Efficient
  multidimensional sampling").

Guarded by tests/test_antialias.py (sub-pixel samples stratified and seeded) and, through the
renders that share light samples over a pixel, tests/test_render.py.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

__all__ = ["stratified_2d", "PixelStrata"]


def stratified_2d(rng: np.random.Generator, n: int, s: int) -> np.ndarray:
    """(n, s, 2) points in [0, 1)^2: a jittered grid if s is a square, else Latin hypercube."""
    m = int(round(math.sqrt(s)))
    jitter = rng.random((n, s, 2))
    if m * m == s:
        k = np.arange(s)
        jitter += np.stack([k % m, k // m], axis=-1).astype(np.float64)   # the cell
        jitter /= m
        return jitter
    # Latin hypercube: each axis stratified, strata paired by an independent permutation
    perm = np.argsort(rng.random((n, s)), axis=1)
    ax0 = (np.arange(s)[None, :] + jitter[..., 0]) / s
    ax1 = (perm + jitter[..., 1]) / s
    return np.stack([ax0, ax1], axis=-1)


def _hash_u64(x: np.ndarray) -> np.ndarray:
    """splitmix64 finaliser (Steele, Lea & Flood 2014) of uint64 values: a fixed, seedable
    integer hash, the same for a pixel wherever its samples fall in a batch."""
    z = x.astype(np.uint64) + np.uint64(0x9E3779B97F4A7C15)
    z ^= z >> np.uint64(30)
    z *= np.uint64(0xBF58476D1CE4E5B9)
    z ^= z >> np.uint64(27)
    z *= np.uint64(0x94D049BB133111EB)
    z ^= z >> np.uint64(31)
    return z


@dataclass(frozen=True)
class PixelStrata:
    """The sub-pixel samples of pixels that share the pixels' light samples.

    A disc or environment light's T = s x share strata per pixel (s per sub-pixel sample) are
    dealt to the pixel's ``share`` sub-samples like a comb: sub-sample j takes stratum
    share k + (j + r) mod share of each group k, with r a per-pixel random rotation (hashed
    from ``seed`` and the pixel).  Every sub-sample then draws a uniformly random one of
    ``share`` stratum sets, so each sub-sample's estimate stays unbiased (its integrand
    differs from its neighbours'), while the pixel's samples fill all T strata: the pixel is
    stratified as if one point drew all T (padding with decorrelating rotations, as in Kollig
    & Keller 2002, "Efficient multidimensional sampling").

    pixel : (N,) int pixel index of each point; sub : (N,) int in [0, share); share : int
    """

    pixel: np.ndarray
    sub: np.ndarray
    share: int
    seed: int = 0

    def __getitem__(self, sl) -> "PixelStrata":
        return PixelStrata(self.pixel[sl], self.sub[sl], self.share, self.seed)

    def strata(self, s: int, salt: int) -> np.ndarray:
        """(N, s) int64 stratum indices in [0, s x share) (class docstring)."""
        key = (np.asarray(self.pixel, np.uint64) * np.uint64(0x100000001B3)
               + np.uint64(int(self.seed) * 1000003 + int(salt)))
        r = (_hash_u64(key) % np.uint64(self.share)).astype(np.int64)
        j = (np.asarray(self.sub, np.int64) + r) % self.share
        return j[:, None] + self.share * np.arange(s, dtype=np.int64)[None, :]

    def uniform_1d(self, rng, s: int, salt: int) -> np.ndarray:
        """(N, s) numbers in [0, 1), one per stratum of :meth:`strata`."""
        c = self.strata(s, salt)
        u = rng.random((len(self.pixel), s))
        u += c
        u /= s * self.share
        return u

    def uniform_2d(self, rng, s: int, salt: int) -> np.ndarray:
        """(N, s, 2) points in [0, 1)^2: the strata are the cells of an m x m jittered grid
        when T = m^2 (cell c: row c // m, column (c + row) mod m, so a sub-sample's cells
        spread over rows and columns), else the first coordinate is stratified only."""
        total = s * self.share
        c = self.strata(s, salt)
        m = int(round(math.sqrt(total)))
        u = rng.random((len(self.pixel), s, 2))   # the jitter, then the point
        if m * m == total:
            k = np.arange(total)    # each cell's column and row, looked up
            u[..., 0] += ((k % m + k // m) % m).astype(np.float64).take(c)
            u[..., 1] += (k // m).astype(np.float64).take(c)
            u /= m
            return u
        u[..., 0] += c
        u[..., 0] /= total
        return u
