"""Stage ``render``: one image per BRDF model x lighting condition x geometry, shaded by
:func:`dermis.rendering.shade.render` on the shared visibility of its mesh and lighting
condition (stage ``visibility``).  The model is looked up by name (``dermis.MODELS``), its
parameters are built from the node's config slice (``Model.scene_params``).
"""
from __future__ import annotations

from dataclasses import asdict

from dermis.pipeline import registry
from dermis.pipeline.artifacts import RenderedImage
from dermis.pipeline.config import CameraConfig
from dermis.pipeline.errors import ConfigError
from dermis.pipeline.graph import Node, StageResult
from dermis.pipeline.imageio import write_exr
from dermis.rendering.options import RenderOptions
from dermis.rendering.shade import render
from dermis.rendering.surface import SURFACES

__all__ = ["NAME", "VERSION", "KERNELS", "GEOMETRY", "geometry_inputs", "node_id", "node", "plan",
           "run"]

NAME = "render"
VERSION = 2
KERNELS = ()   # rendering/surface.py and rendering/shade.py declare the kernels they build
SHARES = (SURFACES,)   # a model adds its own (Model.shares) to its nodes

# geometry -> (mesh node, bump map variant)
GEOMETRY = {"high": ("mesh_high", None), "low": ("mesh_low", None),
            "low_bump": ("mesh_low", "sharp"), "low_bump_blur": ("mesh_low", "blur")}


def geometry_inputs(geometry: str, label: str | None = None) -> dict:
    """Upstream roles of an image of ``geometry``: its mesh, the baked maps when bumped, and
    (given the lighting ``label``) the shared visibility of that mesh and lighting."""
    mesh_node, bump = GEOMETRY[geometry]
    visibility = registry.stage("visibility")
    return {"mesh": mesh_node, **({"maps": "bake"} if bump else {}),
            **({"visibility": visibility.node_id(mesh_node, label)} if label is not None else {})}


def node_id(model: str, label: str, geometry: str) -> str:
    """An image's id: ``render-<model>-<lighting>-<geometry>``."""
    return f"{NAME}-{model}-{label}-{geometry}"


def _model(name: str):
    m = registry.model(name)
    if m.stage != NAME:
        raise ConfigError(f"model = {name!r}: not a model of the render stage (its stage is "
                          f"{m.stage!r})")
    return m


def node(scene, model: str, label: str, lights: tuple, geometry: str) -> Node:
    """One image; the lights, camera rays and seed reach it through its visibility input."""
    m = _model(model)
    base = scene.render.asperity_base if m.bases else None
    params = {"model": model, "label": label, "geometry": geometry,
              "camera": asdict(scene.camera_of(label)), "bump": GEOMETRY[geometry][1],
              "asperity_base": base,
              "optics": scene.optics.to_dict() if m.reads_optics(base) else None}
    indirect = registry.stage("indirect").inputs(scene, GEOMETRY[geometry][0], label)
    return Node(node_id(model, label, geometry), NAME, __name__, params,
                {**geometry_inputs(geometry, label), **indirect},
                label=f"{model} / {label} / {geometry}",
                code=(registry.model_module(model),),
                shares=m.shares + (m.base(base).shares if base is not None else ()))


def plan(scene, plan) -> None:
    """Every BRDF model x lighting condition x geometry, each with its mesh and lighting's
    shared visibility (one node however many models read it)."""
    visibility = registry.stage("visibility")
    for model, label, lights, geometry in plan.images_of(NAME):
        plan.add(visibility.node(scene, GEOMETRY[geometry][0], label, lights))
        plan.add(node(scene, model, label, lights, geometry), provides="image")


def run(params: dict, inputs: dict, ctx) -> StageResult:
    mesh, model, samples = inputs["mesh"], params["model"], inputs["visibility"]
    m, base = _model(model), params["asperity_base"]
    p = m.scene_params(params, ctx.shared)
    base_params = m.base(base).scene_params(params, ctx.shared) if base is not None else None
    result = render(mesh, [], m, p, CameraConfig(**params["camera"]),
                    RenderOptions(maps=inputs.get("maps"), bump=params["bump"], samples=samples,
                                  base=base, base_params=base_params,
                                  indirect=inputs["indirect"].irradiance
                                  if "indirect" in inputs else None),
                    cl_env=ctx.cl, progress=ctx.progress, shared=ctx.shared,
                    keys=(ctx.input_keys["mesh"], ctx.input_keys.get("maps")))
    result.timings["visibility_shared"] = float(
        (samples.info.get("timings") or {}).get("total", 0.0))
    name = f"{model}-{params['label']}-{params['geometry']}"
    write_exr(ctx.out_dir / f"{name}.exr", result.linear)
    image = RenderedImage(result.linear, result.mask, dict(result.timings),
                          {**result.info, "model": model, "light": params["label"],
                           "geometry": params["geometry"]},
                          noise=result.noise)
    return StageResult(image, files=[f"{name}.exr"],
                       info={"timings": result.timings,
                             "kernel_seconds": result.timings.get("kernel_seconds", 0.0)})
