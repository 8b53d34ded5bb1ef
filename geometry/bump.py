"""Bump mapping for the renderer: per-triangle tangent frames and Blinn bump-mapped shading
normals from a baked bump map (J. F. Blinn, "Simulation of wrinkled surfaces", SIGGRAPH 1978),
with the map's mm scale (``BakedMaps.bump_range_mm``).

:func:`bump_shading_normals_at_hits` starts from low-mesh triangle ids and barycentrics, as
the ray casters return them; ``cl/surface.cl`` computes the same normals on the device
(tests/test_render.py compares the two).
"""
from __future__ import annotations

import numpy as np

from dermis.geometry.texture_lookup import bilinear
from dermis.pipeline.artifacts import BakedMaps, Mesh
from dermis.pipeline.errors import DermisError
from dermis.geometry.normals import renormalise_f64, vertex_normals

__all__ = ["triangle_tangent_frames", "bump_shading_normals", "bump_shading_normals_at_hits"]


def triangle_tangent_frames(vertices: np.ndarray, faces: np.ndarray, uv: np.ndarray,
                            uv_faces: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per-triangle partial derivatives of position with respect to the texture coordinates.

    Parameters
    ----------
    vertices : (V, 3) float, mm
    faces : (F, 3) int
    uv : (T, 2) float
    uv_faces : (F, 3) int, per-corner indices into ``uv``

    Returns
    -------
    dpdu, dpdv : (F, 3) float64 each, mm per unit of u (resp. v)
        Solve ``[p1 - p0, p2 - p0] = [dpdu, dpdv] @ [[u1 - u0, u2 - u0], [v1 - v0, v2 - v0]]``
        (pbrt's ``Triangle::Intersect`` derivation).  Triangles with a degenerate UV
        parameterisation (|det| < 1e-20) get zero vectors, which turns bump mapping off there.
    """
    v = np.asarray(vertices, dtype=np.float64)[np.asarray(faces)]
    t = np.asarray(uv, dtype=np.float64)[np.asarray(uv_faces)]
    dp1, dp2 = v[:, 1] - v[:, 0], v[:, 2] - v[:, 0]
    du1, du2 = t[:, 1, 0] - t[:, 0, 0], t[:, 2, 0] - t[:, 0, 0]
    dv1, dv2 = t[:, 1, 1] - t[:, 0, 1], t[:, 2, 1] - t[:, 0, 1]
    det = du1 * dv2 - du2 * dv1
    ok = np.abs(det) > 1e-20
    inv = np.divide(1.0, det, out=np.zeros_like(det), where=ok)[:, None]
    dpdu = (dv2[:, None] * dp1 - dv1[:, None] * dp2) * inv
    dpdv = (du1[:, None] * dp2 - du2[:, None] * dp1) * inv
    return dpdu, dpdv


def bump_shading_normals(normals: np.ndarray, dpdu: np.ndarray, dpdv: np.ndarray,
                         uv: np.ndarray, bump: np.ndarray, *, bump_range_mm: float,
                         step_texels: float = 1.0) -> np.ndarray:
    """Blinn bump-mapped unit shading normals at surface points.

    Parameters
    ----------
    normals : (N, 3) float
        Interpolated (smooth) shading normals of the low mesh, outward; need not be unit.
    dpdu, dpdv : (N, 3) float, mm per unit u / v
        Tangent frame of the triangle under each point (``triangle_tangent_frames()[tri]``).
    uv : (N, 2) float
        Texture coordinates of the points (bottom-left origin).
    bump : (R, R) float
        Normalised bump map (``BakedMaps.bump`` or ``bump_blur``).
    bump_range_mm : float
        mm per unit of ``bump`` (``BakedMaps.bump_range_mm``); the offset does not matter.
    step_texels : float, optional
        Half-width of the central difference, texels.  Default 1 (the map's own resolution;
        smaller steps only resolve the bilinear kinks).

    Returns
    -------
    (N, 3) float32 unit normals.  Zero bump, or zero (degenerate) tangent frames, return the
    normalised input normals unchanged.

    Notes
    -----
    The bumped surface is ``p'(u, v) = p + h(u, v) n`` with height ``h`` in mm, outward
    positive (positive ``h`` raises the surface along ``n``).  Dropping the ``h dn/du`` terms
    (Blinn 1978; pbrt's ``BumpMap`` keeps them, but they are O(h / radius of curvature), < 1 %
    for sub-mm bumps on a face) and writing ``n`` for ``dpdu x dpdv / |dpdu x dpdv|`` gives

        n' = normalize( n + s * (h_u (n x dpdv) - h_v (n x dpdu)) / |dpdu x dpdv| ),

    with ``h_u = dh/du``, ``h_v = dh/dv`` (central differences of bilinear lookups) and
    ``s = sign((dpdu x dpdv) . n)``, which is -1 on mirrored UV charts and keeps the tilt
    right there.  Check on a plane ``p = (a u, a v, 0)``: a ramp ``h = k u`` gives
    ``n' ∝ (-k / a, 0, 1)``, i.e. the normal tilts toward ``-dpdu`` by ``atan(k / a)`` --
    the exact normal of the surface ``z = k x / a``.

    References
    ----------
    J. F. Blinn, "Simulation of wrinkled surfaces", SIGGRAPH 1978, doi:10.1145/965139.507101.
    """
    n = np.asarray(normals, dtype=np.float64)
    n = n / np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-300)
    dpdu = np.asarray(dpdu, dtype=np.float64)
    dpdv = np.asarray(dpdv, dtype=np.float64)
    uv = np.asarray(uv, dtype=np.float64)
    bump = np.asarray(bump, dtype=np.float32)
    if bump.ndim != 2:
        raise DermisError(f"bump_shading_normals: bump has shape {bump.shape}; need (R, R)")
    step = np.array([step_texels / max(bump.shape[1] - 1, 1),
                     step_texels / max(bump.shape[0] - 1, 1)])
    du = np.array([step[0], 0.0])
    dv = np.array([0.0, step[1]])
    h_u = (bilinear(bump, uv + du) - bilinear(bump, uv - du)) * (bump_range_mm / (2 * step[0]))
    h_v = (bilinear(bump, uv + dv) - bilinear(bump, uv - dv)) * (bump_range_mm / (2 * step[1]))
    cross = np.cross(dpdu, dpdv)
    area = np.linalg.norm(cross, axis=1)
    sign = np.where(np.einsum("nd,nd->n", cross, n) < 0, -1.0, 1.0)
    scale = np.divide(sign, area, out=np.zeros_like(area), where=area > 1e-300)
    perturbed = n + scale[:, None] * (h_u[:, None] * np.cross(n, dpdv)
                                      - h_v[:, None] * np.cross(n, dpdu))
    out = perturbed / np.maximum(np.linalg.norm(perturbed, axis=1, keepdims=True), 1e-300)
    return out.astype(np.float32)


def bump_shading_normals_at_hits(low: Mesh, maps: BakedMaps, tri_ids: np.ndarray,
                                 bary: np.ndarray, *, blurred: bool = False) -> np.ndarray:
    """Bump-mapped shading normals at points given by low-mesh triangle and barycentrics.

    Parameters
    ----------
    low : Mesh
        The mesh the maps were baked into (uv, uv_faces; normals or libigl's).
    maps : BakedMaps
    tri_ids : (N,) int, triangle index of each point
    bary : (N, 2) float, barycentrics (b1, b2) of corners 1 and 2, as Embree's / open3d's
        ``primitive_uvs``: point = (1 - b1 - b2) p0 + b1 p1 + b2 p2
    blurred : bool, optional
        Use ``maps.bump_blur`` instead of ``maps.bump``.

    Returns
    -------
    (N, 3) float32 unit shading normals (see :func:`bump_shading_normals`).
    """
    low.check("bump mapping: low", need_uv=True)
    tri_ids = np.asarray(tri_ids, dtype=np.int64)
    b = np.asarray(bary, dtype=np.float64)
    w = np.stack([1.0 - b[:, 0] - b[:, 1], b[:, 0], b[:, 1]], axis=1)
    faces = np.asarray(low.faces)
    uvf = np.asarray(low.uv_faces)
    normals = renormalise_f64(vertex_normals(low))
    n = np.einsum("nk,nkd->nd", w, normals[faces[tri_ids]])
    uv = np.einsum("nk,nkd->nd", w, np.asarray(low.uv, dtype=np.float64)[uvf[tri_ids]])
    dpdu, dpdv = triangle_tangent_frames(low.vertices, faces, low.uv, uvf)
    return bump_shading_normals(n, dpdu[tri_ids], dpdv[tri_ids], uv,
                                maps.bump_blur if blurred else maps.bump,
                                bump_range_mm=maps.bump_range_mm)
