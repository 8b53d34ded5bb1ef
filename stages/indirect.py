"""Stage ``indirect``: one bounce of indirect light at the vertices of one mesh under one
lighting condition (:func:`dermis.lighting.indirect.one_bounce`; docs/science.md §6
"Indirect light").  Only with ``[render] indirect = true``: its nodes then feed every image of
that mesh and lighting, the BRDF models through the render stage (each hit's diffuse response
to the interpolated E_ind, ``rendering/indirect_shading.py``) and the BSSRDF through the
irradiance stage (E_ind at the irradiance points, times the entry transmittance of diffuse
light).  With ``indirect = false`` the stage plans nothing and no other node changes.
"""
from __future__ import annotations

import time

from dermis.lighting.emitters import light_params
from dermis.lighting.indirect import one_bounce
from dermis.lighting.visibility import EMBREE_SCENES, embree_scene
from dermis.models.lafortune import LafortuneParams
from dermis.pipeline import registry
from dermis.pipeline.artifacts import PointIrradiance
from dermis.pipeline.config import LightConfig
from dermis.pipeline.graph import Node, StageResult

__all__ = ["NAME", "VERSION", "KERNELS", "node_id", "node", "inputs", "plan", "run"]

NAME = "indirect"
VERSION = 1
KERNELS = ()
SHARES = (EMBREE_SCENES,)
# The models' images this stage feeds: those of the BRDF renderer and of the BSSRDF.
IMAGE_STAGES = ("render", "bssrdf")


def node_id(mesh_node: str, label: str) -> str:
    return f"{NAME}-{mesh_node}-{label}"


def node(scene, mesh_node: str, label: str, lights: tuple) -> Node:
    """E_ind at ``mesh_node``'s vertices under the lighting condition ``label``: the direct
    irradiance at the vertices with the BSSRDF irradiance's light samples (``[bssrdf]
    irradiance_samples``), ``[render] indirect_samples`` bounce rays per vertex."""
    params = {"label": label, **light_params(lights), "samples": scene.render.indirect_samples,
              "direct_samples": scene.bssrdf.irradiance_samples, "seed": scene.mesh.seed}
    return Node(node_id(mesh_node, label), NAME, __name__, params, {"mesh": mesh_node},
                label=f"indirect {mesh_node} / {label}", locations=("lights[].map",))


def inputs(scene, mesh_node: str, label: str) -> dict:
    """The role of this stage's node among the inputs of an image (or irradiance) node of
    ``mesh_node`` under ``label``: ``{"indirect": id}``, or nothing when the scene has no
    indirect light (the node's definition and key are then those of a scene without it)."""
    return {"indirect": node_id(mesh_node, label)} if scene.render.indirect else {}


def plan(scene, plan) -> None:
    """One node per mesh and lighting condition that an image is rendered with."""
    if not scene.render.indirect:
        return
    geometry = registry.stage("render").GEOMETRY
    for name in IMAGE_STAGES:
        for _model, label, lights, geo in plan.images_of(name):
            plan.add(node(scene, geometry[geo][0], label, lights))


def run(params: dict, inputs: dict, ctx) -> StageResult:
    mesh = inputs["mesh"]
    t0 = time.perf_counter()
    vis = embree_scene(mesh, ctx.shared, ctx.input_keys.get("mesh"))
    lights = [LightConfig(**d) for d in params["lights"]]
    # where the mesh has no albedo texture, the skin fit's diffuse albedo (the BRDF models'
    # own constant there: rendering/shade.py _fallback_albedo)
    e_ind, e_dir = one_bounce(mesh, lights, vis, samples=params["samples"],
                              direct_samples=params["direct_samples"], seed=params["seed"],
                              fallback_albedo=LafortuneParams().rho_d)
    lit = e_dir.sum(axis=1) > 0
    info = {"seconds": time.perf_counter() - t0, "vertices": int(len(e_ind)),
            "samples": params["samples"], "direct_samples": params["direct_samples"],
            "mean_ratio_lit": [float(v) for v in (e_ind[lit].mean(axis=0) /
                                                  max(e_dir[lit].mean(), 1e-30))]
            if lit.any() else [0.0, 0.0, 0.0]}
    return StageResult(PointIrradiance(e_ind, info), info=info)
