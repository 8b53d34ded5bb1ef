"""Stage ``mesh_source``: the procedural head or a scan, in mm, validated (repairs reported).

The procedural head (:mod:`dermis.geometry.procedural_head`) is a synthetic watertight head of
any size; a scan is read by :mod:`dermis.geometry.scan` (a truncated or damaged texture is
refused) and checked by :func:`dermis.geometry.validation.check_extent` (coordinate range, a
surface, a human subject's size: a file in mm declared as m is refused, naming the likely unit)
and :func:`dermis.geometry.validation.validate`.
"""
from __future__ import annotations

from dermis.geometry.procedural_head import make_head
from dermis.geometry.scan import load_scan
from dermis.geometry.validation import check_extent, validate
from dermis.pipeline.errors import DermisError
from dermis.pipeline.graph import Node, StageResult
from dermis.pipeline.store import file_digest

NAME = "mesh_source"
# 2: meshes out of the coordinate range, or with no triangle of non-zero area, refused;
# 3: sizes no human subject has (a unit mistake) and truncated or damaged textures refused
VERSION = 3
KERNELS = ()


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
        mesh = make_head(triangles=params["triangles"], detail=params["detail"],
                         texture_size=params["texture_size"], seed=params["seed"])
        return StageResult(mesh, info={"triangles": mesh.n_triangles})
    mesh = load_scan(params["file"], units=params["units"], texture=params["texture"] or None)
    check_extent(mesh, source=params["file"], units=params["units"])
    mesh, repairs = validate(mesh, source=params["file"])
    if mesh.n_triangles == 0:   # defensive: validate keeps at least one triangle (checked above)
        raise DermisError(f"{params['file']}: no triangle is left after removing degenerate "
                          "ones; the mesh has no surface")
    return StageResult(mesh, info={"repairs": repairs, "triangles": mesh.n_triangles})


def plan(scene, plan) -> None:
    """Every scene starts from its mesh."""
    plan.add(node(scene))
