"""A BRDF's response to one bounce of indirect light (docs/science.md §6 "Indirect light").

At each camera hit the indirect irradiance E_ind (stage ``indirect``, per vertex, interpolated
with the hit's barycentrics) is taken as diffuse, uniform incident radiance E_ind / pi, so the
reflected radiance is

    L_ind(wo) = int f(wo, wi) (E_ind / pi) cos(theta_i) dwi = rho_dh(wo) E_ind / pi,

rho_dh(wo) the model's own directional-hemispherical albedo at the hit (texture, bump-mapped
shading normal and all).  It is estimated with the model's own kernel (``cl/shade.cl``, the
same call as the light samples'): ``DIRECTIONS`` cosine-weighted directions per hit about the
shading normal, each of weight E_ind / (S cos(theta_i)), so the kernel's f W cos(theta_i)
sums to (E_ind / S) sum_s f(wo, wi_s), an unbiased estimate of rho_dh E_ind / pi (exact for a
Lambertian BRDF).  The incident light's true direction is not used: the bounce is assumed
diffuse (lighting/indirect.py).

Guarded by tests/test_indirect.py (Lambert: L_ind = albedo E_ind / pi at every hit, finite,
never negative).
"""
from __future__ import annotations

import numpy as np

from dermis.lighting.indirect import interpolate
from dermis.lighting.strata import stratified_2d
from dermis.lighting.warps import cosine_hemisphere

__all__ = ["DIRECTIONS", "indirect_radiance"]

# Directions per camera hit (a pixel averages spp x DIRECTIONS).  MEASURED-DIRECTIONS
DIRECTIONS = 4
# Hits per batch: DIRECTIONS x this many kernel samples (~60 bytes each on the host).
CHUNK_HITS = 1 << 18


def indirect_radiance(px, shader, faces: np.ndarray, vertex_irradiance: np.ndarray, *,
                      seed: int = 0, directions: int = DIRECTIONS) -> np.ndarray:
    """(H*W, 3) float64 radiance of the model's response to E_ind, box-filtered as the
    direct light's (:func:`dermis.rendering.shade.shade`: per-hit sums / spp).

    px : rendering.surface.PixelSurface of the image's hits
    shader : ``shader(gidx, dirs, wts) -> (f W cos(theta_i) per sample, seconds)``, the
        model's shading call (rendering/shade.py ``_Shader``)
    faces : (F, 3) the mesh's faces (the hits' triangles index them)
    vertex_irradiance : (V, 3) E_ind at the mesh's vertices
    """
    s = int(directions)
    samples = px.samples
    n_pix = px.width * px.height
    radiance = np.zeros((n_pix, 3), np.float64)
    normals = np.asarray(px.surf["shading_normal"], np.float64)
    for c, start in enumerate(range(0, len(px.hit_idx), CHUNK_HITS)):
        hits = np.arange(start, min(len(px.hit_idx), start + CHUNK_HITS))
        e_ind = interpolate(vertex_irradiance, faces, samples.tri[hits], samples.bary[hits])
        rng = np.random.default_rng((seed, c))
        d, cos = cosine_hemisphere(stratified_2d(rng, len(hits), s), normals[hits])
        # W = E_ind / (S cos): the kernel's f W cos is then f E_ind / S (module docstring);
        # a direction on the horizon (cos = 0, probability 0) is given no weight
        w = np.where(cos[..., None] > 0, e_ind[:, None, :] / (s * np.where(cos > 0, cos, 1.0))
                     [..., None], 0.0)
        gidx = np.repeat(hits.astype(np.int32), s)
        out, _ = shader(gidx, d.reshape(-1, 3).astype(np.float32),
                        w.reshape(-1, 3).astype(np.float32))
        pix = px.hit_idx[gidx]
        for k in range(3):
            radiance[:, k] += np.bincount(pix, weights=out[:, k], minlength=n_pix)
    return radiance / px.spp
