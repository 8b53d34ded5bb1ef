"""Stage ``mesh_low``: quadric simplification to the thesis's 16,750 triangles and the thesis's
nearest-vertex UV transfer with seam repair (:func:`dermis.geometry.simplification.simplify`,
:func:`dermis.geometry.uv_transfer.transfer_uv`)."""
from __future__ import annotations

from dermis.geometry.simplification import simplify
from dermis.geometry.uv_transfer import transfer_uv
from dermis.pipeline.graph import Node, StageResult
from dermis.pipeline.registry import stage

NAME = "mesh_low"
VERSION = 1
KERNELS = ()


def node(scene) -> Node:
    return Node(NAME, NAME, __name__, {"target_triangles": scene.mesh.low_triangles},
                {"high": "mesh_high"}, label="simplify + UV transfer")


def run(params: dict, inputs: dict, ctx) -> StageResult:
    high = inputs["high"]
    low = simplify(high, target_triangles=params["target_triangles"])
    low, report = transfer_uv(high, low)
    return StageResult(low, info={"uv_transfer": report, "triangles": low.n_triangles})


def plan(scene, plan) -> None:
    """Only for a low geometry; an output of its own when no image uses the bump maps."""
    geometry = stage("render").GEOMETRY
    if any(geometry[g][0] == NAME for g in scene.render.geometries):
        plan.add(node(scene), target=not any(geometry[g][1] for g in scene.render.geometries))
