"""The reference's own noise: two independent renders, their difference, its fall with spp.

The reference is rendered twice with independent seeds (docs/ground-truth.md): the image is
their mean and (A - B) / 2 estimates its per-pixel error.  The noise is the relative RMSE of
that error on ``factor`` x ``factor`` block means (factor 1 = reference pixels), the same
measure as the models' relative RMSE; measured at fractions of the samples it gives the
constant c = noise x sqrt(spp), from which :mod:`dermis.reports.ground_truth` computes the
path tracer's time to reach a given error.
"""
from __future__ import annotations

import math

import numpy as np

from dermis.geometry.regions import block_mean

__all__ = ["NOISE_FACTORS", "CURVE_FRACTIONS", "curve_checkpoints", "two_seed_noise",
           "noise_curve", "noise_fit"]

# Block factors (on the reference's own pixel grid) at which noise and errors are reported.
NOISE_FACTORS = (1, 2, 4, 8)
# Fractions of the samples at which the two-seed noise is measured (the noise-vs-spp curve).
CURVE_FRACTIONS = (1 / 16, 1 / 8, 1 / 4, 1 / 2, 1)


def curve_checkpoints(spp: int) -> list[int]:
    """Sample counts of one seed at which the noise curve is measured (:data:`CURVE_FRACTIONS`)."""
    return sorted({max(1, int(round(spp * f))) for f in CURVE_FRACTIONS})


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


def noise_curve(curve_a: list, curve_b: list, mask: np.ndarray) -> list[dict]:
    """The two-seed noise per block factor at each checkpoint of two
    :func:`dermis.groundtruth.passes.render_passes` curves: ``{"spp": both seeds' samples,
    "noise": {factor: rel}}`` per checkpoint."""
    curve = []
    for (n, a), (_, b) in zip(curve_a, curve_b):
        curve.append({"spp": 2 * n, "noise": {f: v["rel"] for f, v in
                                               two_seed_noise(a, b, mask).items()}})
    return curve


def noise_fit(noise: dict, curve: list, spp: int) -> dict:
    """c = noise x sqrt(spp) per block factor of ``noise``, from a :func:`noise_curve` of
    ``spp`` samples per seed."""
    # the mean over the checkpoints from 1/4 of the samples on (the early ones carry the
    # heavy-tailed start-up of the estimate)
    fit = {}
    for f in noise:
        vals = [p["noise"][f] * math.sqrt(p["spp"]) for p in curve if f in p["noise"]
                and p["spp"] >= 2 * spp / 4]
        fit[f] = float(np.mean(vals)) if vals else 0.0
    return fit
