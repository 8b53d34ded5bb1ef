"""Preview images of mesh prep: the baked maps, and a Lambert render of high vs low + bump.

For eyeballing a bake (is the albedo in place, are the pores in the bump, does the bump-mapped
low mesh look like the scan?), not for the report's measured images.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

from dermis.geometry.bump import bump_shading_normals_at_hits
from dermis.lighting.visibility import embree_scene
from dermis.pipeline.artifacts import BakedMaps, Mesh
from dermis.rendering.color import linear_to_srgb8
from dermis.reports.sheets import save_png
from dermis.geometry.normals import renormalise_f64, vertex_normals

__all__ = ["save_map_previews", "save_shaded_comparison", "lambert_render"]

# Preview light: directional, from the upper left and grazing (about 65 deg from the view
# axis) so that bumps cast strong shading gradients; not a thesis light (docs/science.md §6
# lists those), just a detail-revealing one.
PREVIEW_LIGHT_DIR = np.array([-0.8, 0.45, 0.4])
PREVIEW_AMBIENT = 0.05       # keeps unlit regions readable
PREVIEW_FOV_DEG = 30.0


def _write_png(path: Path, image: np.ndarray) -> Path:
    """Write a (H, W[, 3]) uint8 image as PNG (:func:`dermis.reports.sheets.save_png`: zlib
    level 1, ~3x faster than the default 6 on the 4096^2 maps, 5.8 -> ~1.8 s for the five)."""
    return save_png(path, image)


def _grey8(x: np.ndarray) -> np.ndarray:
    """[0, 1] floats -> uint8 (values shown as stored, no tone curve)."""
    return np.rint(np.clip(x, 0, 1) * 255).astype(np.uint8)


def save_map_previews(maps: BakedMaps, out_dir) -> list[Path]:
    """Write ``albedo.png``, ``bump.png``, ``bump_blur.png`` and ``coverage.png`` into ``out_dir``.

    Parameters
    ----------
    maps : BakedMaps
    out_dir : path-like, created if missing

    Returns
    -------
    list of Path, the files written.  Bump maps are shown as their normalised [0, 1] values
    (black = ``bump_min_mm``, white = ``bump_min_mm + bump_range_mm``).
    """
    out_dir = Path(out_dir)
    return [
        _write_png(out_dir / "albedo.png", maps.albedo_srgb),
        _write_png(out_dir / "bump.png", _grey8(maps.bump)),
        _write_png(out_dir / "bump_blur.png", _grey8(maps.bump_blur)),
        _write_png(out_dir / "coverage.png", maps.coverage.astype(np.uint8) * 255),
    ]


def _camera_rays(mesh: Mesh, size: int):
    """Pinhole rays from +Z looking down -Z at the mesh's bounding box (Y up)."""
    import open3d as o3d  # heavy (~1 s to import): only when a preview is drawn
    lo, hi = mesh.vertices.min(0), mesh.vertices.max(0)
    centre = 0.5 * (lo + hi)
    half = 0.5 * max(hi[0] - lo[0], hi[1] - lo[1]) * 1.05
    dist = half / np.tan(np.radians(PREVIEW_FOV_DEG / 2)) + (hi[2] - centre[2])
    eye = centre + np.array([0.0, 0.0, dist])
    rays = o3d.t.geometry.RaycastingScene.create_rays_pinhole(
        fov_deg=PREVIEW_FOV_DEG, center=centre.tolist(), eye=eye.tolist(), up=[0, 1, 0],
        width_px=size, height_px=size).numpy()
    # open3d 0.20's grid starts at (+x, -y) in row 0, column 0 (image rotated by 180 deg
    # against the usual top-left origin; checked on a test grid): reverse both axes.
    return o3d.core.Tensor(np.ascontiguousarray(rays[::-1, ::-1]))


