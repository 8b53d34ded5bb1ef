"""The two half images of a render and its own noise estimate (docs/science.md §6).

A pixel's value is ``x = (1 / spp) sum_k y_k`` over the light samples of its camera hits
(rendering/shade.py).  Every stored light sample carries a half: A (sign +1), B (-1) or both
(0), so that ``A = x + d``, ``B = x - d`` with ``d = (1 / spp) sum_k sign_k y_k``; their mean is
the image itself (the same samples, the same sum) and ``noise = (A - B) / 2 = d``
(``RenderedImage.noise``): per pixel, ``noise^2`` estimates the variance of ``x``.

Which half (:func:`sample_signs`):

* ``spp`` >= 2: whole camera samples.  Camera sample k gets the sign of the Thue-Morse
  sequence t(k) (the parity of k's binary digits; +1 where it is 0).  The camera samples are a
  jittered m x m grid (cell k = (k mod m, k div m), rendering/camera.py) or Latin hypercube
  strata (x stratum k), and a pixel's light samples are dealt to them in sets (lighting/
  strata.py :class:`PixelStrata`: camera sample j takes the strata ``(j + r) mod spp`` of
  every group).  Thue-Morse halves of 2^n consecutive indices have equal sums of k^p for p <
  n (Prouhet 1851): for spp = 4 the halves are the pixel's two diagonals, for spp = 16 each
  row and column of the grid holds two samples of each half, and either way each half holds
  as many camera cells and light strata of every part of the pixel and the sphere as the other
  (to first order in the position inside the pixel and in the strata), so E[A] = E[B] wherever
  the pixel's integrand is smooth at that order.  An odd camera sample out (spp odd) is split
  as below.
* ``spp`` = 1 (and the odd camera sample out): the light samples of each light, by t(i) of
  their index i among the hit's samples of that light (the strata of lighting/strata.py and
  lighting/mixture.py follow i); an odd sample out and a light of one sample per hit (point,
  directional) are in both halves (sign 0): with one camera ray through the pixel centre such
  a light's estimate is exact, and its noise is 0.

What the estimate is (tests/test_noise_estimate.py): the halves share the pixel's random strata
rotation and fill complementary strata, so they are not independent: E[noise^2] = Var(x) +
Var(E[A | rotation] - x) + (E[A] - E[B])^2 / 4 - Cov(A, B | rotation) ... with the conditional
halves independent, ``E[noise^2] = Var(x) + E[(E[A|r] - E[B|r])^2] / 4``: the variance a fully
stratified pixel saves over two independent halves shows up as noise.  Thue-Morse halves hold
the same strata rows, columns and first moments, so that term is of second order in the strata
(measured on the default scan under the sunset, tests/test_noise_estimate.py and
bench/results/env_noise.json "noise_estimate").
"""
from __future__ import annotations

import numpy as np

__all__ = ["HALF_A", "HALF_B", "thue_morse_sign", "sample_signs", "half_flags", "signs_of"]

# PixelSamples.flags bits of the halves (bits 0 and 1: pipeline/artifacts.py SAMPLE_LIT and
# SAMPLE_CONTROL); neither bit: in both halves
HALF_A = 4
HALF_B = 8


def thue_morse_sign(k) -> np.ndarray:
    """+1 where the Thue-Morse sequence t(k) (parity of the binary digits of k) is 0, else -1
    (int8)."""
    k = np.asarray(k, np.int64).copy()
    parity = np.zeros(k.shape, np.int64)
    while np.any(k):
        parity ^= k & 1
        k >>= 1
    return (1 - 2 * parity).astype(np.int8)


def sample_signs(sub: np.ndarray, spp: int, columns: list[int]) -> np.ndarray:
    """(N, sum(columns)) int8 half signs of the light samples of N camera hits (module
    docstring): ``sub`` (N,) each hit's camera sample index in [0, spp); ``columns`` the
    samples per hit of each light, in the order :func:`lighting.emitters.sample_lights`
    concatenates them."""
    sub = np.asarray(sub, np.int64)
    paired = spp - spp % 2                       # camera samples split whole
    total = int(sum(columns))
    out = np.empty((len(sub), total), np.int8)
    out[:] = np.where(sub < paired, thue_morse_sign(sub), 0)[:, None].astype(np.int8)
    odd = sub >= paired
    if odd.any():
        per = []
        for s in columns:
            i = np.arange(s)
            per.append(np.where(i < s - s % 2, thue_morse_sign(i), 0).astype(np.int8))
        out[odd] = np.concatenate(per)[None, :]
    return out


def half_flags(signs: np.ndarray) -> np.ndarray:
    """uint8 flag bits (HALF_A, HALF_B, 0) of int8 signs."""
    s = np.asarray(signs)
    return (np.where(s > 0, HALF_A, 0) | np.where(s < 0, HALF_B, 0)).astype(np.uint8)


def signs_of(flags: np.ndarray | None) -> np.ndarray | None:
    """float32 signs (+1, -1, 0) of stored samples from their flags (None: no halves)."""
    if flags is None:
        return None
    f = np.asarray(flags, np.uint8)
    return (((f & HALF_A) > 0).astype(np.float32) - ((f & HALF_B) > 0).astype(np.float32))
