"""Stratified uniform numbers: per point, and spread over the sub-pixel samples of a pixel.

* :func:`stratified_2d` - (n, s, 2) points in [0, 1)^2 per point: a jittered grid when s is
  a square, Latin hypercube strata otherwise (Shirley 1991, "Discrepancy as a quality
  measure for sample distributions"); the disc light's points, the environment light's
  cosine and lobe samples (lighting/emitters.py) and the camera's sub-pixel offsets
  (lighting/visibility.py ``subpixel_offsets``).
* :class:`PixelStrata` - renderers spread a pixel's S light samples over its camera samples
  (``share``) as the points of a scrambled Sobol net, in two halves (the image's own noise
  estimate, rendering/halves.py), each a net of its own: the light samples are stratified
  over the whole pixel in every box shape, not only a grid.  Measured on the default scan
  under the Venice sunset (200 x 200, 8 seeds, spp 4, 16 samples; relative RMSE Lafortune
  against the converged render, the map sampled by luminance): a jittered 4 x 4 grid dealt
  over the camera samples 0.0971, two nets of 8 0.0854 (bench/results/env_noise.json
  "before_nets", "after_nets" "brightness"); one net of 16 is lower still (0.0614 against
  0.0722 with the RGB norm, "after_nets" "joint_net").
* :func:`thue_morse_sign` - the halves of a pixel's camera samples.

Guarded by tests/test_antialias.py (sub-pixel samples stratified and seeded),
tests/test_noise_estimate.py (the nets, their halves) and, through the renders that share
light samples over a pixel, tests/test_render.py.
"""
from __future__ import annotations

import functools
import math
from dataclasses import dataclass

import numpy as np

__all__ = ["stratified_2d", "PixelStrata", "thue_morse_sign"]


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
    with np.errstate(over="ignore"):          # modulo 2^64
        z = np.asarray(x).astype(np.uint64) + np.uint64(0x9E3779B97F4A7C15)
        z ^= z >> np.uint64(30)
        z *= np.uint64(0xBF58476D1CE4E5B9)
        z ^= z >> np.uint64(27)
        z *= np.uint64(0x94D049BB133111EB)
        z ^= z >> np.uint64(31)
    return z


@functools.lru_cache(maxsize=None)
def _sobol_2d(digits: int) -> np.ndarray:
    """(2^digits, 2) int64: the first 2^digits points of the Sobol (0, 2)-sequence as
    ``digits``-digit binary integers (dimension 1 van der Corput, dimension 2 from the
    direction numbers of the polynomial x + 1, m_k = 2 m_(k-1) xor m_(k-1); Sobol 1967).
    Every aligned run of 2^k consecutive points is a (0, k, 2)-net: one point in each of
    the 2^k boxes of every shape 2^-a x 2^-(k - a)."""
    i = np.arange(1 << digits, dtype=np.int64)
    m = [1]
    for _ in range(1, digits):
        m.append((2 * m[-1]) ^ m[-1])
    x = np.zeros_like(i)
    y = np.zeros_like(i)
    for b in range(digits):
        bit = (i >> b) & 1
        x |= bit << (digits - 1 - b)
        y ^= bit * (m[b] << (digits - 1 - b))
    return np.stack([x, y], axis=-1)


# Trees of up to this many flip bits (digits <= 4: 16 points) are applied through a table of
# every tree's scrambled points (32768 x 16 entries), one lookup per point; a tree of 5 or 6
# digits (one 64-bit word: the irradiance pass's nets of 32) looks its first 4 digits up by
# value and flips the rest (the same digits, ~2x faster than flipping all of them)
_LUT_NODES = 15
_LUT_DIGITS = 4
_LUT_MASK = (1 << _LUT_NODES) - 1


@functools.lru_cache(maxsize=None)
def _scramble_table(digits: int, dim: int) -> np.ndarray:
    """(2^nodes * 2^digits,) int64: point i of :func:`_sobol_2d` (dimension ``dim``) scrambled
    by the tree whose flip bits are the integer t (node (depth, prefix) = bit 2^depth - 1 +
    prefix), at t * 2^digits + i."""
    nodes = (1 << digits) - 1
    x = _sobol_2d(digits)[:, dim][None, :]
    t = np.arange(1 << nodes, dtype=np.int64)[:, None]
    y = np.zeros((1 << nodes, 1 << digits), np.int64)
    for depth in range(digits):
        node = (1 << depth) - 1 + (x >> (digits - depth))
        flip = (t >> node) & 1
        y |= (((x >> (digits - 1 - depth)) & 1) ^ flip) << (digits - 1 - depth)
    return y.ravel()


