"""The procedural head's albedo texture: sRGB atlas painted in the skin grid's UV space.

Anatomical region masks (cheek and nose redness, lid crease, lips, nostrils, eyebrows) painted
at the surface points of the texels, plus band-limited noise (mottling, fine pigment, freckles,
blotchy redness, eyebrow hairs); the eyes (sclera, iris, pupil) fill the strip above the skin
atlas (``V_SKIN``, :mod:`dermis.geometry.head_shape`).
"""
from __future__ import annotations

import numpy as np
from scipy import fft, ndimage

from dermis.geometry.head_relief import gauss, lip_mask
from dermis.geometry.head_shape import EYE_RADIUS, V_SKIN, ellipsoid, smoothstep
from dermis.rendering.color import linear_to_srgb8

__all__ = ["albedo_texture"]


# ----------------------------------------------------------------------------------------------
# albedo texture
# ----------------------------------------------------------------------------------------------
# Linear-RGB albedos.  Base: a light skin tone whose sRGB is ~(208, 160, 136); measured diffuse
# albedos of light skin are ~0.5-0.65 red, 0.3-0.4 green, 0.2-0.3 blue (e.g. Donner & Jensen
# 2006, Fig. 8 spectra integrated to RGB; Weyrich et al. 2006).  Others: our choices.
SKIN_LINEAR = np.array([0.63, 0.35, 0.25])
LIP_LINEAR = np.array([0.36, 0.10, 0.095])
BROW_LINEAR = np.array([0.07, 0.045, 0.03])
NOSTRIL_LINEAR = np.array([0.22, 0.07, 0.06])
FRECKLE_TINT = np.array([0.86, 0.78, 0.72])
SCLERA_LINEAR = np.array([0.78, 0.72, 0.66])
IRIS_LINEAR = np.array([0.16, 0.09, 0.045])
MASK_RES = 512             # region masks are smooth: painted at <= 512^2 and upsampled


def _linear_to_srgb8(c):
    """Linear [0, 1] -> sRGB uint8 (:func:`dermis.rendering.color.linear_to_srgb8`), one channel
    at a time so the float32 temporaries stay one channel's size."""
    out = np.empty(c.shape, np.uint8)
    for ch in range(c.shape[-1]):
        out[..., ch] = linear_to_srgb8(c[..., ch])
    return out


def _fft_noise(rng, shape, sigma_px):
    """Unit-variance Gaussian-filtered white noise, periodic in both axes (so seamless in u)."""
    white = rng.standard_normal(shape, dtype=np.float32)
    fy = fft.fftfreq(shape[0]).astype(np.float32)[:, None]
    fx = fft.rfftfreq(shape[1]).astype(np.float32)[None, :]
    filt = np.exp(-2.0 * np.pi ** 2 * sigma_px ** 2 * (fx * fx + fy * fy)).astype(np.float32)
    n = fft.irfft2(fft.rfft2(white) * filt, s=shape)
    return (n / max(float(n.std()), 1e-12)).astype(np.float32)


