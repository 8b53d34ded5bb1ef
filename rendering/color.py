"""Colour: the sRGB transfer curves (IEC 61966-2-1) and Rec. 709 luminance weights.

Everything in dermis is linear RGB (Rec. 709 primaries) until an image is written as PNG.
"""
from __future__ import annotations

import numpy as np

__all__ = ["LUMINANCE", "srgb_to_linear", "linear_to_srgb", "linear_to_srgb8"]

# Rec. 709 / sRGB relative luminance Y = 0.2126 R + 0.7152 G + 0.0722 B (ITU-R BT.709-6).
LUMINANCE = np.array([0.2126, 0.7152, 0.0722], dtype=np.float64)


def srgb_to_linear(c: np.ndarray) -> np.ndarray:
    """IEC 61966-2-1 sRGB decoding of values in [0, 1] (float32)."""
    c = np.asarray(c, dtype=np.float32)
    return np.where(c <= 0.04045, c / 12.92, ((c + 0.055) / 1.055) ** 2.4).astype(np.float32)


def linear_to_srgb(c: np.ndarray, dtype=np.float32) -> np.ndarray:
    """IEC 61966-2-1 sRGB encoding; input clipped to [0, 1]; computed in ``dtype``."""
    c = np.clip(np.asarray(c, dtype=dtype), 0.0, 1.0)
    return np.where(c <= 0.0031308, c * 12.92, 1.055 * np.power(c, 1 / 2.4) - 0.055).astype(dtype)


def linear_to_srgb8(c: np.ndarray, dtype=np.float32) -> np.ndarray:
    """Linear [0, 1] -> sRGB uint8, rounded to nearest."""
    return np.round(linear_to_srgb(c, dtype) * 255.0).astype(np.uint8)
