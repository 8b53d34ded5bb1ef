"""How many samples a Cycles image needs: two independent halves, their noise, and the rule
that picks the sample count to reach a target noise.

An image is the mean of two halves A and B rendered with different seeds; (A - B) / 2
estimates its error, and its noise is the relative RMSE of that error on ``block`` x
``block`` block means over the fully covered blocks (the reference's own measure,
:func:`dermis.groundtruth.noise.two_seed_noise`, here on the camera's pixels so that one
block is one reference pixel).  Path-tracing noise falls as 1 / sqrt(samples), so after a
pilot of p samples per half with noise n_p, p (n_p / target)^2 samples per half reach the
target.  Pure numpy: the render process (:mod:`dermis.cycles.render_job`) imports it.
"""
from __future__ import annotations

import math

import numpy as np

__all__ = ["block_noise", "samples_for", "Halves"]


def _blocks(a: np.ndarray, f: int) -> np.ndarray:
    h, w = a.shape[0] // f * f, a.shape[1] // f * f
    a = a[:h, :w]
    return a.reshape(h // f, f, w // f, f, *a.shape[2:]).mean(axis=(1, 3))


def block_noise(a: np.ndarray, b: np.ndarray, covered: np.ndarray, block: int) -> float:
    """Relative RMSE noise of (a + b) / 2 on ``block``-pixel block means over the blocks whose
    pixels are all ``covered``: sqrt(mean ((A - B) / 2)^2) / sqrt(mean ((A + B) / 2)^2)."""
    m = _blocks(covered.astype(np.float64), block) > 0.999
    if not m.any():
        return 0.0
    A, B = _blocks(a.astype(np.float64), block)[m], _blocks(b.astype(np.float64), block)[m]
    hd, mean = (A - B) / 2.0, (A + B) / 2.0
    rms = math.sqrt(float((mean * mean).mean()))
    return math.sqrt(float((hd * hd).mean())) / rms if rms > 0 else 0.0


def samples_for(noise: float, spp: int, target: float, *, max_spp: int) -> int:
    """Samples per half that bring ``noise`` measured at ``spp`` per half to ``target``
    (1 / sqrt(spp) falloff), at least ``spp`` and at most ``max_spp``."""
    if not noise > target or target <= 0:
        return spp
    need = int(math.ceil(spp * (noise / target) ** 2))
    return int(min(max(need, spp), max_spp))


class Halves:
    """Two half images accumulated over passes, each pass weighted by its samples."""

    def __init__(self):
        self.sum_a = self.sum_b = None
        self.spp = 0
        self.passes: list[dict] = []

    def add(self, a: np.ndarray, b: np.ndarray, spp: int, **log) -> None:
        a, b = a.astype(np.float64) * spp, b.astype(np.float64) * spp
        self.sum_a = a if self.sum_a is None else self.sum_a + a
        self.sum_b = b if self.sum_b is None else self.sum_b + b
        self.spp += spp
        self.passes.append({"spp": int(spp), **log})

    def halves(self) -> tuple[np.ndarray, np.ndarray]:
        return self.sum_a / self.spp, self.sum_b / self.spp
