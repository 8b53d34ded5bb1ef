"""One bounce of indirect light: the irradiance a surface point receives from the rest of the
surface, lit directly (docs/science.md §6 "Indirect light").

The models shade with direct light only (the thesis's choice); a path tracer also carries the
light the skin re-emits onto itself, which brightens concavities most (eye sockets, under the
nose, the ears).  This module estimates the first of those bounces:

    E_ind(x) = int_H L_1(y(x, w)) cos(theta) dw,    L_1(y) = a(y) E_dir(y) / pi,

y(x, w) the first surface point seen from x along w (nothing: L_1 = 0), E_dir(y) the direct
irradiance at y with shadows (:func:`dermis.lighting.irradiance.irradiance` at the mesh
vertices, interpolated at y with the hit's barycentrics) and a(y) the linear albedo there
(the albedo texture at the hit's UV, sRGB decoded as ``cl/surface.cl`` does; a constant
where the mesh has none).

**Approximation.**  The bounce is Lambertian with the skin's total diffuse reflectance: the
texture's albedo is taken as the fraction of E_dir the skin sends back, spread uniformly over
the hemisphere (radiance a E_dir / pi).  The specular surface reflection (a few % of E_dir,
peaked about the mirror direction), the lateral transport of the subsurface light (E_dir
blurred over the profile's ~mm width) and the second and later bounces are left out.  A
surface seen from behind (a ray into the mesh through an opening) re-emits nothing.

**Estimator.**  ``samples`` cosine-weighted directions per point (Malley's method on a
jittered grid, ``lighting/strata.py``), so E_ind = (1 / S) sum_s a(y_s) E_dir(y_s), the pi
of L_1 cancelling the cosine pdf's.  A convex surface sees nothing of itself: every ray
misses and E_ind = 0 exactly.  Rays leave from the point pushed ``Visibility.offset_mm``
along its normal.  Points are processed in independent batches (own seed, own rows of the
result) on ``IRRADIANCE_THREADS`` threads, so the result does not depend on the thread
count, as in :func:`dermis.lighting.irradiance.irradiance`.

Guarded by tests/test_indirect.py (a lit wall beside a floor against the closed-form form
factor, a sphere: exactly 0).
"""
from __future__ import annotations


import numpy as np

from dermis.geometry.normals import vertex_normals
from dermis.geometry.texture_lookup import SRGB8_TO_LINEAR, bilinear
from dermis.lighting.emitters import SamplingOptions
from dermis.lighting.irradiance import irradiance, run_batches
from dermis.lighting.strata import stratified_2d
from dermis.lighting.visibility import interpolate
from dermis.lighting.warps import cosine_hemisphere
from dermis.pipeline.errors import DermisError

__all__ = ["at_points", "surface_albedo", "bounce_irradiance", "one_bounce", "CHUNK_RAYS"]

# Rays per batch: the batch's arrays (origins, directions, hits, the hit's albedo and E_dir,
# ~100 bytes a ray) stay ~50 MB.
CHUNK_RAYS = 1 << 19


def at_points(values: np.ndarray, mesh, points: np.ndarray, visibility) -> np.ndarray:
    """(N, C) float32 per-vertex ``values`` of ``mesh`` at ``points`` (N, 3) mm on its
    surface: interpolated at each point's closest surface point (``Visibility.closest``)."""
    near = visibility.closest(points)
    return interpolate(values, mesh.faces, near.tri, near.bary)


def surface_albedo(mesh, tri: np.ndarray, bary: np.ndarray, fallback) -> np.ndarray:
    """(M, 3) float32 linear albedo of ``mesh`` at hits (``tri``, ``bary``): its texture
    (bilinear, sRGB decoded per texel, the lookup of ``cl/surface.cl``) at the interpolated
    UV, or ``fallback`` (3,) where the mesh has no texture or no UVs."""
    if mesh.texture_srgb is None or mesh.uv is None or mesh.uv_faces is None:
        return np.broadcast_to(np.asarray(fallback, np.float32), (len(tri), 3))
    uv = interpolate(mesh.uv, mesh.uv_faces, tri, bary)
    return bilinear(np.asarray(mesh.texture_srgb), uv, SRGB8_TO_LINEAR)


def _oriented_face_normals(vertices, faces, normals) -> np.ndarray:
    """(F, 3) float32 geometric face normals, flipped where they disagree with the sum of the
    face's vertex normals (the side the mesh calls outside)."""
    v = np.asarray(vertices, np.float32)
    f = np.asarray(faces)
    fn = np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]])
    n = np.asarray(normals, np.float32)
    side = np.einsum("ij,ij->i", fn, n[f[:, 0]] + n[f[:, 1]] + n[f[:, 2]])
    fn[side < 0] *= -1.0
    return fn


