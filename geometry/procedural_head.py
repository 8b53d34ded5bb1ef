"""The embedded default scan: a deterministic procedural human head (skin, eyes, albedo texture).

The skin is one closed, star-shaped surface around a centre ``C``: an implicit field built
from smooth unions of ellipsoids, capsules and slabs (cranium, face, jaw, neck, brow ridge,
eye sockets and lids, nose with alae and nostrils, lips, chin, ears) is solved for its radius
along every direction of a latitude-longitude grid.  The grid's polar angle is re-spaced so
that the meridian arc length per ring is constant (the neck would otherwise get a few rings),
and its size is chosen from the requested triangle count.  Because every vertex sits on its
own ray from ``C`` the surface cannot self-intersect, and the grid's topology (rings closed
by a fan at each pole) makes it a closed 2-manifold with Euler characteristic 2.

Skin-scale detail (pores, fine micro-relief, forehead lines, crow's feet, nasolabial folds,
lip lines, neck rings) is a height field in mm applied along the vertex normal of the smooth
base.  The UV map is the grid's own (longitude -> u with the seam at the back of the head,
ring -> v); seam vertices are duplicated in UV space only.  The albedo texture is painted in
that UV space from anatomical region masks plus band-limited noise.  Eyeballs are separate
closed icospheres sitting in the sockets, textured in a strip at the top of the atlas.

Frame: mm, Y up, face towards +Z, placed like the Lee Perry-Smith scan (nose tip near
(0, -35, 51) mm, top of the head near y = 120 mm; scenes/assets/README.md).
"""
from __future__ import annotations

import numpy as np
from scipy import ndimage

from dermis.geometry.head_albedo import albedo_texture
from dermis.geometry.head_relief import detail_height, grid_normals
from dermis.geometry.head_shape import (EYE_CENTRES, EYE_RADIUS, V_SKIN, bisect_radius, eye_aperture,
                                        grid_faces, grid_size, grid_uv, icosphere, pilot_solve,
                                        ray_points, ring_schedule, solve_grid)
from dermis.pipeline.artifacts import Mesh
from dermis.pipeline.errors import ConfigError

__all__ = ["VERSION", "FRAME_OFFSET", "make_head"]

VERSION = 1

# ----------------------------------------------------------------------------------------------
# limits
# ----------------------------------------------------------------------------------------------
MIN_TRIANGLES = 2_000          # below this the face features are not resolved at all
MAX_TRIANGLES = 20_000_000     # ~10M vertices: a few GB of float64 work arrays
MIN_TEXTURE, MAX_TEXTURE = 64, 16384   # same range as pipeline.config mesh.procedural_texture_size
EYE_FRACTION = 0.01            # eyeballs get at most ~1% of the triangle budget (our choice)

# Design frame -> output frame: the modelled nose tip, (0, -38.2, 113.4) mm in the design frame,
# is shifted to where the Lee Perry-Smith scan has it, (0, -35, 51) mm (measured from
# LeePerrySmith_cm.obj), so cameras framed for the scan frame this head too.
FRAME_OFFSET = np.array([0.0, 3.2, -62.4])


# ----------------------------------------------------------------------------------------------
# public entry point
# ----------------------------------------------------------------------------------------------
def _validate(triangles, detail, texture_size, seed):
    """Refuse bad arguments with a ConfigError naming the parameter, the value and the rule."""
    if isinstance(triangles, bool) or not isinstance(triangles, (int, np.integer)) \
            or not MIN_TRIANGLES <= triangles <= MAX_TRIANGLES:
        raise ConfigError(f"procedural head: triangles = {triangles!r}: must be an integer in "
                          f"[{MIN_TRIANGLES:,}, {MAX_TRIANGLES:,}]")
    if not isinstance(detail, (bool, np.bool_)):
        raise ConfigError(f"procedural head: detail = {detail!r}: must be true or false")
    if isinstance(texture_size, bool) or not isinstance(texture_size, (int, np.integer)) \
            or not MIN_TEXTURE <= texture_size <= MAX_TEXTURE \
            or texture_size & (texture_size - 1):
        raise ConfigError(f"procedural head: texture_size = {texture_size!r}: must be a power of "
                          f"two in [{MIN_TEXTURE}, {MAX_TEXTURE}]")
    if isinstance(seed, bool) or not isinstance(seed, (int, np.integer)) or seed < 0:
        raise ConfigError(f"procedural head: seed = {seed!r}: must be an integer >= 0")


