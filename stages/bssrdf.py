"""Stage ``bssrdf``: Jensen-Buhler pass 2 at every pixel of one BSSRDF image.

Per pixel: the surface seen by the camera (shared with the BRDF renderer,
:func:`dermis.rendering.surface.pixel_surface`), the radiant exitance from the hierarchical
gather over the irradiance points (:func:`dermis.subsurface.exitance.exitance`), the
Fresnel-weighted exit to radiance (:func:`dermis.subsurface.radiance.exitance_to_radiance`),
and the surface reflection
term (Lafortune's specular lobes with rho_d = 0, so the images compare with the BRDF
models').  One node per BSSRDF model (``bssrdf``: the scene's profile model; ``bssrdf_mc``: the
Monte Carlo-tabulated profile; a model with its own ``Model.exitance``, ``bssrdf_adaptive``:
the local model with the gather where its predictor asks, its blend mask written beside the
image), lighting condition and geometry; pass 1 is the ``irradiance`` stage.

The image carries its own noise estimate (``RenderedImage.noise``): the surface term's halves,
the exitance's over the same halves of the camera samples, and the points' irradiance noise
gathered (``exitance``'s ``noise``); docs/science.md §6 "Each image's own noise".
"""
from __future__ import annotations

import time
from dataclasses import asdict

import numpy as np

from dermis.pipeline.artifacts import RenderedImage
from dermis.pipeline.config import CameraConfig, LightConfig, condition_of
from dermis.pipeline.graph import Node, StageResult
from dermis.pipeline.imageio import write_exr
from dermis.pipeline import registry
from dermis.models import lafortune
from dermis.optics.transmittance import Transmittance
from dermis.rendering.halves import camera_halves
from dermis.rendering.options import RenderOptions
from dermis.rendering import shade
from dermis.rendering.surface import SURFACES, pixel_surface
from dermis.subsurface.exitance import (GATHERS, NEAR_TABLES, OCTREES, POINT_TREES, SHADOW_EDGES,
                                        ExitanceOptions, ShadingPoints, exitance)
from dermis.subsurface.near_field import SHARP_LIGHTS
from dermis.subsurface.radiance import exitance_to_radiance
from dermis.subsurface.shadow_edges import sharp_visibility
from dermis.lighting.emitters import light_params
from dermis.lighting.visibility import EMBREE_SCENES, embree_scene

NAME = "bssrdf"
VERSION = 4   # 2: optics-resolved near field, entry/exit transmittance; 3: the blend weight;
#               4: the image's own noise estimate
KERNELS = ()
SHARES = (EMBREE_SCENES, SURFACES, OCTREES, SHADOW_EDGES, NEAR_TABLES, GATHERS, POINT_TREES)
OUTPUT_FOLDER = "render"   # exported beside the BRDF images: render/<model>-<light>-<geometry>.exr


def node_id(model: str, label: str, geometry: str) -> str:
    """A BSSRDF image's id, in the form every image has (``render-<model>-<lighting>-<geometry>``,
    stages/render.py node_id): the images, differences and report stages read them alike."""
    return f"render-{model}-{label}-{geometry}"


def node(scene, label: str, lights: tuple, geometry: str, model: str = "bssrdf") -> Node:
    """One BSSRDF image; ``model`` (a key of ``config.BSSRDF_MODELS``) picks the profiles
    node its gather reads: ``bssrdf`` the scene's ``[optics] profile``, ``bssrdf_mc`` the
    Monte Carlo table.  Points, irradiance and visibility are the same for both."""
    render, profiles = registry.stage("render"), registry.stage("profiles")
    mesh_node, bump = render.GEOMETRY[geometry]
    deps = {**render.geometry_inputs(geometry, label),
            "points": registry.stage("samples").node_id(mesh_node),
            "irradiance": registry.stage("irradiance").node_id(mesh_node, condition_of(label)),
            "profile": profiles.node_id(scene, profiles.profile_of(scene, registry.model(model)))}
    params = {"label": label, "geometry": geometry, "camera": asdict(scene.camera_of(label)),
              "bump": bump, "bssrdf": asdict(scene.bssrdf), **light_params(lights),
              "seed": scene.mesh.seed, "eta": scene.optics.layers[0].eta / scene.optics.eta_above}
    if model != "bssrdf":
        params["model"] = model
    if scene.render.indirect:   # its irradiance holds a bounce of indirect light (exitance.py)
        params["indirect"] = True
    m = registry.model(model)   # a model with its own exitance: its code enters the key
    return Node(node_id(model, label, geometry), NAME, __name__, params, deps,
                label=f"{model} / {label} / {geometry}", locations=("lights[].map",),
                code=(registry.model_module(model),) if m.exitance else (), shares=m.shares)


