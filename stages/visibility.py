"""Stage ``visibility``: the camera and shadow rays of one mesh under one lighting condition,
cast once (:func:`dermis.rendering.cast.cast`) and shared by every model rendered with them
(BRDF models and the BSSRDF): the render nodes (``stages/render.py``, ``stages/bssrdf.py``)
take its :class:`~dermis.pipeline.artifacts.PixelSamples` as an input, so changing a model's
parameters recasts no ray.  One node per (mesh, lighting condition); camera, ``[render] spp``
and seed from the scene.
"""
from __future__ import annotations

from dataclasses import asdict

from dermis.lighting.emitters import light_params
from dermis.lighting.visibility import EMBREE_SCENES, embree_scene
from dermis.pipeline.config import CameraConfig, LightConfig
from dermis.pipeline.graph import Node, StageResult
from dermis.rendering.cast import CAMERA_HITS, cast, glossy_lobes, retro_lobe
from dermis.rendering.options import LightSampling, RenderOptions

__all__ = ["NAME", "VERSION", "KERNELS", "node", "run"]

NAME = "visibility"
VERSION = 2   # 2: each hit's camera sample (PixelSamples.sub)
KERNELS = ()   # rendering/surface.py declares cl/surface.cl
SHARES = (EMBREE_SCENES, CAMERA_HITS)


def node_id(mesh_node: str, label: str) -> str:
    return f"{NAME}-{mesh_node}-{label}"


def node(scene, mesh_node: str, label: str, lights: tuple) -> Node:
    """One node per mesh x lighting condition (camera, spp and seed from the scene)."""
    params = {"mesh": mesh_node, "label": label, **light_params(lights),
              "camera": asdict(scene.camera_of(label)), "spp": scene.render.spp, "seed": scene.mesh.seed}
    env = any(lt.type == "environment" for lt in lights)
    retro = retro_lobe(scene) if env else None
    if retro is not None:          # only then: every other scene keeps its node keys
        params["retro_lobe"] = retro
    elif env and glossy_lobes(scene):
        params["glossy_lobes"] = True
    return Node(node_id(mesh_node, label), NAME, __name__, params, {"mesh": mesh_node},
                label=f"rays {mesh_node} / {label}", locations=("lights[].map",))


def run(params: dict, inputs: dict, ctx) -> StageResult:
    mesh = inputs["mesh"]
    lights = [LightConfig(**d) for d in params["lights"]]
    retro = params.get("retro_lobe")
    # the control variate's non-negative estimator (lighting/control.py control_estimate): Lafortune
    # 0.072 -> 0.043 relative RMSE under the Venice sunset (bench/results/env_noise.json "split")
    sampling = (LightSampling(retro_fraction=retro["fraction"], retro_k=retro["k"],
                              control_variate=True)
                if retro else LightSampling(glossy_lobes=bool(params.get("glossy_lobes")),
                                            control_variate=True))
    options = RenderOptions(spp=params["spp"], seed=params["seed"], sampling=sampling,
                            visibility=embree_scene(mesh, ctx.shared, ctx.input_keys["mesh"]))
    samples = cast(mesh, lights, CameraConfig(**params["camera"]), options,
                   cl_env=ctx.cl, progress=ctx.progress, shared=ctx.shared,
                   mesh_key=ctx.input_keys["mesh"])
    samples.info["label"] = params["label"]
    return StageResult(samples, info={"timings": samples.info["timings"],
                                      "kernel_seconds": samples.info["timings"]["kernel_seconds"]})
