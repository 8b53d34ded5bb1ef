"""Stage ``render``: one image per BRDF model x lighting condition x geometry, shaded by
:func:`dermis.rendering.shade.render` on the shared visibility of its mesh and lighting
condition (stage ``visibility``).  The model is looked up by name (``dermis.MODELS``), its
parameters are built from the node's config slice (``Model.scene_params``).
"""
from __future__ import annotations

from dataclasses import asdict

from dermis.models import asperity, hk93, lafortune
from dermis.pipeline import registry
from dermis.pipeline.artifacts import RenderedImage
from dermis.pipeline.config import CameraConfig
from dermis.pipeline.errors import ConfigError
from dermis.pipeline.graph import Node, StageResult
from dermis.pipeline.imageio import write_exr
from dermis.rendering.options import RenderOptions
from dermis.rendering.shade import render

__all__ = ["NAME", "VERSION", "KERNELS", "GEOMETRY", "geometry_inputs", "visibility_id", "node",
           "run"]

NAME = "render"
VERSION = 2
KERNELS = ()   # rendering/surface.py and rendering/shade.py declare the kernels they build

# The models this stage renders.  Imported, not only looked up by name: a node's key covers
# the code it runs by following import statements (pipeline/codehash.py), which do not reach
# through the registry; node() refuses a model missing here.
KEYED_MODELS = (lafortune.MODEL, asperity.MODEL, hk93.MODEL)

# geometry -> (mesh node, bump map variant)
GEOMETRY = {"high": ("mesh_high", None), "low": ("mesh_low", None),
            "low_bump": ("mesh_low", "sharp"), "low_bump_blur": ("mesh_low", "blur")}


def geometry_inputs(geometry: str, label: str | None = None) -> dict:
    """Upstream roles of an image of ``geometry``: its mesh, the baked maps when bumped, and
    (given the lighting ``label``) the shared visibility of that mesh and lighting."""
    mesh_node, bump = GEOMETRY[geometry]
    return {"mesh": mesh_node, **({"maps": "bake"} if bump else {}),
            **({"visibility": visibility_id(mesh_node, label)} if label is not None else {})}


def visibility_id(mesh_node: str, label: str) -> str:
    """Node id of the shared visibility of a mesh and lighting condition (stages/visibility.py)."""
    return f"visibility-{mesh_node}-{label}"


def _model(name: str):
    m = registry.model(name)
    if m.stage != NAME or m not in KEYED_MODELS:
        raise ConfigError(f"model = {name!r}: not a model of the render stage "
                          f"({', '.join(k.name for k in KEYED_MODELS)})")
    return m


def node(scene, model: str, label: str, lights: tuple, geometry: str) -> Node:
    """One image; the lights, camera rays and seed reach it through its visibility input."""
    m = _model(model)
    base = scene.render.asperity_base if m.bases else None
    params = {"model": model, "label": label, "geometry": geometry,
              "camera": asdict(scene.camera), "bump": GEOMETRY[geometry][1],
              "asperity_base": base,
              "optics": scene.optics.to_dict() if m.reads_optics(base) else None}
    return Node(f"render-{model}-{label}-{geometry}", NAME, __name__, params,
                geometry_inputs(geometry, label), label=f"{model} / {label} / {geometry}")


def run(params: dict, inputs: dict, ctx) -> StageResult:
    mesh, model, samples = inputs["mesh"], params["model"], inputs["visibility"]
    m, base = _model(model), params["asperity_base"]
    p = m.scene_params(params, ctx.memo)
    base_params = m.base(base).scene_params(params, ctx.memo) if base is not None else None
    result = render(mesh, [], m, p, CameraConfig(**params["camera"]),
                    RenderOptions(maps=inputs.get("maps"), bump=params["bump"], samples=samples,
                                  base=base, base_params=base_params),
                    cl_env=ctx.cl, progress=ctx.progress, memo=ctx.memo)
    result.timings["visibility_shared"] = float(
        (samples.info.get("timings") or {}).get("total", 0.0))
    name = f"{model}-{params['label']}-{params['geometry']}"
    write_exr(ctx.out_dir / f"{name}.exr", result.linear)
    image = RenderedImage(result.linear, result.mask, dict(result.timings),
                          {**result.info, "model": model, "light": params["label"],
                           "geometry": params["geometry"]})
    return StageResult(image, files=[f"{name}.exr"],
                       info={"timings": result.timings,
                             "kernel_seconds": result.timings.get("kernel_seconds", 0.0)})
