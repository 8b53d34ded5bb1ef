"""Stage ``irradiance``: irradiance at the BSSRDF sample points from one lighting condition.

Jensen-Buhler pass 1: each point's irradiance with shadows, from
:func:`dermis.physics.lights.irradiance` (thesis: 64 shadow samples for area and environment
lights).  One node per mesh and lighting condition.
"""
from __future__ import annotations

import time

from dermis.pipeline.artifacts import PointIrradiance
from dermis.pipeline.config import LightConfig
from dermis.pipeline.graph import Node, StageResult
from dermis.physics.lights import light_params
from dermis.physics.visibility import shared as shared_visibility

NAME = "irradiance"
VERSION = 1
KERNELS = ()


def node(scene, mesh_node: str, label: str, lights: tuple) -> Node:
    params = {**light_params(lights), "samples": scene.bssrdf.irradiance_samples,
              "seed": scene.mesh.seed}
    return Node(f"irradiance-{mesh_node}-{label}", NAME, __name__, params,
                {"points": f"samples-{mesh_node}", "mesh": mesh_node}, label=f"irradiance {label}",
                locations=("lights[].map",))


def run(params: dict, inputs: dict, ctx) -> StageResult:
    from dermis.physics.lights import irradiance
    pts, mesh = inputs["points"], inputs["mesh"]
    t0 = time.perf_counter()
    vis = shared_visibility(mesh, ctx.memo)
    lights = [LightConfig(**d) for d in params["lights"]]
    E = irradiance(pts.positions, pts.normals, lights, vis.occluded, samples=params["samples"],
                   seed=params["seed"])
    info = {"seconds": time.perf_counter() - t0, "points": int(len(E)),
            "samples": params["samples"]}
    return StageResult(PointIrradiance(E, info), info=info)