def _surface_term(mesh, lights, camera, maps, bump, seed, samples, ctx) -> tuple[np.ndarray, dict]:
    """Lafortune's specular lobes (rho_d = 0): the light reflected at the surface, shaded
    with the shared visibility (the same rays as the BRDF models)."""
    spec = shade.render(mesh, lights, lafortune.MODEL,
                        lafortune.LafortuneParams(rho_d=(0.0, 0.0, 0.0)), camera,
                        RenderOptions(maps=maps, bump=bump, seed=seed, samples=samples,
                                      textured=False), cl_env=ctx.cl, shared=ctx.shared,
                        keys=(ctx.input_keys["mesh"], ctx.input_keys.get("maps")))
    noise = None if spec.noise is None else spec.noise.reshape(-1, 3)
    return spec.linear.reshape(-1, 3), spec.timings, noise


def run(params: dict, inputs: dict, ctx) -> StageResult:
    t_start = time.perf_counter()
    b = params["bssrdf"]
    mesh, maps, profile = inputs["mesh"], inputs.get("maps"), inputs["profile"]
    camera = CameraConfig(**params["camera"])
    lights = [LightConfig(**d) for d in params["lights"]]
    vis = inputs["visibility"]   # shared camera + shadow rays (rendering/cast.py)
    px = pixel_surface(mesh, camera, vis, RenderOptions(maps=maps, bump=params["bump"]),
                       cl_env=ctx.cl, shared=ctx.shared,
                       keys=(ctx.input_keys["mesh"], ctx.input_keys.get("maps")))
    t_vis = time.perf_counter() - t_start
    front, surf = px.front_idx, px.surf
    t0 = time.perf_counter()
    # far part of the profile from the points, near part at each shading point, with the
    # entry transmittance the irradiance stage applied (subsurface/near_field.py)
    transmit = Transmittance(params["eta"], b["surface_reflection"])
    # the mesh's Embree scene only where the near field traces it (point/directional lights'
    # shadow edges): building it for the 1M-triangle scan took 3.5 s of a 10.5 s image
    # re-rendered alone (bench/results/bssrdf.json), unused by area and environment light
    model = registry.model(params.get("model", "bssrdf"))
    vis_embree = (embree_scene(mesh, ctx.shared, ctx.input_keys["mesh"])
                  if model.exitance or any(l.type in SHARP_LIGHTS for l in lights) else None)
    shading = ShadingPoints(surf["position"][front], surf["shading_normal"][front],
                            surf["geo_normal"][front],
                            visible=sharp_visibility(vis, front, surf["position"][front], lights))
    options = ExitanceOptions(epsilon=b["epsilon"], normalisation=b["normalisation"],
                              leaf_size=b["leaf_size"], brute_force=b["brute_force"],
                              transmittance=transmit, indirect=params.get("indirect", False),
                              env=ctx.cl, progress=ctx.progress)
    frame = ({"camera": camera, "pixels": px.hit_idx[front]}   # where the points lie in the
             if model.exitance else {})                       # image (Model.exitance)
    irr = inputs["irradiance"]
    M, stats = (model.exitance or exitance)(
        inputs["points"], irr.irradiance, profile, shading, lights=lights,
        visibility=vis_embree, options=options, shared=ctx.shared, **frame,
        keys=(ctx.input_keys["points"], ctx.input_keys["irradiance"], ctx.input_keys["profile"]),
        noise=getattr(irr, "noise", None))
    M_noise = stats.pop("noise", None)
    blend = stats.pop("blend_image", None)
    stats.pop("blend", None)
    stats.pop("predicted_images", None)
    t_gather = time.perf_counter() - t0
    cos_o = np.einsum("ij,ij->i", surf["shading_normal"][front], surf["wo"][front])
    albedo = None if b["albedo_mode"] == "none" else surf["albedo"][front]
    def radiance(m):
        return exitance_to_radiance(m, cos_o, params["eta"], albedo=albedo,
                                    albedo_mode="replace" if albedo is None else b["albedo_mode"],
                                    rd=profile.Rd, transmittance=transmit)
    L = radiance(M)
    image = px.pixels(L, front)   # box filter over the pixel's camera samples
    # the exitance's noise: its camera samples' halves (the sub-pixel positions, the albedo
    # under them) and the points' noise gathered, to radiance as M (linear in it)
    noise = camera_halves(px, L, front)
    if M_noise is not None:
        noise = noise + px.pixels(radiance(M_noise), front)
    timings = {"visibility": t_vis, "gather": t_gather,
               **{k: float(stats[k]) for k in ("edges_seconds", "near_seconds", "local_seconds",
                                               "predictor_seconds", "adaptive_gather_seconds")
                  if k in stats},
               "kernel_seconds": float(stats.get("kernel_seconds", 0.0)) + px.kernel_seconds}
    if b["surface_reflection"] == "lafortune_lobes":
        spec, spec_t, spec_noise = _surface_term(mesh, lights, camera, maps, params["bump"],
                                                 params["seed"], vis, ctx)
        image += spec
        if spec_noise is not None:
            noise = noise + spec_noise
        timings["surface_reflection"] = spec_t["total"]
        timings["kernel_seconds"] += spec_t.get("kernel_seconds", 0.0)
    image = np.nan_to_num(image, nan=0.0, posinf=0.0, neginf=0.0)
    # the image's own work: the surface pass is shared by the geometry's images (its seconds
    # in "surface_shared", rendering/surface.py pixel_surface), like the visibility
    timings["surface_shared"] = px.surface_seconds
    timings["total"] = time.perf_counter() - t_start - t_vis
    linear = image.reshape(px.height, px.width, 3)
    mask = px.mask
    model = params.get("model", "bssrdf")
    name = f"{model}-{params['label']}-{params['geometry']}"
    write_exr(ctx.out_dir / f"{name}.exr", linear)
    files = [f"{name}.exr"]
    if blend is not None:   # the adaptive model's blend weight per pixel (0 local, 1 gathered)
        write_exr(ctx.out_dir / f"{name}-blend.exr", np.repeat(blend[..., None], 3, axis=2))
        files.append(f"{name}-blend.exr")
    info = {"model": model, "light": params["label"], "geometry": params["geometry"],
            "profile_model": profile.info.get("model", "multipole"),
            "gather": {k: v for k, v in stats.items() if isinstance(v, (int, float, str))}}
    noise = np.nan_to_num(noise, nan=0.0, posinf=0.0, neginf=0.0).reshape(
        px.height, px.width, 3).astype(np.float32)
    return StageResult(RenderedImage(linear, mask, timings, info, noise=noise,
                                     blend=None if blend is None else blend.astype(np.float32)),
                       files=files,
                       info={"timings": timings, "kernel_seconds": timings["kernel_seconds"]})


def plan(scene, plan) -> None:
    """Every BSSRDF model x lighting condition x geometry, with the inputs they share: the
    visibility of the mesh and lighting, the mesh's irradiance points and their irradiance
    under the lighting (the profiles are the profiles stage's)."""
    render = registry.stage("render")
    visibility, samples = registry.stage("visibility"), registry.stage("samples")
    irradiance = registry.stage("irradiance")
    for model, label, lights, geometry in plan.images_of(NAME):
        mesh_node = render.GEOMETRY[geometry][0]
        plan.add(visibility.node(scene, mesh_node, label, lights))
        plan.add(samples.node(scene, mesh_node))
        plan.add(irradiance.node(scene, mesh_node, condition_of(label), lights))
        plan.add(node(scene, label, lights, geometry, model), provides="image")