@functools.lru_cache(maxsize=None)
def _owen_values() -> np.ndarray:
    """(2^15 * 16,) int64: each 4-digit value v scrambled by the tree of flip bits t (the
    first 4 levels of any tree, nodes numbered as :func:`_scramble_table`'s), at t * 16 + v."""
    x = np.arange(1 << _LUT_DIGITS, dtype=np.int64)[None, :]
    t = np.arange(1 << _LUT_NODES, dtype=np.int64)[:, None]
    y = np.zeros((1 << _LUT_NODES, 1 << _LUT_DIGITS), np.int64)
    for depth in range(_LUT_DIGITS):
        node = (1 << depth) - 1 + (x >> (_LUT_DIGITS - depth))
        y |= (((x >> (_LUT_DIGITS - 1 - depth)) & 1) ^ ((t >> node) & 1)) \
            << (_LUT_DIGITS - 1 - depth)
    return y.ravel()


def thue_morse_sign(k) -> np.ndarray:
    """+1 where the Thue-Morse sequence t(k) (parity of the binary digits of k) is 0, else -1
    (int8): the halves of a pixel's camera samples (rendering/halves.py)."""
    k = np.asarray(k, np.int64).copy()
    parity = np.zeros(k.shape, np.int64)
    while np.any(k):
        parity ^= k & 1
        k >>= 1
    return (1 - 2 * parity).astype(np.int8)


def _digits(total: int) -> int:
    return max(1, int(total - 1).bit_length())


