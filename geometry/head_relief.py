"""The procedural head's skin relief: a height field in mm applied along the smooth base's normal.

Pores (pits where band-limited 3D gradient noise peaks; Perlin 2002), a network of shallow
micro-relief furrows, forehead lines, glabellar lines, crow's feet, nasolabial folds, lip lines
and neck rings, all placed on design-frame landmarks (:mod:`dermis.geometry.head_shape`).
"""
from __future__ import annotations

import numpy as np

from dermis.geometry.head_shape import smoothstep

__all__ = ["detail_height", "grid_normals", "gauss", "lip_mask"]

# Skin-detail amplitudes (mm).  Pore depth and wrinkle depths are of the order reported by
# skin-replica profilometry (e.g. Lemperle et al. 2001 wrinkle scale; pores tens of microns);
# the head uses 0.06 mm pores (0.02-0.1 mm in those sources) and somewhat deeper wrinkles.
PORE_DEPTH = 0.06
PORE_SPACING = 0.9             # facial pore density ~1 per mm^2
MICRO_RELIEF = 0.015
FOREHEAD_LINE_DEPTH = 0.15
CROWS_FEET_DEPTH = 0.12
NASOLABIAL_DEPTH = 0.35
LIP_LINE_DEPTH = 0.05
NECK_LINE_DEPTH = 0.15


# ----------------------------------------------------------------------------------------------
# skin detail (height field along the normal, mm)
# ----------------------------------------------------------------------------------------------
def _noise_tables(rng):
    """Permutation and gradient tables of one 3D gradient-noise instance."""
    perm = rng.permutation(256)
    grad = rng.standard_normal((256, 3))
    grad /= np.linalg.norm(grad, axis=1, keepdims=True)
    return np.concatenate([perm, perm]), grad


def _gradient_noise(tables, x, y, z):
    """3D gradient noise (Perlin 2002, quintic fade) at lattice coordinates; ~unit amplitude."""
    perm, grad = tables
    xi, yi, zi = np.floor(x), np.floor(y), np.floor(z)
    fx, fy, fz = x - xi, y - yi, z - zi
    xi, yi, zi = (xi.astype(np.int64) & 255, yi.astype(np.int64) & 255, zi.astype(np.int64) & 255)
    fade = lambda t: t * t * t * (t * (t * 6.0 - 15.0) + 10.0)   # noqa: E731
    ux, uy, uz = fade(fx), fade(fy), fade(fz)
    out = 0.0
    for cx in (0, 1):
        px = perm[xi + cx]
        wx = ux if cx else 1.0 - ux
        for cy in (0, 1):
            pxy = perm[px + yi + cy]
            wy = uy if cy else 1.0 - uy
            for cz in (0, 1):
                h = perm[pxy + zi + cz]
                dot = grad[h, 0] * (fx - cx) + grad[h, 1] * (fy - cy) + grad[h, 2] * (fz - cz)
                out = out + wx * wy * (uz if cz else 1.0 - uz) * dot
    return out * 1.6   # raw range is about +-0.6 for unit gradients


def gauss(p, c, s):
    """Anisotropic Gaussian blob exp(-|(p - c) / s|^2 / 2) on (x, y, z) arrays."""
    return np.exp(-0.5 * (((p[0] - c[0]) / s[0]) ** 2 + ((p[1] - c[1]) / s[1]) ** 2
                          + ((p[2] - c[2]) / s[2]) ** 2))


