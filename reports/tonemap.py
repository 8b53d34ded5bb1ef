"""Tone mapping for comparison: ONE exposure shared by every image of a comparison, sRGB out.

Kept apart from the renderers so that changing the exposure re-renders nothing.
"""
from __future__ import annotations

import math
from typing import Sequence

import numpy as np

from dermis.pipeline.errors import ConfigError
from dermis.physics.color import LUMINANCE, linear_to_srgb

__all__ = ["EXPOSURE_PERCENTILE", "shared_exposure", "tonemap"]

# Default exposure: the 99.5th percentile of the non-zero pixels' luminance maps to 1, so
# specular highlights may clip (0.5 % of pixels) but the skin is not crushed.  Our choice.
EXPOSURE_PERCENTILE = 99.5


def shared_exposure(images: Sequence[np.ndarray], *,
                    percentile: float = EXPOSURE_PERCENTILE) -> float:
    """One exposure for a whole comparison: 1 / the ``percentile`` of the luminance of every
    non-zero pixel of every image (1.0 if all are black)."""
    lum = [np.asarray(im, dtype=np.float32).reshape(-1, 3) @ LUMINANCE.astype(np.float32)
           for im in images]
    lum = np.concatenate(lum) if lum else np.zeros(0, np.float32)
    lum = lum[np.isfinite(lum) & (lum > 0)]
    if lum.size == 0:
        return 1.0
    top = float(np.percentile(lum, percentile))
    return 1.0 / top if top > 0 else 1.0


def tonemap(images: Sequence[np.ndarray], *, exposure: float | None = None,
            percentile: float = EXPOSURE_PERCENTILE) -> list[np.ndarray]:
    """sRGB uint8 versions of linear images, all with ONE exposure so they can be compared.

    Parameters
    ----------
    images : sequence of (H, W, 3) float arrays, linear RGB
    exposure : float, optional
        Multiplier applied before sRGB encoding; None computes it from all images together
        (:func:`shared_exposure`).  Record it with the images (metadata) to redo the mapping.
    percentile : float
        Luminance percentile mapped to 1 when ``exposure`` is None.

    Returns
    -------
    list of (H, W, 3) uint8 arrays: clip(exposure x image, 0, 1) sRGB-encoded (IEC 61966-2-1).
    """
    images = list(images)
    if exposure is None:
        exposure = shared_exposure(images, percentile=percentile)
    if not (math.isfinite(exposure) and exposure > 0):
        raise ConfigError(f"exposure = {exposure}: must be finite and > 0")
    out = []
    for im in images:
        lin = np.nan_to_num(np.asarray(im, dtype=np.float32)) * np.float32(exposure)
        out.append(np.round(linear_to_srgb(lin) * 255.0).astype(np.uint8))
    return out
