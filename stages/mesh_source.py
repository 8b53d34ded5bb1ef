"""Stage ``mesh_source``: the procedural head or a scan, in mm, validated (repairs reported).

The procedural head (:mod:`dermis.stages.procedural_head`) is a synthetic watertight head of
any size; a scan is read by :mod:`dermis.stages.scan_io` and checked by
:func:`dermis.stages.mesh_prep.validate`.
"""
from __future__ import annotations

from dermis.pipeline.graph import Node, StageResult
from dermis.pipeline.store import file_digest

NAME = "mesh_source"
VERSION = 1
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
        from dermis.stages.procedural_head import make_head
        mesh = make_head(triangles=params["triangles"], detail=params["detail"],
                         texture_size=params["texture_size"], seed=params["seed"])
        return StageResult(mesh, info={"triangles": mesh.n_triangles})
    from dermis.stages.mesh_prep import validate
    from dermis.stages.scan_io import load_scan
    mesh = load_scan(params["file"], units=params["units"], texture=params["texture"] or None)
    mesh, repairs = validate(mesh, source=params["file"])
    return StageResult(mesh, info={"repairs": repairs, "triangles": mesh.n_triangles})