def _eye_level(triangles):
    """Icosphere subdivision level of each eyeball: at most EYE_FRACTION of the budget, >= 1."""
    level = 1
    while 2 * 20 * 4 ** (level + 1) <= EYE_FRACTION * triangles and level < 6:
        level += 1
    return level


def make_head(*, triangles: int = 1_000_000, detail: bool = True, texture_size: int = 2048,
        seed: int = 0) -> Mesh:
    """Build the procedural head: closed skin, two eyeballs, UVs and an albedo texture.

    Parameters
    ----------
    triangles : int, optional
        Total triangle count (skin + eyes), met within 0.5%.  The default matches the thesis's
        ~1M-triangle scan.  Allowed: [2,000, 20,000,000].
    detail : bool, optional
        Apply skin-scale relief (pores 0.05-0.1 mm, micro-relief, forehead lines, crow's feet,
        nasolabial folds, lip and neck lines) along the normal; False gives the smooth base.
    texture_size : int, optional
        Side of the square sRGB albedo texture in texels; a power of two in [64, 16384].
    seed : int, optional
        Seeds the relief and texture noise (``np.random.default_rng(seed)``).  The base shape
        does not depend on it.  Same arguments give bit-identical arrays.

    Returns
    -------
    Mesh
        ``vertices`` (V, 3) float64 mm (Y up, face towards +Z, LPS-scan placement); ``faces``
        (F, 3) int32 counter-clockwise from outside; ``normals`` None (mesh prep computes them);
        ``uv`` (T, 2) float32 and ``uv_faces`` (F, 3) int32 with the skin seam at the back of
        the head (phi = +-pi); ``texture_srgb`` (texture_size, texture_size, 3) uint8; ``info``
        with the source, seed, grid size and the face/vertex ranges of each component (the skin
        is closed with Euler characteristic 2; each eyeball is a separate closed sphere).

    Raises
    ------
    ConfigError
        An argument is outside its range (the message names it).

    Notes
    -----
    The skin is star-shaped about ``CENTRE`` by construction: each grid vertex is the root of
    the implicit field along its own ray (Illinois regula falsi, residual < 1e-4 mm), so the
    surface cannot self-intersect.  The rings are spaced by meridian arc length from a coarse
    pilot solve, so triangles are near-uniform in size (~0.5 mm edges at 1M triangles).
    """
    _validate(triangles, detail, texture_size, seed)
    triangles, texture_size, seed = int(triangles), int(texture_size), int(seed)
    rng = np.random.default_rng(seed)
    rng_detail, rng_texture = rng.spawn(2)

    eye_level = _eye_level(triangles)
    eye_v, eye_f = icosphere(eye_level)
    pilot = pilot_solve()
    s_arc, aspect = ring_schedule(*pilot)
    n_t, n_p = grid_size(triangles - 2 * len(eye_f), aspect)
    t = (np.arange(n_t) + 1.0) / (n_t + 1.0)
    theta_of = lambda tt: np.interp(tt * s_arc[-1], s_arc, pilot[0])   # noqa: E731
    theta = theta_of(t)
    phi = -np.pi + 2.0 * np.pi * np.arange(n_p) / n_p

    r, d, n_rebracketed, residual = solve_grid(theta, phi, pilot)
    r = eye_aperture(d, r)
    poles_d = (np.zeros(2), np.array([1.0, -1.0]), np.zeros(2))
    lo, hi = bisect_radius(poles_d, iterations=30)
    r_poles = 0.5 * (lo + hi)
    pos = np.stack(ray_points(d, r), -1).reshape(n_t, n_p, 3)
    top, bottom = np.stack(ray_points(poles_d, r_poles), -1)

    height = np.zeros((n_t, n_p))
    if detail:
        normals = grid_normals(pos, top, bottom)
        flat = pos.reshape(-1, 3)
        height = detail_height((flat[:, 0], flat[:, 1], flat[:, 2]), rng_detail).reshape(n_t, n_p)
        pos = pos + height[..., None] * normals

    skin_v = np.concatenate([top[None], pos.reshape(-1, 3), bottom[None]])
    skin_f = grid_faces(n_t, n_p)
    skin_uv, skin_uvf = grid_uv(t, n_p)

    # eyeballs: separate closed spheres, planar-projected into the strip above the skin atlas
    cell = 1.0 - V_SKIN
    verts, faces, uvs, uv_faces = [skin_v], [skin_f], [skin_uv], [skin_uvf]
    components = [{"name": "skin", "faces": [0, len(skin_f)], "vertices": [0, len(skin_v)],
                   "closed": True}]
    for k, (name, e) in enumerate(zip(("eye_left", "eye_right"), EYE_CENTRES)):
        v0, f0 = sum(len(a) for a in verts), sum(len(a) for a in faces)
        verts.append(e + EYE_RADIUS * eye_v)
        faces.append(eye_f + v0)
        uv = np.stack([cell * (k + 0.5 + 0.5 * eye_v[:, 0]),
                       V_SKIN + cell * (0.5 + 0.5 * eye_v[:, 1])], -1).astype(np.float32)
        uv_faces.append(eye_f + sum(len(a) for a in uvs))
        uvs.append(uv)
        components.append({"name": name, "faces": [f0, f0 + len(eye_f)],
                           "vertices": [v0, v0 + len(eye_v)], "closed": True})

    # texture: positions of texels come from the (pre-detail) radii on the ring grid
    r_ext = np.concatenate([np.full((1, n_p), r_poles[0]), r.reshape(n_t, n_p),
                            np.full((1, n_p), r_poles[1])])
    r_ext = np.concatenate([r_ext, r_ext[:, :1]], axis=1)
    t_ext = np.concatenate([[0.0], t, [1.0]])

    def surface(tt, uu):
        th = theta_of(tt)
        ph = -np.pi + 2.0 * np.pi * uu
        ri = ndimage.map_coordinates(r_ext, [np.interp(tt, t_ext, np.arange(n_t + 2)), uu * n_p],
                                     order=1, mode="nearest")
        dd = (np.sin(th) * np.sin(ph), np.cos(th), np.sin(th) * np.cos(ph))
        return ray_points(dd, ri)

    mm_per_texel = s_arc[-1] / (V_SKIN * texture_size)
    texture = albedo_texture(texture_size, rng_texture, surface, mm_per_texel)

    vertices = np.concatenate(verts) + FRAME_OFFSET
    info = {
        "source": "procedural", "seed": seed, "detail": bool(detail),
        "generator": f"stages.procedural_head v{VERSION}",
        "components": components,
        "grid": {"rings": n_t, "columns": n_p, "eye_level": eye_level},
        "frame": "mm, Y up, face +Z; nose tip near (0, -35, 51) like the Lee Perry-Smith scan",
        "height_mm": float(vertices[:len(skin_v), 1].max() - vertices[:len(skin_v), 1].min()),
        "detail_rms_mm": float(np.sqrt(np.mean(height ** 2))),
        "detail_min_mm": float(height.min()),
        "rays_rebracketed": n_rebracketed,
        "max_residual_mm": residual,
    }
    return Mesh(vertices=vertices, faces=np.concatenate(faces).astype(np.int32), normals=None,
                uv=np.concatenate(uvs).astype(np.float32),
                uv_faces=np.concatenate(uv_faces).astype(np.int32),
                texture_srgb=texture, info=info)