@dataclass(frozen=True)
class PixelStrata:
    """The sub-pixel samples of pixels that share the pixels' light samples.

    A disc or environment light's T = s x share samples of a pixel (s per sub-pixel sample)
    are the first T points of the Sobol (0, 2)-sequence (:func:`_sobol_2d`; its first
    dimension, the van der Corput sequence, in one dimension), randomised per pixel by
    Owen's nested uniform scrambling (Owen 1995, "Randomly permuted (t, m, s)-nets and
    (t, s)-sequences": every digit flipped by a random bit of the digits before it, hashed
    from ``seed``, the pixel and the draw's ``salt``; the digits past the T-th stratum
    uniform), so every point is uniform on [0, 1)^2 and the pixel's T points keep the net's
    strata: for T = 16, one point in each of the 16 x 1, 8 x 2, 4 x 4, 2 x 8 and 1 x 16
    boxes (a jittered 4 x 4 grid has only the 4 x 4).  The points are dealt in consecutive
    blocks of s: the camera samples of the first half (rendering/halves.py, signs +1) the
    first blocks, those of the second half the next ones, an odd camera sample out the
    last; so each camera sample's s points, each half's T / 2 and the pixel's T are nets
    where s and T are powers of 2 (the halves of the image's noise estimate are each
    stratified).  Each sub-sample's estimate stays unbiased (its points are uniform), the
    pixel's stratified as if one point drew all T (Kollig & Keller 2002, "Efficient
    multidimensional sampling", padding by scrambling).

    ``independent``: each half of the pixel's points (rendering/halves.py: the first-half
    camera samples' blocks and the first half of an odd camera sample's points, likewise the
    second) is a net of its own, scrambled on its own, so the two half images are
    independent (their noise estimate unbiased) but the pixel's T points are two nets of
    T / 2, not one net of T.

    pixel : (N,) int pixel index of each point; sub : (N,) int in [0, share); share : int
    """

    pixel: np.ndarray
    sub: np.ndarray
    share: int
    seed: int = 0
    independent: bool = False

    def __getitem__(self, sl) -> "PixelStrata":
        return PixelStrata(self.pixel[sl], self.sub[sl], self.share, self.seed,
                           self.independent)

    def blocks(self) -> np.ndarray:
        """(N,) int64 each point's block of the pixel's points: first-half camera samples
        (Thue-Morse sign +1, rendering/halves.py) in order, then the second half's, then
        an odd one out."""
        j = np.arange(self.share)
        paired = self.share - self.share % 2
        sign = np.where(j < paired, thue_morse_sign(j), 0)
        order = np.concatenate([j[sign > 0], j[sign < 0], j[sign == 0]])
        block = np.empty(self.share, np.int64)
        block[order] = np.arange(self.share)
        return block[np.asarray(self.sub, np.int64)]

    def _layout(self, s: int) -> tuple[np.ndarray, np.ndarray | None, int]:
        """Each of the N x s points' index in its net (N, s), its net (None: one per pixel;
        else 0, 1 the halves, 2 an odd point out: (N, 1) when whole camera samples make the
        halves, (N, s) with an odd one) and the largest net's size."""
        block = self.blocks()[:, None]
        i = np.arange(s)[None, :]
        if not self.independent:
            return block * s + i, None, s * self.share
        h = self.share // 2
        half = s // 2
        group = (block >= h).astype(np.int64)
        index = (block - h * group) * s + i
        if self.share % 2 == 0:
            return index, group, max(h * s, 1)
        odd = block >= 2 * h                              # an odd camera sample's points
        group = np.where(odd, np.where(i < half, 0, np.where(i < 2 * half, 1, 2)), group)
        index = np.where(odd, np.where(i < half, h * s + i,
                                       np.where(i < 2 * half, h * s + i - half, 0)), index)
        return index, group, max(h * s + half, 1)

    def _scrambled(self, s: int, salt: int, dims: int) -> tuple[np.ndarray, int]:
        """(N, s, dims) int64 Owen-scrambled digit strings (class docstring) of each point's
        s points, and their digit count."""
        index, group, total = self._layout(s)
        d = _digits(total)
        key = (np.asarray(self.pixel, np.uint64) * np.uint64(0x100000001B3)
               + np.uint64(int(self.seed) * 1000003 + int(salt)))
        nodes = (1 << d) - 1                      # the tree's flip bits
        words = -(-nodes // 64)
        nets = 1 if group is None else 2 + (self.share % 2)
        out = np.empty(index.shape + (dims,), np.int64)
        for k in range(dims):
            if nodes <= 63:             # one tree word per point's net
                net_salt = _hash_u64(np.arange(nets, dtype=np.uint64) * np.uint64(64 * 4096)
                                     + np.uint64(k * 4096 + 1))
                word = _hash_u64(key[:, None]
                                 ^ (net_salt[0] if group is None else net_salt.take(group)))
                if nodes <= _LUT_NODES:   # the digits looked up
                    bits = (word & np.uint64((1 << nodes) - 1)).astype(np.int64)
                    out[..., k] = _scramble_table(d, k).take(bits * (1 << d) + index)
                    continue
                # the first LUT_DIGITS digits looked up by value, the rest flipped bit by bit
                x = _sobol_2d(d)[:, k].take(index)
                low = d - _LUT_DIGITS
                bits = (word & np.uint64(_LUT_MASK)).astype(np.int64)
                y = _owen_values().take(bits * (1 << _LUT_DIGITS) + (x >> low)) << low
                for depth in range(_LUT_DIGITS, d):
                    node = ((1 << depth) - 1 + (x >> (d - depth))).astype(np.uint64)
                    flip = ((word >> node) & np.uint64(1)).astype(np.int64)
                    y |= (((x >> (d - 1 - depth)) & 1) ^ flip) << (d - 1 - depth)
                out[..., k] = y
                continue
            # each net's random tree: a row per point and net (N, nets * words)
            tree = np.stack([_hash_u64(key ^ _hash_u64(np.uint64((g * 64 + k) * 4096 + w + 1)))
                             for g in range(nets) for w in range(words)], axis=-1)
            x = _sobol_2d(d)[:, k].take(index)
            y = np.zeros_like(x)
            for depth in range(d):
                node = (1 << depth) - 1 + (x >> (d - depth))
                at = node >> 6 if group is None else group * words + (node >> 6)
                word = np.take_along_axis(tree, at, 1)
                flip = ((word >> (node & 63).astype(np.uint64)) & np.uint64(1)).astype(np.int64)
                y |= (((x >> (d - 1 - depth)) & 1) ^ flip) << (d - 1 - depth)
            out[..., k] = y
        return out, d

    def uniform_1d(self, rng, s: int, salt: int) -> np.ndarray:
        """(N, s) numbers in [0, 1): the scrambled van der Corput points of the pixel."""
        digits, d = self._scrambled(s, salt, 1)
        u = rng.random((len(self.pixel), s))
        u += digits[..., 0]
        u /= float(1 << d)
        return u

    def uniform_2d(self, rng, s: int, salt: int) -> np.ndarray:
        """(N, s, 2) points in [0, 1)^2: the scrambled Sobol points of the pixel."""
        digits, d = self._scrambled(s, salt, 2)
        u = rng.random((len(self.pixel), s, 2))   # the jitter, then the point
        u += digits
        u /= float(1 << d)
        return u