def bounce_irradiance(points: np.ndarray, normals: np.ndarray, mesh, direct: np.ndarray,
                      visibility, *, samples: int, seed: int = 0,
                      fallback_albedo=(0.5, 0.5, 0.5)) -> np.ndarray:
    """One-bounce indirect irradiance E_ind at surface points (module docstring).

    Parameters
    ----------
    points : (N, 3) float, mm, on (or just above) the surface of ``mesh``
    normals : (N, 3) float, unit outward normals (zero rows: E_ind = 0)
    mesh : pipeline.artifacts.Mesh, the surface the rays hit (and its albedo texture)
    direct : (V, 3) float, the direct irradiance E_dir at the mesh's vertices (with shadows)
    visibility : lighting.visibility.Visibility of ``mesh``
    samples : int, cosine-weighted rays per point
    seed : int
    fallback_albedo : (3,) linear albedo where the mesh has no texture

    Returns
    -------
    (N, 3) float32 E_ind, in the units of ``direct``.
    """
    p = np.asarray(points, np.float32)
    n = np.asarray(normals, np.float32)
    if p.ndim != 2 or p.shape[1] != 3 or n.shape != p.shape:
        raise DermisError(f"indirect: points {p.shape} and normals {n.shape} must both be (N, 3)")
    e_dir = np.asarray(direct, np.float32)
    if e_dir.shape != (len(mesh.vertices), 3):
        raise DermisError(f"indirect: direct irradiance has shape {e_dir.shape}; need "
                          f"({len(mesh.vertices)}, 3), one row per vertex")
    s = int(samples)
    if s < 1:
        raise DermisError(f"indirect: samples = {samples}; need >= 1")
    faces = np.asarray(mesh.faces)
    face_n = _oriented_face_normals(mesh.vertices, faces, vertex_normals(mesh))
    out = np.zeros((len(p), 3), np.float32)
    chunk = max(1, CHUNK_RAYS // s)
    offset = np.float32(visibility.offset_mm)

    def batch(c: int) -> None:
        start = c * chunk
        ps, ns = p[start:start + chunk], n[start:start + chunk]
        live = np.einsum("ij,ij->i", ns, ns) > 0.5          # unit normals; zero rows: none
        rng = np.random.default_rng((seed, c))
        d, cos = cosine_hemisphere(stratified_2d(rng, len(ps), s), np.where(
            live[:, None], ns, np.float32(1.0)))
        origins = np.repeat(ps + offset * ns, s, axis=0)
        hits = visibility.intersect(origins, d.reshape(-1, 3).astype(np.float32))
        ok = hits.hit & np.repeat(live, s) & (cos.ravel() > 0)
        idx = np.flatnonzero(ok)
        tri = hits.tri[idx]
        # a surface seen from behind (through an opening of the mesh) re-emits nothing
        front = np.einsum("ij,ij->i", face_n[tri], d.reshape(-1, 3)[idx]) < 0
        idx, tri, bary = idx[front], tri[front], hits.bary[idx[front]]
        radiosity = interpolate(e_dir, faces, tri, bary)       # a E_dir = pi L_1 at the hits
        radiosity *= surface_albedo(mesh, tri, bary, fallback_albedo)
        acc = np.zeros((len(ps), 3), np.float64)
        owner = idx // s
        for k in range(3):
            acc[:, k] = np.bincount(owner, weights=radiosity[:, k], minlength=len(ps))
        out[start:start + chunk] = acc / s

    run_batches(batch, len(p), chunk)
    return out


def one_bounce(mesh, lights, visibility, *, samples: int, direct_samples: int, seed: int = 0,
               fallback_albedo=(0.5, 0.5, 0.5)) -> tuple[np.ndarray, np.ndarray]:
    """E_ind at every vertex of ``mesh`` under ``lights``: the direct irradiance at the
    vertices (with shadows; ``direct_samples`` light samples for disc and environment lights),
    then :func:`bounce_irradiance` from the vertices with their normals.

    Returns ((V, 3) float32 E_ind, (V, 3) float32 E_dir) at the vertices."""
    v = np.asarray(mesh.vertices, np.float32)
    n = vertex_normals(mesh)
    direct = irradiance(v, n, lights, visibility.occluded, seed=seed,
                        options=SamplingOptions(samples=int(direct_samples)))
    e_ind = bounce_irradiance(v, n, mesh, direct, visibility, samples=samples, seed=seed + 1,
                              fallback_albedo=fallback_albedo)
    return e_ind, direct