def _cast(mesh: Mesh, rays, scene=None):
    """Primary hits: (mask (H, W), triangle ids, barycentrics (N, 2)), on ``scene`` (the
    mesh's Embree scene, :func:`dermis.lighting.visibility.embree_scene`; the renders of a
    run built it already) or one built here."""
    r = rays.numpy()
    hits = (scene or embree_scene(mesh)).intersect(
        r[..., :3].reshape(-1, 3), r[..., 3:].reshape(-1, 3))
    mask = hits.hit.reshape(r.shape[:2])
    return mask, hits.tri[hits.hit].astype(np.int64), hits.bary[hits.hit]


def _shade(mask: np.ndarray, normals: np.ndarray, albedo: np.ndarray | float = 0.8) -> np.ndarray:
    """Lambert shading of unit normals into an sRGB uint8 image (black background)."""
    light = PREVIEW_LIGHT_DIR / np.linalg.norm(PREVIEW_LIGHT_DIR)
    cos = np.clip(normals @ light, 0, None)
    radiance = np.asarray(albedo, dtype=np.float64) * (PREVIEW_AMBIENT + (1 - PREVIEW_AMBIENT) * cos)
    if radiance.ndim == 1:
        radiance = radiance[:, None] * np.ones(3)
    img = np.zeros(mask.shape + (3,), np.float32)
    img[mask] = radiance
    return linear_to_srgb8(img)


def lambert_render(mesh: Mesh, *, size: int = 800, maps: BakedMaps | None = None,
                   blurred: bool = False, rays=None, scene=None) -> np.ndarray:
    """Grey Lambert image (size, size, 3) uint8 of ``mesh`` seen from +Z.

    Without ``maps`` the shading normal is the mesh's interpolated vertex normal (libigl's
    angle-weighted ones when ``mesh.normals`` is None); with ``maps`` it is the bump-mapped normal
    (:func:`geometry.bump.bump_shading_normals_at_hits`, sharp or blurred bump).
    """
    rays = rays if rays is not None else _camera_rays(mesh, size)
    mask, tri, bary = _cast(mesh, rays, scene)
    if maps is not None:
        n = bump_shading_normals_at_hits(mesh, maps, tri, bary, blurred=blurred)
    else:
        w = np.stack([1 - bary[:, 0] - bary[:, 1], bary[:, 0], bary[:, 1]], 1)
        n = np.einsum("nk,nkd->nd", w, renormalise_f64(vertex_normals(mesh))[mesh.faces[tri]])
    n = n / np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-12)
    return _shade(mask, n)


def save_shaded_comparison(high: Mesh, low: Mesh, maps: BakedMaps, out_path, *,
                           size: int = 800, scenes=(None, None)) -> Path:
    """Side-by-side Lambert renders: high mesh | low + bump | low + blurred bump | low alone
    (the high panel alone when ``low`` is None).

    Parameters
    ----------
    high, low : Mesh, mm
    maps : BakedMaps baked from ``high`` into ``low``
    out_path : path-like of the PNG
    size : int, side of each panel in pixels (800 as the thesis's images, docs/science.md §6)
    scenes : the Embree scenes of ``high`` and ``low`` (the run's shared ones), else built here

    Returns
    -------
    Path of the PNG.  The camera looks down -Z at the high mesh's bounding box (the face
    looks toward +Z, Y up); a grazing directional light from the upper left shows the detail.
    Shading uses a constant grey albedo so that only geometry differs between panels.
    """
    rays = _camera_rays(high, size)
    high_scene = scenes[0] or embree_scene(high)
    panels = [lambert_render(high, rays=rays, scene=high_scene)]
    if low is not None:  # no low mesh (render.geometries = ["high"] or []): the high panel only
        low_scene = scenes[1] or embree_scene(low)
        panels += [lambert_render(low, maps=maps, rays=rays, scene=low_scene),
                   lambert_render(low, maps=maps, blurred=True, rays=rays, scene=low_scene),
                   lambert_render(low, rays=rays, scene=low_scene)]
    gap = np.full((size, 4, 3), 255, np.uint8)
    row = np.concatenate([x for p in panels for x in (p, gap)][:-1], axis=1)
    return _write_png(Path(out_path), row)

