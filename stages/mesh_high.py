"""Stage ``mesh_high``: the ~1M-triangle mesh (Loop subdivision + displacement for scans) with
angle-weighted vertex normals (:func:`dermis.geometry.subdivision.make_high`)."""
from __future__ import annotations

from dermis.geometry.subdivision import make_high
from dermis.geometry.normals import angle_weighted_normals
from dermis.pipeline.graph import Node, StageResult
from dermis.pipeline.imageio import read_image
from dermis.pipeline.registry import stage
from dermis.pipeline.store import file_digest

NAME = "mesh_high"
VERSION = 1
KERNELS = ()


def node(scene) -> Node:
    m = scene.mesh
    disp = scene.resolve(m.displacement)
    params = {"target_triangles": m.high_triangles, "displacement": str(disp) if disp else "",
              "displacement_sha256": file_digest(disp) if disp else "",
              "displacement_scale_mm": m.displacement_scale_mm,
              "displacement_mid": m.displacement_mid}
    return Node(NAME, NAME, __name__, params, {"source": "mesh_source"},
                label="high mesh + normals", locations=("displacement",))


def run(params: dict, inputs: dict, ctx) -> StageResult:
    disp = params["displacement"]
    image = read_image(disp, channels=1, what="mesh.displacement")[..., 0] if disp else None
    high = make_high(inputs["source"], target_triangles=params["target_triangles"],
                     displacement=image, displacement_scale_mm=params["displacement_scale_mm"],
                     displacement_mid=params["displacement_mid"])
    high.normals = angle_weighted_normals(high.vertices, high.faces)
    return StageResult(high, info={"triangles": high.n_triangles})


def plan(scene, plan) -> None:
    """An output of its own when no image uses the low mesh."""
    meshes = {stage("render").GEOMETRY[g][0] for g in scene.render.geometries}
    plan.add(node(scene), target=meshes <= {NAME})
