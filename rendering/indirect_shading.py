"""A BRDF's response to one bounce of indirect light (docs/science.md §6 "Indirect light").

At each camera hit the indirect irradiance E_ind (stage ``indirect``, per vertex, interpolated
with the hit's barycentrics) is taken as diffuse, uniform incident radiance E_ind / pi, so the
reflected radiance is

    L_ind(wo) = int f(wo, wi) (E_ind / pi) cos(theta_i) dwi = rho_dh(wo) E_ind / pi,

rho_dh the model's own directional-hemispherical albedo.  The incident light's true direction
is not used: the bounce is assumed diffuse (lighting/indirect.py).

**rho_dh from the model's own kernel.**  Every BRDF of ``cl/shade.cl`` is isotropic (rho_dh
depends on wo through mu_o = cos(theta_o) only) and affine in the linear albedo a it reads per
hit (Lambert, Lafortune's matte term, HK93's tint of rho_ms, the asperity term over its base),
so rho_dh(mu_o, a) = R0(mu_o) + a (R1(mu_o) - R0(mu_o)) with R0, R1 the albedo at a = 0 and
a = 1.  Both are tabulated once per image at ``TABLE_NODES`` cosines by the model's kernel
itself (the shading call of rendering/shade.py built on synthetic hits), each from
``TABLE_DIRECTIONS`` stratified cosine-weighted directions (each of weight pi / (S cos), so
the kernel's f W cos sums to pi mean(f)), and read per hit by linear interpolation in mu_o.
The table, not per-hit Monte Carlo: the skin fit's sharp Lafortune lobe made 1 / 4 / 16 / 64
cosine directions per hit leave 10.7 / 4.9 / 2.2 / 0.9 % noise per pixel on the default scan
(200 x 200, spp 4; asperity 1.6 / 1.0 / 0.5 / 0.2 %; bench/results/indirect.json
"directions"), whose means agree with the table's within that noise; the table leaves none
and costs 0.3-0.7 s an image.

Guarded by tests/test_indirect.py (Lambert: L_ind = a E_ind / pi at every hit; Lafortune:
its closed-form directional albedo L(mu_o) + a (1 - L(mu_o)); finite, never negative).
"""
from __future__ import annotations

from types import SimpleNamespace
from typing import Callable

import numpy as np

from dermis.lighting.strata import stratified_2d
from dermis.lighting.visibility import interpolate
from dermis.lighting.warps import cosine_hemisphere

__all__ = ["TABLE_NODES", "TABLE_DIRECTIONS", "albedo_table", "indirect_radiance"]

# Cosines mu_o of the table, uniform in [0, 1] (linear interpolation between them).
TABLE_NODES = 65
# Cosine-weighted directions per node and albedo (a 128 x 128 jittered grid).  Measured
# against Lafortune's closed-form directional albedo (lafortune_lobe_albedo): the lobes' part
# within 0.4 % (0.13 % with 4x the directions), 2e-4 of rho_dh at albedo 1; ~1 s per image.
TABLE_DIRECTIONS = 1 << 14
# Kernel samples per shading call (~60 bytes each on the host, as rendering/shade.py's batches).
TABLE_BATCH = 1 << 20


def albedo_table(make_shader: Callable, texture, *, nodes: int = TABLE_NODES,
                 directions: int = TABLE_DIRECTIONS, seed: int = 0) -> np.ndarray:
    """(2, nodes, 3) float64 directional-hemispherical albedo R0, R1 of a model at
    mu_o = j / (nodes - 1), at linear albedo 0 and 1 (module docstring).

    make_shader : ``make_shader(px) -> shader``, the model's shading call built on hits
        ``px`` (``px.surf`` shading_normal, wo, albedo; ``px.texture``), as
        rendering/shade.py ``_Shader``; ``shader(gidx, dirs, wts) -> (f W cos, seconds)``.
    texture : the image's ``PixelSurface.texture`` (whether its albedo is textured: HK93
        reads the albedo only then)
    """
    mu = np.linspace(0.0, 1.0, nodes)
    # grazing node: mu_o = 0 exactly is below every BRDF's horizon test (f = 0); the hits
    # never see it (shading normals are bent to mu_o >= 0.1, cl/surface.cl), its value
    # only anchors the interpolation
    wo = np.stack([np.sqrt(np.maximum(1.0 - mu * mu, 0.0)), np.zeros(nodes), mu], axis=1)
    k = 2 * nodes
    surf = {"shading_normal": np.tile(np.float32([0, 0, 1]), (k, 1)),
            "wo": np.concatenate([wo, wo]).astype(np.float32),
            "albedo": np.repeat(np.float32([[0, 0, 0], [1, 1, 1]]), nodes, axis=0)}
    shader = make_shader(SimpleNamespace(surf=surf, texture=texture))
    rng = np.random.default_rng(seed)
    u = stratified_2d(rng, 1, directions)
    d, cos = cosine_hemisphere(u, np.float64([[0, 0, 1]]))
    d, cos = d[0], cos[0]
    live = cos > 0
    d, w1 = d[live].astype(np.float32), np.pi / (directions * cos[live])
    out = np.zeros((k, 3), np.float64)
    group = max(1, TABLE_BATCH // len(d))          # hits per kernel call
    dirs = np.tile(d, (group, 1))
    wts = np.tile(np.repeat(w1[:, None], 3, axis=1).astype(np.float32), (group, 1))
    for h0 in range(0, k, group):
        hs = np.arange(h0, min(k, h0 + group), dtype=np.int32)
        n = len(hs) * len(d)
        f, _ = shader(np.repeat(hs, len(d)), dirs[:n], wts[:n])
        out[hs] = f.reshape(len(hs), len(d), 3).sum(axis=1, dtype=np.float64)
    return out.reshape(2, nodes, 3)


def indirect_radiance(px, make_shader: Callable, faces: np.ndarray,
                      vertex_irradiance: np.ndarray) -> np.ndarray:
    """(H*W, 3) float64 radiance of the model's response to E_ind, box-filtered as the
    direct light's (:func:`dermis.rendering.shade.shade`: per-hit sums / spp).

    px : rendering.surface.PixelSurface of the image's hits
    make_shader : the model's shading call for given hits (:func:`albedo_table`)
    faces : (F, 3) the mesh's faces (the hits' triangles index them)
    vertex_irradiance : (V, 3) E_ind at the mesh's vertices
    """
    table = albedo_table(make_shader, px.texture)
    nodes = table.shape[1]
    mu = np.einsum("ij,ij->i", px.surf["shading_normal"], px.surf["wo"]).astype(np.float64)
    x = np.clip(mu, 0.0, 1.0) * (nodes - 1)
    j = np.minimum(x.astype(np.int64), nodes - 2)
    t = (x - j)[:, None]
    r0 = table[0, j] * (1 - t) + table[0, j + 1] * t
    r1 = table[1, j] * (1 - t) + table[1, j + 1] * t
    rho = r0 + np.asarray(px.surf["albedo"], np.float64) * (r1 - r0)
    e_ind = interpolate(vertex_irradiance, faces, px.samples.tri, px.samples.bary)
    return px.pixels(rho * e_ind / np.pi).astype(np.float64)
