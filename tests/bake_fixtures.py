"""Synthetic meshes for the bake tests and benchmark: lat-long spheres with analytic UVs.

Not collected by pytest (no ``test_`` prefix); bench/bench_bake.py imports it too.
"""
from __future__ import annotations

from typing import Callable

import numpy as np

from dermis.pipeline.artifacts import Mesh


def latlong_sphere(nlat: int, nlon: int, radius: float | Callable[[np.ndarray], np.ndarray],
                   *, texture_srgb: np.ndarray | None = None, radial_normals: bool = True) -> Mesh:
    """Sphere tessellated on a latitude-longitude grid, with seam-split per-corner UVs.

    theta (polar angle from +z) = pi * (1 - v), phi = 2 pi u.  The poles are single vertices;
    the u = 0 / u = 1 seam shares positions but not UVs.  ``radius`` is a number (mm) or a
    function of unit directions (N, 3) -> (N,) radii.  Faces are counter-clockwise seen from
    outside.  ``radial_normals`` stores the unit directions as vertex normals (exact for a
    sphere); otherwise normals are None (the bake computes angle-weighted ones).
    """
    theta = np.pi * np.arange(1, nlat) / nlat
    phi = 2 * np.pi * np.arange(nlon) / nlon
    st, ct = np.sin(theta)[:, None], np.cos(theta)[:, None]
    ring = np.stack([st * np.cos(phi), st * np.sin(phi), np.broadcast_to(ct, (nlat - 1, nlon))],
                    axis=-1).reshape(-1, 3)
    dirs = np.concatenate([[[0.0, 0.0, 1.0]], ring, [[0.0, 0.0, -1.0]]])
    r = radius(dirs) if callable(radius) else np.full(len(dirs), float(radius))
    vertices = dirs * r[:, None]
    south = len(dirs) - 1

    def vid(i, j):
        """Position index of grid node (i, j); rows 0 and nlat are the poles."""
        j = np.asarray(j) % nlon
        return np.where(i == 0, 0, np.where(i == nlat, south, 1 + (i - 1) * nlon + j))

    def tid(i, j):
        """UV index of grid node (i, j) on the (nlat + 1) x (nlon + 1) UV grid."""
        return i * (nlon + 1) + j

    ii, jj = np.meshgrid(np.arange(nlat), np.arange(nlon), indexing="ij")
    ii, jj = ii.ravel(), jj.ravel()
    a, b, c, d = (ii, jj), (ii + 1, jj), (ii + 1, jj + 1), (ii, jj + 1)
    upper = ii < nlat - 1          # (a, b, c) degenerate at the south pole (b, c = pole)
    lower = ii > 0                 # (a, c, d) degenerate at the north pole (a, d = pole)
    faces, uv_faces = [], []
    for tri, keep in (((a, b, c), upper), ((a, c, d), lower)):
        faces.append(np.stack([vid(*q) for q in tri], axis=1)[keep])
        uv_faces.append(np.stack([tid(*q) for q in tri], axis=1)[keep])
    gi, gj = np.meshgrid(np.arange(nlat + 1), np.arange(nlon + 1), indexing="ij")
    uv = np.stack([gj.ravel() / nlon, 1.0 - gi.ravel() / nlat], axis=1)
    return Mesh(vertices=vertices, faces=np.concatenate(faces).astype(np.int32),
                normals=dirs.astype(np.float32) if radial_normals else None,
                uv=uv.astype(np.float32), uv_faces=np.concatenate(uv_faces).astype(np.int32),
                texture_srgb=texture_srgb)


def direction_of_uv(u: np.ndarray, v: np.ndarray) -> np.ndarray:
    """Unit direction of the lat-long parameterisation at (u, v)."""
    theta, phi = np.pi * (1.0 - v), 2 * np.pi * u
    return np.stack([np.sin(theta) * np.cos(phi), np.sin(theta) * np.sin(phi), np.cos(theta)], -1)


def smooth_colour(dirs: np.ndarray) -> np.ndarray:
    """A smooth linear-RGB colour field on the unit sphere, values in [0.1, 0.9]."""
    x, y, z = dirs[..., 0], dirs[..., 1], dirs[..., 2]
    return np.stack([0.5 + 0.4 * np.sin(2 * x + y), 0.5 + 0.4 * np.cos(3 * z - x),
                     0.5 + 0.4 * np.sin(x * y + 2 * z)], axis=-1)


def srgb8(linear: np.ndarray) -> np.ndarray:
    """Linear [0, 1] -> sRGB uint8 (IEC 61966-2-1), independent of geometry/bake.py."""
    c = np.clip(linear, 0, 1)
    s = np.where(c <= 0.0031308, 12.92 * c, 1.055 * c ** (1 / 2.4) - 0.055)
    return np.rint(s * 255).astype(np.uint8)


def latlong_texture(height: int, width: int,
                    colour: Callable[[np.ndarray], np.ndarray] = smooth_colour) -> np.ndarray:
    """sRGB uint8 texture whose texel (row, col) holds ``colour`` at the lat-long direction of
    u = col / (W - 1), v = 1 - row / (H - 1) (the project's texel-centre rule)."""
    rows, cols = np.meshgrid(np.arange(height), np.arange(width), indexing="ij")
    d = direction_of_uv(cols / (width - 1), 1.0 - rows / (height - 1))
    return srgb8(colour(d))


def bumpy_radius(radius: float, amplitude: float,
                 field: Callable[[np.ndarray], np.ndarray] | None = None):
    """r(dir) = radius + amplitude * f(dir); default f is smooth with |f| <= 1."""
    f = field if field is not None else (
        lambda d: np.sin(3 * d[..., 0] + d[..., 1]) * np.cos(2 * d[..., 2]))
    return lambda d: radius + amplitude * f(d)
