"""Stage ``causes``: the reference's controlled variants for one lighting condition.

Why is every model darker than the path tracer?  Two of the candidate causes are properties
of the reference's scene, measured here by rendering it with that one property changed
(:mod:`dermis.groundtruth.variants`, docs/ground-truth.md "Causes of the distance"):

* ``interreflection``: a diffuse head of the texture's albedo with all bounces over direct
  light only, minus 1, per face region -- every lighting condition;
* ``boundary``: the skin head with a smooth boundary (the models') over the rough one (the
  reference's), each normalised to read the texture as total diffuse reflectance, minus 1
  -- only the conditions of ``[causes] boundary_lights`` (default: those of disc lights only;
  a smooth boundary never connects a path inside skin to a point or directional light).

Each effect comes with its standard error from two independent half-buffers.  One node per
lighting condition the reference renders, on the high mesh at the reference's size; the node
exists when ``[reference]`` and ``[causes]`` are enabled and Mitsuba runs here.  The artifact
is a :class:`RenderedImage` whose ``linear`` is the diffuse head's interreflected light (all
bounces - direct, >= 0) and whose ``info["causes"]`` holds, per cause and region, the effect
per channel and in luminance with its standard error; :mod:`dermis.reports.causes` turns
these and the ground-truth metrics into the causes table.
"""
from __future__ import annotations

import json
import sys
import time
from dataclasses import asdict

import numpy as np

from dermis.geometry.regions import region_colours
from dermis.groundtruth import mitsuba
from dermis.groundtruth.variants import (CAUSE_EFFECTS, VariantOptions, boundary_lights_problem,
                                         boundary_variant, interreflection_variant)
from dermis.lighting.emitters import light_params
from dermis.optics.layers import LayerStack
from dermis.pipeline.artifacts import RenderedImage
from dermis.pipeline.config import MAIN_VIEW, CameraConfig, LightConfig
from dermis.pipeline.errors import ConfigError
from dermis.pipeline.graph import Node, StageResult
from dermis.pipeline.scene_rules import reference_size
from dermis.pipeline.imageio import write_exr, write_png

NAME = "causes"
VERSION = 1
KERNELS = ()
GEOMETRY = "high"
MESH_NODE = "mesh_high"
# the [reference] settings the variants share with the reference (its size, boundary,
# integrator, environment clamp and Mitsuba variant)
REFERENCE_KEYS = ("width", "height", "roughness", "max_depth", "rr_depth", "env_clamp",
                  "variant")


def node_id(label: str) -> str:
    return f"{NAME}-{label}"


def boundary_labels(scene) -> tuple:
    """The lighting conditions of the boundary variant: ``[causes] boundary_lights``, or
    (empty) those whose lights are all discs."""
    groups = dict(scene.light_groups(MAIN_VIEW))
    if scene.causes.boundary_lights:
        return tuple(scene.causes.boundary_lights)
    return tuple(l for l, lights in groups.items() if all(lt.type == "disc" for lt in lights))


def node(scene, label: str, lights: tuple, boundary: bool) -> Node:
    r, c = scene.reference, scene.causes
    w, h = reference_size(scene.camera, r)
    params = {"label": label, "camera": asdict(scene.camera), **light_params(lights),
              "reference": {**{k: getattr(r, k) for k in REFERENCE_KEYS}, "width": w,
                            "height": h},
              "causes": {"diffuse_spp": c.diffuse_spp, "seed": c.seed}, "boundary": boundary}
    if boundary:   # only the boundary variant reads the layer stack and its settings
        params["optics"] = scene.optics.to_dict()
        params["causes"].update(rough_spp=c.rough_spp, smooth_spp=c.smooth_spp,
                                smooth_roughness=c.smooth_roughness,
                                slab_samples=c.slab_samples)
    return Node(node_id(label), NAME, __name__, params, {"mesh": MESH_NODE},
                label=f"causes / {label} (Mitsuba variants)", locations=("lights[].map",))


def _effects(regions: dict) -> dict:
    keys = ("pixels", "lit_pixels", "effect_rgb", "se_rgb", "effect_lum", "se_lum")
    return {name: {k: rec[k] for k in keys if k in rec} for name, rec in regions.items()}


def _slab_info(slab) -> dict:
    return {"Rd": [float(v) for v in slab.Rd], "Rd_stderr": [float(v) for v in slab.Rd_stderr],
            "specular": [float(v) for v in slab.specular], "samples": slab.samples,
            "roughness": slab.info.get("roughness")}