def detail_height(p, rng):
    """Skin relief height (mm, negative = groove) at design-frame points p = (x, y, z)."""
    x, y, z = p
    ax = np.abs(x)
    front = smoothstep(30.0, 60.0, z)
    # pores: pits where band-limited noise peaks; denser and deeper on the nose and cheeks
    t_zone = np.clip(gauss(p, (0, -35, 100), (14, 22, 14)) + gauss((ax, y, z), (42, -30, 72), (16, 16, 16)), 0, 1)
    n = _gradient_noise(_noise_tables(rng), x / PORE_SPACING, y / PORE_SPACING, z / PORE_SPACING)
    h = -PORE_DEPTH * (0.6 + 0.6 * t_zone) * smoothstep(0.45 - 0.15 * t_zone, 0.85, n)
    # micro-relief: a network of shallow furrows along the zero set of a second noise
    m = _gradient_noise(_noise_tables(rng), x / 1.7, y / 1.7, z / 1.7)
    h -= MICRO_RELIEF * np.exp(-(m / 0.15) ** 2)
    ph = rng.uniform(0.0, 2.0 * np.pi, 16)
    amp = rng.uniform(0.6, 1.0, 8)
    # forehead lines: four wavy horizontal grooves, fading towards the temples
    for k in range(4):
        yk = 40.0 + 8.5 * k + 1.6 * np.sin(x / 23.0 + ph[k]) + 0.7 * np.sin(x / 8.0 + ph[k + 4])
        reach = 40.0 + 12.0 * amp[k]
        h -= (FOREHEAD_LINE_DEPTH * amp[k] * np.exp(-((y - yk) / 0.55) ** 2)
              * (1.0 - smoothstep(reach - 20.0, reach, ax)) * front)
    # glabellar (frown) lines between the brows
    h -= (0.8 * FOREHEAD_LINE_DEPTH * np.exp(-((ax - 5.5 - 0.08 * (y - 10.0)) / 0.5) ** 2)
          * smoothstep(6.0, 10.0, y) * (1.0 - smoothstep(22.0, 28.0, y)) * front)
    # crow's feet: a fan of grooves radiating from each lateral canthus
    lx, dy = ax - 44.0, y - 1.5
    rho = np.sqrt(lx * lx + dy * dy) + 1e-9
    psi = np.arctan2(dy, lx)
    step = 0.17
    s = psi / step + 0.25 * np.sin(rho / 3.0 + ph[8])
    dist = np.abs(s - np.round(s)) * step * rho
    h -= (CROWS_FEET_DEPTH * np.exp(-(dist / 0.35) ** 2) * smoothstep(3.0, 7.0, rho)
          * (1.0 - smoothstep(14.0, 22.0, rho)) * (1.0 - smoothstep(0.7, 1.0, np.abs(psi)))
          * smoothstep(35.0, 55.0, z))
    # nasolabial folds: from the nose wing down to beside the mouth corner
    u = (-46.0 - y) / 36.0
    x_c = 18.5 + 11.0 * u + 2.5 * np.sin(np.pi * u)
    h -= (NASOLABIAL_DEPTH * np.exp(-((ax - x_c) / 1.6) ** 2) * smoothstep(-0.05, 0.15, u)
          * (1.0 - smoothstep(0.85, 1.05, u)) * smoothstep(55.0, 70.0, z))
    # vertical lip lines on the vermilion
    lip = lip_mask(p)
    s = x / 1.8 + 0.4 * np.sin(y / 2.5 + ph[9])
    h -= LIP_LINE_DEPTH * np.exp(-((np.abs(s - np.round(s)) * 1.8) / 0.22) ** 2) * lip
    # neck rings on the front and sides
    for k, yk in enumerate((-140.0, -154.0)):
        wave = 2.0 * np.sin(x / 30.0 + ph[10 + k])
        h -= (NECK_LINE_DEPTH * amp[4 + k] * np.exp(-((y - yk - wave) / 0.9) ** 2)
              * smoothstep(-25.0, 10.0, z))
    return h


def lip_mask(p):
    """Vermilion coverage in [0, 1]: the lips' outline seen from the front (Cupid's bow on top)."""
    x, y, z = p
    wu = np.clip(1.0 - (x / 23.0) ** 2, 0.0, None)
    wl = np.clip(1.0 - (x / 20.5) ** 2, 0.0, None)
    bow = 1.0 * np.exp(-(np.abs(x) - 5.0) ** 2 / 8.0) - 1.0 * np.exp(-x * x / 4.0)
    top = -73.5 + (6.8 + bow) * wu ** 0.45
    bottom = -73.5 - 8.0 * wl ** 0.55
    inside = np.minimum(top - y, y - bottom)
    return smoothstep(-0.3, 0.3, inside) * smoothstep(74.0, 80.0, z)


def grid_normals(pos, top, bottom):
    """Outward unit normals of the ring grid (n_t, n_p, 3) by central differences."""
    up = np.concatenate([np.broadcast_to(top, (1,) + pos.shape[1:]), pos[:-1]])
    down = np.concatenate([pos[1:], np.broadcast_to(bottom, (1,) + pos.shape[1:])])
    d_t = down - up
    d_p = np.roll(pos, -1, axis=1) - np.roll(pos, 1, axis=1)
    n = np.cross(d_t, d_p)
    return n / np.maximum(np.linalg.norm(n, axis=-1, keepdims=True), 1e-300)
