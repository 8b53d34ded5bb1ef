"""The two half images of a render and its own noise estimate (docs/science.md §6).

A pixel's value is ``x = (1 / spp) sum_k y_k`` over the light samples of its camera hits
(rendering/shade.py).  Every stored light sample carries a half: A (sign +1), B (-1) or both
(0), so that ``A = x + d``, ``B = x - d`` with ``d = (1 / spp) sum_k sign_k y_k``: their mean is
the image itself (the same samples, the same sum) and ``noise = (A - B) / 2 = d``
(``RenderedImage.noise``).

Which half (:func:`sample_signs`):

* ``spp`` >= 2: whole camera samples, camera sample k by the Thue-Morse sequence t(k) (the
  parity of k's binary digits; +1 where it is 0).  The camera samples are a jittered m x m
  grid (cell k = (k mod m, k div m), rendering/camera.py) or Latin hypercube strata (x
  stratum k); Thue-Morse halves of 2^n consecutive indices have equal sums of k^p for p < n
  (Prouhet 1851): for spp = 4 the halves are the pixel's two diagonals, for spp = 16 each
  row and column holds two cells of each half.  An odd camera sample out (spp odd) is split
  as below.
* ``spp`` = 1 (and the odd camera sample out): the light samples of each light, the first
  half of its samples at the hit against the second half; an odd sample out and a light of
  one sample per hit (point, directional) are in both halves (sign 0): with one camera ray
  through the pixel centre such a light's estimate is exact, and its noise is 0.

The light samples of each half are a net of their own, scrambled on its own
(lighting/strata.py :class:`PixelStrata`, ``LightSampling.independent_halves``), so given
the camera cells the halves are independent and identically distributed, and per pixel

    E[noise^2] = Var(A - B) / 4 = Var(x)

for the light sampling.  The camera cells are fixed (a half holds the same cells in every
render), so where the pixel's content varies across the pixel (edges, texture) E[A] and
E[B] can differ and noise^2 overstates the camera part of the variance by (E[A] - E[B])^2
/ 4; it is exact where the content varies along one image axis only.  With one net for the
pixel (``independent_halves`` False, a less noisy image) the halves share its strata:
E[noise^2] = 2 Var_indep - Var(x), Var_indep the variance of the independent halves' image,
so noise^2 then overstates Var(x) (tests/test_noise_estimate.py checks both relations).
"""
from __future__ import annotations

import numpy as np

from dermis.lighting.strata import thue_morse_sign

__all__ = ["HALF_A", "HALF_B", "thue_morse_sign", "sample_signs", "half_flags", "signs_of",
           "camera_halves"]

# PixelSamples.flags bits of the halves (bits 0 and 1: pipeline/artifacts.py SAMPLE_LIT and
# SAMPLE_CONTROL); neither bit: in both halves
HALF_A = 4
HALF_B = 8


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
    if odd.any():                                # its light samples: first half, second half
        per = []
        for s in columns:
            i = np.arange(s)
            per.append(np.where(i < s // 2, 1, np.where(i < 2 * (s // 2), -1, 0)))
        out[odd] = np.concatenate(per).astype(np.int8)[None, :]
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


def camera_halves(px, values: np.ndarray, idx: np.ndarray | None = None) -> np.ndarray:
    """(H*W, 3) float32 the signed half difference of per-hit ``values`` (of the hits ``idx``
    of a ``PixelSurface``, default all) over each pixel's camera samples: with an even spp
    whole camera samples make the halves (an odd one counts in both); zeros where the hits
    carry no camera sample index (``PixelSamples.sub``).  The BSSRDF's exitance is evaluated
    per camera sample, not per light sample, so this is its share of the image's noise
    from the sub-pixel positions (stages/bssrdf.py)."""
    sub = getattr(px.samples, "sub", None)
    if sub is None:
        return np.zeros((px.width * px.height, 3), np.float32)
    sub = np.asarray(sub) if idx is None else np.asarray(sub)[idx]
    sign = sample_signs(sub, px.spp, [1])[:, 0].astype(np.float64)
    return px.pixels(np.asarray(values, np.float64) * sign[:, None], idx)
