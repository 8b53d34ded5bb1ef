"""Warps of uniform numbers onto the unit disc and the hemisphere, and the vector helpers
the light and lobe samplers share (docs/science.md §6).

* :func:`concentric_disc` - Shirley & Chiu 1997 concentric map of [0, 1)^2 onto the unit
  disc (area preserving): the disc light's sample points and Malley's method;
* :func:`cosine_hemisphere` - cosine-weighted directions about each normal (Malley's
  method on the concentric disc), solid-angle pdf cos / pi: the environment light's cosine
  strategy (lighting/emitters.py);
* :func:`about_axis` - directions at given polar cosines and azimuths about an axis: the
  BRDF lobes' samples (lighting/lobes.py);
* :func:`normalize`, :func:`tangent_frame`, :func:`tangent_frames` - unit vectors and
  orthonormal tangent frames (Duff et al. 2017, as cl/common.h).

(N, S, 3) arrays are computed one component at a time: numpy reduces and broadcasts along a
trailing axis of 3 several times slower.

Guarded by tests/test_lights.py (cosine-distributed hemisphere samples, the disc light's
closed forms).
"""
from __future__ import annotations

import math

import numpy as np

__all__ = ["concentric_disc", "cosine_hemisphere", "about_axis", "normalize", "tangent_frame",
           "tangent_frames"]


def _length(v: np.ndarray) -> np.ndarray:
    """``np.linalg.norm(v, axis=-1)`` of (..., 3) vectors, the same sum ((x^2 + y^2) + z^2)
    taken component by component (numpy reduces and broadcasts along a trailing axis of 3
    several times slower)."""
    x, y, z = v[..., 0], v[..., 1], v[..., 2]
    s = x * x
    s += y * y
    s += z * z
    return np.sqrt(s, out=s)


def normalize(v: np.ndarray) -> np.ndarray:
    """Unit vectors along the last axis (zero vectors stay zero)."""
    if v.ndim < 2 or v.shape[-1] != 3:
        return v / np.maximum(np.linalg.norm(v, axis=-1, keepdims=True), 1e-30)
    n = _length(v)
    n = np.maximum(n, 1e-30, out=n)
    out = np.empty(v.shape, np.result_type(v, n))
    for k in range(3):
        np.divide(v[..., k], n, out=out[..., k])
    return out


def tangent_frame(axis: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Two unit vectors orthogonal to unit ``axis`` (Duff et al. 2017, as cl/common.h)."""
    x, y, z = (float(c) for c in axis)
    s = 1.0 if z >= 0 else -1.0
    a = -1.0 / (s + z)
    b = x * y * a
    t = np.array([1.0 + s * x * x * a, s * b, -s * x])
    bt = np.array([b, s + y * y * a, -y])
    return t, bt


def tangent_frames(axes: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Vectorised :func:`tangent_frame`: (N, 3) unit axes -> two (N, 3) orthonormal tangents."""
    x, y, z = axes[:, 0], axes[:, 1], axes[:, 2]
    s = np.where(z >= 0, 1.0, -1.0)
    a = -1.0 / (s + z)
    b = x * y * a
    t = np.stack([1.0 + s * x * x * a, s * b, -s * x], axis=1)
    bt = np.stack([b, s + y * y * a, -y], axis=1)
    return t, bt


def about_axis(axis: np.ndarray, cos_a: np.ndarray, phi: np.ndarray) -> np.ndarray:
    """(N, S, 3) unit directions at polar cosine ``cos_a`` and azimuth ``phi`` (N, S) about
    the (N, 3) unit ``axis``."""
    sin_a = np.sqrt(np.maximum(1.0 - cos_a * cos_a, 0.0))
    t, b = tangent_frames(axis)
    d = ((sin_a * np.cos(phi))[..., None] * t[:, None] + (sin_a * np.sin(phi))[..., None]
         * b[:, None] + cos_a[..., None] * axis[:, None])
    return normalize(d)


def cosine_hemisphere(u: np.ndarray, normals: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Cosine-weighted directions about each normal (Malley's method, concentric disc).

    u : (N, S, 2) uniform numbers in [0, 1); normals : (N, 3) unit.
    Returns (N, S, 3) float64 unit directions and their cosine with the normal (N, S);
    the solid-angle pdf is cos / pi.
    """
    n = normalize(np.asarray(normals, dtype=np.float64))
    xy = concentric_disc(u)
    x, y = xy[..., 0], xy[..., 1]
    cos = x * x
    cos += y * y
    np.subtract(1.0, cos, out=cos)
    np.sqrt(np.maximum(cos, 0.0, out=cos), out=cos)
    t, b = tangent_frames(n)
    # x t + y b + cos n, normalised: one component at a time (numpy broadcasts along a
    # trailing axis of 3 several times slower)
    dk = [x * t[:, k, None] for k in range(3)]
    for k in range(3):
        dk[k] += y * b[:, k, None]
        dk[k] += cos * n[:, k, None]
    length = dk[0] * dk[0]      # as normalize
    length += dk[1] * dk[1]
    length += dk[2] * dk[2]
    length = np.maximum(np.sqrt(length, out=length), 1e-30, out=length)
    d = np.empty(cos.shape + (3,))
    for k in range(3):
        np.divide(dk[k], length, out=d[..., k])
    return d, cos


def concentric_disc(u: np.ndarray) -> np.ndarray:
    """Shirley & Chiu 1997 concentric map of [0, 1)^2 onto the unit disc (area preserving).

    u : (..., 2) float in [0, 1); returns (..., 2) points in the unit disc, in u's float
    type (float32 in, float32 math: the disc light's 15M samples of an irradiance pass).
    """
    a = 2 * u[..., 0] - 1
    b = 2 * u[..., 1] - 1
    first = np.abs(a) > np.abs(b)
    r = np.where(first, a, b)
    # phi = pi/4 (b / a) or pi/2 - pi/4 (a / b): one division of the smaller by the larger
    ratio = np.where(first, b, a) / np.where(r == 0, 1, r)
    phi = np.where(first, ratio, 2 - ratio) * (math.pi / 4)
    return np.stack([r * np.cos(phi), r * np.sin(phi)], axis=-1)
