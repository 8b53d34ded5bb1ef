"""Stage ``cycles``: Blender Cycles' skin models (models/cycles_*.py) rendered by Cycles.

One image node per Cycles model x mapping (``[cycles] mappings``) x lighting condition of
the main camera x geometry (``[cycles] geometries`` that ``[render] geometries`` also
lists): the scene's mesh, camera, lights and albedo texture rendered by Blender
(:mod:`dermis.cycles.job`: a serving process that keeps the mesh and its BVH from one image
to the next) as two half images of independent seeds, on the reference's pixel grid
(``[cycles] size``), to the noise ``[cycles] target_noise`` on blocks of ``noise_block``
reference pixels (:mod:`dermis.cycles.sampling`), and handed on at the camera's size, each
rendered pixel repeated over the camera pixels it covers.  The
``matched`` images read one slab node per subsurface method (Cycles' flat-slab curves,
:mod:`dermis.cycles.slab`) and the Monte Carlo layer profile (the skin's Rd and mean exit
radius); the mapping itself is :mod:`dermis.cycles.mapping`.  Where bpy is missing the
stage plans nothing and says why once (:mod:`dermis.cycles.availability`).
"""
from __future__ import annotations

import sys
from dataclasses import asdict

import numpy as np

from dermis.cycles import availability, mapping
from dermis.cycles.environment import split_sun
from dermis.cycles.job import run_job
from dermis.cycles.slab import slab_curves
from dermis.geometry.normals import vertex_normals
from dermis.lighting.emitters import light_params
from dermis.pipeline import registry
from dermis.pipeline.artifacts import RenderedImage
from dermis.pipeline.config import CameraConfig, LightConfig
from dermis.pipeline.graph import Node, StageResult
from dermis.pipeline.imageio import write_exr
from dermis.pipeline.scene_rules import reference_size
from dermis.rendering.camera import camera_vectors
from dermis.rendering.color import srgb_to_linear

NAME = "cycles"
VERSION = 2
KERNELS = ()
OUTPUT_FOLDER = "render"
PROFILE = "monte_carlo"   # the skin's Rd and mean exit radius: the path-traced layer profile
MESH = {"high": "mesh_high", "low": "mesh_low"}
# the module the render process runs (started by name, not imported here): its code, and
# the scene building and sampling it imports, enter the nodes' keys
RENDER_PROCESS = "dermis.cycles.render_job"


def image_name(model: str, mapping_name: str) -> str:
    """``cycles_burley`` (matched) or ``cycles_burley_native``."""
    return model if mapping_name == "matched" else f"{model}_{mapping_name}"


def node_id(model: str, mapping_name: str, label: str, geometry: str) -> str:
    return f"render-{image_name(model, mapping_name)}-{label}-{geometry}"


def render_size(scene) -> tuple[int, int]:
    """The pixels Cycles renders: the reference's grid (``[cycles] size = "reference"``),
    where every distance to the truth is measured, or the camera's."""
    if scene.cycles.size == "camera":
        return int(scene.camera.width), int(scene.camera.height)
    return reference_size(scene.camera, scene.reference)


