"""Stage ``mesh_source``: the procedural head or a scan, in mm, validated (repairs reported).

The procedural head (:mod:`dermis.stages.procedural_head`) is a synthetic watertight head of
any size; a scan is read by :mod:`dermis.stages.scan_io` and checked by
:func:`dermis.stages.mesh_prep.validate`.
"""
from __future__ import annotations

import numpy as np

from dermis.pipeline.errors import DermisError
from dermis.pipeline.graph import Node, StageResult
from dermis.pipeline.store import file_digest

NAME = "mesh_source"
VERSION = 2   # 2: meshes out of the coordinate range, or with no triangle of non-zero area, refused
KERNELS = ()

# Coordinates the pipeline can render (mm, after mesh.units): the ray caster and the kernels
# work in float32, whose squares overflow near 1.8e19; a head is ~200 mm.  A mesh beyond
# 1e7 mm (10 km) or smaller than 1e-3 mm (1 um) across is a unit mistake, not a face.
MAX_COORDINATE_MM = 1e7
MIN_EXTENT_MM = 1e-3


def node(scene) -> Node:
    m = scene.mesh
    if m.source == "procedural":
        params = {"source": "procedural", "triangles": m.high_triangles,
                  "detail": m.procedural_detail, "texture_size": m.procedural_texture_size,
                  "seed": m.seed}
        return Node(NAME, NAME, __name__, params, (), label="procedural head")
    path, texture = scene.mesh_path(), scene.resolve(m.texture)
    params = {"source": "scan", "file": str(path), "file_sha256": file_digest(path),
              "units": m.units, "texture": str(texture) if texture else "",
              "texture_sha256": file_digest(texture) if texture else ""}
    return Node(NAME, NAME, __name__, params, (), label="load scan",
                locations=("file", "texture"))


def run(params: dict, inputs: dict, ctx) -> StageResult:
    if params["source"] == "procedural":
        from dermis.stages.procedural_head import make_head
        mesh = make_head(triangles=params["triangles"], detail=params["detail"],
                         texture_size=params["texture_size"], seed=params["seed"])
        return StageResult(mesh, info={"triangles": mesh.n_triangles})
    from dermis.stages.mesh_prep import validate
    from dermis.stages.scan_io import load_scan
    mesh = load_scan(params["file"], units=params["units"], texture=params["texture"] or None)
    check_extent(mesh, source=params["file"], units=params["units"])
    mesh, repairs = validate(mesh, source=params["file"])
    if mesh.n_triangles == 0:   # defensive: validate keeps at least one triangle (checked above)
        raise DermisError(f"{params['file']}: no triangle is left after removing degenerate "
                          "ones; the mesh has no surface")
    return StageResult(mesh, info={"repairs": repairs, "triangles": mesh.n_triangles})


def check_extent(mesh, *, source: str, units: str) -> None:
    """Refuse a mesh whose size the pipeline cannot render, or which has no surface: finite
    coordinates beyond MAX_COORDINATE_MM, an extent below MIN_EXTENT_MM, or no triangle of
    non-zero area (every face degenerate: repeated indices or collinear corners)."""
    from dermis.stages.mesh_prep import _DEGENERATE_REL_AREA
    v = np.asarray(mesh.vertices, dtype=np.float64)
    f = np.asarray(mesh.faces)
    finite = np.isfinite(v).all(axis=1)
    if not finite.all() or v.size == 0 or f.size == 0:
        return  # validate() names NaN/Inf vertices and empty meshes
    used = v[np.unique(f.ravel())] if f.max() < len(v) and f.min() >= 0 else v
    peak = float(np.abs(used).max())
    extent = float(np.linalg.norm(used.max(axis=0) - used.min(axis=0)))
    if peak > MAX_COORDINATE_MM:
        raise DermisError(f"{source}: coordinates reach {peak:.3g} mm (mesh.units = \"{units}\"); "
                          f"allowed: |x| <= {MAX_COORDINATE_MM:g} mm. Check mesh.units, or "
                          "scale the scan in the export")
    if extent < MIN_EXTENT_MM:
        raise DermisError(f"{source}: the mesh is {extent:.3g} mm across (mesh.units = "
                          f"\"{units}\"); allowed: >= {MIN_EXTENT_MM:g} mm. Check mesh.units")
    a, b, c = (v[f[:, k]] for k in range(3))
    twice_area = np.linalg.norm(np.cross(b - a, c - a), axis=1)
    repeated = (f[:, 0] == f[:, 1]) | (f[:, 1] == f[:, 2]) | (f[:, 2] == f[:, 0])
    good = ~repeated & (twice_area > _DEGENERATE_REL_AREA * extent ** 2)
    if not good.any():
        raise DermisError(f"{source}: all {len(f)} triangles are degenerate (repeated vertex "
                          "indices or zero area): the mesh has no surface to render")
