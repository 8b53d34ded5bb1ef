"""Synthetic meshes for the renderer tests and benchmark (not collected: no ``test_`` prefix).

Built here so the renderer does not depend on the mesh-preparation stage: an icosphere
(subdivided icosahedron projected onto the sphere, exact radial normals), a flat grid plane
with UVs (bottom-left origin), and a square occluder.
"""
from __future__ import annotations

import numpy as np

from dermis.pipeline.artifacts import Mesh


def icosphere(radius: float = 100.0, subdivisions: int = 5, centre=(0.0, 0.0, 0.0)) -> Mesh:
    """Sphere of 20 * 4**subdivisions triangles, counter-clockwise seen from outside."""
    t = (1.0 + 5 ** 0.5) / 2.0
    v = np.array([[-1, t, 0], [1, t, 0], [-1, -t, 0], [1, -t, 0], [0, -1, t], [0, 1, t],
                  [0, -1, -t], [0, 1, -t], [t, 0, -1], [t, 0, 1], [-t, 0, -1], [-t, 0, 1]],
                 dtype=np.float64)
    f = np.array([[0, 11, 5], [0, 5, 1], [0, 1, 7], [0, 7, 10], [0, 10, 11], [1, 5, 9],
                  [5, 11, 4], [11, 10, 2], [10, 7, 6], [7, 1, 8], [3, 9, 4], [3, 4, 2],
                  [3, 2, 6], [3, 6, 8], [3, 8, 9], [4, 9, 5], [2, 4, 11], [6, 2, 10],
                  [8, 6, 7], [9, 8, 1]], dtype=np.int64)
    v /= np.linalg.norm(v, axis=1, keepdims=True)
    for _ in range(subdivisions):
        edges = np.sort(np.concatenate([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]]), axis=1)
        uniq, inv = np.unique(edges, axis=0, return_inverse=True)
        mid = v[uniq[:, 0]] + v[uniq[:, 1]]
        mid /= np.linalg.norm(mid, axis=1, keepdims=True)
        m = inv.reshape(3, -1).T + len(v)
        v = np.concatenate([v, mid])
        a, b, c = f[:, 0], f[:, 1], f[:, 2]
        ab, bc, ca = m[:, 0], m[:, 1], m[:, 2]
        f = np.concatenate([np.stack([a, ab, ca], 1), np.stack([b, bc, ab], 1),
                            np.stack([c, ca, bc], 1), np.stack([ab, bc, ca], 1)])
    return Mesh(vertices=v * radius + np.asarray(centre, dtype=np.float64),
                faces=f.astype(np.int32), normals=v.astype(np.float32))


def plane(size: float = 200.0, n: int = 8, z: float = 0.0, centre=(0.0, 0.0),
          texture_srgb=None) -> Mesh:
    """Square grid in the plane z = ``z`` facing +z, (2 n^2) triangles, UV over [0, 1]^2."""
    g = np.linspace(0.0, 1.0, n + 1)
    uu, vv = np.meshgrid(g, g)
    xy = np.stack([(uu.ravel() - 0.5) * size + centre[0], (vv.ravel() - 0.5) * size + centre[1]], 1)
    verts = np.concatenate([xy, np.full((len(xy), 1), z)], axis=1)
    idx = np.arange((n + 1) ** 2).reshape(n + 1, n + 1)
    a, b = idx[:-1, :-1].ravel(), idx[:-1, 1:].ravel()
    c, d = idx[1:, 1:].ravel(), idx[1:, :-1].ravel()
    faces = np.concatenate([np.stack([a, b, c], 1), np.stack([a, c, d], 1)]).astype(np.int32)
    normals = np.tile(np.array([0.0, 0.0, 1.0], np.float32), (len(verts), 1))
    uv = np.stack([uu.ravel(), vv.ravel()], 1).astype(np.float32)
    return Mesh(vertices=verts, faces=faces, normals=normals, uv=uv, uv_faces=faces.copy(),
                texture_srgb=texture_srgb)


def merge(*meshes: Mesh) -> Mesh:
    """Concatenate meshes (positions, faces, normals; UVs dropped unless all have them)."""
    verts, faces, normals, off = [], [], [], 0
    for m in meshes:
        verts.append(np.asarray(m.vertices, dtype=np.float64))
        faces.append(np.asarray(m.faces) + off)
        normals.append(np.asarray(m.normals, dtype=np.float32))
        off += len(m.vertices)
    return Mesh(vertices=np.concatenate(verts), faces=np.concatenate(faces).astype(np.int32),
                normals=np.concatenate(normals))
