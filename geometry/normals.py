"""Vertex normals of a mesh: angle-weighted (Thuermer & Wuethrich 1998, by libigl), and the
normals a mesh carries or, when it carries none, those (docs/science.md §6 "Vertex normals")."""
from __future__ import annotations

import numpy as np

from dermis.pipeline.errors import DermisError

__all__ = ["angle_weighted_normals", "renormalise_f64", "vertex_normals"]


def vertex_normals(mesh) -> np.ndarray:
    """(V, 3) float32 unit normals of ``mesh``: its ``normals`` if set, else angle-weighted ones."""
    if mesh.normals is None:
        return angle_weighted_normals(mesh.vertices, mesh.faces)
    n = np.asarray(mesh.normals, dtype=np.float32)
    if n.shape != np.shape(mesh.vertices):
        raise DermisError(f"mesh.normals has shape {n.shape}; need {np.shape(mesh.vertices)}")
    return n


def angle_weighted_normals(vertices, faces) -> np.ndarray:
    """Angle-weighted unit vertex normals, (V, 3) float32; unused vertices get (0, 0, 0).

    docs/science.md §6 "Vertex normals" (Thuermer & Wuethrich, JGT 3(1), 1998), computed by
    ``igl.per_vertex_normals`` (weighting ANGLE).
    """
    import igl

    n = igl.per_vertex_normals(np.ascontiguousarray(vertices, dtype=np.float64),
                               np.ascontiguousarray(faces, dtype=np.int64),
                               igl.PerVertexNormalsWeightingType.PER_VERTEX_NORMALS_WEIGHTING_TYPE_ANGLE)
    return np.nan_to_num(n, nan=0.0, posinf=0.0, neginf=0.0).astype(np.float32)


def renormalise_f64(normals) -> np.ndarray:
    """``normals`` as float64, NaN set to 0 and each non-zero row rescaled to unit length."""
    n = np.nan_to_num(np.asarray(normals).astype(np.float64))
    length = np.linalg.norm(n, axis=1, keepdims=True)
    return n / np.where(length > 0, length, 1.0)
