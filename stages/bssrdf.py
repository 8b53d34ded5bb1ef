"""Stage ``bssrdf``: Jensen-Buhler pass 2 at every pixel of one BSSRDF image.

Per pixel: the surface seen by the camera (shared with the BRDF renderer,
:func:`dermis.stages.render.pixel_surface`), the radiant exitance from the hierarchical
gather over the irradiance points (:mod:`dermis.stages.gather`), the Fresnel-weighted exit
to radiance (:func:`dermis.stages.gather.exitance_to_radiance`), and the surface reflection
term (Lafortune's specular lobes with rho_d = 0, so the images compare with the BRDF
models').  One node per lighting condition and geometry; pass 1 is the ``irradiance`` stage.
"""
from __future__ import annotations

import time
from dataclasses import asdict

import numpy as np

from dermis.pipeline.artifacts import RenderedImage
from dermis.pipeline.config import CameraConfig, LightConfig
from dermis.pipeline.graph import Node, StageResult
from dermis.pipeline.imageio import write_exr
from dermis.physics.visibility import shared as shared_visibility
from dermis.stages import gather, render
from dermis.physics.lights import light_params

NAME = "bssrdf"
VERSION = 1
KERNELS = ()
OUTPUT_FOLDER = "render"   # exported beside the BRDF images: render/bssrdf-<light>-<geometry>.exr


def node(scene, label: str, lights: tuple, geometry: str) -> Node:
    mesh_node, bump = render.GEOMETRY[geometry]
    deps = {**render.geometry_inputs(geometry), "points": f"samples-{mesh_node}",
            "irradiance": f"irradiance-{mesh_node}-{label}", "profile": "profiles"}
    params = {"label": label, "geometry": geometry, "camera": asdict(scene.camera),
              "bump": bump, "bssrdf": asdict(scene.bssrdf), **light_params(lights),
              "seed": scene.mesh.seed, "eta": scene.optics.layers[0].eta / scene.optics.eta_above}
    return Node(f"render-bssrdf-{label}-{geometry}", NAME, __name__, params, deps,
                label=f"bssrdf / {label} / {geometry}", locations=("lights[].map",))


def _octree(inputs: dict, b: dict, memo: dict):
    """One octree per (points, lighting), shared by the geometries of a mesh in a run."""
    key = ("octree", id(inputs["irradiance"]))
    if key not in memo:
        pts = inputs["points"]
        memo[key] = (inputs["irradiance"], gather.build_octree(
            pts.positions, pts.areas, inputs["irradiance"].irradiance, leaf_size=b["leaf_size"],
            kernel_sigma_mm=pts.info.get("kernel_sigma_mm")))  # the areas' partition of unity
    return memo[key][1]


def _surface_term(mesh, lights, camera, maps, bump, seed, vis, ctx) -> tuple[np.ndarray, dict]:
    """Lafortune's specular lobes (rho_d = 0): the light reflected at the surface."""
    from dermis.stages.brdf_models import LafortuneParams
    spec = render.render(mesh, lights, "lafortune", LafortuneParams(rho_d=(0.0, 0.0, 0.0)),
                         camera, maps=maps, bump=bump, seed=seed, visibility=vis, cl_env=ctx.cl,
                         textured=False)
    return spec.linear.reshape(-1, 3), spec.timings


def run(params: dict, inputs: dict, ctx) -> StageResult:
    t_start = time.perf_counter()
    b = params["bssrdf"]
    mesh, maps, profile = inputs["mesh"], inputs.get("maps"), inputs["profile"]
    camera = CameraConfig(**params["camera"])
    lights = [LightConfig(**d) for d in params["lights"]]
    vis = shared_visibility(mesh, ctx.memo)
    px = render.pixel_surface(mesh, camera, maps=maps, bump=params["bump"], visibility=vis,
                              cl_env=ctx.cl)
    t_vis = time.perf_counter() - t_start
    t0 = time.perf_counter()
    tree = _octree(inputs, b, ctx.memo)
    t_tree = time.perf_counter() - t0
    front, surf = px.front_idx, px.surf
    t0 = time.perf_counter()
    M, stats = gather.gather(tree, profile, surf["position"][front], epsilon=b["epsilon"],
                             normalisation=b["normalisation"], env=ctx.cl,
                             brute_force=b["brute_force"], progress=ctx.progress)
    t_gather = time.perf_counter() - t0
    cos_o = np.einsum("ij,ij->i", surf["shading_normal"][front], surf["wo"][front])
    albedo = None if b["albedo_mode"] == "none" else surf["albedo"][front]
    L = gather.exitance_to_radiance(M, cos_o, params["eta"], albedo=albedo,
                                    albedo_mode="replace" if albedo is None else b["albedo_mode"],
                                    rd=profile.Rd)
    image = np.zeros((px.height * px.width, 3), np.float32)
    image[px.hit_idx[front]] = L
    timings = {"visibility": t_vis, "octree": t_tree, "gather": t_gather,
               "kernel_seconds": float(stats.get("kernel_seconds", 0.0)) + px.kernel_seconds}
    if b["surface_reflection"] == "lafortune_lobes":
        spec, spec_t = _surface_term(mesh, lights, camera, maps, params["bump"], params["seed"],
                                     vis, ctx)
        image += spec
        timings["surface_reflection"] = spec_t["total"]
        timings["kernel_seconds"] += spec_t.get("kernel_seconds", 0.0)
    image = np.nan_to_num(image, nan=0.0, posinf=0.0, neginf=0.0)
    timings["total"] = time.perf_counter() - t_start
    linear = image.reshape(px.height, px.width, 3)
    mask = px.hits.hit.reshape(px.height, px.width)
    name = f"bssrdf-{params['label']}-{params['geometry']}"
    write_exr(ctx.out_dir / f"{name}.exr", linear)
    info = {"model": "bssrdf", "light": params["label"], "geometry": params["geometry"],
            "gather": {k: v for k, v in stats.items() if isinstance(v, (int, float, str))}}
    return StageResult(RenderedImage(linear, mask, timings, info), files=[f"{name}.exr"],
                       info={"timings": timings, "kernel_seconds": timings["kernel_seconds"]})