def _noise_at(rng, size, sigma_px):
    """Noise field (size, size) with the given feature size, generated at a coarse scale if smooth."""
    factor = 1
    while sigma_px / factor > 8.0 and size // (2 * factor) >= 32:
        factor *= 2
    n = _fft_noise(rng, (size // factor, size // factor), sigma_px / factor)
    if factor > 1:
        n = ndimage.zoom(n, factor, order=1, grid_mode=True, mode="grid-wrap")
    return n


def _paint_skin(p):
    """Linear albedo (..., 3) of the skin at design-frame points p = (x, y, z), before noise."""
    x, y, z = p
    ax = np.abs(x)
    q = (ax, y, z)
    red = (0.65 * gauss(q, (44, -32, 72), (13, 12, 14))          # cheeks
           + 0.45 * gauss(p, (0, -40, 104), (8, 9, 8))             # nose tip
           + 0.35 * gauss(q, (15, -47, 91), (6, 6, 6))             # alae
           + 0.35 * gauss(q, (72, -12, -14), (12, 20, 14))         # ears
           + 0.25 * gauss(p, (0, -100, 80), (14, 10, 10))          # chin
           + 0.20 * gauss(p, (0, 25, 90), (30, 20, 15)))           # forehead flush
    red -= 0.35 * smoothstep(-100.0, -150.0, y)                   # paler neck
    c = SKIN_LINEAR * (1.0 - np.array([0.02, 0.28, 0.24]) * np.clip(red, -1, 1)[..., None])
    # darker upper lid crease, slightly bluish under the eyes
    lid = gauss(q, (32, 8, 80), (12, 2.5, 8))
    under = gauss(q, (32, -10, 78), (11, 3.5, 8))
    c *= 1.0 - 0.15 * lid[..., None]
    c *= 1.0 - under[..., None] * np.array([0.12, 0.14, 0.06])
    # vermilion of the lips
    lip = lip_mask(p)[..., None]
    c = c * (1.0 - lip) + LIP_LINEAR * lip
    # nostrils
    nos = (1.0 - smoothstep(-0.5, 1.0, ellipsoid(q, np.array([7.0, -53.5, 98.0]), np.array([4.0, 3.0, 6.5]))))[..., None]
    c = c * (1.0 - nos) + NOSTRIL_LINEAR * nos
    return c


def _brow_mask(p):
    """Eyebrow coverage in [0, 1] at design-frame points (thick medially, tapering laterally)."""
    x, y, z = p
    s = np.clip((np.abs(x) - 12.0) / 40.0, 0.0, 1.0)
    yb = 18.5 + 5.0 * np.sin(np.pi * s) ** 0.8 - 3.0 * s
    hb = 4.3 - 2.6 * s
    m = 1.0 - smoothstep(0.6, 1.1, np.abs(y - yb) / hb)
    m *= smoothstep(10.0, 14.0, np.abs(x)) * (1.0 - smoothstep(48.0, 54.0, np.abs(x)))
    return m * smoothstep(55.0, 70.0, z)


def albedo_texture(size, rng, surface, mm_per_texel):
    """Paint the (size, size, 3) sRGB atlas: skin below v = V_SKIN, eyes in the strip above."""
    res = min(size, MASK_RES)
    rows = np.arange(res)
    v = 1.0 - rows / (res - 1.0)
    u = np.arange(res) / (res - 1.0)
    vv, uu = np.meshgrid(v, u, indexing="ij")
    p = surface(np.clip(1.0 - vv / V_SKIN, 0.0, 1.0), uu)
    lin = _paint_skin(p)
    brow = _brow_mask(p)
    if res != size:
        lin = np.stack([ndimage.zoom(lin[..., ch].astype(np.float32), size / res, order=1,
                                     grid_mode=True, mode="nearest") for ch in range(3)], -1)
        brow = ndimage.zoom(brow.astype(np.float32), size / res, order=1, grid_mode=True, mode="nearest")
    lin = lin.astype(np.float32)
    brow = brow.astype(np.float32)
    px = lambda mm: mm / mm_per_texel   # noqa: E731
    # Full-resolution work is float32 and per channel to keep the peak memory near 10 bytes/texel.
    # Luminance factor: mottling (~3 mm) and fine pigment (~0.3 mm); freckles (~0.35 mm).
    lum = 1.0 + 0.04 * _noise_at(rng, size, px(3.0))
    lum += 0.02 * _noise_at(rng, size, max(px(0.3), 0.5))
    spots = smoothstep(np.float32(2.0), np.float32(2.8), _noise_at(rng, size, max(px(0.35), 0.6)))
    blotch = _noise_at(rng, size, px(12.0))        # blotchy redness (~12 mm)
    # eyebrow hairs: streaks stretched along u (hairs run laterally), darker where dense
    hair = _noise_at(rng, size, max(px(0.12), 0.6))
    hair = ndimage.gaussian_filter1d(hair, max(1.0, px(1.5)), axis=1, mode="wrap")
    hair = smoothstep(np.float32(-0.2), np.float32(0.3), hair / np.float32(max(float(hair.std()), 1e-6)))
    hair *= np.float32(0.45)
    hair += np.float32(0.55)
    hair *= brow
    for ch, red in enumerate((0.0, 0.045, 0.04)):
        c = lin[..., ch]
        if red:
            c *= 1.0 - np.float32(red) * blotch
        c *= lum
        c *= 1.0 - spots * np.float32(1.0 - FRECKLE_TINT[ch])
        c *= 1.0 - hair
        c += np.float32(BROW_LINEAR[ch]) * hair
    # eye strip: sclera, iris, pupil in two squares at the top left
    strip = int(round(size * (1.0 - V_SKIN)))
    if strip >= 4:
        a = (np.arange(strip) + 0.5) / strip * 2.0 - 1.0
        yy, xx = np.meshgrid(-a, a, indexing="ij")
        rho = np.hypot(xx, yy) * EYE_RADIUS
        ang = np.arctan2(yy, xx)
        stri = 1.0 + 0.25 * np.sin(ang * 37.0) * np.sin(ang * 11.0 + 1.0)
        iris = IRIS_LINEAR * (0.6 + 0.8 * smoothstep(1.8, 5.0, rho) * stri)[..., None]
        eye = SCLERA_LINEAR * (1.0 - 0.25 * smoothstep(8.0, 11.5, rho))[..., None] * np.array([1.0, 0.85, 0.85])
        m_iris = (1.0 - smoothstep(5.6, 6.1, rho))[..., None]
        limbus = np.exp(-((rho - 5.7) / 0.35) ** 2)[..., None]
        eye = eye * (1.0 - m_iris) + iris * m_iris
        eye *= 1.0 - 0.6 * limbus
        eye *= (smoothstep(1.7, 2.2, rho) * 0.98 + 0.02)[..., None]
        lin[:strip, :strip] = eye
        if 2 * strip <= size:
            lin[:strip, strip:2 * strip] = eye
    return _linear_to_srgb8(lin)
