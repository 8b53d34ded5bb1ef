"""Render quick previews of the procedural head (Lambert + texture) with open3d's ray caster.

Usage: python bench/preview_procedural_head.py [--triangles N] [--texture 1024] [--out /tmp/head]
Writes <out>_front.png, <out>_threequarter.png, <out>_side.png, <out>_back.png, <out>_grazing.png
(untextured, low sun to show the relief) and <out>_texture.png.  A development aid, not a test.
"""
from __future__ import annotations

import argparse
import time

import numpy as np


def render(mesh, eye, target, *, fov_deg=22.0, size=700, light=(0.4, 0.5, 1.0), textured=True,
           up=(0.0, 1.0, 0.0)):
    """Lambert-shaded image (size, size, 3) float of the mesh seen from ``eye``."""
    import open3d as o3d
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(mesh.vertices.astype(np.float32), mesh.faces.astype(np.uint32))
    rays = o3d.t.geometry.RaycastingScene.create_rays_pinhole(
        fov_deg=fov_deg, center=list(target), eye=list(eye), up=list(up), width_px=size, height_px=size)
    ans = scene.cast_rays(rays)
    hit = np.isfinite(ans["t_hit"].numpy())
    prim = ans["primitive_ids"].numpy()
    bary = ans["primitive_uvs"].numpy()
    v, f = mesh.vertices, mesh.faces
    fn = np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]])
    fn /= np.linalg.norm(fn, axis=1, keepdims=True) + 1e-30
    vn = np.zeros_like(v)
    for k in range(3):
        np.add.at(vn, f[:, k], fn)
    vn /= np.linalg.norm(vn, axis=1, keepdims=True) + 1e-30
    img = np.full((size, size, 3), 0.15)
    p = np.where(hit, prim, 0)
    w = np.stack([1 - bary[..., 0] - bary[..., 1], bary[..., 0], bary[..., 1]], -1)
    n = sum(w[..., k:k + 1] * vn[f[p, k]] for k in range(3))
    n /= np.linalg.norm(n, axis=-1, keepdims=True) + 1e-30
    L = np.asarray(light, float)
    L /= np.linalg.norm(L)
    shade = 0.08 + 0.92 * np.clip(n @ L, 0, None)
    if textured and mesh.texture_srgb is not None:
        uv = sum(w[..., k:k + 1] * mesh.uv[mesh.uv_faces[p, k]] for k in range(3))
        tex = mesh.texture_srgb.astype(float) / 255.0
        tex = np.where(tex <= 0.04045, tex / 12.92, ((tex + 0.055) / 1.055) ** 2.4)
        H, W = tex.shape[:2]
        col = np.clip(np.round(uv[..., 0] * (W - 1)).astype(int), 0, W - 1)
        row = np.clip(np.round((1 - uv[..., 1]) * (H - 1)).astype(int), 0, H - 1)
        alb = tex[row, col]
    else:
        alb = np.full((size, size, 3), 0.7)
    rgb = alb * shade[..., None]
    img[hit] = rgb[hit]
    img = img[::-1]   # open3d's pinhole rays start at the bottom row
    return np.where(img <= 0.0031308, 12.92 * img, 1.055 * np.clip(img, 0, 1) ** (1 / 2.4) - 0.055)


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--triangles", type=int, default=300_000)
    ap.add_argument("--texture", type=int, default=1024)
    ap.add_argument("--no-detail", action="store_true")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--out", default="/tmp/head")
    ap.add_argument("--size", type=int, default=600)
    a = ap.parse_args()
    import OpenImageIO as oiio
    from dermis.geometry import procedural_head
    t0 = time.perf_counter()
    mesh = procedural_head.make_head(triangles=a.triangles, texture_size=a.texture,
                               detail=not a.no_detail, seed=a.seed)
    print(f"built {mesh.n_triangles} triangles in {time.perf_counter() - t0:.2f} s")
    c = mesh.vertices[: mesh.info["components"][0]["vertices"][1]]
    mid = 0.5 * (c.min(0) + c.max(0))
    views = {"front": (0, 0), "threequarter": (40, 5), "side": (90, 0), "back": (180, 10)}
    def save(name, img):
        out = oiio.ImageBuf(oiio.ImageSpec(img.shape[1], img.shape[0], 3, "uint8"))
        out.set_pixels(oiio.ROI(), (np.clip(img, 0, 1) * 255).astype(np.uint8))
        out.write(f"{a.out}_{name}.png")
    for name, (az, el) in views.items():
        az, el = np.radians(az), np.radians(el)
        eye = mid + 900 * np.array([np.sin(az) * np.cos(el), np.sin(el), np.cos(az) * np.cos(el)])
        save(name, render(mesh, eye, mid, size=a.size, light=(0.5, 0.6, 1.0)))
    # close-up of the face under a grazing light, untextured, to see the relief
    face = np.array([0.0, -13.0, 19.0])   # design (0, -20, 80) in the output frame
    save("grazing", render(mesh, face + np.array([150, 40, 380]), face, fov_deg=14, size=a.size,
                           light=(1.0, 0.25, 0.12), textured=False))
    save("face", render(mesh, face + np.array([0, 0, 450]), face, fov_deg=22, size=a.size,
                        light=(0.5, 0.6, 1.0)))
    save("eye", render(mesh, face + np.array([120, 60, 420]), face + np.array([30, 20, 0]), fov_deg=7,
                       size=a.size, light=(0.3, 0.5, 1.0)))
    brow = face + np.array([25.0, 45.0, 8.0])    # forehead lines and crow's feet
    save("relief", render(mesh, brow + np.array([0, 30, 400]), brow, fov_deg=8, size=a.size,
                          light=(1.0, 0.6, 0.25), textured=False))
    tex = mesh.texture_srgb
    out = oiio.ImageBuf(oiio.ImageSpec(tex.shape[1], tex.shape[0], 3, "uint8"))
    out.set_pixels(oiio.ROI(), np.ascontiguousarray(tex))
    out.write(f"{a.out}_texture.png")


if __name__ == "__main__":
    main()