def _block(scene) -> int:
    """The noise block in rendered pixels: ``[cycles] noise_block`` reference pixels."""
    w, _ = render_size(scene)
    ref_w, _ = reference_size(scene.camera, scene.reference)
    return max(int(scene.cycles.noise_block) * w // max(ref_w, 1), 1)


def slab_node(scene, method: str) -> Node:
    s = mapping.surface_inputs(scene.optics, scene.reference.roughness)
    params = {"kind": "slab", "method": method, **s, "threads": scene.cycles.threads,
              "seed": scene.cycles.seed}
    return Node(f"{NAME}-slab-{method.lower()}", NAME, __name__, params, (),
                label=f"Cycles slab curves ({method})", code=(RENDER_PROCESS,))


def node(scene, model: str, mapping_name: str, label: str, lights: tuple, geometry: str) -> Node:
    method = registry.model(model).scene_params(None, None).method
    c = scene.cycles
    params = {"kind": "image", "model": model, "method": method, "mapping": mapping_name,
              "label": label, "geometry": geometry, "camera": asdict(scene.camera),
              "size": list(render_size(scene)),
              **light_params(lights), "optics": scene.optics.to_dict(),
              "roughness": scene.reference.roughness,
              "sampling": {"target_noise": c.target_noise, "block": _block(scene),
                           "pilot_spp": c.pilot_spp, "max_spp": c.max_spp},
              "seed": c.seed, "threads": c.threads}
    profiles = registry.stage("profiles")
    deps = {"mesh": MESH[geometry], "profile": profiles.node_id(scene, PROFILE)}
    if mapping_name == "matched":
        deps["slab"] = slab_node(scene, method).id
    return Node(node_id(model, mapping_name, label, geometry), NAME, __name__, params, deps,
                label=f"{image_name(model, mapping_name)} / {label} / {geometry} (Cycles)",
                locations=("lights[].map",), code=(registry.model_module(model), RENDER_PROCESS))


def _inputs(params, profile, slab) -> dict:
    from dermis.optics.layers import LayerStack
    stack = LayerStack.from_dict(params["optics"])
    if params["mapping"] == "native":
        return mapping.native_inputs(stack, profile.Rd, params["roughness"])
    return mapping.matched_inputs(stack, profile.Rd, mapping.mean_exit_radius(profile), slab,
                                  params["roughness"])


def _run_image(params: dict, inputs: dict, ctx) -> StageResult:
    mesh, profile = inputs["mesh"], inputs["profile"]
    material = {"method": params["method"], **_inputs(params, profile, inputs.get("slab"))}
    camera = CameraConfig(**params["camera"])
    lights = [LightConfig(**d) for d in params["lights"]]
    pos, fwd, _, up = camera_vectors(camera)
    arrays = {"vertices": mesh.vertices, "faces": mesh.faces, "normals": vertex_normals(mesh),
              "uv": mesh.uv, "uv_faces": mesh.uv_faces}
    if mesh.texture_srgb is not None and mesh.uv is not None:
        albedo = srgb_to_linear(np.asarray(mesh.texture_srgb, np.float32) / 255.0)
        if params["mapping"] == "matched":
            slab = inputs["slab"]
            albedo = mapping.invert_reflectance(albedo, slab.grid, slab.rd_e)
        arrays["base_texture"] = albedo.astype(np.float32)
    env = [l for l in lights if l.type == "environment"]
    extra = []
    if env:
        arrays["environment"], sun = split_sun(env[0])
        extra = [sun] if sun is not None else []
    w, h = params["size"]
    job = {"kind": "head", "width": w, "height": h,
           "threads": params["threads"], "seed": params["seed"],
           "camera": {"position": pos.tolist(), "forward": fwd.tolist(), "up": up.tolist(),
                      "fov_deg": camera.fov_deg},
           "lights": [asdict(l) for l in lights] + extra, "material": material,
           "sampling": params["sampling"]}
    result, out = run_job(job, arrays, serve=True)
    a, b = out["half_a"], out["half_b"]
    linear = ((a + b) / 2).astype(np.float32)
    name = f"{image_name(params['model'], params['mapping'])}-{params['label']}-{params['geometry']}"
    write_exr(ctx.out_dir / f"{name}.exr", linear)     # as rendered, at its own size
    # the artifact at the camera's size, each rendered pixel repeated over the camera pixels
    # it covers: every consumer (sheets, differences, the truth's block means, the page)
    # reads it as any model image, and its block means are the render's pixels exactly
    fy, fx = camera.height // h, camera.width // w
    up = (lambda a: np.repeat(np.repeat(a, fy, axis=0), fx, axis=1))   # noqa: E731
    timings = {"total": result["wall_seconds"], "render": result["render_seconds"],
               "scene_build": result["build_seconds"], "startup": result["startup_seconds"],
               "cpu": result["cpu_seconds"], "kernel_seconds": 0.0}
    info = {"model": image_name(params["model"], params["mapping"]), "light": params["label"],
            "geometry": params["geometry"], "renderer": f"Blender {result['blender']} Cycles",
            "method": params["method"], "mapping": params["mapping"], "inputs": material,
            "spp": result["spp"], "noise": result["noise"], "rendered_size": [w, h],
            "noise_block": params["sampling"]["block"], "mesh_reused": result["mesh_reused"],
            "target_noise": params["sampling"]["target_noise"], "passes": result["passes"]}
    return StageResult(RenderedImage(up(linear), up(out["coverage"].astype(bool)), timings, info,
                                     noise=up(((a - b) / 2).astype(np.float32))),
                       files=[f"{name}.exr"], info={"timings": timings, "spp": result["spp"],
                                                    "noise": result["noise"],
                                                    "kernel_seconds": 0.0})


def run(params: dict, inputs: dict, ctx) -> StageResult:
    if params["kind"] == "image":
        return _run_image(params, inputs, ctx)
    curves = slab_curves(params["method"], ior=params["ior"], roughness=params["roughness"],
                         anisotropy=params["anisotropy"], threads=params["threads"],
                         seed=params["seed"])
    return StageResult(curves, info={"seconds": curves.info["seconds"],
                                     "cpu_seconds": curves.info["cpu_seconds"],
                                     "kernel_seconds": 0.0,
                                     "specular": curves.specular.tolist()})


_SKIP_NOTICES: set = set()   # each reason once per process


def plan(scene, plan) -> None:
    """Every Cycles model x mapping x lighting condition of the main camera x geometry, with
    the profiles and slab nodes they read (the close-up views get none); where bpy is
    missing, none, with the reason said once."""
    images = [(m, l, ls, g) for m, l, ls, g in plan.images_of(NAME)
              if g in scene.cycles.geometries and scene.view_of(l) is None]
    if not images:
        return
    reason = availability.missing_reason()
    if reason:
        models = sorted({m for m, *_ in images})
        text = f"Cycles models skipped ({', '.join(models)}): {reason}"
        if text not in _SKIP_NOTICES:
            _SKIP_NOTICES.add(text)
            print(f"dermis: {text}", file=sys.stderr)
        plan.skipped[NAME] = text
        return
    plan.add(registry.stage("profiles").node(scene, PROFILE))
    for model, label, lights, geometry in images:
        for mapping_name in scene.cycles.mappings:
            if mapping_name == "matched":
                method = registry.model(model).scene_params(None, None).method
                plan.add(slab_node(scene, method))
            plan.add(node(scene, model, mapping_name, label, lights, geometry), provides="image")
