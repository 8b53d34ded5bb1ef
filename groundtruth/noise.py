"""The reference's own noise: two independent half-buffers, their difference, its fall with spp.

The reference is traced into two half-buffers with independent seeds (docs/ground-truth.md,
:mod:`dermis.groundtruth.progressive`): the image is their mean and (A - B) / 2 estimates its
per-pixel error.  The noise is the relative RMSE of that error on ``factor`` x ``factor``
block means (factor 1 = reference pixels), the same measure as the models' relative RMSE;
measured after each uniform pass it gives the constant c = noise x sqrt(spp), from which
:mod:`dermis.reports.ground_truth` computes the path tracer's time to reach a given error.
"""
from __future__ import annotations

import math

import numpy as np

from dermis.geometry.regions import block_mean

__all__ = ["NOISE_FACTORS", "two_seed_noise", "noise_fit"]

# Block factors (on the reference's own pixel grid) at which noise and errors are reported.
NOISE_FACTORS = (1, 2, 4, 8)


def two_seed_noise(a: np.ndarray, b: np.ndarray, mask: np.ndarray, factors=NOISE_FACTORS
                   ) -> dict:
    """Relative RMSE noise of the mean of two independent renders, per block factor.

    noise = sqrt(mean ((A - B) / 2)^2) / sqrt(mean ((A + B) / 2)^2) over the fully covered
    blocks and all channels (the definition of the models' ``rel_rmse``); ``_rgb`` per
    channel.  A single render's noise is sqrt(2) times this.
    """
    out = {}
    for f in factors:
        A, m = block_mean(a, mask, f)
        B, _ = block_mean(b, mask, f)
        if not m.any():
            continue
        hd, mean = (A - B)[m] / 2.0, (A + B)[m] / 2.0
        rms = math.sqrt(float((mean * mean).mean()))
        out[str(f)] = {"rel": math.sqrt(float((hd * hd).mean())) / rms if rms > 0 else 0.0,
                       "rel_rgb": [float(math.sqrt((hd[:, c] ** 2).mean())
                                         / max(math.sqrt((mean[:, c] ** 2).mean()), 1e-30))
                                   for c in range(3)],
                       "blocks": int(m.sum())}
    return out


def noise_fit(noise: dict, curve: list, spp: int) -> dict:
    """c = noise x sqrt(spp) per block factor of ``noise``, from a noise curve (``{"spp": both
    halves' samples, "noise": {factor: rel}}`` per pass) ending at ``spp`` samples per half."""
    # the mean over the checkpoints from 1/4 of the samples on (the early ones carry the
    # heavy-tailed start-up of the estimate)
    fit = {}
    for f in noise:
        vals = [p["noise"][f] * math.sqrt(p["spp"]) for p in curve if f in p["noise"]
                and p["spp"] >= 2 * spp / 4]
        fit[f] = float(np.mean(vals)) if vals else 0.0
    return fit