@mitsuba.exclusive
def run(params: dict, inputs: dict, ctx) -> StageResult:
    t_start = time.perf_counter()
    r, c = params["reference"], params["causes"]
    mesh = inputs["mesh"]
    camera = CameraConfig(**params["camera"])
    lights = [LightConfig(**d) for d in params["lights"]]
    boundary = bool(params["boundary"])
    mi = mitsuba.load_mitsuba(r["variant"])
    opts = VariantOptions(width=r["width"], height=r["height"], seed=c["seed"],
                          diffuse_spp=c["diffuse_spp"], rough_spp=c.get("rough_spp", 1),
                          smooth_spp=c.get("smooth_spp", 1), roughness=r["roughness"],
                          smooth_roughness=c.get("smooth_roughness", 0.0),
                          slab_samples=c.get("slab_samples", 1024), max_depth=r["max_depth"],
                          rr_depth=r["rr_depth"], env_clamp=r["env_clamp"])
    # progress: the diffuse head is ~1/7 of the time with the boundary variant (8 of 59 s,
    # bench/results/causes.json)
    share = 0.14 if boundary else 1.0
    prog = ctx.progress
    inter = interreflection_variant(mi, mesh, camera, lights, opts,
                                    progress=(lambda f: prog(share * f)) if prog else None)
    causes = {"interreflection": _effects(inter["regions"])}
    timings = {"interreflection": inter["seconds"]}
    info_b = None
    name = f"causes-{params['label']}"
    files = []
    if boundary:
        b = boundary_variant(mi, mesh, LayerStack.from_dict(params["optics"]), camera, lights,
                             opts, labels=(inter["hit"], inter["labels"]),
                             progress=(lambda f: prog(share + (1 - share) * f)) if prog
                             else None)
        causes["boundary"] = _effects(b["regions"])
        timings["boundary"] = b["seconds"]
        info_b = {"alphas": b["alphas"], "spp_per_half": b["spp"], "normalised": b["normalised"],
                  "slabs": {k: _slab_info(s) for k, s in b["slabs"].items()},
                  "seconds_per_spp": {k: b[k].seconds / (2 * b[k].spp)
                                      for k in ("rough", "smooth")}}
        for k in ("rough", "smooth"):
            write_exr(ctx.out_dir / f"{name}-skin-{k}.exr", b[k].mean.astype(np.float32))
            files.append(f"{name}-skin-{k}.exr")
    hit, labels = inter["hit"], inter["labels"]
    indirect = (inter["all"].mean - inter["direct"].mean).astype(np.float32)
    for k in ("direct", "all"):
        write_exr(ctx.out_dir / f"{name}-diffuse-{k}.exr", inter[k].mean.astype(np.float32))
        files.append(f"{name}-diffuse-{k}.exr")
    write_png(ctx.out_dir / f"{name}-regions.png", region_colours(labels, hit))
    files.append(f"{name}-regions.png")
    timings["total"] = time.perf_counter() - t_start
    timings["kernel_seconds"] = 0.0
    info = {"model": "causes", "light": params["label"], "geometry": GEOMETRY,
            "variant": mi.variant(), "width": r["width"], "height": r["height"],
            "causes": causes, "definitions": {k: CAUSE_EFFECTS[k] for k in causes},
            "diffuse_spp_per_half": inter["spp"], "textured": inter["textured"],
            "boundary": info_b, "hit_pixels": int(hit.sum())}
    (ctx.out_dir / f"{name}.json").write_text(json.dumps(info, indent=1, sort_keys=True))
    files.append(f"{name}.json")
    return StageResult(RenderedImage(indirect, hit, timings, info), files=files,
                       info={"timings": timings, "variant": mi.variant(),
                             "kernel_seconds": 0.0})


_SKIP_NOTICES: set = set()   # each reason once per process


def plan(scene, plan) -> None:
    """One node per lighting condition the reference renders, when ``[reference]`` and
    ``[causes]`` are enabled; none where Mitsuba cannot run (the reference stage has said
    why)."""
    if not (scene.reference.enabled and scene.causes.enabled):
        return
    groups = dict(scene.light_groups(MAIN_VIEW))   # the main camera's (close-ups: none)
    wanted = scene.reference.lights or tuple(groups)
    chosen = boundary_labels(scene)
    for label in scene.causes.boundary_lights:
        if label not in wanted:
            raise ConfigError(f"{scene.path}: causes.boundary_lights: {label!r} is not a "
                              "lighting condition the reference renders "
                              f"({', '.join(wanted)})")
        why = boundary_lights_problem(groups[label])
        if why:
            raise ConfigError(f"{scene.path}: causes.boundary_lights: {label!r}: {why}")
    reason = mitsuba.mitsuba_missing_reason()
    if reason:
        plan.skipped[NAME] = f"Causes stage skipped: {reason}"
        if reason not in _SKIP_NOTICES and "reference" not in plan.skipped:
            _SKIP_NOTICES.add(reason)
            print(f"dermis: causes stage skipped: {reason}", file=sys.stderr)
        return
    for label in wanted:
        if label in groups:
            plan.add(node(scene, label, groups[label], label in chosen), target=True)
