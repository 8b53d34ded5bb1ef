"""Stage ``samples``: uniform irradiance points on one mesh (Jensen-Buhler 2002 pass 1).

The points, their normals and areas come from :func:`dermis.subsurface.points.sample_points`
at the spacing of :func:`dermis.subsurface.points.spacing_from_mfp` (docs/science.md §4).
This stage depends on the mesh and the point spacing only, not on any light, so its artifact
is cached per mesh.
"""
from __future__ import annotations

from dermis.pipeline.graph import Node, StageResult
from dermis.subsurface.points import sample_points, spacing_from_mfp

__all__ = ["VERSION", "KERNELS", "NAME", "node_id", "node", "run"]

NAME = "samples"
VERSION = 3
KERNELS = ()


def node_id(mesh_node: str) -> str:
    return f"{NAME}-{mesh_node}"


def node(scene, mesh_node: str) -> Node:
    params = {"spacing_mm": spacing_from_mfp(scene.optics, scene.bssrdf.point_density),
              "seed": scene.mesh.seed}
    return Node(node_id(mesh_node), NAME, __name__, params, {"mesh": mesh_node},
                label="irradiance points")


def run(params: dict, inputs: dict, ctx) -> StageResult:
    mesh = inputs["mesh"]
    pts = sample_points(mesh.vertices, mesh.faces, spacing_mm=params["spacing_mm"],
                        seed=params["seed"], vertex_normals=mesh.normals)
    return StageResult(pts, info={"points": int(len(pts.positions)),
                                  "spacing_mm": params["spacing_mm"]})
